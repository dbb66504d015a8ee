//! C1 accuracy on simulator test seeds, beside `gather`:
//! `cargo run --release -p dioptra-net --example eval_c1 -- WEIGHTS [SCENES] [SIZE] [SAMPLES]`
//! Each test scene is rendered (pinhole colour 8x8 supersampled, thin-lens ground truth) at
//! foci 0.1, 1.0, 2.0 and 4.0 D; PSNR and SSIM are the renderer's metrics (sRGB).

use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_net::load_net;
use dioptra_render::gather::gather;
use dioptra_render::metrics::quality;
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, Split};
use std::path::Path;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let weights = args
        .get(1)
        .ok_or("usage: eval_c1 WEIGHTS [SCENES] [SIZE] [SAMPLES]")?;
    let scenes: u64 = args.get(2).map_or(Ok(4), |s| s.parse())?;
    let size: usize = args.get(3).map_or(Ok(256), |s| s.parse())?;
    let samples: u32 = args.get(4).map_or(Ok(256), |s| s.parse())?;
    let net = load_net(Some(Path::new(weights)), "c1")?;
    let eye = EyeModel::default();
    let cam = Camera::square(eye, size);
    let (mut n, mut g) = (vec![], vec![]);
    for i in 0..scenes {
        let seed = Split::Test.seed(i);
        let scene = Scene::generate(seed);
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 8)?;
        let rgbd = Rgbd::new(color, depth)?;
        for q in [0.1f32, 1.0, 2.0, 4.0] {
            let gt = render_thin_lens(&scene, &cam, Diopters(q), samples)?;
            let qn = quality(&net.defocus(&rgbd, Diopters(q), &eye)?, &gt, None)?;
            let qg = quality(&gather(&rgbd, Diopters(q), &eye)?, &gt, None)?;
            println!(
                "seed {seed} focus {q:.1} D: network {:.2} dB {:.4} | gather {:.2} dB {:.4}",
                qn.psnr, qn.ssim, qg.psnr, qg.ssim
            );
            n.push((qn.psnr, qn.ssim));
            g.push((qg.psnr, qg.ssim));
        }
    }
    let mean = |v: &[(f64, f64)]| {
        let k = v.len().max(1) as f64;
        (
            v.iter().map(|x| x.0).sum::<f64>() / k,
            v.iter().map(|x| x.1).sum::<f64>() / k,
        )
    };
    let (a, b) = (mean(&n), mean(&g));
    println!(
        "mean over {} images at {size}x{size}: network {:.2} dB SSIM {:.4}; gather {:.2} dB SSIM {:.4}",
        n.len(),
        a.0,
        a.1,
        b.0,
        b.1
    );
    Ok(())
}
