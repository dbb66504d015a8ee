//! Bounds a request's head (request line and headers) before hyper parses it, so that an
//! oversized one gets the API's JSON 431 rather than hyper's empty reply.
//!
//! hyper refuses a head larger than its read buffer, or with more headers than it keeps
//! room for, with a bare 431 and no body. This wrapper sits between the socket and hyper,
//! watches each request's head go by and, once one is too large, answers 431 in JSON
//! itself, reads what the client is still sending (closing a socket with unread input
//! resets it, and the client then never sees the reply), and ends the connection. hyper's
//! own limits are set above these, so it never meets a head this lets through.
//!
//! The head ends at the first empty line. What follows (a body) is not watched; the next
//! request's head starts after the reply to the current one is written. A client that
//! pipelines requests gets hyper's own limits on the later ones.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::task::{ready, Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

/// The largest head passed on to hyper.
pub const MAX_HEAD: usize = 64 * 1024;
/// The most header lines passed on to hyper (hyper's own default is 100).
pub const MAX_HEADER_LINES: usize = 100;
/// hyper's read buffer: above `MAX_HEAD`, so a head this lets through always fits.
pub const HYPER_BUF: usize = 2 * MAX_HEAD;
/// hyper's header count: above `MAX_HEADER_LINES`.
pub const HYPER_MAX_HEADERS: usize = 2 * MAX_HEADER_LINES;
/// After refusing, what the client still sends is read (and dropped) for at most this long
/// or this many bytes before the connection closes.
const DRAIN_FOR: Duration = Duration::from_secs(1);
const DRAIN_BYTES: usize = 16 * 1024 * 1024;

enum State {
    /// Reading a head: `bytes` so far, `lines` ended so far, the last two bytes seen.
    Head {
        bytes: usize,
        lines: usize,
        last: [u8; 2],
    },
    /// The head has ended; a body, or the wait for the reply.
    AfterHead,
    /// A protocol upgrade (WebSocket) was answered: everything passes through.
    Upgraded,
    /// Writing the 431 reply; `written` bytes of it so far.
    Refusing { reply: Vec<u8>, written: usize },
    /// Reading what the client still sends, until it closes, `DRAIN_FOR` or `DRAIN_BYTES`.
    Draining {
        deadline: Pin<Box<tokio::time::Sleep>>,
        read: usize,
    },
    /// The refusal is done: hyper sees the end of the stream.
    Closed,
}

/// The socket as hyper sees it (see the module's comment).
pub struct HeadLimited<IO> {
    io: IO,
    state: State,
}

impl<IO> HeadLimited<IO> {
    pub fn new(io: IO) -> Self {
        HeadLimited {
            io,
            state: State::Head {
                bytes: 0,
                lines: 0,
                last: [0, 0],
            },
        }
    }
}

/// What `bytes` do to a head in progress: `Ok(Some(n))` when it ends after `n` of them,
/// `Ok(None)` when it goes on, `Err(reason)` when it has grown past a limit.
fn scan(
    bytes: &[u8],
    seen: &mut usize,
    lines: &mut usize,
    last: &mut [u8; 2],
) -> Result<Option<usize>, String> {
    for (i, &b) in bytes.iter().enumerate() {
        *seen += 1;
        if *seen > MAX_HEAD {
            return Err(format!(
                "the request's head is over {MAX_HEAD} bytes; the API takes headers of at most {} \
                 bytes",
                super::guard::MAX_HEADERS
            ));
        }
        if b == b'\n' {
            // An empty line ("\r\n" or a bare "\n", which hyper accepts too) ends the head.
            if last[1] == b'\n' || (last[1] == b'\r' && last[0] == b'\n') {
                return Ok(Some(i + 1));
            }
            *lines += 1;
            // The request line is not a header.
            if *lines > MAX_HEADER_LINES + 1 {
                return Err(format!(
                    "the request has over {MAX_HEADER_LINES} header lines; the API takes at \
                     most {MAX_HEADER_LINES}"
                ));
            }
        }
        *last = [last[1], b];
    }
    Ok(None)
}

fn reply_431(reason: &str) -> Vec<u8> {
    let body = serde_json::json!({ "error": reason }).to_string();
    format!(
        "HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-type: application/json\r\n\
         content-length: {}\r\nconnection: close\r\n\r\n{body}",
        body.len()
    )
    .into_bytes()
}

impl<IO: AsyncRead + AsyncWrite + Unpin> AsyncRead for HeadLimited<IO> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        loop {
            match &mut this.state {
                State::AfterHead | State::Upgraded => {
                    return Pin::new(&mut this.io).poll_read(cx, buf);
                }
                State::Head { bytes, lines, last } => {
                    let before = buf.filled().len();
                    ready!(Pin::new(&mut this.io).poll_read(cx, buf))?;
                    match scan(&buf.filled()[before..], bytes, lines, last) {
                        Ok(None) => return Poll::Ready(Ok(())),
                        Ok(Some(_)) => {
                            this.state = State::AfterHead;
                            return Poll::Ready(Ok(()));
                        }
                        Err(reason) => {
                            // hyper never sees these bytes: the reply is ours.
                            buf.set_filled(before);
                            this.state = State::Refusing {
                                reply: reply_431(&reason),
                                written: 0,
                            };
                        }
                    }
                }
                State::Refusing { reply, written } => {
                    while *written < reply.len() {
                        let n = ready!(Pin::new(&mut this.io).poll_write(cx, &reply[*written..]))?;
                        if n == 0 {
                            return Poll::Ready(Err(io::ErrorKind::WriteZero.into()));
                        }
                        *written += n;
                    }
                    ready!(Pin::new(&mut this.io).poll_flush(cx))?;
                    // Shut our side: the client reads the reply and its end of the stream.
                    let _ = ready!(Pin::new(&mut this.io).poll_shutdown(cx));
                    this.state = State::Draining {
                        deadline: Box::pin(tokio::time::sleep(DRAIN_FOR)),
                        read: 0,
                    };
                }
                State::Draining { deadline, read } => {
                    let mut scratch = [0u8; 8192];
                    loop {
                        if *read >= DRAIN_BYTES || deadline.as_mut().poll(cx).is_ready() {
                            break;
                        }
                        let mut sb = ReadBuf::new(&mut scratch);
                        match Pin::new(&mut this.io).poll_read(cx, &mut sb) {
                            Poll::Pending => return Poll::Pending,
                            Poll::Ready(Ok(())) if sb.filled().is_empty() => break,
                            Poll::Ready(Ok(())) => *read += sb.filled().len(),
                            Poll::Ready(Err(_)) => break,
                        }
                    }
                    this.state = State::Closed;
                }
                State::Closed => return Poll::Ready(Ok(())),
            }
        }
    }
}

impl<IO: AsyncRead + AsyncWrite + Unpin> HeadLimited<IO> {
    /// The connection is being refused: its reply is ours, hyper writes nothing more.
    fn refused(&self) -> bool {
        matches!(
            self.state,
            State::Closed | State::Draining { .. } | State::Refusing { .. }
        )
    }

    /// A reply starting to go out ends a request: the next bytes read are a new head.
    /// Interim replies (100 Continue) do not, and a 101 hands the stream to the upgrade.
    fn on_write(&mut self, first: &[u8]) {
        if matches!(self.state, State::AfterHead) && !first.is_empty() {
            if first.starts_with(b"HTTP/1.1 101") {
                self.state = State::Upgraded;
            } else if !first.starts_with(b"HTTP/1.1 1") {
                self.state = State::Head {
                    bytes: 0,
                    lines: 0,
                    last: [0, 0],
                };
            }
        }
    }
}

impl<IO: AsyncRead + AsyncWrite + Unpin> AsyncWrite for HeadLimited<IO> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        if this.refused() {
            return Poll::Ready(Err(io::ErrorKind::BrokenPipe.into()));
        }
        let n = ready!(Pin::new(&mut this.io).poll_write(cx, buf))?;
        if n > 0 {
            this.on_write(buf);
        }
        Poll::Ready(Ok(n))
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        if this.refused() {
            return Poll::Ready(Err(io::ErrorKind::BrokenPipe.into()));
        }
        let n = ready!(Pin::new(&mut this.io).poll_write_vectored(cx, bufs))?;
        if n > 0 {
            let first = bufs.iter().find(|b| !b.is_empty()).map(|b| &b[..]);
            this.on_write(first.unwrap_or(&[]));
        }
        Poll::Ready(Ok(n))
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        if matches!(this.state, State::Closed) {
            // Already shut while refusing.
            return Poll::Ready(Ok(()));
        }
        Pin::new(&mut this.io).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan_all(head: &[u8]) -> Result<Option<usize>, String> {
        let (mut seen, mut lines, mut last) = (0, 0, [0, 0]);
        scan(head, &mut seen, &mut lines, &mut last)
    }

    #[test]
    fn a_head_ends_at_its_empty_line_whatever_the_line_endings() {
        let crlf = b"GET /status HTTP/1.1\r\nHost: x\r\n\r\nBODY";
        assert_eq!(scan_all(crlf), Ok(Some(crlf.len() - 4)));
        let lf = b"GET /status HTTP/1.1\nHost: x\n\nBODY";
        assert_eq!(scan_all(lf), Ok(Some(lf.len() - 4)));
        assert_eq!(scan_all(b"GET /status HTTP/1.1\r\nHost: x\r\n"), Ok(None));
    }

    #[test]
    fn a_head_split_across_reads_is_followed() {
        let head = b"GET / HTTP/1.1\r\nHost: x\r\n\r\n";
        for cut in 1..head.len() {
            let (mut seen, mut lines, mut last) = (0, 0, [0, 0]);
            let first = scan(&head[..cut], &mut seen, &mut lines, &mut last);
            let second = scan(&head[cut..], &mut seen, &mut lines, &mut last);
            assert_eq!(
                (first, second),
                (Ok(None), Ok(Some(head.len() - cut))),
                "cut at {cut}"
            );
        }
    }

    #[test]
    fn too_many_bytes_or_lines_are_refused() {
        let mut big = b"GET / HTTP/1.1\r\nX: ".to_vec();
        big.extend(std::iter::repeat_n(b'a', MAX_HEAD));
        assert!(scan_all(&big).unwrap_err().contains("bytes"));
        let mut many = b"GET / HTTP/1.1\r\n".to_vec();
        for i in 0..=MAX_HEADER_LINES {
            many.extend(format!("X-{i}: 1\r\n").bytes());
        }
        assert!(scan_all(&many).unwrap_err().contains("header lines"));
        let mut allowed = b"GET / HTTP/1.1\r\n".to_vec();
        for i in 0..MAX_HEADER_LINES {
            allowed.extend(format!("X-{i}: 1\r\n").bytes());
        }
        allowed.extend(b"\r\n");
        assert_eq!(scan_all(&allowed), Ok(Some(allowed.len())));
    }
}
