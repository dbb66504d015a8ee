//! dioptra-sched: the sans-IO scheduler that couples the viewer's gaze to focus and paces
//! frames and multifocal layers, plus the gaze signal processing it is built on. It depends on
//! dioptra-core only: no device library, no I/O, no clock.
//!
//! # The event → command contract
//!
//! ```text
//! let mut sched = Scheduler::new(SchedulerConfig::new(Mode::Varifocal))?;
//! let mut out = Vec::new();
//! loop {
//!     let (now, event) = /* the next thing that happened, with the host time it happened */;
//!     out.clear();
//!     sched.step(now, event, &mut out);
//!     for cmd in &out { /* carry it out */ }
//!     // With nothing else to wait for, wake at sched.next_wakeup() and step Event::Tick.
//! }
//! ```
//!
//! - **Time is passed in.** `step(now, event, out)` never reads a clock; `now` is the host
//!   time (one timeline, ns) the event happened or was received. The same events at the same
//!   times give the same commands, so loop tests run on a simulated clock.
//! - **Events** ([`Event`]): gaze samples (core's `GazeSample`: device, receive and mapped
//!   host times); lens readbacks and "command on the wire" reports; lens link lost/back; the
//!   depth map of the frame being rendered (an `Arc<DepthMap>`, diopters, spanning the eye
//!   model's field); sync-hardware events (core's `SequencerEvent`); render finished (frame,
//!   method, render time); manual focus, mode and method changes; vsync; tick; shutdown.
//! - **Commands** ([`Command`], appended to `out` in the order to carry them out): set the lens
//!   power (with the time the model assumes it applies, and an id to report the wire time
//!   against); render a frame ([`FrameRequest`]: in varifocal mode its focus is the lens power
//!   predicted at the frame's display time, so rendered blur matches optical focus); present a
//!   frame at a vsync, or layer i of a frame in multifocal sub-frame i (sent at sub-frame
//!   i - 1's event, so it is on the panel when sub-frame i starts); stop the sequencer.
//!   Both enums are `#[non_exhaustive]`: match them with a `_` arm.
//! - **One render in flight.** A frame slot whose time comes while the renderer is busy is
//!   skipped. At each vsync (multifocal: the last sub-frame event of the cycle before) the
//!   newest frame finished by then is shown; showing the same frame again is a *miss*.
//! - **Accessors**: [`Scheduler::status`] (mode, eye phase, focus, link, counters),
//!   [`Scheduler::latency`] (an HdrHistogram per [`Stage`], µs),
//!   [`Scheduler::predicted_lens_power`], [`Scheduler::next_wakeup`].
//!
//! # Varifocal focus
//!
//! Gaze samples go through [`processing::GazeProcessor`] (validity, blinks, saccades,
//! smoothing, vergence). At fixation onset the fixation depth is read from the depth map in a
//! small window at the gaze point ([`depth`]: surfaces as histogram modes, picked with
//! vergence) and, when outside the deadband of the commanded power, sent at once. During a
//! fixation a changed depth must hold for a confirm time and commands are spaced by a minimum
//! interval, so noise is not chased. Blinks and tracking loss hold focus. A decelerating
//! saccade commands the depth at its predicted landing point, so the lens moves while vision
//! is suppressed. The lens is modelled by its step response ([`lens::LensPredictor`]).
//!
//! Also here: [`lenslet::elemental_images`], the panel image of a lenslet light-field display.

pub mod config;
pub mod depth;
pub mod latency;
pub mod lens;
pub mod lenslet;
pub mod processing;
mod scheduler;

pub use config::{
    ConfigError, DisplayTiming, FocusPolicy, Mode, RenderMethod, RightLens, SchedulerConfig,
};
pub use latency::{Latency, Stage};
pub use lens::{LensDynamics, LensPredictor};
pub use scheduler::{
    Command, CommandId, Counters, Event, FocusReason, FrameId, FrameRequest, LensId, LensStatus,
    LinkStatus, RestoreError, Scheduler, Status, MAX_LENSES,
};

#[cfg(test)]
mod tests;
