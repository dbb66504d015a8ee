//! Pseudo-terminal pairs: a simulator serves the master side, and a driver opens the slave
//! path (e.g. `/dev/pts/7`) through [`crate::serial::SerialLink`] exactly as it would open
//! `/dev/ttyACM0`. This is what `dioptra sim optotune --pty` prints and serves.
//!
//! The master outlives its clients: while no process has the slave open, reads wait for the
//! next client (Linux reports EIO there; that is not an error here) and writes are dropped,
//! as a device's replies are when no host is listening. Clients may come and go.

use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::time::Duration;

use dioptra_core::LinkError;
use nix::fcntl::OFlag;
use nix::sys::termios;

use crate::fdio::{FdIo, Hangup};
use crate::ByteLink;

/// A freshly opened pseudo-terminal: the master as a link, and the path clients open.
#[derive(Debug)]
pub struct PtyPair {
    pub master: PtyMaster,
    pub slave_path: PathBuf,
}

impl PtyPair {
    /// Opens a new pty in raw mode. Must be called inside a tokio runtime.
    pub fn open() -> Result<PtyPair, LinkError> {
        let fail = |what: &str, e: nix::Error| {
            LinkError::Unavailable(format!(
                "cannot create a pseudo-terminal ({what}: {e}); is /dev/ptmx present and \
                 /dev/pts mounted?"
            ))
        };
        let master = nix::pty::posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC)
            .map_err(|e| fail("posix_openpt", e))?;
        nix::pty::grantpt(&master).map_err(|e| fail("grantpt", e))?;
        nix::pty::unlockpt(&master).map_err(|e| fail("unlockpt", e))?;
        let slave_path =
            PathBuf::from(nix::pty::ptsname_r(&master).map_err(|e| fail("ptsname", e))?);
        // Termios requests on the master apply to the slave's line discipline, and stay set
        // while the master is open: every client starts raw, even one that does not
        // configure the line itself.
        let mut t = termios::tcgetattr(&master).map_err(|e| fail("tcgetattr", e))?;
        termios::cfmakeraw(&mut t);
        termios::tcsetattr(&master, termios::SetArg::TCSANOW, &t)
            .map_err(|e| fail("tcsetattr", e))?;
        crate::fdio::set_nonblocking(master.as_raw_fd())
            .map_err(|e| LinkError::Io(format!("pty master: cannot make non-blocking: {e}")))?;
        let io = FdIo::new(
            master,
            Hangup::AwaitPeer,
            format!("pty master for {}", slave_path.display()),
        )?;
        tracing::debug!(slave = %slave_path.display(), "pty open");
        Ok(PtyPair {
            master: PtyMaster {
                io,
                slave_path: slave_path.clone(),
            },
            slave_path,
        })
    }
}

/// The simulator's side of a pty. Closing it hangs up every client.
pub struct PtyMaster {
    io: FdIo<nix::pty::PtyMaster>,
    slave_path: PathBuf,
}

impl std::fmt::Debug for PtyMaster {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.io.name())
    }
}

impl PtyMaster {
    /// The path clients open, e.g. `/dev/pts/7`.
    pub fn slave_path(&self) -> &Path {
        &self.slave_path
    }
}

impl ByteLink for PtyMaster {
    /// Bytes written while no client has the slave open are dropped.
    async fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.io.write_all(bytes).await
    }

    /// Waits for a client's bytes; with no client connected it keeps waiting (until the
    /// timeout) instead of failing.
    async fn read(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        self.io.read(buf, timeout).await
    }

    async fn discard_input(&mut self) -> Result<usize, LinkError> {
        self.io.discard_input()
    }

    fn describe(&self) -> String {
        self.io.name().to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::serial::{SerialLink, SerialSettings};

    // Real fds: no paused time here (auto-advance would fire timeouts while the kernel
    // delivers bytes). Timeouts are generous and only bound a failing test.
    const WAIT: Duration = Duration::from_secs(5);

    async fn expect(link: &mut impl ByteLink, want: &[u8]) {
        let mut buf = vec![0u8; want.len()];
        link.read_exact(&mut buf, WAIT).await.unwrap();
        assert_eq!(buf, want);
    }

    #[tokio::test]
    async fn serial_backend_talks_to_the_master_both_ways() {
        let PtyPair {
            mut master,
            slave_path,
        } = PtyPair::open().unwrap();
        assert!(
            slave_path.starts_with("/dev/pts"),
            "{}",
            slave_path.display()
        );
        let mut client = SerialLink::open(&slave_path, SerialSettings::baud(115_200)).unwrap();
        assert!(client.describe().contains(&*slave_path.to_string_lossy()));

        client.write_all(b"Start").await.unwrap();
        expect(&mut master, b"Start").await;
        // Binary bytes, including ones a cooked tty would translate or swallow.
        let binary: Vec<u8> = (0..=255).collect();
        master.write_all(&binary).await.unwrap();
        expect(&mut client, &binary).await;
        client.write_all(b"\r\n\x03\x04\x11\x13").await.unwrap();
        expect(&mut master, b"\r\n\x03\x04\x11\x13").await;
    }

    #[tokio::test]
    async fn master_serves_a_second_client_after_the_first_leaves() {
        let PtyPair {
            mut master,
            slave_path,
        } = PtyPair::open().unwrap();

        let mut first = SerialLink::open(&slave_path, SerialSettings::baud(115_200)).unwrap();
        first.write_all(b"one").await.unwrap();
        expect(&mut master, b"one").await;
        drop(first);

        // No client: the master waits (timeout), it does not fail; replies are dropped.
        let mut buf = [0u8; 8];
        let r = master.read(&mut buf, Duration::from_millis(50)).await;
        assert_eq!(r, Err(LinkError::Timeout { ms: 50 }));
        master.write_all(b"nobody hears this").await.unwrap();
        assert_eq!(master.discard_input().await, Ok(0));

        // A client that connects while the master is already waiting is served.
        let path = slave_path.clone();
        let second = tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(30)).await;
            let mut c = SerialLink::open(&path, SerialSettings::baud(115_200)).unwrap();
            c.write_all(b"two").await.unwrap();
            c
        });
        expect(&mut master, b"two").await;
        let mut second = second.await.unwrap();
        // As drivers do before each command.
        second.discard_input().await.unwrap();
        master.write_all(b"Ready\r\n").await.unwrap();
        expect(&mut second, b"Ready\r\n").await;
    }

    #[tokio::test]
    async fn client_sees_disconnect_when_the_master_closes() {
        let PtyPair { master, slave_path } = PtyPair::open().unwrap();
        let mut client = SerialLink::open(&slave_path, SerialSettings::baud(115_200)).unwrap();
        drop(master);
        let mut buf = [0u8; 4];
        let r = client.read(&mut buf, WAIT).await;
        assert!(matches!(r, Err(LinkError::Disconnected(_))), "{r:?}");
    }

    #[tokio::test]
    async fn discard_drops_pending_client_bytes() {
        let PtyPair {
            mut master,
            slave_path,
        } = PtyPair::open().unwrap();
        let mut client = SerialLink::open(&slave_path, SerialSettings::baud(115_200)).unwrap();
        client.write_all(b"stale").await.unwrap();
        // Wait until the bytes are there, then discard them all.
        let mut one = [0u8; 1];
        master.read_exact(&mut one, WAIT).await.unwrap();
        let mut dropped = 0;
        tokio::time::timeout(WAIT, async {
            while dropped < 4 {
                dropped += master.discard_input().await.unwrap();
                tokio::task::yield_now().await;
            }
        })
        .await
        .unwrap();
        assert_eq!(dropped, 4);
        client.write_all(b"new").await.unwrap();
        expect(&mut master, b"new").await;
    }
}
