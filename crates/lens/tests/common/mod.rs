//! Shared by the driver tests: a link wrapper that records, corrupts or drops bytes.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::LinkError;
use dioptra_transport::memory::MemoryLink;
use dioptra_transport::ByteLink;

/// What the test does to the bytes between driver and simulator.
#[derive(Default)]
pub struct TapCtl {
    pub written: Vec<u8>,
    pub corrupt_next_write: bool,
    pub corrupt_next_read: bool,
    pub swallow_writes: bool,
}

/// A link that records what the driver sends and can corrupt or drop bytes.
pub struct Tap {
    pub inner: MemoryLink,
    pub ctl: Arc<Mutex<TapCtl>>,
}

impl ByteLink for Tap {
    async fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        let mut bytes = bytes.to_vec();
        let swallow = {
            let mut c = self.ctl.lock().unwrap();
            c.written.extend_from_slice(&bytes);
            if std::mem::take(&mut c.corrupt_next_write) {
                // The CRC's high byte: the command letters stay intact, so the device sees a
                // CRC error rather than an unknown command.
                let last = bytes.len() - 1;
                bytes[last] ^= 0x01;
            }
            c.swallow_writes
        };
        if swallow {
            return Ok(());
        }
        self.inner.write_all(&bytes).await
    }
    async fn read(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        let n = self.inner.read(buf, timeout).await?;
        if n > 0 && std::mem::take(&mut self.ctl.lock().unwrap().corrupt_next_read) {
            // A middle byte: corrupts the content, not the framing.
            buf[n / 2] ^= 0x01;
        }
        Ok(n)
    }
    async fn discard_input(&mut self) -> Result<usize, LinkError> {
        self.inner.discard_input().await
    }
    fn describe(&self) -> String {
        "tap".into()
    }
}
