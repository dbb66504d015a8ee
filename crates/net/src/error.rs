//! Errors of the network crate: each says what went wrong and what to do about it.

use thiserror::Error;

#[derive(Debug, Error)]
pub enum NetError {
    #[error("cannot read weights file {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("weights file is corrupt or not safetensors ({0}); re-export it with `dioptra train` or download it again")]
    Corrupt(String),
    #[error("weights file has no dioptra architecture metadata ({0}); it was not written by dioptra-net")]
    MissingMetadata(String),
    #[error("weights file architecture is invalid: {0}")]
    BadArch(String),
    #[error("tensor {name}: expected shape {expected:?} but the file has {found:?}; the weights do not match their architecture metadata")]
    Shape {
        name: String,
        expected: Vec<usize>,
        found: Vec<usize>,
    },
    #[error("tensor {name}: {what}")]
    Tensor { name: String, what: String },
    #[error("invalid input: {0}")]
    Input(String),
    #[error("network expects config {expected} but was asked for {asked}; load the {asked} weights instead")]
    WrongConfig { expected: String, asked: String },
    #[error(transparent)]
    Render(#[from] dioptra_render::RenderError),
    #[error(transparent)]
    Core(#[from] dioptra_core::InputError),
    #[cfg(feature = "train")]
    #[error("training framework: {0}")]
    Train(#[from] candle_core::Error),
    #[cfg(feature = "train")]
    #[error("training data: {0}")]
    Data(String),
}

pub(crate) fn input(msg: impl Into<String>) -> NetError {
    NetError::Input(msg.into())
}
