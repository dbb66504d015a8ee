//! The rig's CPU stages per content frame at a panel's size, as `dioptra eval --suite panel`
//! times them (the procedural scene's ray cast of one eye, one eye's view synthesised from
//! one RGB-D, both eyes packed into 8-bit sRGB), each run `frames` times: for profiling and
//! quick before/after looks without the suite's rig runs.
//!
//!   cargo run --release -p dioptra-rig --example panel_cpu_stages -- [width] [height] [fov_deg] [frames]
//!
//! Prints each stage's median and fastest wall time.

use dioptra_core::{EyeModel, Rgbd};
use dioptra_render::timing::wall_times_ms;
use dioptra_render::views::{synthesize_rgbd_view, RgbdView};
use dioptra_rig::display::blit::pack_rgba8_srgb;
use dioptra_sim::scene::{render_pinhole, Camera, Scene};

/// The panel suite's scene seed, rays per pixel and interpupillary distance (metres).
const SEED: u64 = 1_000_000;
const SAMPLES: usize = 2;
const IPD_M: f32 = 0.063;

fn main() {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let num = |i: usize, d: f32| a.get(i).map_or(d, |s| s.parse().expect("a number"));
    let (w, h) = (num(0, 960.0) as usize, num(1, 1080.0) as usize);
    let eye = EyeModel {
        fov_horizontal_deg: num(2, 20.0),
        ..EyeModel::default()
    }
    .with_width(w as u32);
    let frames = (num(3, 5.0) as usize).max(1);
    dioptra_render::alloc::keep_freed_memory();
    let scene = Scene::generate(SEED);
    let cam = Camera::new(eye, w, h);
    let time = |name: &str, f: &mut dyn FnMut()| {
        let (t, ()) = wall_times_ms(frames, f);
        println!(
            "{name} {w}x{h}: median {:.1} ms, fastest {:.1} ms ({frames} runs)",
            t[t.len() / 2],
            t[0]
        );
    };
    let mut input = None;
    time("scene ray cast (one eye)", &mut || {
        let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], SAMPLES).expect("cast");
        input = Some(Rgbd::new(c, d).expect("rgbd"));
    });
    let input = input.expect("cast");
    let inputs = [RgbdView {
        position: [0.0, 0.0],
        rgbd: input.clone(),
    }];
    let mut view = None;
    time("eye view from one RGB-D", &mut || {
        view = Some(synthesize_rgbd_view(&inputs, [0.5 * IPD_M, 0.0], &eye).expect("view"));
    });
    let mut bytes = Vec::new();
    time("pack both eyes (8-bit sRGB)", &mut || {
        for _ in 0..2 {
            pack_rgba8_srgb(&input.color, &mut bytes);
            std::hint::black_box(&bytes);
        }
    });
}
