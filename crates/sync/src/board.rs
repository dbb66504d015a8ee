//! The dioptra multifocal sync board over dioptra-protocol, as a [`PlaneSequencer`].
//!
//! Session: `Hello` (the device must be a sync board that runs plane schedules), then a burst
//! of time-sync pings; one more ping per second while events are read keeps the device-to-host
//! mapping (with drift) current. Events carry device time; [`to_sequencer_event`] maps them.

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{
    Clock, ClockMapper, DeviceError, Diopters, PlaneSchedule, PlaneSequencer, SequencerEvent,
    SequencerFault, Timestamp,
};
use dioptra_protocol::{
    Capabilities, DeviceInfo, DeviceKind, ErrorCode, FaultKind, Message,
    PlaneSchedule as WireSchedule,
};
use dioptra_transport::protocol_client::ProtocolClient;
use dioptra_transport::ByteLink;

/// Pings sent when a session opens (PROTOCOL.md 7.1).
const SYNC_BURST: usize = 8;
/// Re-sync this often while reading events.
const RESYNC_EVERY: Duration = Duration::from_secs(1);
/// Silence while running longer than this is an error (a board sends hundreds of events/s).
pub const DEFAULT_EVENT_TIMEOUT: Duration = Duration::from_secs(2);

/// What the driver knows about the board.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardStatus {
    pub info: Option<DeviceInfo>,
    pub schedule: Option<PlaneSchedule>,
    pub running: bool,
    /// Frames from the board that failed to decode.
    pub garbled_frames: u64,
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

    async fn next_event(&mut self) -> Result<SequencerEvent, DeviceError> {
        if !self.running {
            return Err(DeviceError::Invalid(
                "the board is not running: start it first".into(),
            ));
        }
        loop {
            let now = self.clock.now();
            if now.saturating_since(self.last_sync) >= RESYNC_EVERY {
                // Events that arrive meanwhile are queued by the client, not lost.
                self.client.sync_time(1).await?;
                self.last_sync = now;
            }
            let r = self.client.next_event(self.event_timeout).await?;
            match to_sequencer_event(&r.message, r.host_time, self.client.clock_mapper()) {
                Some(ev) if event_host_time(&ev) >= self.started_at => return Ok(ev),
                _ => tracing::debug!(message = ?r.message, "sync board: event skipped"),
            }
        }
    }
}
