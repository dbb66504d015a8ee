//! Arbitrary bytes through the HID descriptor parser, the page 0x12 layout finder and
//! report parsers, and the dioptra tracker's report decoder. Nothing may panic; every field
//! a parsed descriptor declares must read (or refuse) any report; `locate` and `locate_all`
//! must agree; every located field must read (or refuse) any report; a located layout's own
//! Control report must parse as its own.
//!
//! Input: `[descriptor length u16 LE][descriptor][report]`. Seeds: `corpus/hid_reports`.
#![no_main]

use dioptra_gaze::dioptra_tracker::protocol::{decode_sample_report, eye_ray, StreamControl};
use dioptra_gaze::eye_hid::protocol::{ModeRequest, TrackerLayout};
use dioptra_gaze::hid_descriptor;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(s) = decode_sample_report(data) {
        for e in [&s.left, &s.right] {
            let r = eye_ray(e);
            if r.valid {
                let n: f32 = r.direction.iter().map(|v| v * v).sum();
                assert!((n - 1.0).abs() < 1e-3, "a valid ray must be unit length");
            }
        }
    }
    let _ = StreamControl::decode(data);

    let Some((len, rest)) = data.split_first_chunk::<2>() else {
        return;
    };
    let len = usize::from(u16::from_le_bytes(*len)).min(rest.len());
    let (descriptor, report) = rest.split_at(len);
    let Ok(d) = hid_descriptor::parse(descriptor) else {
        return;
    };
    for f in &d.fields {
        let _ = f.read(report);
    }
    let all = TrackerLayout::locate_all(&d);
    if let Err(errors) = &all {
        assert!(!errors.is_empty(), "a failed layout names what it lacks");
    }
    let Ok(layout) = TrackerLayout::locate(&d) else {
        assert!(all.is_err());
        return;
    };
    assert!(all.is_ok());
    for l in layout.fields() {
        let _ = l.get(report);
    }
    let _ = layout.tracking.parse(report);
    let _ = layout.parse_capabilities(report);
    let _ = layout.parse_configuration(report);
    let _ = layout.parse_status(report);
    let control = layout.control_report(ModeRequest(report.first().copied().unwrap_or(3) & 7));
    assert_eq!(control.first(), Some(&layout.control.report_id));
});
