//! The fuzz target's seed inputs (`fuzz/seeds/hid_reports`, committed) are real, parseable reports,
//! so fuzzing starts from inside the parsers rather than at their first length check.

use dioptra_gaze::dioptra_tracker::protocol::decode_sample_report;
use dioptra_gaze::eye_hid::protocol::{ConfigStatus, TrackerLayout};
use dioptra_gaze::hid_descriptor;

fn seed(name: &str) -> Vec<u8> {
    let path = format!(
        "{}/fuzz/seeds/hid_reports/{name}",
        env!("CARGO_MANIFEST_DIR")
    );
    std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// The fuzz input format: `[descriptor length u16 LE][descriptor][report]`.
fn split(data: &[u8]) -> (&[u8], &[u8]) {
    let len = usize::from(u16::from_le_bytes([data[0], data[1]]));
    data[2..].split_at(len)
}

#[test]
fn seeds_parse() {
    let s = decode_sample_report(&seed("dioptra_sample")).unwrap();
    assert_eq!(s.device_time_us, 1_000_000);
    assert_eq!(s.right.origin_mm, [32.0, 0.0, 0.0]);

    let data = seed("page12_tracking");
    let (descriptor, report) = split(&data);
    assert_eq!(descriptor, dioptra_sim::gaze::hid_tracker::DESCRIPTOR);
    let layout = TrackerLayout::locate(&hid_descriptor::parse(descriptor).unwrap()).unwrap();
    let t = layout.tracking.parse(report).unwrap();
    assert_eq!(t.timestamp_us, 1_000_000);
    assert_eq!(t.left_eye_um, Some([268_000.0, 170_000.0, 600_000.0]));

    let data = seed("page12_status");
    let (_, report) = split(&data);
    let st = layout.parse_status(report).unwrap();
    assert_eq!(
        (st.config_status, st.sampling_frequency_hz),
        (ConfigStatus::Ready, Some(500.0))
    );

    let data = seed("page12_compact_tracking");
    let (descriptor, report) = split(&data);
    assert_eq!(
        descriptor,
        dioptra_sim::gaze::hid_tracker::COMPACT_DESCRIPTOR
    );
    let layout = TrackerLayout::locate(&hid_descriptor::parse(descriptor).unwrap()).unwrap();
    let t = layout.tracking.parse(report).unwrap();
    assert_eq!(t.left_eye_um, Some([268_000.0, 170_000.0, 600_000.0]));

    // Microsoft's reference descriptors (tests/data) with reports built from their structs.
    for (name, descriptor) in [
        ("gazehid_tracking", "gazehid_report_descriptor.bin"),
        ("dmf_tracking", "dmf_virtual_eye_gaze_report_descriptor.bin"),
    ] {
        let data = seed(name);
        let (d, report) = split(&data);
        assert_eq!(d, reference(descriptor), "{name}");
        let layout = TrackerLayout::locate(&hid_descriptor::parse(d).unwrap()).unwrap();
        let t = layout.tracking.parse(report).unwrap();
        assert_eq!(t.timestamp_us, 123_456_789, "{name}");
        assert_eq!(t.gaze_point_um, Some([300_000.0, 170_000.0]), "{name}");
    }
    let data = seed("dmf_capabilities");
    let (d, report) = split(&data);
    let layout = TrackerLayout::locate(&hid_descriptor::parse(d).unwrap()).unwrap();
    let c = layout.parse_capabilities(report).unwrap();
    assert_eq!(c.optimum_tracking_distance_um, Some(65_000.0));
}

fn reference(name: &str) -> Vec<u8> {
    let path = format!("{}/tests/data/{name}", env!("CARGO_MANIFEST_DIR"));
    std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}
