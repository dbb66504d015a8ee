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
    Gpu(#[from] GpuError),
    /// A file could not be read or written.
    #[error("{path}: {cause}")]
    Io { path: String, cause: std::io::Error },
    /// A file was read but its contents are not an image this crate understands.
    #[error("{path}: {detail}")]
    Format { path: String, detail: String },
}

/// What can go wrong on the GPU, with what to do about it.
#[derive(Debug, Error)]
pub enum GpuError {
    #[error("no GPU adapter (Vulkan, Metal or DX12) found: install a GPU driver (on Debian, mesa-vulkan-drivers gives a software one) or use --backend cpu")]
    NoAdapter,
    #[error("no GPU adapter matches {want:?}; available: {available}")]
    AdapterNotFound { want: String, available: String },
    #[error("this process already runs on the GPU adapter {have:?}, not {want:?}")]
    AdapterAlreadyChosen { have: String, want: String },
    #[error("the GPU adapter's {what} is {have}; dioptra needs at least {need}")]
    Limit {
        what: &'static str,
        have: u32,
        need: u32,
    },
    #[error("{what} needs {bytes} but this GPU allows at most {max}: use a smaller image or --backend cpu")]
    TooLarge { what: String, bytes: u64, max: u64 },
    #[error("could not open the GPU device: {0}")]
    Device(String),
    #[error("the GPU device was lost (driver reset or removal): restart, or use --backend cpu")]
    DeviceLost,
    #[error("GPU error: {0}")]
    Validation(String),
    #[error("the GPU context's lock was poisoned by an earlier panic")]
    Poisoned,
}

pub(crate) fn invalid(msg: impl Into<String>) -> RenderError {
    RenderError::Input(InputError::InvalidValue(msg.into()))
}

pub(crate) fn mismatch(msg: impl Into<String>) -> RenderError {
    RenderError::Input(InputError::SizeMismatch(msg.into()))
}
