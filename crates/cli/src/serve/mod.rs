//! `dioptra serve --config rig.toml`: the display-control daemon.
//!
//! Tasks (tokio): one per device ([`devices`]), the loop task that feeds the scheduler
//! ([`engine`]) and carries out its commands, render workers (blocking threads, one frame in
//! flight at a time), the recorder's writer thread ([`recording`]) and the API server
//! ([`api`]). Everything stops through one [`CancellationToken`] (Ctrl-C or `POST
//! /shutdown`): the lens task parks the lens at `devices.lens.park_power`, the sync task stops
//! the sequence, and the recording is finished, before [`Daemon::wait`] returns.
//!
//! Threads: with the headless sink the tokio runtime runs on the main thread. With
//! `display.kind = "window"` the main thread belongs to winit's event loop
//! ([`window::run_on_main_thread`]) and the runtime runs on a thread of its own; closing the
//! window cancels the daemon as Ctrl-C does.

pub mod api;
pub mod config;
pub mod devices;
pub mod display;
pub mod engine;
pub mod recording;
pub mod render;
pub mod window;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{Context, Result};
use axum::http::StatusCode;
use dioptra_core::{Clock, Diopters, Timestamp};
use serde::Serialize;
use serde_json::json;
use tokio::sync::{broadcast, mpsc, oneshot};
use tokio_util::sync::CancellationToken;

use config::{Listen, Method, Mode, RigConfig};
use devices::{lock, DeviceInput, ParkReport, Registry, SimDevices};
use display::{DisplaySink, Frame, HeadlessSink};
use engine::{Command, Engine, Input};
use recording::{
    ControlRec, FrameRec, LensCommandRec, LensLinkRec, LensWireRec, Marker, PresentRec, Rec,
    Recorder, RecordingStats, RenderRec, StartRec,
};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The rig config (TOML); see crates/cli/examples/rig-sim.toml.
    #[arg(long)]
    pub config: PathBuf,
}

pub fn run(args: Args) -> Result<()> {
    let cfg = RigConfig::load(&args.config)
        .with_context(|| format!("in the rig config {}", args.config.display()))?;
    let stop = CancellationToken::new();
    match cfg.display.kind {
        config::SinkKind::Headless => serve_blocking(cfg, None, stop),
        // The window's event loop takes this (the main) thread; the daemon runs on another.
        config::SinkKind::Window => {
            let choice = cfg.display.monitor.clone();
            window::run_on_main_thread(choice, stop.clone(), move |ready| {
                serve_blocking(cfg, Some(ready), stop)
            })
        }
    }
}

/// Runs the daemon on a tokio runtime until Ctrl-C, `POST /shutdown` or `stop`.
fn serve_blocking(
    cfg: RigConfig,
    window: Option<window::WindowReady>,
    stop: CancellationToken,
) -> Result<()> {
    let sink: Option<Box<dyn DisplaySink>> = match window {
        Some(w) => Some(Box::new(
            window::WindowSink::new(w.window, w.monitor)
                .context("cannot draw to the display window")?,
        )),
        None => None,
    };
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(async {
            let daemon = Daemon::start_with(cfg, None, sink).await?;
            match daemon.listening() {
                Listening::Tcp(a) => eprintln!("dioptra serve: API on http://{a}"),
                Listening::Unix(p) => eprintln!("dioptra serve: API on unix:{}", p.display()),
            }
            let status = daemon.shared().status_json();
            eprintln!("dioptra serve: display {}", status["display"]["sink"]);
            let cancel = daemon.cancel_token();
            tokio::spawn(async move {
                tokio::select! {
                    r = tokio::signal::ctrl_c() => if r.is_ok() {
                        eprintln!("dioptra serve: stopping (Ctrl-C)");
                    },
                    _ = stop.cancelled() => eprintln!("dioptra serve: stopping (window closed)"),
                }
                cancel.cancel();
            });
            let shared = daemon.shared().clone();
            let report = daemon.wait().await;
            let v = shared.status_json();
            eprintln!(
                "dioptra serve: {} gaze samples, {} lens commands, {} frames shown in {:.1} s",
                v["counts"]["gaze_samples"],
                v["counts"]["lens_commands"],
                v["counts"]["frames_shown"],
                v["uptime_s"].as_f64().unwrap_or(0.0)
            );
            eprintln!("{}", report.summary());
            if report.ok() {
                Ok(())
            } else {
                anyhow::bail!(
                    "the daemon did not stop cleanly: {}",
                    report.problems().join("; ")
                )
            }
        })
}

/// An API command for the loop.
#[derive(Debug, Clone, PartialEq)]
pub enum Control {
    Mode(Mode),
    Method(Method),
    ManualFocus(Option<f32>),
}

impl Control {
    fn rec(&self) -> ControlRec {
        match self {
            Control::Mode(m) => ControlRec::Mode {
                mode: m.as_str().into(),
            },
            Control::Method(m) => ControlRec::Method {
                method: m.as_str().into(),
            },
            Control::ManualFocus(d) => ControlRec::ManualFocus { diopters: *d },
        }
    }
}

struct ControlMsg {
    cmd: Control,
    reply: oneshot::Sender<Result<(), String>>,
}

/// What the loop publishes for `GET /status`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LoopStatus {
    pub mode: Option<Mode>,
    pub method: Option<Method>,
    pub manual_focus_d: Option<f32>,
    /// The newest lens power the scheduler commanded.
    pub commanded_focus_d: Option<f32>,
    /// The newest lens power the lens reported.
    pub lens_power_d: Option<f32>,
    pub gaze_samples: u64,
    pub lens_commands: u64,
    pub sync_events: u64,
    pub frames_requested: u64,
    pub frames_shown: u64,
    pub render_errors: u64,
    pub last_render_ms: Option<f64>,
    /// `method = "auto"`: the planner's choice for the newest frame.
    pub planned: Option<render::Planned>,
    pub display: serde_json::Value,
    pub scheduler: serde_json::Value,
}

/// State shared by the loop, the API and the device tasks.
pub struct Shared {
    pub cfg: RigConfig,
    pub registry: Arc<Registry>,
    pub status: Mutex<LoopStatus>,
    pub stream: broadcast::Sender<Arc<str>>,
    pub recording: Mutex<Option<Recorder>>,
    pub cancel: CancellationToken,
    pub clock: Arc<dyn Clock>,
    /// The simulated devices (none on a hardware rig); set once the devices start.
    pub sims: std::sync::OnceLock<SimDevices>,
    controls: mpsc::Sender<ControlMsg>,
    started: Timestamp,
}

impl Shared {
    pub fn status_json(&self) -> serde_json::Value {
        let now = self.clock.now();
        let status = lock(&self.status).clone();
        let recording = lock(&self.recording)
            .as_ref()
            .map(|r| r.path().display().to_string());
        json!({
            "uptime_s": now.saturating_since(self.started).as_secs_f64(),
            "mode": status.mode,
            "method": if self.cfg.auto_method { json!("auto") } else { json!(status.method) },
            "planned": status.planned.as_ref().map(|p| json!({
                "method": p.choice,
                "predicted_fovea_psnr_db": p.predicted_psnr_db,
                "why": p.why,
            })),
            "focus": {
                "manual_d": status.manual_focus_d,
                "commanded_d": status.commanded_focus_d,
                "lens_d": status.lens_power_d,
                "lens_range_d": [self.cfg.optics.lens_range.min, self.cfg.optics.lens_range.max],
            },
            "devices": self.registry.snapshot(),
            "counts": {
                "gaze_samples": status.gaze_samples,
                "lens_commands": status.lens_commands,
                "sync_events": status.sync_events,
                "frames_requested": status.frames_requested,
                "frames_shown": status.frames_shown,
                "render_errors": status.render_errors,
            },
            "last_render_ms": status.last_render_ms,
            "display": status.display,
            "scheduler": status.scheduler,
            "recording": recording,
            "sim_lens": self.sims.get().and_then(|s| s.lens.as_ref()).map(|(l, plug)| {
                let m = l.model();
                json!({
                    "power_d": m.power().0,
                    "target_d": m.target_power().0,
                    "settled": m.settled(),
                    "plugged": plug.is_plugged(),
                })
            }),
        })
    }

    /// Hands a command to the loop and waits for its answer.
    pub async fn control(&self, cmd: Control) -> Result<(), api::ApiError> {
        let (reply, rx) = oneshot::channel();
        let gone = || {
            api::ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "the daemon is shutting down; the command was not applied",
            )
        };
        self.controls
            .send(ControlMsg { cmd, reply })
            .await
            .map_err(|_| gone())?;
        rx.await
            .map_err(|_| gone())?
            .map_err(|e| api::ApiError::new(StatusCode::CONFLICT, e))
    }

    fn record(&self, t: Timestamp, rec: Rec) {
        if let Some(r) = lock(&self.recording).as_ref() {
            r.record(t, rec);
        }
    }

    fn publish(&self, msg: serde_json::Value) {
        if self.stream.receiver_count() > 0 {
            let _ = self.stream.send(Arc::from(msg.to_string()));
        }
    }

    /// Starts a recording in `recording.dir`; returns its path.
    pub fn start_recording(&self, from_start: bool) -> Result<PathBuf, api::ApiError> {
        let Some(rc) = &self.cfg.recording else {
            return Err(api::ApiError::new(
                StatusCode::CONFLICT,
                "the rig config has no [recording] section with a dir; add one to record",
            ));
        };
        let mut slot = lock(&self.recording);
        if let Some(r) = slot.as_ref() {
            return Err(api::ApiError::new(
                StatusCode::CONFLICT,
                format!("already recording to {}", r.path().display()),
            ));
        }
        std::fs::create_dir_all(&rc.dir).map_err(|e| {
            api::ApiError::new(
                StatusCode::INTERNAL_SERVER_ERROR,
                format!("cannot create {}: {e}", rc.dir.display()),
            )
        })?;
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        let mut path = rc.dir.join(format!("dioptra-{}.mcap", stamp.as_secs()));
        let mut n = 1;
        while path.exists() {
            path = rc.dir.join(format!("dioptra-{}-{n}.mcap", stamp.as_secs()));
            n += 1;
        }
        let r = Recorder::start(&path)
            .map_err(|e| api::ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
        // The rig config and the scheduler's state, so that a replay starts where the run was.
        let st = lock(&self.status).clone();
        r.record(
            self.clock.now(),
            Rec::Start(StartRec {
                config: toml::to_string(&self.cfg).unwrap_or_default(),
                mode: st.mode.unwrap_or(self.cfg.mode).as_str().into(),
                method: st.method.unwrap_or(self.cfg.method).as_str().into(),
                manual_focus_d: st.manual_focus_d,
                from_start,
            }),
        );
        *slot = Some(r);
        Ok(path)
    }

    /// Finishes the recording in progress.
    pub async fn stop_recording(&self) -> Result<RecordingStats, api::ApiError> {
        let r = lock(&self.recording)
            .take()
            .ok_or_else(|| api::ApiError::new(StatusCode::CONFLICT, "not recording"))?;
        r.finish()
            .await
            .map_err(|e| api::ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))
    }
}

/// Where the API ended up listening.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Listening {
    Tcp(SocketAddr),
    Unix(PathBuf),
}

/// A running daemon.
pub struct Daemon {
    shared: Arc<Shared>,
    listening: Listening,
    lens: tokio::task::JoinHandle<ParkReport>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    server: tokio::task::JoinHandle<Result<(), std::io::Error>>,
    looper: tokio::task::JoinHandle<()>,
}

/// How the daemon stopped.
#[derive(Debug, Clone, Serialize)]
pub struct ShutdownReport {
    pub park: Option<ParkReport>,
    pub recording: Option<Result<RecordingStats, String>>,
    pub task_errors: Vec<String>,
}

impl ShutdownReport {
    pub fn problems(&self) -> Vec<String> {
        let mut p = self.task_errors.clone();
        match &self.park {
            Some(ParkReport { error: Some(e), .. }) => p.push(e.clone()),
            None => p.push("the lens task did not report".into()),
            _ => {}
        }
        if let Some(Err(e)) = &self.recording {
            p.push(e.clone());
        }
        p
    }
    pub fn ok(&self) -> bool {
        self.problems().is_empty()
    }
    pub fn summary(&self) -> String {
        let mut s = String::new();
        match &self.park {
            Some(ParkReport {
                park_power,
                reported_power: Some(r),
                error: None,
            }) => s += &format!("lens parked at {park_power} D (reports {r:.3} D)"),
            Some(ParkReport { error: Some(e), .. }) => s += &format!("lens: {e}"),
            _ => s += "lens: no report",
        }
        match &self.recording {
            Some(Ok(r)) => {
                s += &format!(
                    "; recording {} finished ({} messages, {} dropped)",
                    r.path.display(),
                    r.messages,
                    r.dropped
                )
            }
            Some(Err(e)) => s += &format!("; recording failed: {e}"),
            None => {}
        }
        s
    }
}

impl Daemon {
    /// Starts every task with tokio's clock and the headless sink; the API is listening when
    /// this returns.
    #[cfg(test)]
    pub async fn start(cfg: RigConfig) -> Result<Daemon> {
        Self::start_with(cfg, None, None).await
    }

    /// Starts every task with `clock` (default tokio's) and `sink` (default the one
    /// `display.kind` names; the window sink has to be given, made from the window the main
    /// thread opened). The API is listening when this returns.
    pub async fn start_with(
        cfg: RigConfig,
        clock: Option<Arc<dyn Clock>>,
        sink: Option<Box<dyn DisplaySink>>,
    ) -> Result<Daemon> {
        let clock: Arc<dyn Clock> =
            clock.unwrap_or_else(|| Arc::new(dioptra_sim::tokio_clock::TokioClock::new()));
        cfg.validate()?;
        let listen = cfg.listen()?;
        let cancel = CancellationToken::new();
        let registry = Arc::new(Registry::default());
        let (controls_tx, controls_rx) = mpsc::channel(64);
        let (stream, _) = broadcast::channel(1024);
        let renderer = {
            let cfg = cfg.clone();
            tokio::task::spawn_blocking(move || render::Renderer::new(&cfg))
                .await
                .context("the scene renderer's thread failed")?
                .context("cannot render the scene the display shows")?
        };
        let mut engine = Engine::new(&cfg, renderer.input())
            .map_err(anyhow::Error::msg)
            .context("cannot start the scheduler")?;
        let network_missing = renderer.network_missing();
        if cfg.method.0 == dioptra_sched::RenderMethod::Network {
            if let Some((_, why)) = network_missing.iter().find(|(m, _)| *m == cfg.mode) {
                anyhow::bail!("method = \"network\" in {} mode: {why}", cfg.mode.as_str());
            }
        }
        engine.set_network_missing(network_missing);
        let sink: Box<dyn DisplaySink> = match (sink, cfg.display.kind) {
            (Some(s), _) => s,
            (None, config::SinkKind::Headless) => Box::new(HeadlessSink::new(
                cfg.display.png_every,
                cfg.display.png_dir.clone(),
            )?),
            (None, config::SinkKind::Window) => anyhow::bail!(
                "display.kind = \"window\": the window is opened by `dioptra serve` on the main \
                 thread and its sink handed to the daemon"
            ),
        };
        let shared = Arc::new(Shared {
            registry: registry.clone(),
            status: Mutex::new(LoopStatus {
                display: sink.status(),
                ..Default::default()
            }),
            sims: std::sync::OnceLock::new(),
            stream,
            recording: Mutex::new(None),
            cancel: cancel.clone(),
            clock: clock.clone(),
            controls: controls_tx,
            started: clock.now(),
            cfg,
        });
        if shared.cfg.recording.as_ref().is_some_and(|r| r.start) {
            shared
                .start_recording(true)
                .map_err(|e| anyhow::anyhow!("cannot start recording: {}", e.message()))?;
        }
        let (dev_tx, dev_rx) = mpsc::channel(4096);
        let (sims, links, dtasks) =
            devices::spawn_devices(&shared.cfg, &registry, clock.clone(), dev_tx, &cancel)?;
        let _ = shared.sims.set(sims);
        let looper = tokio::spawn(run_loop(
            shared.clone(),
            engine,
            Arc::new(renderer),
            sink,
            links,
            dev_rx,
            controls_rx,
        ));
        let app = api::router(shared.clone());
        let c = cancel.clone();
        let (listening, server) = match listen {
            Listen::Tcp(addr) => {
                let l = tokio::net::TcpListener::bind(addr).await.with_context(|| {
                    format!("cannot listen on {addr} (api.listen); is another daemon running?")
                })?;
                let addr = l.local_addr()?;
                let server = tokio::spawn(async move {
                    axum::serve(l, app)
                        .with_graceful_shutdown(async move { c.cancelled().await })
                        .await
                });
                (Listening::Tcp(addr), server)
            }
            Listen::Unix(path) => {
                let l = bind_unix(&path)?;
                let server = tokio::spawn(async move {
                    axum::serve(l, app)
                        .with_graceful_shutdown(async move { c.cancelled().await })
                        .await
                });
                (Listening::Unix(path), server)
            }
        };
        Ok(Daemon {
            shared,
            listening,
            lens: dtasks.lens,
            tasks: dtasks.others,
            server,
            looper,
        })
    }

    pub fn listening(&self) -> &Listening {
        &self.listening
    }
    pub fn shared(&self) -> &Arc<Shared> {
        &self.shared
    }
    pub fn cancel_token(&self) -> CancellationToken {
        self.shared.cancel.clone()
    }

    /// Waits until the daemon is told to stop, then parks the lens, stops every task and
    /// finishes the recording.
    pub async fn wait(self) -> ShutdownReport {
        let Daemon {
            shared,
            lens,
            tasks,
            server,
            looper,
            listening,
            ..
        } = self;
        shared.cancel.cancelled().await;
        let mut task_errors = Vec::new();
        let park = match lens.await {
            Ok(p) => Some(p),
            Err(e) => {
                task_errors.push(format!("the lens task failed: {e}"));
                None
            }
        };
        for t in tasks {
            if let Err(e) = t.await {
                task_errors.push(format!("a device task failed: {e}"));
            }
        }
        if let Err(e) = looper.await {
            task_errors.push(format!("the loop task failed: {e}"));
        }
        match tokio::time::timeout(Duration::from_secs(5), server).await {
            Ok(Ok(Ok(()))) => {}
            Ok(Ok(Err(e))) => task_errors.push(format!("the API server failed: {e}")),
            Ok(Err(e)) => task_errors.push(format!("the API server task failed: {e}")),
            Err(_) => task_errors.push("the API server did not stop within 5 s".into()),
        }
        if let Listening::Unix(p) = &listening {
            let _ = std::fs::remove_file(p);
        }
        let rec = lock(&shared.recording).take();
        let recording = match rec {
            Some(r) => Some(r.finish().await.map_err(|e| e.to_string())),
            None => None,
        };
        ShutdownReport {
            park,
            recording,
            task_errors,
        }
    }
}

/// Binds a Unix socket readable and writable by its owner only.
fn bind_unix(path: &std::path::Path) -> Result<tokio::net::UnixListener> {
    use std::os::unix::fs::{FileTypeExt, PermissionsExt};
    if let Ok(meta) = std::fs::symlink_metadata(path) {
        if meta.file_type().is_socket() {
            // A stale socket of a daemon that did not clean up.
            std::fs::remove_file(path)
                .with_context(|| format!("cannot remove the stale socket {}", path.display()))?;
        } else {
            anyhow::bail!(
                "{} exists and is not a socket; choose another api.unix path",
                path.display()
            );
        }
    }
    let l = tokio::net::UnixListener::bind(path)
        .with_context(|| format!("cannot listen on {} (api.unix)", path.display()))?;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600))
        .with_context(|| format!("cannot make {} private (0600)", path.display()))?;
    Ok(l)
}

/// A finished render.
struct Rendered {
    frame: u64,
    method: Method,
    focus: Option<Diopters>,
    requested: Timestamp,
    result: Result<render::RenderedFrame, String>,
    took: Duration,
}

/// Finished frames kept for the scheduler to present (it shows the newest ready one).
const FRAMES_KEPT: usize = 4;

/// The loop: feeds device inputs, API commands, finished renders and timers to the
/// scheduler (through [`Engine`]), records each input before it is given and each command as
/// it comes out, and carries the commands out.
async fn run_loop(
    shared: Arc<Shared>,
    mut engine: Engine,
    renderer: Arc<render::Renderer>,
    sink: Box<dyn DisplaySink>,
    links: devices::DeviceLinks,
    mut inputs: mpsc::Receiver<DeviceInput>,
    mut controls: mpsc::Receiver<ControlMsg>,
) {
    let cancel = shared.cancel.clone();
    let clock = shared.clock.clone();
    let (done_tx, mut done_rx) = mpsc::channel::<Rendered>(4);
    let mut ex = Executor {
        shared: &shared,
        links: &links,
        renderer: &renderer,
        done_tx: &done_tx,
        sink,
        frames: std::collections::VecDeque::new(),
        rendering: false,
        pending: None,
    };
    ex.sync_status(&engine);
    let now = clock.now();
    shared.record(now, Rec::Depth(Marker {}));
    let cmds = engine.step(now, Input::Depth).unwrap_or_default();
    ex.execute(now, cmds);
    loop {
        let wake = engine.next_wakeup();
        let sleep = wake.map_or(Duration::from_secs(3600), |t| {
            t.saturating_since(clock.now())
        });
        let now;
        let cmds = tokio::select! {
            biased;
            _ = cancel.cancelled() => break,
            Some(msg) = controls.recv() => {
                now = clock.now();
                let cmd = msg.cmd;
                match engine.step(now, Input::Control(cmd.clone())) {
                    Ok(cmds) => {
                        // Recorded only when applied: a refused command changed nothing.
                        shared.record(now, Rec::Control(cmd.rec()));
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
                match ex.finished(done, now) {
                    Some(input) => engine.step(now, input).unwrap_or_default(),
                    None => continue,
                }
            }
            Some(input) = inputs.recv() => {
                now = clock.now();
                ex.device_input(&input, now);
                engine.step(now, Input::Device(input)).unwrap_or_default()
            }
            _ = tokio::time::sleep(sleep), if wake.is_some() => {
                now = clock.now();
                shared.record(now, Rec::Tick(Marker {}));
                engine.step(now, Input::Tick).unwrap_or_default()
            }
        };
        ex.execute(now, cmds);
        lock(&shared.status).scheduler = engine.status();
    }
    // The scheduler's own shutdown: park command (and sequencer stop), recorded and sent; the
    // lens and sync tasks also park and stop on the same token, whatever happens here.
    let now = clock.now();
    shared.record(now, Rec::Shutdown(Marker {}));
    let cmds = engine.step(now, Input::Shutdown).unwrap_or_default();
    ex.execute(now, cmds);
    lock(&shared.status).scheduler = engine.status();
}

/// Carries out the scheduler's commands.
struct Executor<'a> {
    shared: &'a Arc<Shared>,
    links: &'a devices::DeviceLinks,
    renderer: &'a Arc<render::Renderer>,
    done_tx: &'a mpsc::Sender<Rendered>,
    sink: Box<dyn DisplaySink>,
    frames: std::collections::VecDeque<Frame>,
    rendering: bool,
    /// A render asked for while another was still running.
    pending: Option<RenderJob>,
}

/// A render to do.
struct RenderJob {
    frame: u64,
    mode: Mode,
    method: Method,
    focus: Option<Diopters>,
    /// Gaze point on the frame, pixels (for `method = "auto"`).
    gaze: Option<[f32; 2]>,
    requested: Timestamp,
}

impl Executor<'_> {
    fn sync_status(&self, engine: &Engine) {
        let mut st = lock(&self.shared.status);
        st.mode = Some(engine.mode());
        st.method = Some(engine.method());
        st.manual_focus_d = engine.scheduler().status().manual_focus.map(|d| d.0);
        st.display = self.sink.status();
    }

    fn device_input(&mut self, input: &DeviceInput, now: Timestamp) {
        let sh = self.shared;
        match input {
            DeviceInput::Gaze(g) => {
                sh.record(now, Rec::Gaze(g.into()));
                lock(&sh.status).gaze_samples += 1;
                sh.publish(json!({
                    "type": "gaze",
                    "host_ns": g.host_time.0,
                    "left": { "direction": g.left.direction, "valid": g.left.valid },
                    "right": { "direction": g.right.direction, "valid": g.right.valid },
                }));
            }
            DeviceInput::LensState(s) => {
                sh.record(now, Rec::LensState(s.into()));
                lock(&sh.status).lens_power_d = Some(s.power.0);
                sh.publish(
                    json!({ "type": "lens", "host_ns": s.host_time.0, "power_d": s.power.0 }),
                );
            }
            DeviceInput::LensWire {
                id,
                requested,
                wire_time,
            } => sh.record(
                now,
                Rec::LensWire(LensWireRec {
                    id: *id,
                    requested_d: requested.0,
                    wire_ns: wire_time.0,
                }),
            ),
            DeviceInput::LensLink(up) => sh.record(now, Rec::LensLink(LensLinkRec { up: *up })),
            DeviceInput::Sync(e) => {
                sh.record(now, Rec::Sync(e.into()));
                lock(&sh.status).sync_events += 1;
            }
        }
    }

    fn execute(&mut self, now: Timestamp, cmds: Vec<Command>) {
        let sh = self.shared;
        for c in cmds {
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
                    let _ = self.links.lens_commands.send(Some((id.0, power)));
                    {
                        let mut st = lock(&sh.status);
                        st.commanded_focus_d = Some(power.0);
                        st.lens_commands += 1;
                    }
                    sh.publish(json!({
                        "type": "focus",
                        "host_ns": now.0,
                        "commanded_d": power.0,
                        "reason": engine::reason_name(reason),
                    }));
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
                        focus: req.focus,
                        gaze,
                        requested: now,
                    };
                    if self.rendering {
                        // A render the scheduler no longer waits for (it was asked before a
                        // mode change) is still running: this one starts when it is done.
                        if let Some(old) = self.pending.replace(job) {
                            tracing::warn!(
                                frame = old.frame,
                                "render request replaced before it started"
                            );
                        }
                    } else {
                        self.start_render(job);
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
                    tracing::warn!(command = ?other, "scheduler command this daemon does not know; ignored")
                }
            }
        }
    }

    fn start_render(&mut self, job: RenderJob) {
        self.rendering = true;
        let focus = job
            .focus
            .unwrap_or(Diopters(self.shared.cfg.devices.lens.park_power));
        let (renderer, tx) = (self.renderer.clone(), self.done_tx.clone());
        tokio::task::spawn_blocking(move || {
            let t0 = std::time::Instant::now();
            let result = renderer
                .render(job.mode, job.method, focus, job.gaze)
                .map_err(|e| e.to_string());
            let _ = tx.blocking_send(Rendered {
                frame: job.frame,
                method: job.method,
                focus: job.focus,
                requested: job.requested,
                result,
                took: t0.elapsed(),
            });
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
        let sh = self.shared;
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
            Ok(t) => sh.publish(json!({
                "type": "frame",
                "frame": frame,
                "layer": layer,
                "focus_d": f.focus.0,
                "shown_ns": t.0,
                "repeat": repeat,
            })),
            Err(e) => tracing::warn!(error = %e, "display failed"),
        }
        let mut st = lock(&sh.status);
        st.frames_shown = self.sink.shown();
        st.display = self.sink.status();
    }

    /// A render came back: keeps its frame and returns the scheduler's input for it.
    fn finished(&mut self, done: Rendered, now: Timestamp) -> Option<Input> {
        self.rendering = false;
        if let Some(job) = self.pending.take() {
            self.start_render(job);
        }
        let sh = self.shared;
        lock(&sh.status).last_render_ms = Some(done.took.as_secs_f64() * 1e3);
        match done.result {
            Ok(rendered) => {
                if rendered.planned.is_some() {
                    lock(&sh.status).planned = rendered.planned;
                }
                let layers = rendered.images;
                if self.frames.len() == FRAMES_KEPT {
                    self.frames.pop_front();
                }
                self.frames.push_back(Frame {
                    number: done.frame,
                    layers: Arc::new(layers),
                    focus: done
                        .focus
                        .unwrap_or(Diopters(sh.cfg.devices.lens.park_power)),
                });
            }
            Err(e) => {
                // The scheduler is told all the same: the slot is free again, and the frame,
                // never stored, is never shown.
                tracing::warn!(frame = done.frame, error = %e, "render failed");
                lock(&sh.status).render_errors += 1;
            }
        }
        let render_ns = u64::try_from(done.took.as_nanos()).unwrap_or(u64::MAX);
        sh.record(
            now,
            Rec::Frame(FrameRec {
                frame: done.frame,
                method: done.method.as_str().into(),
                render_ns,
                requested_ns: done.requested.0,
                focus_d: done.focus.map(|d| d.0),
            }),
        );
        Some(Input::RenderFinished {
            frame: done.frame,
            method: done.method,
            render_time: Duration::from_nanos(render_ns),
        })
    }
}

#[cfg(test)]
mod tests;
