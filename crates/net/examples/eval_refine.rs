//! C1R accuracy and time on simulator test seeds, beside the classical render it refines:
//! `cargo run --release -p dioptra-net --example eval_refine -- WEIGHTS [SCENES] [SIZE] [SAMPLES] [train]`
//! (`train`: training seeds 0.. instead, to tell fitting from generalising)
//! Each test scene is rendered (pinhole colour 4x4 supersampled, as `dioptra eval`; thin-lens
//! ground truth at SAMPLES rays per pixel) and scored at `dioptra eval`'s foci. Prints per
//! focus the classical and refined PSNR (sRGB), the fraction of tiles the net ran on and the
//! times, then the means.

use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_net::refine::classical_defocus;
use dioptra_net::{load_net, Task};
use dioptra_render::metrics::psnr;
use dioptra_render::Cpu;
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, Split};
use std::path::Path;
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let weights = args
        .get(1)
        .ok_or("usage: eval_refine WEIGHTS [SCENES] [SIZE] [SAMPLES]")?;
    let scenes: u64 = args.get(2).map_or(Ok(2), |s| s.parse())?;
    let size: usize = args.get(3).map_or(Ok(256), |s| s.parse())?;
    let samples: u32 = args.get(4).map_or(Ok(64), |s| s.parse())?;
    let split = if args.get(5).map(String::as_str) == Some("train") {
        Split::Train
    } else {
        Split::Test
    };
    let net = load_net(Some(Path::new(weights)), "c1r")?;
    let Task::C1r { classical } = net.arch().task else {
        return Err("not a c1r net".into());
    };
    let eye = EyeModel::default().with_width(size as u32);
    let cam = Camera::square(eye, size);
    let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
    let (mut sum_c, mut sum_r, mut sum_f, mut n) = (0.0, 0.0, 0.0, 0.0);
    let (mut t_c, mut t_r) = (0.0, 0.0);
    let mut worst: f64 = f64::INFINITY;
    for i in 0..scenes {
        let seed = split.seed(i);
        let scene = Scene::generate(seed);
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 4)?;
        let rgbd = Rgbd::new(color, depth)?;
        for q in [0.1f32, 0.5, 1.0, 1.5, 2.2, 3.0, 4.0].map(Diopters) {
            let truth = render_thin_lens(&scene, &cam, q, samples)?;
            let t = Instant::now();
            let base = classical_defocus(&Cpu, classical, &rgbd, q, &eye)?;
            let tc = ms(t);
            let t = Instant::now();
            let r = net.refine_defocus(&rgbd, &base, q, &eye)?;
            let tr = ms(t);
            let (pc, pr) = (psnr(&base, &truth, None)?, psnr(&r.image, &truth, None)?);
            println!(
                "seed {seed} focus {:.1} D: {} {pc:.2} dB -> refined {pr:.2} dB ({:+.2}), tiles {:.0}%, {tc:.1} + {tr:.1} ms",
                q.0,
                classical.label(),
                pr - pc,
                100.0 * r.tiles.fraction()
            );
            sum_c += pc;
            sum_r += pr;
            sum_f += r.tiles.fraction();
            worst = worst.min(pr - pc);
            t_c += tc;
            t_r += tr;
            n += 1.0;
        }
    }
    println!(
        "mean over {n} images at {size}x{size}: {} {:.2} dB, refined {:.2} dB ({:+.2}, worst {worst:+.2}); tiles run {:.0}%; time {:.1} ms classical + {:.1} ms refinement",
        classical.label(),
        sum_c / n,
        sum_r / n,
        (sum_r - sum_c) / n,
        100.0 * sum_f / n,
        t_c / n,
        t_r / n
    );
    Ok(())
}
