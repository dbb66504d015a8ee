//! The processor on the simulator's scenes (sans-IO, no driver): each scene's known answer.

use dioptra_core::{GazeSample, Timestamp};
use dioptra_gaze::dioptra_tracker::protocol::eye_ray;
use dioptra_sched::processing::{EyePhase, GazeProcessor, GazeState, ProcessorConfig};
use dioptra_sim::gaze::generator::{TruePhase, TruthSample};
use dioptra_sim::gaze::{GazeGenerator, GeneratorConfig, Scene};

/// Runs `n` samples of a scene through the processor; the truth and the state per sample.
fn run(scene: &str, n: usize, cfg: GeneratorConfig) -> Vec<(TruthSample, GazeState)> {
    let mut g = GazeGenerator::new(Scene::named(scene).unwrap(), cfg).unwrap();
    let mut p = GazeProcessor::new(ProcessorConfig {
        tracker_noise_deg: cfg.noise_deg.max(0.01),
        ..ProcessorConfig::default()
    });
    (0..n)
        .map(|_| {
            let t = g.next_truth();
            let ts = Timestamp::from_micros(t.time_us);
            let s = GazeSample {
                device_time: ts,
                host_receive_time: ts,
                host_time: ts,
                left: eye_ray(&t.reported.left),
                right: eye_ray(&t.reported.right),
            };
            (t, *p.push(&s))
        })
        .collect()
}

fn quiet() -> GeneratorConfig {
    GeneratorConfig {
        blink_rate_hz: 0.0,
        dropout_probability: 0.0,
        ..GeneratorConfig::default()
    }
}

#[test]
fn pursuit_is_told_from_fixation() {
    // 3.6 s: fixate 0.3 s, pursue 24 degrees in 1.5 s (16 deg/s), fixate, pursue back.
    let out = run("pursuit", 1800, quiet());
    let agree = |phase: TruePhase, want: EyePhase| {
        let of: Vec<_> = out.iter().filter(|(t, _)| t.phase == phase).collect();
        of.iter().filter(|(_, s)| s.phase == want).count() as f64 / of.len() as f64
    };
    let pursuit = agree(TruePhase::Pursuit, EyePhase::Pursuit);
    assert!(pursuit > 0.9, "pursuit recognised {pursuit}");
    let fixation = agree(TruePhase::Fixation, EyePhase::Fixation);
    assert!(fixation > 0.7, "fixation recognised {fixation}");
    assert_eq!(out.last().unwrap().1.saccades, 0);
}

#[test]
fn vergence_follows_depth_changes_without_saccades() {
    let out = run("vergence", 2000, quiet());
    for (i, want) in [(495, 0.5), (995, 3.0), (1495, 0.5), (1995, 3.0)] {
        let v = out[i].1.vergence.unwrap();
        assert!((v.diopters - want).abs() < 0.1, "sample {i}: {v:?}");
        assert!(v.sigma_d < 0.05);
    }
    assert_eq!(out.last().unwrap().1.saccades, 0);
}

#[test]
fn scripted_blinks_are_counted_and_dropouts_are_ignored() {
    let cfg = GeneratorConfig {
        blink_rate_hz: 0.0,
        dropout_probability: 0.02,
        ..GeneratorConfig::default()
    };
    // 3.4 s: two cycles of two 150 ms blinks, with a 8 degree saccade after each.
    let out = run("blinks", 1700, cfg);
    let last = out.last().unwrap().1;
    assert_eq!(last.blinks, 4);
    assert!(out
        .iter()
        .filter(|(t, _)| t.phase == TruePhase::Blink)
        .all(|(_, s)| s.phase == EyePhase::Blink));
    // The eyes reopen on the other target, so no saccade is seen (it happened behind the lids)
    // unless the eyes were still moving when they opened.
    assert!(last.saccades <= 4, "{}", last.saccades);
}

#[test]
fn saccade_onsets_are_found_within_two_samples_in_the_saccades_scene() {
    let out = run("saccades", 1600, quiet());
    let mut onsets = Vec::new();
    let mut detections = Vec::new();
    let mut in_saccade = false;
    for i in 1..out.len() {
        // Onset: the true speed passes 30 deg/s (the usual criterion) within a saccade.
        let (a, b) = (&out[i - 1].0, &out[i].0);
        let speed = (b.yaw_deg - a.yaw_deg).hypot(b.pitch_deg - a.pitch_deg) * 500.0;
        if b.phase != TruePhase::Saccade {
            in_saccade = false;
        } else if speed > 30.0 && !in_saccade {
            in_saccade = true;
            onsets.push(i);
        }
        if out[i].1.saccades > out[i - 1].1.saccades {
            detections.push(i);
        }
    }
    assert_eq!(
        onsets.len(),
        detections.len(),
        "{onsets:?} vs {detections:?}"
    );
    for (o, d) in onsets.iter().zip(&detections) {
        assert!(d >= o && d - o <= 2, "onset {o}, detected {d}");
    }
}
