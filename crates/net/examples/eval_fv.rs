//! FV quality per foveal region against the sampled fraction, on simulator test seeds, beside
//! the interpolation-only baseline:
//! `cargo run --release -p dioptra-net --example eval_fv -- WEIGHTS [SCENES] [SIZE]`
//!
//! Each test scene's view grid is rendered (pinhole, 4x4 supersampled, over the 4 mm pupil as
//! in training); the input views are foveated with the renderer's log-polar masks at each
//! log-buffer scale S (every view its own offsets) for two gazes (the centre and a quarter
//! in from the top-left corner). Quality is PSNR / SSIM (the renderer's metrics) per region of
//! `FovealRegion` around the gaze, averaged over every output view, gaze and scene. The
//! baseline is the renderer's interpolation alone: each output view is the interpolated
//! nearest input view (no view synthesis). "LF %" is the sampled share of the whole light
//! field (sampled input pixels / (grid^2 x pixels)), as the paper's tables count it.

use dioptra_core::Rgbd;
use dioptra_net::fv::{foveate_view, grid_positions, view_mask};
use dioptra_net::train::data::DataSpec;
use dioptra_net::{load_net, Task};
use dioptra_render::metrics::{quality, quality_by_region};
use dioptra_sim::scene::{render_pinhole, Camera, Scene, Split};
use std::path::Path;

/// Sums of PSNR and SSIM per region (fovea, P1, P2, full) and their counts.
#[derive(Default, Clone)]
struct Acc {
    sum: [(f64, f64, usize); 4],
}

impl Acc {
    fn add(&mut self, k: usize, psnr: f64, ssim: f64) {
        let s = &mut self.sum[k];
        // An exact match (the baseline's own input view at full sampling) has infinite PSNR:
        // capped at 60 dB so the mean stays finite (stated under the table).
        *s = (s.0 + psnr.min(60.0), s.1 + ssim, s.2 + 1);
    }
    fn cell(&self, k: usize) -> String {
        let (p, s, n) = self.sum[k];
        if n == 0 {
            return "-".into();
        }
        format!("{:.2} / {:.4}", p / n as f64, s / n as f64)
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let weights = args
        .get(1)
        .ok_or("usage: eval_fv WEIGHTS [SCENES] [SIZE]")?;
    let scenes: u64 = args.get(2).map_or(Ok(4), |s| s.parse())?;
    let size: usize = args.get(3).map_or(Ok(128), |s| s.parse())?;
    let net = load_net(Some(Path::new(weights)), "fv")?;
    let Task::Fv { grid, .. } = net.arch().task else {
        return Err("not an FV network".into());
    };
    let inputs = net.arch().task.input_views();
    let spec = DataSpec {
        size,
        ..DataSpec::default()
    };
    let cam = Camera::square(spec.eye()?, size);
    let positions = grid_positions(grid, spec.pupil_mm * 1e-3);
    // The nearest input view of every output view (grid distance), for the baseline.
    let nearest: Vec<usize> = (0..grid * grid)
        .map(|o| {
            let (r, c) = ((o / grid) as i64, (o % grid) as i64);
            (0..inputs.len())
                .min_by_key(|&k| {
                    let (ri, ci) = ((inputs[k] / grid) as i64, (inputs[k] % grid) as i64);
                    (r - ri).pow(2) + (c - ci).pow(2)
                })
                .unwrap_or(0)
        })
        .collect();
    let scales: [Option<f32>; 4] = [None, Some(2.0), Some(3.0), Some(4.0)];
    let gazes = [
        [size as f32 * 0.5, size as f32 * 0.5],
        [size as f32 * 0.25, size as f32 * 0.25],
    ];
    // [novel views, input views] x scale.
    let mut net_acc = vec![vec![Acc::default(); scales.len()]; 2];
    let mut base_acc = vec![vec![Acc::default(); scales.len()]; 2];
    let mut fractions = vec![(0.0f64, 0usize); scales.len()];
    for i in 0..scenes {
        let seed = Split::Test.seed(i);
        let scene = Scene::generate(seed);
        let views = positions
            .iter()
            .map(|&p| {
                let (c, d) = render_pinhole(&scene, &cam, p, spec.supersample)?;
                Ok(Rgbd::new(c, d)?)
            })
            .collect::<Result<Vec<_>, Box<dyn std::error::Error>>>()?;
        for (si, scale) in scales.iter().enumerate() {
            for gaze in gazes {
                let fov = inputs
                    .iter()
                    .enumerate()
                    .map(|(k, &v)| {
                        let m = scale.map(|s| view_mask(gaze, size, s, k));
                        foveate_view(&views[v], m.as_ref())
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                let sampled: f64 = fov.iter().map(|f| f.fraction).sum();
                fractions[si].0 += sampled / (grid * grid) as f64;
                fractions[si].1 += 1;
                let out = net.synthesize_light_field(&fov)?;
                for (o, gt) in views.iter().enumerate() {
                    let base = &fov[nearest[o]].color;
                    let set = usize::from(inputs.contains(&o));
                    for (img, acc) in [
                        (&out[o], &mut net_acc[set][si]),
                        (base, &mut base_acc[set][si]),
                    ] {
                        for (k, (_, q)) in quality_by_region(img, &gt.color, gaze)?
                            .into_iter()
                            .enumerate()
                        {
                            if let Some(q) = q {
                                acc.add(k, q.psnr, q.ssim);
                            }
                        }
                        let q = quality(img, &gt.color, None)?;
                        acc.add(3, q.psnr, q.ssim);
                    }
                }
            }
        }
        eprintln!("scene {seed} done");
    }
    println!(
        "FV {grid}x{grid} from {} views, {size} px, {scenes} test scenes x 2 gazes; PSNR dB / SSIM (network | interpolation only)",
        inputs.len()
    );
    for (set, what) in [
        (
            0,
            "novel views (synthesised; baseline = nearest input view)",
        ),
        (1, "input views (foveated reconstruction)"),
    ] {
        println!("\n{what}");
        println!("| S | LF % sampled | fovea | periphery 1 | periphery 2 | full |");
        println!("|---|---|---|---|---|---|");
        for (si, scale) in scales.iter().enumerate() {
            let s = scale.map_or("every pixel".to_string(), |s| format!("{s}"));
            let f = 100.0 * fractions[si].0 / fractions[si].1.max(1) as f64;
            let (n, b) = (&net_acc[set][si], &base_acc[set][si]);
            let cells: Vec<String> = (0..4)
                .map(|k| format!("{} \\| {}", n.cell(k), b.cell(k)))
                .collect();
            println!("| {s} | {f:.2} | {} |", cells.join(" | "));
        }
    }
    println!("(per-image PSNR capped at 60 dB before averaging: exact copies are infinite)");
    Ok(())
}
