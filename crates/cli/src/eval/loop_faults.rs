//! The control-loop half of the failure-case suite: the whole loop on the rig runtime `dioptra
//! serve` runs (dioptra-rig's simulated rig: the example rig config, real drivers, simulated
//! devices) in varifocal mode under one fault at a time, each against the same run without
//! faults. Measured from ground truth: focus error (the
//! simulated lens's true power against the depth of what the viewer really looks at) over
//! time, frame deadline misses, and recovery times.

use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use dioptra_core::{DepthMap, Plane, Timestamp};
use dioptra_rig::config::Mode;
use dioptra_rig::simulated_rig::{Action, Run, ScriptedRenderer, SimRun};
use dioptra_sim::gaze::generator::{Segment, Target, TruePhase};
use dioptra_sim::gaze::Scene;

use super::report::{mean, num, Table};

const NEAR_D: f32 = 2.0;
const FAR_D: f32 = 0.5;
/// Focus error below which the eye's target is taken as in focus (about the eye's depth of
/// field at a 4 mm pupil).
pub const IN_FOCUS_D: f64 = 0.25;

/// A fault injected into one run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Fault {
    None,
    TrackerNoise,
    TrackerDropouts,
    Blinks,
    LensLag,
    DeadlineMisses,
    Unplug,
}

impl Fault {
    pub const ALL: [Fault; 7] = [
        Fault::None,
        Fault::TrackerNoise,
        Fault::TrackerDropouts,
        Fault::Blinks,
        Fault::LensLag,
        Fault::DeadlineMisses,
        Fault::Unplug,
    ];

    pub fn name(&self) -> &'static str {
        match self {
            Fault::None => "none (baseline)",
            Fault::TrackerNoise => "tracker noise",
            Fault::TrackerDropouts => "tracker dropouts",
            Fault::Blinks => "blinks",
            Fault::LensLag => "lens lag",
            Fault::DeadlineMisses => "renderer deadline misses",
            Fault::Unplug => "lens unplugged",
        }
    }

    pub fn what(&self) -> &'static str {
        match self {
            Fault::None => "default simulated devices: 0.03 deg noise, 0.2 % dropouts, no blinks, 15 ms lens settle, 4 ms renders",
            Fault::TrackerNoise => "tracker noise 0.5 deg per eye and axis (1 sd), 17x the default",
            Fault::TrackerDropouts => "the tracker loses an eye on 20 % of samples",
            Fault::Blinks => "2 spontaneous blinks per second, 150 ms each",
            Fault::LensLag => "the lens settles in 80 ms instead of the 15 ms the scheduler's lens model expects",
            Fault::DeadlineMisses => "every 4th frame takes 2 frame periods (33 ms) to render",
            Fault::Unplug => "the lens cable is pulled at 0.9 s and plugged back at 1.3 s, while the viewer looks from the far surface to the near one (at 1.0 s)",
        }
    }
}

/// Unplug and replug times of [`Fault::Unplug`].
const UNPLUG_AT: Duration = Duration::from_millis(900);
const REPLUG_AT: Duration = Duration::from_millis(1300);

/// Two surfaces filling the field: left half at 0.5 m, right half at 2 m.
fn split_depth() -> Arc<DepthMap> {
    let w = 128;
    let mut p = Plane::new(w, w, FAR_D);
    for y in 0..w {
        for x in 0..w / 2 {
            p.data_mut()[y * w + x] = NEAR_D;
        }
    }
    Arc::new(DepthMap::from_diopters(p).unwrap_or_else(|_| unreachable!("constant depths")))
}

fn gaze_scene() -> Scene {
    let t = |yaw: f64, d: f32| Target {
        yaw_deg: yaw,
        pitch_deg: 1.0,
        diopters: f64::from(d),
    };
    Scene {
        name: "near-far".into(),
        targets: vec![t(-5.0, NEAR_D), t(5.0, FAR_D)],
        script: vec![
            Segment::Fixate { target: 0, ms: 500 },
            Segment::Fixate { target: 1, ms: 500 },
        ],
    }
}

/// What one fault did.
#[derive(Debug, Clone)]
pub struct LoopResult {
    pub fault: Fault,
    /// (seconds, focus error in diopters) every probe.
    pub error: Vec<(f64, f64)>,
    pub mean_error: Option<f64>,
    pub p95_error: Option<f64>,
    /// Share of seeing time (eyes open, not in a saccade) the error exceeds [`IN_FOCUS_D`].
    pub out_of_focus: Option<f64>,
    /// Median and worst time from a saccade landing to the lens within [`IN_FOCUS_D`], ms.
    pub refocus_median_ms: Option<f64>,
    pub refocus_max_ms: Option<f64>,
    /// From the end of the disturbance (replug, blink end) to in focus again, ms (worst).
    pub recovery_ms: Option<f64>,
    pub frames_presented: u64,
    pub misses: u64,
    pub late_frames: u64,
    pub lens_link_losses: u64,
    pub blinks_detected: u64,
    pub simulated_s: f64,
}

/// Renders take 4 ms, or two frame periods every 4th frame when misses are injected.
fn options(fault: Fault, seconds: f64) -> Result<(SimRun, ScriptedRenderer)> {
    let mut o = SimRun::example(Mode::Varifocal, Duration::from_secs_f64(seconds))?;
    o.spec.gaze_scene = gaze_scene();
    o.spec.gaze.blink_rate_hz = 0.0;
    let slow = o.sched.display.frame_period * 2;
    let mut slow_every = None;
    match fault {
        Fault::None => {}
        Fault::TrackerNoise => o.spec.gaze.noise_deg = 0.5,
        Fault::TrackerDropouts => o.spec.gaze.dropout_probability = 0.2,
        Fault::Blinks => o.spec.gaze.blink_rate_hz = 2.0,
        Fault::LensLag => o.spec.lens.settle_time = Duration::from_millis(80),
        Fault::DeadlineMisses => slow_every = Some(4),
        Fault::Unplug => {
            o.actions = vec![
                (UNPLUG_AT, Action::UnplugLens),
                (REPLUG_AT, Action::ReplugLens),
            ]
        }
    }
    let planes = o.cfg.optics.planes.len();
    let count = std::sync::atomic::AtomicU64::new(0);
    let renderer = ScriptedRenderer::new(planes, move |_| {
        let n = count.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        match slow_every {
            Some(every) if n.is_multiple_of(every) => slow,
            _ => Duration::from_millis(4),
        }
    });
    Ok((o, renderer))
}

/// First time at or after `from` (µs) that the error is within [`IN_FOCUS_D`], as a delay, ms.
fn time_to_focus(error: &[(u64, f64)], from: u64, until: u64) -> Option<f64> {
    error
        .iter()
        .find(|(t, e)| *t >= from && *t < until && *e <= IN_FOCUS_D)
        .map(|(t, _)| (t - from) as f64 / 1000.0)
}

fn measure(fault: Fault, r: &Run, seconds: f64) -> LoopResult {
    // Focus error per probe, µs since start.
    let start = r.log.probes.first().map_or(Timestamp::ZERO, |p| p.t);
    let err_us: Vec<(u64, f64)> = r
        .log
        .probes
        .iter()
        .filter_map(|p| {
            // Where the simulated lens puts the display's image, through the simulated optics.
            let (lens, target) = (p.eye_focus?, p.gaze_target_d?);
            Some((
                p.t.saturating_since(start).as_micros() as u64,
                (f64::from(lens.0) - target).abs(),
            ))
        })
        .collect();
    // Statistics count only what the eye sees: open and not in a saccade (vision is
    // suppressed during saccades, and the truth's target switches at their start), after the
    // first 0.1 s (the lens starts anywhere) and before shutdown parks the lens.
    let truth_t0 = r.log.truth.first().map_or(0, |s| s.time_us);
    let phase_at = |t: u64| {
        let i = r
            .log
            .truth
            .partition_point(|s| s.time_us.saturating_sub(truth_t0) <= t);
        r.log.truth.get(i.saturating_sub(1)).map(|s| s.phase)
    };
    let end_us = (seconds * 1e6) as u64;
    let mut sorted: Vec<f64> = err_us
        .iter()
        .filter(|(t, _)| {
            (100_000..end_us).contains(t)
                && !matches!(
                    phase_at(*t),
                    Some(TruePhase::Saccade | TruePhase::Blink) | None
                )
        })
        .map(|e| e.1)
        .collect();
    sorted.sort_by(f64::total_cmp);
    let p95 = (!sorted.is_empty())
        .then(|| sorted[((sorted.len() as f64 * 0.95) as usize).min(sorted.len() - 1)]);
    let out_of_focus = (!sorted.is_empty())
        .then(|| sorted.iter().filter(|&&e| e > IN_FOCUS_D).count() as f64 / sorted.len() as f64);
    let end = err_us.last().map_or(0, |e| e.0);
    // Saccade landings (truth), in the probes' time base.
    let mut landings = Vec::new();
    let mut blink_ends = Vec::new();
    for w in r.log.truth.windows(2) {
        let t = w[1].time_us.saturating_sub(truth_t0);
        if w[0].phase == TruePhase::Saccade && w[1].phase != TruePhase::Saccade {
            landings.push(t);
        }
        if w[0].phase == TruePhase::Blink && w[1].phase != TruePhase::Blink {
            blink_ends.push(t);
        }
    }
    let mut refocus: Vec<f64> = Vec::new();
    for (i, &l) in landings.iter().enumerate() {
        let next = landings.get(i + 1).copied().unwrap_or(end);
        if let Some(ms) = time_to_focus(&err_us, l, next) {
            refocus.push(ms);
        }
    }
    refocus.sort_by(f64::total_cmp);
    let recovery_from: Vec<u64> = match fault {
        Fault::Unplug => vec![REPLUG_AT.as_micros() as u64],
        Fault::Blinks => blink_ends,
        _ => Vec::new(),
    };
    let recovery_ms = recovery_from
        .iter()
        .filter_map(|&t| time_to_focus(&err_us, t, end + 1))
        .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))));
    let c = r.status.counters;
    LoopResult {
        fault,
        error: err_us.iter().map(|(t, e)| (*t as f64 / 1e6, *e)).collect(),
        mean_error: mean(&sorted),
        p95_error: p95,
        out_of_focus,
        refocus_median_ms: refocus.get(refocus.len() / 2).copied(),
        refocus_max_ms: refocus.last().copied(),
        recovery_ms,
        frames_presented: c.frames_presented,
        misses: c.misses,
        late_frames: c.late_frames,
        lens_link_losses: c.lens_link_losses,
        blinks_detected: c.blinks,
        simulated_s: r.simulated.as_secs_f64(),
    }
}

/// Runs every fault for `seconds` of simulated time each.
pub fn run_all(seconds: f64, mut progress: impl FnMut(Fault)) -> Result<Vec<LoopResult>> {
    let mut out = Vec::new();
    for fault in Fault::ALL {
        progress(fault);
        let (opts, renderer) = options(fault, seconds)?;
        let r = opts
            .run_paused(
                Some(ScriptedRenderer::still(&split_depth())),
                Arc::new(renderer),
                None,
            )
            .with_context(|| format!("the simulated rig failed ({})", fault.name()))?;
        out.push(measure(fault, &r, seconds));
    }
    Ok(out)
}

pub const HEADER: [&str; 14] = [
    "fault",
    "mean_focus_error_d",
    "p95_focus_error_d",
    "time_out_of_focus",
    "refocus_median_ms",
    "refocus_max_ms",
    "recovery_ms",
    "frames_presented",
    "deadline_misses",
    "late_frames",
    "lens_link_losses",
    "blinks_detected",
    "simulated_s",
    "what",
];

pub fn table(results: &[LoopResult]) -> Table {
    let mut t = Table::new(&HEADER);
    for r in results {
        t.push(vec![
            r.fault.name().into(),
            num(r.mean_error, 4),
            num(r.p95_error, 4),
            num(r.out_of_focus, 4),
            num(r.refocus_median_ms, 1),
            num(r.refocus_max_ms, 1),
            num(r.recovery_ms, 1),
            r.frames_presented.to_string(),
            r.misses.to_string(),
            r.late_frames.to_string(),
            r.lens_link_losses.to_string(),
            r.blinks_detected.to_string(),
            format!("{:.2}", r.simulated_s),
            r.fault.what().into(),
        ]);
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_to_focus_finds_the_first_in_focus_probe() {
        let e = [(0u64, 1.0), (1000, 0.5), (2000, 0.2), (3000, 0.1)];
        assert_eq!(time_to_focus(&e, 500, 10_000), Some(1.5));
        assert_eq!(time_to_focus(&e, 0, 1500), None);
    }
}
