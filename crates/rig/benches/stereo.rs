//! A binocular frame against a mono one, on the CPU backend: each eye's views made from a
//! content frame (the scene ray cast at each eye, or synthesised from one RGB-D: once per
//! content frame), and one eye's render against a mono render per method, at 256 and 512 px.
//! A stereo frame costs its two eye renders plus, on each new content frame, its views. The
//! light-field panel from a 3 x 3 view grid (`content.views`) is timed beside them.
//! `cargo bench -p dioptra-rig --bench stereo`

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_core::{Diopters, Side, Timestamp};
use dioptra_rig::config::{Method, Mode, RigConfig, EXAMPLE_SIM_BINOCULAR_RIG};
use dioptra_rig::content::stereo::EyeViews;
use dioptra_rig::content::{scene::Pacing, ContentFrame, ContentView};
use dioptra_rig::render::rgbd::RgbdRenderer;
use dioptra_sched::RenderMethod;

fn config(size: usize) -> RigConfig {
    let text = EXAMPLE_SIM_BINOCULAR_RIG
        .replace("width = 96", &format!("width = {size}"))
        .replace("height = 96", &format!("height = {size}"))
        + "\n[content]\nanimate = false\n";
    RigConfig::parse(&text).unwrap()
}

/// Each iteration a content frame the renderer and the views have not seen: nothing cached.
static NUMBER: AtomicU64 = AtomicU64::new(1);

fn fresh(frame: &ContentFrame) -> ContentFrame {
    ContentFrame {
        number: NUMBER.fetch_add(1, Ordering::Relaxed),
        ..frame.clone()
    }
}

fn stereo(c: &mut Criterion) {
    let mut g = c.benchmark_group("stereo");
    g.sample_size(10).measurement_time(Duration::from_secs(4));
    for size in [256usize, 512] {
        let cfg = config(size);
        let content = dioptra_rig::content::open(
            &cfg.content,
            &cfg.display,
            &cfg.eye,
            &cfg.api,
            Pacing::Simulated,
        )
        .unwrap();
        let scene_frame = content.poll(Timestamp::ZERO).unwrap();
        let mono = ContentFrame::new(0, scene_frame.rgbd.clone());
        let views = EyeViews::new(&cfg.eye, &cfg.display).unwrap();
        // The rig's scene frames bring their eyes' views (cast on its worker, as here).
        let scene_only = ContentFrame {
            eyes: None,
            ..scene_frame.clone()
        };
        g.bench_function(
            format!("{size} px eye views: scene ray cast, both eyes"),
            |b| b.iter(|| views.of(&fresh(&scene_only)).unwrap()),
        );
        g.bench_function(
            format!("{size} px eye views: synthesised from one RGB-D, both eyes"),
            |b| b.iter(|| views.of(&fresh(&mono)).unwrap()),
        );
        let ([left, _], _) = views.of(&scene_frame).unwrap();
        let renderer = RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics).unwrap();
        for (mode, method) in [
            (Mode::Varifocal, RenderMethod::Gather),
            (Mode::Multifocal, RenderMethod::Linear),
            (Mode::Multifocal, RenderMethod::Spectral),
            (Mode::Lightfield, RenderMethod::Views),
        ] {
            let eye = scene_frame.for_eye(Side::Left, left.clone());
            for (what, frame) in [("mono", &mono), ("one eye", &eye)] {
                g.bench_function(
                    format!("{size} px {} {}: {what}", mode.as_str(), method.as_str()),
                    |b| {
                        b.iter(|| {
                            renderer
                                .render_frame(
                                    &fresh(frame),
                                    mode,
                                    Method(method),
                                    Diopters(1.0),
                                    None,
                                    false,
                                )
                                .unwrap()
                        })
                    },
                );
            }
        }
        // Light-field content (`content.views = 3`): the panel from a 3 x 3 grid of the
        // scene's pinhole views over the panel's 4 mm, against the one RGB-D above.
        let scene = scene_frame.scene.clone().unwrap();
        let cam = dioptra_rig::content::scene::camera(&cfg.eye, &cfg.display).unwrap();
        let grid: std::sync::Arc<[ContentView]> =
            dioptra_sim::scene::light_field_positions(3, 0.004)
                .unwrap()
                .into_iter()
                .map(|position| {
                    let (c, d) =
                        dioptra_sim::scene::render_pinhole(&scene, &cam, position, 1).unwrap();
                    ContentView {
                        eye: None,
                        position,
                        rgbd: std::sync::Arc::new(dioptra_core::Rgbd::new(c, d).unwrap()),
                    }
                })
                .collect();
        let gridded = ContentFrame {
            views: Some(grid.clone()),
            ..ContentFrame::new(0, grid[4].rgbd.clone())
        };
        g.bench_function(
            format!("{size} px lightfield views: 3 x 3 view grid, mono"),
            |b| {
                b.iter(|| {
                    renderer
                        .render_frame(
                            &fresh(&gridded),
                            Mode::Lightfield,
                            Method(RenderMethod::Views),
                            Diopters(1.0),
                            None,
                            false,
                        )
                        .unwrap()
                })
            },
        );
    }
    g.finish();
}

criterion_group!(benches, stereo);
criterion_main!(benches);
