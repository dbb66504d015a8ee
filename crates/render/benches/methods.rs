//! Speed of the CPU backend at 512 x 512 RGB-D (a sim test scene). Targets from issue 6:
//! gather <= 30 ms; lightfield 36 views <= 80 ms; linear blending 4 planes <= 10 ms;
//! optimized blending 100 iterations <= 10 s; retina per focus <= 20 ms. Beside them (issue
//! 41): a 9 x 9 light field of 256 px views over 1 cm synthesised from 9 of its views.

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::multifocal::{default_focal_samples, MultifocalRetina, DEFAULT_PLANES};
use dioptra_render::views::RgbdView;
use dioptra_render::{backend, DefocusMethod, LightFieldParams, OptimizeParams};
use dioptra_sim::scene::{render_pinhole, Camera, Scene, Split};
use std::hint::black_box;
use std::time::Duration;

fn input() -> Rgbd {
    let cam = Camera::square(EyeModel::default(), 512);
    let scene = Scene::generate(Split::Test.seed(0));
    let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], 1).expect("scene renders");
    Rgbd::new(c, d).expect("same size")
}

fn benches(c: &mut Criterion) {
    // As the dioptra binary runs (see dioptra_render::alloc).
    dioptra_render::alloc::keep_freed_memory();
    let eye = EyeModel::default();
    let cpu = backend("cpu").expect("cpu backend");
    let input = input();
    let q = [Diopters(1.0)];
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();

    let mut g = c.benchmark_group("512x512");
    g.sample_size(10).measurement_time(Duration::from_secs(5));
    g.bench_function("gather", |b| {
        b.iter(|| {
            cpu.defocus(black_box(&input), &q, &eye, DefocusMethod::Gather, &|_| {})
                .expect("gather")
        })
    });
    let lf = DefocusMethod::LightField(LightFieldParams {
        views: 36,
        mip: true,
    });
    g.bench_function("lightfield_36", |b| {
        b.iter(|| {
            cpu.defocus(black_box(&input), &q, &eye, lf, &|_| {})
                .expect("lightfield")
        })
    });
    // Focused at the near end of the range, far content is blurred most: the coarse pyramid
    // levels (built only when a focus needs them) are read here.
    g.bench_function("lightfield_36_focus_4D", |b| {
        b.iter(|| {
            cpu.defocus(black_box(&input), &[Diopters(4.0)], &eye, lf, &|_| {})
                .expect("lightfield")
        })
    });
    g.bench_function("linear_blend_4", |b| {
        b.iter(|| {
            cpu.linear_blend(black_box(&input), &planes)
                .expect("linear")
        })
    });
    let layers = cpu.linear_blend(&input, &planes).expect("linear");
    let foci = default_focal_samples();
    let retina =
        MultifocalRetina::new(&layers, &eye, (foci[0], foci[foci.len() - 1])).expect("retina");
    g.bench_function("retina_multifocal_per_focus", |b| {
        b.iter(|| retina.render(black_box(Diopters(1.3))).expect("retina"))
    });
    g.finish();

    let targets = cpu
        .retina_multifocal(&layers, &foci, &eye)
        .expect("targets");
    let mut g = c.benchmark_group("512x512_slow");
    g.sample_size(10).measurement_time(Duration::from_secs(60));
    g.bench_function("optimized_blend_100", |b| {
        b.iter(|| {
            let p = OptimizeParams {
                iterations: 100,
                tolerance: 0.0,
            };
            cpu.optimized_blend(
                black_box(&targets),
                &foci,
                &planes,
                &eye,
                Some(&layers),
                p,
                &|_| {},
            )
            .expect("opt")
        })
    });
    g.finish();

    // DeepFocus's light field: 9 x 9 views over 1 cm from 9 (corners, edge midpoints, centre).
    let cam = Camera::square(eye, 256);
    let scene = Scene::generate(Split::Test.seed(0));
    let (step, picks) = (0.01 / 8.0, [0usize, 4, 8]);
    let inputs: Vec<RgbdView> = picks
        .iter()
        .flat_map(|&r| picks.iter().map(move |&c| (r, c)))
        .map(|(r, c)| {
            let position = [(c as f32 - 4.0) * step, (r as f32 - 4.0) * step];
            let (color, depth) = render_pinhole(&scene, &cam, position, 1).expect("view");
            RgbdView {
                position,
                rgbd: Rgbd::new(color, depth).expect("same size"),
            }
        })
        .collect();
    let mut g = c.benchmark_group("256x256_lightfield");
    g.sample_size(10).measurement_time(Duration::from_secs(20));
    g.bench_function("synthesize_9x9_from_9", |b| {
        b.iter(|| {
            cpu.synthesize_light_field(black_box(&inputs), 9, 0.01, &eye, &|_| {})
                .expect("light field")
        })
    });
    g.finish();
}

criterion_group!(methods, benches);
criterion_main!(methods);
