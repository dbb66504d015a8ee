//! Accuracy of every method against the thin-lens ground truth on sim test scenes.
//!
//! cargo run --release -p dioptra-render --example accuracy -- [size] [seeds] [slices] [samples]
//! (defaults 256 2 40 256). Prints the ground truth's own error (N vs 4N samples), then per
//! scene and in the mean: gather and lightfield (36 views) over `slices` foci 0.1..4.0 D,
//! whole image and near occlusion boundaries; linear and optimized multifocal retinal
//! images over DeepFocus's 22 foci 0.1..2.2 D.

use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};
use dioptra_render::metrics::{depth_edge_mask, quality};
use dioptra_render::multifocal::{default_focal_samples, linspace, DEFAULT_PLANES};
use dioptra_render::{backend, DefocusMethod, LightFieldParams, OptimizeParams};
use dioptra_sim::scene::{
    render_pinhole, render_thin_lens, render_thin_lens_scrambled, render_thin_lens_stack, Camera,
    Scene, Split,
};
use std::time::Instant;

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let size = *args.first().unwrap_or(&256);
    let seeds = *args.get(1).unwrap_or(&2);
    let slices = *args.get(2).unwrap_or(&40);
    let samples = *args.get(3).unwrap_or(&256) as u32;
    let eye = EyeModel::default();
    let cam = Camera::square(eye, size);
    let cpu = backend("cpu")?;
    println!("size {size}, {seeds} test scenes, {slices} foci 0.1-4.0 D, {samples} ground-truth samples/px");

    // The reference's own error: N against 4N samples, a near and a far focus.
    let scene = Scene::generate(Split::Test.seed(0));
    for q in [0.1f32, 2.0] {
        // Independent scrambles, so shared samples do not hide the error.
        let a = render_thin_lens_scrambled(&scene, &cam, Diopters(q), samples, 1)?;
        let b = render_thin_lens(&scene, &cam, Diopters(q), 4 * samples)?;
        let qa = quality(&a, &b, None)?;
        println!(
            "ground truth self-error at {q} D: {samples} vs {} samples: {:.2} dB, SSIM {:.5}",
            4 * samples,
            qa.psnr,
            qa.ssim
        );
    }

    let foci = linspace(0.1, 4.0, slices);
    let mf_foci = default_focal_samples();
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let lf = DefocusMethod::LightField(LightFieldParams {
        views: 36,
        mip: true,
    });
    let (mut g_all, mut l_all, mut g_edge, mut l_edge, mut lin_all, mut opt_all) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    for s in 0..seeds {
        let seed = Split::Test.seed(s as u64);
        let scene = Scene::generate(seed);
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 8)?;
        let input = Rgbd::new(color, depth)?;
        let mask = depth_edge_mask(
            &input.depth,
            0.3,
            (eye.with_width(size as u32)
                .coc_px(Diopters(0.0), Diopters(1.0))
                * 0.5)
                .ceil() as usize,
        );
        let t0 = Instant::now();
        let gt = render_thin_lens_stack(&scene, &cam, &foci, samples, |_| {})?;
        let t_gt = t0.elapsed();
        let gathered = cpu.defocus(&input, &foci, &eye, DefocusMethod::Gather, &|_| {})?;
        let lightf = cpu.defocus(&input, &foci, &eye, lf, &|_| {})?;
        let score = |imgs: &[RgbImage],
                     m: Option<&Plane>|
         -> Result<(f64, f64), Box<dyn std::error::Error>> {
            let q: Vec<_> = imgs
                .iter()
                .zip(&gt)
                .map(|(a, b)| quality(a, b, m))
                .collect::<Result<_, _>>()?;
            Ok((
                mean(&q.iter().map(|x| x.psnr).collect::<Vec<_>>()),
                mean(&q.iter().map(|x| x.ssim).collect::<Vec<_>>()),
            ))
        };
        let (g, l) = (score(&gathered, None)?, score(&lightf, None)?);
        let (ge, le) = (score(&gathered, Some(&mask))?, score(&lightf, Some(&mask))?);
        println!(
            "seed {seed}: gather {:.2} dB / {:.4}, lightfield36 {:.2} dB / {:.4}; near occlusion boundaries gather {:.2} dB, lightfield {:.2} dB (ground truth {:.1} s)",
            g.0, g.1, l.0, l.1, ge.0, le.0, t_gt.as_secs_f64()
        );
        g_all.push(g.0);
        l_all.push(l.0);
        g_edge.push(ge.0);
        l_edge.push(le.0);

        let mf_gt = render_thin_lens_stack(&scene, &cam, &mf_foci, samples, |_| {})?;
        let linear = cpu.linear_blend(&input, &planes)?;
        let t0 = Instant::now();
        let params = OptimizeParams {
            iterations: 100,
            tolerance: 0.0,
        };
        let (opt, rep) = cpu.optimized_blend(
            &mf_gt,
            &mf_foci,
            &planes,
            &eye,
            Some(&linear),
            params,
            &|_| {},
        )?;
        let t_opt = t0.elapsed();
        let mscore = |imgs: Vec<RgbImage>| -> Result<(f64, f64), Box<dyn std::error::Error>> {
            let q: Vec<_> = imgs
                .iter()
                .zip(&mf_gt)
                .map(|(a, b)| quality(a, b, None))
                .collect::<Result<_, _>>()?;
            Ok((
                mean(&q.iter().map(|x| x.psnr).collect::<Vec<_>>()),
                mean(&q.iter().map(|x| x.ssim).collect::<Vec<_>>()),
            ))
        };
        let lin = mscore(cpu.retina_multifocal(&linear, &mf_foci, &eye)?)?;
        let op = mscore(cpu.retina_multifocal(&opt, &mf_foci, &eye)?)?;
        println!(
            "seed {seed}: multifocal linear {:.2} dB / {:.4}, optimized {:.2} dB / {:.4} ({} iterations, rms {:.5} -> {:.5}, {:.1} s)",
            lin.0,
            lin.1,
            op.0,
            op.1,
            rep.iterations,
            rep.rms.first().map_or(0.0, |r| r.1),
            rep.rms.last().map_or(0.0, |r| r.1),
            t_opt.as_secs_f64()
        );
        lin_all.push(lin.0);
        opt_all.push(op.0);
    }
    println!(
        "MEAN: gather {:.2} dB, lightfield36 {:.2} dB; occlusion boundaries gather {:.2} dB, lightfield36 {:.2} dB; multifocal linear {:.2} dB, optimized {:.2} dB",
        mean(&g_all),
        mean(&l_all),
        mean(&g_edge),
        mean(&l_edge),
        mean(&lin_all),
        mean(&opt_all)
    );
    Ok(())
}
