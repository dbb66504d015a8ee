//! The pre-warp and the transfer pass on the GPU against their CPU twins. Without an adapter
//! each test prints "skipped: no GPU adapter" and returns; with DIOPTRA_REQUIRE_GPU=1 (set by
//! .ci/run) it fails instead.

use dioptra_core::distortion::{ChannelModel, Coefficients, EyepieceModel, Intrinsics};
use dioptra_core::transfer::Transfer;
use dioptra_core::RgbImage;
use dioptra_render::gpu::GpuContext;
use dioptra_render::transfer::gpu::{encode_on_gpu, upload_image, GpuEncodeLut};
use dioptra_render::transfer::EncodeLut;
use dioptra_render::warp::gpu::{warp_to_image, GpuWarpMesh, WarpPipeline};
use dioptra_render::warp::{warp_cpu, WarpDraw, WarpMesh};
use dioptra_render::{Gpu, GpuError};
use std::sync::Arc;

fn gpu() -> Option<Arc<GpuContext>> {
    match Gpu::new(None) {
        Ok(g) => Some(g.context().clone()),
        Err(GpuError::NoAdapter) if std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1") => {
            eprintln!("skipped: no GPU adapter");
            None
        }
        Err(e) => panic!("GPU required (DIOPTRA_REQUIRE_GPU=1) or failed to open: {e}"),
    }
}

/// xorshift64*: fixed-seed inputs.
fn random_image(w: usize, h: usize, seed: u64, lo: f32, hi: f32) -> RgbImage {
    let mut s = seed;
    let d: Vec<f32> = (0..w * h * 3)
        .map(|_| {
            s ^= s >> 12;
            s ^= s << 25;
            s ^= s >> 27;
            let u = ((s.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 40) as f32) / (1u64 << 24) as f32;
            lo + (hi - lo) * u
        })
        .collect();
    RgbImage::from_interleaved(w, h, &d).unwrap()
}

/// An eyepiece for a 240 x 136 panel: pincushion, tangential terms, lateral colour, and a
/// strong rational term on blue, so that the panel's corners are beyond blue's fold (black).
fn eyepiece() -> EyepieceModel {
    let cam = Intrinsics {
        fx: 110.0,
        fy: 112.0,
        cx: 119.5,
        cy: 67.0,
    };
    let k = Coefficients {
        k1: -0.2,
        k2: 0.04,
        p1: 0.002,
        p2: -0.001,
        ..Default::default()
    };
    let ch = |s: f64, k: Coefficients| ChannelModel {
        camera: Intrinsics {
            fx: cam.fx * s,
            fy: cam.fy * s,
            ..cam
        },
        coefficients: k,
    };
    EyepieceModel {
        render: cam,
        channels: [
            ch(1.012, k),
            ch(1.0, k),
            ch(0.99, Coefficients { k2: -0.05, ..k }),
        ],
    }
    .checked("optics.distortion")
    .unwrap()
}

fn max_diff(a: &RgbImage, b: &RgbImage) -> f32 {
    (0..3)
        .flat_map(|c| {
            a.channels[c]
                .data()
                .iter()
                .zip(b.channels[c].data())
                .map(|(x, y)| (x - y).abs())
        })
        .fold(0.0, f32::max)
}

#[test]
fn the_warp_on_the_gpu_matches_its_cpu_twin() {
    let Some(ctx) = gpu() else { return };
    let model = eyepiece();
    // The source rendered at a different size from the panel.
    let mesh = WarpMesh::new(&model, [240, 136], [200, 120], 4).unwrap();
    assert!(
        mesh.unreachable() > 0,
        "the corners must test the black triangles"
    );
    let source = random_image(200, 120, 7, 0.0, 1.0);
    let pipeline = WarpPipeline::new(&ctx, wgpu::TextureFormat::Rgba32Float);
    let gmesh = GpuWarpMesh::new(&ctx, &mesh);
    let gsource = upload_image(&ctx, &source).unwrap();
    let lut = EncodeLut::new(&Transfer::gamma(2.4, 0.002).unwrap());
    let glut = GpuEncodeLut::new(&ctx, &lut).unwrap();
    for (scale, encode) in [(1.0f32, false), (1.04, false), (0.97, true)] {
        let cpu = warp_cpu(
            &source,
            &mesh,
            &WarpDraw {
                scale,
                encode: encode.then_some(&lut),
            },
        )
        .unwrap();
        let gpu =
            warp_to_image(&pipeline, &gsource, &gmesh, scale, encode.then_some(&glut)).unwrap();
        let d = max_diff(&cpu, &gpu);
        eprintln!("scale {scale}, encoded {encode}: GPU - CPU {d:e}");
        // The rasteriser interpolates in f32 as the CPU does, in another order (lavapipe:
        // 6e-5 at most).
        assert!(d < 5e-4, "scale {scale}, encoded {encode}: {d}");
        // Black beyond the fold on both, and light inside.
        assert_eq!(gpu.channels[2].get(0, 0), Some(0.0));
        // The panel reaches farther out than the source (and blue's fold): about half lit.
        let lit = gpu.channels[1].data().iter().filter(|&&v| v > 0.0).count();
        assert!(lit > 15_000, "{lit}");
    }
}

#[test]
fn the_transfer_pass_on_the_gpu_matches_its_cpu_twin() {
    let Some(ctx) = gpu() else { return };
    // Values below 0 and above 1 too (clamped by both).
    let image = random_image(97, 61, 3, -0.1, 1.2);
    let g = upload_image(&ctx, &image).unwrap();
    let table: Vec<(f64, f64)> = (0..=10)
        .map(|k| {
            let c = k as f64 / 10.0;
            (c, 0.2 + 90.0 * c.powf(2.3) + 3.0 * c)
        })
        .collect();
    for t in [
        Transfer::Srgb,
        Transfer::gamma(2.4, 0.001).unwrap(),
        Transfer::Table(dioptra_core::transfer::TransferTable::new("t", &table).unwrap()),
    ] {
        let lut = EncodeLut::new(&t);
        let cpu = lut.encode_image(&image);
        let gpu = encode_on_gpu(&g, &GpuEncodeLut::new(&ctx, &lut).unwrap())
            .unwrap()
            .read()
            .unwrap();
        let d = max_diff(&cpu, &gpu);
        assert!(d < 1e-6, "{}: {d}", t.describe());
    }
}
