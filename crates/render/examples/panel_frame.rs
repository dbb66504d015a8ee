//! Renders a sim test scene at a panel's size with one defocus method, timing each frame: for
//! profiling (`perf record`) and quick looks; the figures to report come from the criterion
//! bench (`benches/panel.rs`).
//!
//!   cargo run --release -p dioptra-render --example panel_frame -- \
//!       [pyramid|foveated|gather] [width] [height] [fov_deg] [focus_D] [frames]

use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::foveated::{foveated, Foveation};
use dioptra_render::gather::gather;
use dioptra_render::pyramid::pyramid;
use dioptra_sim::scene::{render_pinhole, Camera, Scene, Split};
use std::time::Instant;

fn main() {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let method = a.first().map_or("pyramid", |s| s.as_str());
    let num = |i: usize, d: f32| a.get(i).map_or(d, |s| s.parse().expect("a number"));
    let (w, h) = (num(1, 960.0) as usize, num(2, 1080.0) as usize);
    let eye = EyeModel {
        fov_horizontal_deg: num(3, 20.0),
        ..EyeModel::default()
    };
    let q = Diopters(num(4, 1.0));
    let frames = num(5, 5.0) as usize;
    dioptra_render::alloc::keep_freed_memory();
    let cam = Camera::new(eye, w, h);
    let scene = Scene::generate(Split::Test.seed(0));
    let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], 1).expect("scene");
    let input = Rgbd::new(c, d).expect("rgbd");
    let gaze = [0.5 * w as f32, 0.5 * h as f32];
    for _ in 0..frames {
        let t = Instant::now();
        let img = match method {
            "gather" => gather(&input, q, &eye).expect("gather"),
            "foveated" => {
                foveated(&input, q, &eye, &Foveation::at(gaze))
                    .expect("foveated")
                    .image
            }
            _ => pyramid(&input, q, &eye).expect("pyramid"),
        };
        std::hint::black_box(img);
        println!(
            "{method} {w}x{h} {} deg at {} D: {:.1} ms",
            eye.fov_horizontal_deg,
            q.0,
            t.elapsed().as_secs_f64() * 1e3
        );
    }
}
