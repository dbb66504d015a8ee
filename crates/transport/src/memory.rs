//! In-memory duplex byte link: two [`MemoryLink`] ends joined by two bounded pipes.
//!
//! A simulator owns one end and the driver under test the other; both speak the device's
//! real bytes. [`Faults`] injects what real links do to drivers: unplugging, stray bytes
//! and latency.
//!
//! ```
//! # async fn demo() -> Result<(), dioptra_transport::LinkError> {
//! use dioptra_transport::{memory, ByteLink};
//! use std::time::Duration;
//!
//! let (mut host, mut device) = memory::pair(4096);
//! host.write_all(b"Start").await?;
//! let mut buf = [0u8; 5];
//! device.read_exact(&mut buf, Duration::from_secs(1)).await?;
//! device.write_all(b"Ready\r\n").await?;
//! # Ok(()) }
//! ```

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use dioptra_core::LinkError;
use tokio::sync::Notify;
use tokio::time::{sleep_until, Instant};

use crate::ByteLink;

/// Makes a connected pair of links. `capacity` bounds the bytes buffered in each direction
/// (at least 1): a writer waits while the peer has that many bytes unread, like a full
/// kernel buffer.
pub fn pair(capacity: usize) -> (MemoryLink, MemoryLink) {
    let a_to_b = Arc::new(Pipe::new(capacity));
    let b_to_a = Arc::new(Pipe::new(capacity));
    let a = MemoryLink {
        rx: b_to_a.clone(),
        tx: a_to_b.clone(),
        name: "memory link end A".to_string(),
    };
    let b = MemoryLink {
        rx: a_to_b,
        tx: b_to_a,
        name: "memory link end B".to_string(),
    };
    (a, b)
}

/// One end of an in-memory link. Dropping it closes this end: the peer reads what is still
/// buffered and then gets [`LinkError::Disconnected`]; the peer's writes fail at once.
#[derive(Debug)]
pub struct MemoryLink {
    rx: Arc<Pipe>,
    tx: Arc<Pipe>,
    name: String,
}

impl MemoryLink {
    /// Names this end in [`ByteLink::describe`] and error messages.
    pub fn named(mut self, name: impl Into<String>) -> Self {
        self.name = name.into();
        self
    }

    /// A handle that injects faults into this end's link; it may outlive the link.
    pub fn faults(&self) -> Faults {
        Faults {
            rx: self.rx.clone(),
            tx: self.tx.clone(),
        }
    }
}

impl Drop for MemoryLink {
    fn drop(&mut self) {
        self.tx.update(|s| s.writer_open = false);
        self.rx.update(|s| s.reader_open = false);
    }
}

impl ByteLink for MemoryLink {
    async fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        let mut rest = bytes;
        while !rest.is_empty() {
            {
                let mut s = self.tx.lock();
                if let Some(reason) = &s.severed {
                    return Err(LinkError::Disconnected(format!("{}: {reason}", self.name)));
                }
                if !s.reader_open {
                    return Err(LinkError::Disconnected(format!(
                        "{}: the other end was closed",
                        self.name
                    )));
                }
                let space = s.capacity.saturating_sub(s.buffered);
                if space > 0 {
                    let (now, later) = rest.split_at(space.min(rest.len()));
                    let ready_at = Instant::now() + s.latency;
                    s.buffered += now.len();
                    if s.byte_time.is_zero() {
                        s.chunks.push_back(Chunk {
                            ready_at,
                            data: now.to_vec(),
                            pos: 0,
                        });
                    } else {
                        // One byte at a time, as a serial line delivers them.
                        let mut t = s
                            .chunks
                            .back()
                            .map_or(ready_at, |c| c.ready_at.max(ready_at));
                        for &b in now {
                            t += s.byte_time;
                            s.chunks.push_back(Chunk {
                                ready_at: t,
                                data: vec![b],
                                pos: 0,
                            });
                        }
                    }
                    rest = later;
                    drop(s);
                    self.tx.readable.notify_one();
                    continue;
                }
            }
            // Full: wait for the reader to make room (or for the link to break).
            self.tx.writable.notified().await;
        }
        Ok(())
    }

    async fn read(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        if buf.is_empty() {
            return Ok(0);
        }
        let deadline = Instant::now() + timeout;
        loop {
            let next_ready = {
                let mut s = self.rx.lock();
                if let Some(reason) = &s.severed {
                    return Err(LinkError::Disconnected(format!("{}: {reason}", self.name)));
                }
                let n = s.take_ready(Some(buf), Instant::now());
                if n > 0 {
                    drop(s);
                    self.rx.writable.notify_one();
                    return Ok(n);
                }
                if s.chunks.is_empty() && !s.writer_open {
                    return Err(LinkError::Disconnected(format!(
                        "{}: the other end was closed",
                        self.name
                    )));
                }
                s.chunks.front().map(|c| c.ready_at)
            };
            if Instant::now() >= deadline {
                return Err(crate::timeout_error(timeout));
            }
            // Wake for new bytes, for delayed bytes coming due, or at the deadline.
            let wake = next_ready.map_or(deadline, |t| t.min(deadline));
            tokio::select! {
                _ = self.rx.readable.notified() => {}
                _ = sleep_until(wake) => {}
            }
        }
    }

    async fn discard_input(&mut self) -> Result<usize, LinkError> {
        let mut s = self.rx.lock();
        if let Some(reason) = &s.severed {
            return Err(LinkError::Disconnected(format!("{}: {reason}", self.name)));
        }
        let n = s.take_ready(None, Instant::now());
        let gone = s.chunks.is_empty() && !s.writer_open;
        drop(s);
        self.rx.writable.notify_one();
        if gone {
            return Err(LinkError::Disconnected(format!(
                "{}: the other end was closed",
                self.name
            )));
        }
        Ok(n)
    }

    fn describe(&self) -> String {
        self.name.clone()
    }
}

/// Fault injection for one end of an in-memory link (from [`MemoryLink::faults`]).
/// Cloneable and usable from any task, while the link is in use.
#[derive(Debug, Clone)]
pub struct Faults {
    /// The pipe the owning end reads from.
    rx: Arc<Pipe>,
    /// The pipe the owning end writes to.
    tx: Arc<Pipe>,
}

impl Faults {
    /// Unplugs the link: from now on every operation on either end fails with
    /// [`LinkError::Disconnected`] carrying `reason`; buffered bytes are lost, as on a real
    /// unplug. Pending reads and writes wake at once.
    pub fn disconnect(&self, reason: impl Into<String>) {
        let reason = reason.into();
        for pipe in [&self.rx, &self.tx] {
            pipe.update(|s| {
                s.severed.get_or_insert_with(|| reason.clone());
                s.chunks.clear();
                s.buffered = 0;
            });
        }
    }

    /// True once [`Faults::disconnect`] was called.
    pub fn is_disconnected(&self) -> bool {
        self.rx.lock().severed.is_some()
    }

    /// Makes `bytes` arrive at the owning end, after what is already buffered, as if the
    /// peer had sent them (e.g. a stray `N\r\n`). Not bounded by the capacity.
    pub fn inject(&self, bytes: &[u8]) {
        if bytes.is_empty() {
            return;
        }
        self.rx.update(|s| {
            s.buffered += bytes.len();
            s.chunks.push_back(Chunk {
                ready_at: Instant::now(),
                data: bytes.to_vec(),
                pos: 0,
            });
        });
    }

    /// Bytes the peer writes from now on reach the owning end `latency` after they were
    /// written (order is kept). Measured on tokio's clock, so paused-time tests stay exact.
    pub fn set_latency(&self, latency: Duration) {
        self.rx.update(|s| s.latency = latency);
    }

    /// Bytes the peer writes from now on arrive one at a time, `byte_time` apart, after the
    /// latency: a serial line's pace (115200 baud 8N1 is 86.8 µs a byte). Zero: at once.
    /// A reader wakes at tokio's timer resolution (1 ms), so a faster pace arrives in bursts
    /// of the bytes due by then: partial frames all the same.
    pub fn set_byte_time(&self, byte_time: Duration) {
        self.rx.update(|s| s.byte_time = byte_time);
    }
}

/// One direction of the link.
#[derive(Debug)]
struct Pipe {
    state: Mutex<PipeState>,
    /// Wakes the reader: bytes arrived, the writer closed, or the link was severed.
    readable: Notify,
    /// Wakes the writer: room was made, the reader closed, or the link was severed.
    writable: Notify,
}

#[derive(Debug)]
struct PipeState {
    chunks: VecDeque<Chunk>,
    /// Unread bytes in `chunks`.
    buffered: usize,
    capacity: usize,
    latency: Duration,
    /// Time between bytes ([`Faults::set_byte_time`]).
    byte_time: Duration,
    writer_open: bool,
    reader_open: bool,
    /// Set by [`Faults::disconnect`].
    severed: Option<String>,
}

#[derive(Debug)]
struct Chunk {
    ready_at: Instant,
    data: Vec<u8>,
    pos: usize,
}

impl Pipe {
    fn new(capacity: usize) -> Self {
        Pipe {
            state: Mutex::new(PipeState {
                chunks: VecDeque::new(),
                buffered: 0,
                capacity: capacity.max(1),
                latency: Duration::ZERO,
                byte_time: Duration::ZERO,
                writer_open: true,
                reader_open: true,
                severed: None,
            }),
            readable: Notify::new(),
            writable: Notify::new(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, PipeState> {
        // The state stays consistent even if a holder panicked (no multi-step invariants
        // are left half-done across a panic point), so a poisoned lock is still usable.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Changes the state and wakes both sides to re-examine it.
    fn update(&self, f: impl FnOnce(&mut PipeState)) {
        f(&mut self.lock());
        self.readable.notify_one();
        self.writable.notify_one();
    }
}

impl PipeState {
    /// Moves bytes that are due by `now` into `out` (or drops them when `out` is `None`),
    /// up to `out`'s length; returns how many.
    fn take_ready(&mut self, mut out: Option<&mut [u8]>, now: Instant) -> usize {
        let mut taken = 0;
        while let Some(chunk) = self.chunks.front_mut() {
            if chunk.ready_at > now {
                break;
            }
            let avail = &chunk.data[chunk.pos..];
            let n = match out.as_deref_mut() {
                Some(out) => {
                    let n = avail.len().min(out.len() - taken);
                    out[taken..taken + n].copy_from_slice(&avail[..n]);
                    n
                }
                None => avail.len(),
            };
            chunk.pos += n;
            taken += n;
            self.buffered -= n;
            if chunk.pos == chunk.data.len() {
                self.chunks.pop_front();
            }
            if out.as_ref().is_some_and(|o| taken == o.len()) {
                break;
            }
        }
        taken
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const SEC: Duration = Duration::from_secs(1);

    #[tokio::test(start_paused = true)]
    async fn bytes_flow_both_ways() {
        let (mut a, mut b) = pair(64);
        a.write_all(b"Start").await.unwrap();
        let mut buf = [0u8; 5];
        b.read_exact(&mut buf, SEC).await.unwrap();
        assert_eq!(&buf, b"Start");
        b.write_all(b"Ready\r\n").await.unwrap();
        let mut buf = [0u8; 7];
        a.read_exact(&mut buf, SEC).await.unwrap();
        assert_eq!(&buf, b"Ready\r\n");
    }

    #[tokio::test(start_paused = true)]
    async fn a_paced_link_delivers_one_byte_per_byte_time() {
        let (mut a, mut b) = pair(64);
        // Above tokio's 1 ms timer resolution, so each byte is its own wake-up.
        let byte = Duration::from_millis(2);
        a.faults().set_byte_time(byte);
        let t0 = Instant::now();
        b.write_all(b"abc").await.unwrap();
        let mut buf = [0u8; 3];
        let mut got = Vec::new();
        while got.len() < 3 {
            let n = a.read(&mut buf, SEC).await.unwrap();
            got.extend_from_slice(&buf[..n]);
            assert_eq!(n, 1, "one byte per read: they arrive apart");
            assert_eq!(Instant::now() - t0, byte * got.len() as u32);
        }
        assert_eq!(got, b"abc");
    }

    #[tokio::test(start_paused = true)]
    async fn read_times_out_and_link_stays_usable() {
        let (mut a, mut b) = pair(64);
        let mut buf = [0u8; 4];
        let err = a.read(&mut buf, Duration::from_millis(250)).await;
        assert_eq!(err, Err(LinkError::Timeout { ms: 250 }));
        b.write_all(b"ok").await.unwrap();
        assert_eq!(a.read(&mut buf, SEC).await, Ok(2));
        assert_eq!(&buf[..2], b"ok");
    }

    #[tokio::test(start_paused = true)]
    async fn read_exact_reports_the_whole_timeout_after_a_partial_reply() {
        let (mut a, mut b) = pair(64);
        b.write_all(b"Rea").await.unwrap();
        let mut buf = [0u8; 7];
        let r = a.read_exact(&mut buf, Duration::from_millis(40)).await;
        assert_eq!(r, Err(LinkError::Timeout { ms: 40 }));
    }

    #[tokio::test(start_paused = true)]
    async fn empty_buffer_and_zero_timeout() {
        let (mut a, mut b) = pair(64);
        assert_eq!(a.read(&mut [], SEC).await, Ok(0));
        let mut buf = [0u8; 4];
        assert_eq!(
            a.read(&mut buf, Duration::ZERO).await,
            Err(LinkError::Timeout { ms: 0 })
        );
        b.write_all(b"x").await.unwrap();
        assert_eq!(a.read(&mut buf, Duration::ZERO).await, Ok(1));
    }

    #[tokio::test(start_paused = true)]
    async fn dropping_one_end_disconnects_after_buffered_bytes() {
        let (mut a, mut b) = pair(64);
        b.write_all(b"last words").await.unwrap();
        drop(b);
        let mut buf = [0u8; 10];
        a.read_exact(&mut buf, SEC).await.unwrap();
        assert_eq!(&buf, b"last words");
        assert!(matches!(
            a.read(&mut buf, SEC).await,
            Err(LinkError::Disconnected(_))
        ));
        assert!(matches!(
            a.write_all(b"x").await,
            Err(LinkError::Disconnected(_))
        ));
    }

    #[tokio::test(start_paused = true)]
    async fn drop_wakes_a_waiting_reader() {
        let (mut a, b) = pair(64);
        let reader = tokio::spawn(async move {
            let mut buf = [0u8; 4];
            a.read(&mut buf, Duration::from_secs(3600)).await
        });
        tokio::task::yield_now().await;
        drop(b);
        assert!(matches!(
            reader.await.unwrap(),
            Err(LinkError::Disconnected(_))
        ));
    }

    #[tokio::test(start_paused = true)]
    async fn injected_disconnect_hits_both_ends_and_drops_buffered_bytes() {
        let (mut a, mut b) = pair(64);
        let faults = a.faults();
        b.write_all(b"lost").await.unwrap();
        faults.disconnect("cable pulled");
        assert!(faults.is_disconnected());
        let mut buf = [0u8; 4];
        let e = a.read(&mut buf, SEC).await.unwrap_err();
        assert!(e.to_string().contains("cable pulled"), "{e}");
        assert!(matches!(
            b.read(&mut buf, SEC).await,
            Err(LinkError::Disconnected(_))
        ));
        assert!(matches!(
            b.write_all(b"x").await,
            Err(LinkError::Disconnected(_))
        ));
        assert!(matches!(
            a.discard_input().await,
            Err(LinkError::Disconnected(_))
        ));
    }

    #[tokio::test(start_paused = true)]
    async fn disconnect_wakes_a_writer_blocked_on_a_full_pipe() {
        let (mut a, _b) = pair(4);
        let faults = a.faults();
        let writer = tokio::spawn(async move { a.write_all(b"more than four").await });
        tokio::task::yield_now().await;
        faults.disconnect("unplugged");
        assert!(matches!(
            writer.await.unwrap(),
            Err(LinkError::Disconnected(_))
        ));
    }

    #[tokio::test(start_paused = true)]
    async fn full_pipe_applies_backpressure_until_read() {
        let (mut a, mut b) = pair(4);
        let writer = tokio::spawn(async move { a.write_all(b"0123456789").await.map(|()| a) });
        let mut got = Vec::new();
        let mut buf = [0u8; 3];
        while got.len() < 10 {
            let n = b.read(&mut buf, SEC).await.unwrap();
            got.extend_from_slice(&buf[..n]);
        }
        assert_eq!(got, b"0123456789");
        writer.await.unwrap().unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn discard_drops_stray_and_injected_bytes_only() {
        let (mut a, mut b) = pair(64);
        b.write_all(b"N\r\n").await.unwrap();
        a.faults().inject(b"junk");
        assert_eq!(a.discard_input().await, Ok(7));
        assert_eq!(a.discard_input().await, Ok(0));
        b.write_all(b"fresh").await.unwrap();
        let mut buf = [0u8; 5];
        a.read_exact(&mut buf, SEC).await.unwrap();
        assert_eq!(&buf, b"fresh");
    }

    #[tokio::test(start_paused = true)]
    async fn latency_delays_delivery_and_discard_keeps_bytes_in_flight() {
        let (mut a, mut b) = pair(64);
        a.faults().set_latency(Duration::from_millis(15));
        b.write_all(b"late").await.unwrap();
        let mut buf = [0u8; 4];
        assert_eq!(
            a.read(&mut buf, Duration::from_millis(10)).await,
            Err(LinkError::Timeout { ms: 10 })
        );
        // Not yet arrived, so not discarded.
        assert_eq!(a.discard_input().await, Ok(0));
        a.read_exact(&mut buf, Duration::from_millis(10))
            .await
            .unwrap();
        assert_eq!(&buf, b"late");
    }

    #[test]
    fn describe_uses_the_given_name() {
        let (a, _b) = pair(1);
        let a = a.named("optotune sim");
        assert_eq!(a.describe(), "optotune sim");
    }

    proptest! {
        /// Whatever the chunking of writes and reads and the pipe size, the byte stream
        /// arrives intact and in order.
        #[test]
        fn stream_survives_any_chunking(
            data in proptest::collection::vec(any::<u8>(), 0..600),
            write_sizes in proptest::collection::vec(1usize..50, 1..20),
            read_size in 1usize..64,
            capacity in 1usize..40,
        ) {
            let rt = tokio::runtime::Builder::new_current_thread()
                .enable_time()
                .start_paused(true)
                .build()
                .unwrap();
            let got = rt.block_on(async {
                let (mut a, mut b) = pair(capacity);
                let expected = data.len();
                let to_send = data.clone();
                let writer = tokio::spawn(async move {
                    let mut rest = &to_send[..];
                    for size in write_sizes.iter().cycle() {
                        if rest.is_empty() {
                            break;
                        }
                        let (now, later) = rest.split_at((*size).min(rest.len()));
                        a.write_all(now).await.unwrap();
                        rest = later;
                    }
                    a
                });
                let mut got = Vec::new();
                let mut buf = vec![0u8; read_size];
                while got.len() < expected {
                    let n = b.read(&mut buf, SEC).await.unwrap();
                    got.extend_from_slice(&buf[..n]);
                }
                drop(writer.await.unwrap());
                got
            });
            prop_assert_eq!(got, data);
        }
    }
}
