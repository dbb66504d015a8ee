//! The dioptra multifocal sync board over dioptra-protocol, as a [`PlaneSequencer`] and, for a
//! board with a photodiode input, a [`Photodiode`].
//!
//! Session: `Hello` (the device must be a sync board that runs plane schedules), then a burst
//! of time-sync pings; one more ping per second while events are read keeps the device-to-host
//! mapping (with drift) current. Events carry device time; [`to_sequencer_event`] and
//! [`to_light_edge`] map them.
//!
//! Sub-frame events and photodiode edges share the link. Whichever interface reads keeps what
//! belongs to the other in a bounded queue, and [`SyncBoard::next_board_event`] returns both
//! kinds in arrival order for a caller that wants both.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{
    Clock, ClockMapper, DeviceError, Diopters, LightEdge, LightEvent, LightQueue, LinkError,
    Photodiode, PlaneSchedule, PlaneSequencer, SequencerEvent, SequencerFault, Timestamp,
};
use dioptra_protocol::{
    Capabilities, DeviceInfo, DeviceKind, ErrorCode, FaultKind, Message, PhotodiodeConfig,
    PhotodiodeEdge, PlaneSchedule as WireSchedule,
};
use dioptra_transport::protocol_client::ProtocolClient;
use dioptra_transport::ByteLink;

/// Pings sent when a session opens (PROTOCOL.md 7.1).
const SYNC_BURST: usize = 8;
/// Re-sync this often while reading events.
const RESYNC_EVERY: Duration = Duration::from_secs(1);
/// Silence while running longer than this is an error (a board sends hundreds of events/s).
pub const DEFAULT_EVENT_TIMEOUT: Duration = Duration::from_secs(2);
/// Most events of one kind kept for the other interface's reader; the oldest go first.
const MAX_QUEUED: usize = 4096;

/// The photodiode input's comparator band, in fractions of the sensor's full scale: the light
/// is on above `threshold + hysteresis`, off below `threshold - hysteresis`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhotodiodeBand {
    pub threshold: f32,
    pub hysteresis: f32,
}

impl Default for PhotodiodeBand {
    /// Half scale, with 5 % of the scale either side: a white patch on any panel reads far
    /// above it, black far below.
    fn default() -> Self {
        PhotodiodeBand {
            threshold: 0.5,
            hysteresis: 0.05,
        }
    }
}

/// The wire config for `band` (`None`: input off), or why the board cannot take it.
pub fn wire_photodiode_config(
    band: Option<PhotodiodeBand>,
) -> Result<PhotodiodeConfig, DeviceError> {
    let Some(band) = band else {
        return Ok(PhotodiodeConfig {
            enabled: false,
            threshold: 1,
            hysteresis: 0,
        });
    };
    let scale = f32::from(u16::MAX);
    let (t, h) = (band.threshold, band.hysteresis);
    // The band must lie strictly inside the scale or one edge could never happen.
    if !(t.is_finite() && h.is_finite() && h >= 0.0 && t - h > 0.0 && t + h < 1.0) {
        return Err(DeviceError::Invalid(format!(
            "photodiode threshold {t} +/- hysteresis {h} must lie strictly inside 0..1 of the sensor's scale"
        )));
    }
    let config = PhotodiodeConfig {
        enabled: true,
        threshold: (t * scale).round() as u16,
        hysteresis: (h * scale).round() as u16,
    };
    config
        .validate()
        .map_err(|e| DeviceError::Invalid(format!("photodiode band: {e}")))?;
    Ok(config)
}

/// A board edge as a [`LightEdge`], its device time mapped to host time (`received`, the host
/// time the frame arrived, until the clocks are synchronised).
pub fn to_light_edge(
    edge: &PhotodiodeEdge,
    received: Timestamp,
    mapper: &ClockMapper,
) -> LightEdge {
    LightEdge {
        device_time: Timestamp::from_micros(edge.device_time_us),
        host_receive_time: received,
        host_time: mapper.to_host(edge.device_time_us).unwrap_or(received),
        rising: edge.rising,
        level: Some(f32::from(edge.level) / f32::from(u16::MAX)),
    }
}

/// What the board reports: sub-frames and faults, or light on its photodiode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum BoardEvent {
    Sequencer(SequencerEvent),
    Light(LightEvent),
}

/// What the driver knows about the board.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardStatus {
    pub info: Option<DeviceInfo>,
    pub schedule: Option<PlaneSchedule>,
    pub running: bool,
    /// Frames from the board that failed to decode.
    pub garbled_frames: u64,
    /// The photodiode input's band while it reports.
    pub photodiode: Option<PhotodiodeBand>,
    /// Photodiode edges the board reported lost (gaps in its edge counter), and ones this
    /// driver dropped because nobody read them.
    pub light_edges_lost: u64,
}

/// A dioptra sync board on any [`ByteLink`] (its USB serial port, a pty, an in-memory pair).
pub struct SyncBoard<L: ByteLink> {
    client: ProtocolClient<L>,
    clock: Arc<dyn Clock>,
    trigger_rising: bool,
    schedule: Option<PlaneSchedule>,
    running: bool,
    /// Host time the last Start was sent: events from before it are stale (e.g. from a
    /// session that left the board running), and are dropped.
    started_at: Timestamp,
    last_sync: Timestamp,
    event_timeout: Duration,
    photodiode: Option<PhotodiodeBand>,
    /// The board's counter value the next edge should carry.
    next_edge: u32,
    light_lost: u64,
    /// Read for the other interface's reader, in arrival order.
    light_queue: LightQueue,
    sequencer_queue: VecDeque<SequencerEvent>,
    /// An edge read after a gap, returned after the gap's `Lost` report.
    held_edge: Option<LightEvent>,
}

/// The wire schedule for `schedule`, or why it cannot be sent.
pub fn wire_schedule(
    schedule: &PlaneSchedule,
    trigger_rising: bool,
) -> Result<WireSchedule, DeviceError> {
    let us = |d: Duration, what: &str| {
        u32::try_from(d.as_micros())
            .map_err(|_| DeviceError::Invalid(format!("{what} {d:?} is too long for the board")))
    };
    let powers: Vec<f32> = schedule.planes().iter().map(|p| p.0).collect();
    WireSchedule::new(
        &powers,
        us(schedule.subframe_period(), "sub-frame period")?,
        us(schedule.settle_allowance(), "settle allowance")?,
        trigger_rising,
    )
    .map_err(|e| DeviceError::Invalid(format!("{e} (in whole microseconds)")))
}

/// A board event as a [`SequencerEvent`], its device time mapped to host time (`received`,
/// the host time the frame arrived, until the clocks are synchronised). `None` for messages
/// that are not sequencer events.
pub fn to_sequencer_event(
    message: &Message,
    received: Timestamp,
    mapper: &ClockMapper,
) -> Option<SequencerEvent> {
    match message {
        Message::SubframeEvent(e) => Some(SequencerEvent::SubframeStart {
            frame: e.frame,
            plane_index: e.plane_index,
            device_time: Timestamp::from_micros(e.device_time_us),
            host_time: mapper.to_host(e.device_time_us).unwrap_or(received),
            lens_power: e
                .lens_power_d
                .is_finite()
                .then_some(Diopters(e.lens_power_d)),
        }),
        Message::Fault(f) => Some(SequencerEvent::Fault {
            fault: match f.kind {
                FaultKind::MissedVsync => SequencerFault::MissedVsync,
                FaultKind::LateSettle => SequencerFault::LateSettle,
                other => SequencerFault::Other(other as u16),
            },
            frame: f.frame,
            plane_index: f.plane_index,
            host_time: mapper.to_host(f.device_time_us).unwrap_or(received),
        }),
        _ => None,
    }
}

fn event_host_time(ev: &SequencerEvent) -> Timestamp {
    match ev {
        SequencerEvent::SubframeStart { host_time, .. }
        | SequencerEvent::Fault { host_time, .. } => *host_time,
    }
}

impl<L: ByteLink> SyncBoard<L> {
    /// Opens a session on `link`: checks the device is a sync board and synchronises clocks.
    pub async fn connect(link: L, clock: Arc<dyn Clock>) -> Result<Self, DeviceError> {
        let mut board = SyncBoard {
            client: ProtocolClient::new(link, clock.clone()),
            clock,
            trigger_rising: true,
            schedule: None,
            running: false,
            started_at: Timestamp::ZERO,
            last_sync: Timestamp::ZERO,
            event_timeout: DEFAULT_EVENT_TIMEOUT,
            photodiode: None,
            next_edge: 0,
            light_lost: 0,
            light_queue: LightQueue::new(MAX_QUEUED),
            sequencer_queue: VecDeque::new(),
            held_edge: None,
        };
        board.open_session().await?;
        Ok(board)
    }

    /// Frames start on the rising (default) or falling vsync edge; applies from the next program.
    pub fn with_trigger_rising(mut self, rising: bool) -> Self {
        self.trigger_rising = rising;
        self
    }

    pub fn with_event_timeout(mut self, timeout: Duration) -> Self {
        self.event_timeout = timeout;
        self
    }

    async fn open_session(&mut self) -> Result<(), DeviceError> {
        // A 0x00 ends whatever garbage the board holds (PROTOCOL.md 1.1).
        self.client.link_mut().write_all(&[0]).await?;
        let info = self.client.hello().await?;
        if info.kind != DeviceKind::SyncBoard
            || !info.capabilities.contains(Capabilities::PLANE_SCHEDULE)
        {
            return Err(DeviceError::Invalid(format!(
                "{} is a {:?}, not a sync board that runs plane schedules",
                self.client.link().describe(),
                info.kind
            )));
        }
        if info.capabilities.contains(Capabilities::TIME_SYNC) {
            self.client.sync_time(SYNC_BURST).await?;
            self.last_sync = self.clock.now();
        }
        Ok(())
    }

    pub fn status(&self) -> BoardStatus {
        BoardStatus {
            info: self.client.device_info().cloned(),
            schedule: self.schedule.clone(),
            running: self.running,
            garbled_frames: self.client.garbled_frames(),
            photodiode: self.photodiode,
            light_edges_lost: self.light_lost + self.light_queue.dropped(),
        }
    }

    /// Whether the board has a photodiode input (its `PHOTODIODE` capability).
    pub fn has_photodiode(&self) -> bool {
        self.client
            .device_info()
            .is_some_and(|i| i.capabilities.contains(Capabilities::PHOTODIODE))
    }

    /// Switches the photodiode input on with `band`, or off with `None`. Edges then arrive
    /// whether or not a schedule runs.
    pub async fn set_photodiode(
        &mut self,
        band: Option<PhotodiodeBand>,
    ) -> Result<(), DeviceError> {
        let config = wire_photodiode_config(band)?;
        if band.is_none() && !self.has_photodiode() {
            self.photodiode = None;
            return Ok(()); // no input, nothing to switch off
        }
        if !self.has_photodiode() {
            return Err(DeviceError::Invalid(format!(
                "the sync board on {} has no photodiode input (its firmware does not announce PHOTODIODE)",
                self.client.link().describe()
            )));
        }
        self.expect_ack(&Message::PhotodiodeConfig(config)).await?;
        // The board restarts its counter; edges of the last config still queued are stale.
        self.photodiode = band;
        self.next_edge = 0;
        self.held_edge = None;
        self.light_queue.clear();
        Ok(())
    }

    /// The next event of either kind: first those kept while one interface read, then in the
    /// order the board sent them. Sub-frame events come
    /// while a schedule runs, light events while the photodiode input is on; with neither
    /// there is nothing to wait for and this is an error.
    pub async fn next_board_event(&mut self) -> Result<BoardEvent, DeviceError> {
        if let Some(e) = self.sequencer_queue.pop_front() {
            return Ok(BoardEvent::Sequencer(e));
        }
        if let Some(e) = self.light_queue.pop() {
            return Ok(BoardEvent::Light(e));
        }
        self.read_board_event().await
    }

    /// Reads the link for the next event (resynchronising the clocks once a second).
    async fn read_board_event(&mut self) -> Result<BoardEvent, DeviceError> {
        if let Some(e) = self.held_edge.take() {
            return Ok(BoardEvent::Light(e));
        }
        if !self.running && self.photodiode.is_none() {
            return Err(DeviceError::Invalid(
                "the board is neither running a schedule nor reporting its photodiode: start it or switch the photodiode on first".into(),
            ));
        }
        loop {
            let now = self.clock.now();
            let since_sync = now.saturating_since(self.last_sync);
            if since_sync >= RESYNC_EVERY {
                // Events that arrive meanwhile are queued by the client, not lost. The ping
                // also proves the link alive while a quiet photodiode sends nothing.
                self.client.sync_time(1).await?;
                self.last_sync = now;
                continue;
            }
            // Sub-frames come every few ms, so silence while running is a fault; the light on
            // a photodiode may not change for minutes, so then only the next ping is due.
            let wait = if self.running {
                self.event_timeout
            } else {
                RESYNC_EVERY - since_sync
            };
            let r = match self.client.next_event(wait).await {
                Ok(r) => r,
                Err(DeviceError::Link(LinkError::Timeout { .. })) if !self.running => continue,
                Err(e) => return Err(e),
            };
            if let Message::PhotodiodeEdge(edge) = &r.message {
                if self.photodiode.is_none() {
                    tracing::debug!(?edge, "sync board: photodiode edge while off, skipped");
                    continue;
                }
                let light =
                    LightEvent::Edge(to_light_edge(edge, r.host_time, self.client.clock_mapper()));
                // A gap in the board's counter: it dropped edges it could not send.
                let gap = edge.edge.wrapping_sub(self.next_edge);
                self.next_edge = edge.edge.wrapping_add(1);
                if gap > 0 {
                    self.light_lost += u64::from(gap);
                    self.held_edge = Some(light);
                    return Ok(BoardEvent::Light(LightEvent::Lost {
                        count: u64::from(gap),
                        host_time: r.host_time,
                    }));
                }
                return Ok(BoardEvent::Light(light));
            }
            match to_sequencer_event(&r.message, r.host_time, self.client.clock_mapper()) {
                Some(ev) if self.running && event_host_time(&ev) >= self.started_at => {
                    return Ok(BoardEvent::Sequencer(ev))
                }
                _ => tracing::debug!(message = ?r.message, "sync board: event skipped"),
            }
        }
    }

    fn keep_sequencer(&mut self, event: SequencerEvent) {
        self.sequencer_queue.push_back(event);
        if self.sequencer_queue.len() > MAX_QUEUED {
            self.sequencer_queue.pop_front();
        }
    }

    /// Host time of a board timestamp, once clocks are synchronised.
    pub fn device_to_host(&self, device_time_us: u64) -> Option<Timestamp> {
        self.client.device_to_host(device_time_us)
    }

    /// After an unplug: takes the reopened link, opens a new session and restores the
    /// schedule (and restarts it if it was running).
    pub async fn reconnect(&mut self, link: L) -> Result<(), DeviceError> {
        self.client.reset_session(link);
        let was_running = std::mem::take(&mut self.running);
        self.open_session().await?;
        if let Some(band) = self.photodiode {
            self.set_photodiode(Some(band)).await?;
        }
        if let Some(schedule) = self.schedule.clone() {
            self.program(&schedule).await?;
            if was_running {
                self.start().await?;
            }
        }
        Ok(())
    }

    async fn expect_ack(&mut self, message: &Message) -> Result<(), DeviceError> {
        let r = self.client.request(message).await?;
        match r.message {
            Message::Ack => Ok(()),
            other => Err(DeviceError::Protocol(format!(
                "expected Ack to {message:?}, board sent {other:?}"
            ))),
        }
    }
}

impl<L: ByteLink> PlaneSequencer for SyncBoard<L> {
    /// Loads `schedule`, stopping the board first when it is running (also when another
    /// session left it running: the board answers Busy).
    async fn program(&mut self, schedule: &PlaneSchedule) -> Result<(), DeviceError> {
        let message = Message::PlaneSchedule(wire_schedule(schedule, self.trigger_rising)?);
        match self.expect_ack(&message).await {
            Err(DeviceError::Refused { code, .. }) if code == ErrorCode::Busy as u16 => {
                self.stop().await?;
                self.expect_ack(&message).await?;
            }
            other => other?,
        }
        self.running = false;
        self.schedule = Some(schedule.clone());
        Ok(())
    }

    async fn start(&mut self) -> Result<(), DeviceError> {
        self.started_at = self.clock.now();
        self.expect_ack(&Message::Start).await?;
        self.running = true;
        Ok(())
    }

    async fn stop(&mut self) -> Result<(), DeviceError> {
        self.running = false;
        self.expect_ack(&Message::Stop).await
    }

    /// The next sub-frame event or fault; photodiode edges read meanwhile are kept for
    /// [`Photodiode::next_light`].
    async fn next_event(&mut self) -> Result<SequencerEvent, DeviceError> {
        if let Some(e) = self.sequencer_queue.pop_front() {
            return Ok(e);
        }
        if !self.running {
            return Err(DeviceError::Invalid(
                "the board is not running: start it first".into(),
            ));
        }
        loop {
            match self.read_board_event().await? {
                BoardEvent::Sequencer(e) => return Ok(e),
                BoardEvent::Light(e) => self.light_queue.push(e),
            }
        }
    }
}

impl<L: ByteLink> Photodiode for SyncBoard<L> {
    /// The next photodiode edge (switch the input on with [`SyncBoard::set_photodiode`]);
    /// sub-frame events read meanwhile are kept for [`PlaneSequencer::next_event`].
    async fn next_light(&mut self) -> Result<LightEvent, DeviceError> {
        if let Some(e) = self.light_queue.pop() {
            return Ok(e);
        }
        if self.photodiode.is_none() {
            return Err(DeviceError::Invalid(
                "the board's photodiode input is off: switch it on first".into(),
            ));
        }
        loop {
            match self.read_board_event().await? {
                BoardEvent::Light(e) => return Ok(e),
                BoardEvent::Sequencer(e) => self.keep_sequencer(e),
            }
        }
    }
}
