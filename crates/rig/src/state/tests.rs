//! `/status` as a whole: its keys on a running simulated rig, one lens and a lens per eye.

use std::collections::BTreeSet;

use serde_json::Value;

use crate::config::{RigConfig, EXAMPLE_SIM_BINOCULAR_RIG, EXAMPLE_SIM_RIG};
use crate::{Rig, RigSetup};

/// Every key path of `v` (`a.b.c`; an array's elements under `a[]`), except below the keys
/// whose children are data rather than a schema (latency stages, errors by method).
fn key_paths(v: &Value, at: &str, out: &mut BTreeSet<String>) {
    const DATA: [&str; 3] = [
        "scheduler.latency_us",
        "render_errors.by_method",
        "render.stages",
    ];
    if DATA.contains(&at) {
        return;
    }
    match v {
        Value::Object(m) => {
            for (k, v) in m {
                let path = if at.is_empty() {
                    k.clone()
                } else {
                    format!("{at}.{k}")
                };
                out.insert(path.clone());
                key_paths(v, &path, out);
            }
        }
        Value::Array(a) => {
            for v in a {
                key_paths(v, &format!("{at}[]"), out);
            }
        }
        _ => {}
    }
}

/// The status of `text`'s rig after 2 s of simulated time.
async fn status_of(text: &str) -> Value {
    let mut setup = RigSetup::new(RigConfig::parse(text).unwrap());
    setup.simulated_time = true;
    let rig = Rig::start(setup).await.unwrap();
    tokio::time::sleep(std::time::Duration::from_secs(2)).await;
    let v = rig.state().status_json();
    rig.state().cancel.cancel();
    rig.wait().await;
    v
}

fn paths(v: &Value) -> Vec<String> {
    let mut out = BTreeSet::new();
    key_paths(v, "", &mut out);
    out.into_iter().collect()
}

/// `/status`'s key paths on the example rig (one lens), as they were before each part
/// published its own status, and `problems`, which that added.
const ONE_LENS: &[&str] = &[
    "clock",
    "clock.source",
    "clock.wall_zero_ns",
    "content",
    "content.animated",
    "content.cast_reduced",
    "content.cast_size",
    "content.failed",
    "content.last_error",
    "content.late",
    "content.newest_age_ms",
    "content.rendered",
    "content.scene_time_ms",
    "content.seed",
    "content.shown",
    "content.since_ns",
    "content.source",
    "content.update_ms",
    "content.update_slowed",
    "counts",
    "counts.fallback_frames",
    "counts.frames_requested",
    "counts.frames_shown",
    "counts.gaze_samples",
    "counts.lens_commands",
    "counts.render_errors",
    "counts.sync_events",
    "device_tasks",
    "device_tasks.lens_poll_ms",
    "device_tasks.link",
    "device_tasks.link.backoff_max_ms",
    "device_tasks.link.backoff_min_ms",
    "device_tasks.link.connect_timeout_ms",
    "device_tasks.link.timeouts_lost",
    "device_tasks.park_timeout_ms",
    "devices",
    "devices.gaze",
    "devices.gaze.connects",
    "devices.gaze.driver",
    "devices.gaze.failures",
    "devices.gaze.last_error",
    "devices.gaze.port",
    "devices.gaze.state",
    "devices.lens",
    "devices.lens.connects",
    "devices.lens.driver",
    "devices.lens.failures",
    "devices.lens.last_error",
    "devices.lens.port",
    "devices.lens.state",
    "devices.sync",
    "devices.sync.connects",
    "devices.sync.driver",
    "devices.sync.failures",
    "devices.sync.last_error",
    "devices.sync.port",
    "devices.sync.state",
    "display",
    "display.distinct_fps",
    "display.distinct_frames",
    "display.eye_offset_px",
    "display.eye_offset_px.left",
    "display.eye_offset_px.right",
    "display.last",
    "display.last.focus_d",
    "display.last.frame",
    "display.last.marker_white",
    "display.last.shown_ns",
    "display.last.size_compensation",
    "display.late",
    "display.layout",
    "display.mean_interval_ms",
    "display.misfit",
    "display.misfit.count",
    "display.misfit.newest",
    "display.mono_on_stereo",
    "display.places",
    "display.places.one",
    "display.pngs_written",
    "display.refresh_hz",
    "display.refreshes",
    "display.repeated_refreshes",
    "display.scale",
    "display.shown",
    "display.sink",
    "display.surface",
    "eye_views",
    "focus",
    "focus.commanded_d",
    "focus.commanded_focus_d",
    "focus.focus_range_d",
    "focus.lens_d",
    "focus.lens_focus_d",
    "focus.lens_range_d",
    "focus.lens_settled",
    "focus.manual_d",
    "host_ns",
    "last_render_ms",
    "lsl",
    "method",
    "mode",
    "optics",
    "optics.eyes",
    "optics.magnification",
    "optics.map",
    "optics.source",
    "planned",
    "problems",
    "recording",
    "render",
    "render.adapter",
    "render.backend",
    "render.cpu_because",
    "render.decomposition",
    "render.gpu_time_us",
    "render.images_read_back",
    "render.network",
    "render.refine",
    "render.refine_tiles_run",
    "render.spectral_on",
    "render.stages",
    "render.timestamps",
    "render_errors",
    "render_errors.by_method",
    "render_errors.last",
    "scheduler",
    "scheduler.commanded_d",
    "scheduler.commanded_focus_d",
    "scheduler.counters",
    "scheduler.counters.blinks",
    "scheduler.counters.frames_presented",
    "scheduler.counters.frames_rendered",
    "scheduler.counters.frames_requested",
    "scheduler.counters.gaze_samples",
    "scheduler.counters.ignored_events",
    "scheduler.counters.late_frames",
    "scheduler.counters.lens_commands",
    "scheduler.counters.lens_commands_held",
    "scheduler.counters.lens_link_losses",
    "scheduler.counters.lens_readbacks",
    "scheduler.counters.misses",
    "scheduler.counters.renders_skipped",
    "scheduler.counters.saccades",
    "scheduler.counters.sequencer_faults",
    "scheduler.fixation_depth_d",
    "scheduler.last_settle_ms",
    "scheduler.latency_us",
    "scheduler.lens_link",
    "scheduler.method",
    "scheduler.mode",
    "scheduler.phase",
    "scheduler.shown_frame",
    "scheduler.vergence_d",
    "sim_lens",
    "sim_lens.plugged",
    "sim_lens.power_d",
    "sim_lens.settled",
    "sim_lens.target_d",
    "subframes",
    "subframes.faults",
    "subframes.lens_measured_by",
    "subframes.measured",
    "subframes.off_target",
    "subframes.off_target_rate",
    "subframes.started",
    "subframes.tolerance_d",
    "uptime_s",
];

/// The same on the example binocular rig (a lens per eye).
const LENS_PER_EYE: &[&str] = &[
    "clock",
    "clock.source",
    "clock.wall_zero_ns",
    "content",
    "content.animated",
    "content.cast_reduced",
    "content.cast_size",
    "content.failed",
    "content.last_error",
    "content.late",
    "content.newest_age_ms",
    "content.rendered",
    "content.scene_time_ms",
    "content.seed",
    "content.shown",
    "content.since_ns",
    "content.source",
    "content.update_ms",
    "content.update_slowed",
    "counts",
    "counts.fallback_frames",
    "counts.frames_requested",
    "counts.frames_shown",
    "counts.gaze_samples",
    "counts.lens_commands",
    "counts.render_errors",
    "counts.sync_events",
    "device_tasks",
    "device_tasks.lens_poll_ms",
    "device_tasks.link",
    "device_tasks.link.backoff_max_ms",
    "device_tasks.link.backoff_min_ms",
    "device_tasks.link.connect_timeout_ms",
    "device_tasks.link.timeouts_lost",
    "device_tasks.park_timeout_ms",
    "devices",
    "devices.gaze",
    "devices.gaze.connects",
    "devices.gaze.driver",
    "devices.gaze.failures",
    "devices.gaze.last_error",
    "devices.gaze.port",
    "devices.gaze.state",
    "devices.lens_left",
    "devices.lens_left.connects",
    "devices.lens_left.driver",
    "devices.lens_left.failures",
    "devices.lens_left.last_error",
    "devices.lens_left.port",
    "devices.lens_left.state",
    "devices.lens_right",
    "devices.lens_right.connects",
    "devices.lens_right.driver",
    "devices.lens_right.failures",
    "devices.lens_right.last_error",
    "devices.lens_right.port",
    "devices.lens_right.state",
    "display",
    "display.distinct_fps",
    "display.distinct_frames",
    "display.eye_offset_px",
    "display.eye_offset_px.left",
    "display.eye_offset_px.right",
    "display.last",
    "display.last.focus_d",
    "display.last.frame",
    "display.last.marker_white",
    "display.last.shown_ns",
    "display.last.size_compensation",
    "display.late",
    "display.layout",
    "display.mean_interval_ms",
    "display.misfit",
    "display.misfit.count",
    "display.misfit.newest",
    "display.mono_on_stereo",
    "display.places",
    "display.places.left",
    "display.places.right",
    "display.pngs_written",
    "display.refresh_hz",
    "display.refreshes",
    "display.repeated_refreshes",
    "display.scale",
    "display.shown",
    "display.sink",
    "display.surface",
    "eye_views",
    "eye_views.failed",
    "eye_views.half_ipd_mm",
    "eye_views.last_error",
    "eye_views.last_ms",
    "eye_views.made",
    "eye_views.made_on",
    "eye_views.source",
    "focus",
    "focus.commanded_d",
    "focus.commanded_focus_d",
    "focus.focus_range_d",
    "focus.left",
    "focus.left.commanded_d",
    "focus.left.commanded_focus_d",
    "focus.left.lens_d",
    "focus.left.lens_focus_d",
    "focus.left.link",
    "focus.lens_d",
    "focus.lens_focus_d",
    "focus.lens_range_d",
    "focus.lens_settled",
    "focus.manual_d",
    "focus.right",
    "focus.right.commanded_d",
    "focus.right.commanded_focus_d",
    "focus.right.lens_d",
    "focus.right.lens_focus_d",
    "focus.right.link",
    "host_ns",
    "last_render_ms",
    "lsl",
    "method",
    "mode",
    "optics",
    "optics.eyes",
    "optics.left",
    "optics.left.magnification",
    "optics.left.map",
    "optics.left.source",
    "optics.right",
    "optics.right.magnification",
    "optics.right.map",
    "optics.right.source",
    "planned",
    "problems",
    "recording",
    "render",
    "render.adapter",
    "render.backend",
    "render.cpu_because",
    "render.decomposition",
    "render.gpu_time_us",
    "render.images_read_back",
    "render.network",
    "render.refine",
    "render.refine_tiles_run",
    "render.spectral_on",
    "render.stages",
    "render.timestamps",
    "render_errors",
    "render_errors.by_method",
    "render_errors.last",
    "scheduler",
    "scheduler.commanded_d",
    "scheduler.commanded_focus_d",
    "scheduler.counters",
    "scheduler.counters.blinks",
    "scheduler.counters.frames_presented",
    "scheduler.counters.frames_rendered",
    "scheduler.counters.frames_requested",
    "scheduler.counters.gaze_samples",
    "scheduler.counters.ignored_events",
    "scheduler.counters.late_frames",
    "scheduler.counters.lens_commands",
    "scheduler.counters.lens_commands_held",
    "scheduler.counters.lens_link_losses",
    "scheduler.counters.lens_readbacks",
    "scheduler.counters.misses",
    "scheduler.counters.renders_skipped",
    "scheduler.counters.saccades",
    "scheduler.counters.sequencer_faults",
    "scheduler.fixation_depth_d",
    "scheduler.last_settle_ms",
    "scheduler.latency_us",
    "scheduler.lens_link",
    "scheduler.method",
    "scheduler.mode",
    "scheduler.phase",
    "scheduler.shown_frame",
    "scheduler.vergence_d",
    "sim_lens",
    "sim_lens.left",
    "sim_lens.left.plugged",
    "sim_lens.left.power_d",
    "sim_lens.left.settled",
    "sim_lens.left.target_d",
    "sim_lens.right",
    "sim_lens.right.plugged",
    "sim_lens.right.power_d",
    "sim_lens.right.settled",
    "sim_lens.right.target_d",
    "subframes",
    "subframes.faults",
    "subframes.lens_measured_by",
    "subframes.measured",
    "subframes.off_target",
    "subframes.off_target_rate",
    "subframes.started",
    "subframes.tolerance_d",
    "uptime_s",
];

/// `/status` keeps its keys whoever assembles it; `problems` is a list, empty on a rig whose
/// simulated devices all run.
#[tokio::test(start_paused = true)]
async fn status_keeps_its_keys_and_lists_its_problems() {
    for (text, want) in [
        (EXAMPLE_SIM_RIG, ONE_LENS),
        (EXAMPLE_SIM_BINOCULAR_RIG, LENS_PER_EYE),
    ] {
        let mut v = status_of(text).await;
        // Renders take real time on the paused clock, so on a loaded machine the display can
        // run late and say so (`display` / `method`); nothing else may be wrong.
        let problems = v["problems"].as_array_mut().unwrap();
        problems.retain(|p| !(p["part"] == "display" && p["key"] == "method"));
        assert_eq!(paths(&v), want, "{v:#}");
        assert_eq!(v["problems"], serde_json::json!([]), "{v:#}");
    }
}

/// Renders take real time on the paused clock, so on a loaded machine (tests in parallel) the
/// display can run late and say so (`display` / `method`): the problems but that one.
fn not_lateness(mut problems: Vec<crate::problem::Problem>) -> Vec<crate::problem::Problem> {
    problems.retain(|p| !(p.part == "display" && p.key == "method"));
    problems
}

/// A device that goes down is listed under `problems` with its port's key, and leaves the
/// list when it is back; its own status keeps its `last_error`.
#[tokio::test(start_paused = true)]
async fn a_lens_unplugged_is_a_problem_until_it_is_back() {
    let mut setup = RigSetup::new(RigConfig::parse(EXAMPLE_SIM_RIG).unwrap());
    setup.simulated_time = true;
    let rig = Rig::start(setup).await.unwrap();
    let state = rig.state().clone();
    tokio::time::sleep(std::time::Duration::from_secs(1)).await;
    assert_eq!(not_lateness(state.problems()), Vec::new());
    let plug = || {
        &state.devices().sims().unwrap().lenses[0]
            .as_ref()
            .unwrap()
            .plug
    };
    plug().unplug();
    let mut problems = Vec::new();
    for _ in 0..100 {
        problems = not_lateness(state.problems());
        if !problems.is_empty() {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    assert_eq!(problems.len(), 1, "{problems:?}");
    let p = &problems[0];
    assert_eq!((p.part, p.key.as_str()), ("devices", "devices.lens.port"));
    assert!(p.problem.contains("the lens device"), "{}", p.problem);
    let v = state.status_json();
    assert!(
        v["problems"]
            .as_array()
            .unwrap()
            .iter()
            .any(|p| p["key"] == "devices.lens.port"),
        "{v:#}"
    );
    assert!(v["devices"]["lens"]["last_error"].is_string(), "{v:#}");
    plug().replug();
    for _ in 0..200 {
        if not_lateness(state.problems()).is_empty() {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    assert_eq!(not_lateness(state.problems()), Vec::new());
    state.cancel().cancel();
    rig.wait().await;
}
