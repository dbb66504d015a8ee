//! The page 0x12 driver against the simulated tracker, over the in-memory HID link, and
//! the layout finder on a hand-written descriptor with a different field layout.

use std::sync::Arc;

use dioptra_core::{DeviceError, GazeSource, LinkError};
use dioptra_gaze::eye_hid::protocol::{
    ConfigStatus, LayoutError, ModeRequest, ReportError, TrackerLayout,
};
use dioptra_gaze::eye_hid::{HidEyeTracker, HidTrackerConfig};
use dioptra_gaze::hid_descriptor::{self, ReportKind};
use dioptra_sched::processing::Angles;
use dioptra_sim::gaze::hid_tracker::{self, HidTrackerSetup};
use dioptra_sim::gaze::{Faults, GazeGenerator, GeneratorConfig, Scene};
use dioptra_sim::tokio_clock::TokioClock;

fn generator(noise: bool) -> GazeGenerator {
    let mut cfg = GeneratorConfig::default();
    if !noise {
        cfg.noise_deg = 0.0;
        cfg.dropout_probability = 0.0;
        cfg.blink_rate_hz = 0.0;
    }
    GazeGenerator::new(Scene::named("saccades").unwrap(), cfg).unwrap()
}

async fn connect(
    setup: HidTrackerSetup,
) -> (
    Result<HidEyeTracker<dioptra_transport::hid::memory::MemoryHidLink>, DeviceError>,
    dioptra_sim::gaze::SimTracker<hid_tracker::TrackerState>,
) {
    let clock = Arc::new(TokioClock::new());
    let (link, sim) = hid_tracker::spawn(Box::new(generator(false)), setup);
    let cfg = HidTrackerConfig {
        modes: ModeRequest::GAZE_POINT
            .with(ModeRequest::EYE_POSITION)
            .with(ModeRequest::HEAD_POSITION),
        ..HidTrackerConfig::default()
    };
    (HidEyeTracker::connect(link, cfg, clock).await, sim)
}

#[tokio::test(start_paused = true)]
async fn streams_gaze_that_matches_the_generator() {
    let (tracker, sim) = connect(HidTrackerSetup::default()).await;
    let mut tracker = tracker.unwrap();
    let info = tracker.info().clone();
    assert_eq!(info.sampling_frequency_hz, Some(500.0));
    assert_eq!(info.screen_um, (600_000.0, 340_000.0));
    assert_eq!(
        info.capabilities.optimum_tracking_distance_um,
        Some(600_000.0)
    );
    assert_eq!(info.capabilities.tracker_quality, Some(2));
    assert_eq!(tracker.rate_hz(), 500.0);

    // The generator is deterministic: a twin gives the truth for every sample sent.
    let mut truth = generator(false);
    let first = tracker.next_tracking().await.unwrap();
    // Samples before the stream started were not sent: skip the twin to the same time.
    let mut t = truth.next_truth();
    while t.reported.device_time_us < first.data.timestamp_us {
        t = truth.next_truth();
    }
    assert_eq!(t.reported.device_time_us, first.data.timestamp_us);
    let head = first.data.head_direction_deg.unwrap();
    assert!((head[1] - 1.5).abs() < 1e-9, "{head:?}");
    assert_eq!(
        first.data.head_position_um,
        Some([300_000.0, 170_000.0, 600_000.0])
    );
    let mut worst: f64 = 0.0;
    for _ in 0..2000 {
        let s = tracker.next_sample().await.unwrap();
        let t = truth.next_truth();
        assert_eq!(s.device_time.as_micros(), t.reported.device_time_us);
        assert!(s.left.valid && s.right.valid);
        // Both rays meet at the gaze point on the screen plane (z = 0 in the driver's frame).
        let v = dioptra_sched::processing::vergence::vergence(&s.left, &s.right, 0.1).unwrap();
        assert!(v.point_mm.unwrap()[2].abs() < 0.5, "{v:?}");
        // The cyclopean direction is the generator's gaze (µm rounding aside).
        let d: Vec<f64> = (0..3)
            .map(|k| f64::from(s.left.direction[k] + s.right.direction[k]))
            .collect();
        let a = Angles::from_direction([d[0], d[1], d[2]]);
        let err = a.distance_deg(&Angles {
            yaw_deg: t.yaw_deg,
            pitch_deg: t.pitch_deg,
        });
        worst = worst.max(err);
    }
    // Averaging two unit rays is not quite the ray from between the eyes: a few hundredths
    // of a degree at these vergence angles, on top of µm rounding.
    assert!(worst < 0.15, "worst angular error {worst} deg");
    // Host times: the link has no latency here, so mapping lands on receive time; the
    // simulated clock runs 30 ppm fast.
    let s = tracker.next_sample().await.unwrap();
    let gap = s.host_time.signed_diff_ns(s.host_receive_time).abs();
    assert!(gap < 100_000, "{gap} ns");
    let drift = tracker.clock_mapper().drift_ppm().unwrap();
    assert!((drift - 30.0).abs() < 5.0, "drift {drift} ppm");
    assert!(sim.sent() > 2000);
}

#[tokio::test(start_paused = true)]
async fn an_unreadable_configuration_falls_back_to_capabilities() {
    let (tracker, _sim) = connect(HidTrackerSetup {
        configuration_readable: false,
        screen_width_mm: 500.0,
        ..HidTrackerSetup::default()
    })
    .await;
    let info = tracker.unwrap().info().clone();
    assert_eq!(info.configuration, None);
    assert_eq!(info.screen_um, (500_000.0, 340_000.0));
}

#[tokio::test(start_paused = true)]
async fn a_tracker_needing_calibration_is_a_refusal() {
    let (r, _sim) = connect(HidTrackerSetup {
        status_when_done: 4,
        ..HidTrackerSetup::default()
    })
    .await;
    match r.unwrap_err() {
        DeviceError::Refused { code, detail } => {
            assert_eq!(code, 4);
            assert!(detail.contains("calibration"), "{detail}");
        }
        e => panic!("{e:?}"),
    }
    // Stuck configuring: refused once the ready timeout passes.
    let (r, _sim) = connect(HidTrackerSetup {
        configuring_polls: 100_000,
        ..HidTrackerSetup::default()
    })
    .await;
    assert!(
        matches!(&r, Err(DeviceError::Refused { code: 2, detail }) if detail.contains("configuring")),
        "{r:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn short_reports_stalls_and_unplugs_are_typed_errors() {
    let (tracker, sim) = connect(HidTrackerSetup::default()).await;
    let mut tracker = tracker.unwrap();
    tracker.next_sample().await.unwrap();
    sim.set_faults(Faults {
        truncate_to: Some(20),
        ..Faults::default()
    });
    // Reports already queued are whole; the first cut one is an error.
    let e = loop {
        match tracker.next_sample().await {
            Ok(_) => continue,
            Err(e) => break e,
        }
    };
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("20 bytes")),
        "{e:?}"
    );
    // Another report id is skipped, not an error.
    sim.set_faults(Faults::default());
    sim.inject(&[9, 1, 2, 3]);
    while tracker.skipped_reports() == 0 {
        tracker.next_sample().await.unwrap();
    }
    sim.set_faults(Faults {
        silent: true,
        ..Faults::default()
    });
    let e = loop {
        if let Err(e) = tracker.next_sample().await {
            break e;
        }
    };
    assert_eq!(e, DeviceError::Link(LinkError::Timeout { ms: 100 }));
    sim.disconnect("cable pulled");
    let e = tracker.next_sample().await.unwrap_err();
    assert!(e.needs_reconnect(), "{e:?}");
}

/// A descriptor laid out differently from the simulator's: no Configuration report,
/// timestamp as 8 x 8 bits after the gaze point, 16-bit gaze point in units of 0.1 mm
/// (cm, exponent -2), eye positions in the right-then-left order, and padding.
#[rustfmt::skip]
const OTHER_LAYOUT: &[u8] = &[
    0x05, 0x12, 0x09, 0x01, 0xa1, 0x01,
    0x85, 0x07, 0x09, 0x10, 0xa1, 0x02,
    0x16, 0x00, 0x80, 0x26, 0xff, 0x7f, 0x75, 0x10, 0x55, 0x0e, 0x65, 0x11,
    0x09, 0x24, 0xa1, 0x00, 0x09, 0x22, 0x09, 0x21, 0x95, 0x02, 0x81, 0x02, 0xc0, // Y then X
    0x55, 0x00, 0x65, 0x00,
    0x75, 0x04, 0x95, 0x01, 0x81, 0x03,                               // 4 bits padding
    0x15, 0x00, 0x26, 0xff, 0x00, 0x75, 0x08, 0x95, 0x08, 0x09, 0x20, 0x81, 0x02, // timestamp
    0x17, 0x00, 0x00, 0x00, 0x80, 0x27, 0xff, 0xff, 0xff, 0x7f, 0x75, 0x20, 0x95, 0x03,
    0x09, 0x26, 0xa1, 0x00, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x81, 0x02, 0xc0,
    0x09, 0x25, 0xa1, 0x00, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x81, 0x02, 0xc0,
    0xc0,
    0x85, 0x08, 0x09, 0x11, 0xa1, 0x02, 0x15, 0x00, 0x26, 0xe8, 0x03, 0x75, 0x10, 0x95, 0x01,
    0x0a, 0x00, 0x03, 0xb1, 0x02, 0xc0,                               // sampling frequency here
    0x85, 0x09, 0x09, 0x13, 0xa1, 0x02, 0x75, 0x08, 0x0a, 0x01, 0x03, 0xb1, 0x02, 0xc0,
    0x85, 0x0a, 0x09, 0x14, 0xa1, 0x02, 0x75, 0x03, 0x0a, 0x00, 0x04, 0xb1, 0x02,
    0x75, 0x05, 0xb1, 0x03, 0xc0,
    0xc0,
];

#[test]
fn a_different_layout_is_located_and_read() {
    let d = hid_descriptor::parse(OTHER_LAYOUT).unwrap();
    let l = TrackerLayout::locate(&d).unwrap();
    assert_eq!(
        (l.tracking.report_id, l.tracking.len),
        (7, 1 + 4 + 1 + 8 + 24)
    );
    assert!(l.configuration.is_none());
    // Build a report by hand: gaze (x 123.4 mm, y 56.7 mm) as 0.1 mm units, Y first.
    let mut r = vec![0u8; l.tracking.len];
    r[0] = 7;
    r[1..3].copy_from_slice(&567i16.to_le_bytes());
    r[3..5].copy_from_slice(&1234i16.to_le_bytes());
    // Timestamp starts after 4 padding bits: byte 5, high nibble.
    let ts: u64 = 0x0123_4567_89ab_cdef;
    let bits = u128::from(ts) << 4;
    for i in 0..9 {
        r[5 + i] |= (bits >> (8 * i)) as u8;
    }
    // The eyes start mid-byte (bit 100): write them through the located fields.
    let right = l.tracking.right_eye.as_ref().unwrap();
    let left = l.tracking.left_eye.as_ref().unwrap();
    for (k, v) in [30_000, -2_000, 650_000].into_iter().enumerate() {
        assert!(right[k].field.write(&mut r, i64::from(v)));
        assert!(left[k].field.write(&mut r, i64::from(v - 64_000)));
    }
    let data = l.tracking.parse(&r).unwrap();
    assert_eq!(data.timestamp_us, ts);
    let g = data.gaze_point_um.unwrap();
    assert!(
        (g[0] - 123_400.0).abs() < 1e-6 && (g[1] - 56_700.0).abs() < 1e-6,
        "{g:?}"
    );
    assert_eq!(data.right_eye_um, Some([30_000.0, -2_000.0, 650_000.0]));
    assert_eq!(data.left_eye_um, Some([-34_000.0, -66_000.0, 586_000.0]));
    // Feature reports: sampling frequency in Capabilities, 3-bit mode request.
    let caps = l.parse_capabilities(&[8, 0xe8, 0x03]).unwrap();
    assert_eq!(caps.sampling_frequency_hz, Some(1000.0));
    assert_eq!(
        l.parse_status(&[9, 2]).unwrap().config_status,
        ConfigStatus::Configuring
    );
    assert_eq!(l.control_report(ModeRequest(5)), vec![10, 5]);
    // Malformed reports.
    assert_eq!(
        l.tracking.parse(&r[..10]),
        Err(ReportError::Short {
            id: 7,
            needed: 38,
            got: 10
        })
    );
    assert_eq!(l.tracking.parse(&[]), Err(ReportError::Empty));
    assert!(matches!(
        l.tracking.parse(&[8, 0, 0]),
        Err(ReportError::WrongId { .. })
    ));
    assert!(l.parse_status(&[9]).is_err());
}

#[test]
fn descriptors_without_required_usages_are_refused_by_name() {
    let mut no_control = OTHER_LAYOUT.to_vec();
    // Turn the Mode Request usage (0x400) into an unassigned one (0x401).
    let at = no_control
        .windows(3)
        .position(|w| w == [0x0a, 0x00, 0x04])
        .unwrap();
    no_control[at + 1] = 0x01;
    let d = hid_descriptor::parse(&no_control).unwrap();
    let e = TrackerLayout::locate(&d).unwrap_err();
    assert!(
        matches!(
            e,
            LayoutError::Missing {
                what: "Mode Request",
                kind: ReportKind::Feature,
                ..
            }
        ),
        "{e:?}"
    );
    assert!(e.to_string().contains("Mode Request"));
    // No gaze point at all: the simulator of the dioptra tracker is not a page 0x12 device.
    let d = hid_descriptor::parse(dioptra_sim::gaze::dioptra_tracker::DESCRIPTOR).unwrap();
    let e = TrackerLayout::locate(&d).unwrap_err();
    assert!(
        matches!(
            e,
            LayoutError::Missing {
                what: "Timestamp",
                ..
            }
        ),
        "{e:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn the_wrong_device_fails_at_connect_with_the_reason() {
    let clock = Arc::new(TokioClock::new());
    let (link, _sim) = dioptra_sim::gaze::dioptra_tracker::spawn(Box::new(generator(false)));
    let e = HidEyeTracker::connect(link, HidTrackerConfig::default(), clock)
        .await
        .unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("Timestamp")),
        "{e:?}"
    );
}
