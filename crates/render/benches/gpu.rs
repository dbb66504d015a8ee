//! The GPU backend at 512 x 512 RGB-D (the sim test scene of `--bench methods`): criterion's
//! wall time per frame includes uploads and readbacks; beside it, printed once per method, the
//! GPU time from timestamp queries (where the adapter has them), dispatches, submissions and
//! bytes moved per frame. At the end a table of every per-frame method: GPU wall time, GPU
//! time, dispatches, submissions and bytes moved, and the CPU backend's wall time on the same
//! input. Without an adapter it says so and measures nothing.

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use dioptra_render::foveate::LogPolar;
use dioptra_render::multifocal::DEFAULT_PLANES;
use dioptra_render::retina::LfView;
use dioptra_render::timing::median_wall_ms;
use dioptra_render::{Backend, Cpu, DefocusMethod, Gpu, Layers, LightFieldParams};
use dioptra_sim::scene::{render_pinhole, Camera, Scene, Split};
use std::hint::black_box;
use std::time::Duration;

fn input() -> Rgbd {
    let cam = Camera::square(EyeModel::default(), 512);
    let scene = Scene::generate(Split::Test.seed(0));
    let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], 1).expect("scene renders");
    Rgbd::new(c, d).expect("same size")
}

fn report(name: &str, gpu: &Gpu) {
    let s = gpu.last_stats();
    let t = s
        .gpu_ns
        .map_or("n/a (no timestamp queries)".to_string(), |ns| {
            format!("{:.2} ms", ns * 1e-6)
        });
    eprintln!(
        "{name}: GPU time {t}; {} dispatches, {} submissions, {:.2} MB up, {:.2} MB down per frame",
        s.dispatches,
        s.submissions,
        s.bytes_uploaded as f64 / 1e6,
        s.bytes_read_back as f64 / 1e6
    );
    for (label, ns) in &s.passes {
        eprintln!("    {label:<14} {:.3} ms", ns * 1e-6);
    }
}

fn benches(c: &mut Criterion) {
    let gpu = match Gpu::new(None) {
        Ok(g) => g,
        Err(e) => {
            eprintln!("skipped: no GPU adapter ({e})");
            return;
        }
    };
    let a = gpu.context().adapter();
    eprintln!(
        "adapter: {} ({}, {})",
        a.name,
        a.backend,
        if a.software { "software" } else { "hardware" }
    );
    let eye = EyeModel::default();
    let input = input();
    let q = [Diopters(1.0)];
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let mut g = c.benchmark_group("gpu_512x512");
    g.sample_size(10).measurement_time(Duration::from_secs(5));

    let mut run = |name: &str, f: &mut dyn FnMut()| {
        g.bench_function(name, |b| b.iter(&mut *f));
        f();
        report(name, &gpu);
    };
    run("gather", &mut || {
        gpu.defocus(black_box(&input), &q, &eye, DefocusMethod::Gather, &|_| {})
            .expect("gather");
    });
    let lf = DefocusMethod::LightField(LightFieldParams {
        views: 36,
        mip: true,
    });
    run("lightfield_36", &mut || {
        gpu.defocus(black_box(&input), &q, &eye, lf, &|_| {})
            .expect("lightfield");
    });
    run("lightfield_36_focus_4D", &mut || {
        gpu.defocus(black_box(&input), &[Diopters(4.0)], &eye, lf, &|_| {})
            .expect("lightfield");
    });
    run("linear_blend_4", &mut || {
        gpu.linear_blend(black_box(&input), &planes)
            .expect("linear");
    });
    let layers = dioptra_render::Cpu
        .linear_blend(&input, &planes)
        .expect("linear");
    run("retina_multifocal_per_focus", &mut || {
        gpu.retina_multifocal(black_box(&layers), &q, &eye)
            .expect("retina");
    });
    run("retina_varifocal", &mut || {
        gpu.retina_varifocal(black_box(&input.color), Diopters(2.0), Diopters(1.0), &eye)
            .expect("retina");
    });
    // A 5 x 5 light field over 4 mm (the pupil): all 25 views are uploaded each frame.
    let views: Vec<LfView> = (0..25)
        .map(|k| LfView {
            position: [
                ((k % 5) as f32 - 2.0) * 0.001,
                ((k / 5) as f32 - 2.0) * 0.001,
            ],
            image: input.color.clone(),
        })
        .collect();
    run("retina_lightfield_5x5", &mut || {
        gpu.retina_lightfield(black_box(&views), 0.001, Diopters(1.0), &eye)
            .expect("retina lf");
    });
    // Optimized blending against the 22-slice gather focal stack: lavapipe takes about 15 s
    // per iteration at this size, so one timed call of 2 iterations stands in for criterion.
    let foci = dioptra_render::multifocal::default_focal_samples();
    let targets = dioptra_render::Cpu
        .defocus(&input, &foci, &eye, DefocusMethod::Gather, &|_| {})
        .expect("targets");
    let params = dioptra_render::OptimizeParams {
        iterations: 2,
        tolerance: 0.0,
    };
    let t = std::time::Instant::now();
    gpu.optimized_blend(
        &targets,
        &foci,
        &planes,
        &eye,
        Some(&layers),
        params,
        &|_| {},
    )
    .expect("optimized");
    eprintln!(
        "optimized_2 (one call): wall {:.0} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    report("optimized_2", &gpu);
    // View synthesis: 3 x 3 views from 5 RGB-D inputs (the same image at 5 positions), one
    // timed call.
    let inputs: Vec<dioptra_render::views::RgbdView> = [
        (-1.0, -1.0),
        (1.0, -1.0),
        (0.0, 0.0),
        (-1.0, 1.0),
        (1.0, 1.0),
    ]
    .iter()
    .map(|&(x, y)| dioptra_render::views::RgbdView {
        position: [x * 0.005, y * 0.005],
        rgbd: input.clone(),
    })
    .collect();
    let t = std::time::Instant::now();
    gpu.synthesize_light_field(&inputs, 3, 0.01, &eye, &|_| {})
        .expect("views");
    eprintln!(
        "views_3x3_from_5 (one call, 9 views): wall {:.0} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    report("views_3x3_from_5", &gpu);
    let other = dioptra_render::Cpu
        .defocus(&input, &q, &eye, DefocusMethod::Gather, &|_| {})
        .expect("gather")
        .remove(0);
    run("psnr_ssim", &mut || {
        gpu.quality(black_box(&input.color), &other, None)
            .expect("quality");
    });
    let fov = LogPolar::centred(512, 512, 2.0);
    run("foveate_s2", &mut || {
        gpu.foveate(black_box(&input.color), &fov).expect("foveate");
    });
    g.finish();
    table(&gpu, &input, &other, &layers, &views, &fov);
}

/// The report table: per method, GPU wall time (uploads and readbacks included), GPU time
/// from timestamp queries, dispatches, submissions and bytes moved per frame, and the CPU
/// backend's wall time on the same input (median of 3 each).
fn table(
    gpu: &Gpu,
    input: &Rgbd,
    other: &RgbImage,
    layers: &Layers,
    views: &[LfView],
    fov: &LogPolar,
) {
    let eye = EyeModel::default();
    let q = [Diopters(1.0)];
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let lf = DefocusMethod::LightField(LightFieldParams {
        views: 36,
        mip: true,
    });
    type Call<'a> = Box<dyn Fn(&dyn Backend) + 'a>;
    let methods: Vec<(&str, Call)> = vec![
        (
            "gather",
            Box::new(|b: &dyn Backend| {
                b.defocus(input, &q, &eye, DefocusMethod::Gather, &|_| {})
                    .expect("gather");
            }),
        ),
        (
            "lightfield_36",
            Box::new(|b: &dyn Backend| {
                b.defocus(input, &q, &eye, lf, &|_| {}).expect("lightfield");
            }),
        ),
        (
            "linear_blend_4",
            Box::new(|b: &dyn Backend| {
                b.linear_blend(input, &planes).expect("linear");
            }),
        ),
        (
            "retina_multifocal_per_focus",
            Box::new(|b: &dyn Backend| {
                b.retina_multifocal(layers, &q, &eye).expect("retina");
            }),
        ),
        (
            "retina_varifocal",
            Box::new(|b: &dyn Backend| {
                b.retina_varifocal(&input.color, Diopters(2.0), Diopters(1.0), &eye)
                    .expect("retina");
            }),
        ),
        (
            "retina_lightfield_5x5",
            Box::new(|b: &dyn Backend| {
                b.retina_lightfield(views, 0.001, Diopters(1.0), &eye)
                    .expect("retina lf");
            }),
        ),
        (
            "psnr_ssim",
            Box::new(|b: &dyn Backend| {
                b.quality(&input.color, other, None).expect("quality");
            }),
        ),
        (
            "foveate_s2",
            Box::new(|b: &dyn Backend| {
                b.foveate(&input.color, fov).expect("foveate");
            }),
        ),
    ];
    eprintln!();
    eprintln!("| method (512x512) | GPU wall ms | GPU time ms (timestamps) | dispatches | submissions | MB up | MB down | CPU wall ms |");
    eprintln!("|---|---|---|---|---|---|---|---|");
    for (name, call) in &methods {
        let g = median_wall_ms(3, || call(gpu)).0;
        let s = gpu.last_stats();
        let c = median_wall_ms(3, || call(&Cpu)).0;
        eprintln!(
            "| {name} | {g:.1} | {} | {} | {} | {:.2} | {:.2} | {c:.1} |",
            s.gpu_ns
                .map_or("n/a".to_string(), |ns| format!("{:.1}", ns * 1e-6)),
            s.dispatches,
            s.submissions,
            s.bytes_uploaded as f64 / 1e6,
            s.bytes_read_back as f64 / 1e6,
        );
    }
}

criterion_group!(gpu_benches, benches);
criterion_main!(gpu_benches);
