//! The pyramid method against gather and the thin-lens truth on sim test scenes, at the test
//! suite's 256 px over 20 degrees and at a panel's pixel density (256 px over 5 degrees: 51
//! px/deg, as a 960 px panel over 19 degrees), with each method's time.
//!
//!   cargo run --release -p dioptra-render --example pyramid_accuracy -- [size] [scenes] [spp]

use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::gather::gather;
use dioptra_render::metrics::psnr;
use dioptra_render::pyramid::pyramid;
use dioptra_sim::scene::{render_pinhole, render_thin_lens_stack, Camera, Scene, Split};
use std::time::Instant;

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .map(|a| a.parse().expect("numbers"))
        .collect();
    let size = args.first().copied().unwrap_or(256);
    let scenes = args.get(1).copied().unwrap_or(2) as u64;
    let spp = args.get(2).copied().unwrap_or(64) as u32;
    let foci = [Diopters(0.1), Diopters(1.0), Diopters(2.5), Diopters(4.0)];
    for fov in [20.0f32, 5.0] {
        let eye = EyeModel {
            fov_horizontal_deg: fov,
            ..EyeModel::default()
        };
        let cam = Camera::square(eye, size);
        let (mut pg, mut pp, mut gp) = (vec![], vec![], vec![]);
        let (mut tg, mut tp) = (0.0, 0.0);
        for s in 0..scenes {
            let scene = Scene::generate(Split::Test.seed(s));
            let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 6).expect("pinhole");
            let input = Rgbd::new(color, depth).expect("rgbd");
            let truth = render_thin_lens_stack(&scene, &cam, &foci, spp, |_| {}).expect("truth");
            for (k, &q) in foci.iter().enumerate() {
                let t = Instant::now();
                let g = gather(&input, q, &eye).expect("gather");
                tg += t.elapsed().as_secs_f64();
                let t = Instant::now();
                let p = pyramid(&input, q, &eye).expect("pyramid");
                tp += t.elapsed().as_secs_f64();
                let a = psnr(&g, &truth[k], None).unwrap();
                let b = psnr(&p, &truth[k], None).unwrap();
                let c = psnr(&p, &g, None).unwrap();
                println!(
                    "fov {fov:4.1} scene {s} focus {:.1}: gather {a:.2} dB, pyramid {b:.2} dB ({:+.2}), pyramid vs gather {c:.1} dB",
                    q.0,
                    b - a
                );
                pg.push(a);
                pp.push(b);
                gp.push(c);
            }
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        println!(
            "fov {fov}: mean gather {:.2} dB, pyramid {:.2} dB ({:+.2}); worst difference {:+.2}; time gather {:.0} ms, pyramid {:.0} ms per frame",
            mean(&pg),
            mean(&pp),
            mean(&pp) - mean(&pg),
            pp.iter().zip(&pg).map(|(a, b)| a - b).fold(f64::INFINITY, f64::min),
            1e3 * tg / pg.len() as f64,
            1e3 * tp / pg.len() as f64
        );
    }
}
