//! The loop: feeds device inputs, API commands, finished renders and timers to the scheduler
//! (through [`Engine`]), records each input before it is given and each command as it comes
//! out, and carries the commands out: lens commands to the lens task first, renders to the
//! render worker, frames to the display sink. [`LoopHook`]s see all of it as it happens.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use dioptra_core::{lock, Diopters, Timestamp};
use serde_json::json;
use tokio::sync::mpsc;

use crate::config::{Method, Mode};
use crate::devices::{DeviceInput, DeviceLinks, LensOrder};
use crate::display::{DisplaySink, Frame};
use crate::engine::{self, Command, Engine, Input};
use crate::recording::{
    FrameRec, LensCommandRec, LensLinkRec, LensWireRec, Marker, PresentRec, Rec, RenderRec,
};
use crate::render::{RenderJob, Renderer};
use crate::{Control, ControlMsg, RigState};

/// Sees what the loop does, on the loop's task: keep it quick. The simulated-rig builder
/// records ground truth through one; `dioptra hil` measures through one.
pub trait LoopHook: Send {
    /// A device input, before the scheduler gets it.
    fn input(&mut self, _now: Timestamp, _input: &DeviceInput) {}
    /// A command the scheduler gave, as it is carried out.
    fn command(&mut self, _now: Timestamp, _cmd: &Command) {}
    /// A render finished (`ok`: it made its images).
    fn rendered(&mut self, _now: Timestamp, _frame: u64, _took: Duration, _ok: bool) {}
    /// When the hook wants [`LoopHook::wake`] called.
    fn next_wakeup(&self) -> Option<Timestamp> {
        None
    }
    fn wake(&mut self, _now: Timestamp, _engine: &Engine) {}
    /// The loop stopped, after the scheduler's shutdown.
    fn stopped(&mut self, _now: Timestamp, _engine: &Engine) {}
}

/// A finished render.
struct Rendered {
    job: RenderJob,
    /// The focus the scheduler asked for (`None`: it gave none).
    focus: Option<Diopters>,
    requested: Timestamp,
    result: Result<crate::render::RenderOutput, RenderFailure>,
    took: Duration,
}

/// Why a frame did not render, and what is shown instead.
struct RenderFailure {
    kind: &'static str,
    message: String,
    /// The renderer's unblurred frame ([`Renderer::unblurred`]).
    unblurred: Option<Vec<dioptra_core::RgbImage>>,
}

/// A kind of render error (method and kind) is logged at most once per this long.
const RENDER_ERROR_LOG_EVERY: Duration = Duration::from_secs(10);

/// Finished frames kept for the scheduler to present (it shows the newest ready one).
const FRAMES_KEPT: usize = 4;

pub(crate) struct LoopParts {
    pub state: Arc<RigState>,
    pub engine: Engine,
    pub renderer: Arc<dyn Renderer>,
    pub sink: Box<dyn DisplaySink>,
    pub links: DeviceLinks,
    pub inputs: mpsc::Receiver<DeviceInput>,
    pub controls: mpsc::Receiver<ControlMsg>,
    pub hooks: Vec<Box<dyn LoopHook>>,
    /// Cancelled when the loop has carried out the scheduler's shutdown: the device tasks stop.
    pub devices_stop: tokio_util::sync::CancellationToken,
}

pub(crate) async fn run_loop(parts: LoopParts) {
    let LoopParts {
        state,
        mut engine,
        renderer,
        sink,
        links,
        mut inputs,
        mut controls,
        hooks,
        devices_stop,
    } = parts;
    let cancel = state.cancel.clone();
    let clock = state.clock.clone();
    let (done_tx, mut done_rx) = mpsc::channel::<Rendered>(4);
    let mut ex = Executor {
        state: &state,
        links: &links,
        renderer: &renderer,
        done_tx: &done_tx,
        sink,
        frames: VecDeque::new(),
        rendering: false,
        pending: None,
        hooks,
        new_depth: None,
        error_log: std::collections::HashMap::new(),
    };
    ex.sync_status(&engine);
    let now = clock.now();
    if let Some(d) = renderer.depth(now) {
        let arrival = renderer.take_arrival();
        ex.give_content(&mut engine, now, d, arrival).await;
    }
    loop {
        let wake = [
            engine.next_wakeup(),
            ex.hooks.iter().filter_map(|h| h.next_wakeup()).min(),
        ]
        .into_iter()
        .flatten()
        .min();
        let sleep = wake.map_or(Duration::from_secs(3600), |t| {
            t.saturating_since(clock.now())
        });
        let now;
        // The wall time a gaze sample arrived, for the lens command it causes.
        let mut cause = None;
        let cmds = tokio::select! {
            biased;
            _ = cancel.cancelled() => break,
            Some(msg) = controls.recv() => {
                now = clock.now();
                let cmd = msg.cmd;
                match engine.step(now, Input::Control(cmd.clone())) {
                    Ok(cmds) => {
                        // Recorded only when applied: a refused command changed nothing.
                        let rec = cmd.rec();
                        if let Some(l) = &state.lsl {
                            l.marker(now, "control", serde_json::to_value(&rec).unwrap_or_default());
                        }
                        state.record(now, Rec::Control(rec));
                        if let Control::Mode(_) = cmd {
                            let _ = links.multifocal.send(engine.mode() == Mode::Multifocal);
                        }
                        ex.sync_status(&engine);
                        let _ = msg.reply.send(Ok(()));
                        cmds
                    }
                    Err(e) => {
                        let _ = msg.reply.send(Err(e));
                        continue;
                    }
                }
            }
            Some(done) = done_rx.recv() => {
                now = clock.now();
                let input = ex.finished(done, now);
                engine.step(now, input).unwrap_or_default()
            }
            Some(input) = inputs.recv() => {
                now = clock.now();
                if let DeviceInput::Gaze(_, at) = &input {
                    cause = Some(*at);
                }
                ex.device_input(&input, now);
                let gaze = match (&state.lsl, &input) {
                    (Some(_), DeviceInput::Gaze(g, _)) => Some(*g),
                    _ => None,
                };
                let cmds = engine.step(now, Input::Device(input)).unwrap_or_default();
                // With the scheduler's reading of it: eye phase and fused vergence.
                if let (Some(l), Some(g)) = (&state.lsl, gaze) {
                    let st = engine.scheduler().status();
                    l.gaze(&g, st.phase.as_str(), st.vergence_d);
                }
                cmds
            }
            _ = tokio::time::sleep(sleep), if wake.is_some() => {
                now = clock.now();
                for h in &mut ex.hooks {
                    if h.next_wakeup().is_some_and(|t| t <= now) {
                        h.wake(now, &engine);
                    }
                }
                if engine.next_wakeup().is_some_and(|t| t <= now) {
                    state.record(now, Rec::Tick(Marker {}));
                    engine.step(now, Input::Tick).unwrap_or_default()
                } else {
                    continue;
                }
            }
        };
        ex.execute(now, cmds, cause).await;
        // A frame was asked for and the content had moved on: the scheduler reads the new
        // depth.
        if let Some((d, arrival)) = ex.new_depth.take() {
            ex.give_content(&mut engine, now, d, arrival).await;
        }
        lock(&state.status).scheduler = engine.status();
    }
    // The scheduler's own shutdown: its park command (and sequencer stop), recorded and sent
    // before the device tasks are told to stop, so the lens task sends it first.
    let now = clock.now();
    state.record(now, Rec::Shutdown(Marker {}));
    let cmds = engine.step(now, Input::Shutdown).unwrap_or_default();
    ex.execute(now, cmds, None).await;
    devices_stop.cancel();
    // What the devices report while they stop (the park on the wire, the lens's last
    // read-backs) is still recorded and given to the scheduler, until every device task has
    // ended; its commands are no longer carried out.
    let drain = async {
        while let Some(input) = inputs.recv().await {
            let now = clock.now();
            ex.device_input(&input, now);
            let _ = engine.step(now, Input::Device(input));
        }
    };
    if tokio::time::timeout(DRAIN_LIMIT, drain).await.is_err() {
        tracing::warn!("a device task did not stop within {DRAIN_LIMIT:?} of shutdown");
    }
    let now = clock.now();
    lock(&state.status).scheduler = engine.status();
    for h in &mut ex.hooks {
        h.stopped(now, &engine);
    }
}

/// How long the loop waits for the device tasks to stop after its shutdown (parking takes up
/// to [`crate::devices::DeviceSettings::park_timeout`]).
const DRAIN_LIMIT: Duration = Duration::from_secs(10);

/// Carries out the scheduler's commands.
struct Executor<'a> {
    state: &'a Arc<RigState>,
    links: &'a DeviceLinks,
    renderer: &'a Arc<dyn Renderer>,
    done_tx: &'a mpsc::Sender<Rendered>,
    sink: Box<dyn DisplaySink>,
    frames: VecDeque<Frame>,
    rendering: bool,
    /// A render asked for while another was still running.
    pending: Option<(RenderJob, Option<Diopters>, Timestamp)>,
    hooks: Vec<Box<dyn LoopHook>>,
    /// The content's depth when it changed at a frame request, for the scheduler.
    new_depth: Option<(Arc<dioptra_core::DepthMap>, Option<crate::render::Arrival>)>,
    /// Per (method, error kind): when it was last logged, and how many since.
    error_log: std::collections::HashMap<(String, &'static str), (Timestamp, u64)>,
}

impl Executor<'_> {
    /// Gives the scheduler the content's new depth, and when that content frame arrived.
    async fn give_content(
        &mut self,
        engine: &mut Engine,
        now: Timestamp,
        depth: Arc<dioptra_core::DepthMap>,
        arrival: Option<crate::render::Arrival>,
    ) {
        let scene_ns = self.renderer.content_time().map(|t| t.0);
        self.state
            .record(now, Rec::Depth(crate::recording::DepthRec { scene_ns }));
        let cmds = engine.step(now, Input::Depth(depth)).unwrap_or_default();
        self.execute(now, cmds, None).await;
        if let Some(a) = arrival {
            self.state.record(
                now,
                Rec::Content(crate::recording::ContentRec {
                    arrived_ns: a.arrived.0,
                    ready_ns: a.ready.0,
                }),
            );
            let cmds = engine.step(now, Input::Content(a)).unwrap_or_default();
            self.execute(now, cmds, None).await;
        }
    }

    fn sync_status(&self, engine: &Engine) {
        let mut st = lock(&self.state.status);
        st.mode = Some(engine.mode());
        st.method = Some(engine.method());
        st.manual_focus_d = engine.scheduler().status().manual_focus.map(|d| d.0);
        st.display = self.sink.status();
    }

    fn device_input(&mut self, input: &DeviceInput, now: Timestamp) {
        for h in &mut self.hooks {
            h.input(now, input);
        }
        let sh = self.state;
        match input {
            DeviceInput::Gaze(g, _) => {
                sh.record(now, Rec::Gaze(g.into()));
                lock(&sh.status).gaze_samples += 1;
                sh.publish(|| {
                    json!({
                        "type": "gaze",
                        "host_ns": g.host_time.0,
                        "left": { "direction": g.left.direction, "valid": g.left.valid },
                        "right": { "direction": g.right.direction, "valid": g.right.valid },
                    })
                });
            }
            DeviceInput::LensState(s) => {
                sh.record(now, Rec::LensState(s.into()));
                let commanded = {
                    let mut st = lock(&sh.status);
                    st.lens_power_d = Some(s.power.0);
                    st.commanded_focus_d
                };
                if let Some(l) = &sh.lsl {
                    l.lens_state(s, commanded);
                }
                sh.publish(
                    || json!({ "type": "lens", "host_ns": s.host_time.0, "power_d": s.power.0 }),
                );
            }
            DeviceInput::LensWire {
                id,
                requested,
                wire_time,
                ..
            } => {
                if let Some(l) = &sh.lsl {
                    l.lens_wire(*wire_time, requested.0);
                }
                sh.record(
                    now,
                    Rec::LensWire(LensWireRec {
                        id: *id,
                        requested_d: requested.0,
                        wire_ns: wire_time.0,
                    }),
                )
            }
            DeviceInput::LensLink(up) => sh.record(now, Rec::LensLink(LensLinkRec { up: *up })),
            DeviceInput::Sync(e) => {
                sh.record(now, Rec::Sync(e.into()));
                let mut st = lock(&sh.status);
                st.sync_events += 1;
                match e {
                    dioptra_core::SequencerEvent::SubframeStart {
                        frame,
                        plane_index,
                        lens_power,
                        host_time,
                        ..
                    } => {
                        st.subframes += 1;
                        let plane = sh.cfg.optics.planes.get(usize::from(*plane_index));
                        if let Some(l) = &sh.lsl {
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
                        if let (Some(p), Some(l)) = (plane, lens_power) {
                            st.subframes_measured += 1;
                            if (l.0 - p).abs() > crate::SUBFRAME_TOLERANCE_D {
                                st.subframes_off_target += 1;
                            }
                        }
                    }
                    dioptra_core::SequencerEvent::Fault { .. } => st.subframe_faults += 1,
                }
            }
        }
    }

    async fn execute(&mut self, now: Timestamp, cmds: Vec<Command>, cause: Option<Instant>) {
        // Lens commands first: nothing else the loop does waits in front of them.
        let mut lens_sent = false;
        for c in &cmds {
            if let Command::SetLensPower { id, power, .. } = *c {
                self.links.lens_commands.send_replace(Some(LensOrder {
                    id: id.0,
                    power,
                    caused_by_gaze: cause,
                }));
                lens_sent = true;
            }
        }
        if lens_sent {
            // Let the lens task write it before this task goes on.
            tokio::task::yield_now().await;
        }
        let sh = self.state;
        for c in cmds {
            for h in &mut self.hooks {
                h.command(now, &c);
            }
            match c {
                Command::SetLensPower {
                    id,
                    power,
                    apply_at,
                    reason,
                } => {
                    sh.record(
                        now,
                        Rec::LensCommand(LensCommandRec {
                            id: id.0,
                            power_d: power.0,
                            apply_at_ns: apply_at.0,
                            reason: engine::reason_name(reason),
                        }),
                    );
                    {
                        let mut st = lock(&sh.status);
                        st.commanded_focus_d = Some(power.0);
                        st.lens_commands += 1;
                    }
                    sh.publish(|| {
                        json!({
                            "type": "focus",
                            "host_ns": now.0,
                            "commanded_d": power.0,
                            "reason": engine::reason_name(reason),
                        })
                    });
                }
                Command::RenderFrame(req) => {
                    let mode = Mode::from_sched(req.mode);
                    let method = Method(req.method);
                    sh.record(
                        now,
                        Rec::Render(RenderRec {
                            frame: req.frame.0,
                            mode: mode.as_str().into(),
                            method: method.as_str().into(),
                            focus_d: req.focus.map(|d| d.0),
                            display_ns: req.display_time.0,
                        }),
                    );
                    lock(&sh.status).frames_requested += 1;
                    // The frame shows the content as it is now.
                    if let Some(d) = self.renderer.depth(now) {
                        self.new_depth = Some((d, self.renderer.take_arrival()));
                    }
                    let d = &sh.cfg.display;
                    let gaze = req.gaze.and_then(|a| {
                        let (x, y) = dioptra_sched::depth::pixel_of(
                            a.direction(),
                            d.width as usize,
                            sh.cfg.eye.fov_deg,
                        )?;
                        Some([
                            (x + 0.5 * f64::from(d.width)) as f32,
                            (y + 0.5 * f64::from(d.height)) as f32,
                        ])
                    });
                    let job = RenderJob {
                        frame: req.frame.0,
                        mode,
                        method,
                        focus: req
                            .focus
                            .unwrap_or(Diopters(sh.cfg.devices.lens.park_power)),
                        gaze,
                        auto: sh.auto_method.load(std::sync::atomic::Ordering::Relaxed),
                        display_time: req.display_time,
                    };
                    if self.rendering {
                        // A render the scheduler no longer waits for (it was asked before a
                        // mode change) is still running: this one starts when it is done.
                        if let Some((old, _, _)) = self.pending.replace((job, req.focus, now)) {
                            tracing::warn!(
                                frame = old.frame,
                                "render request replaced before it started"
                            );
                        }
                    } else {
                        self.start_render(job, req.focus, now);
                    }
                }
                Command::Present {
                    frame,
                    vsync,
                    repeat,
                    ..
                } => self.present(now, frame.0, None, vsync, repeat),
                Command::PresentLayer {
                    frame,
                    layer,
                    start,
                    repeat,
                    ..
                } => self.present(now, frame.0, Some(layer), start, repeat),
                Command::StopSequencer => {
                    sh.record(now, Rec::StopSequencer(Marker {}));
                    let _ = self.links.multifocal.send(false);
                }
                other => {
                    tracing::warn!(command = ?other, "scheduler command this rig does not know; ignored")
                }
            }
        }
    }

    /// Renders on a blocking thread. The frame counts as finished at its start plus its cost
    /// on the rig's clock: on the system clock that is when the render returns; on a
    /// simulated clock (frozen while the blocking thread works) the worker sleeps the cost.
    fn start_render(&mut self, job: RenderJob, focus: Option<Diopters>, requested: Timestamp) {
        self.rendering = true;
        let (renderer, tx, clock) = (
            self.renderer.clone(),
            self.done_tx.clone(),
            self.state.clock.clone(),
        );
        tokio::spawn(async move {
            let started = clock.now();
            let job_kept = job.clone();
            let worker = renderer.clone();
            let r = tokio::task::spawn_blocking(move || {
                let t0 = Instant::now();
                let result = worker.render(&job).map_err(|e| RenderFailure {
                    kind: crate::render::error_kind(&e),
                    message: e.to_string(),
                    unblurred: worker.unblurred(&job),
                });
                let took = match &result {
                    Ok(out) => out.cost.unwrap_or_else(|| t0.elapsed()),
                    Err(_) => t0.elapsed(),
                };
                (job, result, took)
            })
            .await;
            // A renderer that panics fails its frame like any error: the loop must hear back,
            // or it would wait for this frame forever.
            let (job, result, took) = r.unwrap_or_else(|e| {
                let unblurred = renderer.unblurred(&job_kept);
                let failure = RenderFailure {
                    kind: "panic",
                    message: format!("the render thread failed: {e}"),
                    unblurred,
                };
                (job_kept, Err(failure), Duration::ZERO)
            });
            let finish = started + took;
            tokio::time::sleep(finish.saturating_since(clock.now())).await;
            let _ = tx
                .send(Rendered {
                    job,
                    focus,
                    requested,
                    result,
                    took,
                })
                .await;
        });
    }

    fn present(
        &mut self,
        now: Timestamp,
        frame: u64,
        layer: Option<u8>,
        at: Timestamp,
        repeat: bool,
    ) {
        let sh = self.state;
        sh.record(
            now,
            Rec::Present(PresentRec {
                frame,
                layer,
                at_ns: at.0,
                repeat,
            }),
        );
        let Some(f) = self.frames.iter().find(|f| f.number == frame) else {
            tracing::warn!(frame, "asked to present a frame that is not rendered");
            return;
        };
        let shown = match layer {
            None => self.sink.present(f, at),
            Some(l) => self.sink.present_layer(f, usize::from(l), at),
        };
        match shown {
            Ok(t) => {
                if let Some(l) = &sh.lsl {
                    l.marker(
                        t,
                        "frame",
                        json!({
                            "frame": frame,
                            "layer": layer,
                            "focus_d": f.focus.0,
                            "repeat": repeat,
                        }),
                    );
                }
                sh.publish(|| {
                    json!({
                        "type": "frame",
                        "frame": frame,
                        "layer": layer,
                        "focus_d": f.focus.0,
                        "shown_ns": t.0,
                        "repeat": repeat,
                    })
                })
            }
            Err(e) => tracing::warn!(error = %e, "display failed"),
        }
        let mut st = lock(&sh.status);
        st.frames_shown = self.sink.shown();
        st.display = self.sink.status();
    }

    /// Counts a failed render, logs it (once per kind and [`RENDER_ERROR_LOG_EVERY`]) and keeps
    /// the unblurred frame in its place. The scheduler is told the frame finished all the
    /// same: its slot is free again, and the display goes on.
    fn render_failed(&mut self, now: Timestamp, job: &RenderJob, failure: RenderFailure) {
        let method = job.method.as_str().to_string();
        {
            let mut st = lock(&self.state.status);
            st.render_errors += 1;
            *st.render_errors_by_method
                .entry(method.clone())
                .or_default() += 1;
            st.last_render_error = Some(crate::RenderErrorNote {
                frame: job.frame,
                method: method.clone(),
                kind: failure.kind,
                error: failure.message.clone(),
                focus_d: job.focus.0,
            });
        }
        let key = (method.clone(), failure.kind);
        let entry = self.error_log.entry(key);
        let log = match entry {
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
                frame = job.frame,
                method = %method,
                focus_d = job.focus.0,
                suppressed_since_last = more,
                error = %failure.message,
                "render failed; showing the unblurred frame (more of this kind are logged at most every 10 s)"
            );
        }
        if let Some(images) = failure.unblurred {
            lock(&self.state.status).fallback_frames += 1;
            self.keep_frame(job, images.into_iter().map(Into::into).collect());
        }
    }

    fn keep_frame(&mut self, job: &RenderJob, images: Vec<crate::render::FrameImage>) {
        if self.frames.len() == FRAMES_KEPT {
            self.frames.pop_front();
        }
        self.frames.push_back(Frame {
            number: job.frame,
            layers: Arc::new(images),
            focus: job.focus,
        });
    }

    /// A render came back: keeps its frame and returns the scheduler's input for it.
    fn finished(&mut self, done: Rendered, now: Timestamp) -> Input {
        self.rendering = false;
        if let Some((job, focus, requested)) = self.pending.take() {
            self.start_render(job, focus, requested);
        }
        let sh = self.state;
        lock(&sh.status).last_render_ms = Some(done.took.as_secs_f64() * 1e3);
        for h in &mut self.hooks {
            h.rendered(now, done.job.frame, done.took, done.result.is_ok());
        }
        match done.result {
            Ok(rendered) => {
                if rendered.planned.is_some() {
                    lock(&sh.status).planned = rendered.planned;
                }
                self.keep_frame(&done.job, rendered.images);
            }
            Err(failure) => self.render_failed(now, &done.job, failure),
        }
        let render_ns = u64::try_from(done.took.as_nanos()).unwrap_or(u64::MAX);
        sh.record(
            now,
            Rec::Frame(FrameRec {
                frame: done.job.frame,
                method: done.job.method.as_str().into(),
                render_ns,
                requested_ns: done.requested.0,
                focus_d: done.focus.map(|d| d.0),
            }),
        );
        Input::RenderFinished {
            frame: done.job.frame,
            method: done.job.method,
            render_time: Duration::from_nanos(render_ns),
        }
    }
}
