//! The whole loop on simulated devices: the scheduler driving the real lens, eye-tracker and
//! sync-board drivers, each talking to its simulator over an in-memory link, on tokio's clock.
//! Run [`run`] inside a runtime with paused time (`#[tokio::test(start_paused = true)]`, or
//! `Builder::start_paused`) and the loop runs as fast as the host computes it, in simulated
//! time; rendering takes whatever simulated time the [`Frames`] implementation says.
//!
//! One task per device, as in the daemon: the gaze task forwards samples, the lens task sends
//! powers, polls readbacks and reopens a lost link, the board task forwards sub-frame events;
//! the loop itself steps the scheduler and carries out its commands. Ground truth (what the
//! eyes really do, where the simulated lens really is) is recorded beside it.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant as WallInstant};

use dioptra_core::{
    Clock, DepthMap, DeviceError, Diopters, GazeSource, LinkError, PlaneSequencer, PowerRange,
    Timestamp, VarifocalLens,
};
use dioptra_gaze::dioptra_tracker::{DioptraTracker, DioptraTrackerConfig};
use dioptra_lens::{ControllerConfig, LensController, LensLimits, Opener};
use dioptra_sched::processing::EyePhase;
use dioptra_sched::{
    Command, CommandId, Event, FocusReason, FrameRequest, LinkStatus, Mode, Scheduler,
    SchedulerConfig,
};
use dioptra_sim::gaze::generator::{SampleSource, TruthSample};
use dioptra_sim::gaze::{dioptra_tracker as sim_tracker, GazeGenerator, GeneratorConfig, Scene};
use dioptra_sim::lens_controller::{LensControllerSim, LensControllerSimConfig};
use dioptra_sim::serve::{serve, ByteDevice};
use dioptra_sim::sync_board::{SyncBoardSim, SyncBoardSimConfig};
use dioptra_sim::tokio_clock::TokioClock;
use dioptra_sync::board::SyncBoard;
use dioptra_transport::memory::{self, Faults, MemoryLink};
use tokio::sync::mpsc;
use tokio::time::{sleep_until, timeout, Instant};

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // No invariant spans a panic point: a poisoned lock is still consistent.
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// A simulator shared between its serve task and the test, which reads its ground truth.
pub struct Shared<D>(pub Arc<Mutex<D>>);

impl<D: ByteDevice> ByteDevice for Shared<D> {
    fn wait(&self, now: Timestamp) -> Duration {
        lock(&self.0).wait(now)
    }
    fn advance_to(&mut self, now: Timestamp, out: &mut Vec<u8>) {
        lock(&self.0).advance_to(now, out)
    }
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        lock(&self.0).receive(bytes, out)
    }
    fn idle(&mut self, out: &mut Vec<u8>) {
        lock(&self.0).idle(out)
    }
}

#[derive(Default)]
struct LensSlot {
    sim: Option<Arc<Mutex<LensControllerSim>>>,
    faults: Option<Faults>,
    unplugged: bool,
    opened: u32,
}

/// The simulated lens controller as a person at the bench sees it: plug, unplug, and look at
/// the lens itself.
#[derive(Clone, Default)]
pub struct LensBench(Arc<Mutex<LensSlot>>);

impl LensBench {
    /// Pulls the cable: the link breaks and the device cannot be reopened until
    /// [`LensBench::replug`].
    pub fn unplug(&self) {
        let mut s = lock(&self.0);
        s.unplugged = true;
        if let Some(f) = &s.faults {
            f.disconnect("lens cable pulled");
        }
    }
    pub fn replug(&self) {
        lock(&self.0).unplugged = false;
    }
    /// How many times the driver opened the device (1 + reconnects).
    pub fn opened(&self) -> u32 {
        lock(&self.0).opened
    }
    /// The simulated lens's true power at `now`, and the power it is heading to.
    pub fn truth(&self, now: Timestamp) -> Option<(Diopters, Diopters)> {
        let sim = lock(&self.0).sim.clone()?;
        let mut sim = lock(&sim);
        sim.advance_to(now);
        Some((sim.lens().power(), sim.lens().target_power()))
    }

    fn opener(&self, cfg: LensControllerSimConfig, clock: TokioClock) -> Opener<MemoryLink> {
        let bench = self.clone();
        Opener::new(move || {
            let r = bench.open(cfg.clone(), clock);
            async move { r }
        })
    }

    fn open(
        &self,
        cfg: LensControllerSimConfig,
        clock: TokioClock,
    ) -> Result<MemoryLink, LinkError> {
        let mut s = lock(&self.0);
        if s.unplugged {
            return Err(LinkError::Unavailable(
                "no lens controller is plugged in".into(),
            ));
        }
        let (host, mut dev) = memory::pair(4096);
        let sim = Arc::new(Mutex::new(LensControllerSim::new(cfg)));
        let mut served = Shared(sim.clone());
        tokio::spawn(async move {
            let _ = serve(&mut dev, &mut served, &clock).await;
        });
        s.sim = Some(sim);
        s.faults = Some(host.faults());
        s.opened += 1;
        Ok(host.named("simulated lens controller"))
    }
}

/// A gaze generator that also records what the eyes really did.
struct Recorded {
    gen: GazeGenerator,
    truth: Arc<Mutex<Vec<TruthSample>>>,
}

impl SampleSource for Recorded {
    fn next_sample(&mut self) -> Option<(u64, dioptra_protocol::BinocularSample)> {
        let s = self.gen.next_truth();
        lock(&self.truth).push(s);
        Some((s.time_us, s.reported))
    }
    fn rate_hz(&self) -> f64 {
        self.gen.rate_hz()
    }
}

/// Something scripted to happen during a run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Action {
    UnplugLens,
    ReplugLens,
    ManualFocus(Option<Diopters>),
}

/// What to run.
#[derive(Debug, Clone)]
pub struct RigOptions {
    pub sched: SchedulerConfig,
    /// What the viewer looks at (targets must lie on the depth maps' surfaces).
    pub gaze_scene: Scene,
    pub gaze: GeneratorConfig,
    /// Delay from exposure to delivery of each gaze report, µs: minimum and uniform jitter.
    pub gaze_latency_us: (u64, u64),
    pub lens: LensControllerSimConfig,
    pub board: SyncBoardSimConfig,
    /// Lens readback interval.
    pub lens_poll: Duration,
    /// How often a lost lens link is retried.
    pub lens_retry: Duration,
    /// Ground truth is sampled this often (`None`: not at all).
    pub probe: Option<Duration>,
    pub duration: Duration,
    /// Simulated time after shutdown before the run ends (for the lens to park).
    pub after_shutdown: Duration,
    pub actions: Vec<(Duration, Action)>,
}

impl RigOptions {
    pub fn new(mode: Mode, gaze_scene: Scene, duration: Duration) -> Self {
        RigOptions {
            sched: SchedulerConfig::new(mode),
            gaze_scene,
            gaze: GeneratorConfig::default(),
            gaze_latency_us: (1500, 500),
            lens: LensControllerSimConfig::default(),
            board: SyncBoardSimConfig {
                // The board's lens steps between planes within a sub-frame's settle allowance.
                lens: dioptra_sim::lens_model::LensModelConfig {
                    settle_time: Duration::from_micros(1200),
                    ..Default::default()
                },
                ..Default::default()
            },
            lens_poll: Duration::from_millis(2),
            lens_retry: Duration::from_millis(50),
            probe: Some(Duration::from_millis(1)),
            duration,
            after_shutdown: Duration::from_millis(200),
            actions: Vec::new(),
        }
    }
}

/// The renderer side of the loop.
pub trait Frames {
    /// The scene's depth map (diopters, spanning the eye's field) for the frame asked for at
    /// `t`; `None` keeps the last one. Also asked once at the start.
    fn depth(&mut self, t: Timestamp) -> Option<Arc<DepthMap>>;
    /// Makes the frame; returns the simulated time it takes.
    fn render(&mut self, req: &FrameRequest) -> Duration;
    /// A frame or layer went on the display at `t`.
    fn presented(&mut self, _cmd: &Command, _t: Timestamp) {}
}

/// Ground truth at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Probe {
    pub t: Timestamp,
    /// The simulated lens's true power and the power it heads to.
    pub lens_power: Option<Diopters>,
    pub lens_target: Option<Diopters>,
    /// The scheduler's model of the lens.
    pub predicted: Option<Diopters>,
    pub commanded: Option<Diopters>,
    /// The depth of what the viewer really looks at, and the eyes' vergence, diopters.
    pub gaze_target_d: Option<f64>,
    pub vergence_d: Option<f64>,
    pub phase: EyePhase,
}

/// A lens command as issued.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensCommand {
    pub t: Timestamp,
    pub id: CommandId,
    pub power: Diopters,
    pub reason: FocusReason,
    /// When the driver had it on the wire (`None`: never, the link was down).
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
    /// Wall-clock host path per lens command that a gaze sample caused: from the loop
    /// receiving the sample to the driver having written the command.
    pub host_path: Vec<Duration>,
    pub gaze_samples: u64,
    pub sequencer_events: u64,
    pub link_events: Vec<(Timestamp, LinkStatus)>,
    pub gaze_errors: Vec<String>,
}

/// The result of [`run`].
pub struct Run {
    pub log: Log,
    pub scheduler: Scheduler,
    pub lens: LensBench,
    /// Simulated time covered, and the wall time it took.
    pub simulated: Duration,
    pub wall: Duration,
}

enum Msg {
    Sched(Event),
    /// A gaze-caused command's host path (wall clock).
    HostPath(Duration),
    Wire(CommandId, Timestamp),
    GazeError(String),
}

enum LensReq {
    Set {
        id: CommandId,
        power: Diopters,
        received: Option<WallInstant>,
    },
}

async fn lens_task(
    mut d: LensController<MemoryLink>,
    mut rx: mpsc::UnboundedReceiver<LensReq>,
    tx: mpsc::UnboundedSender<Msg>,
    poll: Duration,
    retry: Duration,
) {
    let mut up = true;
    let lost = |up: &mut bool, e: &DeviceError| {
        if *up && (e.needs_reconnect() || matches!(e, DeviceError::Link(_))) {
            *up = false;
            return true;
        }
        false
    };
    loop {
        match timeout(if up { poll } else { retry }, rx.recv()).await {
            Ok(None) => return,
            Ok(Some(LensReq::Set {
                id,
                power,
                received,
            })) => {
                if !up {
                    continue;
                }
                match d.set_power(power).await {
                    Ok(wire) => {
                        if let Some(r) = received {
                            let _ = tx.send(Msg::HostPath(r.elapsed()));
                        }
                        let _ = tx.send(Msg::Wire(id, wire));
                        let _ = tx.send(Msg::Sched(Event::LensCommandWritten {
                            id,
                            wire_time: wire,
                        }));
                    }
                    Err(e) => {
                        if lost(&mut up, &e) {
                            let _ = tx.send(Msg::Sched(Event::LensLink(LinkStatus::Lost)));
                        }
                    }
                }
            }
            // Idle: read the lens back, which also reopens a lost link.
            Err(_) => match d.state().await {
                Ok(s) => {
                    if !up {
                        up = true;
                        let _ = tx.send(Msg::Sched(Event::LensLink(LinkStatus::Connected)));
                    }
                    let _ = tx.send(Msg::Sched(Event::LensState(s)));
                }
                Err(e) => {
                    if lost(&mut up, &e) {
                        let _ = tx.send(Msg::Sched(Event::LensLink(LinkStatus::Lost)));
                    }
                }
            },
        }
    }
}

/// Runs the loop for `opts.duration` of simulated time, then shuts it down. Needs a tokio
/// runtime (paused time for a fast, deterministic run).
pub async fn run(opts: RigOptions, frames: &mut dyn Frames) -> Result<Run, DeviceError> {
    let wall_start = WallInstant::now();
    let origin = Instant::now();
    let clock = TokioClock::new();
    let shared_clock: Arc<dyn Clock> = Arc::new(clock);
    let at = |t: Timestamp| origin + Duration::from_nanos(t.as_nanos());
    let mode = opts.sched.mode;
    let mut sched =
        Scheduler::new(opts.sched.clone()).map_err(|e| DeviceError::Invalid(e.to_string()))?;
    let (tx, mut rx) = mpsc::unbounded_channel::<Msg>();

    // Gaze.
    let truth = Arc::new(Mutex::new(Vec::new()));
    let gen = GazeGenerator::new(opts.gaze_scene.clone(), opts.gaze)
        .map_err(|e| DeviceError::Invalid(format!("gaze scene: {e}")))?;
    let (link, tracker_sim) = sim_tracker::spawn(Box::new(Recorded {
        gen,
        truth: truth.clone(),
    }));
    tracker_sim.set_faults(dioptra_sim::gaze::Faults {
        latency_us: opts.gaze_latency_us,
        ..Default::default()
    });
    let mut tracker =
        DioptraTracker::connect(link, DioptraTrackerConfig::default(), shared_clock.clone())
            .await?;
    let gtx = tx.clone();
    let gaze_task = tokio::spawn(async move {
        loop {
            match tracker.next_sample().await {
                Ok(s) => {
                    if gtx.send(Msg::Sched(Event::Gaze(s))).is_err() {
                        return;
                    }
                }
                Err(e) => {
                    let _ = gtx.send(Msg::GazeError(e.to_string()));
                    if e.needs_reconnect() {
                        return;
                    }
                }
            }
        }
    });

    // Lens (varifocal and light field; the sync board moves its own lens in multifocal).
    let bench = LensBench::default();
    let (lens_tx, lens_rx) = mpsc::unbounded_channel();
    let lens_task_h = if mode != Mode::Multifocal {
        let range = opts.sched.lens_range;
        let limits = LensLimits::new(
            PowerRange::new(range.min, range.max)
                .ok_or_else(|| DeviceError::Invalid("lens range".into()))?,
        );
        let d = LensController::connect_with(
            bench.opener(opts.lens.clone(), clock),
            ControllerConfig::new(limits),
            shared_clock.clone(),
        )
        .await?;
        Some(tokio::spawn(lens_task(
            d,
            lens_rx,
            tx.clone(),
            opts.lens_poll,
            opts.lens_retry,
        )))
    } else {
        drop(lens_rx);
        None
    };

    // Sync board (multifocal).
    let (stop_tx, mut stop_rx) = mpsc::unbounded_channel::<()>();
    let board_task = if mode == Mode::Multifocal {
        let schedule = opts
            .sched
            .planes
            .clone()
            .ok_or_else(|| DeviceError::Invalid("multifocal needs planes".into()))?;
        let (host, mut dev) = memory::pair(8192);
        let cfg = opts.board.clone();
        tokio::spawn(async move {
            let mut sim = SyncBoardSim::new(cfg);
            let _ = serve(&mut dev, &mut sim, &clock).await;
        });
        let mut b = SyncBoard::connect(host, shared_clock.clone()).await?;
        b.program(&schedule).await?;
        b.start().await?;
        let btx = tx.clone();
        Some(tokio::spawn(async move {
            loop {
                tokio::select! {
                    _ = stop_rx.recv() => {
                        let _ = b.stop().await;
                        return;
                    }
                    ev = b.next_event() => match ev {
                        Ok(e) => {
                            if btx.send(Msg::Sched(Event::Sequencer(e))).is_err() {
                                return;
                            }
                        }
                        Err(_) => return,
                    }
                }
            }
        }))
    } else {
        None
    };

    let mut log = Log::default();
    let mut out = Vec::new();
    let mut work: VecDeque<(Timestamp, Event)> = VecDeque::new();
    // Render completions, by simulated finish time.
    let mut finishing: Vec<(Timestamp, Event)> = Vec::new();
    let mut actions = opts.actions.clone();
    actions.sort_by_key(|a| a.0);
    let mut actions: VecDeque<(Duration, Action)> = actions.into();
    let start = clock.now();
    let end = start + opts.duration;
    let mut stop_at: Option<Timestamp> = None;
    let mut next_probe = opts.probe.map(|_| start);
    if let Some(d) = frames.depth(start) {
        work.push_back((start, Event::Depth(d)));
    }
    work.push_back((start, Event::Tick));

    loop {
        // Step everything queued, carrying out commands (which may queue more events).
        while let Some((now, ev)) = work.pop_front() {
            let received = matches!(ev, Event::Gaze(_)).then(WallInstant::now);
            out.clear();
            sched.step(now, ev, &mut out);
            // A lens command goes out before anything else (a render) runs on this thread,
            // as it would from the daemon's scheduler task.
            let lens_first = out
                .iter()
                .any(|c| matches!(c, Command::SetLensPower { .. }));
            for cmd in out.drain(..) {
                match cmd {
                    Command::SetLensPower {
                        id, power, reason, ..
                    } => {
                        log.lens_commands.push(LensCommand {
                            t: now,
                            id,
                            power,
                            reason,
                            wire: None,
                        });
                        let _ = lens_tx.send(LensReq::Set {
                            id,
                            power,
                            received,
                        });
                    }
                    Command::RenderFrame(r) => {
                        log.frames_requested.push((now, r));
                        if let Some(d) = frames.depth(now) {
                            work.push_back((now, Event::Depth(d)));
                        }
                        let took = frames.render(&r);
                        finishing.push((
                            now + took,
                            Event::RenderFinished {
                                frame: r.frame,
                                method: r.method,
                                render_time: took,
                            },
                        ));
                    }
                    c @ (Command::Present { .. } | Command::PresentLayer { .. }) => {
                        frames.presented(&c, now);
                        log.presents.push((now, c));
                    }
                    Command::StopSequencer => {
                        let _ = stop_tx.send(());
                    }
                    _ => {}
                }
                if lens_first && matches!(cmd, Command::SetLensPower { .. }) {
                    tokio::task::yield_now().await;
                }
            }
        }
        let now = clock.now();
        if stop_at.is_some_and(|t| now >= t) {
            break;
        }
        if stop_at.is_none() && now >= end {
            work.push_back((now, Event::Shutdown));
            stop_at = Some(now + opts.after_shutdown);
            continue;
        }
        if let Some(&(after, action)) = actions.front() {
            if start + after <= now {
                actions.pop_front();
                match action {
                    Action::UnplugLens => bench.unplug(),
                    Action::ReplugLens => bench.replug(),
                    Action::ManualFocus(f) => work.push_back((now, Event::ManualFocus(f))),
                }
                continue;
            }
        }
        if let Some(p) = next_probe.filter(|p| *p <= now) {
            let truth_now = lock(&truth)
                .iter()
                .rev()
                .find(|s| Timestamp::from_micros(s.time_us) <= now)
                .copied();
            let (lens_power, lens_target) = bench.truth(now).unzip();
            let st = sched.status();
            log.probes.push(Probe {
                t: now,
                lens_power,
                lens_target,
                predicted: sched.predicted_lens_power(now),
                commanded: st.commanded_power,
                gaze_target_d: truth_now.map(|s| s.target_diopters),
                vergence_d: truth_now.map(|s| s.diopters),
                phase: st.phase,
            });
            next_probe = opts.probe.map(|d| p + d);
            continue;
        }
        finishing.sort_by_key(|f| f.0);
        if finishing.first().is_some_and(|f| f.0 <= now) {
            let (t, ev) = finishing.remove(0);
            work.push_back((t, ev));
            continue;
        }
        let wake = [
            sched.next_wakeup(),
            finishing.first().map(|f| f.0),
            next_probe,
            actions.front().map(|a| start + a.0),
            Some(stop_at.unwrap_or(end)),
        ]
        .into_iter()
        .flatten()
        .min()
        .unwrap_or(end)
        .max(now);
        tokio::select! {
            biased;
            m = rx.recv() => match m {
                Some(Msg::Sched(ev)) => {
                    match &ev {
                        Event::Gaze(_) => log.gaze_samples += 1,
                        Event::Sequencer(_) => log.sequencer_events += 1,
                        Event::LensLink(l) => log.link_events.push((clock.now(), *l)),
                        _ => {}
                    }
                    work.push_back((clock.now(), ev));
                }
                Some(Msg::HostPath(d)) => log.host_path.push(d),
                Some(Msg::Wire(id, wire)) => {
                    if let Some(c) = log.lens_commands.iter_mut().rev().find(|c| c.id == id) {
                        c.wire = Some(wire);
                    }
                }
                Some(Msg::GazeError(e)) => log.gaze_errors.push(e),
                None => break,
            },
            _ = sleep_until(at(wake)) => {
                if sched.next_wakeup().is_some_and(|w| w <= clock.now()) {
                    work.push_back((clock.now(), Event::Tick));
                }
            }
        }
    }
    let simulated = clock.now().saturating_since(start);
    gaze_task.abort();
    if let Some(h) = board_task {
        h.abort();
    }
    drop(lens_tx);
    if let Some(h) = lens_task_h {
        let _ = h.await;
    }
    drop(tracker_sim);
    log.truth = std::mem::take(&mut *lock(&truth));
    Ok(Run {
        log,
        scheduler: sched,
        lens: bench,
        simulated,
        wall: wall_start.elapsed(),
    })
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
