//! The loop: feeds device inputs, API commands, new content frames, finished renders and
//! timers to the scheduler (through [`Engine`]) and carries its commands out: lens commands to
//! the lens task first, renders to the render worker, frames to the display sink. It does
//! nothing else: the recording, `/status`, the WebSocket and LSL are [`LoopHook`]s
//! (`observers`) that see all of it as it happens, as the simulated rig's ground
//! truth and `dioptra hil` do.
//!
//! A content frame is an event of its own: the loop polls the content source when a frame
//! arrives (a stream's [`Content::arrivals`]), when one falls due on the source's clock
//! ([`Content::next_due`]) and before every other step, so the scheduler always has the
//! newest frame's depth before it asks for a render, and each render job carries the frame
//! whose depth the scheduler has.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use dioptra_core::{Diopters, Side, Timestamp};
use tokio::sync::mpsc;

use crate::content::stereo::EyeViews;
use crate::content::{Content, ContentFrame};
use crate::devices::{DeviceInput, DeviceLinks, LensOrder};
use crate::display::config::MarkerEvent;
use crate::display::{DisplaySink, Frame, Marker};
use crate::engine::{Command, Control, Engine, Input};
use crate::mode::{Method, Mode};
use crate::render::{Planned, RenderJob, RenderOutput, Renderer};
use crate::state::{ControlMsg, LoopCmd, PendingRecording, RigState};

/// Sees what the loop does, on the loop's task: keep it quick. The rig's recording, status,
/// WebSocket and LSL outlets are hooks (`observers`); the simulated-rig builder
/// records ground truth through one; `dioptra hil` measures through one.
pub trait LoopHook: Send {
    /// The loop starts, with the scheduler and the display as they are.
    fn started(&mut self, _now: Timestamp, _engine: &Engine, _sink: &dyn DisplaySink) {}
    /// A device input, as the scheduler has just taken it (`engine` holds its reading of it;
    /// the commands it caused come next).
    fn input(&mut self, _now: Timestamp, _input: &DeviceInput, _engine: &Engine) {}
    /// An API command the scheduler took (a refused one changed nothing and is not seen).
    fn control(&mut self, _now: Timestamp, _cmd: &Control, _engine: &Engine) {}
    /// A new content frame: the scheduler has its depth and arrival.
    fn content(&mut self, _now: Timestamp, _frame: &ContentFrame) {}
    /// The scheduler's timer is due and it is about to step.
    fn tick(&mut self, _now: Timestamp) {}
    /// A command the scheduler gave, as it is carried out.
    fn command(&mut self, _now: Timestamp, _cmd: &Command) {}
    /// A render came back (made, or failed).
    fn rendered(&mut self, _now: Timestamp, _report: &RenderReport<'_>) {}
    /// A frame (multifocal: a layer) went to the display.
    fn presented(&mut self, _now: Timestamp, _shown: &Presented, _sink: &dyn DisplaySink) {}
    /// The display refused frame `frame` (it does not fit its place); the sink counted it.
    fn not_shown(&mut self, _now: Timestamp, _frame: u64, _sink: &dyn DisplaySink) {}
    /// The loop finished a turn (the scheduler stepped and its commands were carried out).
    fn stepped(&mut self, _now: Timestamp, _engine: &Engine) {}
    /// The scheduler's shutdown is next.
    fn shutdown(&mut self, _now: Timestamp) {}
    /// When the hook wants [`LoopHook::wake`] called.
    fn next_wakeup(&self) -> Option<Timestamp> {
        None
    }
    fn wake(&mut self, _now: Timestamp, _engine: &Engine) {}
    /// The loop stopped, after the scheduler's shutdown.
    fn stopped(&mut self, _now: Timestamp, _engine: &Engine) {}
}

/// A render that came back, as hooks see it.
#[derive(Debug)]
pub struct RenderReport<'a> {
    pub job: &'a RenderJob,
    /// The focus the scheduler asked for (`None`: it gave none).
    pub focus: Option<Diopters>,
    pub requested: Timestamp,
    /// What the render counts as having taken.
    pub took: Duration,
    /// Made (with the planner's choice, where it chose), or why not.
    pub outcome: Result<Option<&'a Planned>, &'a RenderFailure>,
}

impl RenderReport<'_> {
    /// What the render took, ns.
    pub fn render_ns(&self) -> u64 {
        u64::try_from(self.took.as_nanos()).unwrap_or(u64::MAX)
    }
}

/// Why a frame did not render.
#[derive(Debug)]
pub struct RenderFailure {
    pub kind: &'static str,
    pub message: String,
    /// The content was shown unblurred in its place ([`crate::render::unblurred`]).
    pub fallback: bool,
}

/// A frame (or a multifocal layer) the display took.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Presented {
    pub frame: u64,
    pub layer: Option<u8>,
    /// The focus it was rendered for; a multifocal layer's plane.
    pub focus: Diopters,
    /// When it is on screen.
    pub shown: Timestamp,
    /// The scheduler showed it again (no newer frame was ready).
    pub repeat: bool,
    /// The marker patch's colour in this present (true: white), if the rig draws one.
    pub marker_white: Option<bool>,
    /// Each eye's magnification compensation in this present ([`Frame::size_compensation`]).
    pub size_compensation: [Option<f32>; 2],
}

/// A finished render.
struct Rendered {
    job: RenderJob,
    /// The focus the scheduler asked for (`None`: it gave none).
    focus: Option<Diopters>,
    requested: Timestamp,
    /// The frame's images (a stereo layout: the left eye's, and the right eye's), or why not
    /// and what is shown instead (the unblurred content, in both eyes' places).
    result: Result<(RenderOutput, Option<RenderOutput>), (RenderFailure, Unblurred)>,
    took: Duration,
}

/// The unblurred content shown in a failed render's place (`None`: nothing to show).
type Unblurred = Option<Vec<dioptra_core::RgbImage>>;

/// A failed render, and the unblurred content shown in its place.
fn failure(
    kind: &'static str,
    message: String,
    job: &RenderJob,
    content: &ContentFrame,
    planes: usize,
) -> (RenderFailure, Option<Vec<dioptra_core::RgbImage>>) {
    let unblurred = crate::render::unblurred(job.mode, content, planes);
    let failure = RenderFailure {
        kind,
        message,
        fallback: unblurred.is_some(),
    };
    (failure, unblurred)
}

/// Renders each eye of a stereo layout, one after the other on the rig's backend: the left
/// eye's view at `job.focus`, the right eye's at `job.focus_right` (its own lens's focus;
/// `focus` where the rig has one lens). Views synthesised from one RGB-D are made on the
/// renderer's device where it can ([`Renderer::render_eyes_on_device`]), else on the host.
fn render_eyes(
    renderer: &dyn Renderer,
    views: &EyeViews,
    job: &RenderJob,
    content: &ContentFrame,
) -> Result<(RenderOutput, Option<RenderOutput>), dioptra_render::RenderError> {
    if views.synthesises(content) {
        let started = Instant::now();
        let positions = [views.position(Side::Left), views.position(Side::Right)];
        if let Some(made) = renderer.render_eyes_on_device(job, content, positions) {
            views.note_on_device(made.as_ref().map(|e| e.made), started.elapsed());
            let [left, right] = made?.outputs;
            return Ok((left, Some(right)));
        }
    }
    let ([left, right], _) = views.of(content)?;
    let left_out = renderer.render(job, &content.for_eye(Side::Left, left))?;
    let right_job = RenderJob {
        focus: job.focus_right.unwrap_or(job.focus),
        ..job.clone()
    };
    let right_out = renderer.render(&right_job, &content.for_eye(Side::Right, right))?;
    Ok((left_out, Some(right_out)))
}

/// Finished frames kept for the scheduler to present (it shows the newest ready one).
const FRAMES_KEPT: usize = 4;

pub(crate) struct LoopParts {
    pub state: Arc<RigState>,
    pub engine: Engine,
    pub content: Arc<dyn Content>,
    pub renderer: Arc<dyn Renderer>,
    pub sink: Box<dyn DisplaySink>,
    pub links: DeviceLinks,
    pub inputs: mpsc::Receiver<DeviceInput>,
    pub controls: mpsc::Receiver<ControlMsg>,
    pub hooks: Vec<Box<dyn LoopHook>>,
    /// Cancelled when the loop has carried out the scheduler's shutdown: the device tasks stop.
    pub devices_stop: tokio_util::sync::CancellationToken,
}

/// What woke the loop.
enum Woke {
    Control(ControlMsg),
    Rendered(Box<Rendered>),
    Input(DeviceInput),
    /// A content frame arrived or fell due.
    Content,
    /// A timer: the scheduler's or a hook's.
    Timer,
}

pub(crate) async fn run_loop(parts: LoopParts) {
    let LoopParts {
        state,
        mut engine,
        content,
        renderer,
        sink,
        links,
        mut inputs,
        mut controls,
        hooks,
        devices_stop,
    } = parts;
    let cancel = state.cancel.clone();
    let clock = state.clock.clock.clone();
    let arrivals = content.arrivals();
    let (done_tx, mut done_rx) = mpsc::channel::<Rendered>(4);
    let now = clock.now();
    // A stereo layout renders each eye from its own view of the content.
    let eye_views = state.content.eye_views().cloned();
    let mut ex = Executor {
        eye_views,
        state: &state,
        links: &links,
        renderer: &renderer,
        done_tx: &done_tx,
        sink,
        frames: VecDeque::new(),
        rendering: false,
        pending: None,
        hooks,
        on_show: None,
        marker: state.cfg.display.marker_patch.as_ref().map(Marker::new),
        compensate: compensation_plan(&state.cfg),
    };
    for h in &mut ex.hooks {
        h.started(now, &engine, ex.sink.as_ref());
    }
    ex.take_content(&mut engine, content.as_ref(), now).await;
    loop {
        let wake = [
            engine.next_wakeup(),
            ex.hooks.iter().filter_map(|h| h.next_wakeup()).min(),
            content.next_due(),
        ]
        .into_iter()
        .flatten()
        .min();
        let sleep = wake.map_or(Duration::from_secs(3600), |t| {
            t.saturating_since(clock.now())
        });
        let woke = tokio::select! {
            biased;
            _ = cancel.cancelled() => break,
            Some(msg) = controls.recv() => Woke::Control(msg),
            Some(done) = done_rx.recv() => Woke::Rendered(Box::new(done)),
            Some(input) = inputs.recv() => Woke::Input(input),
            _ = async { arrivals.as_ref()?.notified().await; Some(()) }, if arrivals.is_some() => {
                Woke::Content
            }
            _ = tokio::time::sleep(sleep), if wake.is_some() => Woke::Timer,
        };
        let now = clock.now();
        // The newest content first: a render the scheduler asks for now shows it.
        ex.take_content(&mut engine, content.as_ref(), now).await;
        // The wall time a gaze sample arrived, for the lens command it causes.
        let mut cause = None;
        let cmds = match woke {
            Woke::Control(msg) => {
                let cmd = match msg.cmd {
                    LoopCmd::StartRecording(p) => {
                        let r = ex.start_recording(*p, &engine, now);
                        let _ = msg.reply.send(r);
                        continue;
                    }
                    LoopCmd::Control(c) => c,
                };
                match engine.step(now, Input::Control(cmd.clone())) {
                    Ok(cmds) => {
                        if let Control::Mode(_) = cmd {
                            let _ = links.multifocal.send(engine.mode() == Mode::Multifocal);
                            ex.marker_event(MarkerEvent::ModeChange);
                        }
                        for h in &mut ex.hooks {
                            h.control(now, &cmd, &engine);
                        }
                        let _ = msg.reply.send(Ok(()));
                        cmds
                    }
                    Err(e) => {
                        let _ = msg.reply.send(Err(e));
                        continue;
                    }
                }
            }
            Woke::Rendered(done) => {
                content.rendered(done.took, now);
                let input = ex.finished(*done, now);
                engine.step(now, input).unwrap_or_default()
            }
            Woke::Input(input) => {
                if let DeviceInput::Gaze(_, at) = &input {
                    cause = Some(*at);
                }
                let cmds = engine
                    .step(now, Input::Device(input.clone()))
                    .unwrap_or_default();
                for h in &mut ex.hooks {
                    h.input(now, &input, &engine);
                }
                cmds
            }
            Woke::Content => Vec::new(),
            Woke::Timer => {
                for h in &mut ex.hooks {
                    if h.next_wakeup().is_some_and(|t| t <= now) {
                        h.wake(now, &engine);
                    }
                }
                if engine.next_wakeup().is_some_and(|t| t <= now) {
                    for h in &mut ex.hooks {
                        h.tick(now);
                    }
                    engine.step(now, Input::Tick).unwrap_or_default()
                } else {
                    continue;
                }
            }
        };
        ex.execute(&engine, now, cmds, cause).await;
        for h in &mut ex.hooks {
            h.stepped(now, &engine);
        }
    }
    // The scheduler's own shutdown: its park command (and sequencer stop), recorded and sent
    // before the device tasks are told to stop, so the lens task sends it first.
    let now = clock.now();
    for h in &mut ex.hooks {
        h.shutdown(now);
    }
    let cmds = engine.step(now, Input::Shutdown).unwrap_or_default();
    ex.execute(&engine, now, cmds, None).await;
    devices_stop.cancel();
    // What the devices report while they stop (the park on the wire, the lens's last
    // read-backs) is still recorded and given to the scheduler, until every device task has
    // ended; its commands are no longer carried out.
    let drain = async {
        while let Some(input) = inputs.recv().await {
            let now = clock.now();
            let _ = engine.step(now, Input::Device(input.clone()));
            for h in &mut ex.hooks {
                h.input(now, &input, &engine);
            }
        }
    };
    if tokio::time::timeout(DRAIN_LIMIT, drain).await.is_err() {
        tracing::warn!("a device task did not stop within {DRAIN_LIMIT:?} of shutdown");
    }
    let now = clock.now();
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
    /// The content frame whose depth the scheduler has: what a render job shows.
    on_show: Option<ContentFrame>,
    /// The marker patch's colour, present by present (`display.marker_patch`).
    marker: Option<Marker>,
    /// A stereo layout: each eye's view of the content ([`crate::content::stereo`]).
    eye_views: Option<Arc<EyeViews>>,
    /// Each eye's image (the one image's or the left's, then the right's) with the
    /// magnification compensated: its lens and the reference power.
    compensate: [Option<(usize, Diopters)>; 2],
}

/// Which eyes' images have their magnification compensated (`optics.compensate_magnification`),
/// with their lens and reference power.
fn compensation_plan(cfg: &crate::config::RigConfig) -> [Option<(usize, Diopters)>; 2] {
    let mut plan = [None; 2];
    match cfg.eye_images() {
        Ok(images) => {
            for image in images {
                let slot = usize::from(image.eye == Some(Side::Right));
                plan[slot] = image.reference.map(|r| (image.lens, r));
            }
        }
        // Never: the config was validated with the same call.
        Err(e) => tracing::error!(error = %e, "the eyes' image settings"),
    }
    plan
}

impl Executor<'_> {
    fn marker_event(&mut self, event: MarkerEvent) {
        if let Some(m) = &mut self.marker {
            m.event(event);
        }
    }

    /// Writes a recording's `/start` with the scheduler's state and the depth it has now, and
    /// makes it the recording: every input after this step is in it.
    fn start_recording(
        &self,
        p: PendingRecording,
        engine: &Engine,
        now: Timestamp,
    ) -> Result<(), String> {
        let PendingRecording {
            recorder,
            mut start,
            path,
            meta,
        } = p;
        start.mode = engine.mode().as_str().into();
        start.method = engine.method().as_str().into();
        start.scheduler_state = Some(Box::new(
            serde_json::to_value(engine.scheduler().state())
                .map_err(|e| format!("cannot record the scheduler's state: {e}"))?,
        ));
        start.depth_scene_ns = self
            .on_show
            .as_ref()
            .and_then(|f| f.scene_time.map(|t| t.0));
        self.state
            .install_recording(recorder, start, &path, &meta, now)
            .map_err(|e| e.to_string())
    }

    /// Polls the content source; a new frame's depth (and when it arrived) goes to the
    /// scheduler.
    async fn take_content(&mut self, engine: &mut Engine, content: &dyn Content, now: Timestamp) {
        let Some(frame) = content.poll(now) else {
            return;
        };
        let mut cmds = engine
            .step(now, Input::Depth(frame.depth()))
            .unwrap_or_default();
        if let Some(a) = frame.arrival {
            cmds.extend(engine.step(now, Input::Content(a)).unwrap_or_default());
        }
        for h in &mut self.hooks {
            h.content(now, &frame);
        }
        self.on_show = Some(frame);
        self.execute(engine, now, cmds, None).await;
    }

    async fn execute(
        &mut self,
        engine: &Engine,
        now: Timestamp,
        cmds: Vec<Command>,
        cause: Option<Instant>,
    ) {
        // Lens commands first, each lens's back to back: nothing else the loop does waits in
        // front of them.
        let mut lens_sent = false;
        for c in &cmds {
            if let Command::SetLensPower {
                lens, id, power, ..
            } = *c
            {
                if let Some(link) = self.links.lens_commands.get(lens.index()) {
                    link.send_replace(Some(LensOrder {
                        id: id.0,
                        power,
                        caused_by_gaze: cause,
                    }));
                    lens_sent = true;
                }
            }
        }
        if lens_sent {
            self.marker_event(MarkerEvent::LensCommand);
        }
        if lens_sent {
            // Let the lens task write it before this task goes on.
            tokio::task::yield_now().await;
        }
        for c in cmds {
            for h in &mut self.hooks {
                h.command(now, &c);
            }
            match c {
                Command::SetLensPower { .. } => {}
                Command::RenderFrame(req) => {
                    let sh = self.state;
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
                        mode: Mode::from_sched(req.mode),
                        method: Method(req.method),
                        focus: req
                            .focus
                            .unwrap_or(Diopters(sh.cfg.devices.lens.first().park_power)),
                        focus_right: req.focus_right,
                        gaze,
                        auto: sh.render.auto(),
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
                    display_time,
                    repeat,
                } => {
                    let c = self.compensation_at(engine, display_time);
                    self.present(now, frame.0, None, vsync, repeat, c)
                }
                Command::PresentLayer {
                    frame,
                    layer,
                    start,
                    repeat,
                    ..
                } => {
                    let c = self.compensation_at(engine, start);
                    self.present(now, frame.0, Some(layer), start, repeat, c)
                }
                Command::StopSequencer => {
                    let _ = self.links.multifocal.send(false);
                }
                other => {
                    tracing::warn!(command = ?other, "scheduler command this rig does not know; ignored")
                }
            }
        }
    }

    /// Renders on a blocking thread, from the content frame on show. The frame counts as
    /// finished at its start plus its cost on the rig's clock: on the system clock that is
    /// when the render returns; on a simulated clock (frozen while the blocking thread works)
    /// the worker sleeps the cost.
    fn start_render(&mut self, job: RenderJob, focus: Option<Diopters>, requested: Timestamp) {
        let Some(content) = self.on_show.clone() else {
            // Never: the loop takes the first content frame before anything else.
            tracing::error!(frame = job.frame, "no content to render");
            return;
        };
        self.rendering = true;
        let (renderer, tx, clock) = (
            self.renderer.clone(),
            self.done_tx.clone(),
            self.state.clock.clock.clone(),
        );
        let planes = self.state.cfg.optics.planes.len();
        let eye_views = self.eye_views.clone();
        tokio::spawn(async move {
            let started = clock.now();
            let job_kept = job.clone();
            let content_kept = content.clone();
            let r = tokio::task::spawn_blocking(move || {
                let t0 = Instant::now();
                let result = match &eye_views {
                    None => renderer.render(&job, &content).map(|out| (out, None)),
                    Some(views) => render_eyes(renderer.as_ref(), views, &job, &content),
                };
                let result = result.map_err(|e| {
                    failure(
                        crate::render::error_kind(&e),
                        e.to_string(),
                        &job,
                        &content,
                        planes,
                    )
                });
                // A scripted cost per eye adds up; otherwise the wall time both took.
                let took = match &result {
                    Ok((out, right)) => out.cost.map_or_else(
                        || t0.elapsed(),
                        |l| l + right.as_ref().and_then(|r| r.cost).unwrap_or_default(),
                    ),
                    Err(_) => t0.elapsed(),
                };
                (job, result, took)
            })
            .await;
            // A renderer that panics fails its frame like any error: the loop must hear back,
            // or it would wait for this frame forever.
            let (job, result, took) = r.unwrap_or_else(|e| {
                let f = failure(
                    "panic",
                    format!("the render thread failed: {e}"),
                    &job_kept,
                    &content_kept,
                    planes,
                );
                (job_kept, Err(f), Duration::ZERO)
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

    /// Each eye's magnification compensation for a frame on screen at `at`: at the power its
    /// lens's model predicts then (while the lens moves), else the newest power commanded.
    fn compensation_at(&self, engine: &Engine, at: Timestamp) -> [Option<f32>; 2] {
        self.compensate.map(|plan| {
            let (lens, reference) = plan?;
            let id = crate::devices::input::LensId(lens as u8);
            let power = engine.scheduler().predicted_power_of(id, at).or_else(|| {
                self.state.optics.focus().commanded_by_lens[lens.min(1)].map(Diopters)
            })?;
            let c = self
                .state
                .optics
                .of(id)
                .size_compensation(power, reference)?;
            Some(c as f32)
        })
    }

    fn present(
        &mut self,
        now: Timestamp,
        frame: u64,
        layer: Option<u8>,
        at: Timestamp,
        repeat: bool,
        size_compensation: [Option<f32>; 2],
    ) {
        let Some(f) = self.frames.iter().find(|f| f.number == frame) else {
            tracing::warn!(frame, "asked to present a frame that is not rendered");
            return;
        };
        let mut f = f.clone();
        f.size_compensation = size_compensation;
        f.marker = self
            .marker
            .as_mut()
            .map(|m| m.on_present(self.state.display.marker()));
        let shown = match layer {
            None => self.sink.present(&f, at),
            Some(l) => self.sink.present_layer(&f, usize::from(l), at),
        };
        match shown {
            Ok(t) => {
                // A multifocal layer is seen at its plane, whatever focus the frame had.
                let plane = layer.and_then(|l| self.state.cfg.optics.planes.get(usize::from(l)));
                let p = Presented {
                    frame,
                    layer,
                    focus: plane.map_or(f.focus, |&d| Diopters(d)),
                    shown: t,
                    repeat,
                    marker_white: f.marker.map(|m| m.white),
                    size_compensation,
                };
                for h in &mut self.hooks {
                    h.presented(now, &p, self.sink.as_ref());
                }
            }
            // Not shown (a misfit): the sink counts it and logs each reason once.
            Err(crate::display::DisplayError::NotShown(_)) => {
                for h in &mut self.hooks {
                    h.not_shown(now, frame, self.sink.as_ref());
                }
            }
            Err(e) => tracing::warn!(error = %e, "display failed"),
        }
    }

    fn keep_frame(
        &mut self,
        job: &RenderJob,
        images: Vec<crate::render::FrameImage>,
        right: Option<Vec<crate::render::FrameImage>>,
    ) {
        if self.frames.len() == FRAMES_KEPT {
            self.frames.pop_front();
        }
        self.frames.push_back(Frame {
            number: job.frame,
            layers: Arc::new(images),
            focus: job.focus,
            right: right.map(Arc::new),
            marker: None,
            size_compensation: [None; 2],
        });
    }

    /// A render came back: keeps its frame (or, when it failed, the unblurred content in its
    /// place: the scheduler is told the frame finished all the same, so its slot is free
    /// again and the display goes on) and returns the scheduler's input for it.
    fn finished(&mut self, done: Rendered, now: Timestamp) -> Input {
        self.rendering = false;
        if let Some((job, focus, requested)) = self.pending.take() {
            self.start_render(job, focus, requested);
        }
        let Rendered {
            job,
            focus,
            requested,
            result,
            took,
        } = done;
        let (images, right, planned, failure) = match result {
            Ok((out, right)) => (Some(out.images), right.map(|r| r.images), out.planned, None),
            Err((failure, unblurred)) => (
                unblurred.map(|i| i.into_iter().map(Into::into).collect()),
                None,
                None,
                Some(failure),
            ),
        };
        let report = RenderReport {
            job: &job,
            focus,
            requested,
            took,
            outcome: match &failure {
                None => Ok(planned.as_ref()),
                Some(f) => Err(f),
            },
        };
        for h in &mut self.hooks {
            h.rendered(now, &report);
        }
        let render_time = Duration::from_nanos(report.render_ns());
        if let Some(images) = images {
            self.keep_frame(&job, images, right);
        }
        Input::RenderFinished {
            frame: job.frame,
            method: job.method,
            render_time,
        }
    }
}

#[cfg(test)]
mod tests;
