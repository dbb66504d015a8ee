//! The whole loop on simulated devices and tokio's paused clock, run by dioptra-rig as
//! `dioptra serve` runs it: the scheduler with the real lens, eye-tracker and sync-board
//! drivers against their simulators, the daemon's device tasks and loop.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{DepthMap, Diopters, Plane, Timestamp};
use dioptra_rig::config::{Mode, RigConfig, EXAMPLE_SIM_RIG};
use dioptra_rig::devices::LensId;
use dioptra_rig::recording::Rec;
use dioptra_rig::render::rgbd::RgbdRenderer;
use dioptra_rig::simulated_rig::{Action, Run, ScriptedRenderer, SimRun};
use dioptra_rig::{Rig, RigSetup};
use dioptra_sched::{Command, FocusReason, LinkStatus};
use dioptra_sim::gaze::generator::{Segment, Target, TruePhase};
use dioptra_sim::gaze::Scene;

const NEAR_D: f32 = 2.0; // 0.5 m
const FAR_D: f32 = 0.5; // 2 m

/// Two objects filling the field: left half at 0.5 m, right half at 2 m (256 px over 20°).
fn split_depth() -> Arc<DepthMap> {
    let w = 256;
    let mut p = Plane::new(w, w, FAR_D);
    for y in 0..w {
        for x in 0..w / 2 {
            p.data_mut()[y * w + x] = NEAR_D;
        }
    }
    Arc::new(DepthMap::from_diopters(p).unwrap())
}

fn target(yaw: f64, diopters: f32) -> Target {
    Target {
        yaw_deg: yaw,
        pitch_deg: 1.0,
        diopters: f64::from(diopters),
    }
}

/// Fixations alternating between the near object (left) and the far one (right).
fn near_far(ms: u32) -> Scene {
    Scene {
        name: "near-far".into(),
        targets: vec![target(-5.0, NEAR_D), target(5.0, FAR_D)],
        script: vec![
            Segment::Fixate { target: 0, ms },
            Segment::Fixate { target: 1, ms },
        ],
    }
}

/// The example rig in `mode` with its tracker at 500 Hz, `edit` applied to its config text.
fn config(mode: Mode, edit: impl Fn(String) -> String) -> RigConfig {
    let method = dioptra_sched::RenderMethod::default_for(mode.sched()).as_str();
    let text = EXAMPLE_SIM_RIG
        .replace(
            "mode = \"varifocal\"",
            &format!("mode = \"{}\"", mode.as_str()),
        )
        .replace("method = \"gather\"", &format!("method = \"{method}\""))
        .replace("sim_rate_hz = 250.0", "sim_rate_hz = 500.0");
    RigConfig::parse(&edit(text)).unwrap()
}

fn options(mode: Mode, scene: Scene, seconds: f64) -> SimRun {
    let mut o = SimRun::new(config(mode, |t| t), Duration::from_secs_f64(seconds)).unwrap();
    o.spec.gaze_scene = scene;
    // Blinks only where a test scripts them.
    o.spec.gaze.blink_rate_hz = 0.0;
    o
}

async fn go(opts: SimRun, render: Duration) -> Run {
    let planes = opts.cfg.optics.planes.len();
    let renderer = ScriptedRenderer::new(planes, move |_| render);
    let content = ScriptedRenderer::still(&split_depth());
    opts.run(Some(content), Arc::new(renderer), None)
        .await
        .unwrap()
}

/// True saccades as (start, landing) times, µs, with the depth of the target landed on.
fn saccades(r: &Run) -> Vec<(u64, u64, f64)> {
    let mut out = Vec::new();
    let mut start = None;
    for w in r.log.truth.windows(2) {
        match (w[0].phase, w[1].phase) {
            (p, TruePhase::Saccade) if p != TruePhase::Saccade => start = Some(w[1].time_us),
            (TruePhase::Saccade, TruePhase::Fixation) => {
                if let Some(s) = start.take() {
                    out.push((s, w[1].time_us, w[1].target_diopters));
                }
            }
            _ => {}
        }
    }
    out
}

fn us(t: Timestamp) -> u64 {
    t.as_micros()
}

#[tokio::test(start_paused = true)]
async fn a_saccade_between_near_and_far_moves_the_lens_by_landing_and_it_settles_in_time() {
    let opts = options(Mode::Varifocal, near_far(500), 3.2);
    let settle = opts.spec.lens.settle_time;
    let period_us = (1e6 / opts.spec.gaze.rate_hz) as u64;
    let max_delivery_us = opts.spec.gaze_latency_us.0 + opts.spec.gaze_latency_us.1;
    let r = go(opts, Duration::from_millis(4)).await;
    let sacc = saccades(&r);
    assert!(sacc.len() >= 5, "{sacc:?}");
    let cmds = &r.log.lens_commands;
    for &(start, land, depth) in &sacc {
        // The first command to the new depth after the saccade began.
        let c = cmds
            .iter()
            .find(|c| us(c.t) >= start && (f64::from(c.power.0) - depth).abs() < 0.05)
            .unwrap_or_else(|| panic!("no command to {depth} D after {start} µs: {cmds:?}"));
        // Within one gaze sample of the fixation's onset, counting the sample's delivery.
        assert!(
            us(c.t) <= land + max_delivery_us + period_us,
            "command at {} µs, landing at {land} µs",
            us(c.t)
        );
        // Nothing else was sent for this fixation, so settling is timed from that command.
        let next = cmds
            .iter()
            .find(|n| n.t > c.t && n.reason != FocusReason::Park)
            .map_or(u64::MAX, |n| us(n.t));
        assert!(next > land + 300_000, "a second command at {next} µs");
        // Parking at the end of the run also ends the window.
        let next = cmds
            .iter()
            .find(|n| n.t > c.t)
            .map_or(u64::MAX, |n| us(n.t));
        // The real (simulated) lens settles within 2 % of the step within its settle time
        // of the command reaching the wire (probes are 1 ms apart).
        let wire = us(c.wire.expect("the command went on the wire"));
        let prev = r
            .log
            .probes
            .iter()
            .rev()
            .find(|p| us(p.t) <= wire)
            .and_then(|p| p.lens_power)
            .unwrap();
        let tol = 0.02 * (c.power.0 - prev.0).abs().max(0.5);
        let settled_at = r
            .log
            .probes
            .iter()
            .filter(|p| us(p.t) >= wire && us(p.t) < next.min(wire + 200_000))
            .scan(None, |since: &mut Option<u64>, p| {
                let ok = (p.lens_power.unwrap().0 - c.power.0).abs() <= tol;
                *since = if ok { since.or(Some(us(p.t))) } else { None };
                Some(*since)
            })
            .last()
            .flatten()
            .expect("the lens never settled");
        let took = Duration::from_micros(settled_at - wire);
        assert!(
            took <= settle + Duration::from_millis(1),
            "settled {took:?} after the wire, settle time {settle:?}"
        );
        // And it had settled by (or within a settle time of) the eye landing.
        assert!(settled_at <= land + 1000 * settle.as_millis() as u64);
    }
    let st = r.status;
    assert_eq!(st.counters.saccades as usize, sacc.len());
    assert!(r.log.gaze_errors.is_empty(), "{:?}", r.log.gaze_errors);
}

#[tokio::test(start_paused = true)]
async fn a_blink_holds_focus() {
    let scene = Scene {
        name: "blink".into(),
        targets: vec![target(-5.0, NEAR_D)],
        script: vec![
            Segment::Fixate { target: 0, ms: 600 },
            Segment::Blink { ms: 180 },
        ],
    };
    let r = go(
        options(Mode::Varifocal, scene, 2.5),
        Duration::from_millis(4),
    )
    .await;
    let blinks: Vec<u64> = r
        .log
        .truth
        .iter()
        .filter(|s| s.phase == TruePhase::Blink)
        .map(|s| s.time_us)
        .collect();
    assert!(blinks.len() > 200, "{} blink samples", blinks.len());
    assert!(r.status.counters.blinks >= 3);
    // One command at the first fixation, and none for the blinks or after them (park aside).
    let gaze_cmds: Vec<_> = r
        .log
        .lens_commands
        .iter()
        .filter(|c| c.reason != FocusReason::Park)
        .collect();
    assert_eq!(gaze_cmds.len(), 1, "{gaze_cmds:?}");
    assert_eq!(gaze_cmds[0].power, Diopters(NEAR_D));
    // The real lens stays where it was through every blink.
    let in_blink = r
        .log
        .probes
        .iter()
        .filter(|p| blinks.binary_search(&(us(p.t) / 2000 * 2000)).is_ok());
    let mut n = 0;
    for p in in_blink {
        n += 1;
        assert!(
            (p.lens_power.unwrap().0 - NEAR_D).abs() < 0.03,
            "{:?} at {}",
            p.lens_power,
            p.t
        );
    }
    assert!(n > 200, "{n} probes in blinks");
}

/// Lens commands over a 5 s fixation right on the near/far edge with a noisy tracker (drift
/// and microsaccades carry the gaze back and forth across it), the eyes verged between the
/// two surfaces so vergence favours neither.
async fn edge_fixation(policy: impl FnOnce(&mut dioptra_sched::SchedulerConfig)) -> Run {
    let scene = Scene {
        name: "edge".into(),
        targets: vec![target(0.0, 0.5 * (NEAR_D + FAR_D))],
        script: vec![Segment::Fixate {
            target: 0,
            ms: 10_000,
        }],
    };
    let mut opts = options(Mode::Varifocal, scene, 5.0);
    opts.spec.gaze.noise_deg = 0.1;
    opts.probe = None;
    policy(&mut opts.sched);
    go(opts, Duration::from_millis(4)).await
}

#[tokio::test(start_paused = true)]
async fn a_noisy_fixation_at_an_edge_does_not_make_the_lens_chase_noise() {
    let gaze_cmds = |r: &Run| {
        r.log
            .lens_commands
            .iter()
            .filter(|c| c.reason != FocusReason::Park)
            .count()
    };
    let r = edge_fixation(|_| {}).await;
    let n = gaze_cmds(&r);
    // The minimum interval bounds it at 33 in 5 s; smoothing, the confirm time and the
    // deadband leave only the times the drifting gaze really stayed across the edge.
    assert!(
        n <= 10,
        "{n} lens commands in 5 s: {:?}",
        r.log.lens_commands
    );
    assert!(r.log.gaze_samples > 2000);
    // The same gaze read naively (unsmoothed, every change sent at once) does chase: the
    // check above does not pass for want of noise.
    let naive = edge_fixation(|c| {
        c.focus.deadband_d = 0.0;
        c.focus.confirm = Duration::ZERO;
        c.focus.min_interval = Duration::ZERO;
        c.gaze.smoothing.min_cutoff_hz = 1000.0;
    })
    .await;
    assert!(
        gaze_cmds(&naive) > 5 * n.max(1),
        "naive: {}",
        gaze_cmds(&naive)
    );
}

/// Multifocal with the sync board for 1000 frames; returns (misses, presented, run).
async fn multifocal(render: Duration) -> (u64, u64, Run) {
    let scene = Scene::named("saccades").unwrap();
    let mut opts = options(Mode::Multifocal, scene, 1000.0 / 60.0 + 0.05);
    opts.probe = None;
    let r = go(opts, render).await;
    let c = r.status.counters;
    (c.misses, c.frames_presented, r)
}

/// Checks lockstep: layer i in sub-frame i, the four layers of a cycle from one frame.
/// Returns the number of cycles whose frame repeated the previous cycle's.
fn check_lockstep(r: &Run) -> u64 {
    let mut layers: Vec<(u32, u8, u64, bool)> = Vec::new();
    for (_, c) in &r.log.presents {
        if let Command::PresentLayer {
            frame,
            layer,
            sync_frame,
            repeat,
            ..
        } = *c
        {
            layers.push((sync_frame, layer, frame.0, repeat));
        }
    }
    let mut repeats = 0;
    let mut prev: Option<u64> = None;
    for (k, l) in layers.iter().enumerate() {
        if k > 0 {
            let p = layers[k - 1];
            let want = if p.1 == 3 {
                (p.0 + 1, 0)
            } else {
                (p.0, p.1 + 1)
            };
            assert_eq!((l.0, l.1), want, "sub-frames out of step at {k}");
        }
        if l.1 == 0 {
            if prev == Some(l.2) {
                repeats += 1;
                assert!(l.3, "a repeat not flagged at {k}");
            } else {
                assert!(!l.3);
            }
            prev = Some(l.2);
        } else {
            assert_eq!(
                Some(l.2),
                prev,
                "layers of one cycle from two frames at {k}"
            );
        }
    }
    repeats
}

#[tokio::test(start_paused = true)]
async fn multifocal_runs_1000_frames_without_a_miss_when_rendering_keeps_up() {
    let (misses, presented, r) = multifocal(Duration::from_millis(5)).await;
    assert!(presented >= 1000, "{presented} frames");
    assert_eq!(misses, 0);
    assert_eq!(check_lockstep(&r), 0);
    assert!(r.log.sequencer_events >= 4000);
}

#[tokio::test(start_paused = true)]
async fn multifocal_counts_misses_when_rendering_is_slow() {
    // 1.5 frame periods per frame: every other cycle must show its predecessor again.
    let (misses, presented, r) = multifocal(Duration::from_millis(25)).await;
    assert!(presented >= 999, "{presented} frames");
    assert_eq!(misses, check_lockstep(&r), "counted vs seen");
    let share = misses as f64 / presented as f64;
    assert!((share - 0.5).abs() < 0.01, "{misses} of {presented}");
}

#[tokio::test(start_paused = true)]
async fn unplugging_the_lens_mid_run_is_survived_and_recovered() {
    let mut opts = options(Mode::Varifocal, near_far(400), 4.0);
    opts.actions = vec![
        (Duration::from_millis(1300), Action::UnplugLens),
        (Duration::from_millis(1900), Action::ReplugLens),
    ];
    let r = go(opts, Duration::from_millis(4)).await;
    let links: Vec<LinkStatus> = r.log.link_events.iter().map(|l| l.1).collect();
    assert_eq!(
        links,
        [
            LinkStatus::Connected,
            LinkStatus::Lost,
            LinkStatus::Connected
        ]
    );
    assert_eq!(r.lens_opened, 2);
    let (lost_at, back_at) = (r.log.link_events[1].0, r.log.link_events[2].0);
    // Found lost at the first exchange after the pull: a command or the next read-back.
    let poll = r.state.devices().settings().lens_poll;
    assert!(
        us(lost_at) >= 1_300_000 && lost_at.saturating_since(Timestamp(1_300_000_000)) <= poll,
        "{lost_at}"
    );
    // Back at the daemon's first reconnect attempt after the replug (its backoff), plus the
    // connect handshake.
    let replug = Timestamp(1_900_000_000);
    let attempt = r
        .state
        .devices()
        .settings()
        .link
        .attempts_after_loss(16)
        .into_iter()
        .map(|d| lost_at + d)
        .find(|&t| t >= replug)
        .unwrap();
    assert!(
        back_at >= attempt && back_at.saturating_since(attempt) < Duration::from_millis(20),
        "back at {back_at}, the attempt after the replug at {attempt}"
    );
    // Gaze kept flowing while the lens was away.
    let during = r
        .log
        .truth
        .iter()
        .filter(|s| s.time_us > us(lost_at) && s.time_us < us(back_at))
        .count();
    assert!(during > 250, "{during}");
    assert_eq!(r.status.counters.lens_link_losses, 1);
    // After reconnecting, the lens follows the gaze again: at each probe well inside a
    // fixation after the replug, the real lens is at the depth looked at.
    let mut checked = 0;
    for p in r
        .log
        .probes
        .iter()
        .filter(|p| us(p.t) > us(back_at) + 50_000)
    {
        let Some(truth) = r.log.truth.iter().rev().find(|s| s.time_us <= us(p.t)) else {
            continue;
        };
        // 60 ms into a fixation (saccade, detection and settle are over).
        let steady = r
            .log
            .truth
            .iter()
            .filter(|s| s.time_us + 60_000 >= truth.time_us && s.time_us <= truth.time_us)
            .all(|s| s.phase == TruePhase::Fixation);
        if steady && us(p.t) < 4_000_000 {
            let lens = p.lens_power.unwrap().0;
            assert!(
                (f64::from(lens) - truth.target_diopters).abs() < 0.05,
                "at {}: lens {lens}, target {}",
                p.t,
                truth.target_diopters
            );
            checked += 1;
        }
    }
    assert!(checked > 1000, "{checked}");
}

#[tokio::test(start_paused = true)]
async fn shutdown_parks_the_lens() {
    let mut opts = SimRun::new(
        config(Mode::Varifocal, |t| {
            t.replace("park_power = 0.5", "park_power = 0.25")
        }),
        Duration::from_secs(1),
    )
    .unwrap();
    opts.spec.gaze_scene = near_far(300);
    opts.spec.gaze.blink_rate_hz = 0.0;
    let r = go(opts, Duration::from_millis(4)).await;
    let last = r.log.lens_commands.last().unwrap();
    assert_eq!(last.reason, FocusReason::Park);
    assert_eq!(last.power, Diopters(0.25));
    assert!(last.wire.is_some());
    let end = r.log.probes.last().unwrap();
    assert!((end.lens_target.unwrap().0 - 0.25).abs() < 1e-4, "{end:?}");
    assert!((end.lens_power.unwrap().0 - 0.25).abs() < 0.01, "{end:?}");
    assert!(r.status.shutting_down);
    // Frames stop with shutdown.
    let shutdown_at = last.t;
    assert!(r.log.frames_requested.iter().all(|f| f.0 <= shutdown_at));
}

/// The rig `dioptra serve` starts from a config (`Rig::start` of `RigSetup::new`, the API
/// aside) and the simulated rig the demo, eval and these tests run from the same config record
/// the same topics and the same device-task settings.
#[tokio::test(start_paused = true)]
async fn serve_and_the_simulated_rig_build_the_same_rig_from_one_config() {
    let dir = tempfile::tempdir().unwrap();
    // A still scene: the scripted renderer's content does not move either, so both record
    // the same topics.
    let recording_to = |sub: &str| {
        let d = dir.path().join(sub).display().to_string();
        config(Mode::Varifocal, move |t| {
            t.replace("dir = \"recordings\"", &format!("dir = {d:?}"))
                .replace("start = false", "start = true")
                + "\n[content]\nanimate = false\n"
        })
    };
    let served = Rig::start(RigSetup::new(recording_to("serve")))
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(500)).await;
    served.state().cancel().cancel();
    let served = served.wait().await;
    let simulated = SimRun::new(recording_to("sim"), Duration::from_millis(500))
        .unwrap()
        .run(
            Some(ScriptedRenderer::still(&split_depth())),
            Arc::new(ScriptedRenderer::new(4, |_| Duration::from_millis(4))),
            None,
        )
        .await
        .unwrap()
        .report;
    let read = |r: &dioptra_rig::ShutdownReport| {
        let path = &r.recording.as_ref().unwrap().as_ref().unwrap().path;
        let rec = dioptra_rig::recording::read(path).unwrap();
        assert!(rec.complete);
        let topics: BTreeSet<&'static str> = rec.messages.iter().map(|(_, m)| m.topic()).collect();
        let start = rec
            .messages
            .iter()
            .find_map(|(_, m)| match m {
                Rec::Start(s) => Some(s.clone()),
                _ => None,
            })
            .unwrap();
        (topics, start)
    };
    let (served_topics, served_start) = read(&served);
    let (sim_topics, sim_start) = read(&simulated);
    assert_eq!(served_topics, sim_topics);
    assert!(served_topics.contains("/lens/command") && served_topics.contains("/gaze"));
    assert!(!served_start.device_tasks.is_null());
    assert_eq!(served_start.device_tasks, sim_start.device_tasks);
    assert!(served.ok() && simulated.ok(), "{served:?} {simulated:?}");
}

/// The rig's renderer with a fixed render cost on the rig's clock. Without one a frame counts
/// as taking its wall time, so on a loaded machine renders slow enough to skip a scene step
/// made this test fail (shown 19 of 20).
struct FixedCost(RgbdRenderer);

impl dioptra_rig::render::Renderer for FixedCost {
    fn render(
        &self,
        job: &dioptra_rig::render::RenderJob,
        content: &dioptra_rig::content::ContentFrame,
    ) -> Result<dioptra_rig::render::RenderOutput, dioptra_render::RenderError> {
        let mut out = self.0.render(job, content)?;
        out.cost = Some(Duration::from_millis(8));
        Ok(out)
    }
}

/// The daemon's procedural scene moves with the rig's clock: on simulated time each frame it
/// shows is the scene at the last 50 ms step before the frame was asked for, none late, and
/// the recording holds each frame's scene time (what a replay renders).
#[tokio::test(start_paused = true)]
async fn the_procedural_scene_moves_with_rig_time() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().display().to_string();
    let cfg = config(Mode::Varifocal, move |t| {
        t.replace("dir = \"recordings\"", &format!("dir = {d:?}"))
            .replace("start = false", "start = true")
    });
    let renderer =
        FixedCost(RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics).unwrap());
    let r = SimRun::new(cfg, Duration::from_secs(1))
        .unwrap()
        .run(None, Arc::new(renderer), None)
        .await
        .unwrap();
    assert!(r.report.ok(), "{:?}", r.report);
    let content = &r.state.status_json()["content"];
    assert_eq!(content["source"], "scene", "{content}");
    assert_eq!(content["animated"], true, "{content}");
    // Frames of 0, 50, ..., 950 ms (60 Hz frames ask for each), none late.
    assert_eq!(content["shown"], 20, "{content}");
    assert_eq!(content["late"], 0, "{content}");
    assert_eq!(content["scene_time_ms"], 950.0, "{content}");
    let path = &r.report.recording.as_ref().unwrap().as_ref().unwrap().path;
    let rec = dioptra_rig::recording::read(path).unwrap();
    let depths: Vec<(Timestamp, u64)> = rec
        .messages
        .iter()
        .filter_map(|(t, m)| match m {
            Rec::Depth(d) => Some((*t, d.scene_ns.unwrap())),
            _ => None,
        })
        .collect();
    let step = 50_000_000;
    for (k, (t, scene_ns)) in depths.iter().enumerate() {
        assert_eq!(*scene_ns, k as u64 * step, "depth {k} at {t:?}");
        assert!(
            t.0 >= *scene_ns && t.0 < scene_ns + step,
            "depth {k} at {t:?}"
        );
    }
    assert_eq!(depths.len(), 20);
}

/// The example rig with the simulated lens in a thin-lens layout (display 25 cm from the lens,
/// the pupil 15 mm behind it: demand = X / (1 + 0.015 X), X = 4 - lens power) and, if given, a
/// calibration table the rig believes (its text, as a recording would carry it).
fn through_optics(table: Option<String>) -> SimRun {
    let mut text = EXAMPLE_SIM_RIG
        .replace("sim_rate_hz = 250.0", "sim_rate_hz = 500.0")
        .replace(
            "subframe_hz = 240.0\n",
            "subframe_hz = 240.0\n[optics.layout]\ndisplay_distance_m = 0.25\neye_relief_m = 0.015\n",
        );
    let mut tables = std::collections::BTreeMap::new();
    if let Some(t) = table {
        text = text.replace("[optics]\n", "[optics]\ncalibration = \"cal.csv\"\n");
        tables.insert("cal.csv".into(), t);
    }
    let cfg = RigConfig::parse_with_tables(&text, tables).unwrap();
    let mut o = SimRun::new(cfg, Duration::from_secs_f64(3.2)).unwrap();
    o.spec.gaze_scene = near_far(500);
    o.spec.gaze.blink_rate_hz = 0.0;
    o
}

/// The example binocular rig (a lens per eye) with its tracker at 500 Hz, on `scene`.
fn binocular(scene: Scene, seconds: f64) -> SimRun {
    let text = dioptra_rig::config::EXAMPLE_SIM_BINOCULAR_RIG
        .replace("sim_rate_hz = 250.0", "sim_rate_hz = 500.0");
    let cfg = RigConfig::parse(&text).unwrap();
    let mut o = SimRun::new(cfg, Duration::from_secs_f64(seconds)).unwrap();
    o.spec.gaze_scene = scene;
    o.spec.gaze.blink_rate_hz = 0.0;
    o
}

/// A table of the layout's demand every 0.25 D over the lens range, `offset_d` added.
fn layout_table(offset_d: f64) -> String {
    let mut t = String::from("command_d,demand_d\n");
    for k in 0..=20 {
        let c = -1.0 + 0.25 * f64::from(k);
        let x = 4.0 - c;
        t += &format!("{c},{}\n", x / (1.0 + 0.015 * x) + offset_d);
    }
    t
}

/// The median of |where the eye must focus - the depth looked at| while fixating.
fn median_focus_error(r: &Run) -> f64 {
    let mut e: Vec<f64> = r
        .log
        .probes
        .iter()
        .filter(|p| p.phase == dioptra_sched::processing::EyePhase::Fixation)
        .filter_map(|p| Some((f64::from(p.eye_focus?.0) - p.gaze_target_d?).abs()))
        .collect();
    assert!(e.len() > 1000, "{} fixation probes", e.len());
    e.sort_by(f64::total_cmp);
    e[e.len() / 2]
}

#[tokio::test(start_paused = true)]
async fn through_the_optics_the_eye_sees_what_it_looks_at_and_a_wrong_calibration_shows() {
    let render = Duration::from_millis(4);
    // The layout as the rig's map: the lens goes where the formula says.
    let r = go(through_optics(None), render).await;
    assert_eq!(
        r.state
            .optics()
            .of(dioptra_rig::devices::LensId::FIRST)
            .source_name(),
        "layout"
    );
    // Near (2 D) by hand: X = 2 / (1 - 0.03) = 2.061856, command 4 - X = 1.938144 D.
    assert!(
        r.log
            .lens_commands
            .iter()
            .any(|c| (c.power.0 - 1.938144).abs() < 1e-4),
        "{:?}",
        r.log.lens_commands
    );
    let layout = median_focus_error(&r);
    assert!(layout < 0.02, "{layout} D through the layout");
    // A table measured on the same optics: the same.
    let r = go(through_optics(Some(layout_table(0.0))), render).await;
    assert_eq!(
        r.state
            .optics()
            .of(dioptra_rig::devices::LensId::FIRST)
            .source_name(),
        "calibration"
    );
    let calibrated = median_focus_error(&r);
    assert!(calibrated < 0.02, "{calibrated} D with a good table");
    // A table 0.5 D off (measured with the display moved): the eye is 0.5 D out of focus.
    let r = go(through_optics(Some(layout_table(0.5))), render).await;
    let wrong = median_focus_error(&r);
    assert!(
        (wrong - 0.5).abs() < 0.03,
        "{wrong} D with a table 0.5 D off"
    );
}

/// The example rig in varifocal mode with a simulated photodiode over a marker patch toggled
/// every frame, `edit` applied to its config text.
fn photodiode_rig(photodiode: &str, display: &str) -> RigConfig {
    config(Mode::Varifocal, |t| {
        let t = t.replace(
            "png_every = 0 ",
            &format!(
                "marker_patch = {{ corner = \"top-left\", size = 8 }}\n{display}\npng_every = 0 "
            ),
        );
        format!("{t}\n[devices.photodiode]\n{photodiode}\n")
    })
}

/// Runs `cfg` for `seconds` with the patch held black for the first half second, recording
/// what the photon match needs; returns the run and the match.
async fn photons(cfg: RigConfig, seconds: f64) -> (Run, dioptra_rig::photons::PhotonReport) {
    use dioptra_rig::photons::{analyse, PhotonLog, PhotonRecorder};
    let log = Arc::new(std::sync::Mutex::new(PhotonLog {
        recording: true,
        ..Default::default()
    }));
    let mut opts = SimRun::new(cfg, Duration::from_secs_f64(seconds)).unwrap();
    opts.spec.gaze_scene = near_far(400);
    opts.spec.gaze.blink_rate_hz = 0.0;
    opts.hooks.push(Box::new(PhotonRecorder::new(log.clone())));
    opts.actions = vec![
        (Duration::ZERO, Action::HoldMarker(true)),
        (Duration::from_millis(500), Action::HoldMarker(false)),
    ];
    let r = go(opts, Duration::from_millis(4)).await;
    let log = std::mem::take(&mut *log.lock().unwrap());
    // Refreshes are judged up to a quarter second before the rig stopped.
    let until = Timestamp::from_millis((seconds * 1000.0) as u64 - 250);
    let report = analyse(&log, until, Duration::from_millis(250)).unwrap();
    (r, report)
}

const SERIAL_LINE: &str = "driver = \"serial-line\"\nport = \"sim\"";
/// The input of the example rig's simulated sync board.
const ON_THE_SYNC_BOARD: &str = "driver = \"sync\"";

#[tokio::test(start_paused = true)]
async fn the_panels_photon_latency_is_recovered_within_0_2_ms() {
    for (photodiode, persistence) in [
        (SERIAL_LINE, ""),
        (ON_THE_SYNC_BOARD, ""),
        (SERIAL_LINE, "sim_persistence_ms = 2.0"),
    ] {
        // Not the 4 ms default the scheduler assumes, to show the figure is the panel's.
        let display = format!("sim_photon_latency_ms = 7.3\n{persistence}");
        let (_, r) = photons(photodiode_rig(photodiode, &display), 3.0).await;
        let n = r.vsync_to_photons.len();
        // 2.5 s at 60 Hz toggled every frame: 150 changes; a pulsed panel's dark ones have
        // no edge of their own.
        let least = if persistence.is_empty() { 140 } else { 70 };
        assert!(n >= least, "{photodiode} {persistence}: {n} matched");
        for d in &r.vsync_to_photons {
            let off_us = (d.as_secs_f64() * 1e6 - 7_300.0).abs();
            assert!(off_us <= 200.0, "{photodiode} {persistence}: {d:?}");
        }
        // Judged from the end of the hold (0.5 s) to a quarter second before the stop: 135.
        assert!(
            r.refreshes_checked >= 130,
            "{photodiode} {persistence}: {} refreshes judged",
            r.refreshes_checked
        );
        assert!(r.refreshes_wrong.is_empty(), "{:?}", r.refreshes_wrong);
        assert_eq!(r.edges_lost, 0);
    }
}

#[tokio::test(start_paused = true)]
async fn a_dropped_frame_in_the_simulated_display_is_reported_as_one() {
    let cfg = photodiode_rig(SERIAL_LINE, "sim_dropped_refreshes = [100]");
    let (run, r) = photons(cfg, 3.0).await;
    let panel = run.state.devices().sims().unwrap().panel.clone().unwrap();
    let dropped: Vec<(Timestamp, u64)> = panel
        .lock()
        .refreshes()
        .filter(|f| f.dropped)
        .map(|f| (f.vsync, f.frame))
        .collect();
    assert_eq!(dropped.len(), 1);
    assert_eq!(r.refreshes_wrong, dropped, "{r:?}");
    assert_eq!(r.frames_never_seen.len(), 1);
    // The latency is still the panel's own around it.
    assert!(r
        .vsync_to_photons
        .iter()
        .all(|d| (d.as_secs_f64() * 1e6 - 4_000.0).abs() <= 200.0));
}

#[tokio::test(start_paused = true)]
async fn gaze_to_photons_is_the_host_path_plus_render_plus_the_display_latency() {
    let (run, r) = photons(photodiode_rig(SERIAL_LINE, ""), 4.0).await;
    let g = &r.gaze_to_photons;
    // A fixation change every 400 ms after the hold: most of them drive the lens.
    assert!(g.len() >= 5, "{} samples", g.len());
    let period = Duration::from_secs_f64(1.0 / 60.0);
    let panel = run.state.devices().sims().unwrap().panel.clone().unwrap();
    let panel = panel.lock();
    for s in g {
        // The parts: the loop's own path (no wait in simulated time), then the next frame
        // request and its one-frame render lead, then the display's 4 ms.
        assert!(s.gaze_to_command < Duration::from_micros(100), "{s:?}");
        // The frame requested a render lead (one period) before its vsync, at the first
        // request after the command; tokio's timers fire on the millisecond, so a request can
        // come up to 1 ms late and its frame then has less than a full lead.
        assert!(
            s.command_to_vsync + Duration::from_millis(1) >= period
                && s.command_to_vsync <= 2 * period,
            "{s:?}"
        );
        let sum = s.gaze_to_command + s.command_to_vsync + Duration::from_millis(4);
        let off = s.total.as_secs_f64() - sum.as_secs_f64();
        assert!(off.abs() <= 200e-6, "{s:?}: {off:e} s off");
        // And against the panel's own record of when that frame lit up (what the photodiode
        // saw went through its clock and the driver's mapping; this did not).
        let lit = panel
            .refreshes()
            .find(|f| f.frame == s.frame && !f.dropped)
            .unwrap()
            .light_at;
        let truth = lit.saturating_since(s.gaze_received);
        let off = s.total.as_secs_f64() - truth.as_secs_f64();
        assert!(
            off.abs() <= 200e-6,
            "{s:?}: {off:e} s from the panel's record"
        );
    }
}

/// When each simulated lens (`right`: the right eye's) first sat within `tol` of `power`
/// from `from` until `until`, µs.
fn settled_at(r: &Run, right: bool, power: f32, from: u64, until: u64, tol: f32) -> Option<u64> {
    r.log
        .probes
        .iter()
        .filter(|p| us(p.t) >= from && us(p.t) < until)
        .scan(None, |since: &mut Option<u64>, p| {
            let lens = if right {
                p.lens_power_right
            } else {
                p.lens_power
            };
            let ok = lens.is_some_and(|l| (l.0 - power).abs() <= tol);
            *since = if ok { since.or(Some(us(p.t))) } else { None };
            Some(*since)
        })
        .last()
        .flatten()
}

/// A lens per eye: one fixation estimate drives both. At every saccade between the near and
/// far objects both lenses are commanded to the new depth, left then right at the same
/// instant, and each (its own simulated Lens Driver 4) settles there within its settle time
/// of its command reaching the wire.
#[tokio::test(start_paused = true)]
async fn both_lenses_follow_one_fixation_through_saccades() {
    let opts = binocular(near_far(500), 3.2);
    let settle = opts.spec.lens.settle_time;
    let r = go(opts, Duration::from_millis(4)).await;
    let sacc = saccades(&r);
    assert!(sacc.len() >= 5, "{sacc:?}");
    let cmds = &r.log.lens_commands;
    for &(start, land, depth) in &sacc {
        let to = |lens: u8| {
            cmds.iter()
                .find(|c| {
                    c.lens.0 == lens
                        && us(c.t) >= start
                        && (f64::from(c.power.0) - depth).abs() < 0.05
                })
                .unwrap_or_else(|| panic!("lens {lens}: no command to {depth} D after {start} µs"))
        };
        let (l, rr) = (to(0), to(1));
        // One decision: both commands issued at once, the left first.
        assert_eq!(l.t, rr.t);
        assert_eq!(l.id.0 + 1, rr.id.0);
        assert!(
            us(l.t) <= land + 10_000,
            "command at {} µs, landing {land}",
            us(l.t)
        );
        for (c, right) in [(l, false), (rr, true)] {
            let wire = us(c.wire.expect("on the wire"));
            let at = settled_at(&r, right, c.power.0, wire, wire + 200_000, 0.03)
                .unwrap_or_else(|| panic!("lens {} never settled at {} D", c.lens.0, c.power.0));
            assert!(
                Duration::from_micros(at - wire) <= settle + Duration::from_millis(1),
                "lens {} settled {} µs after its wire",
                c.lens.0,
                at - wire
            );
        }
    }
    // Both lenses parked at the end.
    let end = r.log.probes.last().unwrap();
    assert!((end.lens_power.unwrap().0 - 0.5).abs() < 0.01, "{end:?}");
    assert!(
        (end.lens_power_right.unwrap().0 - 0.5).abs() < 0.01,
        "{end:?}"
    );
    assert!(r.report.ok(), "{:?}", r.report);
    assert!(r.report.park_right.is_some());
}

/// Each lens is driven through its own eye's optics map: with the right eye a -0.5 D myope
/// ([optics.right], 0 mm vertex), every decision sends the right lens 0.5 D more than the left
/// (both lenses on the identity map otherwise), and frames are rendered at the focus each
/// lens gives its eye.
#[tokio::test(start_paused = true)]
async fn each_lens_follows_its_own_eyes_optics_map() {
    let text = dioptra_rig::config::EXAMPLE_SIM_BINOCULAR_RIG
        .replace("sim_rate_hz = 250.0", "sim_rate_hz = 500.0")
        .replace(
            "[eye]",
            "[optics.right]\nprescription_sphere_d = -0.5\nprescription_vertex_mm = 0.0\n\n[eye]",
        );
    let cfg = RigConfig::parse(&text).unwrap();
    let mut opts = SimRun::new(cfg, Duration::from_secs_f64(2.0)).unwrap();
    opts.spec.gaze_scene = near_far(400);
    opts.spec.gaze.blink_rate_hz = 0.0;
    let r = go(opts, Duration::from_millis(4)).await;
    assert_eq!(r.state.optics().of(LensId(1)).source_name(), "identity");
    let cmds = &r.log.lens_commands;
    let left: Vec<_> = cmds.iter().filter(|c| c.lens.0 == 0).collect();
    let right: Vec<_> = cmds.iter().filter(|c| c.lens.0 == 1).collect();
    assert!(left.len() >= 3, "{cmds:?}");
    assert_eq!(left.len(), right.len());
    for (l, r) in left.iter().zip(&right) {
        assert_eq!(l.t, r.t);
        if l.reason == FocusReason::Park {
            // Each parks where its own section says (both at 0.5 D in the example).
            assert_eq!((l.power.0, r.power.0), (0.5, 0.5));
        } else {
            assert!((r.power.0 - l.power.0 - 0.5).abs() < 1e-4, "{l:?} {r:?}");
        }
    }
}

/// Unplugging the right eye's lens holds that eye only: while it is away the left lens keeps
/// following the saccades, nothing is sent to the right one, and when it is plugged back in
/// it is sent the current focus and both follow again.
#[tokio::test(start_paused = true)]
async fn unplugging_the_right_lens_holds_that_eye_while_the_left_keeps_focusing() {
    let mut opts = binocular(near_far(400), 4.0);
    let (pull, back) = (1_300_000u64, 2_600_000u64);
    opts.actions = vec![
        (Duration::from_micros(pull), Action::UnplugLensOf(LensId(1))),
        (Duration::from_micros(back), Action::ReplugLensOf(LensId(1))),
    ];
    let r = go(opts, Duration::from_millis(4)).await;
    let right_links: Vec<(Timestamp, LinkStatus)> = r
        .log
        .link_events
        .iter()
        .filter(|l| l.2 == LensId(1))
        .map(|l| (l.0, l.1))
        .collect();
    let left_links: Vec<LinkStatus> = r
        .log
        .link_events
        .iter()
        .filter(|l| l.2 == LensId(0))
        .map(|l| l.1)
        .collect();
    assert_eq!(
        left_links,
        [LinkStatus::Connected],
        "the left lens stayed up"
    );
    assert_eq!(
        right_links.iter().map(|l| l.1).collect::<Vec<_>>(),
        [
            LinkStatus::Connected,
            LinkStatus::Lost,
            LinkStatus::Connected
        ]
    );
    let (lost_at, back_at) = (us(right_links[1].0), us(right_links[2].0));
    assert!(lost_at >= pull && back_at >= back, "{lost_at} {back_at}");
    assert_eq!(r.lenses_opened, [1, 2]);
    // While it was away: saccades moved the left lens, and no command reached the right one.
    let sacc: Vec<_> = saccades(&r)
        .into_iter()
        .filter(|s| s.0 > lost_at + 50_000 && s.1 + 100_000 < back_at)
        .collect();
    assert!(sacc.len() >= 2, "{sacc:?}");
    let cmds = &r.log.lens_commands;
    for &(start, _, depth) in &sacc {
        let left = cmds
            .iter()
            .find(|c| {
                c.lens.0 == 0 && us(c.t) >= start && (f64::from(c.power.0) - depth).abs() < 0.05
            })
            .expect("the left lens followed");
        let wire = us(left.wire.expect("on the wire"));
        assert!(settled_at(&r, false, left.power.0, wire, wire + 100_000, 0.03).is_some());
    }
    assert!(
        !cmds
            .iter()
            .any(|c| c.lens.0 == 1 && us(c.t) > lost_at && us(c.t) < back_at),
        "a command was handed to the unplugged lens"
    );
    // Held: the right lens stayed where it was when it was pulled.
    let held: Vec<f32> = r
        .log
        .probes
        .iter()
        .filter(|p| us(p.t) > lost_at && us(p.t) < back_at)
        .filter_map(|p| p.lens_power_right.map(|d| d.0))
        .collect();
    let (lo, hi) = held
        .iter()
        .fold((f32::MAX, f32::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
    assert!(
        hi - lo < 0.05,
        "the right lens moved while unplugged: {lo}..{hi}"
    );
    // Back: sent the current focus (the left lens's), and both follow the next saccade.
    let reconnect = cmds
        .iter()
        .find(|c| c.lens.0 == 1 && us(c.t) >= back_at)
        .expect("a command after the replug");
    assert_eq!(reconnect.reason, FocusReason::Reconnect);
    let left_then = cmds
        .iter()
        .rev()
        .find(|c| c.lens.0 == 0 && c.t <= reconnect.t)
        .unwrap();
    assert!((reconnect.power.0 - left_then.power.0).abs() < 1e-4);
    let after: Vec<_> = saccades(&r)
        .into_iter()
        .filter(|s| s.0 > back_at + 50_000)
        .collect();
    let &(start, _, depth) = after.first().expect("a saccade after the replug");
    for lens in [0u8, 1] {
        assert!(
            cmds.iter().any(|c| c.lens.0 == lens
                && us(c.t) >= start
                && (f64::from(c.power.0) - depth).abs() < 0.05),
            "lens {lens} did not follow after the replug"
        );
    }
    assert!(r.report.ok(), "{:?}", r.report);
}
