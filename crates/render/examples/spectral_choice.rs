//! The spectral decomposition's targets, chosen by measurement: time and accuracy side by side
//! for each way of making what the solve fits (depth slices in the frequency domain, or a
//! focal stack rendered by gather or the light field, at several focal sample counts), the
//! prior's weight and the projected steps after the clamp; beside linear blending and
//! optimized blending of a gathered stack (what the daemon's `method = "optimized"` runs).
//!
//! `cargo run --release -p dioptra-render --example spectral_choice -- [SIZE] [SCENES] [SAMPLES] [CACHE]`
//! (defaults 256, 2 test scenes, 48 ground-truth rays per pixel). Scores: the retinal images
//! of the layers at 22 foci over 0.1 to 2.2 D against the thin-lens focal stack (dioptra-sim),
//! mean PSNR over foci per scene, as `dioptra eval` scores multifocal methods. Times: median of
//! 3 warm runs on the CPU backend. Ground truth is cached as EXR in CACHE (default
//! target/spectral-choice) so a rerun only times.

use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use dioptra_render::composite::composite_stack;
use dioptra_render::io::{read_color, write_color};
use dioptra_render::metrics::psnr;
use dioptra_render::multifocal::{default_focal_samples, DEFAULT_PLANES};
use dioptra_render::spectral::{SpectralPlan, SpectralTargets};
use dioptra_render::timing::median_wall_ms;
use dioptra_render::{
    backend, DefocusMethod, Layers, LightFieldParams, OptimizeParams, SpectralParams,
};
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, Split};
use std::path::PathBuf;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Median time (ms) of 3 runs after a warm-up, and the last output.
fn timed<T>(f: impl FnMut() -> T) -> (f64, T) {
    median_wall_ms(3, f)
}

struct SceneData {
    seed: u64,
    input: Rgbd,
    truth: Vec<RgbImage>,
}

fn main() {
    dioptra_render::alloc::keep_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    let size: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(256);
    let scenes: u64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(2);
    let samples: u32 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(48);
    let cache = PathBuf::from(
        args.get(4)
            .cloned()
            .unwrap_or_else(|| "target/spectral-choice".into()),
    );
    let eye = EyeModel::default();
    let cam = Camera::square(eye, size);
    let cpu = backend("cpu").expect("cpu");
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let foci = default_focal_samples();
    let data: Vec<SceneData> = (0..scenes)
        .map(|s| {
            let seed = Split::Test.seed(s);
            let scene = Scene::generate(seed);
            let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], 4).expect("scene");
            let truth = foci
                .iter()
                .map(|&q| {
                    let p = cache.join(format!("{seed}_{size}_{samples}_{:.2}.exr", q.0));
                    if let Ok(img) = read_color(&p) {
                        return img;
                    }
                    let img = render_thin_lens(&scene, &cam, q, samples).expect("truth");
                    let _ = std::fs::create_dir_all(&cache);
                    let _ = write_color(&p, &img);
                    img
                })
                .collect();
            eprintln!("scene {seed}: ground truth ready");
            SceneData {
                seed,
                input: Rgbd::new(c, d).expect("rgbd"),
                truth,
            }
        })
        .collect();
    let score = |l: &Layers, sd: &SceneData| -> f64 {
        let seen = cpu.retina_multifocal(l, &foci, &eye).expect("retina");
        seen.iter()
            .zip(&sd.truth)
            .map(|(a, b)| psnr(a, b, None).expect("psnr"))
            .sum::<f64>()
            / foci.len() as f64
    };
    println!("| method | targets | foci | slice step D | prior | steps | targets ms | solve ms | total ms | PSNR dB (mean) | per scene |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let row = |name: &str,
               tg: &str,
               nf: &str,
               st: &str,
               pr: &str,
               it: &str,
               tt: f64,
               ts: f64,
               ps: &[f64]| {
        let per: Vec<String> = ps.iter().map(|p| format!("{p:.2}")).collect();
        let fmt = |v: f64| {
            if v.is_nan() {
                "".to_string()
            } else {
                format!("{v:.1}")
            }
        };
        println!(
            "| {name} | {tg} | {nf} | {st} | {pr} | {it} | {} | {} | {:.1} | {:.2} | {} |",
            fmt(tt),
            fmt(ts),
            if tt.is_nan() { ts } else { tt + ts },
            ps.iter().sum::<f64>() / ps.len() as f64,
            per.join(" / ")
        );
    };
    // Baselines.
    let mut ps = Vec::new();
    let mut tl = Vec::new();
    for sd in &data {
        let (t, l) = timed(|| cpu.linear_blend(&sd.input, &planes).expect("linear"));
        tl.push(t);
        ps.push(score(&l, sd));
    }
    row("linear", "", "", "", "", "", f64::NAN, median(tl), &ps);
    let its: &[usize] = if std::env::var("SPECTRAL_SKIP_BASELINES").is_ok() {
        &[]
    } else {
        &[10, 30]
    };
    for &it in its {
        let mut ps = Vec::new();
        let mut tt = Vec::new();
        for sd in &data {
            let (t, l) = timed(|| {
                let stack = cpu
                    .defocus(&sd.input, &foci, &eye, DefocusMethod::Gather, &|_| {})
                    .expect("stack");
                let lin = cpu.linear_blend(&sd.input, &planes).expect("linear");
                let p = OptimizeParams {
                    iterations: it,
                    tolerance: 0.0,
                };
                cpu.optimized_blend(&stack, &foci, &planes, &eye, Some(&lin), p, &|_| {})
                    .expect("optimized")
                    .0
            });
            tt.push(t);
            ps.push(score(&l, sd));
        }
        row(
            "optimized-gather",
            "gather",
            "22",
            "",
            "",
            &it.to_string(),
            f64::NAN,
            median(tt),
            &ps,
        );
    }
    // Variants: TARGETS:FOCI:SLICE_STEP:PRIOR:STEPS, TARGETS one of slices, nslices, gather,
    // lf12, lf36, comp12, comp36 (the composite stack) or truth (the ground-truth stack
    // itself: an oracle no rig has).
    let specs: Vec<String> = match std::env::var("SPECTRAL_VARIANTS") {
        Ok(v) => v.split_whitespace().map(String::from).collect(),
        Err(_) => [
            "slices:22:0.6:0.02:0",
            "slices:22:0.3:0.02:0",
            "slices:22:0.3:0.2:0",
            "gather:22:0.3:0.2:0",
            "lf36:22:0.3:0.2:0",
            "truth:22:0.3:0.2:0",
            "truth:22:0.3:0.02:10",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect(),
    };
    // How close each kind of target stack is to the truth (varifocal PSNR at the 22 foci).
    let mut quality: Vec<(String, Vec<f64>)> = Vec::new();
    for spec in &specs {
        let f: Vec<&str> = spec.split(':').collect();
        let num = |i: usize, d: f32| f.get(i).and_then(|s| s.parse().ok()).unwrap_or(d);
        let kind = f[0];
        let base = SpectralParams::default();
        let p = SpectralParams {
            focal_samples: num(1, 22.0) as usize,
            slice_step: num(2, base.slice_step),
            prior: num(3, base.prior),
            iterations: num(4, 0.0) as usize,
            ..base
        };
        let views = |k: &str| LightFieldParams {
            views: if k.ends_with("12") { 12 } else { 36 },
            mip: true,
        };
        let method = match kind {
            "gather" => Some(DefocusMethod::Gather),
            "lf36" | "lf12" => Some(DefocusMethod::LightField(views(kind))),
            _ => None,
        };
        let p = SpectralParams {
            targets: match (kind, method) {
                ("slices", _) => SpectralTargets::Slices,
                ("nslices", _) => SpectralTargets::NormalizedSlices,
                ("comp12" | "comp36", _) => SpectralTargets::Composite(views(kind)),
                (_, Some(m)) => SpectralTargets::Defocus(m),
                _ => SpectralTargets::Defocus(DefocusMethod::Gather),
            },
            ..p
        };
        let plan = SpectralPlan::new(&eye, &planes, size, size, p).expect("plan");
        let vf = p.foci();
        let (mut ps, mut tt, mut ts) = (Vec::new(), Vec::new(), Vec::new());
        let mut q = Vec::new();
        for sd in &data {
            let (t1, targets) = timed(|| match (kind, method) {
                ("slices" | "nslices", _) => plan.targets_rgbd(&sd.input).expect("targets"),
                ("truth", _) => {
                    let stack: Vec<RgbImage> = vf
                        .iter()
                        .map(|f| {
                            let k = foci.iter().position(|g| (g.0 - f.0).abs() < 1e-4);
                            sd.truth[k.expect("the truth's foci")].clone()
                        })
                        .collect();
                    plan.targets_stack(&sd.input, &stack).expect("targets")
                }
                (_, Some(m)) => {
                    let stack = cpu
                        .defocus(&sd.input, &vf, &eye, m, &|_| {})
                        .expect("stack");
                    plan.targets_stack(&sd.input, &stack).expect("targets")
                }
                ("comp12" | "comp36", _) => {
                    let stack = composite_stack(&sd.input, &vf, &eye, views(kind)).expect("stack");
                    plan.targets_stack(&sd.input, &stack).expect("targets")
                }
                _ => panic!("unknown targets {kind}"),
            });
            let (t2, (l, _)) = timed(|| plan.solve(&targets).expect("solve"));
            tt.push(t1);
            ts.push(t2);
            ps.push(score(&l, sd));
            if quality.iter().any(|(k, _)| k == kind) {
                continue;
            }
            let stack: Option<Vec<RgbImage>> = match (kind, method) {
                ("slices", _) => {
                    let nodes: Vec<Diopters> = plan.nodes().iter().map(|&x| Diopters(x)).collect();
                    let sl = cpu.linear_blend(&sd.input, &nodes).expect("slices");
                    Some(cpu.retina_multifocal(&sl, &foci, &eye).expect("stack"))
                }
                (_, Some(m)) => Some(
                    cpu.defocus(&sd.input, &foci, &eye, m, &|_| {})
                        .expect("stack"),
                ),
                ("comp12" | "comp36", _) => {
                    Some(composite_stack(&sd.input, &foci, &eye, views(kind)).expect("stack"))
                }
                _ => None,
            };
            if let Some(st) = stack {
                q.push(
                    st.iter()
                        .zip(&sd.truth)
                        .map(|(a, b)| psnr(a, b, None).expect("psnr"))
                        .sum::<f64>()
                        / foci.len() as f64,
                );
            }
        }
        if !q.is_empty() {
            quality.push((kind.to_string(), q));
        }
        let tg = match kind {
            "slices" => format!("{} depth slices", plan.nodes().len()),
            "nslices" => format!("{} depth slices, normalised", plan.nodes().len()),
            "gather" => "gather stack".into(),
            "lf36" => "lightfield 36 stack".into(),
            "lf12" => "lightfield 12 stack".into(),
            "comp12" => "composite (lightfield 12 at steps, smooth disk blur elsewhere)".into(),
            "comp36" => "composite (lightfield 36 at steps, smooth disk blur elsewhere)".into(),
            _ => "ground-truth stack (oracle)".into(),
        };
        let st = if kind.ends_with("slices") {
            format!("{}", p.slice_step)
        } else {
            String::new()
        };
        row(
            "spectral",
            &tg,
            &p.focal_samples.to_string(),
            &st,
            &p.prior.to_string(),
            &p.iterations.to_string(),
            median(tt),
            median(ts),
            &ps,
        );
    }
    println!("\n| target stack | PSNR against the truth, dB (mean of 22 foci) | per scene |\n|---|---|---|");
    for (k, q) in &quality {
        let per: Vec<String> = q.iter().map(|p| format!("{p:.2}")).collect();
        println!(
            "| {k} | {:.2} | {} |",
            q.iter().sum::<f64>() / q.len() as f64,
            per.join(" / ")
        );
    }
    let seeds: Vec<String> = data.iter().map(|d| d.seed.to_string()).collect();
    println!(
        "\nscenes {} at {size} px, ground truth {samples} rays per pixel",
        seeds.join(", ")
    );
}
