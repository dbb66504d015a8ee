//! Reopening a link after the device went away (unplug and replug), shared by both drivers.

use std::future::Future;
use std::path::PathBuf;
use std::pin::Pin;

use dioptra_core::LinkError;
use dioptra_transport::discovery::SerialIdentity;
use dioptra_transport::serial::{SerialLink, SerialSettings};

/// The future an [`Opener`] returns.
pub type OpenFuture<L> = Pin<Box<dyn Future<Output = Result<L, LinkError>> + Send>>;

/// Opens a fresh link to the same device, e.g. the same serial path again.
pub struct Opener<L>(Box<dyn FnMut() -> OpenFuture<L> + Send>);

impl<L> Opener<L> {
    pub fn new<F, Fut>(mut open: F) -> Self
    where
        F: FnMut() -> Fut + Send + 'static,
        Fut: Future<Output = Result<L, LinkError>> + Send + 'static,
    {
        Opener(Box::new(move || Box::pin(open())))
    }

    pub async fn open(&mut self) -> Result<L, LinkError> {
        (self.0)().await
    }
}

impl Opener<SerialLink> {
    /// Opens the serial device `id` names, looked up again at every open: by its USB serial
    /// number, when `id` has one, on whatever tty it came back on after an unplug; a device on
    /// the configured path with another serial number is refused, naming both
    /// ([`SerialIdentity::locate`]).
    pub fn serial(id: SerialIdentity, settings: SerialSettings) -> Self {
        Self::serial_in(PathBuf::from("/sys"), id, settings)
    }

    /// [`Opener::serial`] with sysfs at `sys_root`.
    pub fn serial_in(sys_root: PathBuf, id: SerialIdentity, settings: SerialSettings) -> Self {
        Opener::new(move || {
            let (id, sys_root) = (id.clone(), sys_root.clone());
            async move {
                let tty = tokio::task::spawn_blocking(move || id.locate_in(&sys_root))
                    .await
                    .map_err(|e| LinkError::Io(format!("looking the serial device up: {e}")))??;
                SerialLink::open(tty, settings)
            }
        })
    }
}

impl<L> std::fmt::Debug for Opener<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Opener")
    }
}
