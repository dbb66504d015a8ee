//! The spectral decomposition's speed targets (issue 42), on the CPU backend with a sim test
//! scene: at 256 x 256 the whole decomposition from RGB-D (its target stack included) at most
//! 1/4 of optimized blending's 10 iterations on a gathered stack (`optimized_gather_10`, what
//! the daemon's `method = "optimized"` runs, measured here beside it), and the solve itself
//! (the unconstrained fit of a rendered stack, the clamp and the projected steps) at most
//! 30 ms; at 512 x 512 both are reported. Where a GPU adapter exists, the GPU backend beside
//! them at 256 x 256 (`gpu_whole`, `gpu_solve`: wall time per frame, uploads and readbacks
//! included; on a machine with only lavapipe that is a software rasteriser on the same CPU).
//! `optimized_own_targets_10`: 10 iterations fitted to spectral's own targets instead (its
//! composite stack at its 6 foci, stack included), the comparator read literally.

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::composite::composite_stack;
use dioptra_render::multifocal::{default_focal_samples, DEFAULT_PLANES};
use dioptra_render::spectral::{plan_for, SpectralTargets};
use dioptra_render::{backend, Backend, DefocusMethod, Gpu, OptimizeParams, SpectralParams};
use dioptra_sim::scene::{render_pinhole, Camera, Scene, Split};
use std::hint::black_box;
use std::time::Duration;

fn input(size: usize) -> Rgbd {
    let cam = Camera::square(EyeModel::default(), size);
    let scene = Scene::generate(Split::Test.seed(0));
    let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], 1).expect("scene renders");
    Rgbd::new(c, d).expect("same size")
}

fn benches(c: &mut Criterion) {
    dioptra_render::alloc::keep_freed_memory();
    let eye = EyeModel::default();
    let cpu = backend("cpu").expect("cpu backend");
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let params = SpectralParams::default();
    let gpu = match Gpu::new(None) {
        Ok(g) => Some(g),
        Err(e) => {
            eprintln!("no GPU rows: {e}");
            None
        }
    };
    for size in [256usize, 512] {
        let input = input(size);
        let mut g = c.benchmark_group(format!("spectral_{size}"));
        g.sample_size(10).measurement_time(Duration::from_secs(4));
        g.bench_function("whole", |b| {
            b.iter(|| {
                cpu.spectral_blend(black_box(&input), &planes, &eye, params)
                    .expect("spectral")
            })
        });
        let plan = plan_for(&eye, &planes, size, size, params).expect("plan");
        let target_stack = |input: &Rgbd| {
            match params.targets {
                SpectralTargets::Defocus(m) => cpu.defocus(input, &params.foci(), &eye, m, &|_| {}),
                SpectralTargets::Composite(lf) => composite_stack(input, &params.foci(), &eye, lf),
                t => panic!("the default targets are a rendered stack, not {t:?}"),
            }
            .expect("stack")
        };
        let stack = target_stack(&input);
        g.bench_function("target_stack", |b| {
            b.iter(|| target_stack(black_box(&input)))
        });
        g.bench_function("solve", |b| {
            b.iter(|| {
                let t = plan.targets_stack(black_box(&input), &stack).expect("fit");
                plan.solve(&t).expect("solve")
            })
        });
        if let Some(gpu) = gpu.as_ref().filter(|_| size == 256) {
            g.bench_function("gpu_whole", |b| {
                b.iter(|| {
                    gpu.spectral_blend(black_box(&input), &planes, &eye, params)
                        .expect("gpu spectral")
                })
            });
            g.bench_function("gpu_solve", |b| {
                b.iter(|| {
                    gpu.spectral_blend_stack(black_box(&input), &stack, &planes, &eye, params)
                        .expect("gpu spectral solve")
                })
            });
        }
        // 10 iterations of optimized blending from linear blending (its time included).
        let optimized_10 = |stack: &[dioptra_core::RgbImage], foci: &[Diopters]| {
            let lin = cpu.linear_blend(&input, &planes).expect("linear");
            let p = OptimizeParams {
                iterations: 10,
                tolerance: 0.0,
            };
            cpu.optimized_blend(stack, foci, &planes, &eye, Some(&lin), p, &|_| {})
                .expect("optimized")
        };
        let foci = default_focal_samples();
        g.bench_function("optimized_gather_10", |b| {
            b.iter(|| {
                let stack = cpu
                    .defocus(
                        black_box(&input),
                        &foci,
                        &eye,
                        DefocusMethod::Gather,
                        &|_| {},
                    )
                    .expect("stack");
                optimized_10(&stack, &foci)
            })
        });
        // The same 10 iterations fitted to spectral's own targets (its composite stack at its
        // 6 foci, the stack's time included): the comparator with the same targets.
        let own_foci = params.foci();
        g.bench_function("optimized_own_targets_10", |b| {
            b.iter(|| {
                let stack = target_stack(black_box(&input));
                optimized_10(&stack, &own_foci)
            })
        });
        g.finish();
    }
}

criterion_group!(spectral, benches);
criterion_main!(spectral);
