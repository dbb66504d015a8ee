//! What the device tasks and the loop tell each other: a device's input to the loop
//! ([`DeviceInput`]) and a lens command for a lens task ([`LensOrder`]).

use std::time::{Duration, Instant};

use dioptra_core::{Diopters, GazeSample, LensState, LightEvent, SequencerEvent, Timestamp};
pub use dioptra_sched::LensId;

/// A lens command for the lens task: the scheduler's command id, the power, and when the gaze
/// sample that caused it was received (wall clock), for the host-path figure.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensOrder {
    pub id: u64,
    pub power: Diopters,
    pub caused_by_gaze: Option<Instant>,
}

/// What a device task tells the loop. A lens's inputs name it ([`LensId`]: the one lens,
/// or the left eye's, is 0).
#[derive(Debug, Clone, PartialEq)]
pub enum DeviceInput {
    /// A gaze sample, and when the gaze task received it from the driver (wall clock).
    Gaze(GazeSample, Instant),
    LensState(LensId, LensState),
    /// Lens command `id` (for `requested`) went on the wire at `wire_time`. `host_path` is
    /// the wall time from the gaze task receiving the sample that caused it to the driver
    /// having written it.
    LensWire {
        lens: LensId,
        id: u64,
        requested: Diopters,
        wire_time: Timestamp,
        host_path: Option<Duration>,
    },
    /// The lens link came up (true: connected, and the last commanded power re-sent) or went
    /// down (false).
    LensLink(LensId, bool),
    Sync(SequencerEvent),
    /// Light on the photodiode over the marker patch (from its own device, or from the sync
    /// board's input).
    Light(LightEvent),
}
