//! What watches the loop: the recording, the status `/status` shows, the WebSocket's messages,
//! the Lab Streaming Layer outlets and a simulated panel's marker patch, each a [`LoopHook`] the loop calls as it goes. The
//! loop itself ([`crate::executor`]) only steps the scheduler and carries out its commands.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{lock, Timestamp};
use serde_json::json;

use crate::content::ContentFrame;
use crate::devices::DeviceInput;
use crate::devices::LensId;
use crate::display::pacing::{Notice, Pacing};
use crate::display::DisplaySink;
use crate::engine::{self, Command, Control, Engine};
use crate::executor::{LoopHook, Presented, RenderReport};
use crate::mode::{Method, Mode};
use crate::recording::{
    ContentRec, DepthRec, FrameRec, LensCommandRec, LensLinkRec, LensStateRec, LensWireRec, Marker,
    PresentRec, Rec, RenderRec,
};
use crate::render::RenderErrorNote;
use crate::state::{lens_settled, RigState, SUBFRAME_TOLERANCE_D};
use dioptra_core::Side;

/// The observers every rig has, in the order the loop calls them.
pub(crate) fn standard(state: &Arc<RigState>) -> Vec<Box<dyn LoopHook>> {
    let mut hooks: Vec<Box<dyn LoopHook>> = vec![
        Box::new(Recording(state.clone())),
        Box::new(Status {
            state: state.clone(),
            error_log: HashMap::new(),
            scheduler_at: None,
            scheduler_due: false,
        }),
        Box::new(WebSocket(state.clone())),
        Box::new(Lateness::new(state.clone())),
    ];
    hooks.push(Box::new(DebugLog {
        state: state.clone(),
        late_frames: 0,
        misses: 0,
    }));
    if state.lsl.is_some() {
        hooks.push(Box::new(Lsl {
            state: state.clone(),
            commanded: [None; 2],
        }));
    }
    hooks
}

/// The loop's and the scheduler's events at debug level (`RUST_LOG=debug`, or
/// `RUST_LOG=dioptra_rig::scheduler=debug` / `dioptra_rig::loop=debug` for one of them): the
/// scheduler's lens commands, render requests and late frames; the lenses' read-backs and
/// links, content arrivals and renders as the loop sees them.
struct DebugLog {
    state: Arc<RigState>,
    /// The scheduler's counts of late frames and misses at the last step.
    late_frames: u64,
    misses: u64,
}

impl DebugLog {
    /// How log lines name lens `lens`: `right lens`, or `lens` on a rig with one.
    fn lens(&self, lens: LensId) -> String {
        match self.state.cfg.devices.lens.side(lens.index()) {
            Some(side) => format!("{} lens", side.as_str()),
            None => "lens".into(),
        }
    }
}

impl LoopHook for DebugLog {
    fn command(&mut self, _now: Timestamp, cmd: &Command) {
        match cmd {
            Command::SetLensPower {
                lens,
                power,
                reason,
                ..
            } => tracing::debug!(
                target: "dioptra_rig::scheduler",
                "{}: command {:.3} D ({reason:?})",
                self.lens(*lens),
                power.0
            ),
            Command::RenderFrame(r) => tracing::debug!(
                target: "dioptra_rig::scheduler",
                "render frame {} ({:?}, {:?}{})",
                r.frame.0,
                r.mode,
                r.method,
                r.focus.map_or(String::new(), |f| format!(", focus {:.3} D", f.0))
            ),
            _ => {}
        }
    }
    fn input(&mut self, _now: Timestamp, input: &DeviceInput, _engine: &Engine) {
        match input {
            DeviceInput::LensState(lens, s) => tracing::debug!(
                target: "dioptra_rig::loop",
                "{}: read back {:.3} D{}",
                self.lens(*lens),
                s.power.0,
                match s.settled {
                    Some(true) => ", settled",
                    Some(false) => ", moving",
                    None => "",
                }
            ),
            DeviceInput::LensWire {
                lens, requested, ..
            } => tracing::debug!(
                target: "dioptra_rig::loop",
                "{}: {:.3} D on the wire",
                self.lens(*lens),
                requested.0
            ),
            DeviceInput::LensLink(lens, up) => tracing::debug!(
                target: "dioptra_rig::loop",
                "{}: link {}",
                self.lens(*lens),
                if *up { "up" } else { "down" }
            ),
            _ => {}
        }
    }
    fn content(&mut self, _now: Timestamp, frame: &ContentFrame) {
        let waited = frame
            .arrival
            .map(|a| a.ready.saturating_since(a.arrived).as_secs_f64() * 1e3);
        tracing::debug!(
            target: "dioptra_rig::loop",
            "content frame {} arrived{}",
            frame.number,
            waited.map_or(String::new(), |ms| format!(" ({ms:.1} ms after it was due)"))
        );
    }
    fn rendered(&mut self, _now: Timestamp, report: &RenderReport<'_>) {
        match report.outcome {
            Ok(_) => tracing::debug!(
                target: "dioptra_rig::loop",
                "frame {} rendered in {:.1} ms",
                report.job.frame,
                report.took.as_secs_f64() * 1e3
            ),
            Err(f) => tracing::debug!(
                target: "dioptra_rig::loop",
                "frame {} failed to render ({}): {}",
                report.job.frame,
                f.kind,
                f.message
            ),
        }
    }
    fn stepped(&mut self, _now: Timestamp, engine: &Engine) {
        // The scheduler's status is made only for a log that shows it.
        if !tracing::enabled!(target: "dioptra_rig::scheduler", tracing::Level::DEBUG) {
            return;
        }
        let c = engine.scheduler().status().counters;
        if c.late_frames > self.late_frames {
            tracing::debug!(
                target: "dioptra_rig::scheduler",
                "{} frame(s) shown later than the slot they were rendered for ({} in all)",
                c.late_frames - self.late_frames,
                c.late_frames
            );
        }
        if c.misses > self.misses {
            tracing::debug!(
                target: "dioptra_rig::scheduler",
                "{} presentation(s) showed the frame before again: the next was not ready ({} \
                 in all)",
                c.misses - self.misses,
                c.misses
            );
        }
        (self.late_frames, self.misses) = (c.late_frames, c.misses);
    }
}

/// Writes what the scheduler got and what it commanded into the recording in progress
/// (none: nothing), in the order the loop handled it, which `dioptra replay` follows.
struct Recording(Arc<RigState>);

impl Recording {
    /// The eye of lens `lens` on a rig with a lens per eye (`None`: the rig's one lens).
    fn eye(&self, lens: LensId) -> Option<Side> {
        self.0.cfg.devices.lens.side(lens.index())
    }
}

impl LoopHook for Recording {
    fn input(&mut self, now: Timestamp, input: &DeviceInput, _engine: &Engine) {
        let rec = match input {
            DeviceInput::Gaze(g, _) => Rec::Gaze(g.into()),
            DeviceInput::LensState(lens, s) => Rec::LensState(LensStateRec {
                eye: self.eye(*lens),
                ..s.into()
            }),
            DeviceInput::LensWire {
                lens,
                id,
                requested,
                wire_time,
                ..
            } => Rec::LensWire(LensWireRec {
                id: *id,
                requested_d: requested.0,
                wire_ns: wire_time.0,
                eye: self.eye(*lens),
            }),
            DeviceInput::LensLink(lens, up) => Rec::LensLink(LensLinkRec {
                up: *up,
                eye: self.eye(*lens),
            }),
            DeviceInput::Sync(e) => Rec::Sync(e.into()),
            DeviceInput::Light(e) => Rec::Light(e.into()),
        };
        self.0.record(now, rec);
    }
    fn control(&mut self, now: Timestamp, cmd: &Control, _engine: &Engine) {
        self.0.record(now, Rec::Control(cmd.rec()));
    }
    fn content(&mut self, now: Timestamp, frame: &ContentFrame) {
        let scene_ns = frame.scene_time.map(|t| t.0);
        self.0.record(now, Rec::Depth(DepthRec { scene_ns }));
        if let Some(a) = frame.arrival {
            self.0.record(
                now,
                Rec::Content(ContentRec {
                    arrived_ns: a.arrived.0,
                    ready_ns: a.ready.0,
                }),
            );
        }
    }
    fn tick(&mut self, now: Timestamp) {
        self.0.record(now, Rec::Tick(Marker {}));
    }
    fn presented(&mut self, now: Timestamp, p: &Presented, _sink: &dyn DisplaySink) {
        if p.size_compensation.iter().any(Option::is_some) {
            self.0.record(
                now,
                Rec::Image(crate::recording::ImageRec {
                    frame: p.frame,
                    layer: p.layer,
                    shown_ns: p.shown.0,
                    size_compensation: p.size_compensation,
                }),
            );
        }
    }
    fn command(&mut self, now: Timestamp, cmd: &Command) {
        let rec = match *cmd {
            Command::SetLensPower {
                lens,
                id,
                power,
                apply_at,
                reason,
            } => Rec::LensCommand(LensCommandRec {
                id: id.0,
                power_d: power.0,
                apply_at_ns: apply_at.0,
                reason: engine::reason_name(reason),
                focus_d: Some(self.0.optics.of(lens).focus_of(power).0),
                eye: self.eye(lens),
            }),
            Command::RenderFrame(req) => Rec::Render(RenderRec {
                frame: req.frame.0,
                mode: Mode::from_sched(req.mode).as_str().into(),
                method: Method(req.method).as_str().into(),
                focus_d: req.focus.map(|d| d.0),
                display_ns: req.display_time.0,
            }),
            Command::Present {
                frame,
                vsync,
                repeat,
                ..
            } => Rec::Present(PresentRec {
                frame: frame.0,
                layer: None,
                at_ns: vsync.0,
                repeat,
            }),
            Command::PresentLayer {
                frame,
                layer,
                start,
                repeat,
                ..
            } => Rec::Present(PresentRec {
                frame: frame.0,
                layer: Some(layer),
                at_ns: start.0,
                repeat,
            }),
            Command::StopSequencer => Rec::StopSequencer(Marker {}),
            _ => return,
        };
        self.0.record(now, rec);
    }
    fn rendered(&mut self, now: Timestamp, r: &RenderReport<'_>) {
        self.0.record(
            now,
            Rec::Frame(FrameRec {
                frame: r.job.frame,
                method: r.job.method.as_str().into(),
                render_ns: r.render_ns(),
                requested_ns: r.requested.0,
                focus_d: r.focus.map(|d| d.0),
            }),
        );
    }
    fn shutdown(&mut self, now: Timestamp) {
        self.0.record(now, Rec::Shutdown(Marker {}));
    }
}

/// A kind of render error (method and kind) is logged at most once per this long.
const RENDER_ERROR_LOG_EVERY: Duration = Duration::from_secs(10);

/// Keeps what `/status` shows of the loop ([`crate::state::LoopStatus`]) and what the loop
/// hands the parts to publish (the lenses' focus, the renders, the display), and logs failed
/// renders.
struct Status {
    state: Arc<RigState>,
    /// Per (method, error kind): when it was last logged, and how many since.
    error_log: HashMap<(String, &'static str), (Timestamp, u64)>,
    /// When `/status`'s scheduler part was last made, and whether steps since wait for it.
    scheduler_at: Option<Timestamp>,
    scheduler_due: bool,
}

/// `/status`'s scheduler part (counters, latency percentiles) is made at most this often:
/// after every step it cost the loop most of a core in a debug build, starving the devices'
/// inputs (lens read-backs) on a loaded machine.
const SCHEDULER_STATUS_EVERY: std::time::Duration = std::time::Duration::from_millis(20);

impl Status {
    fn refresh_scheduler(&mut self, now: Timestamp, engine: &Engine) {
        lock(&self.state.loop_status).scheduler = engine.status();
        self.scheduler_at = Some(now);
        self.scheduler_due = false;
    }

    fn modes(&self, engine: &Engine) {
        let mut st = lock(&self.state.loop_status);
        st.mode = Some(engine.mode());
        st.method = Some(engine.method());
        st.manual_focus_d = engine.scheduler().status().manual_focus.map(|d| d.0);
    }

    /// Logs a failed render once per method and kind and [`RENDER_ERROR_LOG_EVERY`].
    fn log_failure(
        &mut self,
        now: Timestamp,
        r: &RenderReport<'_>,
        kind: &'static str,
        message: &str,
    ) {
        let method = r.job.method.as_str().to_string();
        let log = match self.error_log.entry((method.clone(), kind)) {
            std::collections::hash_map::Entry::Vacant(v) => {
                v.insert((now, 0));
                Some(0)
            }
            std::collections::hash_map::Entry::Occupied(mut o) => {
                let (last, since) = o.get_mut();
                if now.saturating_since(*last) >= RENDER_ERROR_LOG_EVERY {
                    let n = *since;
                    *last = now;
                    *since = 0;
                    Some(n)
                } else {
                    *since += 1;
                    None
                }
            }
        };
        if let Some(more) = log {
            tracing::warn!(
                frame = r.job.frame,
                method = %method,
                focus_d = r.job.focus.0,
                suppressed_since_last = more,
                error = %message,
                "render failed; showing the unblurred frame (more of this kind are logged at most every 10 s)"
            );
        }
    }
}

impl LoopHook for Status {
    fn started(&mut self, _now: Timestamp, engine: &Engine, sink: &dyn DisplaySink) {
        self.modes(engine);
        self.state.display.sink_status(sink.status());
    }
    fn input(&mut self, _now: Timestamp, input: &DeviceInput, engine: &Engine) {
        let sh = &self.state;
        let mut st = lock(&sh.loop_status);
        match input {
            DeviceInput::Gaze(..) => st.gaze_samples += 1,
            DeviceInput::LensState(lens, s) => {
                let target = lens_target(engine, *lens);
                let settled = lens_settled(
                    s,
                    target.map(|d| d.0),
                    engine.scheduler().config().settled_tolerance_d,
                );
                sh.optics.reported(*lens, s.power, settled);
            }
            // A lens whose link is down reports nothing: its last read-back is no longer
            // where it is.
            DeviceInput::LensLink(lens, false) => sh.optics.lost(*lens),
            DeviceInput::Sync(e) => {
                st.sync_events += 1;
                match e {
                    dioptra_core::SequencerEvent::SubframeStart {
                        plane_index,
                        lens_power,
                        ..
                    } => {
                        st.subframes += 1;
                        let plane = sh.cfg.optics.planes.get(usize::from(*plane_index));
                        if let (Some(p), Some(l)) = (plane, lens_power) {
                            st.subframes_measured += 1;
                            if (l.0 - p).abs() > SUBFRAME_TOLERANCE_D {
                                st.subframes_off_target += 1;
                            }
                        }
                    }
                    dioptra_core::SequencerEvent::Fault { .. } => st.subframe_faults += 1,
                }
            }
            DeviceInput::Light(dioptra_core::LightEvent::Edge(_)) => st.light_edges += 1,
            DeviceInput::Light(dioptra_core::LightEvent::Lost { count, .. }) => {
                st.light_edges_lost += count
            }
            DeviceInput::LensWire { .. } | DeviceInput::LensLink(..) => {}
        }
    }
    fn control(&mut self, _now: Timestamp, _cmd: &Control, engine: &Engine) {
        self.modes(engine);
        // An API change shows in the scheduler part at the step's end.
        self.scheduler_at = None;
    }
    fn command(&mut self, _now: Timestamp, cmd: &Command) {
        let mut st = lock(&self.state.loop_status);
        match cmd {
            Command::SetLensPower { lens, power, .. } => {
                self.state.optics.commanded(*lens, *power);
                st.lens_commands += 1;
            }
            Command::RenderFrame(_) => st.frames_requested += 1,
            _ => {}
        }
    }
    fn rendered(&mut self, now: Timestamp, r: &RenderReport<'_>) {
        match &r.outcome {
            Ok(planned) => self.state.render.made(r.took, *planned),
            Err(f) => self.state.render.failed(
                r.took,
                RenderErrorNote {
                    frame: r.job.frame,
                    method: r.job.method.as_str().to_string(),
                    kind: f.kind,
                    error: f.message.clone(),
                    focus_d: r.job.focus.0,
                },
                f.fallback,
            ),
        }
        if let Err(f) = &r.outcome {
            self.log_failure(now, r, f.kind, &f.message);
        }
    }
    fn presented(&mut self, _now: Timestamp, _p: &Presented, sink: &dyn DisplaySink) {
        self.state.display.presented(sink.status(), sink.shown());
    }
    fn not_shown(&mut self, _now: Timestamp, _frame: u64, sink: &dyn DisplaySink) {
        // The misfit count and reason reach /status though nothing is shown.
        self.state.display.not_shown(sink.status());
    }
    fn stepped(&mut self, now: Timestamp, engine: &Engine) {
        let fresh = self
            .scheduler_at
            .is_some_and(|t| now.saturating_since(t) < SCHEDULER_STATUS_EVERY);
        if fresh && !self.scheduler_due {
            self.scheduler_due = true;
        } else if !fresh {
            self.refresh_scheduler(now, engine);
        }
    }
    fn next_wakeup(&self) -> Option<Timestamp> {
        let at = self.scheduler_at?;
        self.scheduler_due
            .then(|| at.saturating_add(SCHEDULER_STATUS_EVERY))
    }
    fn wake(&mut self, now: Timestamp, engine: &Engine) {
        if self.scheduler_due {
            self.refresh_scheduler(now, engine);
        }
    }
    fn stopped(&mut self, _now: Timestamp, engine: &Engine) {
        lock(&self.state.loop_status).scheduler = engine.status();
    }
}

/// Watches the display's pacing ([`Pacing`]): logs a rig that misses its deadlines (the
/// first miss, then a summary at most every few seconds) and publishes the distinct frames
/// per second to `/status.display`.
struct Lateness {
    state: Arc<RigState>,
    pacing: Option<Pacing>,
    advice: String,
}

impl Lateness {
    fn new(state: Arc<RigState>) -> Lateness {
        Lateness {
            state,
            pacing: None,
            advice: String::new(),
        }
    }

    fn log(&self, notice: Option<Notice>) {
        let Some(n) = notice else { return };
        match n {
            Notice::OnTime(s) => tracing::info!("{s}"),
            Notice::FirstMiss(s) | Notice::Summary(s) | Notice::NoFrame(s) => {
                tracing::warn!("{s}")
            }
        }
    }

    fn publish(&self) {
        if let Some(p) = &self.pacing {
            self.state.display.pacing(p.status(), &self.advice);
        }
    }
}

impl LoopHook for Lateness {
    fn started(&mut self, now: Timestamp, engine: &Engine, _sink: &dyn DisplaySink) {
        let cfg = &self.state.cfg;
        let budget = crate::render::budget::FrameBudget::of(cfg, engine.mode());
        self.advice = crate::render::budget::generic_advice(budget.period_key);
        let period = Duration::from_secs_f64(budget.period_ms / 1e3);
        self.pacing = Some(Pacing::new(now, period, self.advice.clone()));
        self.publish();
    }
    fn rendered(&mut self, _now: Timestamp, r: &RenderReport<'_>) {
        if let Some(p) = &mut self.pacing {
            p.rendered(r.took);
        }
    }
    fn presented(&mut self, now: Timestamp, shown: &Presented, _sink: &dyn DisplaySink) {
        // A multifocal frame counts once per plane cycle (its first layer).
        if shown.layer.is_some_and(|l| l > 0) {
            return;
        }
        let notice = self
            .pacing
            .as_mut()
            .and_then(|p| p.presented(now, shown.frame, shown.repeat));
        self.log(notice);
        self.publish();
    }
    fn next_wakeup(&self) -> Option<Timestamp> {
        self.pacing.as_ref()?.next_check()
    }
    fn wake(&mut self, now: Timestamp, _engine: &Engine) {
        let notice = self.pacing.as_mut().and_then(|p| p.check(now));
        self.log(notice);
        self.publish();
    }
}

/// The WebSocket's messages (`GET /stream`): gaze with the scheduler's reading of it, lens
/// read-backs with their target and whether the lens settled there, focus commands, frames
/// shown, sub-frames, and the API's controls; made only while someone listens. Each has the
/// host time it happened (`host_ns`).
struct WebSocket(Arc<RigState>);

/// The power the scheduler last commanded `lens` (its read-backs' target).
fn lens_target(engine: &Engine, lens: LensId) -> Option<dioptra_core::Diopters> {
    engine
        .scheduler()
        .status()
        .lenses
        .get(lens.index())
        .copied()
        .flatten()
        .and_then(|l| l.commanded_power)
}

fn eye_json(e: &dioptra_core::EyeRay) -> serde_json::Value {
    json!({
        "direction": e.direction,
        "origin_mm": e.origin_mm,
        "pupil_mm": e.pupil_mm,
        "valid": e.valid,
    })
}

impl LoopHook for WebSocket {
    fn input(&mut self, _now: Timestamp, input: &DeviceInput, engine: &Engine) {
        match input {
            DeviceInput::Gaze(g, _) => self.0.publish(|| {
                let st = engine.scheduler().status();
                json!({
                    "type": "gaze",
                    "host_ns": g.host_time.0,
                    "device_ns": g.device_time.0,
                    "host_receive_ns": g.host_receive_time.0,
                    "left": eye_json(&g.left),
                    "right": eye_json(&g.right),
                    "phase": st.phase.as_str(),
                    "vergence_d": st.vergence_d,
                })
            }),
            DeviceInput::LensState(lens, s) => {
                let eye = self.0.cfg.devices.lens.side(lens.index());
                self.0.publish(|| {
                    let target = lens_target(engine, *lens);
                    let tolerance = engine.scheduler().config().settled_tolerance_d;
                    let optics = self.0.optics.of(*lens);
                    let mut m = json!({
                        "type": "lens",
                        "host_ns": s.host_time.0,
                        "power_d": s.power.0,
                        "focus_d": optics.focus_of(s.power).0,
                        "target_d": target.map(|d| d.0),
                        "target_focus_d": target.map(|d| optics.focus_of(d).0),
                        "settled": lens_settled(s, target.map(|d| d.0), tolerance),
                        "current_ma": s.current_ma,
                        "temperature_c": s.temperature_c,
                    });
                    if let Some(e) = eye {
                        m["eye"] = json!(e.as_str());
                    }
                    m
                })
            }
            DeviceInput::Sync(dioptra_core::SequencerEvent::SubframeStart {
                frame,
                plane_index,
                lens_power,
                host_time,
                ..
            }) => self.0.publish(|| {
                let plane = self.0.cfg.optics.planes.get(usize::from(*plane_index));
                json!({
                    "type": "subframe",
                    "host_ns": host_time.0,
                    "frame": frame,
                    "plane": plane_index,
                    "plane_d": plane,
                    "lens_d": lens_power.map(|d| d.0),
                })
            }),
            _ => {}
        }
    }
    fn control(&mut self, now: Timestamp, cmd: &Control, _engine: &Engine) {
        self.0.publish(|| {
            let mut m = serde_json::to_value(cmd.rec()).unwrap_or_default();
            if let Some(o) = m.as_object_mut() {
                o.insert("type".into(), json!("control"));
                o.insert("host_ns".into(), json!(now.0));
            }
            m
        });
    }
    fn command(&mut self, now: Timestamp, cmd: &Command) {
        if let Command::SetLensPower {
            lens,
            power,
            reason,
            ..
        } = *cmd
        {
            let eye = self.0.cfg.devices.lens.side(lens.index());
            self.0.publish(|| {
                let mut m = json!({
                    "type": "focus",
                    "host_ns": now.0,
                    "commanded_d": power.0,
                    "focus_d": self.0.optics.of(lens).focus_of(power).0,
                    "reason": engine::reason_name(reason),
                });
                if let Some(e) = eye {
                    m["eye"] = json!(e.as_str());
                }
                m
            });
        }
    }
    fn presented(&mut self, _now: Timestamp, p: &Presented, _sink: &dyn DisplaySink) {
        self.0.publish(|| {
            json!({
                "type": "frame",
                "host_ns": p.shown.0,
                "frame": p.frame,
                "layer": p.layer,
                "focus_d": p.focus.0,
                "shown_ns": p.shown.0,
                "repeat": p.repeat,
            })
        });
    }
}

/// The Lab Streaming Layer outlets (`[lsl] enabled = true`): gaze with the scheduler's reading
/// of it, lens commands on the wire and read-backs (each lens's outlet), and markers.
struct Lsl {
    state: Arc<RigState>,
    /// Each lens's newest power commanded (its outlet's read-backs carry it).
    commanded: [Option<dioptra_core::Diopters>; 2],
}

impl Lsl {
    fn outlets(&self) -> Option<&crate::lsl::LslOutlets> {
        self.state.lsl.as_ref()
    }
}

impl LoopHook for Lsl {
    fn input(&mut self, _now: Timestamp, input: &DeviceInput, engine: &Engine) {
        let Some(l) = self.outlets() else { return };
        match input {
            DeviceInput::Gaze(g, _) => {
                // With the scheduler's reading of it: eye phase and fused vergence.
                let st = engine.scheduler().status();
                l.gaze(g, st.phase.as_str(), st.vergence_d);
            }
            DeviceInput::LensState(lens, s) => {
                let commanded = self.commanded.get(lens.index()).copied().flatten();
                l.lens_state(*lens, s, commanded, self.state.optics.of(*lens))
            }
            DeviceInput::LensWire {
                lens,
                requested,
                wire_time,
                ..
            } => l.lens_wire(*lens, *wire_time, *requested, self.state.optics.of(*lens)),
            DeviceInput::Sync(dioptra_core::SequencerEvent::SubframeStart {
                frame,
                plane_index,
                lens_power,
                host_time,
                ..
            }) => {
                let plane = self.state.cfg.optics.planes.get(usize::from(*plane_index));
                l.marker(
                    *host_time,
                    "subframe",
                    json!({
                        "frame": frame,
                        "plane": plane_index,
                        "plane_d": plane,
                        "lens_d": lens_power.map(|d| d.0),
                    }),
                );
            }
            _ => {}
        }
    }
    fn control(&mut self, now: Timestamp, cmd: &Control, _engine: &Engine) {
        if let Some(l) = self.outlets() {
            l.marker(
                now,
                "control",
                serde_json::to_value(cmd.rec()).unwrap_or_default(),
            );
        }
    }
    fn command(&mut self, _now: Timestamp, cmd: &Command) {
        if let Command::SetLensPower { lens, power, .. } = cmd {
            if let Some(c) = self.commanded.get_mut(lens.index()) {
                *c = Some(*power);
            }
        }
    }
    fn presented(&mut self, _now: Timestamp, p: &Presented, _sink: &dyn DisplaySink) {
        if let Some(l) = self.outlets() {
            l.marker(
                p.shown,
                "frame",
                json!({
                    "frame": p.frame,
                    "layer": p.layer,
                    "focus_d": p.focus.0,
                    "repeat": p.repeat,
                }),
            );
        }
    }
}

/// Shows each presented frame's marker patch on the simulated panel, so that a simulated
/// photodiode sees what the display draws (whichever sink draws it).
pub struct PanelFeed(pub dioptra_sim::panel::SharedPanel);

impl LoopHook for PanelFeed {
    fn presented(&mut self, _now: Timestamp, shown: &Presented, _sink: &dyn DisplaySink) {
        if let Some(white) = shown.marker_white {
            self.0.lock().present(shown.shown, shown.frame, white);
        }
    }
}
