//! One loop that serves any byte-speaking simulated device on a `ByteLink`: an in-memory
//! link in tests, a pty master for `dioptra sim ... --pty`.

use std::time::Duration;

use dioptra_core::{Clock, LinkError, Timestamp};
use dioptra_transport::ByteLink;

/// A simulated device, sans-IO: bytes in, bytes out, time passed in.
pub trait ByteDevice {
    /// How long to wait for input before time is advanced again.
    fn wait(&self, now: Timestamp) -> Duration;
    /// Moves the device's models to `now`; events it emits go to `out`.
    fn advance_to(&mut self, now: Timestamp, out: &mut Vec<u8>);
    /// Handles bytes from the host; replies go to `out`.
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>);
    /// Nothing arrived within [`ByteDevice::wait`].
    fn idle(&mut self, _out: &mut Vec<u8>) {}
}

/// A simulator shared between the task serving it and whoever inspects it (a test reading its
/// ground truth, the daemon's status): every call locks it.
impl<D: ByteDevice> ByteDevice for std::sync::Arc<std::sync::Mutex<D>> {
    fn wait(&self, now: Timestamp) -> Duration {
        dioptra_core::lock(self).wait(now)
    }
    fn advance_to(&mut self, now: Timestamp, out: &mut Vec<u8>) {
        dioptra_core::lock(self).advance_to(now, out)
    }
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        dioptra_core::lock(self).receive(bytes, out)
    }
    fn idle(&mut self, out: &mut Vec<u8>) {
        dioptra_core::lock(self).idle(out)
    }
}

/// Serves `sim` on `link` until the link fails (a pty master waits for clients instead).
/// The device follows `clock`: wall time for a pty served to another process, tokio's
/// (pausable) clock in tests.
pub async fn serve<L: ByteLink, D: ByteDevice>(
    link: &mut L,
    sim: &mut D,
    clock: &dyn Clock,
) -> Result<(), LinkError> {
    let mut buf = [0u8; 512];
    let mut out = Vec::with_capacity(512);
    loop {
        let r = link.read(&mut buf, sim.wait(clock.now())).await;
        sim.advance_to(clock.now(), &mut out);
        match r {
            Ok(n) => sim.receive(&buf[..n], &mut out),
            Err(LinkError::Timeout { .. }) => sim.idle(&mut out),
            Err(e) => return Err(e),
        }
        if !out.is_empty() {
            link.write_all(&out).await?;
            out.clear();
        }
    }
}
