//! The scheduler: events in, commands out. See the crate documentation for the contract.

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{DepthMap, Diopters, GazeSample, LensState, SequencerEvent, Timestamp};

use crate::config::{ConfigError, Mode, RenderMethod, SchedulerConfig};
use crate::depth::fixation_depth;
use crate::latency::{Latency, Stage};
use crate::lens::LensPredictor;
use crate::processing::{Angles, EyePhase, GazeProcessor, GazeState};

/// A frame's number. Whole-frame modes count display slots from 0; in multifocal mode it is
/// the sync hardware's frame number.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    Default,
    serde::Serialize,
    serde::Deserialize,
)]
pub struct FrameId(pub u64);

/// Names one lens command, so the executor can report when it went on the wire.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    Default,
    serde::Serialize,
    serde::Deserialize,
)]
pub struct CommandId(pub u64);

/// Which lens: 0 is the rig's only lens (or the left eye's), 1 the right eye's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct LensId(pub u8);

impl LensId {
    /// The only lens of a one-lens rig; the left eye's on a binocular one.
    pub const FIRST: LensId = LensId(0);
    pub fn index(self) -> usize {
        usize::from(self.0)
    }
}

/// Whether the lens's link is up, as the executor last reported.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub enum LinkStatus {
    #[default]
    Connected,
    Lost,
}

/// Why the lens was commanded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FocusReason {
    /// The first sample of a fixation (after a saccade, a blink, or at start).
    FixationOnset,
    /// The depth under a continuing fixation or pursuit changed, and stayed changed.
    Fixation,
    /// The depth at a decelerating saccade's predicted landing point.
    SaccadeLanding,
    /// A manual focus from the operator.
    Manual,
    /// The lens came back after its link was lost: the current target again.
    Reconnect,
    /// Shutdown: the configured park power.
    Park,
    /// Multifocal mode, which gaze does not drive the varifocal lens in: held at the park
    /// power until something commands it (else it sits wherever it relaxed, perhaps outside
    /// the rig's range).
    MultifocalHold,
}

/// What the executor reports to the scheduler. `now` (passed beside it) is when it happened.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Event {
    /// A binocular gaze sample, with its device, receive and mapped host times.
    Gaze(GazeSample),
    /// A readback of a lens; re-anchors its model and completes settle timing.
    LensState(LensId, LensState),
    /// Command `id` to `lens` went on the wire at `wire_time` (what
    /// `VarifocalLens::set_power` returns).
    LensCommandWritten {
        lens: LensId,
        id: CommandId,
        wire_time: Timestamp,
    },
    /// A lens's link went down or came back (after the driver reopened it). Each lens is held
    /// or commanded on its own: one lost lens does not hold the other.
    LensLink(LensId, LinkStatus),
    /// The depth map (diopters) of the scene frame now being rendered, spanning the eye
    /// model's horizontal field. Fixation depth is read from the latest one.
    Depth(Arc<DepthMap>),
    /// The content frame whose depth came last arrived at `arrived` (a stream frame's request,
    /// a file frame's due time) and was ready to render at `ready`. The executor gives it when
    /// it arrives, before the frame that shows it is requested: the next frame requested shows
    /// it (a newer arrival before that request replaces it).
    Content {
        arrived: Timestamp,
        ready: Timestamp,
    },
    /// An event from the multifocal sync hardware.
    Sequencer(SequencerEvent),
    /// The renderer finished `frame`, which took `render_time`.
    RenderFinished {
        frame: FrameId,
        method: RenderMethod,
        render_time: Duration,
    },
    /// Focus at this distance (diopters) regardless of gaze; `None` returns to gaze.
    ManualFocus(Option<Diopters>),
    /// Switches mode (ignored, and counted, when the mode cannot run with this config).
    SetMode(Mode),
    /// Switches render method (ignored, and counted, when it does not suit the mode).
    SetMethod(RenderMethod),
    /// A display vsync at this time: whole-frame modes lock their frame clock to it.
    Vsync(Timestamp),
    /// Nothing happened; lets timers (frame requests, vsyncs) run. See
    /// [`Scheduler::next_wakeup`].
    Tick,
    /// Stop: park the lens (and stop the sequencer in multifocal mode); no more frames.
    Shutdown,
}

/// A frame for the renderer to make.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameRequest {
    pub frame: FrameId,
    pub mode: Mode,
    pub method: RenderMethod,
    /// Varifocal: the focus to render defocus for, diopters: the lens power predicted at
    /// `display_time`, through the focus map (the first lens's: the only one, or the left
    /// eye's). `None` in other modes.
    pub focus: Option<Diopters>,
    /// Varifocal: the lens power predicted at `display_time`.
    pub lens_power: Option<Diopters>,
    /// Varifocal with a lens per eye: the right eye's focus, from its own lens.
    pub focus_right: Option<Diopters>,
    /// When the frame's light reaches the eye (first sub-frame in multifocal mode).
    pub display_time: Timestamp,
    /// Latest smoothed gaze (for foveation), and the host time of its sample.
    pub gaze: Option<Angles>,
    pub gaze_time: Option<Timestamp>,
}

/// What the scheduler asks the executor to do, in order.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum Command {
    /// Drive the lens to `power`. The scheduler's model assumes it takes effect at
    /// `apply_at` (`now` + the configured command latency): a driver that can schedule
    /// (`LensController::set_power_at`) may apply it exactly then; others send it at once.
    /// Report the wire time with [`Event::LensCommandWritten`].
    SetLensPower {
        lens: LensId,
        id: CommandId,
        power: Diopters,
        apply_at: Timestamp,
        reason: FocusReason,
    },
    /// Render a frame; report [`Event::RenderFinished`] when done. One is in flight at most.
    RenderFrame(FrameRequest),
    /// Whole-frame modes: show `frame` from the vsync at `vsync`. `repeat` when it is the
    /// frame already on screen (a deadline miss).
    Present {
        frame: FrameId,
        vsync: Timestamp,
        display_time: Timestamp,
        repeat: bool,
    },
    /// Multifocal: show layer `layer` of `frame` in the sub-frame that starts at `start`
    /// (sync-hardware frame `sync_frame`). Sent one sub-frame ahead, at the previous
    /// sub-frame's event, so the layer is on the panel when its sub-frame starts. `repeat`
    /// when `frame` was shown in the previous cycle too (its successor missed its deadline).
    PresentLayer {
        frame: FrameId,
        layer: u8,
        sync_frame: u32,
        start: Timestamp,
        repeat: bool,
    },
    /// Stop the sync hardware's sequence (before parking the lens on shutdown).
    StopSequencer,
}

/// Running totals.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub struct Counters {
    pub gaze_samples: u64,
    pub saccades: u64,
    pub blinks: u64,
    pub lens_commands: u64,
    /// Focus changes not sent because the lens link was down (the latest is sent on reconnect).
    pub lens_commands_held: u64,
    pub lens_readbacks: u64,
    pub lens_link_losses: u64,
    pub frames_requested: u64,
    pub frames_rendered: u64,
    /// Vsyncs (whole-frame) or plane cycles (multifocal) that showed a frame.
    pub frames_presented: u64,
    /// Presentations that showed the previous frame again because the next was not ready.
    pub misses: u64,
    /// New frames shown later than the slot they were rendered for.
    pub late_frames: u64,
    /// Frame slots not requested because the renderer was still busy.
    pub renders_skipped: u64,
    pub sequencer_faults: u64,
    /// Events that could not be applied (unknown frame, unsuitable method or mode).
    pub ignored_events: u64,
}

/// What the scheduler is doing now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Status {
    pub mode: Mode,
    pub method: RenderMethod,
    pub phase: EyePhase,
    /// Latest smoothed gaze.
    pub gaze: Option<Angles>,
    /// Fused vergence depth, diopters.
    pub vergence_d: Option<f64>,
    pub manual_focus: Option<Diopters>,
    /// Depth at the gaze point the last time it was read, diopters.
    pub fixation_depth: Option<Diopters>,
    /// The first lens's power last commanded (or held while its link is down).
    pub commanded_power: Option<Diopters>,
    /// The first lens's link.
    pub lens_link: LinkStatus,
    /// Last command's time from the wire to a settled readback (any lens).
    pub last_settle: Option<Duration>,
    pub shown_frame: Option<FrameId>,
    pub shutting_down: bool,
    pub counters: Counters,
    /// Each lens (index: [`LensId`]); `None` beyond the rig's lenses.
    pub lenses: [Option<LensStatus>; MAX_LENSES],
}

/// The most lenses a rig has: one per eye.
pub const MAX_LENSES: usize = 2;

/// One lens as the scheduler sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensStatus {
    /// The power last commanded (or held while its link is down).
    pub commanded_power: Option<Diopters>,
    pub link: LinkStatus,
    /// Its last command's time from the wire to a settled readback.
    pub last_settle: Option<Duration>,
}

/// One lens's link, model and command in flight.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
struct LensTrack {
    model: LensPredictor,
    link: LinkStatus,
    /// The power last commanded (or held while the link is down).
    commanded: Option<Diopters>,
    tracked: Option<Tracked>,
    last_settle: Option<Duration>,
}

/// The command whose latency is being followed.
#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
struct Tracked {
    id: CommandId,
    power: Diopters,
    sent_at: Timestamp,
    /// (host receive, mapped device time) of the gaze sample that caused it.
    trigger: Option<(Timestamp, Timestamp)>,
    wire: Option<Timestamp>,
    settled: bool,
}

#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
struct InFlight {
    frame: FrameId,
    gaze_time: Option<Timestamp>,
    /// Arrival of the content frame it shows first.
    content_time: Option<Timestamp>,
}

#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
struct Ready {
    frame: FrameId,
    at: Timestamp,
    gaze_time: Option<Timestamp>,
    content_time: Option<Timestamp>,
}

/// Finished frames remembered (newest last); the newest ready by a deadline is shown.
const READY_KEPT: usize = 4;

/// Whole-frame display clock: slot k's vsync is `base + (k - base_slot) * period`.
#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
struct FrameClock {
    base: Timestamp,
    base_slot: u64,
    next_request: u64,
    next_vsync: u64,
}

/// Why [`Scheduler::restore`] failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RestoreError {
    #[error("{0}")]
    Config(ConfigError),
    #[error("the scheduler state does not fit this version of the scheduler: {0}")]
    State(String),
}

/// The sans-IO scheduler. See the crate documentation.
///
/// Its state is data (serde): [`Scheduler::state`] and [`Scheduler::restore`] carry it into a
/// recording started mid-run, so a replay starts where the run was. Not in it: the config
/// (the rig config makes it again; mode and method are given to `restore`), the depth map (the
/// content gives it again) and the latency statistics (they start afresh).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Scheduler {
    #[serde(skip, default = "placeholder_config")]
    cfg: SchedulerConfig,
    processor: GazeProcessor,
    /// Each lens, by [`LensId`].
    lenses: Vec<LensTrack>,
    #[serde(skip, default = "fresh_latency")]
    latency: Latency,
    #[serde(skip)]
    depth: Option<Arc<DepthMap>>,
    /// Arrival of a content frame that no requested frame shows yet.
    content_new: Option<Timestamp>,
    counters: Counters,
    prev_phase: EyePhase,
    /// Treat the next fixation sample as an onset (after manual focus or a mode change).
    reevaluate: bool,
    manual: Option<Diopters>,
    /// The first lens's power last decided (what focus decisions compare against; every lens
    /// is commanded the same focus through its own map).
    commanded: Option<Diopters>,
    last_command_at: Option<Timestamp>,
    /// A fixation target outside the deadband, and since when.
    pending: Option<(Timestamp, Diopters)>,
    landing_sent: bool,
    /// Where the current (or last) saccade started.
    saccade_from: Option<Angles>,
    next_command_id: u64,
    last_settle: Option<Duration>,
    fixation_depth: Option<Diopters>,
    last_gaze: Option<(Timestamp, Angles)>,
    clock: Option<FrameClock>,
    in_flight: Option<InFlight>,
    ready: Vec<Ready>,
    shown: Option<FrameId>,
    /// Multifocal: the frame shown in the current plane cycle, and whether it is a repeat.
    cycle: Option<(FrameId, bool)>,
    shutting_down: bool,
}

/// How far ahead the landing point is predicted (the processor clamps to its own maximum).
const LANDING_HORIZON: Duration = Duration::from_millis(100);
/// A saccade this young may still be a noise spike: no landing prediction yet.
const MIN_SACCADE_FOR_LANDING: Duration = Duration::from_millis(6);
/// A saccade whose speed fell below this share of its peak is decelerating.
const DECELERATING: f64 = 0.8;

fn since(later: Timestamp, earlier: Timestamp) -> Duration {
    later.saturating_since(earlier)
}

/// Replaced by [`Scheduler::restore`] before a restored scheduler is used.
fn placeholder_config() -> SchedulerConfig {
    SchedulerConfig::new(Mode::Varifocal)
}

fn fresh_latency() -> Latency {
    // The histograms' bounds are constants that Latency::new's tests create.
    Latency::new().expect("the latency histograms' constant bounds")
}

impl Scheduler {
    /// The scheduler's state without its config, depth map and latency statistics: give it to
    /// [`Scheduler::restore`] (through any serde format that keeps `f64`s exact).
    pub fn state(&self) -> &impl serde::Serialize {
        self
    }

    /// The scheduler whose [`Scheduler::state`] was `state`, running `cfg` with the `mode`
    /// and `method` it had then (the API may have changed them since start) and the `depth`
    /// map it had (the content's frame then).
    pub fn restore<'de, D: serde::Deserializer<'de>>(
        cfg: SchedulerConfig,
        mode: Mode,
        method: RenderMethod,
        depth: Option<Arc<DepthMap>>,
        state: D,
    ) -> Result<Self, RestoreError> {
        cfg.validate().map_err(RestoreError::Config)?;
        let mut s: Scheduler = serde::Deserialize::deserialize(state)
            .map_err(|e: D::Error| RestoreError::State(e.to_string()))?;
        s.cfg = SchedulerConfig {
            mode,
            method,
            ..cfg
        };
        s.depth = depth;
        s.cfg.validate().map_err(RestoreError::Config)?;
        Ok(s)
    }

    /// A scheduler for `cfg`; the error names the bad setting.
    pub fn new(cfg: SchedulerConfig) -> Result<Self, ConfigError> {
        cfg.validate()?;
        let latency = Latency::new().map_err(|e| ConfigError::Histogram(e.to_string()))?;
        Ok(Scheduler {
            processor: GazeProcessor::new(cfg.gaze),
            lenses: (0..cfg.lens_count())
                .map(|i| LensTrack {
                    model: LensPredictor::new(cfg.dynamics_of(LensId(i as u8))),
                    link: LinkStatus::Connected,
                    commanded: None,
                    tracked: None,
                    last_settle: None,
                })
                .collect(),
            latency,
            depth: None,
            content_new: None,
            counters: Counters::default(),
            prev_phase: EyePhase::Unknown,
            reevaluate: false,
            manual: None,
            commanded: None,
            last_command_at: None,
            pending: None,
            landing_sent: false,
            saccade_from: None,
            next_command_id: 0,
            last_settle: None,
            fixation_depth: None,
            last_gaze: None,
            clock: None,
            in_flight: None,
            ready: Vec::with_capacity(READY_KEPT + 1),
            shown: None,
            cycle: None,
            shutting_down: false,
            cfg,
        })
    }

    pub fn config(&self) -> &SchedulerConfig {
        &self.cfg
    }

    /// Handles `event`, which happened at `now`, and appends the resulting commands to `out`
    /// (it does not clear `out`; reuse one buffer to avoid allocating). Timers due by `now`
    /// (frame requests, vsyncs) run after the event. `now` should not go backwards; an
    /// earlier `now` is treated as a late report, never as time travel.
    pub fn step(&mut self, now: Timestamp, event: Event, out: &mut Vec<Command>) {
        match event {
            Event::Gaze(s) => self.on_gaze(now, &s, out),
            Event::LensState(lens, s) => {
                self.on_lens_state(lens, &s);
                if self.cfg.mode == Mode::Multifocal
                    && self.commanded.is_none()
                    && !self.shutting_down
                {
                    let park = self.cfg.park_power;
                    self.command(now, park, FocusReason::MultifocalHold, None, out);
                }
            }
            Event::LensCommandWritten {
                lens,
                id,
                wire_time,
            } => self.on_written(lens, id, wire_time),
            Event::LensLink(lens, l) => self.on_link(now, lens, l, out),
            Event::Depth(d) => self.depth = Some(d),
            Event::Content { arrived, ready } => self.on_content(arrived, ready),
            Event::Sequencer(e) => self.on_sequencer(now, &e, out),
            Event::RenderFinished {
                frame,
                method,
                render_time,
            } => self.on_render_finished(now, frame, method, render_time),
            Event::ManualFocus(f) => self.on_manual(now, f, out),
            Event::SetMode(m) => self.on_mode(m),
            Event::SetMethod(m) => {
                if m.suits(self.cfg.mode) {
                    self.cfg.method = m;
                } else {
                    self.counters.ignored_events += 1;
                }
            }
            Event::Vsync(t) => self.on_vsync(t),
            Event::Tick => {}
            Event::Shutdown => self.on_shutdown(now, out),
        }
        self.run_frame_clock(now, out);
    }

    /// When the scheduler next has something to do with no event (a frame request or a
    /// vsync): step it with [`Event::Tick`] then. `None` when only events move it (multifocal
    /// mode, shutdown, or before the first step).
    pub fn next_wakeup(&self) -> Option<Timestamp> {
        if self.shutting_down || self.cfg.mode == Mode::Multifocal {
            return None;
        }
        let c = self.clock?;
        let lead = self.cfg.display.render_lead;
        Some(
            self.vsync_time(&c, c.next_request)
                .saturating_sub(lead)
                .min(self.vsync_time(&c, c.next_vsync)),
        )
    }

    pub fn status(&self) -> Status {
        let st = self.processor.state();
        Status {
            mode: self.cfg.mode,
            method: self.cfg.method,
            phase: st.phase,
            gaze: st.smoothed,
            vergence_d: st.vergence.map(|v| v.diopters),
            manual_focus: self.manual,
            fixation_depth: self.fixation_depth,
            commanded_power: self.commanded,
            lens_link: self
                .lenses
                .first()
                .map_or(LinkStatus::Connected, |l| l.link),
            last_settle: self.last_settle,
            shown_frame: self.shown,
            shutting_down: self.shutting_down,
            counters: Counters {
                saccades: st.saccades,
                blinks: st.blinks,
                ..self.counters
            },
            lenses: std::array::from_fn(|i| {
                self.lenses.get(i).map(|l| LensStatus {
                    commanded_power: l.commanded,
                    link: l.link,
                    last_settle: l.last_settle,
                })
            }),
        }
    }

    pub fn latency(&self) -> &Latency {
        &self.latency
    }

    /// The gaze processor's state after the latest sample.
    pub fn gaze(&self) -> &GazeState {
        self.processor.state()
    }

    /// The first lens's power the model predicts at `t` from the commands and readbacks so far.
    pub fn predicted_lens_power(&self, t: Timestamp) -> Option<Diopters> {
        self.predicted_power_of(LensId::FIRST, t)
    }

    /// `lens`'s power its model predicts at `t`.
    pub fn predicted_power_of(&self, lens: LensId, t: Timestamp) -> Option<Diopters> {
        self.lenses.get(lens.index())?.model.power_at(t)
    }

    /// When the model predicts the first lens settles (within the settled tolerance) after
    /// `from`.
    pub fn predicted_settle(&self, from: Timestamp) -> Option<Timestamp> {
        self.lenses
            .first()?
            .model
            .settled_by(from, self.cfg.settled_tolerance_d)
    }

    /// The focus (accommodation demand, diopters) that `power` on `lens` gives the eye: the
    /// one place that turns a lens's power into a focus.
    pub fn focus_of(&self, lens: LensId, power: Diopters) -> Diopters {
        self.cfg.optics_of(lens).focus_of(power)
    }

    /// The power of `lens` for `focus`, inside the lens range: the one place that turns a
    /// focus into a lens command.
    fn power_of(&self, lens: LensId, focus: Diopters) -> Diopters {
        self.cfg
            .lens_range
            .clamp(self.cfg.optics_of(lens).command_for(focus))
    }

    // ---- focus ----

    fn on_gaze(&mut self, now: Timestamp, s: &GazeSample, out: &mut Vec<Command>) {
        self.counters.gaze_samples += 1;
        if s.host_receive_time >= s.host_time {
            self.latency.record(
                Stage::TrackerToHost,
                since(s.host_receive_time, s.host_time),
            );
        }
        let prev = self.prev_phase;
        let before = self.processor.state().smoothed;
        let st = *self.processor.push(s);
        self.prev_phase = st.phase;
        if let Some(a) = st.smoothed {
            self.last_gaze = Some((st.time, a));
        }
        if self.cfg.mode != Mode::Varifocal || self.shutting_down || self.manual.is_some() {
            return;
        }
        match st.phase {
            EyePhase::Saccade => {
                if prev != EyePhase::Saccade {
                    self.landing_sent = false;
                    self.saccade_from = before;
                }
                self.saccade_landing(now, &st, s, out);
            }
            EyePhase::Fixation | EyePhase::Pursuit => {
                // A tiny "saccade" (tracker noise, a microsaccade) does not end the fixation.
                let small = prev == EyePhase::Saccade
                    && matches!((self.saccade_from, st.raw), (Some(a), Some(b))
                        if a.distance_deg(&b) < self.cfg.focus.min_saccade_deg);
                let onset = self.reevaluate
                    || (!matches!(prev, EyePhase::Fixation | EyePhase::Pursuit) && !small)
                    || self.commanded.is_none();
                let gaze = if onset { st.raw } else { st.smoothed };
                let vergence = st.vergence.map(|v| (v.diopters, v.sigma_d));
                let Some(target) = gaze.and_then(|a| self.focus_power(a.direction(), vergence))
                else {
                    return;
                };
                if onset {
                    self.reevaluate = false;
                    self.pending = None;
                    self.command_if_moved(now, target, FocusReason::FixationOnset, Some(s), out);
                } else {
                    self.fixation_update(now, target, s, out);
                }
            }
            EyePhase::Blink | EyePhase::Lost | EyePhase::Unknown => {
                // Hold focus: the eye is shut or unseen, and will most likely reopen on the
                // same thing.
                self.pending = None;
            }
        }
    }

    fn saccade_landing(
        &mut self,
        now: Timestamp,
        st: &GazeState,
        s: &GazeSample,
        out: &mut Vec<Command>,
    ) {
        // Noise spikes look like saccades for a sample or two; a real one between objects
        // lasts 20 ms or more.
        if !self.cfg.focus.predict_landing
            || self.landing_sent
            || since(st.time, st.phase_since) < MIN_SACCADE_FOR_LANDING
        {
            return;
        }
        let Some(peak) = self.processor.saccade_peak_dps() else {
            return;
        };
        if st.speed_dps >= DECELERATING * peak {
            return;
        }
        let travelled = match (self.saccade_from, st.raw) {
            (Some(a), Some(b)) => a.distance_deg(&b),
            _ => 0.0,
        };
        if travelled < self.cfg.focus.min_saccade_deg {
            return;
        }
        let Some(landing) = self.processor.predict(now + LANDING_HORIZON) else {
            return;
        };
        // Vergence is still on the old target mid-saccade: the depth map alone decides.
        if let Some(target) = self.focus_power(landing.direction, None) {
            self.landing_sent = true;
            self.command_if_moved(now, target, FocusReason::SaccadeLanding, Some(s), out);
        }
    }

    /// During a fixation: send a new target only once it has held outside the deadband for
    /// the confirm time, and no more often than the minimum interval.
    fn fixation_update(
        &mut self,
        now: Timestamp,
        target: Diopters,
        s: &GazeSample,
        out: &mut Vec<Command>,
    ) {
        if self
            .commanded
            .is_some_and(|c| self.within_deadband(c, target))
        {
            self.pending = None;
            return;
        }
        match self.pending {
            Some((t0, p)) if self.within_deadband(p, target) => {
                let confirmed = since(now, t0) >= self.cfg.focus.confirm;
                let spaced = self
                    .last_command_at
                    .is_none_or(|t| since(now, t) >= self.cfg.focus.min_interval);
                if confirmed && spaced {
                    self.pending = None;
                    self.command_if_moved(now, target, FocusReason::Fixation, Some(s), out);
                }
            }
            _ => self.pending = Some((now, target)),
        }
    }

    /// The lens power for looking along `direction`: depth map first, vergence without one.
    fn focus_power(
        &mut self,
        direction: [f64; 3],
        vergence: Option<(f64, f64)>,
    ) -> Option<Diopters> {
        let from_map = self.depth.as_ref().and_then(|d| {
            fixation_depth(
                d,
                direction,
                self.cfg.eye.fov_horizontal_deg,
                &self.cfg.focus.window,
                vergence,
            )
        });
        let depth = from_map.or_else(|| {
            vergence
                .filter(|v| v.1 <= self.cfg.focus.vergence_only_max_sigma_d && v.0.is_finite())
                .map(|v| Diopters(v.0.max(0.0) as f32))
        })?;
        self.fixation_depth = Some(depth);
        let power = self.cfg.optics.command_for(depth);
        power.is_finite().then(|| self.cfg.lens_range.clamp(power))
    }

    fn command_if_moved(
        &mut self,
        now: Timestamp,
        power: Diopters,
        reason: FocusReason,
        trigger: Option<&GazeSample>,
        out: &mut Vec<Command>,
    ) {
        if self
            .commanded
            .is_some_and(|c| self.within_deadband(c, power))
        {
            return;
        }
        self.command(now, power, reason, trigger, out);
    }

    /// Whether two lens commands put the image within the deadband of each other: compared
    /// as the focus they give, since the deadband is the eye's depth of field.
    fn within_deadband(&self, a: Diopters, b: Diopters) -> bool {
        let o = &self.cfg.optics;
        (o.focus_of(a).0 - o.focus_of(b).0).abs() <= self.cfg.focus.deadband_d
    }

    /// Commands the first lens's `power` (and every other lens the same focus, through its
    /// own map). A lens whose link is down is held: it gets its power when it comes back.
    fn command(
        &mut self,
        now: Timestamp,
        power: Diopters,
        reason: FocusReason,
        trigger: Option<&GazeSample>,
        out: &mut Vec<Command>,
    ) {
        let power = self.cfg.lens_range.clamp(power);
        if !power.is_finite() {
            return;
        }
        self.commanded = Some(power);
        self.last_command_at = Some(now);
        let focus = self.focus_of(LensId::FIRST, power);
        for i in 0..self.lenses.len() {
            let lens = LensId(i as u8);
            let p = match (i, reason) {
                (0, _) => power,
                // Each lens parks where its own section says.
                (_, FocusReason::Park | FocusReason::MultifocalHold) => {
                    self.cfg.park_power_of(lens)
                }
                _ => self.power_of(lens, focus),
            };
            self.command_lens(now, lens, p, reason, trigger, out);
        }
    }

    /// Sends `power` to one lens (or holds it while the lens's link is down).
    fn command_lens(
        &mut self,
        now: Timestamp,
        lens: LensId,
        power: Diopters,
        reason: FocusReason,
        trigger: Option<&GazeSample>,
        out: &mut Vec<Command>,
    ) {
        if !power.is_finite() {
            return;
        }
        let id = CommandId(self.next_command_id);
        let apply_at = now + self.cfg.dynamics_of(lens).command_latency;
        let Some(l) = self.lenses.get_mut(lens.index()) else {
            return;
        };
        l.commanded = Some(power);
        if l.link == LinkStatus::Lost {
            self.counters.lens_commands_held += 1;
            return;
        }
        self.next_command_id += 1;
        l.model.command(apply_at, power);
        l.tracked = Some(Tracked {
            id,
            power,
            sent_at: now,
            trigger: trigger.map(|s| (s.host_receive_time, s.host_time)),
            wire: None,
            settled: false,
        });
        self.counters.lens_commands += 1;
        out.push(Command::SetLensPower {
            lens,
            id,
            power,
            apply_at,
            reason,
        });
    }

    fn on_written(&mut self, lens: LensId, id: CommandId, wire: Timestamp) {
        let Some(t) = self
            .lenses
            .get_mut(lens.index())
            .and_then(|l| l.tracked.as_mut())
            .filter(|t| t.id == id)
        else {
            return;
        };
        t.wire = Some(wire);
        if let Some((receive, _)) = t.trigger {
            self.latency.record(Stage::HostToWire, since(wire, receive));
        }
    }

    fn on_lens_state(&mut self, lens: LensId, s: &LensState) {
        self.counters.lens_readbacks += 1;
        let readback_tol = self.cfg.readback_tolerance_d;
        let tol = self.cfg.settled_tolerance_d;
        let Some(l) = self.lenses.get_mut(lens.index()) else {
            self.counters.ignored_events += 1;
            return;
        };
        l.model.observe(s.host_time, s.power, readback_tol);
        let Some(t) = l.tracked.as_mut() else {
            return;
        };
        let start = t.wire.unwrap_or(t.sent_at);
        if t.settled || s.host_time < start {
            return;
        }
        if s.settled.unwrap_or(true) && (s.power.0 - t.power.0).abs() <= tol {
            t.settled = true;
            let d = since(s.host_time, start);
            l.last_settle = Some(d);
            self.last_settle = Some(d);
            self.latency.record(Stage::WireToSettled, d);
            if let Some((_, gaze)) = t.trigger {
                self.latency
                    .record(Stage::GazeToSettled, since(s.host_time, gaze));
            }
        }
    }

    fn on_link(
        &mut self,
        now: Timestamp,
        lens: LensId,
        status: LinkStatus,
        out: &mut Vec<Command>,
    ) {
        let Some(l) = self.lenses.get_mut(lens.index()) else {
            self.counters.ignored_events += 1;
            return;
        };
        match (l.link, status) {
            (LinkStatus::Connected, LinkStatus::Lost) => {
                l.link = LinkStatus::Lost;
                self.counters.lens_link_losses += 1;
                // Where the lens is after a reconnect is unknown until it is read back.
                l.model.forget();
                l.tracked = None;
            }
            (LinkStatus::Lost, LinkStatus::Connected) => {
                l.link = LinkStatus::Connected;
                let held = l.commanded;
                let target = if self.shutting_down {
                    Some(self.cfg.park_power_of(lens))
                } else {
                    held
                };
                if let Some(p) = target {
                    self.command_lens(now, lens, p, FocusReason::Reconnect, None, out);
                }
            }
            _ => {}
        }
    }

    fn on_manual(&mut self, now: Timestamp, focus: Option<Diopters>, out: &mut Vec<Command>) {
        match focus {
            Some(f) if f.is_finite() && !self.shutting_down => {
                self.manual = Some(f);
                self.pending = None;
                self.fixation_depth = Some(f);
                let p = self.cfg.optics.command_for(f);
                if p.is_finite() {
                    self.command(now, p, FocusReason::Manual, None, out);
                }
            }
            None => {
                self.manual = None;
                self.reevaluate = true;
            }
            Some(_) => self.counters.ignored_events += 1,
        }
    }

    fn on_mode(&mut self, m: Mode) {
        if m == self.cfg.mode {
            return;
        }
        if m == Mode::Multifocal && self.cfg.planes.is_none() {
            self.counters.ignored_events += 1;
            return;
        }
        self.cfg.mode = m;
        if !self.cfg.method.suits(m) {
            self.cfg.method = RenderMethod::default_for(m);
        }
        self.clock = None;
        self.in_flight = None;
        self.ready.clear();
        self.shown = None;
        self.cycle = None;
        self.reevaluate = true;
    }

    fn on_shutdown(&mut self, now: Timestamp, out: &mut Vec<Command>) {
        if self.shutting_down {
            return;
        }
        self.shutting_down = true;
        self.pending = None;
        if self.cfg.mode == Mode::Multifocal {
            out.push(Command::StopSequencer);
        }
        self.command(now, self.cfg.park_power, FocusReason::Park, None, out);
    }

    // ---- frames ----

    fn request(&mut self, frame: FrameId, display_time: Timestamp, out: &mut Vec<Command>) {
        // Each eye's image is rendered at the focus its own lens is predicted to give.
        let focus_at = |lens: LensId| {
            let l = self.lenses.get(lens.index())?;
            let p = l
                .model
                .power_at(display_time)
                .or(l.commanded)
                .unwrap_or(self.cfg.park_power_of(lens));
            Some((self.focus_of(lens, p), p))
        };
        let (first, right) = if self.cfg.mode == Mode::Varifocal {
            (focus_at(LensId::FIRST), focus_at(LensId(1)))
        } else {
            (None, None)
        };
        let (focus, lens_power) = first.unzip();
        let focus_right = right.map(|r| r.0);
        let gaze_time = self.last_gaze.map(|g| g.0);
        self.in_flight = Some(InFlight {
            frame,
            gaze_time,
            content_time: self.content_new.take(),
        });
        self.counters.frames_requested += 1;
        out.push(Command::RenderFrame(FrameRequest {
            frame,
            mode: self.cfg.mode,
            method: self.cfg.method,
            focus,
            lens_power,
            focus_right,
            display_time,
            gaze: self.last_gaze.map(|g| g.1),
            gaze_time,
        }));
    }

    fn on_content(&mut self, arrived: Timestamp, ready: Timestamp) {
        if ready >= arrived {
            self.latency
                .record(Stage::ContentReceived, since(ready, arrived));
        }
        // Given before the request of the frame that shows it. A newer arrival replaces an
        // older one that no frame showed.
        self.content_new = Some(arrived);
    }

    fn on_render_finished(
        &mut self,
        now: Timestamp,
        frame: FrameId,
        method: RenderMethod,
        render_time: Duration,
    ) {
        let Some(f) = self.in_flight.filter(|f| f.frame == frame) else {
            self.counters.ignored_events += 1;
            return;
        };
        self.in_flight = None;
        self.counters.frames_rendered += 1;
        self.latency.record_render(method, render_time);
        if self.ready.len() == READY_KEPT {
            self.ready.remove(0);
        }
        self.ready.push(Ready {
            frame,
            at: now,
            gaze_time: f.gaze_time,
            content_time: f.content_time,
        });
    }

    /// The newest frame finished by `deadline`.
    fn ready_by(&self, deadline: Timestamp) -> Option<Ready> {
        self.ready.iter().rev().find(|r| r.at <= deadline).copied()
    }

    /// Decides what to show from `deadline` on; returns (frame, repeat).
    fn choose_frame(
        &mut self,
        deadline: Timestamp,
        slot: FrameId,
        display_time: Timestamp,
    ) -> Option<(FrameId, bool)> {
        let r = self.ready_by(deadline)?;
        let repeat = self.shown == Some(r.frame);
        self.counters.frames_presented += 1;
        if repeat {
            self.counters.misses += 1;
        } else {
            if r.frame != slot {
                self.counters.late_frames += 1;
            }
            if let Some(g) = r.gaze_time {
                self.latency
                    .record(Stage::GazeToDisplay, since(display_time, g));
            }
            // Content first shown now: this frame's, or that of an older frame it overtook.
            let first = self
                .ready
                .iter_mut()
                .filter(|f| f.frame.0 <= r.frame.0)
                .filter_map(|f| f.content_time.take())
                .min();
            if let Some(c) = first {
                self.latency
                    .record(Stage::ContentToPresented, since(display_time, c));
            }
        }
        self.shown = Some(r.frame);
        Some((r.frame, repeat))
    }

    fn vsync_time(&self, c: &FrameClock, slot: u64) -> Timestamp {
        let p = self.cfg.display.frame_period;
        if slot >= c.base_slot {
            c.base + p.saturating_mul((slot - c.base_slot).min(u64::from(u32::MAX)) as u32)
        } else {
            c.base.saturating_sub(
                p.saturating_mul((c.base_slot - slot).min(u64::from(u32::MAX)) as u32),
            )
        }
    }

    fn on_vsync(&mut self, t: Timestamp) {
        if self.cfg.mode == Mode::Multifocal {
            return;
        }
        let Some(mut c) = self.clock else {
            // The first vsync is slot 1's, so slot 0 can be requested a lead before it.
            self.clock = Some(FrameClock {
                base: t,
                base_slot: 0,
                next_request: 0,
                next_vsync: 0,
            });
            return;
        };
        // Lock the slot nearest `t` to it.
        let p = self.cfg.display.frame_period.as_nanos().max(1) as i128;
        let off = t.signed_diff_ns(self.vsync_time(&c, c.next_vsync)) as i128;
        let k = c.next_vsync as i128 + (off + p / 2).div_euclid(p);
        c.base = t;
        c.base_slot = k.max(0) as u64;
        self.clock = Some(c);
    }

    fn run_frame_clock(&mut self, now: Timestamp, out: &mut Vec<Command>) {
        if self.shutting_down || self.cfg.mode == Mode::Multifocal {
            return;
        }
        let lead = self.cfg.display.render_lead;
        let period = self.cfg.display.frame_period;
        let mut c = *self.clock.get_or_insert(FrameClock {
            base: now + lead,
            base_slot: 0,
            next_request: 0,
            next_vsync: 0,
        });
        // After a long stall, skip ahead instead of replaying every missed slot.
        let behind = since(now, self.vsync_time(&c, c.next_vsync));
        if behind > period.saturating_mul(4) {
            let skip = (behind.as_nanos() / period.as_nanos().max(1)) as u64;
            c.next_vsync += skip;
            c.next_request = c.next_request.max(c.next_vsync);
            self.counters.renders_skipped += skip;
        }
        loop {
            let req_t = self.vsync_time(&c, c.next_request).saturating_sub(lead);
            let vs_t = self.vsync_time(&c, c.next_vsync);
            if req_t <= now && req_t <= vs_t && c.next_request >= c.next_vsync {
                let slot = c.next_request;
                c.next_request += 1;
                if self.in_flight.is_none() {
                    let display = self.vsync_time(&c, slot) + self.cfg.display.latency;
                    self.request(FrameId(slot), display, out);
                } else {
                    self.counters.renders_skipped += 1;
                }
            } else if vs_t <= now {
                let slot = c.next_vsync;
                c.next_vsync += 1;
                c.next_request = c.next_request.max(c.next_vsync);
                let display = vs_t + self.cfg.display.latency;
                if let Some((frame, repeat)) = self.choose_frame(vs_t, FrameId(slot), display) {
                    out.push(Command::Present {
                        frame,
                        vsync: vs_t,
                        display_time: display,
                        repeat,
                    });
                }
            } else {
                break;
            }
        }
        self.clock = Some(c);
    }

    fn on_sequencer(&mut self, _now: Timestamp, e: &SequencerEvent, out: &mut Vec<Command>) {
        let (frame, plane, start) = match *e {
            SequencerEvent::Fault { .. } => {
                self.counters.sequencer_faults += 1;
                return;
            }
            SequencerEvent::SubframeStart {
                frame,
                plane_index,
                host_time,
                ..
            } => (frame, plane_index, host_time),
        };
        if self.cfg.mode != Mode::Multifocal || self.shutting_down {
            return;
        }
        // Each event readies the *next* sub-frame: a layer must be on the panel before its
        // sub-frame starts, so waiting for that sub-frame's own event would show it late. The
        // next cycle's frame is therefore chosen at the last sub-frame's event.
        let Some(schedule) = self.cfg.planes.as_ref() else {
            return;
        };
        let (n, sub, period) = (
            schedule.planes().len(),
            schedule.subframe_period(),
            schedule.frame_period(),
        );
        if usize::from(plane) >= n {
            // Not a plane of this schedule: a confused board; show nothing for it.
            self.counters.ignored_events += 1;
            return;
        }
        let next_plane = (usize::from(plane) + 1) % n;
        let next_frame = if next_plane == 0 {
            frame.wrapping_add(1)
        } else {
            frame
        };
        let next_start = start + sub;
        if next_plane == 0 {
            let slot = FrameId(u64::from(next_frame));
            self.cycle = self.choose_frame(start, slot, next_start);
            // Layers for the cycle after, unless the renderer is still busy.
            if self.in_flight.is_none() {
                self.request(FrameId(slot.0 + 1), next_start + period, out);
            } else {
                self.counters.renders_skipped += 1;
            }
        }
        if let Some((f, repeat)) = self.cycle {
            out.push(Command::PresentLayer {
                frame: f,
                layer: next_plane as u8,
                sync_frame: next_frame,
                start: next_start,
                repeat,
            });
        }
    }
}
