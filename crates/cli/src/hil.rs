//! `dioptra hil --config rig.toml`: the hardware-in-the-loop latency harness. It runs the rig
//! a config describes on the rig runtime `dioptra serve` runs (dioptra-rig: the same device
//! tasks, loop, scheduler and runtime; the real drivers, on hardware or on the in-process
//! simulators for `port = "sim"`), watches it through a loop hook, and measures:
//!
//! 1. gaze sample to lens command written (the host path): for every lens command a gaze
//!    sample caused, the wall time from the gaze task receiving the sample from its driver to
//!    the lens driver having written the command; and command to wire (the loop handing the
//!    command to the lens task to the driver's write completing);
//! 2. command to settled: `--trials` lens steps between a quarter and three quarters of
//!    `optics.lens_range`, commanded as manual focus through the loop, each timed from the
//!    command to the first readback within 0.05 D (and not reporting "moving"). Readbacks
//!    come every `devices.lens.poll_ms`, so these figures are quantised to it (a photodiode
//!    watches the display, not the lens: settling is the lens's own readback);
//! 3. sub-frame timing (when `devices.sync` is configured): the rig is switched to multifocal
//!    mode and the sequencer's sub-frame start times (device clock) are compared with the
//!    programmed period `1 / optics.subframe_hz`, the plane order with the programmed
//!    schedule, and faults counted. Skipped for a DLPC350, which reports no sub-frame times
//!    of its own.
//!
//! 4. content latency (when `[content]` is a stream or files): from a content frame's arrival
//!    to its being ready, and to the display time of the first frame showing it, from the
//!    rig's own latency histograms. With `source = "stream"` the harness plays the application:
//!    `--trials` frames through the stream's `PUT /frame` path at `display.frame_hz`.
//! 5. in photons (when `[devices.photodiode]` is configured, during phase 1): the marker patch
//!    is held black, then toggled as `display.marker_patch.toggle_on` says while the rig follows
//!    gaze, and the photodiode's edges are matched to the presents ([`dioptra_rig::photons`]):
//!    `vsync to photons` (the display's latency), `frame presented to photons`, `gaze sample to
//!    photons` (a gaze sample received, through the lens command it caused and the first frame
//!    rendered for the new focus, to that frame's light), and the refreshes that showed another
//!    frame than their own (dropped or late frames, seen optically). Without a photodiode the
//!    summary says there is no optical measurement.
//!
//! It writes `summary.txt` and `summary.json` (HdrHistogram percentiles) and one PNG histogram
//! per measurement to `--out`. With simulated devices every output says SIMULATED.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use dioptra_core::{SequencerEvent, Timestamp};
use hdrhistogram::Histogram;
use plotters::prelude::*;
use serde_json::json;
use tokio::sync::mpsc;

use dioptra_rig::config::{Mode, Port, RigConfig, SyncDriver};
use dioptra_rig::devices::{DeviceInput, LensId, State};
use dioptra_rig::engine::Command;
use dioptra_rig::executor::LoopHook;
use dioptra_rig::photons::{PhotonLog, PhotonRecorder, PhotonReport};
use dioptra_rig::{Control, Rig, RigSetup};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The rig config (as for `dioptra serve`).
    #[arg(long)]
    config: PathBuf,
    /// Trials per measurement (lens steps; gaze-to-command samples; sub-frame intervals).
    #[arg(long, default_value_t = 100)]
    trials: usize,
    /// Where to write summary.txt, summary.json and the PNG histograms.
    #[arg(long, default_value = "hil-out")]
    out: PathBuf,
    /// Seconds to wait for every device to connect.
    #[arg(long, default_value_t = 5.0)]
    connect_timeout_s: f64,
}

/// A step's readback counts as settled within this many diopters of the command.
const SETTLE_TOLERANCE_D: f32 = 0.05;
/// A lens step that has not settled by then is counted as unsettled.
const STEP_TIMEOUT: Duration = Duration::from_secs(1);

/// One measurement: its name, what it is, and its histogram (microseconds).
struct Measure {
    key: &'static str,
    title: &'static str,
    hist: Histogram<u64>,
    /// Signed mean, µs (the histogram holds magnitudes for signed quantities).
    signed_mean_us: Option<f64>,
    note: String,
}

impl Measure {
    fn new(key: &'static str, title: &'static str) -> Measure {
        Measure {
            key,
            title,
            hist: Histogram::new_with_bounds(1, 3_600_000_000, 3).expect("valid bounds"),
            signed_mean_us: None,
            note: String::new(),
        }
    }
    fn record_us(&mut self, us: f64) {
        let _ = self.hist.record(us.round().max(1.0) as u64);
    }
}

fn ts_us(a: Timestamp, b: Timestamp) -> f64 {
    (b.0 as f64 - a.0 as f64) / 1e3
}

/// Names each configured device, its config key and port, and whether it is simulated.
fn devices_of(cfg: &RigConfig) -> Vec<(String, String, Port)> {
    let d = &cfg.devices;
    let mut v: Vec<(String, String, Port)> = d
        .lens
        .each()
        .into_iter()
        .enumerate()
        .map(|(i, l)| {
            (
                d.lens.name(i),
                format!("{}.port", d.lens.key(i)),
                l.port.clone(),
            )
        })
        .collect();
    v.push((
        "gaze".into(),
        "devices.gaze.port".into(),
        d.gaze.port.clone(),
    ));
    if let Some(s) = &d.sync {
        v.push(("sync".into(), "devices.sync.port".into(), s.port.clone()));
    }
    if let Some(port) = d.photodiode.as_ref().and_then(|p| p.port.clone()) {
        v.push(("photodiode".into(), "devices.photodiode.port".into(), port));
    }
    v
}

/// How long the marker patch is held black before the photon measurement (the anchor needs
/// the light off long enough that its first edge is the first white frame's).
fn photon_hold(frame_hz: f64) -> Duration {
    Duration::from_millis(300).max(Duration::from_secs_f64(4.0 / frame_hz))
}

/// A match searches this far after the first white present for its light.
const MAX_PHOTON_LATENCY: Duration = Duration::from_millis(250);

pub fn run(args: Args) -> Result<()> {
    if !(1..=100_000).contains(&args.trials) {
        bail!(
            "--trials {} is out of range: expected 1 to 100000",
            args.trials
        );
    }
    if !(args.connect_timeout_s > 0.0 && args.connect_timeout_s <= 600.0) {
        bail!(
            "--connect-timeout-s {} is out of range: expected more than 0 and at most 600",
            args.connect_timeout_s
        );
    }
    let cfg = RigConfig::load(&args.config)
        .with_context(|| format!("rig config {}", args.config.display()))?;
    for note in cfg.notices() {
        eprintln!("dioptra hil: note: {note}");
    }
    let devices = devices_of(&cfg);
    // A device path that does not exist is absent: say so before opening anything.
    for (name, key, port) in &devices {
        if let Port::Path(p) = port {
            if !p.exists() {
                bail!(
                    "{key} = \"{}\": the {name} device is not present (no such file); connect it, \
                     fix the path, or set {key} = \"sim\" to run the harness on a simulator",
                    p.display()
                );
            }
        }
    }
    let simulated: Vec<&str> = devices
        .iter()
        .filter(|d| d.2 == Port::Sim)
        .map(|d| d.0.as_str())
        .collect();
    let all_sim = simulated.len() == devices.len();
    let banner = if all_sim {
        "SIMULATED: every device is a dioptra-sim simulator (port = \"sim\"); these figures \
         measure this host and the simulators, not hardware"
            .to_string()
    } else if simulated.is_empty() {
        "hardware: every device is real".to_string()
    } else {
        format!(
            "PARTLY SIMULATED: {} simulated (port = \"sim\"), the rest real",
            simulated.join(", ")
        )
    };
    println!("dioptra hil: {}", args.config.display());
    println!("{banner}");
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create the output folder {}", args.out.display()))?;
    // The runtime `dioptra serve` runs the rig on.
    let rt = crate::common::rig_runtime()?;
    let (measures, optical) = rt.block_on(measure(&cfg, &args, &devices))?;
    write_outputs(
        &args.out,
        &args.config,
        &banner,
        all_sim,
        &measures,
        &optical,
    )?;
    println!(
        "\nwrote {}: summary.txt, summary.json, {}",
        args.out.display(),
        measures
            .iter()
            .map(|m| format!("{}.png", m.key))
            .collect::<Vec<_>>()
            .join(", ")
    );
    if let Optical::Failed(why) = optical {
        bail!(
            "the photodiode was configured and its light could not be matched to the frames: {why}"
        );
    }
    Ok(())
}

/// What the photon measurement found.
enum Optical {
    /// No photodiode is configured.
    NoPhotodiode,
    Measured(PhotonReport),
    /// It ran and could not match the light to the frames: why.
    Failed(String),
}

/// What the hook forwards from the rig's loop to the harness.
enum Seen {
    Input(DeviceInput),
    /// The loop handed command `id` (power `.2`, D) to lens `.0`'s task at time `.3`.
    LensCommand(LensId, u64, f32, Timestamp),
    /// The loop stopped: the scheduler's latency histograms.
    Stopped(Box<dioptra_sched::Latency>),
}

/// Forwards what the loop sees to the harness, which measures outside the loop's task.
struct Forward(mpsc::UnboundedSender<Seen>);

impl LoopHook for Forward {
    fn input(
        &mut self,
        _now: Timestamp,
        input: &DeviceInput,
        _engine: &dioptra_rig::engine::Engine,
    ) {
        let _ = self.0.send(Seen::Input(input.clone()));
    }
    fn command(&mut self, now: Timestamp, cmd: &Command) {
        if let Command::SetLensPower {
            lens, id, power, ..
        } = cmd
        {
            let _ = self.0.send(Seen::LensCommand(*lens, id.0, power.0, now));
        }
    }
    fn stopped(&mut self, _now: Timestamp, engine: &dioptra_rig::engine::Engine) {
        let latency = engine.scheduler().latency().clone();
        let _ = self.0.send(Seen::Stopped(Box::new(latency)));
    }
}

/// Plays the application of a `source = "stream"` rig: `n` frames at `hz` through the
/// stream's `PUT /frame` path, a bright square stepping between 0.5 and 2 m. Returns the
/// frames accepted.
async fn push_stream_frames(
    state: &std::sync::Arc<dioptra_rig::RigState>,
    n: usize,
    hz: f64,
) -> usize {
    use dioptra_rig::content::stream::{ColorFormat, DepthKind, FrameDesc};
    let d = &state.cfg().display;
    let (w, h) = (d.width as usize, d.height as usize);
    let desc = FrameDesc {
        width: w,
        height: h,
        color: ColorFormat::Rgb8,
        depth: DepthKind::Metres,
        near: None,
        far: None,
        seq: None,
        app_time_ns: None,
    };
    let mut accepted = 0;
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / hz));
    // An application late with one frame sends the next a period later, not two at once.
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    for i in 0..n {
        tick.tick().await;
        let near = if i % 2 == 0 { 0.5f32 } else { 2.0 };
        let inside =
            |x: usize, y: usize| (w / 4..3 * w / 4).contains(&x) && (h / 4..3 * h / 4).contains(&y);
        let mut color = Vec::with_capacity(w * h * 3);
        let mut depth = Vec::with_capacity(w * h * 4);
        for y in 0..h {
            for x in 0..w {
                let v = if inside(x, y) { 230u8 } else { 40 };
                color.extend_from_slice(&[v, v, v]);
                let m = if inside(x, y) { near } else { 3.0 };
                depth.extend_from_slice(&m.to_le_bytes());
            }
        }
        let st = state.clone();
        let now = state.clock().now();
        let ok = tokio::task::spawn_blocking(move || {
            st.content()
                .source()
                .frame_ingest()
                .is_some_and(|s| s.submit(&desc, &color, &depth, now).is_ok())
        })
        .await
        .unwrap_or(false);
        accepted += usize::from(ok);
    }
    accepted
}

/// A histogram of the rig's scheduler as a measurement.
fn from_latency(
    key: &'static str,
    title: &'static str,
    h: &Histogram<u64>,
    note: String,
) -> Measure {
    let mut m = Measure::new(key, title);
    let _ = m.hist.add(h);
    m.note = note;
    m
}

async fn measure(
    cfg: &RigConfig,
    args: &Args,
    devices: &[(String, String, Port)],
) -> Result<(Vec<Measure>, Optical)> {
    let (tx, mut rx) = mpsc::unbounded_channel::<Seen>();
    let mut setup = RigSetup::new(cfg.clone());
    setup.hooks.push(Box::new(Forward(tx)));
    let photodiode = cfg.devices.photodiode.is_some();
    let photon_log = std::sync::Arc::new(std::sync::Mutex::new(PhotonLog::default()));
    if photodiode {
        setup
            .hooks
            .push(Box::new(PhotonRecorder::new(photon_log.clone())));
    }
    let rig = Rig::start(setup)
        .await
        .map_err(|e| anyhow::anyhow!("cannot start the rig: {e}"))?;
    let state = rig.state().clone();
    let registry = state.devices().registry().clone();

    // Every device must connect.
    let deadline = tokio::time::Instant::now() + Duration::from_secs_f64(args.connect_timeout_s);
    loop {
        let snap = registry.snapshot();
        if snap.values().all(|s| s.state == State::Ok) && snap.len() == devices.len() {
            break;
        }
        if tokio::time::Instant::now() >= deadline {
            state.cancel().cancel();
            let _ = rig.wait().await;
            let missing: Vec<String> = devices
                .iter()
                .filter_map(|(name, key, port)| {
                    let s = snap.get(name)?;
                    (s.state != State::Ok).then(|| {
                        format!(
                            "{key} = \"{port}\": the {name} device ({} driver) did not connect within {} s: {}",
                            s.driver,
                            args.connect_timeout_s,
                            s.last_error.as_deref().unwrap_or("no answer")
                        )
                    })
                })
                .collect();
            bail!("{}", missing.join("\n"));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    println!(
        "devices connected: {}",
        devices
            .iter()
            .map(|d| format!("{} ({})", d.0, d.2))
            .collect::<Vec<_>>()
            .join(", ")
    );

    let lenses = cfg.devices.lens.count();
    let mut host_path = Measure::new(
        "gaze_to_command",
        if lenses > 1 {
            "gaze sample received to both lens commands written (host path)"
        } else {
            "gaze sample received to lens command written (host path)"
        },
    );
    let mut skew = Measure::new(
        "inter_eye_skew",
        "left and right lens commands of one gaze sample: written, right minus left (|skew|)",
    );
    let mut to_wire = Measure::new("command_to_wire", "lens command to on the wire");
    let mut settled = Measure::new("command_to_settled", "lens command to settled (readback)");
    let mut subframe = Measure::new(
        "subframe_timing_error",
        "sub-frame start error against the programmed period",
    );

    // The photodiode watches phase 1: the patch held black first, so that its first edge
    // anchors the match.
    if photodiode {
        state.display().marker().hold_black(true);
        tokio::time::sleep(photon_hold(cfg.display.frame_hz)).await;
        dioptra_core::lock(&photon_log).recording = true;
        state.display().marker().hold_black(false);
    }
    // 1. Gaze to lens command written: the rig follows gaze as `dioptra serve` does.
    let phase_limit = Duration::from_secs(30.max(args.trials as u64 / 4).min(300));
    let phase_end = tokio::time::Instant::now() + phase_limit;
    // What arrived while the devices connected would count its wait: drop it.
    while rx.try_recv().is_ok() {}
    let mut handed: Vec<(LensId, u64, Timestamp)> = Vec::new();
    // The host paths of one decision's commands (handed at the same time), by lens, until
    // every lens's is written.
    let mut decision: Option<(Timestamp, Vec<Option<f64>>)> = None;
    let mut skew_sum = 0.0f64;
    let mut gaze_samples = 0u64;
    let mut gaze_commands = 0u64;
    while (host_path.hist.len() as usize) < args.trials && tokio::time::Instant::now() < phase_end {
        let seen = tokio::select! {
            s = rx.recv() => s,
            _ = tokio::time::sleep_until(phase_end) => None,
        };
        match seen {
            Some(Seen::Input(DeviceInput::Gaze(..))) => gaze_samples += 1,
            Some(Seen::LensCommand(lens, id, _, at)) => handed.push((lens, id, at)),
            Some(Seen::Input(DeviceInput::LensWire {
                lens,
                id,
                wire_time,
                host_path: path,
                ..
            })) => {
                let Some(&(_, _, at)) = handed.iter().rev().find(|h| h.1 == id) else {
                    continue;
                };
                to_wire.record_us(ts_us(at, wire_time));
                let Some(p) = path else { continue };
                let us = p.as_secs_f64() * 1e6;
                if decision.as_ref().is_none_or(|d| d.0 != at) {
                    decision = Some((at, vec![None; lenses]));
                }
                let Some((_, paths)) = decision.as_mut() else {
                    continue;
                };
                if let Some(slot) = paths.get_mut(lens.index()) {
                    *slot = Some(us);
                }
                // Every lens's command of this sample is written: the slowest is the path.
                if paths.iter().all(Option::is_some) {
                    let all: Vec<f64> = paths.iter().flatten().copied().collect();
                    gaze_commands += 1;
                    host_path.record_us(all.iter().copied().fold(0.0, f64::max));
                    if let [l, r] = all[..] {
                        skew.record_us((r - l).abs());
                        skew_sum += r - l;
                    }
                    decision = None;
                }
            }
            _ => {}
        }
    }
    host_path.note = if lenses > 1 {
        format!(
            "{gaze_samples} gaze samples in; {gaze_commands} focus changes caused by a gaze sample, each timed (wall clock) from the gaze task receiving the sample from its driver to both lens drivers having written their commands (the later of the two), through the rig's loop and scheduler as `dioptra serve` runs them"
        )
    } else {
        format!(
            "{gaze_samples} gaze samples in; {gaze_commands} lens commands caused by a gaze sample, each timed (wall clock) from the gaze task receiving the sample from its driver to the lens driver having written the command, through the rig's loop and scheduler as `dioptra serve` runs them"
        )
    };
    let n_skew = skew.hist.len();
    skew.signed_mean_us = (n_skew > 0).then(|| skew_sum / n_skew as f64);
    skew.note = format!(
        "{n_skew} focus changes sent to both lenses: the right lens's command written less the left's (wall clock, from the same gaze sample); the loop hands both to their lens tasks back to back, left first"
    );
    println!("gaze to lens command: {gaze_commands} samples ({gaze_samples} gaze samples)");
    let optical = if photodiode {
        let until = state.clock().now();
        let log = std::mem::take(&mut *dioptra_core::lock(&photon_log));
        match dioptra_rig::photons::analyse(&log, until, MAX_PHOTON_LATENCY) {
            Ok(r) => {
                println!(
                    "photons: {} edges ({} lost), {} of {} patch changes matched; {} refreshes judged, {} duplicated; {} frames missed",
                    r.edges,
                    r.edges_lost,
                    r.matched,
                    r.transitions,
                    r.refreshes_checked,
                    r.refreshes_wrong.len(),
                    r.frames_never_seen.len()
                );
                Optical::Measured(r)
            }
            Err(why) => {
                println!("photons: no optical measurement: {why}");
                Optical::Failed(why)
            }
        }
    } else {
        println!("photons: skipped (the config names no devices.photodiode)");
        Optical::NoPhotodiode
    };

    // 2. Lens steps through manual focus, timed to the first readback at the commanded power.
    let r = cfg.optics.lens_range;
    let (lo, hi) = (
        r.min + 0.25 * (r.max - r.min),
        r.min + 0.75 * (r.max - r.min),
    );
    let mut unsettled = 0usize;
    for i in 0..args.trials {
        // The lens power to reach, asked for as the focus it gives through the optics map.
        let p = if i % 2 == 0 { hi } else { lo };
        let focus = state
            .optics()
            .of(dioptra_rig::devices::LensId::FIRST)
            .focus_of(dioptra_core::Diopters(p))
            .0;
        while rx.try_recv().is_ok() {}
        state
            .control(Control::ManualFocus(Some(focus)))
            .await
            .map_err(|e| anyhow::anyhow!("manual focus {focus} D was refused: {e}"))?;
        let end = tokio::time::Instant::now() + STEP_TIMEOUT;
        // Each lens's command, whether it is on the wire, and when it settled.
        // (Each lens is commanded its own power for the focus: its eye's optics map.)
        let mut command: Vec<Option<(u64, f32, Timestamp)>> = vec![None; lenses];
        let mut wired = vec![false; lenses];
        let mut settled_at: Vec<Option<Timestamp>> = vec![None; lenses];
        let mut done = false;
        while tokio::time::Instant::now() < end {
            let seen = tokio::select! {
                s = rx.recv() => s,
                _ = tokio::time::sleep_until(end) => None,
            };
            match seen {
                Some(Seen::LensCommand(lens, id, power, at)) => {
                    if let Some(c) = command.get_mut(lens.index()) {
                        *c = Some((id, power, at));
                    }
                }
                Some(Seen::Input(DeviceInput::LensWire {
                    lens,
                    id,
                    wire_time,
                    ..
                })) if command
                    .get(lens.index())
                    .copied()
                    .flatten()
                    .is_some_and(|c| c.0 == id) =>
                {
                    if let Some(Some((_, _, at))) = command.get(lens.index()) {
                        to_wire.record_us(ts_us(*at, wire_time));
                    }
                    wired[lens.index()] = true;
                }
                Some(Seen::Input(DeviceInput::LensState(lens, s)))
                    if wired.get(lens.index()) == Some(&true)
                        && settled_at[lens.index()].is_none()
                        && command[lens.index()]
                            .is_some_and(|c| (s.power.0 - c.1).abs() <= SETTLE_TOLERANCE_D)
                        && s.settled != Some(false) =>
                {
                    settled_at[lens.index()] = Some(s.host_time);
                    // Every lens settled: from the (first) command to the last settle.
                    if settled_at.iter().all(Option::is_some) {
                        let from = command.iter().flatten().map(|c| c.2).min();
                        let last = settled_at.iter().flatten().max().copied();
                        if let (Some(at), Some(t)) = (from, last) {
                            settled.record_us(ts_us(at, t));
                        }
                        done = true;
                        break;
                    }
                }
                None if tokio::time::Instant::now() >= end => break,
                _ => {}
            }
        }
        if !done {
            unsettled += 1;
        }
    }
    let _ = state.control(Control::ManualFocus(None)).await;
    settled.note = format!(
        "{} steps between lens powers {lo:.2} and {hi:.2} D (manual focus through the rig's loop and its optics map: {}); settled = first readback within {SETTLE_TOLERANCE_D} D not reporting moving; readbacks every {} ms (devices.lens.poll_ms), so figures are quantised to it; {unsettled} steps not settled within {} ms. A photodiode watches the display, not the lens: settling is the lens's own readback",
        args.trials,
        state.optics().of(dioptra_rig::devices::LensId::FIRST).describe(),
        state.devices().settings().lens_poll.as_millis(),
        STEP_TIMEOUT.as_millis()
    );
    println!(
        "lens steps: {} settled, {unsettled} not",
        settled.hist.len()
    );
    to_wire.note =
        "from the loop handing the command to the lens task to the driver's write completing"
            .into();

    // 3. Sub-frame timing against the programmed schedule, in multifocal mode.
    let mut measures = vec![host_path, to_wire, settled];
    if lenses > 1 {
        measures.insert(1, skew);
    }
    if let Optical::Measured(r) = &optical {
        measures.extend(photon_measures(r, cfg));
    }
    let sync_driver = cfg.devices.sync.as_ref().map(|s| s.driver);
    if sync_driver == Some(SyncDriver::Dlpc350) {
        // Its driver predicts sub-frame starts from the programmed sequence (the controller
        // reports none), so comparing them with that program would measure nothing.
        println!(
            "sub-frame timing: skipped (the DLPC350 reports no sub-frame times: its driver \
             predicts them from the programmed sequence, so there is nothing to compare)"
        );
    } else if sync_driver.is_some() {
        let period_us = 1e6 / cfg.optics.subframe_hz;
        let planes = cfg.optics.planes.len();
        let before = state.loop_status().mode.unwrap_or(cfg.mode);
        state
            .control(Control::Mode(Mode::Multifocal))
            .await
            .map_err(|e| anyhow::anyhow!("cannot switch to multifocal mode: {e}"))?;
        let end = tokio::time::Instant::now()
            + Duration::from_secs(10).max(Duration::from_secs_f64(
                3.0 * args.trials as f64 / cfg.optics.subframe_hz,
            ));
        let (mut last, mut out_of_order, mut faults, mut sum) =
            (None::<(u32, u8, Timestamp)>, 0u64, 0u64, 0.0f64);
        while (subframe.hist.len() as usize) < args.trials && tokio::time::Instant::now() < end {
            let seen = tokio::select! {
                s = rx.recv() => s,
                _ = tokio::time::sleep_until(end) => None,
            };
            match seen {
                Some(Seen::Input(DeviceInput::Sync(SequencerEvent::SubframeStart {
                    frame,
                    plane_index,
                    device_time,
                    ..
                }))) => {
                    if let Some((f0, p0, t0)) = last {
                        let expected_plane = (usize::from(p0) + 1) % planes.max(1);
                        if usize::from(plane_index) != expected_plane {
                            out_of_order += 1;
                        }
                        // Consecutive sub-frames of one running sequence only.
                        if frame >= f0 {
                            let err = ts_us(t0, device_time) - period_us;
                            subframe.record_us(err.abs());
                            sum += err;
                        }
                    }
                    last = Some((frame, plane_index, device_time));
                }
                Some(Seen::Input(DeviceInput::Sync(SequencerEvent::Fault { .. }))) => faults += 1,
                _ => {}
            }
        }
        let _ = state.control(Control::Mode(before)).await;
        let n = subframe.hist.len();
        subframe.signed_mean_us = (n > 0).then(|| sum / n as f64);
        subframe.note = format!(
            "{n} intervals between sub-frame starts (sync board clock) against the programmed {period_us:.1} us ({} Hz, {planes} planes); histogram of |error|; {out_of_order} sub-frames out of the programmed plane order; {faults} faults (late settle, missed vsync)",
            cfg.optics.subframe_hz
        );
        println!("sub-frames: {n} intervals, {out_of_order} out of order, {faults} faults");
        measures.push(subframe);
    } else {
        println!("sub-frame timing: skipped (the config names no devices.sync)");
    }
    // 4. Content latency: the harness is the application of a stream rig.
    use dioptra_rig::config::ContentSource;
    let source = cfg.content.source;
    let pushed = if source == ContentSource::Stream {
        let n = push_stream_frames(&state, args.trials, cfg.display.frame_hz).await;
        // The last frames reach the display.
        tokio::time::sleep(Duration::from_millis(200)).await;
        println!("content: {n} of {} stream frames accepted", args.trials);
        Some(n)
    } else {
        None
    };
    state.cancel().cancel();
    let report = rig.wait().await;
    if !report.ok() {
        println!(
            "the rig did not stop cleanly: {}",
            report.problems().join("; ")
        );
    }
    let mut latency = None;
    // The hook sends the figures as the loop stops, then is dropped with the rig.
    while let Ok(Some(s)) = tokio::time::timeout(Duration::from_secs(5), rx.recv()).await {
        if let Seen::Stopped(l) = s {
            latency = Some(l);
            break;
        }
    }
    if source != ContentSource::Scene {
        let Some(l) = latency else {
            bail!("the rig's loop stopped without its latency figures");
        };
        use dioptra_sched::Stage;
        let how = match pushed {
            Some(n) => format!(
                "{n} frames pushed by the harness through the stream's PUT /frame path (copy, checks, conversion) at display.frame_hz = {} Hz, {}x{}",
                cfg.display.frame_hz, cfg.display.width, cfg.display.height
            ),
            None => "the files source's frames over the whole run, arrival being each frame's due time in the sequence".into(),
        };
        let received = l.stage(Stage::ContentReceived);
        let shown = l.stage(Stage::ContentToPresented);
        println!(
            "content: {} frames received, {} shown (the rest replaced by newer ones first)",
            received.len(),
            shown.len()
        );
        measures.push(from_latency(
            "content_received",
            "content frame arrival to ready",
            received,
            format!("{how}; from a frame's arrival to its being ready to render, for each frame the display took up (frames a newer one replaced first are not counted)"),
        ));
        measures.push(from_latency(
            "content_to_presented",
            "content frame arrival to presented",
            shown,
            format!("{how}; from a frame's arrival to the display time of the first frame showing it (frames replaced before any frame showed them are not counted)"),
        ));
    }
    Ok((measures, optical))
}

fn median_ms(v: impl Iterator<Item = Duration>) -> f64 {
    let mut v: Vec<Duration> = v.collect();
    v.sort_unstable();
    v.get(v.len() / 2)
        .map_or(f64::NAN, |d| d.as_secs_f64() * 1e3)
}

/// The photon figures as measurements.
fn photon_measures(r: &PhotonReport, cfg: &RigConfig) -> Vec<Measure> {
    let patch = cfg.display.marker_patch.as_ref();
    let toggled = patch.map_or(String::new(), |m| {
        m.toggle_on
            .iter()
            .map(|e| e.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    });
    let how = format!(
        "the photodiode's edges matched to the presents that changed the marker patch (toggled on: {toggled}); {} of {} changes matched, refresh period {:.3} ms, lit {:.3} ms per refresh; {} edges, {} lost",
        r.matched,
        r.transitions,
        r.refresh_period.as_secs_f64() * 1e3,
        r.pulse_width.as_secs_f64() * 1e3,
        r.edges,
        r.edges_lost
    );
    let mut vsync = Measure::new("vsync_to_photons", "vsync to photons");
    r.vsync_to_photons
        .iter()
        .for_each(|d| vsync.record_us(d.as_secs_f64() * 1e6));
    vsync.note = format!(
        "from the vsync a frame is shown from (as the display sink reports it) to the photodiode's edge: the display's latency (scan-out to the patch, pixel response, any compositor frames); {how}"
    );
    let mut presented = Measure::new("frame_presented_to_photons", "frame presented to photons");
    r.presented_to_photons
        .iter()
        .for_each(|d| presented.record_us(d.as_secs_f64() * 1e6));
    presented.note = format!(
        "from the loop handing the frame to the display sink to the photodiode's edge; {how}"
    );
    let mut gaze = Measure::new("gaze_to_photons", "gaze sample to photons");
    r.gaze_to_photons
        .iter()
        .for_each(|g| gaze.record_us(g.total.as_secs_f64() * 1e6));
    let g = &r.gaze_to_photons;
    gaze.note = format!(
        "end to end, for {} lens commands a gaze sample caused: from the gaze task receiving the sample to the light of the first frame rendered for the new focus (the first requested after the command). Medians of its parts: gaze to lens command {:.3} ms, command to that frame's vsync (the next frame request, the render, the wait for vsync) {:.3} ms, vsync to photons {:.3} ms. The tracker's own delay (exposure to receipt) comes before it",
        g.len(),
        median_ms(g.iter().map(|g| g.gaze_to_command)),
        median_ms(g.iter().map(|g| g.command_to_vsync)),
        median_ms(g.iter().map(|g| g.vsync_to_photons)),
    );
    vec![vsync, presented, gaze]
}

/// The optical frame count, for summary.txt and summary.json.
fn optical_json(optical: &Optical) -> serde_json::Value {
    match optical {
        Optical::NoPhotodiode => json!({
            "measured": false,
            "why": "no photodiode is configured ([devices.photodiode] and display.marker_patch), so there is no optical measurement",
        }),
        Optical::Failed(why) => json!({ "measured": false, "why": why }),
        Optical::Measured(r) => json!({
            "measured": true,
            "refreshes_checked": r.refreshes_checked,
            "refreshes_duplicated": r.refreshes_wrong.len(),
            "refreshes_unknown": r.refreshes_unknown,
            "duplicated_vsyncs_ns": r.refreshes_wrong.iter().take(100).map(|w| w.0 .0).collect::<Vec<_>>(),
            "frames_checked": r.frames_checked,
            "frames_missed": r.frames_never_seen.len(),
            "missed_frames": r.frames_never_seen.iter().take(100).collect::<Vec<_>>(),
            "edges": r.edges,
            "edges_lost": r.edges_lost,
            "patch_changes": r.transitions,
            "patch_changes_matched": r.matched,
        }),
    }
}

fn optical_text(optical: &Optical) -> String {
    match optical {
        Optical::NoPhotodiode => "no optical measurement: no photodiode is configured ([devices.photodiode] and display.marker_patch)".into(),
        Optical::Failed(why) => format!("no optical measurement: {why}"),
        Optical::Measured(r) => format!(
            "frames seen optically: {} refreshes judged by the light in their lit time, {} duplicated (showed another frame's patch than their own: the previous image again, their frame dropped or late), {} not judged (edges lost around them); {} frames judged, {} missed (never seen on any of their refreshes)",
            r.refreshes_checked,
            r.refreshes_wrong.len(),
            r.refreshes_unknown,
            r.frames_checked,
            r.frames_never_seen.len()
        ),
    }
}

fn stats_json(m: &Measure) -> serde_json::Value {
    let h = &m.hist;
    let q = |p: f64| (!h.is_empty()).then(|| h.value_at_quantile(p));
    json!({
        "title": m.title,
        "count": h.len(),
        "min_us": (!h.is_empty()).then(|| h.min()),
        "p50_us": q(0.5),
        "p90_us": q(0.9),
        "p99_us": q(0.99),
        "max_us": (!h.is_empty()).then(|| h.max()),
        "mean_us": (!h.is_empty()).then(|| h.mean()),
        "signed_mean_us": m.signed_mean_us,
        "note": m.note,
    })
}

fn write_outputs(
    out: &Path,
    config: &Path,
    banner: &str,
    simulated: bool,
    measures: &[Measure],
    optical: &Optical,
) -> Result<()> {
    let mut txt = format!(
        "dioptra hil --config {}\n{banner}\n\nvalues in microseconds (HdrHistogram, 3 significant digits)\n\n{}\n",
        config.display(),
        optical_text(optical)
    );
    println!("  {}", optical_text(optical));
    for m in measures {
        let h = &m.hist;
        txt.push_str(&format!("\n## {} ({})\n{}\n", m.title, m.key, m.note));
        if h.is_empty() {
            txt.push_str("no samples\n");
            println!("  {}: no samples", m.title);
            continue;
        }
        let line = format!(
            "n = {}, min {}, p50 {}, p90 {}, p99 {}, max {}, mean {:.1}{}",
            h.len(),
            h.min(),
            h.value_at_quantile(0.5),
            h.value_at_quantile(0.9),
            h.value_at_quantile(0.99),
            h.max(),
            h.mean(),
            m.signed_mean_us
                .map(|s| format!(", signed mean {s:.2}"))
                .unwrap_or_default()
        );
        println!("  {}: {line} us", m.title);
        txt.push_str(&line);
        txt.push_str("\n       value   percentile   total count\n");
        for v in h.iter_quantiles(1) {
            txt.push_str(&format!(
                "{:>12} {:>12.6} {:>13}\n",
                v.value_iterated_to(),
                v.quantile_iterated_to(),
                v.count_since_last_iteration()
            ));
        }
        histogram_png(&out.join(format!("{}.png", m.key)), m, simulated)?;
    }
    std::fs::write(out.join("summary.txt"), txt)
        .with_context(|| format!("cannot write {}", out.join("summary.txt").display()))?;
    let js = json!({
        "config": config.display().to_string(),
        "simulated": simulated,
        "devices": banner,
        "measurements": measures.iter().map(|m| (m.key.to_string(), stats_json(m))).collect::<serde_json::Map<_, _>>(),
        "optical_frames": optical_json(optical),
    });
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&js)?)
        .with_context(|| format!("cannot write {}", out.join("summary.json").display()))?;
    Ok(())
}

fn histogram_png(path: &Path, m: &Measure, simulated: bool) -> Result<()> {
    crate::common::charts::font();
    let h = &m.hist;
    let top = h.value_at_quantile(0.999).max(1);
    let nbins = 40u64;
    let bin = (top / nbins).max(1);
    let mut counts = vec![0u64; nbins as usize + 1];
    for v in h.iter_recorded() {
        let i = ((v.value_iterated_to() / bin) as usize).min(nbins as usize);
        counts[i] += v.count_at_value();
    }
    let ymax = counts.iter().copied().max().unwrap_or(1).max(1);
    let err = |e: &dyn std::fmt::Debug| anyhow::anyhow!("drawing {} failed: {e:?}", path.display());
    let root = BitMapBackend::new(path, (800, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let title = format!("{}{}", m.title, if simulated { " (SIMULATED)" } else { "" });
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(
            0f64..((nbins + 1) * bin) as f64 / 1e3,
            0u64..ymax + ymax / 10 + 1,
        )
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("ms")
        .y_desc("count")
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .draw_series(counts.iter().enumerate().map(|(i, &c)| {
            let x0 = (i as u64 * bin) as f64 / 1e3;
            let x1 = ((i as u64 + 1) * bin) as f64 / 1e3;
            Rectangle::new([(x0, 0), (x1, c)], BLUE.mix(0.6).filled())
        }))
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}
