//! C1R and C4R per frame at 512 x 512 on a test scene (seed 1000000), CPU: the classical
//! render, the error map, and the refinement (input, tiled net, composition), so where a
//! frame's time goes is visible. Target (issue 21): C1R's whole frame (classical + refine)
//! below the 36-view light field's time, also benchmarked here. The shipped weights when
//! present (else random weights of the preset: the time depends on the architecture and the
//! tiles, not on the values).

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_net::refine::{classical_defocus, error_tiles, refine_defocus_input};
use dioptra_net::{Arch, Classical, CpuNet, Task, Weights};
use dioptra_render::multifocal::linear_blend;
use dioptra_render::{Backend, Cpu, DefocusMethod, LightFieldParams};
use dioptra_sim::scene::{render_pinhole, Camera, Scene, Split};

fn net(config: &str) -> CpuNet {
    dioptra_net::load_net(None, config).unwrap_or_else(|_| {
        let arch = Arch::preset(config).expect("preset");
        CpuNet::new(Weights::random(&arch, 1).expect("weights")).expect("net")
    })
}

fn bench(c: &mut Criterion) {
    // As the dioptra binary runs (see dioptra_render::alloc).
    dioptra_render::alloc::keep_freed_memory();
    let size = 512;
    let eye = EyeModel::default().with_width(size as u32);
    let cam = Camera::square(eye, size);
    let scene = Scene::generate(Split::Test.seed(0));
    let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 2).expect("scene");
    let rgbd = Rgbd::new(color, depth).expect("rgbd");
    let c1r = net("c1r");
    let Task::C1r { classical } = c1r.arch().task else {
        panic!("not a c1r net");
    };
    let mut g = c.benchmark_group("refine_512");
    g.sample_size(10);
    for q in [0.1f32, 1.0, 4.0] {
        let q = Diopters(q);
        let base = classical_defocus(&Cpu, classical, &rgbd, q, &eye).expect("classical");
        let tiles = error_tiles(&rgbd.depth, q, &eye).expect("tiles");
        eprintln!(
            "focus {:.1} D: the net runs on {:.0} % of the tiles",
            q.0,
            100.0 * tiles.fraction()
        );
        let x = refine_defocus_input(&rgbd, &base, q, &eye).expect("input");
        let tag = format!("{:.1}D", q.0);
        g.bench_function(format!("c1r_frame_{tag}"), |b| {
            b.iter(|| {
                let base = classical_defocus(&Cpu, classical, &rgbd, q, &eye).expect("classical");
                c1r.refine_defocus(&rgbd, &base, q, &eye).expect("refine")
            })
        });
        g.bench_function(
            format!("classical_{}_{tag}", classical.label().replace(' ', "_")),
            |b| b.iter(|| classical_defocus(&Cpu, classical, &rgbd, q, &eye).expect("classical")),
        );
        g.bench_function(format!("error_map_{tag}"), |b| {
            b.iter(|| error_tiles(&rgbd.depth, q, &eye).expect("tiles"))
        });
        g.bench_function(format!("c1r_input_{tag}"), |b| {
            b.iter(|| refine_defocus_input(&rgbd, &base, q, &eye).expect("input"))
        });
        g.bench_function(format!("c1r_net_on_tiles_{tag}"), |b| {
            b.iter(|| c1r.forward_tiles(&x, &tiles).expect("net"))
        });
        g.bench_function(format!("c1r_net_whole_image_{tag}"), |b| {
            b.iter(|| c1r.forward(&x).expect("net"))
        });
        g.bench_function(format!("c1r_refine_{tag}"), |b| {
            b.iter(|| c1r.refine_defocus(&rgbd, &base, q, &eye).expect("refine"))
        });
        let lf36 = DefocusMethod::LightField(LightFieldParams {
            views: 36,
            mip: true,
        });
        g.bench_function(format!("lightfield_36_views_{tag}"), |b| {
            b.iter(|| Cpu.defocus(&rgbd, &[q], &eye, lf36, &|_| {}).expect("lf36"))
        });
        if classical != Classical::Gather {
            g.bench_function(format!("gather_{tag}"), |b| {
                b.iter(|| {
                    Cpu.defocus(&rgbd, &[q], &eye, DefocusMethod::Gather, &|_| {})
                        .expect("gather")
                })
            });
        }
    }
    let c4r = net("c4r");
    let planes: Vec<Diopters> = c4r
        .arch()
        .task
        .planes()
        .expect("planes")
        .iter()
        .map(|&p| Diopters(p))
        .collect();
    g.bench_function("c4r_layers", |b| {
        b.iter(|| {
            let linear = linear_blend(&rgbd, &planes).expect("linear");
            c4r.refine_decompose(&rgbd, &linear).expect("refine")
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
