//! The device traits the scheduler drives. Drivers implement them over real or simulated
//! links; the scheduler never links a hardware library.

use std::future::Future;
use std::time::Duration;

use crate::error::{DeviceError, InputError};
use crate::time::Timestamp;
use crate::units::{Diopters, PowerRange};

/// What a lens reports about itself. Fields a device cannot measure are `None`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensState {
    pub power: Diopters,
    pub current_ma: Option<f32>,
    pub temperature_c: Option<f32>,
    pub settled: Option<bool>,
    /// Host time at which the reply arrived.
    pub host_time: Timestamp,
}

/// A condition a device reported that does not stop it (a status warning), for the caller to
/// report once, naming the device: drivers do not know which eye a device serves.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DeviceWarning {
    /// What the device said, in its own terms (e.g. a status bit's name).
    pub condition: String,
    /// What it means for the user, and what to do about it.
    pub meaning: String,
}

impl std::fmt::Display for DeviceWarning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.condition, self.meaning)
    }
}

/// A focus-tunable lens. Implementations enforce [`VarifocalLens::power_range`] themselves:
/// a request outside it is clamped or refused, and never sent.
pub trait VarifocalLens: Send {
    /// The range this driver will drive the lens within.
    fn power_range(&self) -> PowerRange;
    /// Commands `power`; resolves when the command is on the wire, with that host time.
    fn set_power(
        &mut self,
        power: Diopters,
    ) -> impl Future<Output = Result<Timestamp, DeviceError>> + Send;
    /// Reads back power, current and temperature.
    fn state(&mut self) -> impl Future<Output = Result<LensState, DeviceError>> + Send;
    /// Warnings the device raised since the last call, each once per (re)connect.
    fn take_warnings(&mut self) -> Vec<DeviceWarning> {
        Vec::new()
    }
}

/// Which eye.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Side {
    Left,
    Right,
}

impl Side {
    pub const BOTH: [Side; 2] = [Side::Left, Side::Right];

    /// `left` or `right`, as configs, the API and recordings spell it.
    pub fn as_str(self) -> &'static str {
        match self {
            Side::Left => "left",
            Side::Right => "right",
        }
    }

    pub fn parse(s: &str) -> Option<Side> {
        Side::BOTH.into_iter().find(|e| e.as_str() == s)
    }
}

/// One eye's gaze ray in the head frame.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct EyeRay {
    /// Eye position (cornea or rotation centre, as the tracker reports), millimetres.
    pub origin_mm: [f32; 3],
    /// Unit gaze direction; +z forward, +x right, +y up.
    pub direction: [f32; 3],
    pub pupil_mm: f32,
    pub valid: bool,
}

/// Both eyes at one instant.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GazeSample {
    /// The tracker's own clock.
    pub device_time: Timestamp,
    /// When the host received the sample.
    pub host_receive_time: Timestamp,
    /// The device time mapped onto the host timeline by the driver's clock-offset estimate.
    pub host_time: Timestamp,
    pub left: EyeRay,
    pub right: EyeRay,
}

/// A source of binocular gaze samples, in order.
pub trait GazeSource: Send {
    /// Nominal sample rate, Hz.
    fn rate_hz(&self) -> f32;
    /// Waits for the next sample.
    fn next_sample(&mut self) -> impl Future<Output = Result<GazeSample, DeviceError>> + Send;
}

/// Most planes a plane schedule may hold (the wire protocol's limit).
pub const MAX_PLANES: usize = 16;

/// The focal planes a multifocal rig cycles through, one per sub-frame.
#[derive(Debug, Clone, PartialEq)]
pub struct PlaneSchedule {
    planes: Vec<Diopters>,
    subframe_period: Duration,
    settle_allowance: Duration,
}

impl PlaneSchedule {
    pub fn new(
        planes: Vec<Diopters>,
        subframe_period: Duration,
        settle_allowance: Duration,
    ) -> Result<Self, InputError> {
        if planes.is_empty() || planes.len() > MAX_PLANES {
            return Err(InputError::InvalidValue(format!(
                "a plane schedule needs 1 to {MAX_PLANES} planes, got {}",
                planes.len()
            )));
        }
        if let Some(p) = planes.iter().find(|p| !p.is_finite()) {
            return Err(InputError::InvalidValue(format!(
                "plane power {p} is not finite"
            )));
        }
        if subframe_period.is_zero() {
            return Err(InputError::InvalidValue(
                "sub-frame period must be > 0".into(),
            ));
        }
        if settle_allowance >= subframe_period {
            return Err(InputError::InvalidValue(format!(
                "settle allowance {settle_allowance:?} must be shorter than the sub-frame period {subframe_period:?}"
            )));
        }
        Ok(PlaneSchedule {
            planes,
            subframe_period,
            settle_allowance,
        })
    }
    pub fn planes(&self) -> &[Diopters] {
        &self.planes
    }
    pub fn subframe_period(&self) -> Duration {
        self.subframe_period
    }
    pub fn settle_allowance(&self) -> Duration {
        self.settle_allowance
    }
    /// One full cycle through every plane.
    pub fn frame_period(&self) -> Duration {
        self.subframe_period * self.planes.len() as u32
    }
}

/// Something that went wrong during a sequence, as the sync hardware saw it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SequencerFault {
    MissedVsync,
    LateSettle,
    Other(u16),
}

/// What the sync hardware reports while a schedule runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SequencerEvent {
    SubframeStart {
        frame: u32,
        plane_index: u8,
        device_time: Timestamp,
        host_time: Timestamp,
        /// Lens power reached at the sub-frame's start, when the hardware measures it.
        lens_power: Option<Diopters>,
    },
    Fault {
        fault: SequencerFault,
        frame: u32,
        plane_index: u8,
        host_time: Timestamp,
    },
}

/// Sync hardware that steps a lens through focal planes in lockstep with a display.
pub trait PlaneSequencer: Send {
    fn program(
        &mut self,
        schedule: &PlaneSchedule,
    ) -> impl Future<Output = Result<(), DeviceError>> + Send;
    fn start(&mut self) -> impl Future<Output = Result<(), DeviceError>> + Send;
    fn stop(&mut self) -> impl Future<Output = Result<(), DeviceError>> + Send;
    /// Waits for the next event.
    fn next_event(&mut self) -> impl Future<Output = Result<SequencerEvent, DeviceError>> + Send;
}

/// The light on a photodiode crossed its threshold: the moment light left (or stopped leaving)
/// the patch of display the sensor watches.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightEdge {
    /// The device's own clock.
    pub device_time: Timestamp,
    /// When the host received the report.
    pub host_receive_time: Timestamp,
    /// The device time mapped onto the host timeline by the driver's clock-offset estimate.
    pub host_time: Timestamp,
    /// The light came on (true) or went off (false).
    pub rising: bool,
    /// Sensor level just after the edge, 0 to 1 of full scale, when the device measures one.
    pub level: Option<f32>,
}

/// What a photodiode reports, in order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LightEvent {
    Edge(LightEdge),
    /// The device could not report `count` edges (its queue overflowed, or an edge went
    /// missing between two of the same direction): the light between the edges around this
    /// is unknown.
    Lost {
        count: u64,
        host_time: Timestamp,
    },
}

impl LightEvent {
    /// Host time of the edge, or of the report of the loss.
    pub fn host_time(&self) -> Timestamp {
        match self {
            LightEvent::Edge(e) => e.host_time,
            LightEvent::Lost { host_time, .. } => *host_time,
        }
    }
}

/// Light events read and not yet taken, at most `capacity` of them: when it is full, the
/// oldest make way for one [`LightEvent::Lost`] in their place, so a reader that falls behind
/// learns how many edges it missed and where.
#[derive(Debug, Clone)]
pub struct LightQueue {
    events: std::collections::VecDeque<LightEvent>,
    capacity: usize,
    dropped: u64,
}

impl LightQueue {
    /// A queue of at least 2 events.
    pub fn new(capacity: usize) -> Self {
        LightQueue {
            events: std::collections::VecDeque::new(),
            capacity: capacity.max(2),
            dropped: 0,
        }
    }

    pub fn push(&mut self, event: LightEvent) {
        self.events.push_back(event);
        if self.events.len() <= self.capacity {
            return;
        }
        let (mut count, mut host_time) = (0, event.host_time());
        while self.events.len() >= self.capacity {
            match self.events.pop_front() {
                Some(LightEvent::Edge(e)) => {
                    count += 1;
                    self.dropped += 1;
                    host_time = e.host_time;
                }
                Some(LightEvent::Lost {
                    count: c,
                    host_time: t,
                }) => {
                    count += c;
                    host_time = t;
                }
                None => break,
            }
        }
        match self.events.front_mut() {
            Some(LightEvent::Lost { count: c, .. }) => *c += count,
            _ => self
                .events
                .push_front(LightEvent::Lost { count, host_time }),
        }
    }

    pub fn pop(&mut self) -> Option<LightEvent> {
        self.events.pop_front()
    }

    pub fn clear(&mut self) {
        self.events.clear();
    }

    pub fn len(&self) -> usize {
        self.events.len()
    }

    pub fn is_empty(&self) -> bool {
        self.events.is_empty()
    }

    /// Edges dropped for lack of room so far.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }
}

/// A light sensor that timestamps the edges of the light it sees (a photodiode and a
/// comparator on a microcontroller or on the sync board).
pub trait Photodiode: Send {
    /// Waits for the next edge (or loss report). Silence is normal while the light does not
    /// change: implementations check their link meanwhile and fail only when it breaks.
    fn next_light(&mut self) -> impl Future<Output = Result<LightEvent, DeviceError>> + Send;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_light_queue_reports_what_it_dropped_in_its_place() {
        let edge = |us: u64, rising| {
            LightEvent::Edge(LightEdge {
                device_time: Timestamp::from_micros(us),
                host_receive_time: Timestamp::from_micros(us),
                host_time: Timestamp::from_micros(us),
                rising,
                level: None,
            })
        };
        let mut q = LightQueue::new(4);
        for k in 0..10 {
            q.push(edge(k, k % 2 == 0));
        }
        // Room for 4: one Lost in front of the newest 3.
        assert_eq!(q.len(), 4);
        assert_eq!(
            q.pop(),
            Some(LightEvent::Lost {
                count: 7,
                host_time: Timestamp::from_micros(6)
            })
        );
        let rest: Vec<u64> = std::iter::from_fn(|| q.pop())
            .map(|e| e.host_time().as_micros())
            .collect();
        assert_eq!(rest, [7, 8, 9]);
        assert_eq!(q.dropped(), 7);
        assert!(q.is_empty());
    }

    #[test]
    fn plane_schedule_validation() {
        let ms = Duration::from_millis;
        let ok = PlaneSchedule::new(vec![Diopters(0.2), Diopters(2.0)], ms(4), ms(2)).unwrap();
        assert_eq!(ok.frame_period(), ms(8));
        assert!(PlaneSchedule::new(vec![], ms(4), ms(1)).is_err());
        assert!(PlaneSchedule::new(vec![Diopters(1.0); 17], ms(4), ms(1)).is_err());
        assert!(PlaneSchedule::new(vec![Diopters(f32::NAN)], ms(4), ms(1)).is_err());
        assert!(PlaneSchedule::new(vec![Diopters(1.0)], ms(0), ms(0)).is_err());
        let e = PlaneSchedule::new(vec![Diopters(1.0)], ms(4), ms(4)).unwrap_err();
        assert!(e.to_string().contains("settle allowance"));
    }
}
