//! Speed target (issue 9): one scheduler step for one gaze sample ≤ 20 µs median, in
//! varifocal mode with a 256 x 256 depth map (fixation depth read at every fixation sample).

use std::sync::Arc;
use std::time::Duration;

use criterion::{black_box, criterion_group, criterion_main, Criterion};
use dioptra_core::{DepthMap, EyeRay, GazeSample, Plane, Timestamp};
use dioptra_sched::{Event, Mode, Scheduler, SchedulerConfig};

/// Both eyes on (yaw, 0) at `diopters`.
fn sample(t_us: u64, yaw: f64, diopters: f64, noise: f64) -> GazeSample {
    let y = yaw.to_radians();
    let dist = 1000.0 / diopters;
    let pt = [y.sin() * dist, 0.0, y.cos() * dist];
    let eye = |x: f64, n: f64| {
        let d = [pt[0] - x + n, pt[1] + n, pt[2]];
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        EyeRay {
            origin_mm: [x as f32, 0.0, 0.0],
            direction: [
                (d[0] / len) as f32,
                (d[1] / len) as f32,
                (d[2] / len) as f32,
            ],
            pupil_mm: 4.0,
            valid: true,
        }
    };
    let t = Timestamp::from_micros(t_us);
    GazeSample {
        device_time: t,
        host_receive_time: t,
        host_time: t,
        left: eye(-32.0, noise),
        right: eye(32.0, -noise),
    }
}

/// 400 ms fixations alternating between a near (-5°, 2 D) and a far (+5°, 0.5 D) object with
/// 40 ms saccades between them, 500 Hz, a little tracker noise.
fn stream(n: usize) -> Vec<GazeSample> {
    (0..n)
        .map(|i| {
            let t_us = i as u64 * 2000;
            let phase = (t_us % 880_000) as f64;
            let (yaw, d) = if phase < 400_000.0 {
                (-5.0, 2.0)
            } else if phase < 440_000.0 {
                let s = (phase - 400_000.0) / 40_000.0;
                (
                    -5.0 + 10.0 * s * s * s * (10.0 - 15.0 * s + 6.0 * s * s),
                    2.0,
                )
            } else if phase < 840_000.0 {
                (5.0, 0.5)
            } else {
                let s = (phase - 840_000.0) / 40_000.0;
                (
                    5.0 - 10.0 * s * s * s * (10.0 - 15.0 * s + 6.0 * s * s),
                    0.5,
                )
            };
            let noise = 0.02 * ((i as f64 * 12.9898).sin() * 43758.5453).fract();
            sample(t_us, yaw, d, noise)
        })
        .collect()
}

fn step(c: &mut Criterion) {
    let w = 256;
    let mut p = Plane::new(w, w, 0.5);
    for y in 0..w {
        for x in 0..w / 2 {
            p.data_mut()[y * w + x] = 2.0;
        }
    }
    let depth = Arc::new(DepthMap::from_diopters(p).unwrap());
    let samples = stream(20_000);
    let fresh = || {
        let mut s = Scheduler::new(SchedulerConfig::new(Mode::Varifocal)).unwrap();
        s.step(
            Timestamp::ZERO,
            Event::Depth(depth.clone()),
            &mut Vec::new(),
        );
        s
    };
    let mut sched = fresh();
    let mut out = Vec::with_capacity(16);
    let mut i = 0;
    c.bench_function(
        "scheduler step: one gaze sample (varifocal, 256² depth)",
        |b| {
            b.iter(|| {
                if i == samples.len() {
                    sched = fresh();
                    i = 0;
                }
                let s = samples[i];
                i += 1;
                out.clear();
                sched.step(s.host_time, Event::Gaze(black_box(s)), &mut out);
                out.len()
            })
        },
    );
}

criterion_group! {
    name = benches;
    config = Criterion::default().measurement_time(Duration::from_secs(5));
    targets = step
}
criterion_main!(benches);
