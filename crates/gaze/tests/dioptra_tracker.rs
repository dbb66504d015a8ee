//! The dioptra tracker driver against its simulator, and the processing chain on the
//! simulator's scenes with known targets.

use std::sync::Arc;

use dioptra_core::{DeviceError, GazeSource, LinkError};
use dioptra_gaze::dioptra_tracker::protocol::{decode_sample_report, StreamControl};
use dioptra_gaze::dioptra_tracker::{DioptraTracker, DioptraTrackerConfig};
use dioptra_gaze::eye_hid::protocol::ReportError;
use dioptra_sched::processing::{EyePhase, GazeProcessor, ProcessorConfig};
use dioptra_sim::gaze::dioptra_tracker::{self as sim_tracker, encode_sample_report};
use dioptra_sim::gaze::generator::TruePhase;
use dioptra_sim::gaze::{Faults, GazeGenerator, GeneratorConfig, Scene};
use dioptra_sim::tokio_clock::TokioClock;

fn generator(scene: &str, cfg: GeneratorConfig) -> GazeGenerator {
    GazeGenerator::new(Scene::named(scene).unwrap(), cfg).unwrap()
}

async fn connect(
    g: GazeGenerator,
    cfg: DioptraTrackerConfig,
) -> (
    Result<DioptraTracker<dioptra_transport::hid::memory::MemoryHidLink>, DeviceError>,
    dioptra_sim::gaze::SimTracker<sim_tracker::TrackerState>,
) {
    let (link, sim) = sim_tracker::spawn(Box::new(g));
    (
        DioptraTracker::connect(link, cfg, Arc::new(TokioClock::new())).await,
        sim,
    )
}

#[tokio::test(start_paused = true)]
async fn samples_arrive_exactly_as_generated() {
    let cfg = GeneratorConfig {
        dropout_probability: 0.05,
        ..GeneratorConfig::default()
    };
    let (tracker, sim) = connect(generator("saccades", cfg), DioptraTrackerConfig::default()).await;
    let mut tracker = tracker.unwrap();
    assert_eq!(tracker.rate_hz(), 500.0);
    let mut truth = generator("saccades", cfg);
    let mut invalid = 0;
    for i in 0..1500 {
        let s = tracker.next_sample().await.unwrap();
        let t = truth.next_truth().reported;
        assert_eq!(s.device_time.as_micros(), t.device_time_us, "sample {i}");
        assert_eq!(s.left.valid, t.left.valid);
        assert_eq!(s.right.origin_mm, t.right.origin_mm);
        if s.right.valid {
            for k in 0..3 {
                assert!((s.right.direction[k] - t.right.direction[k]).abs() < 1e-6);
            }
        }
        invalid += usize::from(!s.left.valid);
        assert!(
            s.host_time
                >= s.host_receive_time
                    .saturating_sub(std::time::Duration::from_micros(50))
        );
    }
    assert!(invalid > 20, "{invalid}");
    assert!(sim.sent() >= 1500);
}

#[tokio::test(start_paused = true)]
async fn rates_are_checked_and_refusals_reported() {
    let g = || generator("fixation", GeneratorConfig::default());
    let (r, _sim) = connect(
        g(),
        DioptraTrackerConfig {
            rate_hz: Some(2000),
            ..Default::default()
        },
    )
    .await;
    assert!(matches!(r, Err(DeviceError::OutOfRange { requested, .. }) if requested == 2000.0));
    // The simulator runs at 500 Hz and refuses another rate: a stalled request, an I/O error.
    let (r, _sim) = connect(
        g(),
        DioptraTrackerConfig {
            rate_hz: Some(250),
            ..Default::default()
        },
    )
    .await;
    assert!(
        matches!(&r, Err(DeviceError::Link(LinkError::Io(m))) if m.contains("500 Hz")),
        "{r:?}"
    );
    let (r, _sim) = connect(
        g(),
        DioptraTrackerConfig {
            rate_hz: Some(500),
            ..Default::default()
        },
    )
    .await;
    assert!(r.is_ok());
    // A page 0x12 device is not a dioptra tracker.
    let (link, _sim) = dioptra_sim::gaze::hid_tracker::spawn(Box::new(g()), Default::default());
    let e = DioptraTracker::connect(
        link,
        DioptraTrackerConfig::default(),
        Arc::new(TokioClock::new()),
    )
    .await
    .unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("not a dioptra tracker")),
        "{e:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn malformed_reports_stalls_and_unplugs() {
    let (tracker, sim) = connect(
        generator("fixation", GeneratorConfig::default()),
        DioptraTrackerConfig::default(),
    )
    .await;
    let mut tracker = tracker.unwrap();
    tracker.next_sample().await.unwrap();
    sim.set_faults(Faults {
        silent: true,
        ..Faults::default()
    });
    // Drain what is queued, then a garbage payload.
    while tracker.next_sample().await.is_ok() {}
    sim.inject(&[1, 3, 0xff, 0xff, 0xff]);
    let e = tracker.next_sample().await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("does not decode")),
        "{e:?}"
    );
    sim.inject(&[1, 60, 0]);
    let e = tracker.next_sample().await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("3 bytes")),
        "{e:?}"
    );
    sim.inject(&[7, 0]);
    let e = tracker.next_sample().await.unwrap_err();
    assert_eq!(e, DeviceError::Link(LinkError::Timeout { ms: 100 }));
    assert_eq!(tracker.skipped_reports(), 1);
    sim.set_faults(Faults::default());
    tracker.next_sample().await.unwrap();
    tracker.stop().await.unwrap();
    while tracker.next_sample().await.is_ok() {}
    drop(sim);
    assert!(tracker.next_sample().await.unwrap_err().needs_reconnect());
}

/// With 1-3 ms of jittered delivery latency and a device clock 30 ppm fast, the mapped host
/// time of each sample sits near exposure + the minimum latency, far steadier than receive time.
#[tokio::test(start_paused = true)]
async fn device_time_maps_to_host_time_through_latency_jitter() {
    let cfg = GeneratorConfig::default();
    let (link, sim) = sim_tracker::spawn(Box::new(generator("fixation", cfg)));
    sim.set_faults(Faults {
        latency_us: (1_000, 2_000),
        ..Faults::default()
    });
    let clock = Arc::new(TokioClock::new());
    let mut tracker = DioptraTracker::connect(link, DioptraTrackerConfig::default(), clock)
        .await
        .unwrap();
    let (mut worst_mapped, mut worst_receive) = (0i64, 0i64);
    for i in 0..3000 {
        let s = tracker.next_sample().await.unwrap();
        // The generator's true exposure time on the host timeline (both start at zero).
        let dev = s.device_time.as_micros() as f64;
        let exposure_ns = ((dev - 1e6) / (1.0 + 30e-6) * 1e3) as i64;
        if i >= 1500 {
            let mapped = s.host_time.as_nanos() as i64 - exposure_ns - 1_000_000;
            let received = s.host_receive_time.as_nanos() as i64 - exposure_ns - 1_000_000;
            worst_mapped = worst_mapped.max(mapped.abs());
            worst_receive = worst_receive.max(received.abs());
        }
    }
    assert!(
        worst_mapped < 250_000,
        "mapped time off by up to {worst_mapped} ns"
    );
    assert!(
        worst_receive > 1_500_000,
        "receive jitter {worst_receive} ns"
    );
    let drift = tracker.clock_mapper().drift_ppm().unwrap();
    assert!((drift - 30.0).abs() < 15.0, "drift {drift} ppm");
}

#[test]
fn report_decoding_checks_every_length() {
    let mut g = generator("saccades", GeneratorConfig::default());
    let s = g.next_truth().reported;
    let r = encode_sample_report(&s).unwrap();
    assert_eq!(decode_sample_report(&r), Ok(s));
    let n = usize::from(r[1]);
    assert_eq!(decode_sample_report(&r[..2 + n]), Ok(s));
    assert_eq!(
        decode_sample_report(&r[..1 + n]),
        Err(ReportError::Short {
            id: 1,
            needed: 2 + n,
            got: 1 + n
        })
    );
    let mut long = r;
    long[1] += 1; // claims one byte of padding as payload
    assert!(matches!(
        decode_sample_report(&long),
        Err(ReportError::Malformed { .. })
    ));
    long[1] = 69;
    assert!(matches!(
        decode_sample_report(&long),
        Err(ReportError::Malformed { .. })
    ));
    assert_eq!(decode_sample_report(&[]), Err(ReportError::Empty));
    assert!(matches!(
        decode_sample_report(&[1]),
        Err(ReportError::Short { .. })
    ));
    assert!(matches!(
        decode_sample_report(&[2, 0]),
        Err(ReportError::WrongId { .. })
    ));
    let c = StreamControl {
        streaming: true,
        rate_hz: 1000,
        version: 1,
    };
    assert_eq!(StreamControl::decode(&c.encode()), Ok(c));
    assert!(StreamControl::decode(&[2, 7, 0, 0, 1]).is_err());
    assert!(StreamControl::decode(&[2, 1]).is_err());
    assert!(StreamControl::decode(&[]).is_err());
}

/// Driver and processor on the "saccades" scene: every scripted saccade is found, and the
/// fused vergence reaches each target's depth.
#[tokio::test(start_paused = true)]
async fn processing_recovers_the_scene() {
    let cfg = GeneratorConfig {
        noise_deg: 0.02,
        blink_rate_hz: 0.0,
        ..GeneratorConfig::default()
    };
    let (tracker, _sim) =
        connect(generator("saccades", cfg), DioptraTrackerConfig::default()).await;
    let mut tracker = tracker.unwrap();
    let mut truth = generator("saccades", cfg);
    let mut p = GazeProcessor::new(ProcessorConfig {
        tracker_noise_deg: 0.02,
        ..ProcessorConfig::default()
    });
    let mut true_saccades = 0;
    let mut was_saccade = false;
    let mut depth_errors = Vec::new();
    // 3.2 s: two passes over four targets, 400 ms each.
    for i in 0..1600 {
        let s = tracker.next_sample().await.unwrap();
        let t = truth.next_truth();
        let st = *p.push(&s);
        let saccade = t.phase == TruePhase::Saccade;
        if saccade && !was_saccade {
            true_saccades += 1;
        }
        was_saccade = saccade;
        // Near the end of each fixation, against the eyes' actual vergence (still settling
        // towards the target's depth).
        if i % 200 == 195 {
            assert_eq!(st.phase, EyePhase::Fixation, "sample {i}");
            let v = st.vergence.unwrap();
            depth_errors.push((v.diopters - t.diopters).abs());
        }
    }
    assert_eq!(p.state().saccades, true_saccades);
    assert!(true_saccades >= 7, "{true_saccades}");
    let worst = depth_errors.iter().cloned().fold(0.0, f64::max);
    assert!(worst < 0.1, "vergence errors {depth_errors:?}");
}
