//! The eyepiece pre-warp and the transfer pass at a rig's size (1920 x 1080 per eye): building
//! the mesh (once per eyepiece), the CPU twin (the headless sink's), and the GPU pass drawn into
//! a float texture and read back (the window draws into its surface instead, without the
//! readback). Without a GPU adapter the GPU rows are skipped, said on stderr.

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_core::transfer::Transfer;
use dioptra_core::RgbImage;
use dioptra_render::transfer::gpu::{encode_on_gpu, upload_image, GpuEncodeLut};
use dioptra_render::transfer::EncodeLut;
use dioptra_render::warp::gpu::{warp_to_image, GpuWarpMesh, WarpPipeline};
use dioptra_render::warp::{example_eyepiece, warp_cpu, WarpDraw, WarpMesh, DEFAULT_STEP_PX};
use dioptra_render::Gpu;
use std::hint::black_box;
use std::time::Duration;

const PANEL: [usize; 2] = [1920, 1080];

fn frame() -> RgbImage {
    let [w, h] = PANEL;
    let d: Vec<f32> = (0..3 * w * h)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0)
        .collect();
    RgbImage::from_interleaved(w, h, &d).expect("size")
}

fn benches(c: &mut Criterion) {
    let model = example_eyepiece();
    let source = frame();
    let lut = EncodeLut::new(&Transfer::gamma(2.4, 0.001).expect("valid"));
    let mut g = c.benchmark_group("warp_1080p");
    g.sample_size(10).measurement_time(Duration::from_secs(10));
    g.bench_function("mesh build (4 px step)", |b| {
        b.iter(|| black_box(WarpMesh::new(&model, PANEL, PANEL, DEFAULT_STEP_PX).unwrap()))
    });
    let mesh = WarpMesh::new(&model, PANEL, PANEL, DEFAULT_STEP_PX).unwrap();
    let draw = WarpDraw {
        scale: 1.02,
        encode: Some(&lut),
    };
    g.bench_function("CPU warp + encode", |b| {
        b.iter(|| black_box(warp_cpu(&source, &mesh, &draw).unwrap()))
    });
    g.bench_function("CPU encode", |b| {
        b.iter(|| black_box(lut.encode_image(&source)))
    });
    let gpu = match Gpu::new(None) {
        Ok(g) => g,
        Err(e) => {
            eprintln!("GPU rows skipped: no GPU adapter ({e})");
            return;
        }
    };
    let ctx = gpu.context().clone();
    eprintln!("adapter: {}", ctx.adapter().name);
    let pipeline = WarpPipeline::new(&ctx, wgpu::TextureFormat::Rgba32Float);
    let gmesh = GpuWarpMesh::new(&ctx, &mesh);
    let gsource = upload_image(&ctx, &source).unwrap();
    let glut = GpuEncodeLut::new(&ctx, &lut).unwrap();
    g.bench_function("GPU warp + encode, read back", |b| {
        b.iter(|| black_box(warp_to_image(&pipeline, &gsource, &gmesh, 1.02, Some(&glut)).unwrap()))
    });
    g.bench_function("GPU encode, in GPU memory", |b| {
        b.iter(|| black_box(encode_on_gpu(&gsource, &glut).unwrap()))
    });
    g.finish();
}

criterion_group!(warp, benches);
criterion_main!(warp);
