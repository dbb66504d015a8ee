//! Encode + frame + decode of the two hottest messages. Target: <= 1 us median each.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_protocol::{
    decode_frame, encode_frame, BinocularSample, EyeSample, Message, MAX_FRAME_LEN,
};

fn round_trip(c: &mut Criterion, name: &str, message: &Message) {
    let mut wire = [0u8; MAX_FRAME_LEN];
    c.bench_function(name, |b| {
        b.iter(|| {
            let len = encode_frame(black_box(513), black_box(message), &mut wire)
                .expect("the message fits a frame");
            decode_frame(black_box(&wire[..len])).expect("the frame decodes")
        })
    });
}

fn codec(c: &mut Criterion) {
    round_trip(
        c,
        "set_focal_power/encode_decode",
        &Message::SetFocalPower {
            diopters: 1.25,
            apply_at_us: 123_460_000,
        },
    );
    let eye = EyeSample {
        origin_mm: [-31.5, 0.25, 12.0],
        direction: [0.0, 0.6, 0.8],
        pupil_mm: 4.0,
        valid: true,
    };
    round_trip(
        c,
        "binocular_sample/encode_decode",
        &Message::BinocularSample(BinocularSample {
            device_time_us: 124_008_333,
            left: eye,
            right: EyeSample {
                origin_mm: [31.5, 0.25, 12.0],
                ..eye
            },
        }),
    );
}

criterion_group!(benches, codec);
criterion_main!(benches);
