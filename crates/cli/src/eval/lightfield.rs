//! Light fields from sparse RGB-D views (issue 41): the classical synthesis of a 9 x 9 light
//! field from 5 or 9 of its views, and the shipped C5R's refinement of it, scored on the novel views against the test scenes' own
//! ray-cast views, beside the nearest input shown in place of each novel view; its time on
//! each backend and the GPU's largest difference from the CPU; and the foveated light field
//! (FV's per-view log-polar samples, the rest filled within each view or across views) per
//! foveal region, against the
//! truth and against the full synthesis, with the fraction of the rays kept.

use std::time::Instant;

use anyhow::{Context, Result};
use dioptra_core::{EyeModel, RgbImage, Rgbd};
use dioptra_net::fv::{foveate_light_field, region_psnr, Fill};
use dioptra_net::gpu::GpuNet;
use dioptra_net::refine::refine_light_field;
use dioptra_net::{CpuNet, Task};
use dioptra_render::views::{RgbdView, WarpErrors};
use dioptra_render::Backend;
use dioptra_sim::scene::{light_field_positions, render_pinhole, Camera, Scene, Split};
use indicatif::ProgressBar;

use super::report::{num, Table};

/// What the light-field part measures.
pub struct LightFieldPlan {
    /// Pixels per side of a view.
    pub size: usize,
    /// Test scenes.
    pub scenes: usize,
    /// Views per side of the light field.
    pub grid: usize,
    /// Side of the square the views span, metres.
    pub span: f32,
    /// Input view counts (5, 9).
    pub inputs: Vec<usize>,
    /// Log-buffer scales of the foveated rows.
    pub foveate: Vec<f32>,
}

impl LightFieldPlan {
    /// Progress units: per scene, its truth, then each input count on each backend, once
    /// classical and once refined when a C5R net runs.
    pub fn units(&self, backends: usize, refine: bool) -> u64 {
        let runs = if refine { 2 } else { 1 };
        (self.scenes * (1 + self.inputs.len() * backends * runs)) as u64
    }
}

/// One synthesis: a scene, an input count, a backend (or the nearest-input baseline).
pub struct LightFieldRow {
    pub method: &'static str,
    pub backend: &'static str,
    pub inputs: usize,
    pub seed: u64,
    /// Mean over the novel views (of the mean squared error), dB.
    pub psnr: f64,
    pub time_ms: Option<f64>,
    /// Largest |GPU - CPU| over every view and channel (GPU rows).
    pub max_diff: Option<f64>,
}

/// One foveated light field: a scene, a log-buffer scale, per region the PSNR against the
/// truth and against the full synthesis (novel views), and the fraction of the rays kept.
pub struct FoveatedRow {
    pub seed: u64,
    pub scale: Option<f32>,
    /// How the unsampled rays were filled: "within" each view, or "across" views (empty for
    /// the full synthesis).
    pub fill: &'static str,
    pub fraction: f64,
    pub truth: Vec<(&'static str, f64)>,
    pub full: Vec<(&'static str, f64)>,
}

/// PSNR of `views` against `truth` over the novel views (`novel`), of their mean squared
/// error.
fn novel_psnr(views: &[RgbImage], truth: &[RgbImage], novel: &[usize]) -> Result<f64> {
    let mut mse = 0.0;
    for &k in novel {
        mse += 10f64.powf(-dioptra_render::metrics::psnr(&views[k], &truth[k], None)? / 10.0);
    }
    Ok(-10.0 * (mse / novel.len() as f64).log10())
}

/// `c5r`: the refinement net whose rows (`refine`) sit beside the classical ones: the warp and
/// its error map on the CPU, the net on each backend (as `dioptra lightfield --method refine`).
pub fn run(
    plan: &LightFieldPlan,
    backends: &[&dyn Backend],
    c5r: Option<&CpuNet>,
    bar: &ProgressBar,
) -> Result<(Vec<LightFieldRow>, Vec<FoveatedRow>)> {
    // The net on the GPU, once (a GPU backend that cannot take it gets no refine row).
    let gpu_net = match c5r {
        Some(n) if backends.iter().any(|b| b.name() == "gpu") => {
            Some(GpuNet::new(n.weights().clone(), None).context("the C5R net on the GPU")?)
        }
        _ => None,
    };
    let eye = EyeModel::default();
    let cam = Camera::square(eye, plan.size);
    let positions = light_field_positions(plan.grid, plan.span)?;
    let centre = [plan.size as f32 * 0.5; 2];
    let (mut rows, mut foveated) = (Vec::new(), Vec::new());
    for s in 0..plan.scenes {
        let seed = Split::Test.seed(s as u64);
        let scene = Scene::generate(seed);
        bar.set_message(format!("light field {}px scene {seed}: truth", plan.size));
        let truth: Vec<(RgbImage, Rgbd)> = positions
            .iter()
            .map(|&p| {
                let (color, depth) = render_pinhole(&scene, &cam, p, 2)?;
                let rgbd = Rgbd::new(color.clone(), depth)?;
                Ok((color, rgbd))
            })
            .collect::<Result<_>>()
            .with_context(|| format!("cannot render test scene {seed}'s light field"))?;
        let truth_images: Vec<RgbImage> = truth.iter().map(|(c, _)| c.clone()).collect();
        bar.inc(1);
        for &k in &plan.inputs {
            let picks = Task::C5 {
                views: k,
                grid: plan.grid,
            }
            .input_views();
            let novel: Vec<usize> = (0..positions.len())
                .filter(|i| !picks.contains(i))
                .collect();
            let inputs: Vec<RgbdView> = picks
                .iter()
                .map(|&i| RgbdView {
                    position: positions[i],
                    rgbd: truth[i].1.clone(),
                })
                .collect();
            // The baseline: each novel view shown as its nearest input.
            let nearest: Vec<RgbImage> = positions
                .iter()
                .map(|p| {
                    let d = |i: usize| (positions[i][0] - p[0]).hypot(positions[i][1] - p[1]);
                    let best = picks.iter().copied().min_by(|&a, &b| d(a).total_cmp(&d(b)));
                    truth_images[best.unwrap_or(0)].clone()
                })
                .collect();
            rows.push(LightFieldRow {
                method: "nearest input",
                backend: "",
                inputs: k,
                seed,
                psnr: novel_psnr(&nearest, &truth_images, &novel)?,
                time_ms: None,
                max_diff: None,
            });
            // Classical on each backend, then (when a C5R ships) refined on each; the GPU's
            // views compared with the CPU's of the same method.
            let mut cpu_views: Option<Vec<RgbImage>> = None;
            for method in ["classical", "refine"] {
                let net = match (method, c5r) {
                    ("classical", _) => None,
                    (_, Some(n)) => Some(n),
                    (_, None) => break,
                };
                let mut cpu_of_method: Option<Vec<RgbImage>> = None;
                for backend in backends {
                    bar.set_message(format!(
                        "light field {}px scene {seed}: {k} inputs, {method} on {}",
                        plan.size,
                        backend.name()
                    ));
                    let t = Instant::now();
                    let lf = match net {
                        None => backend.synthesize_light_field(
                            &inputs,
                            plan.grid,
                            plan.span,
                            &eye,
                            &|_| {},
                        )?,
                        Some(net) => {
                            let refine = |v: &Rgbd, e: &WarpErrors| match (&gpu_net, backend.name())
                            {
                                (Some(g), "gpu") => g.refine_view(v, e),
                                _ => net.refine_view(v, e),
                            };
                            refine_light_field(
                                &inputs,
                                plan.grid,
                                plan.span,
                                &eye,
                                &refine,
                                &|_| {},
                            )?
                        }
                    };
                    let time_ms = t.elapsed().as_secs_f64() * 1e3;
                    let views: Vec<RgbImage> = lf.into_iter().map(|v| v.image).collect();
                    let max_diff = match (&cpu_of_method, backend.name()) {
                        (Some(c), "gpu") => Some(max_difference(c, &views)),
                        _ => None,
                    };
                    rows.push(LightFieldRow {
                        method,
                        backend: backend.name(),
                        inputs: k,
                        seed,
                        psnr: novel_psnr(&views, &truth_images, &novel)?,
                        time_ms: Some(time_ms),
                        max_diff,
                    });
                    if backend.name() == "cpu" {
                        cpu_of_method = Some(views);
                    }
                    bar.inc(1);
                }
                if method == "classical" {
                    cpu_views = cpu_of_method;
                }
            }
            // Foveation of the CPU's full synthesis from the most inputs (novel views only).
            if let (Some(full), true) = (&cpu_views, Some(&k) == plan.inputs.iter().max()) {
                let pick = |v: &[RgbImage]| novel.iter().map(|&i| v[i].clone()).collect::<Vec<_>>();
                let (full_novel, truth_novel) = (pick(full), pick(&truth_images));
                foveated.push(FoveatedRow {
                    seed,
                    scale: None,
                    fill: "",
                    fraction: 1.0,
                    truth: region_psnr(&full_novel, &truth_novel, centre)?,
                    full: Vec::new(),
                });
                // Each view's depth from the same warp, for the fill across views.
                let depths = dioptra_render::views::light_field_depths(&inputs, &positions, &eye)?;
                for &scale in &plan.foveate {
                    for (name, fill) in [
                        ("within", Fill::WithinViews),
                        (
                            "across",
                            Fill::AcrossViews {
                                depths: &depths,
                                positions: &positions,
                                eye: &eye,
                            },
                        ),
                    ] {
                        let (views, fraction) = foveate_light_field(full, centre, scale, fill)?;
                        let views = pick(&views);
                        foveated.push(FoveatedRow {
                            seed,
                            scale: Some(scale),
                            fill: name,
                            fraction,
                            truth: region_psnr(&views, &truth_novel, centre)?,
                            full: region_psnr(&views, &full_novel, centre)?,
                        });
                    }
                }
            }
        }
    }
    Ok((rows, foveated))
}

/// The largest |a - b| over every view, channel and pixel.
fn max_difference(a: &[RgbImage], b: &[RgbImage]) -> f64 {
    a.iter()
        .zip(b)
        .flat_map(|(x, y)| x.channels.iter().zip(&y.channels))
        .flat_map(|(p, q)| p.data().iter().zip(q.data()))
        .map(|(u, v)| f64::from((u - v).abs()))
        .fold(0.0, f64::max)
}

pub const HEADER: [&str; 7] = [
    "method",
    "backend",
    "inputs",
    "seed",
    "psnr_novel_db",
    "time_ms",
    "max_abs_diff_from_cpu",
];

pub fn table(rows: &[LightFieldRow]) -> Table {
    let mut t = Table::new(&HEADER);
    for r in rows {
        t.push(vec![
            r.method.into(),
            r.backend.into(),
            r.inputs.to_string(),
            r.seed.to_string(),
            num(Some(r.psnr), 3),
            num(r.time_ms, 1),
            r.max_diff.map_or(String::new(), |d| format!("{d:e}")),
        ]);
    }
    t
}

pub const FOVEATED_HEADER: [&str; 10] = [
    "seed",
    "scale",
    "fill",
    "rays_kept",
    "fovea_db",
    "periphery1_db",
    "periphery2_db",
    "fovea_vs_full_db",
    "periphery1_vs_full_db",
    "periphery2_vs_full_db",
];

pub fn foveated_table(rows: &[FoveatedRow]) -> Table {
    let mut t = Table::new(&FOVEATED_HEADER);
    let region =
        |v: &[(&str, f64)], name: &str| num(v.iter().find(|(n, _)| *n == name).map(|(_, p)| *p), 3);
    for r in rows {
        let mut row = vec![
            r.seed.to_string(),
            r.scale.map_or("full".into(), |s| format!("{s}")),
            if r.fill.is_empty() {
                "-".into()
            } else {
                r.fill.into()
            },
            format!("{:.5}", r.fraction),
        ];
        for v in [&r.truth, &r.full] {
            for name in ["fovea", "periphery 1", "periphery 2"] {
                row.push(region(v, name));
            }
        }
        t.push(row);
    }
    t
}
