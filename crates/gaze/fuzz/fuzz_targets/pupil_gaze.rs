//! Arbitrary bytes through the Pupil Capture gaze decoder and Pupil Remote's reply parsers.
//! Nothing may panic; a decoded datum has a finite timestamp; every eye it yields makes a
//! ray that is either invalid or unit length.
//!
//! Input: `[topic selector][payload]`; the selector picks the binocular, a monocular or a
//! non-gaze topic.
#![no_main]

use dioptra_gaze::pupil::protocol::{decode_gaze, eye_ray, parse_port, parse_time};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = parse_port(text);
        if let Ok(t) = parse_time(text) {
            assert!(t.is_finite());
        }
    }
    let Some((selector, payload)) = data.split_first() else {
        return;
    };
    let topic = ["gaze.3d.01.", "gaze.3d.0.", "gaze.3d.1.", "pupil.0.3d"][usize::from(selector % 4)];
    let Ok(d) = decode_gaze(topic, payload) else {
        return;
    };
    assert!(d.timestamp_s.is_finite());
    for eye in [d.left.as_ref(), d.right.as_ref()] {
        let r = eye_ray(eye, true);
        if r.valid {
            let n: f32 = r.direction.iter().map(|v| v * v).sum();
            assert!((n - 1.0).abs() < 1e-3, "a valid ray must be unit length");
        }
    }
});
