//! Errors from the optics methods and image I/O.

use dioptra_core::InputError;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum RenderError {
    /// Bad images or parameters (sizes, NaN, out-of-range values).
    #[error(transparent)]
    Input(#[from] InputError),
    /// The backend has no implementation of this method.
    #[error("the {backend} backend does not implement {method}")]
    Unsupported {
        backend: &'static str,
        method: &'static str,
    },
    /// The GPU backend failed (no adapter, limits, device lost).
    #[error(transparent)]
    Gpu(#[from] crate::gpu::GpuError),
    /// A file could not be read or written.
    #[error("{path}: {cause}")]
    Io { path: String, cause: std::io::Error },
    /// A file was read but its contents are not an image this crate understands.
    #[error("{path}: {detail}")]
    Format { path: String, detail: String },
}

pub(crate) fn invalid(msg: impl Into<String>) -> RenderError {
    RenderError::Input(InputError::InvalidValue(msg.into()))
}

pub(crate) fn mismatch(msg: impl Into<String>) -> RenderError {
    RenderError::Input(InputError::SizeMismatch(msg.into()))
}
