//! Reopening a link after the device went away (unplug and replug), shared by both drivers.

use std::future::Future;
use std::pin::Pin;

use dioptra_core::LinkError;

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

impl<L> std::fmt::Debug for Opener<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Opener")
    }
}
