//! Errors shared across crates. A device's refusal is kept apart from a broken link,
//! so callers can tell "retry / reconnect" from "fix the request".

use thiserror::Error;

/// The byte or report link to a device failed. Reconnecting may help; resending the
/// same request to the same link will not.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum LinkError {
    /// Nothing arrived within the allowed time.
    #[error("timed out after {ms} ms waiting for the device")]
    Timeout { ms: u64 },
    /// The device went away (unplugged, port closed, peer dropped).
    #[error("device disconnected: {0}")]
    Disconnected(String),
    /// The link cannot be opened at all on this machine (no permission, no USB, no such port).
    #[error("{0}")]
    Unavailable(String),
    /// Any other operating-system I/O failure.
    #[error("I/O error: {0}")]
    Io(String),
}

impl LinkError {
    /// True when the link is lost and reopening it is the right recovery: the device went
    /// away, the OS failed the I/O, or the link cannot be used at all. A timeout is not a
    /// loss by itself (a busy device answers late); callers that keep a link decide after how
    /// many timeouts in a row to treat it as lost.
    pub fn needs_reconnect(&self) -> bool {
        matches!(
            self,
            LinkError::Disconnected(_) | LinkError::Io(_) | LinkError::Unavailable(_)
        )
    }
}

impl From<std::io::Error> for LinkError {
    fn from(e: std::io::Error) -> Self {
        use std::io::ErrorKind::*;
        match e.kind() {
            TimedOut | WouldBlock => LinkError::Timeout { ms: 0 },
            BrokenPipe | ConnectionReset | ConnectionAborted | UnexpectedEof | NotConnected => {
                LinkError::Disconnected(e.to_string())
            }
            NotFound | PermissionDenied => LinkError::Unavailable(e.to_string()),
            _ => LinkError::Io(e.to_string()),
        }
    }
}

/// What a device driver reports to its caller.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum DeviceError {
    /// The link broke; see [`LinkError`].
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The device understood the request and refused it.
    #[error("device refused the request (code {code}): {detail}")]
    Refused { code: u16, detail: String },
    /// The device sent bytes that do not decode (bad CRC, wrong length, unknown message).
    #[error("malformed reply from device: {0}")]
    Protocol(String),
    /// The caller asked for something outside the configured safe range; nothing was sent.
    #[error("{what} {requested} is outside the allowed range {min}..={max}; nothing was sent")]
    OutOfRange {
        what: &'static str,
        requested: f64,
        min: f64,
        max: f64,
    },
    /// A request that the driver cannot make in its current state.
    #[error("invalid request: {0}")]
    Invalid(String),
}

impl DeviceError {
    /// True when the link must be reopened before the device can be used again.
    pub fn needs_reconnect(&self) -> bool {
        matches!(self, DeviceError::Link(e) if e.needs_reconnect())
    }
}

/// Invalid input data (images, sizes, parameters) given to a pure function.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum InputError {
    #[error("size mismatch: {0}")]
    SizeMismatch(String),
    #[error("invalid value: {0}")]
    InvalidValue(String),
}
