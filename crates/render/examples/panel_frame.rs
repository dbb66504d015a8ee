//! Renders a sim test scene at a panel's size with one defocus method, timing each frame: for
//! profiling (`perf record`) and quick looks; the figures to report come from the criterion
//! bench (`benches/panel.rs`).
//!
//!   cargo run --release -p dioptra-render --example panel_frame -- \
//!       [pyramid|foveated|gather|hybrid[,...]] [width] [height] [fov_deg] [focus_D] [frames]
//!
//! Prints per method the median wall time and the median CPU time (all threads) per frame;
//! `hybrid` is the gaze-contingent multifocal decomposition onto the default planes (its
//! defaults, gaze at the centre), with its stages' wall times from the last frame. With
//! `PANEL_TRUTH_SPP=N` the thin-lens truth is ray traced at N samples per pixel and each
//! defocus method's PSNR against it is printed in the fovea (a disk of 5 degrees radius
//! around the gaze, as `foveated`'s default full-resolution radius) and over the whole image.
//! Each method's line ends with a checksum of its last image's bits (FNV-1a over the planes),
//! so that a change meant to keep outputs identical can be checked at a panel's size.

use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::foveated::{foveated, Foveation};
use dioptra_render::gather::gather;
use dioptra_render::hybrid::{hybrid_blend, HybridParams};
use dioptra_render::metrics::{disk_mask, psnr};
use dioptra_render::multifocal::DEFAULT_PLANES;
use dioptra_render::pyramid::pyramid;
use dioptra_render::timing::process_cpu_ms;
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, Split};
use std::time::Instant;

fn main() {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let method = a.first().map_or("pyramid", |s| s.as_str());
    let num = |i: usize, d: f32| a.get(i).map_or(d, |s| s.parse().expect("a number"));
    let (w, h) = (num(1, 960.0) as usize, num(2, 1080.0) as usize);
    let eye = EyeModel {
        fov_horizontal_deg: num(3, 20.0),
        ..EyeModel::default()
    };
    let q = Diopters(num(4, 1.0));
    let frames = num(5, 5.0) as usize;
    dioptra_render::alloc::keep_freed_memory();
    let cam = Camera::new(eye, w, h);
    let scene = Scene::generate(Split::Test.seed(0));
    let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], 1).expect("scene");
    let input = Rgbd::new(c, d).expect("rgbd");
    let gaze = [0.5 * w as f32, 0.5 * h as f32];
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let truth = std::env::var("PANEL_TRUTH_SPP").ok().map(|spp| {
        let spp = spp.parse().expect("PANEL_TRUTH_SPP: a number");
        render_thin_lens(&scene, &cam, q, spp).expect("truth")
    });
    let px_per_deg = 1.0f32.to_radians().tan() / eye.with_width(w as u32).pixel_pitch_tan();
    let fovea = disk_mask(w, h, gaze, 5.0 * px_per_deg);
    for method in method.split(',') {
        let (mut wall, mut cpu) = (Vec::new(), Vec::new());
        let mut stages = None;
        let mut last = None;
        let mut checksum = 0u64;
        for _ in 0..frames {
            let (t, c) = (Instant::now(), process_cpu_ms());
            let img = match method {
                "hybrid" => {
                    let (layers, report) =
                        hybrid_blend(&input, &planes, &eye, Some(gaze), &HybridParams::default())
                            .expect("hybrid");
                    stages = Some(report.stages_ms);
                    layers.images.into_iter().next().expect("a layer")
                }
                "gather" => gather(&input, q, &eye).expect("gather"),
                "foveated" => {
                    foveated(&input, q, &eye, &Foveation::at(gaze))
                        .expect("foveated")
                        .image
                }
                _ => pyramid(&input, q, &eye).expect("pyramid"),
            };
            if let (Some(t), true) = (&truth, method != "hybrid") {
                last = Some((
                    psnr(&img, t, Some(&fovea)).expect("psnr"),
                    psnr(&img, t, None).expect("psnr"),
                ));
            }
            checksum = bits_checksum(&img);
            std::hint::black_box(img);
            wall.push(t.elapsed().as_secs_f64() * 1e3);
            cpu.push(process_cpu_ms() - c);
        }
        let median = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        println!(
            "{method} {w}x{h} {} deg at {} D: median of {frames}: {:.1} ms wall, {:.1} ms CPU (all threads), checksum {checksum:016x}",
            eye.fov_horizontal_deg,
            q.0,
            median(&mut wall),
            median(&mut cpu)
        );
        if let Some((fov, all)) = last {
            println!("  against the thin-lens truth: fovea {fov:.2} dB, whole image {all:.2} dB");
        }
        if let Some(s) = stages {
            println!("  hybrid stages (last frame, wall ms): {s:?}");
        }
    }
}

/// FNV-1a over the bits of the image's planes, red then green then blue.
fn bits_checksum(img: &dioptra_core::RgbImage) -> u64 {
    img.channels
        .iter()
        .flat_map(|p| p.data())
        .fold(0xcbf2_9ce4_8422_2325, |h, v| {
            (h ^ u64::from(v.to_bits())).wrapping_mul(0x100_0000_01b3)
        })
}
