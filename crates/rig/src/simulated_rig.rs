//! A whole rig on simulated devices, through [`Rig::start`] as `dioptra serve` starts it: the
//! same device tasks, loop and render worker, with every device a dioptra-sim simulator on an
//! in-memory link. Run it inside a tokio runtime with paused time (`#[tokio::test(start_paused
//! = true)]`, or [`SimRun::run_paused`]) and it runs as fast as the host computes it, in
//! simulated time: a frame's render counts the time its [`Renderer`] says, or the wall time
//! it really took. What it shows is a [`Content`] of its own (the config's by default).
//!
//! Ground truth is recorded beside what the rig did: the gaze generator's true eye movements,
//! and, every [`SimRun::probe`], where the simulated lens really is.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant as WallInstant};

use dioptra_core::{lock, Clock, Diopters, RgbImage, Timestamp};
use dioptra_render::RenderError;
use dioptra_sched::processing::EyePhase;
use dioptra_sched::{Command, CommandId, FocusReason, FrameRequest, LinkStatus, SchedulerConfig};
use dioptra_sim::gaze::generator::TruthSample;

use crate::config::{ConfigError, RigConfig};
use crate::content::{Content, ContentFrame};
use crate::devices::config::{GazeDriver, Port};
use crate::devices::simulators::{SimDevices, SimSpec};
use crate::devices::{DeviceInput, LensId};
use crate::display::DisplaySink;
use crate::engine::{sched_config, Engine};
use crate::executor::LoopHook;
use crate::mode::Mode;
use crate::render::{RenderJob, RenderOutput, Renderer};
use crate::{Control, Rig, RigError, RigSetup, RigState, ShutdownReport};

/// Something scripted to happen during a run, at a time after its start.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Action {
    /// Pulls the lens cable (the one lens, or the left eye's): the link breaks and the device
    /// cannot be reopened until [`Action::ReplugLens`].
    UnplugLens,
    ReplugLens,
    /// The same for one lens of a rig with a lens per eye.
    UnplugLensOf(LensId),
    ReplugLensOf(LensId),
    ManualFocus(Option<Diopters>),
    /// Holds the marker patch black (true) or lets it toggle again (false).
    HoldMarker(bool),
}

/// What to run.
pub struct SimRun {
    pub cfg: RigConfig,
    /// The simulators (from the config; a run may script the gaze or inject faults).
    pub spec: SimSpec,
    /// The scheduler's settings (from the config).
    pub sched: SchedulerConfig,
    /// Ground truth is sampled this often (`None`: not at all).
    pub probe: Option<Duration>,
    /// Simulated time until the rig is told to stop.
    pub duration: Duration,
    /// Simulated time after the rig stopped before the last probe (the lens has parked).
    pub after_shutdown: Duration,
    pub actions: Vec<(Duration, Action)>,
    /// Loop hooks of the test's own (e.g. [`crate::photons::PhotonRecorder`]).
    pub hooks: Vec<Box<dyn LoopHook>>,
}

impl SimRun {
    /// `cfg` run for `duration` of simulated time. Every device must be simulated.
    pub fn new(cfg: RigConfig, duration: Duration) -> Result<SimRun, RigError> {
        cfg.validate()?;
        let d = &cfg.devices;
        let lens_keys: Vec<String> = (0..d.lens.count())
            .map(|i| format!("{}.port", d.lens.key(i)))
            .collect();
        let ports = d
            .lens
            .each()
            .into_iter()
            .zip(&lens_keys)
            .map(|(l, k)| (k.as_str(), Some(&l.port)))
            .chain([
                ("devices.gaze.port", Some(&d.gaze.port)),
                ("devices.sync.port", d.sync.as_ref().map(|s| &s.port)),
                (
                    "devices.photodiode.port",
                    d.photodiode.as_ref().and_then(|p| p.port.as_ref()),
                ),
            ]);
        for (key, port) in ports {
            if let Some(p) = port.filter(|p| **p != Port::Sim) {
                return Err(RigError::Config(ConfigError::Invalid {
                    key: key.into(),
                    message: format!(
                        "{p}: a simulated run needs every device simulated (port = \"sim\")"
                    ),
                }));
            }
        }
        if d.gaze.driver == GazeDriver::Pupil {
            // Its simulator is reached over real sockets, which a paused clock would outrun.
            return Err(RigError::Config(ConfigError::Invalid {
                key: "devices.gaze.driver".into(),
                message: "pupil: the simulated Pupil Capture runs on real loopback sockets and real time; a simulated-time run needs dioptra-tracker or hid (run the pupil rig with `dioptra serve`)".into(),
            }));
        }
        let sched = sched_config(&cfg).map_err(RigError::Scheduler)?;
        let mut spec = SimSpec::from_config(&cfg, sched.display.latency)?;
        spec.record_gaze_truth = true;
        Ok(SimRun {
            cfg,
            spec,
            sched,
            probe: Some(Duration::from_millis(1)),
            duration,
            after_shutdown: Duration::from_millis(200),
            actions: Vec::new(),
            hooks: Vec::new(),
        })
    }

    /// The example rig of simulated devices in `mode`, with the mode's default method.
    pub fn example(mode: Mode, duration: Duration) -> Result<SimRun, RigError> {
        Self::new(example_config(mode)?, duration)
    }

    /// Runs on a new single-threaded runtime with paused time.
    pub fn run_paused(
        self,
        content: Option<Arc<dyn Content>>,
        renderer: Arc<dyn Renderer>,
        sink: Option<Box<dyn DisplaySink>>,
    ) -> Result<Run, RigError> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .start_paused(true)
            .build()
            .map_err(|e| RigError::Task(format!("cannot start a runtime: {e}")))?;
        rt.block_on(self.run(content, renderer, sink))
    }

    /// Starts the rig with `content` (`None`: the config's) rendered by `renderer`, carries
    /// out the actions, stops it after `duration` and returns what it recorded. Needs a tokio
    /// runtime (paused time for a fast, deterministic run).
    pub async fn run(
        self,
        content: Option<Arc<dyn Content>>,
        renderer: Arc<dyn Renderer>,
        sink: Option<Box<dyn DisplaySink>>,
    ) -> Result<Run, RigError> {
        let wall = WallInstant::now();
        let clock: Arc<dyn Clock> = Arc::new(dioptra_sim::tokio_clock::TokioClock::new());
        let start = clock.now();
        let log = Arc::new(Mutex::new(Log::default()));
        let sims = Arc::new(std::sync::OnceLock::<SimDevices>::new());
        let optics = self.spec.optics.clone();
        let hook = TruthRecorder {
            optics: optics.clone(),
            log: log.clone(),
            sims: sims.clone(),
            probe: self.probe,
            next_probe: self.probe.map(|_| start),
            last_gaze_truth: 0,
        };
        let mut setup = RigSetup::new(self.cfg);
        setup.simulated_time = true;
        setup.clock = Some(clock.clone());
        setup.content = content;
        setup.renderer = Some(renderer);
        setup.sink = sink;
        setup.sim = Some(self.spec);
        setup.scheduler = Some(self.sched);
        setup.hooks.push(Box::new(hook));
        setup.hooks.extend(self.hooks);
        let rig = Rig::start(setup).await?;
        let state = rig.state().clone();
        if let Some(s) = state.devices.sims() {
            let _ = sims.set(s.clone());
        }
        let mut actions = self.actions;
        actions.sort_by_key(|a| a.0);
        let script = {
            let (state, clock) = (state.clone(), clock.clone());
            tokio::spawn(async move {
                for (after, action) in actions {
                    crate::sleep_until(clock.as_ref(), start + after).await;
                    act(&state, action).await;
                }
            })
        };
        crate::sleep_until(clock.as_ref(), start + self.duration).await;
        state.cancel.cancel();
        script.abort();
        let report = rig.wait().await;
        tokio::time::sleep(self.after_shutdown).await;
        let now = clock.now();
        let mut log = std::mem::take(&mut *lock(&log));
        let end = log
            .end
            .take()
            .ok_or_else(|| RigError::Task("the rig's loop stopped without its shutdown".into()))?;
        // The last probe: where the lens came to rest after parking.
        if self.probe.is_some() {
            let (lens_power, lens_target) = lens_truth(state.devices.sims(), 0, now).unzip();
            let (lens_power_right, lens_target_right) =
                lens_truth(state.devices.sims(), 1, now).unzip();
            log.probes.push(Probe {
                t: now,
                lens_power,
                eye_focus: lens_power.map(|p| optics.focus_of(p)),
                lens_target,
                lens_power_right,
                lens_target_right,
                predicted: None,
                commanded: end.status.commanded_power,
                commanded_focus: end
                    .status
                    .commanded_power
                    .map(|c| state.optics.of(LensId::FIRST).focus_of(c)),
                gaze_target_d: None,
                vergence_d: None,
                phase: end.status.phase,
            });
        }
        if let Some(t) = state.devices.sims().and_then(|s| s.gaze_truth.as_ref()) {
            log.truth = std::mem::take(&mut *lock(t));
        }
        if let Some(g) = state.devices.registry().snapshot().get("gaze") {
            if g.failures > 0 {
                log.gaze_errors.extend(g.last_error.clone());
            }
        }
        Ok(Run {
            log,
            status: end.status,
            latency: end.latency,
            lens_opened: state
                .devices
                .sims()
                .and_then(|s| s.lenses.first()?.as_ref())
                .map_or(0, |l| l.plug.opened()),
            lenses_opened: state.devices.sims().map_or_else(Vec::new, |s| {
                s.lenses
                    .iter()
                    .map(|l| l.as_ref().map_or(0, |l| l.plug.opened()))
                    .collect()
            }),
            report,
            state,
            simulated: now.saturating_since(start),
            wall: wall.elapsed(),
        })
    }
}

async fn act(state: &RigState, action: Action) {
    let lens_plug = |lens: LensId| {
        state
            .devices
            .sims()
            .and_then(|s| s.lenses.get(lens.index())?.as_ref())
            .map(|l| l.plug.clone())
    };
    match action {
        Action::UnplugLens | Action::UnplugLensOf(_) => {
            let lens = match action {
                Action::UnplugLensOf(l) => l,
                _ => LensId::FIRST,
            };
            if let Some(p) = lens_plug(lens) {
                p.unplug()
            }
        }
        Action::ReplugLens | Action::ReplugLensOf(_) => {
            let lens = match action {
                Action::ReplugLensOf(l) => l,
                _ => LensId::FIRST,
            };
            if let Some(p) = lens_plug(lens) {
                p.replug()
            }
        }
        Action::ManualFocus(f) => {
            if let Err(e) = state.control(Control::ManualFocus(f.map(|d| d.0))).await {
                tracing::warn!(error = %e, "scripted manual focus refused");
            }
        }
        Action::HoldMarker(hold) => state.display.marker().hold_black(hold),
    }
}

/// The example rig of simulated devices in `mode`, with the mode's default method.
pub fn example_config(mode: Mode) -> Result<RigConfig, RigError> {
    let text = crate::config::EXAMPLE_SIM_RIG
        .replace(
            "mode = \"varifocal\"",
            &format!("mode = \"{}\"", mode.as_str()),
        )
        .replace(
            "method = \"gather\"",
            &format!(
                "method = \"{}\"",
                dioptra_sched::RenderMethod::default_for(mode.sched()).as_str()
            ),
        );
    Ok(RigConfig::parse(&text)?)
}

/// Where simulated lens `index` really is at `now`, and the power it heads to.
fn lens_truth(
    sims: Option<&SimDevices>,
    index: usize,
    now: Timestamp,
) -> Option<(Diopters, Diopters)> {
    let lens = sims?.lenses.get(index)?.as_ref()?.lens.as_ref()?.at(now);
    Some((lens.power(), lens.target_power()))
}

/// Ground truth at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Probe {
    pub t: Timestamp,
    /// The simulated lens's true power and the power it heads to (the one lens, or the left
    /// eye's).
    pub lens_power: Option<Diopters>,
    /// Where the eye must focus to see the display sharp at the lens's true power: through
    /// the simulated optics ([`SimSpec::optics`]), the focus a corrected eye would have. The
    /// identity map makes it the lens power.
    pub eye_focus: Option<Diopters>,
    pub lens_target: Option<Diopters>,
    /// The right eye's lens, on a rig with a lens per eye.
    pub lens_power_right: Option<Diopters>,
    pub lens_target_right: Option<Diopters>,
    /// The scheduler's model of the lens.
    pub predicted: Option<Diopters>,
    pub commanded: Option<Diopters>,
    /// The focus the rig's optics map says the command gives (what the rig aimed at).
    pub commanded_focus: Option<Diopters>,
    /// The depth of what the viewer really looks at, and the eyes' vergence, diopters.
    pub gaze_target_d: Option<f64>,
    pub vergence_d: Option<f64>,
    pub phase: EyePhase,
}

/// A lens command as issued.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensCommand {
    pub t: Timestamp,
    /// Which lens (the one lens, or the left eye's, is the first).
    pub lens: LensId,
    pub id: CommandId,
    pub power: Diopters,
    pub reason: FocusReason,
    /// When the driver had it on the wire (`None`: never, e.g. the link was down).
    pub wire: Option<Timestamp>,
}

/// Everything a run recorded.
#[derive(Debug, Default)]
pub struct Log {
    pub lens_commands: Vec<LensCommand>,
    pub presents: Vec<(Timestamp, Command)>,
    pub frames_requested: Vec<(Timestamp, FrameRequest)>,
    pub probes: Vec<Probe>,
    pub truth: Vec<TruthSample>,
    /// Wall-clock host path per lens command a gaze sample caused: from the gaze task
    /// receiving the sample to the lens driver having written the command (the figure `dioptra
    /// hil` reports on hardware).
    pub host_path: Vec<Duration>,
    pub gaze_samples: u64,
    pub sequencer_events: u64,
    /// Each lens link change: when, the new status, and which lens.
    pub link_events: Vec<(Timestamp, LinkStatus, LensId)>,
    /// The gaze device's last error when it was lost during the run.
    pub gaze_errors: Vec<String>,
    end: Option<End>,
}

#[derive(Debug)]
struct End {
    status: dioptra_sched::Status,
    latency: dioptra_sched::Latency,
}

/// The result of [`SimRun::run`].
pub struct Run {
    pub log: Log,
    /// The scheduler's status and latency figures when the rig stopped.
    pub status: dioptra_sched::Status,
    pub latency: dioptra_sched::Latency,
    /// How many links the lens task opened (1 + reconnects): the one lens, or the left eye's.
    pub lens_opened: u32,
    /// The same for each lens.
    pub lenses_opened: Vec<u32>,
    pub report: ShutdownReport,
    pub state: Arc<RigState>,
    /// Simulated time covered, and the wall time it took.
    pub simulated: Duration,
    pub wall: Duration,
}

/// The hook that records the run.
struct TruthRecorder {
    /// The simulated optics: lens power -> where the eye must focus.
    optics: dioptra_core::OpticsMap,
    log: Arc<Mutex<Log>>,
    sims: Arc<std::sync::OnceLock<SimDevices>>,
    probe: Option<Duration>,
    next_probe: Option<Timestamp>,
    /// Truth samples already searched (probes move forward in time).
    last_gaze_truth: usize,
}

impl TruthRecorder {
    fn gaze_truth_at(&mut self, now: Timestamp) -> Option<TruthSample> {
        let truth = self.sims.get()?.gaze_truth.as_ref()?;
        let truth = lock(truth);
        let mut i = self.last_gaze_truth.min(truth.len());
        while i < truth.len() && Timestamp::from_micros(truth[i].time_us) <= now {
            i += 1;
        }
        self.last_gaze_truth = i.saturating_sub(1);
        i.checked_sub(1).map(|j| truth[j])
    }
}

impl LoopHook for TruthRecorder {
    fn input(&mut self, now: Timestamp, input: &DeviceInput, _engine: &Engine) {
        let mut log = lock(&self.log);
        match input {
            DeviceInput::Gaze(..) => log.gaze_samples += 1,
            DeviceInput::Sync(_) => log.sequencer_events += 1,
            DeviceInput::Light(_) => {}
            DeviceInput::LensLink(lens, up) => log.link_events.push((
                now,
                if *up {
                    LinkStatus::Connected
                } else {
                    LinkStatus::Lost
                },
                *lens,
            )),
            DeviceInput::LensWire {
                id,
                wire_time,
                host_path,
                ..
            } => {
                if let Some(c) = log.lens_commands.iter_mut().rev().find(|c| c.id.0 == *id) {
                    c.wire.get_or_insert(*wire_time);
                }
                log.host_path.extend(*host_path);
            }
            DeviceInput::LensState(..) => {}
        }
    }

    fn command(&mut self, now: Timestamp, cmd: &Command) {
        let mut log = lock(&self.log);
        match *cmd {
            Command::SetLensPower {
                lens,
                id,
                power,
                reason,
                ..
            } => log.lens_commands.push(LensCommand {
                t: now,
                lens,
                id,
                power,
                reason,
                wire: None,
            }),
            Command::RenderFrame(r) => log.frames_requested.push((now, r)),
            Command::Present { .. } | Command::PresentLayer { .. } => {
                log.presents.push((now, *cmd))
            }
            _ => {}
        }
    }

    fn next_wakeup(&self) -> Option<Timestamp> {
        self.next_probe
    }

    fn wake(&mut self, now: Timestamp, engine: &Engine) {
        let (Some(p), Some(every)) = (self.next_probe, self.probe) else {
            return;
        };
        let truth = self.gaze_truth_at(now);
        let (lens_power, lens_target) = lens_truth(self.sims.get(), 0, now).unzip();
        let (lens_power_right, lens_target_right) = lens_truth(self.sims.get(), 1, now).unzip();
        let st = engine.scheduler().status();
        lock(&self.log).probes.push(Probe {
            t: now,
            lens_power,
            eye_focus: lens_power.map(|p| self.optics.focus_of(p)),
            lens_target,
            lens_power_right,
            lens_target_right,
            predicted: engine.scheduler().predicted_lens_power(now),
            commanded: st.commanded_power,
            commanded_focus: st
                .commanded_power
                .map(|c| engine.scheduler().config().optics.focus_of(c)),
            gaze_target_d: truth.map(|s| s.target_diopters),
            vergence_d: truth.map(|s| s.diopters),
            phase: st.phase,
        });
        self.next_probe = Some((p + every).max(now));
    }

    fn stopped(&mut self, _now: Timestamp, engine: &Engine) {
        self.next_probe = None;
        lock(&self.log).end = Some(End {
            status: engine.scheduler().status(),
            latency: engine.scheduler().latency().clone(),
        });
    }
}

/// A renderer for loop tests: every frame takes the simulated time `cost` gives (its images
/// are 1 x 1 pixels: nothing looks at them). The content they show is a still frame of a
/// depth map: [`ScriptedRenderer::still`].
pub struct ScriptedRenderer {
    planes: usize,
    cost: Box<dyn Fn(&RenderJob) -> Duration + Send + Sync>,
}

impl ScriptedRenderer {
    pub fn new(
        planes: usize,
        cost: impl Fn(&RenderJob) -> Duration + Send + Sync + 'static,
    ) -> Self {
        ScriptedRenderer {
            planes,
            cost: Box::new(cost),
        }
    }

    /// One still frame of `depth` (black): the content loop tests show.
    pub fn still(depth: &dioptra_core::DepthMap) -> Arc<dyn Content> {
        Arc::new(crate::content::Still::of_depth(depth))
    }
}

impl Renderer for ScriptedRenderer {
    fn render(
        &self,
        job: &RenderJob,
        _content: &ContentFrame,
    ) -> Result<RenderOutput, RenderError> {
        let layers = if job.mode == Mode::Multifocal {
            self.planes
        } else {
            1
        };
        Ok(RenderOutput {
            images: vec![RgbImage::new(1, 1, [0.5; 3]).into(); layers],
            planned: None,
            cost: Some((self.cost)(job)),
        })
    }
}

/// Percentile (0..=100) of durations, by nearest rank; `None` when empty.
pub fn percentile(values: &[Duration], p: f64) -> Option<Duration> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort();
    let rank = ((p / 100.0) * v.len() as f64).ceil().max(1.0) as usize;
    v.get(rank.min(v.len()) - 1).copied()
}
