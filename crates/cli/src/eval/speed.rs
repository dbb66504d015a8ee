//! Speed against accuracy: every method and setting on test-split scenes, timed (median of
//! warm runs) and scored against thin-lens ground truth at each focus.

use std::time::Instant;

use anyhow::{Context, Result};
use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use dioptra_render::metrics::quality;
use dioptra_render::{Backend, Cpu};
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, Split};
use indicatif::ProgressBar;

use super::methods::{self, Method, MultifocalTargets, Nets};
use super::report::{median, num, Table};

/// One measurement: a method and setting on a backend, size, scene and focus.
#[derive(Debug, Clone)]
pub struct SpeedRow {
    pub method: Method,
    pub backend: &'static str,
    pub size: usize,
    pub seed: u64,
    pub focus: Option<f32>,
    pub time_ms: Option<f64>,
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    pub note: String,
}

pub const HEADER: [&str; 11] = [
    "method", "setting", "backend", "size", "scene", "focus_d", "time_ms", "psnr_db", "ssim",
    "runs", "note",
];

/// What to run.
pub struct SpeedPlan {
    pub sizes: Vec<usize>,
    pub scenes: usize,
    pub runs: usize,
    pub truth_samples: u32,
    /// Foci of the varifocal methods.
    pub defocus_foci: Vec<Diopters>,
    /// Foci the multifocal methods are fitted to and scored at (retinal images).
    pub multifocal_foci: Vec<Diopters>,
    pub methods: Vec<Method>,
}

impl SpeedPlan {
    /// Units of work for the progress bar: one per (scene, backend, method, focus) and one per
    /// ground-truth slice.
    pub fn units(&self, backends: usize) -> u64 {
        let per_backend: usize = self
            .methods
            .iter()
            .map(|m| {
                if m.multifocal() {
                    1
                } else {
                    self.defocus_foci.len()
                }
            })
            .sum();
        let truth = self.truth_foci().len();
        (self.sizes.len() * self.scenes * (per_backend * backends + truth)) as u64
    }

    /// Every focus ground truth is needed at (varifocal and multifocal foci together).
    pub fn truth_foci(&self) -> Vec<Diopters> {
        let mut all: Vec<Diopters> = self.multifocal_foci.clone();
        for q in &self.defocus_foci {
            if !all.iter().any(|a| (a.0 - q.0).abs() < 1e-4) {
                all.push(*q);
            }
        }
        all
    }
}

/// Runs `f` once to warm up, then `runs` times; returns the median time (ms) and the last
/// output.
fn timed<T>(runs: usize, mut f: impl FnMut() -> Result<T>) -> Result<(f64, T)> {
    let mut out = f()?;
    let mut times = Vec::with_capacity(runs);
    for _ in 0..runs {
        let t = Instant::now();
        out = f()?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok((median(&times).unwrap_or(f64::NAN), out))
}

fn truth_at(truth: &[(Diopters, RgbImage)], q: Diopters) -> Option<&RgbImage> {
    truth
        .iter()
        .find(|(f, _)| (f.0 - q.0).abs() < 1e-4)
        .map(|(_, i)| i)
}

/// Runs the plan on `backends`; rows in the order measured.
pub fn run(
    plan: &SpeedPlan,
    backends: &[&dyn Backend],
    nets: &Nets,
    bar: &ProgressBar,
) -> Result<Vec<SpeedRow>> {
    let eye = EyeModel::default();
    let mut rows = Vec::new();
    let truth_foci = plan.truth_foci();
    for &size in &plan.sizes {
        let cam = Camera::square(eye, size);
        for s in 0..plan.scenes {
            let seed = Split::Test.seed(s as u64);
            let scene = Scene::generate(seed);
            bar.set_message(format!("{size}px scene {seed}: ground truth"));
            let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 4)
                .with_context(|| format!("cannot render test scene {seed}"))?;
            let input = Rgbd::new(color, depth)?;
            let mut truth = Vec::with_capacity(truth_foci.len());
            for &q in &truth_foci {
                truth.push((q, render_thin_lens(&scene, &cam, q, plan.truth_samples)?));
                bar.inc(1);
            }
            let stack: Vec<RgbImage> = plan
                .multifocal_foci
                .iter()
                .filter_map(|&q| truth_at(&truth, q).cloned())
                .collect();
            let linear_init = Cpu.linear_blend(&input, &methods::planes())?;
            let targets = MultifocalTargets {
                stack: &stack,
                foci: &plan.multifocal_foci,
                linear_init: &linear_init,
            };
            for backend in backends {
                for &m in &plan.methods {
                    bar.set_message(format!(
                        "{size}px scene {seed}: {} on {}",
                        m.label(),
                        backend.name()
                    ));
                    let base = SpeedRow {
                        method: m,
                        backend: backend.name(),
                        size,
                        seed,
                        focus: None,
                        time_ms: None,
                        psnr: None,
                        ssim: None,
                        note: String::new(),
                    };
                    let units = if m.multifocal() {
                        1
                    } else {
                        plan.defocus_foci.len() as u64
                    };
                    if m.network() && backend.name() != "cpu" {
                        rows.push(SpeedRow {
                            note: "no GPU inference: dioptra-net runs on the CPU".into(),
                            ..base
                        });
                        bar.inc(units);
                        continue;
                    }
                    let choice = if m.network() {
                        Some(nets.choose(m)?)
                    } else {
                        None
                    };
                    let net = choice.as_ref().map(|c| c.net.as_ref());
                    let trained = choice.as_ref().is_none_or(|c| c.trained);
                    let note = choice.as_ref().map(|c| c.note.clone()).unwrap_or_default();
                    if m.multifocal() {
                        let r = timed(plan.runs, || {
                            methods::decompose(*backend, m, net, &input, &targets, &eye)
                        });
                        match r {
                            Ok((ms, layers)) if trained => {
                                let seen =
                                    Cpu.retina_multifocal(&layers, &plan.multifocal_foci, &eye)?;
                                for (q, img) in plan.multifocal_foci.iter().zip(&seen) {
                                    let t = truth_at(&truth, *q).context("missing ground truth")?;
                                    let qa = quality(img, t, None)?;
                                    rows.push(SpeedRow {
                                        focus: Some(q.0),
                                        time_ms: Some(ms),
                                        psnr: Some(qa.psnr),
                                        ssim: Some(qa.ssim),
                                        note: note.clone(),
                                        ..base.clone()
                                    });
                                }
                            }
                            Ok((ms, _)) => rows.push(SpeedRow {
                                time_ms: Some(ms),
                                note,
                                ..base
                            }),
                            Err(e) => rows.push(SpeedRow {
                                note: format!("failed: {e:#}"),
                                ..base
                            }),
                        }
                        bar.inc(1);
                        continue;
                    }
                    // Varifocal: one frame per focus. An untrained net is timed at one focus.
                    let foci: Vec<Diopters> = if trained {
                        plan.defocus_foci.clone()
                    } else {
                        vec![Diopters(1.0)]
                    };
                    for q in foci {
                        let r = timed(plan.runs, || {
                            methods::defocus(*backend, m, net, &input, q, &eye)
                        });
                        let row = match r {
                            Ok((ms, img)) if trained => {
                                let t = truth_at(&truth, q).context("missing ground truth")?;
                                let qa = quality(&img, t, None)?;
                                SpeedRow {
                                    focus: Some(q.0),
                                    time_ms: Some(ms),
                                    psnr: Some(qa.psnr),
                                    ssim: Some(qa.ssim),
                                    note: note.clone(),
                                    ..base.clone()
                                }
                            }
                            Ok((ms, _)) => SpeedRow {
                                focus: Some(q.0),
                                time_ms: Some(ms),
                                note: note.clone(),
                                ..base.clone()
                            },
                            Err(e) => SpeedRow {
                                focus: Some(q.0),
                                note: format!("failed: {e:#}"),
                                ..base.clone()
                            },
                        };
                        rows.push(row);
                    }
                    bar.inc(units);
                }
            }
        }
    }
    Ok(rows)
}

pub fn table(rows: &[SpeedRow], runs: usize) -> Table {
    let mut t = Table::new(&HEADER);
    for r in rows {
        t.push(vec![
            r.method.name().into(),
            r.method.setting(),
            r.backend.into(),
            r.size.to_string(),
            r.seed.to_string(),
            r.focus.map_or(String::new(), |f| format!("{f:.2}")),
            num(r.time_ms, 3),
            num(r.psnr, 3),
            num(r.ssim, 5),
            if r.time_ms.is_some() {
                runs.to_string()
            } else {
                String::new()
            },
            r.note.clone(),
        ]);
    }
    t
}
