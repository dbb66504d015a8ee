use super::*;
use crate::config::RigConfig;
use dioptra_core::EyeRay;

fn sample() -> GazeSample {
    GazeSample {
        device_time: Timestamp(5_000_000_000),
        host_receive_time: Timestamp(2_001_000_000),
        host_time: Timestamp(2_000_000_000),
        left: EyeRay {
            origin_mm: [-32.0, 0.0, 0.0],
            direction: [0.1, 0.0, 0.995],
            pupil_mm: 4.0,
            valid: true,
        },
        right: EyeRay {
            origin_mm: [32.0, 0.0, 0.0],
            direction: [-0.1, 0.0, 0.995],
            pupil_mm: 4.1,
            valid: true,
        },
    }
}

/// A lens per eye: a lens outlet per eye, between the gaze and marker outlets (the order
/// the LSL thread pushes to).
#[test]
fn a_lens_per_eye_has_a_lens_outlet_per_eye() {
    let one = RigConfig::parse(crate::config::EXAMPLE_SIM_RIG).unwrap();
    let names: Vec<String> = stream_specs(&one.lsl, &one.devices)
        .into_iter()
        .map(|s| s.name)
        .collect();
    assert_eq!(names, ["dioptra-gaze", "dioptra-lens", "dioptra-markers"]);
    let two = RigConfig::parse(crate::config::EXAMPLE_SIM_BINOCULAR_RIG).unwrap();
    let specs = stream_specs(&two.lsl, &two.devices);
    let names: Vec<&str> = specs.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "dioptra-gaze",
            "dioptra-lens-left",
            "dioptra-lens-right",
            "dioptra-markers"
        ]
    );
    assert!(specs[1..3]
        .iter()
        .all(|s| s.kind == "Lens" && s.source_id == s.name));
}

#[test]
fn a_gaze_sample_fills_every_declared_channel_in_order() {
    let v = gaze_values(&sample(), "fixation", Some(2.0));
    assert_eq!(v.len(), GAZE_CHANNELS.len());
    let at = |label: &str| v[GAZE_CHANNELS.iter().position(|c| c.label == label).unwrap()];
    assert_eq!(at("left_position_x"), -32.0);
    assert_eq!(at("right_pupil_diameter"), f64::from(4.1f32));
    assert_eq!(at("left_valid"), 1.0);
    // Converging eyes look straight ahead together.
    assert!(at("cyclopean_direction_x").abs() < 1e-9);
    assert!((at("cyclopean_direction_z") - 1.0).abs() < 1e-9);
    assert_eq!(at("vergence_depth"), 2.0);
    assert_eq!(at("eye_phase"), 1.0);
    assert_eq!(at("device_time"), 5.0);
    assert_eq!(at("host_time"), 2.0);
}

#[test]
fn an_invalid_eye_is_nan_and_the_cyclopean_ray_is_the_other_one() {
    let mut g = sample();
    g.left.valid = false;
    let v = gaze_values(&g, "saccade", None);
    assert!(v[0..7].iter().all(|x| x.is_nan()), "{v:?}");
    assert_eq!(v[7], 0.0);
    let right_dir = &v[8..11];
    let cyc = &v[16..19];
    let n = (0.1f64.powi(2) + 0.995f64.powi(2)).sqrt();
    for (c, r) in cyc.iter().zip(right_dir) {
        assert!((c - r / n).abs() < 1e-6, "{cyc:?} {right_dir:?}");
    }
    assert_eq!(v[19], 1.0);
    assert!(v[20].is_nan());
    assert_eq!(v[21], 3.0);
    g.right.valid = false;
    let v = gaze_values(&g, "blink", None);
    assert!(v[16..19].iter().all(|x| x.is_nan()));
    assert_eq!(v[19], 0.0);
}

#[test]
fn the_clock_map_keeps_the_tightest_pair() {
    // Host readings 0, 10 (wide pair), then 20, 21 (tight): LSL read 1000 and 1020.5.
    let host = [0.0, 10.0, 20.0, 21.0];
    let lsl = [1000.0, 1020.5];
    let (mut h, mut l) = (host.iter(), lsl.iter());
    let m = ClockMap::estimate(2, || *h.next().unwrap(), || *l.next().unwrap());
    assert_eq!(m.offset_s, 1000.0);
    assert_eq!(m.lsl_time(Timestamp(3_000_000_000)), 1003.0);
}

#[test]
fn the_specs_name_three_streams_by_the_configured_name() {
    let mut cfg = RigConfig::parse(crate::config::EXAMPLE_SIM_RIG).unwrap();
    cfg.lsl.name = "rig7".into();
    let s = stream_specs(&cfg.lsl, &cfg.devices);
    let names: Vec<_> = s.iter().map(|s| (s.name.as_str(), s.kind)).collect();
    assert_eq!(
        names,
        [
            ("rig7-gaze", "Gaze"),
            ("rig7-lens", "Lens"),
            ("rig7-markers", "Markers")
        ]
    );
    assert_eq!(s[0].rate_hz, cfg.devices.gaze.sim_rate_hz);
}

#[test]
fn markers_are_json_with_the_event_first() {
    let cfg = RigConfig::parse(crate::config::EXAMPLE_SIM_RIG).unwrap();
    let (o, rx) = LslOutlets::to_channel(&cfg.lsl, &cfg.devices);
    o.marker(Timestamp(7), "frame", json!({ "frame": 3 }));
    match rx.try_recv().unwrap() {
        LslSample::Marker { t, text } => {
            assert_eq!(t, Timestamp(7));
            let v: Value = serde_json::from_str(&text).unwrap();
            assert_eq!(v, json!({ "event": "frame", "frame": 3 }));
        }
        other => panic!("{other:?}"),
    }
}

/// What a running simulated rig hands its outlets.
#[tokio::test(start_paused = true)]
async fn a_running_rig_hands_gaze_lens_and_markers_to_its_outlets() {
    use crate::{Control, Rig, RigSetup};
    let cfg = RigConfig::parse(crate::config::EXAMPLE_SIM_RIG).unwrap();
    let rate = cfg.devices.gaze.sim_rate_hz;
    let (outlets, rx) = LslOutlets::to_channel(&cfg.lsl, &cfg.devices);
    let mut setup = RigSetup::new(cfg);
    setup.simulated_time = true;
    setup.lsl = Some(outlets);
    let rig = Rig::start(setup).await.unwrap();
    let state = rig.state().clone();
    tokio::time::sleep(std::time::Duration::from_secs(2)).await;
    state
        .control(Control::ManualFocus(Some(2.0)))
        .await
        .unwrap();
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    assert_eq!(state.status_json()["lsl"]["dropped"], 0);
    state.cancel.cancel();
    rig.wait().await;

    let (mut gaze, mut lens, mut markers) = (vec![], vec![], vec![]);
    for s in rx.try_iter() {
        match s {
            LslSample::Gaze { t, values } => gaze.push((t, values)),
            LslSample::Lens { t, values, .. } => lens.push((t, values)),
            LslSample::Marker { t, text } => markers.push((t, text)),
        }
    }
    // 2.5 s of samples, each with every channel, in time order.
    let expected = 2.5 * rate;
    assert!(
        (gaze.len() as f64) > 0.9 * expected && (gaze.len() as f64) < 1.1 * expected,
        "{} gaze samples for {expected}",
        gaze.len()
    );
    assert!(gaze.iter().all(|(_, v)| v.len() == GAZE_CHANNELS.len()));
    assert!(gaze.windows(2).all(|w| w[0].0 <= w[1].0));
    // The scheduler's phase reached the stream: the saccades scene has fixations.
    let phase = GAZE_CHANNELS
        .iter()
        .position(|c| c.label == "eye_phase")
        .unwrap();
    assert!(gaze.iter().any(|(_, v)| v[phase] == 1.0));
    // Commands on the wire and read-backs, the manual 2 D among the commands.
    assert!(lens.iter().all(|(_, v)| v.len() == LENS_CHANNELS.len()));
    // The example rig's map is the identity: the focus channels equal the powers.
    assert!(lens
        .iter()
        .any(|(_, v)| v[0] == LENS_EVENT_COMMANDED && v[1] == 2.0 && v[4] == 2.0));
    assert!(lens
        .iter()
        .any(|(_, v)| v[0] == LENS_EVENT_READ_BACK && v[2].is_finite()));
    let events: Vec<Value> = markers
        .iter()
        .map(|(_, m)| serde_json::from_str(m).unwrap())
        .collect();
    assert!(events.iter().any(|e| e["event"] == "frame"));
    assert!(events
        .iter()
        .any(|e| e["event"] == "control" && e["kind"] == "manual_focus" && e["diopters"] == 2.0));
}

#[tokio::test(start_paused = true)]
async fn lsl_on_simulated_time_is_refused() {
    let mut cfg = RigConfig::parse(crate::config::EXAMPLE_SIM_RIG).unwrap();
    cfg.lsl.enabled = true;
    let mut setup = crate::RigSetup::new(cfg);
    setup.simulated_time = true;
    let e = crate::Rig::start(setup).await.err().expect("refused");
    assert!(e.to_string().contains("simulated time"), "{e}");
}

#[cfg(not(feature = "lsl"))]
#[test]
fn without_the_feature_starting_outlets_says_how_to_build_them() {
    let cfg = RigConfig::parse(crate::config::EXAMPLE_SIM_RIG).unwrap();
    let clock: Arc<dyn Clock> = Arc::new(dioptra_sim::tokio_clock::TokioClock::new());
    let e = LslOutlets::start(&cfg.lsl, &cfg.devices, clock)
        .err()
        .expect("no liblsl");
    assert!(e.contains("--features lsl"), "{e}");
}

#[test]
fn a_full_queue_drops_and_counts_rather_than_blocking_the_loop() {
    let cfg = RigConfig::parse(crate::config::EXAMPLE_SIM_RIG).unwrap();
    let (o, _rx) = LslOutlets::to_channel(&cfg.lsl, &cfg.devices);
    for _ in 0..QUEUE + 5 {
        o.marker(Timestamp(0), "x", json!({}));
    }
    let s = o.status_json();
    assert_eq!(s["queued"], QUEUE as u64);
    assert_eq!(s["dropped"], 5);
}
