//! The serial-line photodiode over any [`ByteLink`]: a USB serial port to a microcontroller
//! running the sketch in firmware-protocol/photodiode/, a pty to `dioptra sim photodiode`, or an
//! in-memory link to the simulator.
//!
//! Session: a newline (ends whatever partial command the device holds), then `v` until the
//! hello line comes (opening the port resets many Arduino boards, which then take a second or
//! two to boot and send it by themselves), the version checked, then a burst of clock-sync
//! pings (`s`). While edges are read, one ping per second keeps the device-to-host mapping
//! (with drift) current and proves the link alive when the light does not change. The mapping
//! is the one every dioptra driver uses ([`ClockMapper`], minimum round trip): the device
//! clock when the ping arrived, against the midpoint of the host's send and receive times.
//!
//! Nothing the device sends is fatal except a link failure, silence where a reply is due, or
//! another protocol version: malformed lines are counted ([`PhotodiodeStatus`]) and skipped;
//! a missing edge (two of the same level in a row) or an `!overflow` becomes a
//! [`LightEvent::Lost`]; a hello in the middle of the stream (the board restarted) resets the
//! clock mapping and resynchronises.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{
    Clock, ClockMapper, DeviceError, LightEdge, LightEvent, LightQueue, LinkError, Photodiode,
    Timestamp,
};
use dioptra_transport::ByteLink;
use tokio::time::Instant;

use crate::ids::{HELLO_NAME, LINE_PROTOCOL_VERSION};
use crate::protocol::{command, Line, LineError, LineParser};

/// How the driver talks to one device.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SerialPhotodiodeConfig {
    /// Wait this long for the hello line at connect (a board reset by the port opening takes
    /// 1-2 s to boot).
    pub hello_timeout: Duration,
    /// Wait this long for a sync reply.
    pub reply_timeout: Duration,
    /// Pings at connect; the one with the smallest round trip sets the offset.
    pub sync_burst: usize,
    /// One ping this often while reading edges.
    pub resync_every: Duration,
}

impl Default for SerialPhotodiodeConfig {
    fn default() -> Self {
        SerialPhotodiodeConfig {
            hello_timeout: Duration::from_secs(3),
            // A sketch answers from its loop, within a USB frame or two; USB-serial bridges
            // with a latency timer (FTDI: 16 ms by default) take longer.
            reply_timeout: Duration::from_millis(100),
            sync_burst: 8,
            resync_every: Duration::from_secs(1),
        }
    }
}

/// Asks for the hello line this often while waiting for it.
const HELLO_RETRY: Duration = Duration::from_millis(500);
/// Most events read ahead (during a sync exchange) and not yet taken.
const MAX_PENDING: usize = 4096;

/// What the driver knows about the device and what it has seen.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PhotodiodeStatus {
    /// The hello line's text (board, firmware, sensor).
    pub about: String,
    pub edges: u64,
    /// Edges the device reported lost (`!overflow`) or that went missing (two of one level
    /// in a row).
    pub lost: u64,
    /// Lines that did not parse, edges whose time went backwards.
    pub malformed_lines: u64,
    /// The newest of them, for the log and the status page.
    pub last_malformed: Option<String>,
    /// Hello lines in the middle of the stream: the board restarted.
    pub restarts: u64,
}

/// A connected serial-line photodiode.
pub struct SerialPhotodiode<L: ByteLink> {
    link: L,
    clock: Arc<dyn Clock>,
    cfg: SerialPhotodiodeConfig,
    parser: LineParser,
    /// Lines parsed but not yet handled, with the host time their bytes arrived.
    inbox: VecDeque<(Result<Line, LineError>, Timestamp)>,
    mapper: ClockMapper,
    /// Events read while the clock mapping was empty (during the first sync exchange after
    /// connect or a restart), their edges stamped with the receive time: mapped once it is not.
    held: Vec<LightEvent>,
    /// The first sync reply has come: a hello from now on means the board restarted (before
    /// it, one is the answer to a `v` the board may have answered twice).
    in_session: bool,
    pending: LightQueue,
    last_sync: Timestamp,
    last_level: Option<bool>,
    last_edge_us: Option<u64>,
    status: PhotodiodeStatus,
}

impl<L: ByteLink> std::fmt::Debug for SerialPhotodiode<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SerialPhotodiode")
            .field("link", &self.link.describe())
            .field("status", &self.status)
            .finish_non_exhaustive()
    }
}

impl<L: ByteLink> SerialPhotodiode<L> {
    /// Opens a session with the default config.
    pub async fn connect(link: L, clock: Arc<dyn Clock>) -> Result<Self, DeviceError> {
        Self::connect_with(link, SerialPhotodiodeConfig::default(), clock).await
    }

    /// Opens a session: waits for the hello line, checks the version, synchronises clocks.
    pub async fn connect_with(
        link: L,
        cfg: SerialPhotodiodeConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, DeviceError> {
        let mut d = SerialPhotodiode {
            link,
            clock,
            cfg,
            parser: LineParser::new(),
            inbox: VecDeque::new(),
            mapper: ClockMapper::new(),
            held: Vec::new(),
            in_session: false,
            pending: LightQueue::new(MAX_PENDING),
            last_sync: Timestamp::ZERO,
            last_level: None,
            last_edge_us: None,
            status: PhotodiodeStatus::default(),
        };
        d.link.write_all(b"\n").await?;
        d.hello().await?;
        d.sync_time(cfg.sync_burst.max(1)).await?;
        Ok(d)
    }

    /// What the driver has seen so far.
    pub fn status(&self) -> PhotodiodeStatus {
        let mut s = self.status.clone();
        s.lost += self.pending.dropped();
        s
    }

    /// Host time of a device timestamp, once clocks are synchronised.
    pub fn device_to_host(&self, device_time_us: u64) -> Option<Timestamp> {
        self.mapper.to_host(device_time_us)
    }

    pub fn link(&self) -> &L {
        &self.link
    }

    async fn hello(&mut self) -> Result<(), DeviceError> {
        let end = Instant::now() + self.cfg.hello_timeout;
        loop {
            self.link.write_all(command::HELLO).await?;
            let retry = (Instant::now() + HELLO_RETRY).min(end);
            loop {
                match self.read_line(retry).await {
                    Ok((Line::Hello { version, about }, _)) => {
                        check_version(version, &self.link.describe())?;
                        self.status.about = about;
                        return Ok(());
                    }
                    // Whatever the device sent before it knew a host was there.
                    Ok(_) => {}
                    Err(DeviceError::Link(LinkError::Timeout { .. })) if Instant::now() < end => {
                        break
                    }
                    Err(DeviceError::Link(LinkError::Timeout { .. })) => {
                        return Err(DeviceError::Protocol(format!(
                            "no hello line ({HELLO_NAME},{LINE_PROTOCOL_VERSION},...) from {} within {:?}{}: is it running the dioptra photodiode sketch, at {} baud?",
                            self.link.describe(),
                            self.cfg.hello_timeout,
                            self.last_malformed_note(),
                            crate::ids::BAUD
                        )))
                    }
                    Err(e) => return Err(e),
                }
            }
        }
    }

    fn last_malformed_note(&self) -> String {
        match &self.status.last_malformed {
            Some(m) => format!(
                " ({} malformed lines, the last {m})",
                self.status.malformed_lines
            ),
            None => String::new(),
        }
    }

    /// Runs `rounds` ping/reply exchanges and feeds them to the clock mapper. Edges that
    /// arrive meanwhile are kept in order.
    pub async fn sync_time(&mut self, rounds: usize) -> Result<(), DeviceError> {
        for _ in 0..rounds {
            let sent = self.clock.now();
            self.link.write_all(command::SYNC).await?;
            let deadline = Instant::now() + self.cfg.reply_timeout;
            loop {
                let (line, received) = match self.read_line(deadline).await {
                    Ok(l) => l,
                    Err(DeviceError::Link(LinkError::Timeout { .. })) => {
                        // A reply cut short by the timeout must not swallow the next one.
                        self.parser.reset();
                        return Err(DeviceError::Link(LinkError::Timeout {
                            ms: self.cfg.reply_timeout.as_millis() as u64,
                        }));
                    }
                    Err(e) => return Err(e),
                };
                if let Line::Sync { device_time_us } = line {
                    self.mapper.add_exchange(sent, device_time_us, received);
                    self.in_session = true;
                    self.map_held_edges();
                    break;
                }
                self.handle(line, received)?;
            }
        }
        self.last_sync = self.clock.now();
        Ok(())
    }

    /// The next parsed line and the host time its bytes arrived, reading until `deadline`.
    /// Lines that do not parse are counted and skipped.
    async fn read_line(&mut self, deadline: Instant) -> Result<(Line, Timestamp), DeviceError> {
        loop {
            while let Some((line, received)) = self.inbox.pop_front() {
                match line {
                    Ok(line) => return Ok((line, received)),
                    Err(e) => self.malformed(e.to_string()),
                }
            }
            let mut buf = [0u8; 256];
            let left = deadline.saturating_duration_since(Instant::now());
            let n = self.link.read(&mut buf, left).await?;
            let received = self.clock.now();
            for line in self.parser.push(&buf[..n]) {
                self.inbox.push_back((line, received));
            }
        }
    }

    /// Events held while the mapping was empty, their edges now mapped, in order.
    fn map_held_edges(&mut self) {
        for mut event in std::mem::take(&mut self.held) {
            if let LightEvent::Edge(e) = &mut event {
                if let Some(t) = self.mapper.to_host(e.device_time.as_micros()) {
                    e.host_time = t;
                }
            }
            self.pending.push(event);
        }
    }

    /// Queues `event` for the reader, or holds it until the clocks are synchronised.
    fn emit(&mut self, event: LightEvent) {
        if self.in_session {
            self.pending.push(event);
        } else {
            self.held.push(event);
        }
    }

    fn malformed(&mut self, what: String) {
        tracing::debug!(device = %self.link.describe(), "photodiode: {what}");
        self.status.malformed_lines += 1;
        self.status.last_malformed = Some(what);
    }

    /// Turns one line into events (kept in `pending`).
    fn handle(&mut self, line: Line, received: Timestamp) -> Result<(), DeviceError> {
        match line {
            Line::Edge { device_time_us, on } => {
                if self.last_edge_us.is_some_and(|t| device_time_us < t) {
                    self.malformed(format!(
                        "an edge at {device_time_us} us, before the previous one: skipped"
                    ));
                    return Ok(());
                }
                if self.last_level == Some(on) {
                    // The edge between two of the same level went missing.
                    self.status.lost += 1;
                    self.emit(LightEvent::Lost {
                        count: 1,
                        host_time: received,
                    });
                }
                self.last_edge_us = Some(device_time_us);
                self.last_level = Some(on);
                self.status.edges += 1;
                self.emit(LightEvent::Edge(LightEdge {
                    device_time: Timestamp::from_micros(device_time_us),
                    host_receive_time: received,
                    host_time: self.mapper.to_host(device_time_us).unwrap_or(received),
                    rising: on,
                    level: None,
                }));
            }
            Line::Overflow { lost } => {
                self.status.lost += lost;
                // The level after the lost edges is unknown: the next edge starts afresh.
                self.last_level = None;
                self.emit(LightEvent::Lost {
                    count: lost,
                    host_time: received,
                });
            }
            Line::Hello { version, about } => {
                check_version(version, &self.link.describe())?;
                if !self.in_session {
                    return Ok(());
                }
                tracing::warn!(device = %self.link.describe(), "photodiode restarted: resynchronising its clock");
                self.status.restarts += 1;
                self.status.about = about;
                self.mapper.reset();
                self.in_session = false;
                self.last_edge_us = None;
                self.last_level = None;
                // Resynchronise before the next edge is mapped.
                self.last_sync = Timestamp::ZERO;
            }
            // A late reply to a ping that timed out.
            Line::Sync { .. } => {}
            Line::Comment(text) => {
                tracing::debug!(device = %self.link.describe(), "photodiode says: {text}")
            }
        }
        Ok(())
    }
}

fn check_version(version: u32, device: &str) -> Result<(), DeviceError> {
    if version == LINE_PROTOCOL_VERSION {
        return Ok(());
    }
    Err(DeviceError::Invalid(format!(
        "the photodiode on {device} speaks line protocol version {version}, this dioptra speaks {LINE_PROTOCOL_VERSION}: update the sketch or dioptra"
    )))
}

impl<L: ByteLink> Photodiode for SerialPhotodiode<L> {
    async fn next_light(&mut self) -> Result<LightEvent, DeviceError> {
        loop {
            if self.clock.now().saturating_since(self.last_sync) >= self.cfg.resync_every {
                self.sync_time(1).await?;
            }
            if let Some(e) = self.pending.pop() {
                return Ok(e);
            }
            let until_sync = self
                .cfg
                .resync_every
                .saturating_sub(self.clock.now().saturating_since(self.last_sync));
            match self.read_line(Instant::now() + until_sync).await {
                Ok((line, received)) => self.handle(line, received)?,
                // Quiet light: time for the next ping, which checks the link.
                Err(DeviceError::Link(LinkError::Timeout { .. })) => {}
                Err(e) => return Err(e),
            }
        }
    }
}
