//! The page 0x12 driver against the simulated tracker (both of its layouts), over the
//! in-memory HID link; the layout finder on Microsoft's two reference descriptors
//! (`tests/data`, sources in its README) and on a hand-written descriptor with a different
//! field layout.

use std::sync::Arc;

use dioptra_core::{DeviceError, GazeSource, LinkError};
use dioptra_gaze::eye_hid::protocol::{
    ConfigStatus, LayoutError, ModeRequest, ReportError, TrackerLayout,
};
use dioptra_gaze::eye_hid::{HidEyeTracker, HidTrackerConfig};
use dioptra_gaze::hid_descriptor::{self, ReportKind};
use dioptra_sched::processing::Angles;
use dioptra_sim::gaze::hid_tracker::{self, HidTrackerSetup, SimLayout};
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
    assert_eq!(info.capabilities.tracker_quality, Some(1));
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

const GAZEHID: &[u8] = include_bytes!("data/gazehid_report_descriptor.bin");
const DMF: &[u8] = include_bytes!("data/dmf_virtual_eye_gaze_report_descriptor.bin");

/// A Tracking Data report as the sources' packed structs lay it out (GazeHid `inc/Tracker.h`
/// `GAZE_REPORT`, DMF `GAZE_DATA`): id 0x10, u64 timestamp, i32 gaze x/y, then 4 x 3 i32
/// (left eye, right eye, head position, head direction). Built from the structs, not from
/// the descriptor, so it checks the parser's offsets.
fn reference_gaze_report(timestamp: u64, values: [i32; 14]) -> Vec<u8> {
    let mut r = vec![0x10];
    r.extend(timestamp.to_le_bytes());
    for v in values {
        r.extend(v.to_le_bytes());
    }
    r
}

/// `declares_head`: DMF declares Head Position and Head Direction; GazeHid pads them.
fn check_reference_layout(descriptor: &[u8], declares_head: bool) {
    use dioptra_gaze::eye_hid::protocol::usage;
    let d = hid_descriptor::parse(descriptor).unwrap();
    let l = TrackerLayout::locate(&d).unwrap();
    let t = &l.tracking;
    assert_eq!((t.report_id, t.len), (0x10, 65));
    assert_eq!(
        (t.timestamp.field.bit_offset, t.timestamp.field.total_bits()),
        (0, 64)
    );
    // cm with exponent -4 is 1 µm per count; s with exponent -6 is 1 µs.
    assert_eq!((t.gaze_point[0].scale, t.timestamp.scale), (1.0, 1.0));
    let offsets = |g: &Option<[dioptra_gaze::eye_hid::protocol::Located; 3]>| {
        g.as_ref().map(|g| g.each_ref().map(|l| l.field.bit_offset))
    };
    assert_eq!(offsets(&t.left_eye), Some([128, 160, 192]));
    assert_eq!(offsets(&t.right_eye), Some([224, 256, 288]));
    if declares_head {
        assert_eq!(offsets(&t.head_position), Some([320, 352, 384]));
        // DMF's Head Direction keeps the cm unit of the positions: ignored, with a note.
        assert!(l.notes[0].contains("Head Direction"), "{:?}", l.notes);
    } else {
        assert_eq!(t.head_position, None);
    }
    assert_eq!(t.head_direction, None);
    assert_eq!(l.notes.len(), usize::from(declares_head), "{:?}", l.notes);
    assert_eq!(
        (l.capabilities.report_id, l.capabilities.len),
        (0x11, 1 + 1 + 20)
    );
    assert!(l.capabilities.has(usage::OPTIMUM_TRACKING_DISTANCE));
    let config = l.configuration.as_ref().unwrap();
    assert_eq!((config.report_id, config.len), (0x12, 1 + 18));
    assert_eq!((l.status.report_id, l.status.len), (0x13, 4));
    assert_eq!(l.control_report(ModeRequest(3)), vec![0x14, 3]);

    let r = reference_gaze_report(
        123_456_789,
        [
            150_000, 90_000, // gaze point, µm from the top-left corner
            118_000, 95_000, 600_000, // left eye
            182_000, 95_000, 601_000, // right eye
            150_000, 95_000, 600_500, // head position
            0, 1_500_000, 0, // head direction
        ],
    );
    let g = t.parse(&r).unwrap();
    assert_eq!(g.timestamp_us, 123_456_789);
    assert_eq!(g.gaze_point_um, Some([150_000.0, 90_000.0]));
    assert_eq!(g.left_eye_um, Some([118_000.0, 95_000.0, 600_000.0]));
    assert_eq!(g.right_eye_um, Some([182_000.0, 95_000.0, 601_000.0]));
    // Feature reports as the sources' structs lay them out.
    let mut caps = vec![0x11, 1];
    for v in [50_000u32, 65_000, 90_000, 527_000, 296_000] {
        caps.extend(v.to_le_bytes());
    }
    let c = l.parse_capabilities(&caps).unwrap();
    assert_eq!(c.tracker_quality, Some(1));
    assert_eq!(c.optimum_tracking_distance_um, Some(65_000.0));
    assert_eq!(c.max_screen_height_um, Some(296_000.0));
    let mut conf = vec![0x12, 0x4d, 0x53, 1, 0, 7, 0, 0, 0, 0x22, 0x07];
    conf.extend(527_000u32.to_le_bytes());
    conf.extend(296_000u32.to_le_bytes());
    let conf = l.parse_configuration(&conf).unwrap().unwrap();
    assert_eq!(conf.calibrated_screen_width_um, Some(527_000.0));
    let st = l.parse_status(&[0x13, 1, 100, 0]).unwrap();
    assert_eq!(
        (st.config_status, st.sampling_frequency_hz),
        (ConfigStatus::Ready, Some(100.0))
    );
}

#[test]
fn microsoft_gazehid_reference_descriptor_is_located_and_read() {
    check_reference_layout(GAZEHID, false);
}

#[test]
fn microsoft_dmf_reference_descriptor_is_located_and_read() {
    check_reference_layout(DMF, true);
}

/// The report collections' usages are a hint, not a requirement: the same descriptor with
/// every usage before a Logical collection removed still locates.
#[test]
fn usage_less_logical_collections_are_located_by_usage() {
    let mut d = Vec::new();
    let mut i = 0;
    while i < GAZEHID.len() {
        if GAZEHID[i..].starts_with(&[0x09]) && GAZEHID.get(i + 2..i + 4) == Some(&[0xa1, 0x02]) {
            i += 2; // drop "Usage (Tracking Data | Capabilities | ...)"
            continue;
        }
        d.push(GAZEHID[i]);
        i += 1;
    }
    assert_eq!(d.len(), GAZEHID.len() - 2 * 6);
    let parsed = hid_descriptor::parse(&d).unwrap();
    let l = TrackerLayout::locate(&parsed).unwrap();
    assert_eq!(
        (
            l.tracking.report_id,
            l.capabilities.report_id,
            l.status.report_id,
            l.control.report_id
        ),
        (0x10, 0x11, 0x13, 0x14)
    );
    assert!(l.tracking.left_eye.is_some());
}

#[test]
fn every_missing_requirement_is_named() {
    // Only the Tracking Data collection of the GazeHid descriptor: no feature reports.
    let end = GAZEHID
        .windows(4)
        .position(|w| w == [0x09, 0x11, 0xa1, 0x02])
        .unwrap();
    let mut d = GAZEHID[..end].to_vec();
    d.push(0xc0);
    let errors = TrackerLayout::locate_all(&hid_descriptor::parse(&d).unwrap()).unwrap_err();
    let text: Vec<String> = errors.iter().map(ToString::to_string).collect();
    assert_eq!(errors.len(), 3, "{text:?}");
    for what in ["Capabilities", "Configuration Status", "Mode Request"] {
        assert!(text.iter().any(|t| t.contains(what)), "{text:?}");
    }
}

/// The simulator's second layout (16-bit fields in 0.1 mm, report ids 1-5) drives the same
/// gaze as the reference layout.
#[tokio::test(start_paused = true)]
async fn the_compact_simulated_layout_streams_the_same_gaze() {
    let mut trackers = Vec::new();
    for layout in [SimLayout::Reference, SimLayout::Compact] {
        let (t, sim) = connect(HidTrackerSetup {
            layout,
            ..HidTrackerSetup::default()
        })
        .await;
        let t = t.unwrap();
        assert_eq!(t.layout().tracking.report_id, layout.report_ids()[0]);
        trackers.push((t, sim));
    }
    assert_eq!(trackers[1].0.layout().tracking.len, 1 + 8 + 14 * 2);
    for _ in 0..50 {
        let a = trackers[0].0.next_tracking().await.unwrap();
        let b = trackers[1].0.next_tracking().await.unwrap();
        assert_eq!(a.data.timestamp_us, b.data.timestamp_us);
        let (ga, gb) = (a.data.gaze_point_um.unwrap(), b.data.gaze_point_um.unwrap());
        // 0.1 mm steps against 1 µm steps.
        assert!((ga[0] - gb[0]).abs() <= 50.0 && (ga[1] - gb[1]).abs() <= 50.0);
        let (ha, hb) = (
            a.data.head_direction_deg.unwrap(),
            b.data.head_direction_deg.unwrap(),
        );
        assert!((ha[1] - 1.5).abs() < 1e-9 && (hb[1] - 1.5).abs() < 1e-9);
    }
}
