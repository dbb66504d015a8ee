//! Defocus at a prototype's panel size (issue 54), CPU backend: gather, the pyramid method and
//! the pyramid foveated around the centre (5 degrees at full resolution), per eye at
//! 960 x 1080, 1440 x 1600 and 2160 x 2160, over 20 and 90 degrees horizontal field, a sim
//! test scene focused at 1 D. Each figure is one eye's frame; a binocular rig renders two.
//!
//!   cargo bench -p dioptra-render --bench panel
//!   DIOPTRA_PANEL_SIZES=960x1080,1440x1600 cargo bench -p dioptra-render --bench panel
//!
//! Gather is skipped where the planner predicts one frame over `GATHER_LIMIT_MS` (its cost
//! grows with the blur's area: seconds per frame at 2160 px over 20 degrees); the prediction
//! is printed instead.

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::foveated::{foveated, Foveation};
use dioptra_render::gather::gather;
use dioptra_render::planner::{predict_frame_cost, FrameSpec};
use dioptra_render::pyramid::pyramid;
use dioptra_render::DefocusMethod;
use dioptra_sim::scene::{render_pinhole, Camera, Scene, Split};
use std::hint::black_box;
use std::time::Duration;

const SIZES: [(usize, usize); 3] = [(960, 1080), (1440, 1600), (2160, 2160)];
const FIELDS_DEG: [f32; 2] = [20.0, 90.0];
const FOCUS: Diopters = Diopters(1.0);
/// Gather runs only where one frame is predicted under this, ms.
const GATHER_LIMIT_MS: f64 = 3000.0;

/// The sizes to run: `DIOPTRA_PANEL_SIZES` (`WxH,WxH`), else all of [`SIZES`].
fn sizes() -> Vec<(usize, usize)> {
    let Ok(list) = std::env::var("DIOPTRA_PANEL_SIZES") else {
        return SIZES.to_vec();
    };
    list.split(',')
        .map(|s| {
            let (w, h) = s
                .trim()
                .split_once('x')
                .unwrap_or_else(|| panic!("DIOPTRA_PANEL_SIZES: {s:?} is not WxH"));
            let n = |v: &str| {
                v.parse::<usize>()
                    .unwrap_or_else(|_| panic!("DIOPTRA_PANEL_SIZES: {s:?} is not WxH"))
            };
            (n(w), n(h))
        })
        .collect()
}

fn benches(c: &mut Criterion) {
    // As the dioptra binary runs (see dioptra_render::alloc).
    dioptra_render::alloc::keep_freed_memory();
    let scene = Scene::generate(Split::Test.seed(0));
    for (w, h) in sizes() {
        for fov_deg in FIELDS_DEG {
            let eye = EyeModel {
                fov_horizontal_deg: fov_deg,
                ..EyeModel::default()
            };
            let cam = Camera::new(eye, w, h);
            let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 1).expect("scene");
            let input = Rgbd::new(color, depth).expect("same size");
            let fov = Foveation::at([0.5 * w as f32, 0.5 * h as f32]);
            let mut g = c.benchmark_group(format!("{w}x{h}_{fov_deg}deg"));
            g.sample_size(10).measurement_time(Duration::from_secs(4));
            let gather_ms = predict_frame_cost(&FrameSpec {
                method: DefocusMethod::Gather,
                cores: 2,
                ..FrameSpec::new(w, h, eye)
            })
            .map_or(f64::INFINITY, |c| c.wall_ms);
            if gather_ms <= GATHER_LIMIT_MS {
                g.bench_function("gather", |b| {
                    b.iter(|| gather(black_box(&input), FOCUS, &eye).expect("gather"))
                });
            } else {
                eprintln!(
                    "{w}x{h} over {fov_deg} deg: gather skipped, predicted {:.1} s a frame on 2 cores",
                    gather_ms * 1e-3
                );
            }
            g.bench_function("pyramid", |b| {
                b.iter(|| pyramid(black_box(&input), FOCUS, &eye).expect("pyramid"))
            });
            g.bench_function("pyramid_foveated_5deg", |b| {
                b.iter(|| foveated(black_box(&input), FOCUS, &eye, &fov).expect("foveated"))
            });
            g.finish();
        }
    }
}

criterion_group!(panel, benches);
criterion_main!(panel);
