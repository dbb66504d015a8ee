//! Where the spectral decomposition's time goes at a panel's size: each stage of one frame
//! timed alone on the CPU backend (median of a few warm runs).
//!
//! `cargo run --release -p dioptra-render --example spectral_profile -- [WIDTH] [HEIGHT] [RUNS]`
//! `[FOV_DEG]` (defaults 960 x 1080, 3 runs, 20 degrees over the width; a test scene of
//! dioptra-sim). First the whole default decomposition (on the grid its `scale` chooses),
//! then the full-resolution stages.

use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use dioptra_render::composite::{composite_stack, step_reach};
use dioptra_render::gather::gather_smooth;
use dioptra_render::lightfield::LightFieldPrep;
use dioptra_render::multifocal::{linear_blend, DEFAULT_PLANES};
use dioptra_render::spectral::{spectral_blend, SpectralPlan, SpectralTargets};
use dioptra_render::spectral_coarse::scale_for;
use dioptra_render::timing::{process_cpu_ms, wall_times_ms};
use dioptra_render::SpectralParams;
use dioptra_sim::scene::{render_pinhole, Camera, Scene, Split};

thread_local! {
    static CPU_MS: std::cell::Cell<f64> = const { std::cell::Cell::new(0.0) };
}

/// Median wall time (ms) of `runs` runs after a warm-up (the mean CPU time per run in CPU_MS).
fn timed<T>(runs: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    f();
    let c0 = process_cpu_ms();
    let (t, out) = wall_times_ms(runs, f);
    CPU_MS.set((process_cpu_ms() - c0) / runs as f64);
    (t[t.len() / 2], out)
}

fn main() {
    dioptra_render::alloc::keep_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    let w: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(960);
    let h: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1080);
    let runs: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(3);
    // The field over the width (degrees): default 20; a window of a larger panel keeps the
    // panel's pixel pitch (e.g. 7.57 for 360 px of a 960 px, 20 degree panel).
    let fov: f32 = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(20.0);
    let eye = EyeModel {
        fov_horizontal_deg: fov,
        ..EyeModel::default()
    };
    let cam = Camera::new(eye, w, h);
    let scene = Scene::generate(Split::Test.seed(0));
    let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], 1).expect("scene");
    let input = Rgbd::new(c, d).expect("rgbd");
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let params = SpectralParams::default();
    let foci = params.foci();
    let lp = match params.targets {
        SpectralTargets::Composite(lp) => lp,
        t => panic!("the default targets are the composite stack, not {t:?}"),
    };
    let report =
        |name: &str, ms: f64| println!("{name:<40} {ms:>9.1} ms  (CPU {:.1} ms)", CPU_MS.get());
    // `SPECTRAL_PROFILE_HYBRID=N`: only the hybrid's default, N times (for a sampling profiler).
    if let Some(n) = std::env::var("SPECTRAL_PROFILE_HYBRID")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
    {
        let p = dioptra_render::hybrid::HybridParams::default();
        let (t, (_, rep)) = timed(n, || {
            dioptra_render::hybrid::hybrid_blend(&input, &planes, &eye, None, &p).expect("hybrid")
        });
        report("hybrid (default)", t);
        println!("{rep:?}");
        return;
    }
    println!("{w} x {h}, {} threads", rayon::current_num_threads());
    // The whole decomposition as `method = "spectral"` runs it (its defaults: the grid chosen
    // from the blur), then `SPECTRAL_SCALE=S` (1: full resolution) if set;
    // `SPECTRAL_PROFILE_WHOLE=N`: only this, N runs.
    let whole_runs = std::env::var("SPECTRAL_PROFILE_WHOLE")
        .ok()
        .and_then(|v| v.parse::<usize>().ok());
    let scale_env = std::env::var("SPECTRAL_SCALE")
        .ok()
        .and_then(|v| v.parse::<usize>().ok());
    for scale in [Some(params.scale), scale_env].into_iter().flatten() {
        let p = SpectralParams { scale, ..params };
        let s = scale_for(&eye, &planes, w, p.scale, p.focal_range).expect("scale");
        let (t, (_, rep)) = timed(whole_runs.unwrap_or(runs), || {
            spectral_blend(&input, &planes, &eye, p).expect("spectral")
        });
        report(&format!("spectral_blend, scale {scale} (grid 1/{s})"), t);
        println!("{rep:?}");
    }
    if whole_runs.is_some() {
        return;
    }
    let (t, plan) = timed(1, || {
        SpectralPlan::new(&eye, &planes, w, h, params).expect("plan")
    });
    report("plan (once per settings)", t);
    let (pw, ph) = plan.grid();
    println!("padded grid {pw} x {ph}");
    let (t, _) = timed(runs, || linear_blend(&input, &planes).expect("linear"));
    report("linear blend", t);
    // The composite stack, stage by stage.
    let (t, reach) = timed(runs, || {
        foci.iter()
            .map(|&q| step_reach(&input.depth, q, &eye, 0.0).expect("reach"))
            .collect::<Vec<_>>()
    });
    report("  step reach (6 foci)", t);
    let reached: Vec<f64> = reach
        .iter()
        .map(|r| r.reached.iter().filter(|&&b| b).count() as f64 / (w * h) as f64)
        .collect();
    println!("  reached fraction per focus {reached:.3?}");
    let (t, _) = timed(runs, || {
        let prep = LightFieldPrep::new(&input, &eye, lp).expect("prep");
        foci.iter()
            .zip(&reach)
            .map(|(&q, r)| prep.render_masked(q, Some(&r.reached)).expect("lf"))
            .collect::<Vec<RgbImage>>()
    });
    report("  light field, masked (6 foci)", t);
    let (t, _) = timed(runs, || {
        foci.iter()
            .zip(&reach)
            .map(|(&q, r)| {
                let smooth: Vec<bool> = r.reached.iter().map(|b| !b).collect();
                gather_smooth(&input, q, &eye, &smooth).expect("gather")
            })
            .collect::<Vec<RgbImage>>()
    });
    report("  gather_smooth (6 foci)", t);
    let (t, stack) = timed(runs, || {
        composite_stack(&input, &foci, &eye, lp).expect("stack")
    });
    report("composite stack (whole)", t);
    let (t, y0) = timed(runs, || plan.targets_stack(&input, &stack).expect("fit"));
    report("targets_stack (30 fwd FFT + apply)", t);
    let p0 = SpectralPlan::new(
        &eye,
        &planes,
        w,
        h,
        SpectralParams {
            iterations: 0,
            ..params
        },
    )
    .expect("plan");
    let y00 = p0.targets_stack(&input, &stack).expect("fit");
    let (t, _) = timed(runs, || p0.solve(&y00).expect("solve"));
    report("solve, 0 steps (12 inv FFT + clamp)", t);
    let (t, (_, rep)) = timed(runs, || plan.solve(&y0).expect("solve"));
    report(&format!("solve, {} steps", params.iterations), t);
    println!("{rep:?}");
}
