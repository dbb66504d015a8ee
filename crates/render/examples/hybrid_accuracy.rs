//! The hybrid decomposition's accuracy and time beside linear blending and full spectral, at a
//! panel's size: retinal PSNR over the foci against the thin-lens truth, over the whole image
//! and in the fovea (a 5 degree disk around the gaze), per test scene; and what the eye sees
//! against what it sees of full spectral, in the fovea and outside it.
//!
//! `cargo run --release -p dioptra-render --example hybrid_accuracy -- [WIDTH] [HEIGHT] [SCENES] [SAMPLES] [FOCI] [CACHE]`
//! (defaults 960 x 1080, 2 test scenes, 16 ground-truth rays per pixel, 12 foci over 0.1 to
//! 2.2 D, truth cached as EXR in CACHE, default target/hybrid-accuracy). The gaze is the
//! image centre, or `HYBRID_GAZE=x,y` (fractions of the size). Spectral at full resolution
//! (the reference), its default (on the grid its `scale` chooses from the blur) and, with
//! `SPECTRAL_SCALES="2 3 ..."`, on those grids. Variants of the hybrid:
//! `HYBRID_VARIANTS="SCALE:FOVEA_DEG:EDGES:STEPS:SOLVER:VIEWS:FOCI ..."` (default "default",
//! the defaults; SCALE 0 automatic; EDGES 1 optimise only where a depth step reaches the
//! fovea, 0 always; STEPS the spectral solve's steps after the clamp; SOLVER pg or admmRHO;
//! VIEWS the composite targets' light-field views; FOCI the focal samples fitted). Times: median of 3 warm runs, wall clock, with
//! the process's CPU time beside it (the machine may be shared: CPU time is what one frame
//! costs whatever the load).

use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};
use dioptra_render::hybrid::{hybrid_blend, HybridParams};
use dioptra_render::io::{read_color, write_color};
use dioptra_render::metrics::psnr;
use dioptra_render::multifocal::{linspace, DEFAULT_PLANES};
use dioptra_render::spectral::{SpectralSolver, SpectralTargets};
use dioptra_render::spectral_coarse::scale_for;
use dioptra_render::timing::{process_cpu_ms, wall_times_ms};
use dioptra_render::{backend, Layers, LightFieldParams, SpectralParams};
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, Split};
use std::path::PathBuf;
use std::time::Instant;

/// Median wall time (ms) of 3 runs after a warm-up, the mean CPU time (ms) and the last output.
fn timed<T>(mut f: impl FnMut() -> T) -> (f64, f64, T) {
    f();
    let c0 = process_cpu_ms();
    let (t, out) = wall_times_ms(3, f);
    (t[1], (process_cpu_ms() - c0) / 3.0, out)
}

fn disk_mask(w: usize, h: usize, centre: [f32; 2], radius: f32) -> Plane {
    let mut p = Plane::new(w, h, 0.0);
    for (i, v) in p.data_mut().iter_mut().enumerate() {
        let dx = (i % w) as f32 + 0.5 - centre[0];
        let dy = (i / w) as f32 + 0.5 - centre[1];
        if dx * dx + dy * dy <= radius * radius {
            *v = 1.0;
        }
    }
    p
}

/// A hybrid variant from `SCALE:FOVEA_DEG:EDGES:STEPS:SOLVER:VIEWS:FOCI` (each optional, left
/// to right; SOLVER pg or admmRHO, e.g. admm0.3), or `default`.
fn variant(v: &str) -> HybridParams {
    let d = HybridParams::default();
    if v == "default" {
        return d;
    }
    let f: Vec<&str> = v.split(':').collect();
    let num = |i: usize| f.get(i).and_then(|s| s.parse::<f32>().ok());
    let solver = match f.get(4) {
        Some(s) if s.starts_with("admm") => SpectralSolver::Admm {
            rho: s[4..].parse().unwrap_or(0.3),
        },
        Some(_) => SpectralSolver::ProjectedGradient,
        None => d.spectral.solver,
    };
    let targets = match (d.spectral.targets, num(5)) {
        (SpectralTargets::Composite(lp), Some(v)) => SpectralTargets::Composite(LightFieldParams {
            views: v as usize,
            ..lp
        }),
        (t, _) => t,
    };
    HybridParams {
        scale: num(0).map_or(d.scale, |v| v as usize),
        fovea_deg: num(1).unwrap_or(d.fovea_deg),
        edges_only: num(2).map_or(d.edges_only, |v| v != 0.0),
        spectral: SpectralParams {
            iterations: num(3).map_or(d.spectral.iterations, |v| v as usize),
            solver,
            targets,
            focal_samples: num(6).map_or(d.spectral.focal_samples, |v| v as usize),
            ..d.spectral
        },
        ..d
    }
}

fn main() {
    dioptra_render::alloc::keep_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: usize| args.get(i).and_then(|s| s.parse().ok()).unwrap_or(d);
    let (w, h) = (arg(1, 960), arg(2, 1080));
    let (scenes, samples, nfoci) = (arg(3, 2) as u64, arg(4, 16) as u32, arg(5, 12));
    let cache = PathBuf::from(
        args.get(6)
            .cloned()
            .unwrap_or_else(|| "target/hybrid-accuracy".into()),
    );
    let gaze_frac: [f32; 2] = std::env::var("HYBRID_GAZE")
        .ok()
        .and_then(|v| {
            let p: Vec<f32> = v.split(',').filter_map(|s| s.parse().ok()).collect();
            (p.len() == 2).then(|| [p[0], p[1]])
        })
        .unwrap_or([0.5, 0.5]);
    let gaze = [gaze_frac[0] * w as f32, gaze_frac[1] * h as f32];
    let variants: Vec<(String, HybridParams)> = std::env::var("HYBRID_VARIANTS")
        .unwrap_or_else(|_| "default".into())
        .split_whitespace()
        .map(|v| (v.to_string(), variant(v)))
        .collect();
    let eye = EyeModel::default().with_width(w as u32);
    let cam = Camera::new(eye, w, h);
    let px_per_deg = 1.0f32.to_radians().tan() / eye.pixel_pitch_tan();
    let fovea = disk_mask(w, h, gaze, 2.5 * px_per_deg);
    let mut periphery = fovea.clone();
    periphery.data_mut().iter_mut().for_each(|v| *v = 1.0 - *v);
    let cpu = backend("cpu").expect("cpu");
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let foci = linspace(0.1, 2.2, nfoci);
    println!(
        "{w} x {h}, gaze ({:.0}, {:.0}) px, fovea radius {:.0} px, {nfoci} foci, truth {samples} rays/px, {} threads",
        gaze[0],
        gaze[1],
        2.5 * px_per_deg,
        rayon::current_num_threads()
    );
    println!();
    println!("| scene | method | wall ms | CPU ms | PSNR all (dB) | PSNR fovea (dB) | fovea vs spectral's retina (dB) | outside the fovea vs spectral's retina (dB) | note |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for s in 0..scenes {
        let seed = Split::Test.seed(s);
        let scene = Scene::generate(seed);
        let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], 4).expect("scene");
        let input = Rgbd::new(c, d).expect("rgbd");
        let t0 = Instant::now();
        let truth: Vec<RgbImage> = foci
            .iter()
            .map(|&q| {
                let p = cache.join(format!("{seed}_{w}x{h}_{samples}_{:.3}.exr", q.0));
                if let Ok(img) = read_color(&p) {
                    return img;
                }
                let img = render_thin_lens(&scene, &cam, q, samples).expect("truth");
                let _ = std::fs::create_dir_all(&cache);
                let _ = write_color(&p, &img);
                img
            })
            .collect();
        eprintln!(
            "scene {seed}: truth ready in {:.0} s",
            t0.elapsed().as_secs_f64()
        );
        let seen = |l: &Layers| cpu.retina_multifocal(l, &foci, &eye).expect("retina");
        let score = |r: &[RgbImage], mask: Option<&Plane>| -> f64 {
            r.iter()
                .zip(&truth)
                .map(|(a, b)| psnr(a, b, mask).expect("psnr"))
                .sum::<f64>()
                / r.len() as f64
        };
        let (tl, cl, lin) = timed(|| cpu.linear_blend(&input, &planes).expect("linear"));
        // Full spectral: the reference, at full resolution.
        let full = SpectralParams {
            scale: 1,
            ..SpectralParams::default()
        };
        let (ts, cs, (spec, _)) = timed(|| {
            cpu.spectral_blend(&input, &planes, &eye, full)
                .expect("spectral")
        });
        let spec_seen = seen(&spec);
        let vs_spec = |r: &[RgbImage], mask: &Plane| -> f64 {
            r.iter()
                .zip(&spec_seen)
                .map(|(a, b)| psnr(a, b, Some(mask)).expect("psnr"))
                .sum::<f64>()
                / r.len() as f64
        };
        let row = |name: &str, t: f64, c: f64, r: &[RgbImage], note: &str| {
            println!(
                "| {seed} | {name} | {t:.1} | {c:.1} | {:.2} | {:.2} | {:.2} | {:.2} | {note} |",
                score(r, None),
                score(r, Some(&fovea)),
                vs_spec(r, &fovea),
                vs_spec(r, &periphery)
            );
        };
        let lin_seen = seen(&lin);
        row("linear", tl, cl, &lin_seen, "");
        row("spectral, full resolution", ts, cs, &spec_seen, "");
        // The default, on the grid it chooses from the blur.
        let d = SpectralParams::default();
        let s = scale_for(&eye, &planes, w, d.scale, d.focal_range).expect("scale");
        let (t, c, (l, _)) = timed(|| {
            cpu.spectral_blend(&input, &planes, &eye, d)
                .expect("spectral")
        });
        row(
            "spectral (default)",
            t,
            c,
            &seen(&l),
            &format!("grid 1/{s} plus linear detail"),
        );
        // Other grids and settings: `SPECTRAL_SCALES="2 3 4:gather 4:foci4 4:views6 ..."`
        // (the scale, then optionally gather targets, the focal samples or the composite's
        // light-field views).
        for v in std::env::var("SPECTRAL_SCALES")
            .unwrap_or_default()
            .split_whitespace()
        {
            let mut f = v.split(':');
            let Some(scale) = f.next().and_then(|s| s.parse::<usize>().ok()) else {
                continue;
            };
            let mut p = SpectralParams { scale, ..d };
            for opt in f {
                if opt == "gather" {
                    p.targets = SpectralTargets::Defocus(dioptra_render::DefocusMethod::Gather);
                } else if let Some(n) = opt.strip_prefix("foci").and_then(|n| n.parse().ok()) {
                    p.focal_samples = n;
                } else if let (Some(n), SpectralTargets::Composite(lp)) = (
                    opt.strip_prefix("views").and_then(|n| n.parse().ok()),
                    p.targets,
                ) {
                    p.targets = SpectralTargets::Composite(LightFieldParams { views: n, ..lp });
                }
            }
            let (t, c, (l, _)) = timed(|| {
                cpu.spectral_blend(&input, &planes, &eye, p)
                    .expect("spectral")
            });
            row(&format!("spectral, grid 1/{v}"), t, c, &seen(&l), "");
        }
        // Other solvers for the full spectral: `SPECTRAL_SOLVERS="pg:10 admm:0.3:2 ..."`.
        for v in std::env::var("SPECTRAL_SOLVERS")
            .unwrap_or_default()
            .split_whitespace()
        {
            let f: Vec<&str> = v.split(':').collect();
            let num = |i: usize| f.get(i).and_then(|s| s.parse::<f32>().ok());
            let (solver, steps) = match f[0] {
                "admm" => (
                    SpectralSolver::Admm {
                        rho: num(1).unwrap_or(0.3),
                    },
                    num(2).unwrap_or(2.0) as usize,
                ),
                _ => (
                    SpectralSolver::ProjectedGradient,
                    num(1).unwrap_or(5.0) as usize,
                ),
            };
            let p = SpectralParams {
                solver,
                iterations: steps,
                ..full
            };
            let (t, c, (l, rep)) = timed(|| {
                cpu.spectral_blend(&input, &planes, &eye, p)
                    .expect("spectral")
            });
            row(
                &format!("spectral {v}"),
                t,
                c,
                &seen(&l),
                &format!(
                    "objective {:.3e} -> {:.3e}",
                    rep.objective_clamped, rep.objective_final
                ),
            );
        }
        for (name, p) in &variants {
            let (t, c, (l, rep)) =
                timed(|| hybrid_blend(&input, &planes, &eye, Some(gaze), p).expect("hybrid"));
            let note = match rep.window {
                Some(win) => format!(
                    "window {}x{} at ({}, {}), scale {}",
                    win.width, win.height, win.x0, win.y0, win.scale
                ),
                None => "no depth step in the fovea: linear".into(),
            };
            row(&format!("hybrid {name}"), t, c, &seen(&l), &note);
        }
    }
}
