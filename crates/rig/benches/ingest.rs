//! Ingest of one streamed RGB-D frame (`[content] source = "stream"`): the daemon's side of
//! `PUT /frame` (check, sRGB to linear, depth to diopters; the ring adds one copy of the slot)
//! at 512 x 512 and 1920 x 1080, for 8-bit colour with metres and with a reversed-Z depth
//! buffer, the frame's memory reused as the daemon reuses it.
//! `cargo bench -p dioptra-rig --bench ingest`

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_core::Timestamp;
use dioptra_rig::content::stream::{ColorFormat, DepthKind, FrameDesc, StreamFrames};

fn ingest(c: &mut Criterion) {
    for (w, h) in [(512usize, 512usize), (1920, 1080)] {
        for (kind, v) in [
            (DepthKind::Metres, 1.5f32),
            (DepthKind::VulkanReversed, 0.05),
        ] {
            let s = StreamFrames::open(w, h, None).unwrap();
            let color: Vec<u8> = (0..w * h * 3).map(|i| (i % 251) as u8).collect();
            let depth: Vec<u8> = (0..w * h).flat_map(|_| v.to_le_bytes()).collect();
            let mut desc = FrameDesc {
                width: w,
                height: h,
                color: ColorFormat::Rgb8,
                depth: kind,
                near: Some(0.1),
                far: Some(f32::INFINITY),
                seq: None,
                app_time_ns: None,
            };
            c.bench_function(&format!("ingest {w}x{h} rgb8 {kind:?}"), |b| {
                b.iter(|| {
                    desc.seq = None;
                    s.submit(&desc, &color, &depth, Timestamp(0)).unwrap();
                    // The display takes it up and, showing the next, hands it back, as the
                    // daemon's renderer does.
                    let frame = s.take_new().unwrap().0;
                    let shown = std::hint::black_box(frame.depth.data()[0]);
                    s.recycle(frame);
                    shown
                })
            });
        }
    }
}

criterion_group!(benches, ingest);
criterion_main!(benches);
