//! C4 accuracy on simulator test seeds, beside `linear` and `optimized` blending:
//! `cargo run --release -p dioptra-net --example eval_c4 -- WEIGHTS [SCENES] [SIZE] [SAMPLES] [ITERATIONS]`
//! Each test scene is rendered (pinhole colour 8x8 supersampled, thin-lens ground truth at the
//! net's training foci); each method's layers go through the renderer's retinal model at
//! those foci and are scored against the ground truth (retinal PSNR and SSIM, sRGB).
//! Optimized blending is fitted to that same ground-truth stack (its best case).

use dioptra_core::{Diopters, EyeModel, Millimeters, Rgbd};
use dioptra_net::{load_net, Task};
use dioptra_render::metrics::quality;
use dioptra_render::multifocal::{linear_blend, optimized_blend, OptimizeParams};
use dioptra_render::retina::retina_multifocal;
use dioptra_render::Layers;
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, Split};
use std::path::Path;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let usage = "usage: eval_c4 WEIGHTS [SCENES] [SIZE] [SAMPLES] [ITERATIONS]";
    let weights = args.get(1).ok_or(usage)?;
    let scenes: u64 = args.get(2).map_or(Ok(4), |s| s.parse())?;
    let size: usize = args.get(3).map_or(Ok(256), |s| s.parse())?;
    let samples: u32 = args.get(4).map_or(Ok(64), |s| s.parse())?;
    let iterations: usize = args.get(5).map_or(Ok(100), |s| s.parse())?;
    let net = load_net(Some(Path::new(weights)), "c4")?;
    let Task::C4 { planes, foci } = &net.arch().task else {
        return Err("not a C4 net".into());
    };
    let planes: Vec<Diopters> = planes.iter().copied().map(Diopters).collect();
    let foci: Vec<Diopters> = foci.iter().copied().map(Diopters).collect();
    // The eye the training data used (crates/net/src/train/data.rs DataSpec::default).
    let eye = EyeModel {
        pupil_diameter: Millimeters(4.0),
        fov_horizontal_deg: 20.0,
        ..EyeModel::default()
    }
    .with_width(size as u32)
    .validated()?;
    let cam = Camera::square(eye, size);
    let mut sums = [(0.0f64, 0.0f64); 3];
    let mut n = 0usize;
    for i in 0..scenes {
        let seed = Split::Test.seed(i);
        let scene = Scene::generate(seed);
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 8)?;
        let rgbd = Rgbd::new(color, depth)?;
        let truth = foci
            .iter()
            .map(|&q| render_thin_lens(&scene, &cam, q, samples))
            .collect::<Result<Vec<_>, _>>()?;
        let linear = linear_blend(&rgbd, &planes)?;
        let optimized = optimized_blend(
            &truth,
            &foci,
            &planes,
            &eye,
            Some(&linear),
            OptimizeParams {
                iterations,
                tolerance: 0.0,
            },
            |_| {},
        )?
        .0;
        let network = net.decompose(&rgbd)?;
        let mut line = format!("seed {seed}:");
        for (k, (name, layers)) in [
            ("network", &network),
            ("linear", &linear),
            ("optimized", &optimized),
        ]
        .into_iter()
        .enumerate()
        {
            let (p, s) = score(layers, &truth, &foci, &eye)?;
            sums[k].0 += p;
            sums[k].1 += s;
            line += &format!(" {name} {p:.2} dB {s:.4} |");
        }
        n += 1;
        println!("{}", line.trim_end_matches(" |"));
    }
    let k = n.max(1) as f64;
    println!(
        "mean retinal quality over {n} scenes x {} foci at {size}x{size}: network {:.2} dB SSIM {:.4}; linear {:.2} dB SSIM {:.4}; optimized ({iterations} it.) {:.2} dB SSIM {:.4}",
        foci.len(),
        sums[0].0 / k,
        sums[0].1 / k,
        sums[1].0 / k,
        sums[1].1 / k,
        sums[2].0 / k,
        sums[2].1 / k
    );
    Ok(())
}

/// Mean retinal PSNR and SSIM of `layers` over `foci`.
fn score(
    layers: &Layers,
    truth: &[dioptra_core::RgbImage],
    foci: &[Diopters],
    eye: &EyeModel,
) -> Result<(f64, f64), Box<dyn std::error::Error>> {
    let seen = retina_multifocal(layers, foci, eye)?;
    let (mut p, mut s) = (0.0, 0.0);
    for (img, gt) in seen.iter().zip(truth) {
        let q = quality(img, gt, None)?;
        p += q.psnr;
        s += q.ssim;
    }
    let k = foci.len().max(1) as f64;
    Ok((p / k, s / k))
}
