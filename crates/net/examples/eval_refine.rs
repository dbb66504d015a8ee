//! C1R or C4R accuracy and time on simulator test seeds, beside the classical result it refines:
//! `cargo run --release -p dioptra-net --example eval_refine -- WEIGHTS [SCENES] [SIZE] [SAMPLES] [train|occluders|gate]`
//! (`train`: training seeds 0.. instead, to tell fitting from generalising; `occluders`: C1R
//! on the occluder family, `Scene::generate_occluders`, seeds 5000.. of the training range,
//! which no shipped net trained on, each focused at its wall and at one other focus; `gate`:
//! C1R's gain under each own-blur threshold of the error map on those validation seeds, how
//! `refine::MIN_OWN_BLUR_PX` was chosen)
//! Each test scene is rendered (pinhole colour 4x4 supersampled, as `dioptra eval`; thin-lens
//! ground truth at SAMPLES rays per pixel). C1R is scored at `dioptra eval`'s foci: per focus
//! the classical and refined PSNR (sRGB), the fraction of tiles the net ran on and the times.
//! C4R is scored by the retinal images of its layers at the net's foci, beside its classical
//! input (the decomposition its weights name: linear blending or spectral), linear blending and
//! optimized blending with 10 iterations (fitting the thin-lens stack, as `dioptra eval`).

use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use dioptra_net::refine::{
    classical_composite, classical_defocus, classical_layers, compose_defocus, error_tiles_with,
    refine_defocus_input,
};
use dioptra_net::{load_net, CpuNet, Task};
use dioptra_render::metrics::psnr;
use dioptra_render::multifocal::{linear_blend, optimized_blend};
use dioptra_render::retina::retina_multifocal;
use dioptra_render::Cpu;
use dioptra_render::{Layers, OptimizeParams};
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
    let mode = args.get(5).map(String::as_str);
    let split = if mode == Some("train") {
        Split::Train
    } else {
        Split::Test
    };
    let w = dioptra_net::Weights::load(Path::new(weights))?;
    if w.arch.task.name() == "c4r" {
        return eval_c4r(&CpuNet::new(w)?, scenes, size, samples, split);
    }
    let net = load_net(Some(Path::new(weights)), "c1r")?;
    let Task::C1r { classical } = net.arch().task else {
        return Err("not a c1r net".into());
    };
    match mode {
        Some("occluders") => return occluders(&net, classical, scenes, size, samples),
        Some("gate") => return own_blur_gate(&net, classical, scenes, size, samples),
        _ => {}
    }
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
            let (pc, pr) = (
                psnr(&r.classical, &truth, None)?,
                psnr(&r.image, &truth, None)?,
            );
            println!(
                "seed {seed} focus {:.1} D: {} (gather where smooth) {pc:.2} dB -> refined {pr:.2} dB ({:+.2}), tiles {:.0}%, {tc:.1} + {tr:.1} ms",
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
        "mean over {n} images at {size}x{size}: {} + gather where smooth {:.2} dB, refined {:.2} dB ({:+.2}, worst {worst:+.2}); tiles run {:.0}%; time {:.1} ms classical + {:.1} ms refinement",
        classical.label(),
        sum_c / n,
        sum_r / n,
        (sum_r - sum_c) / n,
        100.0 * sum_f / n,
        t_c / n,
        t_r / n
    );
    failure_cases(&net, classical)
}

/// The first validation seed, random and occluder-family scenes alike: training used seeds
/// from 0 (64 random scenes, at most 96 occluder scenes), the test seeds are 1000000..
const VALIDATION_SEEDS: u64 = 5000;

/// C1R on `scenes` occluder-family scenes (rods and boxes before a textured wall) that no net
/// trained on: per scene at its wall's focus (looking through the fence) and at one focus
/// drawn from the seed in 0.6-4 D; how many fall below the classical input, and the worst.
fn occluders(
    net: &CpuNet,
    classical: dioptra_net::Classical,
    scenes: u64,
    size: usize,
    samples: u32,
) -> Result<(), Box<dyn std::error::Error>> {
    let eye = EyeModel::default().with_width(size as u32);
    let cam = Camera::square(eye, size);
    // [at the wall, elsewhere]: (sum classical, sum refined, below, worst)
    let mut acc = [(0.0f64, 0.0f64, 0usize, f64::INFINITY); 2];
    for seed in VALIDATION_SEEDS..VALIDATION_SEEDS + scenes {
        let scene = Scene::generate_occluders(seed);
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 4)?;
        let rgbd = Rgbd::new(color, depth)?;
        for (k, q) in [1.0 / scene.wall_depth, other_focus(seed)]
            .into_iter()
            .enumerate()
        {
            let q = Diopters(q);
            let truth = render_thin_lens(&scene, &cam, q, samples)?;
            let base = classical_defocus(&Cpu, classical, &rgbd, q, &eye)?;
            let r = net.refine_defocus(&rgbd, &base, q, &eye)?;
            let (pc, pr) = (
                psnr(&r.classical, &truth, None)?,
                psnr(&r.image, &truth, None)?,
            );
            println!(
                "occluder seed {seed} focus {:.2} D ({}): {pc:.2} dB -> refined {pr:.2} dB ({:+.2}), tiles {:.0}%",
                q.0,
                if k == 0 { "its wall" } else { "other" },
                pr - pc,
                100.0 * r.tiles.fraction()
            );
            let a = &mut acc[k];
            a.0 += pc / scenes as f64;
            a.1 += pr / scenes as f64;
            a.2 += usize::from(pr < pc);
            a.3 = a.3.min(pr - pc);
        }
    }
    for (k, (c, r, below, worst)) in acc.into_iter().enumerate() {
        println!(
            "occluder scenes at {size}x{size}, focus {}: classical {c:.2} dB, refined {r:.2} dB ({:+.2}); {below} of {scenes} below, worst {worst:+.2}",
            if k == 0 { "at the wall" } else { "elsewhere" },
            r - c
        );
    }
    Ok(())
}

/// Own-blur thresholds (CoC diameter, pixels) `gate` compares; 0 is the map without one.
const GATES: [f32; 7] = [0.0, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0];

/// The focus `occluders` and `gate` give an occluder scene besides its wall's: 0.6-4 D from
/// the seed.
fn other_focus(seed: u64) -> f32 {
    0.6 + 3.4 * (seed.wrapping_mul(2_654_435_761) % 1000) as f32 / 1000.0
}

/// C1R's mean gain over its classical input under each of [`GATES`], on validation seeds
/// (never trained on, never the test seeds): `Scene::generate` from [`VALIDATION_SEEDS`] at
/// eval's foci, and occluder scenes from the same seed at their wall's and another focus.
/// The net runs once per image; each gate only changes which of its pixels count.
fn own_blur_gate(
    net: &CpuNet,
    classical: dioptra_net::Classical,
    scenes: u64,
    size: usize,
    samples: u32,
) -> Result<(), Box<dyn std::error::Error>> {
    let eye = EyeModel::default().with_width(size as u32);
    let cam = Camera::square(eye, size);
    // Per image, per gate: refined PSNR minus the classical input's.
    let gains = |scene: &Scene, q: Diopters| -> Result<Vec<f64>, Box<dyn std::error::Error>> {
        let (color, depth) = render_pinhole(scene, &cam, [0.0, 0.0], 4)?;
        let rgbd = Rgbd::new(color, depth)?;
        let truth = render_thin_lens(scene, &cam, q, samples)?;
        let light = classical_defocus(&Cpu, classical, &rgbd, q, &eye)?;
        let y = net.forward(&refine_defocus_input(&rgbd, &light, q, &eye)?)?;
        let score = |img: &RgbImage| psnr(img, &truth, None);
        // The composite depends on which pixels a blurred step reaches, not on the threshold.
        let reach = error_tiles_with(&rgbd.depth, q, &eye, 0.0)?;
        let base = classical_composite(&rgbd, &light, &reach, q, &eye)?;
        let base_psnr = score(&base)?;
        let mut out = Vec::with_capacity(GATES.len());
        for gate in GATES {
            let tiles = error_tiles_with(&rgbd.depth, q, &eye, gate)?;
            out.push(score(&compose_defocus(&base, &y, &tiles)?)? - base_psnr);
        }
        Ok(out)
    };
    let report = |what: &str, rows: &[Vec<f64>]| {
        let n = rows.len() as f64;
        let cells: Vec<String> = GATES
            .iter()
            .enumerate()
            .map(|(k, g)| {
                let mean = rows.iter().map(|r| r[k]).sum::<f64>() / n;
                let worst = rows.iter().map(|r| r[k]).fold(f64::INFINITY, f64::min);
                format!("{g} px {mean:+.3} (worst {worst:+.2})")
            })
            .collect();
        println!("{what}, {} images: {}", rows.len(), cells.join(" | "));
    };
    let mut random = Vec::new();
    for seed in VALIDATION_SEEDS..VALIDATION_SEEDS + scenes {
        let scene = Scene::generate(seed);
        for q in [0.1f32, 0.5, 1.0, 1.5, 2.2, 3.0, 4.0].map(Diopters) {
            random.push(gains(&scene, q)?);
        }
        eprintln!("random scene {seed} done");
    }
    let (mut wall, mut other) = (Vec::new(), Vec::new());
    for seed in VALIDATION_SEEDS..VALIDATION_SEEDS + 3 * scenes {
        let scene = Scene::generate_occluders(seed);
        wall.push(gains(&scene, Diopters(1.0 / scene.wall_depth))?);
        other.push(gains(&scene, Diopters(other_focus(seed)))?);
    }
    println!("gain over the classical input at {size}x{size} under each own-blur threshold:");
    report("random scenes at eval's foci", &random);
    report("occluder scenes at their wall", &wall);
    report("occluder scenes elsewhere", &other);
    Ok(())
}

/// C1R on `dioptra eval`'s failure suite (192 px, 48 rays), whole image and inside each
/// case's region, beside its classical input and gather.
fn failure_cases(
    net: &CpuNet,
    classical: dioptra_net::Classical,
) -> Result<(), Box<dyn std::error::Error>> {
    let mut below = 0;
    for case in dioptra_sim::scene::failure::failure_cases(192)? {
        let (color, depth) = case.input(&case.scene)?;
        let rgbd = Rgbd::new(color, depth)?;
        let truth = render_thin_lens(&case.scene, &case.camera, case.focus, 48)?;
        let e = &case.camera.eye;
        let base = classical_defocus(&Cpu, classical, &rgbd, case.focus, e)?;
        let r = net.refine_defocus(&rgbd, &base, case.focus, e)?;
        let (base, refined) = (r.classical, r.image);
        let g = dioptra_render::gather::gather(&rgbd, case.focus, e)?;
        let (c, r) = (psnr(&base, &truth, None)?, psnr(&refined, &truth, None)?);
        let region = |img| psnr(img, &truth, Some(&case.mask));
        let (cr, rr, gr) = (region(&base)?, region(&refined)?, region(&g)?);
        below += usize::from(r < c) + usize::from(rr < cr);
        println!(
            "failure case {}: {c:.2} -> {r:.2} dB ({:+.2}), region {cr:.2} -> {rr:.2} dB ({:+.2}; gather {gr:.2})",
            case.name,
            r - c,
            rr - cr
        );
    }
    println!("failure cases: {below} scores below the classical input (whole image and region)");
    Ok(())
}

/// C4R against its classical input (linear blending or spectral), linear blending and
/// optimized blending (10 iterations), retinal PSNR.
fn eval_c4r(
    net: &CpuNet,
    scenes: u64,
    size: usize,
    samples: u32,
    split: Split,
) -> Result<(), Box<dyn std::error::Error>> {
    let Task::C4r {
        planes,
        foci,
        classical,
    } = &net.arch().task
    else {
        return Err("not a c4r net".into());
    };
    let classical = *classical;
    let planes: Vec<Diopters> = planes.iter().map(|&p| Diopters(p)).collect();
    let foci: Vec<Diopters> = foci.iter().map(|&q| Diopters(q)).collect();
    let eye = EyeModel::default().with_width(size as u32);
    let cam = Camera::square(eye, size);
    let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
    let mut sums = [0.0f64; 4];
    let mut times = [0.0f64; 4];
    let mut worst = f64::INFINITY;
    for i in 0..scenes {
        let seed = split.seed(i);
        let scene = Scene::generate(seed);
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 4)?;
        let rgbd = Rgbd::new(color, depth)?;
        let truth = foci
            .iter()
            .map(|&q| render_thin_lens(&scene, &cam, q, samples))
            .collect::<Result<Vec<_>, _>>()?;
        let t = Instant::now();
        let linear = linear_blend(&rgbd, &planes)?;
        let t_lin = ms(t);
        let t = Instant::now();
        let base = classical_layers(&Cpu, classical, &rgbd, &planes, &eye)?;
        let t_base = ms(t);
        let t = Instant::now();
        let refined = net.refine_decompose(&rgbd, &base)?;
        let t_ref = ms(t) + t_base;
        let t = Instant::now();
        let params = OptimizeParams {
            iterations: 10,
            tolerance: 0.0,
        };
        let (opt, _) =
            optimized_blend(&truth, &foci, &planes, &eye, Some(&linear), params, |_| {})?;
        let t_opt = ms(t);
        let score = |l: &Layers| -> Result<f64, Box<dyn std::error::Error>> {
            let seen = retina_multifocal(l, &foci, &eye)?;
            let mut s = 0.0;
            for (img, gt) in seen.iter().zip(&truth) {
                s += psnr(img, gt, None)? / foci.len() as f64;
            }
            Ok(s)
        };
        let p = [
            score(&linear)?,
            score(&refined)?,
            score(&opt)?,
            score(&base)?,
        ];
        worst = worst.min(p[1] - p[3]);
        println!(
            "seed {seed}: linear {:.2} dB ({t_lin:.1} ms), {} {:.2} dB ({t_base:.1} ms), refined {:.2} dB ({:+.2} over {}, {t_ref:.1} ms), optimized 10 it {:.2} dB ({t_opt:.0} ms)",
            p[0],
            classical.label(),
            p[3],
            p[1],
            p[1] - p[3],
            classical.label(),
            p[2]
        );
        for k in 0..4 {
            sums[k] += p[k] / scenes as f64;
        }
        times[0] += t_lin / scenes as f64;
        times[1] += t_ref / scenes as f64;
        times[2] += t_opt / scenes as f64;
        times[3] += t_base / scenes as f64;
    }
    println!(
        "classical input {}: {:.2} dB {:.1} ms; refined minus it: mean {:+.2} dB, worst scene {worst:+.2} dB",
        classical.label(),
        sums[3],
        times[3],
        sums[1] - sums[3]
    );
    println!(
        "mean over {scenes} scenes at {size}x{size} (retinal, {} foci): linear {:.2} dB {:.1} ms; refined {:.2} dB {:.1} ms; optimized 10 it {:.2} dB {:.0} ms",
        foci.len(),
        sums[0],
        times[0],
        sums[1],
        times[1],
        sums[2],
        times[2]
    );
    Ok(())
}
