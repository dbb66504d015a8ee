//! dioptra-rig: the running rig. One implementation that `dioptra serve`, `dioptra hil`, the
//! demo, `dioptra eval --suite loop` and the whole-loop tests all run, so the figures they
//! publish describe the code that drives a rig.
//!
//! - [`config`]: the rig config (`rig.toml`), composed of the sections each part owns in its
//!   own `config` module (type, defaults, checks): [`devices::config`], [`optics::config`],
//!   [`display::config`], [`content::config`], [`render::config`], [`recording::config`],
//!   [`lsl::config`], [`api`]; `mode` and `method` in [`mode`].
//! - [`devices`]: one task per device (lens, gaze, sync), opened through the drivers' table
//!   ([`devices::open`]), with one policy for lost links and backoff.
//! - [`executor`]: the loop that steps the scheduler ([`engine`]) and carries out its commands;
//!   [`executor::LoopHook`]s see what it does: the recording, `/status`, the WebSocket and LSL
//!   among them ([`observers`]).
//! - [`state`]: what the loop, the API and the device tasks share ([`RigState`]): the config
//!   and each part's handle ([`devices::DevicesHandle`], [`content::ContentHandle`],
//!   [`render::RenderHandle`], [`display::DisplayHandle`], [`optics::OpticsHandle`],
//!   [`recording::RecordingHandle`], [`lsl::LslOutlets`]), through which the part publishes
//!   its status; `/status` composes them, with `problems`: what is wrong now, each entry
//!   naming its part and the config key to look at ([`problem::Problem`]).
//! - [`content`]: what the rig shows ([`content::Content`]: the procedural scene, a lab's
//!   files, a stream), apart from how it is rendered; the loop hears of each frame when it
//!   arrives.
//! - [`render`]: the render worker's [`render::Renderer`], which renders a job from a content
//!   frame ([`render::rgbd::RgbdRenderer`], the rig's own).
//! - [`display`]: where frames go ([`display::DisplaySink`]; headless here, the window in the
//!   binary, which draws with [`display::blit`]), and the marker patch a photodiode watches.
//! - [`photons`]: latency measured in photons (`dioptra hil`): a photodiode's edges matched to
//!   the presents that toggled the marker patch.
//! - [`recording`]: MCAP recordings.
//! - [`devices::simulators`]: the simulated devices of `port = "sim"`; `simulated_rig`
//!   (feature `simulated`): a whole rig on simulated devices and tokio's paused clock,
//!   recording ground truth.
//!
//! No module imports one above it. The layers, lowest first (`crates/rig/LAYERS`, checked by
//! `scripts/check_layers.py` in CI): the vocabulary (the config's error, [`problem`],
//! [`mode`]); each part's config section; [`config`], which composes them; what the parts hand
//! each other (device inputs, content frames, render jobs, display frames, recordings); the
//! parts at work, each with the handle through which it publishes its status (its `status`
//! module: [`devices`], [`content`], [`render`], [`display`], [`optics`], [`lsl`]), and the
//! scheduler's adapter ([`engine`]); [`state`], which holds the handles and composes `/status`
//! and its `problems`; the loop ([`executor`]); what watches it ([`observers`], [`photons`],
//! which hand each part what the loop saw); this crate root, which
//! starts and stops a rig ([`Rig`]); and above it the simulated rig and the tests that start a
//! whole rig. A part's `mod.rs` (or parent file) sits on top of its own children: it declares,
//! re-exports and builds on them, and they never import it.
//!
//! Everything stops through one [`CancellationToken`] ([`RigState::cancel`]): the loop carries
//! out the scheduler's shutdown (its park command), then the device tasks stop (the lens task
//! parks the lens and waits for it, the sync task stops the sequence), and [`Rig::wait`]
//! finishes the recording.

pub mod api;
pub mod config;
pub mod content;
pub mod devices;
pub mod display;
pub mod engine;
pub mod executor;
pub mod lsl;
pub mod mode;
pub mod observers;
pub mod optics;
pub mod photons;
pub mod problem;
pub mod recording;
pub mod render;
#[cfg(feature = "simulated")]
pub mod simulated_rig;
pub mod state;

use std::sync::{Arc, Mutex};

use dioptra_core::{Clock, Timestamp};
use dioptra_sched::SchedulerConfig;
use serde::Serialize;
use thiserror::Error;
use tokio::sync::{broadcast, mpsc};
use tokio_util::sync::CancellationToken;

use config::{ConfigError, RigConfig};
use content::Content;
use content::ContentHandle;
use devices::simulators::SimSpec;
use devices::DevicesHandle;
use devices::{DeviceInput, DeviceSettings, ParkReport, Registry};
use display::DisplayHandle;
use display::{DisplaySink, HeadlessSink};
use engine::Engine;
use executor::LoopHook;
use optics::OpticsHandle;
use recording::RecordingHandle;
use recording::RecordingStats;
use render::RenderHandle;
use render::Renderer;
use state::wall_ns;

/// Why a rig did not start.
#[derive(Debug, Error)]
pub enum RigError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Content(#[from] content::ContentError),
    #[error("cannot start the renderer: {0}")]
    Renderer(#[source] dioptra_render::RenderError),
    #[error("cannot start the scheduler: {0}")]
    Scheduler(String),
    #[error("method = \"{method}\" in {mode} mode: {why}")]
    NetworkMissing {
        method: &'static str,
        mode: &'static str,
        why: String,
    },
    #[error("cannot start the devices: {0}")]
    Devices(#[source] dioptra_core::DeviceError),
    #[error("the display: {0}")]
    Display(#[source] display::DisplayError),
    #[error("cannot start recording: {0}")]
    Recording(#[source] ControlError),
    #[error("display.kind = \"window\": the window is opened on the main thread by the binary and its sink handed to the rig")]
    WindowSinkNeeded,
    #[error("a rig task failed to start: {0}")]
    Task(String),
    #[error("[lsl] enabled = true: {0}")]
    Lsl(String),
}

pub use engine::Control;
pub use problem::Problem;
pub use render::RenderErrorNote;
pub use state::{
    lens_settled, ControlError, LoopStatus, RecordingMeta, RigClock, RigState, SUBFRAME_TOLERANCE_D,
};

/// What a rig is made of. [`RigSetup::new`] is a rig as its config describes it (what `dioptra
/// serve` runs); the simulated-rig builder and `dioptra hil` change only what they name.
pub struct RigSetup {
    pub cfg: RigConfig,
    /// The rig's clock (default tokio's: wall time, or simulated time under a paused runtime).
    pub clock: Option<Arc<dyn Clock>>,
    /// Default: the content `[content]` describes (the procedural scene of
    /// `display.scene_seed` without one).
    pub content: Option<Arc<dyn Content>>,
    /// Default: [`render::rgbd::RgbdRenderer`] of the config.
    pub renderer: Option<Arc<dyn Renderer>>,
    /// Default: the headless sink (`display.kind = "window"` needs the binary's window sink).
    pub sink: Option<Box<dyn DisplaySink>>,
    /// Default: [`SimSpec::from_config`].
    pub sim: Option<SimSpec>,
    /// Default: [`engine::sched_config`] of the config.
    pub scheduler: Option<SchedulerConfig>,
    pub hooks: Vec<Box<dyn LoopHook>>,
    /// The clock is simulated (a paused runtime): its times have no wall-clock anchor.
    pub simulated_time: bool,
    /// Default: liblsl's outlets when `[lsl] enabled = true` (tests hand in
    /// [`lsl::LslOutlets::to_channel`]).
    pub lsl: Option<lsl::LslOutlets>,
}

impl RigSetup {
    pub fn new(cfg: RigConfig) -> RigSetup {
        RigSetup {
            cfg,
            clock: None,
            content: None,
            renderer: None,
            sink: None,
            sim: None,
            scheduler: None,
            hooks: Vec::new(),
            simulated_time: false,
            lsl: None,
        }
    }
}

/// How the rig stopped.
#[derive(Debug, Clone, Serialize)]
pub struct ShutdownReport {
    /// The one lens, or the left eye's.
    pub park: Option<ParkReport>,
    /// The right eye's lens, on a rig with a lens per eye.
    pub park_right: Option<ParkReport>,
    /// Whether the rig has a lens per eye (then `park_right` must report too).
    pub lens_per_eye: bool,
    pub recording: Option<Result<RecordingStats, String>>,
    pub task_errors: Vec<String>,
}

impl ShutdownReport {
    pub fn problems(&self) -> Vec<String> {
        let mut p = self.task_errors.clone();
        for (name, park) in self.parks() {
            match park {
                Some(ParkReport { error: Some(e), .. }) => p.push(format!("{name}: {e}")),
                None => p.push(format!("the {name} task did not report")),
                _ => {}
            }
        }
        if let Some(Err(e)) = &self.recording {
            p.push(e.clone());
        }
        p
    }
    pub fn ok(&self) -> bool {
        self.problems().is_empty()
    }
    /// Each lens's park report, by name (`lens`, or `left lens` and `right lens`).
    fn parks(&self) -> Vec<(&'static str, &Option<ParkReport>)> {
        if self.lens_per_eye {
            vec![("left lens", &self.park), ("right lens", &self.park_right)]
        } else {
            vec![("lens", &self.park)]
        }
    }

    pub fn summary(&self) -> String {
        let parks: Vec<String> = self
            .parks()
            .into_iter()
            .map(|(name, park)| match park {
                Some(ParkReport {
                    park_power,
                    reported_power: Some(r),
                    error: None,
                }) => format!("{name} parked at {park_power} D (reports {r:.3} D)"),
                Some(ParkReport { error: Some(e), .. }) => format!("{name}: {e}"),
                _ => format!("{name}: no report"),
            })
            .collect();
        let mut s = parks.join("; ");
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

/// A running rig.
pub struct Rig {
    state: Arc<RigState>,
    /// Each lens task's park report, in lens order.
    lens: tokio::task::JoinHandle<Vec<Result<ParkReport, tokio::task::JoinError>>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    looper: tokio::task::JoinHandle<()>,
    devices_stop: CancellationToken,
}

/// Device inputs the loop has not taken yet; beyond this a gaze task waits.
const INPUT_QUEUE: usize = 4096;

impl Rig {
    /// Validates the config, makes the renderer (in a blocking thread: the scene is ray cast),
    /// and starts the device tasks and the loop. Needs a tokio runtime.
    pub async fn start(setup: RigSetup) -> Result<Rig, RigError> {
        let RigSetup {
            cfg,
            clock,
            content,
            renderer,
            sink,
            sim,
            scheduler,
            hooks,
            simulated_time,
            lsl,
        } = setup;
        cfg.validate()?;
        let cfg = Arc::new(cfg);
        let clock: Arc<dyn Clock> =
            clock.unwrap_or_else(|| Arc::new(dioptra_sim::tokio_clock::TokioClock::new()));
        let lsl = match lsl {
            Some(l) => Some(l),
            None if cfg.lsl.enabled && simulated_time => {
                return Err(RigError::Lsl(
                    "this run is on simulated time, which LSL's clock cannot follow; LSL \
                     outlets run with `dioptra serve`"
                        .into(),
                ))
            }
            None if cfg.lsl.enabled => Some(
                lsl::LslOutlets::start(&cfg.lsl, &cfg.devices, clock.clone())
                    .map_err(RigError::Lsl)?,
            ),
            None => None,
        };
        let content: Arc<dyn Content> = match content {
            Some(c) => c,
            None => {
                let c = cfg.clone();
                let pacing = if simulated_time {
                    content::scene::Pacing::Simulated
                } else {
                    content::scene::Pacing::RealTime
                };
                tokio::task::spawn_blocking(move || {
                    content::open(&c.content, &c.display, &c.eye, &c.api, pacing)
                })
                .await
                .map_err(|e| RigError::Task(e.to_string()))??
            }
        };
        let renderer: Arc<dyn Renderer> = match renderer {
            Some(r) => r,
            None => {
                let c = cfg.clone();
                let r = tokio::task::spawn_blocking(move || {
                    render::rgbd::RgbdRenderer::new(&c.render, &c.eye, &c.display, &c.optics)
                })
                .await
                .map_err(|e| RigError::Task(e.to_string()))?
                .map_err(RigError::Renderer)?;
                Arc::new(r)
            }
        };
        let mut engine = match scheduler {
            Some(s) => Engine::with_config(s),
            None => Engine::new(&cfg),
        }
        .map_err(RigError::Scheduler)?;
        let network_missing = renderer.network_missing();
        if let Some((_, _, why)) = network_missing
            .iter()
            .find(|(m, r, _)| *m == cfg.mode && *r == cfg.method.0)
        {
            return Err(RigError::NetworkMissing {
                method: cfg.method.as_str(),
                mode: cfg.mode.as_str(),
                why: why.clone(),
            });
        }
        engine.set_network_missing(network_missing);
        let sink: Box<dyn DisplaySink> = match (sink, cfg.display.kind) {
            (Some(s), _) => s,
            (None, config::SinkKind::Headless) => {
                Box::new(HeadlessSink::for_display(&cfg.display).map_err(RigError::Display)?)
            }
            (None, config::SinkKind::Window) => return Err(RigError::WindowSinkNeeded),
        };
        let spec = match sim {
            Some(s) => s,
            None => SimSpec::from_config(&cfg, engine.scheduler().config().display.latency)?,
        };
        let settings = DeviceSettings::from_config(&cfg.devices);
        let (controls_tx, controls_rx) = mpsc::channel(64);
        let (websocket, _) = broadcast::channel(1024);
        let registry = Arc::new(Registry::default());
        let sched = engine.scheduler().config();
        let maps = std::iter::once(sched.optics.clone())
            .chain(sched.right_lens.as_ref().map(|r| r.optics.clone()))
            .collect();
        let eye_views = match cfg.display.stereo() {
            true => Some(Arc::new(
                content::stereo::EyeViews::new(&cfg.eye, &cfg.display)
                    .map_err(RigError::Renderer)?,
            )),
            false => None,
        };
        let state = Arc::new(RigState {
            devices: DevicesHandle::new(cfg.devices.clone(), registry.clone(), settings),
            content: ContentHandle::new(content.clone(), eye_views),
            render: RenderHandle::new(renderer.clone(), cfg.auto_method),
            display: DisplayHandle::new(sink.status()),
            optics: OpticsHandle::new(maps, cfg.optics.lens_range, cfg.devices.lens.clone()),
            recording: RecordingHandle::default(),
            lsl,
            loop_status: Mutex::new(LoopStatus::default()),
            clock: RigClock {
                wall_zero_ns: (!simulated_time).then(|| wall_ns().saturating_sub(clock.now().0)),
                source: if simulated_time {
                    "simulated time (tokio's paused clock), from the run's start"
                } else {
                    "the host's monotonic clock (CLOCK_MONOTONIC, through tokio), from daemon start"
                },
                clock: clock.clone(),
                started: clock.now(),
            },
            websocket,
            cancel: CancellationToken::new(),
            controls: controls_tx,
            cfg: cfg.clone(),
        });
        if cfg.recording.as_ref().is_some_and(|r| r.start) {
            state.start_recording(true).map_err(RigError::Recording)?;
        }
        let (dev_tx, dev_rx) = mpsc::channel::<DeviceInput>(INPUT_QUEUE);
        let devices_stop = CancellationToken::new();
        let (sims, links, dtasks) = devices::spawn_devices(
            &cfg,
            &spec,
            settings,
            &registry,
            clock,
            dev_tx,
            &devices_stop,
        )
        .map_err(RigError::Devices)?;
        state.devices.set_sims(sims);
        let panel_feed = spec
            .panel
            .clone()
            .map(|p| Box::new(observers::PanelFeed(p)) as Box<dyn LoopHook>);
        let looper = tokio::spawn(executor::run_loop(executor::LoopParts {
            state: state.clone(),
            engine,
            content,
            renderer,
            sink,
            links,
            inputs: dev_rx,
            controls: controls_rx,
            hooks: observers::standard(&state)
                .into_iter()
                .chain(panel_feed)
                .chain(hooks)
                .collect(),
            devices_stop: devices_stop.clone(),
        }));
        let (lens_tasks, parked) = (dtasks.lenses, state.devices.lens_parked().clone());
        let lens = tokio::spawn(async move {
            let mut reports = Vec::new();
            for t in lens_tasks {
                reports.push(t.await);
            }
            parked.cancel();
            reports
        });
        Ok(Rig {
            state,
            lens,
            tasks: dtasks.others,
            looper,
            devices_stop,
        })
    }

    pub fn state(&self) -> &Arc<RigState> {
        &self.state
    }

    /// Waits until the rig is told to stop ([`RigState::cancel`]), then lets the loop carry
    /// out the scheduler's shutdown, parks the lens, stops every device task and finishes
    /// the recording.
    pub async fn wait(self) -> ShutdownReport {
        let Rig {
            state,
            lens,
            tasks,
            looper,
            devices_stop,
        } = self;
        state.cancel.cancelled().await;
        let mut task_errors = Vec::new();
        if let Err(e) = looper.await {
            task_errors.push(format!("the loop task failed: {e}"));
        }
        // Normally the loop did this after its shutdown step.
        devices_stop.cancel();
        let mut parks = match lens.await {
            Ok(reports) => reports
                .into_iter()
                .map(|r| {
                    r.map_err(|e| task_errors.push(format!("a lens task failed: {e}")))
                        .ok()
                })
                .collect(),
            Err(e) => {
                task_errors.push(format!("the lens tasks failed: {e}"));
                Vec::new()
            }
        }
        .into_iter();
        let park = parks.next().flatten();
        let park_right = parks.next().flatten();
        for t in tasks {
            if let Err(e) = t.await {
                task_errors.push(format!("a device task failed: {e}"));
            }
        }
        let rec = state.recording.current().take();
        let recording = match rec {
            Some(r) => Some(r.finish().await.map_err(|e| e.to_string())),
            None => None,
        };
        ShutdownReport {
            park,
            park_right,
            lens_per_eye: state.cfg.devices.lens.count() > 1,
            recording,
            task_errors,
        }
    }
}

/// Waits on `clock` until `t` (tokio's timer; simulated under a paused runtime).
pub async fn sleep_until(clock: &dyn Clock, t: Timestamp) {
    tokio::time::sleep(t.saturating_since(clock.now())).await;
}
