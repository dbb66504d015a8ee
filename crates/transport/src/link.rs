use std::future::Future;
use std::time::Duration;

use dioptra_core::LinkError;
use tokio::time::Instant;

/// An async, bidirectional byte stream to one device.
///
/// Methods take `&mut self`: one driver owns a link and issues one operation at a time.
/// The futures are `Send`, so a driver generic over `L: ByteLink` can run on any tokio
/// runtime. Dropping a future (e.g. on cancellation) never leaves the link unusable; bytes
/// that arrived meanwhile stay buffered for the next read.
///
/// Errors: [`LinkError::Timeout`] when nothing arrived in time (the link stays usable);
/// [`LinkError::Disconnected`] once the device or peer is gone (reopen to recover);
/// [`LinkError::Io`] for other OS failures.
pub trait ByteLink: Send {
    /// Hands all of `bytes` to the transport. Returns once the OS (or the in-memory pipe)
    /// holds them, not when the device has received them.
    fn write_all(&mut self, bytes: &[u8]) -> impl Future<Output = Result<(), LinkError>> + Send;

    /// Waits up to `timeout` for at least one byte and returns how many were put in `buf`.
    /// An empty `buf` returns `Ok(0)` at once. A zero `timeout` returns what already arrived
    /// or [`LinkError::Timeout`].
    fn read(
        &mut self,
        buf: &mut [u8],
        timeout: Duration,
    ) -> impl Future<Output = Result<usize, LinkError>> + Send;

    /// Fills all of `buf` within `timeout` (one deadline for the whole buffer, not per
    /// chunk). On timeout the bytes read so far are lost: callers frame replies by expected
    /// length and resynchronise with [`ByteLink::discard_input`].
    fn read_exact(
        &mut self,
        buf: &mut [u8],
        timeout: Duration,
    ) -> impl Future<Output = Result<(), LinkError>> + Send {
        async move {
            let deadline = Instant::now() + timeout;
            let mut filled = 0;
            while filled < buf.len() {
                let left = deadline.saturating_duration_since(Instant::now());
                match self.read(&mut buf[filled..], left).await {
                    // `read` promises at least one byte; don't spin on a link that breaks that.
                    Ok(0) if left.is_zero() => return Err(crate::timeout_error(timeout)),
                    Ok(n) => filled += n,
                    // Report the caller's whole timeout, not the remainder of the last wait.
                    Err(LinkError::Timeout { .. }) => return Err(crate::timeout_error(timeout)),
                    Err(e) => return Err(e),
                }
            }
            Ok(())
        }
    }

    /// Drops bytes that have already arrived and not been read (stray replies, a device's
    /// unsolicited `N\r\n`); returns how many. Does not wait for more.
    fn discard_input(&mut self) -> impl Future<Output = Result<usize, LinkError>> + Send;

    /// What this link is connected to, for logs and error messages
    /// (e.g. `serial /dev/ttyACM0 at 115200 baud`).
    fn describe(&self) -> String;
}
