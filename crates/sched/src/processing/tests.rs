//! The processor on synthetic signals with known answers.

use dioptra_core::{EyeRay, GazeSample, Timestamp};

use super::*;

const IPD_MM: f64 = 64.0;

/// A tiny deterministic normal generator (SplitMix64 + Box-Muller).
struct Noise(u64);
impl Noise {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn normal(&mut self) -> f64 {
        let u = self.uniform().max(1e-12);
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * self.uniform()).cos()
    }
}

/// Both eyes fixating the point at `a` and `diopters`, each ray perturbed by `noise_deg`.
fn sample(t_us: u64, a: Angles, diopters: f64, noise_deg: f64, rng: &mut Noise) -> GazeSample {
    let dist = 1000.0 / diopters;
    let p = glam::DVec3::from(a.direction()) * dist;
    let eye = |x: f64, rng: &mut Noise| {
        let o = glam::DVec3::new(x, 0.0, 0.0);
        let d = unit(p - o).unwrap();
        let mut ang = Angles::from_direction(d.to_array());
        ang.yaw_deg += noise_deg * rng.normal();
        ang.pitch_deg += noise_deg * rng.normal();
        let d = ang.direction();
        EyeRay {
            origin_mm: [x as f32, 0.0, 0.0],
            direction: [d[0] as f32, d[1] as f32, d[2] as f32],
            pupil_mm: 4.0,
            valid: true,
        }
    };
    let t = Timestamp::from_micros(t_us);
    GazeSample {
        device_time: t,
        host_receive_time: t,
        host_time: t,
        left: eye(-IPD_MM / 2.0, rng),
        right: eye(IPD_MM / 2.0, rng),
    }
}

/// Minimum-jerk position fraction at `s` in [0, 1].
fn min_jerk(s: f64) -> f64 {
    let s = s.clamp(0.0, 1.0);
    s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
}

fn yaw(y: f64) -> Angles {
    Angles {
        yaw_deg: y,
        pitch_deg: 0.0,
    }
}

#[test]
fn ten_degree_saccade_at_500_hz_is_detected_within_two_samples() {
    let mut rng = Noise(1);
    let mut p = GazeProcessor::new(ProcessorConfig::default());
    let (period, onset_us) = (2_000u64, 200_000u64);
    let dur = saccades::main_sequence_duration_ms(10.0) * 1e3;
    let pos = |t: u64| {
        let s = (t as f64 - onset_us as f64) / dur;
        yaw(-5.0 + 10.0 * min_jerk(s))
    };
    // The movement starts where the true speed passes 30 deg/s (the usual onset criterion).
    let mut true_onset = None;
    let mut detected = None;
    for i in 0..200u64 {
        let t = i * period;
        let v = (pos(t + 1).yaw_deg - pos(t).yaw_deg) * 1e6;
        if v > 30.0 && true_onset.is_none() {
            true_onset = Some(i);
        }
        let st = p.push(&sample(t, pos(t), 1.0, 0.02, &mut rng));
        if st.phase == EyePhase::Saccade && detected.is_none() {
            detected = Some(i);
        }
    }
    let (o, d) = (true_onset.unwrap(), detected.unwrap());
    assert!(d >= o && d - o <= 2, "onset sample {o}, detected at {d}");
    assert_eq!(p.state().saccades, 1);
    assert_eq!(p.state().phase, EyePhase::Fixation);
    let centre = p.state().fixation.unwrap().centre;
    assert!((centre.yaw_deg - 5.0).abs() < 0.05, "{centre:?}");
}

#[test]
fn fixation_noise_is_smoothed_and_saccades_are_not_lagged() {
    let mut rng = Noise(2);
    let mut p = GazeProcessor::new(ProcessorConfig::default());
    let (mut raw_err, mut smooth_err, mut n) = (0.0, 0.0, 0.0);
    for i in 0..500u64 {
        let st = p.push(&sample(i * 2_000, yaw(3.0), 1.0, 0.05, &mut rng));
        if i > 100 {
            raw_err += (st.raw.unwrap().yaw_deg - 3.0).powi(2);
            smooth_err += (st.smoothed.unwrap().yaw_deg - 3.0).powi(2);
            n += 1.0;
        }
    }
    let (raw_rms, smooth_rms) = ((raw_err / n).sqrt(), (smooth_err / n).sqrt());
    assert!(
        smooth_rms < raw_rms / 2.5,
        "raw {raw_rms} smoothed {smooth_rms}"
    );
    assert_eq!(p.state().saccades, 0);
    // A 15 degree saccade: during it the smoothed gaze is the raw gaze.
    let dur = saccades::main_sequence_duration_ms(15.0) * 1e3;
    let t0 = 1_000_000u64;
    let mut in_saccade = 0;
    for i in 0..100u64 {
        let t = t0 + i * 2_000;
        let a = yaw(3.0 + 15.0 * min_jerk(i as f64 * 2_000.0 / dur));
        let st = *p.push(&sample(t, a, 1.0, 0.05, &mut rng));
        if st.phase == EyePhase::Saccade {
            in_saccade += 1;
            assert_eq!(st.smoothed, st.raw);
        }
        if (i as f64) * 2_000.0 > dur + 10_000.0 {
            let lag = (st.smoothed.unwrap().yaw_deg - 18.0).abs();
            assert!(
                lag < 0.3,
                "10 ms after landing the smoothed gaze is {lag} deg off"
            );
        }
    }
    assert!(in_saccade >= 10, "{in_saccade} saccade samples");
    assert_eq!(p.state().saccades, 1);
}

#[test]
fn microsaccades_and_noise_are_not_saccades() {
    let mut rng = Noise(3);
    let mut p = GazeProcessor::new(ProcessorConfig::default());
    for i in 0..1000u64 {
        // A 0.4 degree microsaccade every 400 ms.
        let k = i / 200;
        let s = ((i % 200) as f64 * 2_000.0) / 22_000.0;
        let a = yaw(k as f64 * 0.4 + 0.4 * min_jerk(s));
        p.push(&sample(i * 2_000, a, 1.0, 0.02, &mut rng));
    }
    assert_eq!(p.state().saccades, 0);
}

#[test]
fn vergence_fuses_to_the_fixated_depth() {
    let mut rng = Noise(4);
    let mut p = GazeProcessor::new(ProcessorConfig {
        tracker_noise_deg: 0.05,
        ..ProcessorConfig::default()
    });
    for i in 0..150u64 {
        p.push(&sample(i * 2_000, yaw(4.0), 2.0, 0.05, &mut rng));
    }
    assert_eq!(p.state().saccades, 0);
    let v = p.state().vergence.unwrap();
    assert!((v.diopters - 2.0).abs() < 0.01, "{v:?}");
    let single = p.state().vergence_raw.unwrap();
    assert!(v.sigma_d < single.sigma_d / 4.0, "{v:?} vs {single:?}");
    // Noise-free: exact.
    let mut p = GazeProcessor::new(ProcessorConfig::default());
    p.push(&sample(0, yaw(0.0), 2.0, 0.0, &mut rng));
    assert!((p.state().vergence.unwrap().diopters - 2.0).abs() < 0.05);
}

#[test]
fn blinks_and_loss_are_told_apart_and_tracking_resumes_cleanly() {
    let mut rng = Noise(5);
    let mut p = GazeProcessor::new(ProcessorConfig::default());
    let closed = |t: u64, rng: &mut Noise| {
        let mut s = sample(t, yaw(0.0), 1.0, 0.0, rng);
        s.left.valid = false;
        s.right.valid = false;
        s
    };
    let mut t = 0;
    let step = |p: &mut GazeProcessor, s: GazeSample| *p.push(&s);
    for _ in 0..50 {
        t += 2_000;
        step(&mut p, sample(t, yaw(0.0), 1.0, 0.02, &mut rng));
    }
    for _ in 0..50 {
        t += 2_000;
        assert_eq!(step(&mut p, closed(t, &mut rng)).phase, EyePhase::Blink);
    }
    // The eye reopens 10 degrees away: no saccade is made up across the gap.
    for _ in 0..50 {
        t += 2_000;
        let st = step(&mut p, sample(t, yaw(10.0), 1.0, 0.02, &mut rng));
        assert_eq!(st.phase, EyePhase::Fixation);
    }
    assert_eq!((p.state().blinks, p.state().saccades), (1, 0));
    for _ in 0..300 {
        t += 2_000;
        step(&mut p, closed(t, &mut rng));
    }
    assert_eq!(p.state().phase, EyePhase::Lost);
    // One eye is enough.
    t += 2_000;
    let mut one = sample(t, yaw(2.0), 1.0, 0.0, &mut rng);
    one.left.valid = false;
    let st = step(&mut p, one);
    assert_eq!(st.phase, EyePhase::Fixation);
    assert!((st.raw.unwrap().yaw_deg - 2.0).abs() < 0.5);
    assert!(st.vergence_raw.is_none());
}

#[test]
fn a_burst_of_queued_reports_is_timed_by_the_device_clock() {
    // Fixation samples 2 ms apart on the device, received (and mapped) 10 µs apart.
    let mut rng = Noise(8);
    let mut p = GazeProcessor::new(ProcessorConfig::default());
    for i in 0..50u64 {
        let mut s = sample(i * 2_000, yaw(1.0), 1.0, 0.02, &mut rng);
        s.host_time = Timestamp::from_micros(100_000 + i * 10);
        p.push(&s);
    }
    assert_eq!(p.state().saccades, 0);
    assert!(p.state().speed_dps < 30.0, "{}", p.state().speed_dps);
    assert_eq!(p.state().time, Timestamp::from_micros(100_490));
    // A device clock that steps back restarts the history rather than making up speed.
    let mut s = sample(0, yaw(6.0), 1.0, 0.0, &mut rng);
    s.host_time = Timestamp::from_micros(200_000);
    assert_eq!(p.push(&s).speed_dps, 0.0);
    assert_eq!(p.state().saccades, 0);
}

#[test]
fn samples_out_of_order_are_rejected() {
    let mut rng = Noise(6);
    let mut p = GazeProcessor::new(ProcessorConfig::default());
    p.push(&sample(10_000, yaw(1.0), 1.0, 0.0, &mut rng));
    let before = *p.state();
    let st = *p.push(&sample(10_000, yaw(9.0), 1.0, 0.0, &mut rng));
    assert_eq!(st.rejected, 1);
    assert_eq!(st.raw, before.raw);
    p.push(&sample(5_000, yaw(9.0), 1.0, 0.0, &mut rng));
    assert_eq!(p.state().rejected, 2);
}

#[test]
fn prediction_extrapolates_pursuit_and_saccades() {
    let mut rng = Noise(7);
    let mut p = GazeProcessor::new(ProcessorConfig::default());
    assert!(p.predict(Timestamp::ZERO).is_none());
    // 20 deg/s pursuit at 250 Hz.
    for i in 0..100u64 {
        let t = i * 4_000;
        p.push(&sample(
            t,
            yaw(-10.0 + 20.0 * t as f64 * 1e-6),
            1.0,
            0.01,
            &mut rng,
        ));
    }
    assert_eq!(p.state().phase, EyePhase::Pursuit);
    let now = p.state().time;
    let pred = p
        .predict(now + std::time::Duration::from_millis(50))
        .unwrap();
    let truth = -10.0 + 20.0 * (now.as_micros() + 50_000) as f64 * 1e-6;
    assert!(
        (pred.angles.yaw_deg - truth).abs() < 0.3,
        "{pred:?} vs {truth}"
    );
    assert_eq!(pred.horizon_us, 50_000);
    // The horizon is capped.
    let far = p.predict(now + std::time::Duration::from_secs(5)).unwrap();
    assert_eq!(far.horizon_us, 100_000);

    // A 12 degree saccade at 1000 Hz: once past peak speed, predicting to the end lands near
    // the target; a hold-last-sample predictor would be degrees off.
    let mut p = GazeProcessor::new(ProcessorConfig::default());
    let dur = saccades::main_sequence_duration_ms(12.0) * 1e3;
    let onset = 100_000u64;
    let mut checked = false;
    for i in 0..200u64 {
        let t = i * 1_000;
        let a = yaw(12.0 * min_jerk((t as f64 - onset as f64) / dur));
        let st = *p.push(&sample(t, a, 1.0, 0.0, &mut rng));
        let since = t as f64 - onset as f64;
        if st.phase == EyePhase::Saccade && since > 0.6 * dur && !checked {
            let pred = p
                .predict(Timestamp::from_micros(onset + dur as u64))
                .unwrap();
            let err = (pred.angles.yaw_deg - 12.0).abs();
            let hold = (st.raw.unwrap().yaw_deg - 12.0).abs();
            assert!(
                err < 1.0 && err < hold / 2.0,
                "predicted {err} deg off, holding {hold}"
            );
            checked = true;
        }
    }
    assert!(checked);
}

mod arbitrary_input {
    use super::*;
    use proptest::prelude::*;

    fn any_f32() -> impl Strategy<Value = f32> {
        prop_oneof![
            4 => -2.0f32..2.0,
            1 => Just(f32::NAN),
            1 => Just(f32::INFINITY),
            1 => Just(0.0f32),
            1 => any::<f32>(),
        ]
    }

    fn any_eye() -> impl Strategy<Value = EyeRay> {
        (
            proptest::array::uniform3(any_f32()),
            proptest::array::uniform3(any_f32()),
            any::<bool>(),
        )
            .prop_map(|(o, d, valid)| EyeRay {
                origin_mm: o.map(|v| v * 40.0),
                direction: d,
                pupil_mm: 4.0,
                valid,
            })
    }

    proptest! {
        /// Whatever a device or caller feeds it, the processor neither panics nor reports a
        /// non-finite angle or depth.
        #[test]
        fn never_panics_or_goes_non_finite(
            steps in proptest::collection::vec((0u64..20_000, any_eye(), any_eye()), 1..200)
        ) {
            let mut p = GazeProcessor::new(ProcessorConfig::default());
            let mut t = 0u64;
            for (dt, left, right) in steps {
                t = t.wrapping_add(dt);
                let ts = Timestamp::from_micros(t);
                let s = GazeSample { device_time: ts, host_receive_time: ts, host_time: ts, left, right };
                let st = *p.push(&s);
                for a in [st.raw, st.smoothed].into_iter().flatten() {
                    prop_assert!(a.yaw_deg.is_finite() && a.pitch_deg.is_finite());
                }
                if let Some(v) = st.vergence {
                    prop_assert!(v.diopters.is_finite() && v.sigma_d.is_finite());
                }
                if let Some(g) = p.predict(ts + std::time::Duration::from_millis(30)) {
                    prop_assert!(g.angles.yaw_deg.is_finite() && g.direction.iter().all(|v| v.is_finite()));
                }
            }
        }
    }
}
