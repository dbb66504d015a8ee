//! Non-blocking file-descriptor I/O on tokio's reactor, shared by the serial backend and the
//! pty master. The fd must already be in O_NONBLOCK mode.

use std::io;
use std::os::fd::{AsRawFd, RawFd};
use std::time::Duration;

use dioptra_core::LinkError;
use tokio::io::unix::AsyncFd;
use tokio::time::{sleep, timeout_at, Instant};

/// What a hang-up (EIO, POLLHUP or end of file) means for this fd.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Hangup {
    /// The device is gone: report [`LinkError::Disconnected`].
    Disconnect,
    /// A pty master whose slave is not open: no client yet, or one left. Reads wait for the
    /// next client; writes are dropped, as a device's replies are when no host listens.
    AwaitPeer,
}

/// How often a pty master with no client checks whether one has arrived. tokio keeps a
/// hang-up as permanent readiness (right for sockets, wrong for a pty whose clients come
/// and go), so while no client is connected the fd is taken off the reactor and polled.
const PEER_POLL: Duration = Duration::from_millis(10);

/// `discard_input` stops after this many bytes, so a peer that never stops sending cannot
/// keep it busy forever.
const DISCARD_LIMIT: usize = 1 << 20;

pub(crate) fn set_nonblocking(fd: RawFd) -> io::Result<()> {
    // SAFETY: fcntl on a caller-owned, open fd with integer arguments only.
    let flags = unsafe { libc::fcntl(fd, libc::F_GETFL) };
    if flags < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: as above.
    if unsafe { libc::fcntl(fd, libc::F_SETFL, flags | libc::O_NONBLOCK) } < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

fn sys_read(fd: RawFd, buf: &mut [u8]) -> io::Result<usize> {
    // SAFETY: `buf` is valid for `buf.len()` writable bytes for the duration of the call.
    let n = unsafe { libc::read(fd, buf.as_mut_ptr().cast(), buf.len()) };
    if n < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(n as usize)
    }
}

fn sys_write(fd: RawFd, buf: &[u8]) -> io::Result<usize> {
    // SAFETY: `buf` is valid for `buf.len()` readable bytes for the duration of the call.
    let n = unsafe { libc::write(fd, buf.as_ptr().cast(), buf.len()) };
    if n < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(n as usize)
    }
}

/// True when the other side has hung up (for a pty master: no slave open).
fn hung_up(fd: RawFd) -> bool {
    let mut pfd = libc::pollfd {
        fd,
        events: 0,
        revents: 0,
    };
    // SAFETY: one valid pollfd, zero timeout.
    let r = unsafe { libc::poll(&mut pfd, 1, 0) };
    r > 0 && pfd.revents & libc::POLLHUP != 0
}

/// Errors that mean the device (or the pty's client) went away.
fn is_hangup(e: &io::Error) -> bool {
    matches!(
        e.raw_os_error(),
        Some(libc::EIO | libc::ENXIO | libc::ENODEV | libc::EPIPE | libc::ESHUTDOWN)
    )
}

fn gone(name: &str, detail: impl std::fmt::Display) -> LinkError {
    LinkError::Disconnected(format!("{name}: {detail}"))
}

/// The outcome of one non-blocking read.
enum Attempt {
    Data(usize),
    WouldBlock,
    NoPeer,
}

/// Classifies one read's result.
fn attempt(r: io::Result<usize>, hangup: Hangup, name: &str) -> Result<Attempt, LinkError> {
    match r {
        Ok(0) if hangup == Hangup::AwaitPeer => Ok(Attempt::NoPeer),
        Ok(0) => Err(gone(name, "end of file (device closed or unplugged)")),
        Ok(n) => Ok(Attempt::Data(n)),
        Err(e) if e.kind() == io::ErrorKind::WouldBlock => Ok(Attempt::WouldBlock),
        Err(e) if e.kind() == io::ErrorKind::Interrupted => Ok(Attempt::WouldBlock),
        Err(e) if is_hangup(&e) && hangup == Hangup::AwaitPeer => Ok(Attempt::NoPeer),
        Err(e) if is_hangup(&e) => Err(gone(name, e)),
        Err(e) => Err(LinkError::Io(format!("{name}: read failed: {e}"))),
    }
}

/// The fd number without ownership, for registering with the reactor; the owner is
/// [`FdIo::inner`], which outlives every registration.
struct Raw(RawFd);

impl AsRawFd for Raw {
    fn as_raw_fd(&self) -> RawFd {
        self.0
    }
}

pub(crate) struct FdIo<T: AsRawFd> {
    /// `None` while a pty master has no client (see [`PEER_POLL`]). Declared before
    /// `inner`, so it is deregistered before `inner` closes the fd.
    reactor: Option<AsyncFd<Raw>>,
    inner: T,
    hangup: Hangup,
    /// For error messages, e.g. `serial /dev/ttyACM0`.
    name: String,
}

impl<T: AsRawFd> FdIo<T> {
    /// Registers `inner` (already non-blocking) with the current tokio runtime's reactor.
    pub(crate) fn new(inner: T, hangup: Hangup, name: String) -> Result<Self, LinkError> {
        let mut io = FdIo {
            reactor: None,
            inner,
            hangup,
            name,
        };
        io.register()?;
        Ok(io)
    }

    fn register(&mut self) -> Result<(), LinkError> {
        // Registering outside a runtime would panic inside tokio.
        if tokio::runtime::Handle::try_current().is_err() {
            return Err(LinkError::Io(format!(
                "{}: must be opened inside a tokio runtime (with IO enabled)",
                self.name
            )));
        }
        self.reactor = None; // deregister first: the same fd cannot be added twice
                             // SAFETY: `self.inner` owns the fd and keeps it open and unchanged for as long as
                             // this registration exists: `reactor` is dropped (or replaced) before `inner`.
        let registered = unsafe { AsyncFd::register(Raw(self.inner.as_raw_fd())) };
        self.reactor = Some(registered.map_err(|e| {
            LinkError::Io(format!(
                "{}: cannot register with the async runtime: {e}",
                self.name
            ))
        })?);
        Ok(())
    }

    /// The pty's client left: stop watching the fd (its hang-up would stay "ready").
    fn park(&mut self) {
        if self.reactor.take().is_some() {
            tracing::debug!(link = %self.name, "client closed the pty; waiting for the next one");
        }
    }

    pub(crate) fn name(&self) -> &str {
        &self.name
    }

    pub(crate) async fn read(
        &mut self,
        buf: &mut [u8],
        timeout: Duration,
    ) -> Result<usize, LinkError> {
        if buf.is_empty() {
            return Ok(0);
        }
        match timeout_at(Instant::now() + timeout, self.read_until_data(buf)).await {
            Ok(r) => r,
            Err(_) => Err(crate::timeout_error(timeout)),
        }
    }

    async fn read_until_data(&mut self, buf: &mut [u8]) -> Result<usize, LinkError> {
        let fd = self.inner.as_raw_fd();
        loop {
            // Try first: data may be there before the reactor reports readiness.
            match attempt(sys_read(fd, buf), self.hangup, &self.name)? {
                Attempt::Data(n) => return Ok(n),
                Attempt::NoPeer => {
                    self.park();
                    sleep(PEER_POLL).await;
                    continue;
                }
                Attempt::WouldBlock => {}
            }
            if self.reactor.is_none() {
                tracing::debug!(link = %self.name, "a client opened the pty");
                self.register()?;
            }
            let Some(reactor) = self.reactor.as_mut() else {
                continue;
            };
            let mut guard = reactor
                .readable_mut()
                .await
                .map_err(|e| LinkError::Io(format!("{}: poll failed: {e}", self.name)))?;
            match attempt(sys_read(fd, buf), self.hangup, &self.name)? {
                Attempt::Data(n) => return Ok(n),
                // A hang-up stays "ready" in tokio; a device that reports one is gone even
                // if its read says "try again".
                Attempt::WouldBlock if guard.ready().is_read_closed() => {
                    if self.hangup == Hangup::Disconnect {
                        return Err(gone(&self.name, "hung up"));
                    }
                    self.park();
                }
                Attempt::WouldBlock => guard.clear_ready(),
                Attempt::NoPeer => self.park(),
            }
        }
    }

    pub(crate) async fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        let fd = self.inner.as_raw_fd();
        let mut rest = bytes;
        while !rest.is_empty() {
            if self.hangup == Hangup::AwaitPeer && hung_up(fd) {
                self.park();
                tracing::trace!(link = %self.name, len = rest.len(), "no client on the pty; bytes dropped");
                return Ok(());
            }
            match sys_write(fd, rest) {
                Ok(n) => {
                    rest = &rest[n.min(rest.len())..];
                    continue;
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {}
                Err(e) if is_hangup(&e) && self.hangup == Hangup::AwaitPeer => {
                    self.park();
                    return Ok(());
                }
                Err(e) if is_hangup(&e) => return Err(gone(&self.name, e)),
                Err(e) => return Err(LinkError::Io(format!("{}: write failed: {e}", self.name))),
            }
            // The kernel buffer is full: wait for room.
            if self.reactor.is_none() {
                self.register()?;
            }
            let Some(reactor) = self.reactor.as_mut() else {
                continue;
            };
            let mut guard = reactor
                .writable_mut()
                .await
                .map_err(|e| LinkError::Io(format!("{}: poll failed: {e}", self.name)))?;
            if guard.ready().is_write_closed() {
                // Re-examined at the top of the loop: the write fails or the peer is gone.
                if self.hangup == Hangup::Disconnect {
                    return Err(gone(&self.name, "hung up"));
                }
                self.park();
                continue;
            }
            guard.clear_ready();
        }
        Ok(())
    }

    /// Reads and drops everything already received, without waiting.
    pub(crate) fn discard_input(&mut self) -> Result<usize, LinkError> {
        let fd = self.inner.as_raw_fd();
        let mut scratch = [0u8; 1024];
        let mut total = 0;
        loop {
            match attempt(sys_read(fd, &mut scratch), self.hangup, &self.name)? {
                Attempt::Data(n) if total + n < DISCARD_LIMIT => total += n,
                Attempt::Data(n) => return Ok(total + n),
                Attempt::WouldBlock | Attempt::NoPeer => return Ok(total),
            }
        }
    }
}
