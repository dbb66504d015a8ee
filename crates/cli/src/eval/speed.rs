//! Speed against accuracy: every method and setting on test-split scenes, timed (median of
//! warm runs) and scored against thin-lens ground truth at each focus.

use std::time::Instant;

use anyhow::{Context, Result};
use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use dioptra_net::gpu::GpuNet;
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
    /// Timed warm runs (0: one cold run); `None` when not timed.
    pub runs: Option<usize>,
    /// C1R: the fraction of the error map's tiles the net ran on.
    pub tiles: Option<f64>,
    pub note: String,
}

pub const HEADER: [&str; 12] = [
    "method",
    "setting",
    "backend",
    "size",
    "scene",
    "focus_d",
    "time_ms",
    "psnr_db",
    "ssim",
    "runs",
    "tiles_run",
    "note",
];

/// What to run.
pub struct SpeedPlan {
    pub sizes: Vec<usize>,
    pub scenes: usize,
    pub runs: usize,
    /// Longest a measurement's timed runs may take together, ms.
    pub budget_ms: f64,
    /// Sizes the GPU backend runs at.
    pub gpu_sizes: Vec<usize>,
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
    pub fn units(&self, cpu: bool, gpu: bool) -> u64 {
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
        self.sizes
            .iter()
            .map(|s| {
                let backends = usize::from(cpu) + usize::from(gpu && self.gpu_sizes.contains(s));
                (self.scenes * (per_backend * backends + truth)) as u64
            })
            .sum()
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

/// How a measurement was timed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Timing {
    /// Median of the timed runs, ms.
    pub ms: f64,
    /// Timed runs after the warm-up; 0 when only the warm-up (cold) run was timed.
    pub runs: usize,
    /// The warm-up took longer than the budget: costlier settings are skipped.
    pub over_budget: bool,
}

impl Timing {
    pub fn note(&self, wanted: usize) -> String {
        match self.runs {
            0 => "timed once, cold: one run took longer than --budget-s".into(),
            r if r < wanted => {
                format!("timed {r} warm run(s), not {wanted}: {wanted} would exceed --budget-s")
            }
            _ => String::new(),
        }
    }
}

/// Runs `f` once to warm up, then `runs` times (fewer when `runs` of them would take longer
/// than `budget_ms`, at least one unless the warm-up alone took longer); returns the median
/// time and the last output.
fn timed<T>(runs: usize, budget_ms: f64, mut f: impl FnMut() -> Result<T>) -> Result<(Timing, T)> {
    let t = Instant::now();
    let mut out = f()?;
    let warm_ms = t.elapsed().as_secs_f64() * 1e3;
    if warm_ms > budget_ms {
        return Ok((
            Timing {
                ms: warm_ms,
                runs: 0,
                over_budget: true,
            },
            out,
        ));
    }
    let n = ((budget_ms / warm_ms.max(1e-3)).floor() as usize).clamp(1, runs.max(1));
    let mut times = Vec::with_capacity(n);
    for _ in 0..n {
        let t = Instant::now();
        out = f()?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok((
        Timing {
            ms: median(&times).unwrap_or(f64::NAN),
            runs: n,
            over_budget: false,
        },
        out,
    ))
}

/// `note` and `more` joined by "; ".
fn join(note: &str, more: &str) -> String {
    match (note.is_empty(), more.is_empty()) {
        (_, true) => note.to_string(),
        (true, false) => more.to_string(),
        (false, false) => format!("{note}; {more}"),
    }
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
    // Methods (per backend, size and scene) whose cheaper setting already overran the budget, and
    // the cost and time of the last setting measured, to predict the next one's.
    type Key = (&'static str, &'static str, usize, u64);
    let mut exhausted: std::collections::HashSet<Key> = Default::default();
    let mut last: std::collections::HashMap<Key, (f64, f64)> = Default::default();
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
                if backend.name() != "cpu" && !plan.gpu_sizes.contains(&size) {
                    continue;
                }
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
                        runs: None,
                        tiles: None,
                        note: String::new(),
                    };
                    let units = if m.multifocal() {
                        1
                    } else {
                        plan.defocus_foci.len() as u64
                    };
                    let key = (m.name(), backend.name(), size, seed);
                    if exhausted.contains(&key) {
                        rows.push(SpeedRow {
                            note: "skipped: a cheaper setting of this method already took longer than --budget-s for one run".into(),
                            ..base
                        });
                        bar.inc(units);
                        continue;
                    }
                    if let Some(&(cost, ms)) = last.get(&key) {
                        let predicted = ms * m.relative_cost() / cost;
                        if predicted > plan.budget_ms {
                            rows.push(SpeedRow {
                                note: format!(
                                    "skipped: predicted {:.0} s per run from a cheaper setting, over --budget-s",
                                    predicted / 1e3
                                ),
                                ..base
                            });
                            bar.inc(units);
                            continue;
                        }
                    }
                    let choice = if m.network() {
                        Some(nets.choose(m)?)
                    } else {
                        None
                    };
                    // The same weights uploaded to the GPU (once per setting, size and scene:
                    // a few hundred kB).
                    let gpu_net = match &choice {
                        Some(c) if backend.name() != "cpu" => {
                            match GpuNet::new(c.net.weights().clone(), None) {
                                Ok(n) => Some(n),
                                Err(e) => {
                                    rows.push(SpeedRow {
                                        note: format!("failed: no GPU network: {e}"),
                                        ..base
                                    });
                                    bar.inc(units);
                                    continue;
                                }
                            }
                        }
                        _ => None,
                    };
                    let net = match (&gpu_net, &choice) {
                        (Some(g), _) => Some(methods::NetOn::Gpu(g)),
                        (None, Some(c)) => Some(methods::NetOn::Cpu(c.net.as_ref())),
                        (None, None) => None,
                    };
                    let trained = choice.as_ref().is_none_or(|c| c.trained);
                    let note = choice.as_ref().map(|c| c.note.clone()).unwrap_or_default();
                    if m.multifocal() {
                        let r = timed(plan.runs, plan.budget_ms, || {
                            methods::decompose(*backend, m, net, &input, &targets, &eye)
                        });
                        if let Ok((t, _)) = &r {
                            if t.over_budget {
                                exhausted.insert(key);
                            }
                            last.insert(key, (m.relative_cost(), t.ms));
                        }
                        match r {
                            Ok((t, layers)) if trained => {
                                let seen =
                                    Cpu.retina_multifocal(&layers, &plan.multifocal_foci, &eye)?;
                                for (q, img) in plan.multifocal_foci.iter().zip(&seen) {
                                    let gt =
                                        truth_at(&truth, *q).context("missing ground truth")?;
                                    let qa = quality(img, gt, None)?;
                                    rows.push(SpeedRow {
                                        focus: Some(q.0),
                                        time_ms: Some(t.ms),
                                        psnr: Some(qa.psnr),
                                        ssim: Some(qa.ssim),
                                        runs: Some(t.runs),
                                        note: join(&note, &t.note(plan.runs)),
                                        ..base.clone()
                                    });
                                }
                            }
                            Ok((t, _)) => rows.push(SpeedRow {
                                time_ms: Some(t.ms),
                                runs: Some(t.runs),
                                note: join(&note, &t.note(plan.runs)),
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
                        if exhausted.contains(&key) {
                            rows.push(SpeedRow {
                                focus: Some(q.0),
                                note: "skipped: this setting already took longer than --budget-s for one run at another focus".into(),
                                ..base.clone()
                            });
                            continue;
                        }
                        let r = timed(plan.runs, plan.budget_ms, || {
                            methods::defocus(*backend, m, net, &input, q, &eye)
                        });
                        if let Ok((t, _)) = &r {
                            if t.over_budget {
                                exhausted.insert(key);
                            }
                            last.insert(key, (m.relative_cost(), t.ms));
                        }
                        let row = match r {
                            Ok((t, (img, tiles))) if trained => {
                                let gt = truth_at(&truth, q).context("missing ground truth")?;
                                let qa = quality(&img, gt, None)?;
                                SpeedRow {
                                    focus: Some(q.0),
                                    time_ms: Some(t.ms),
                                    psnr: Some(qa.psnr),
                                    ssim: Some(qa.ssim),
                                    runs: Some(t.runs),
                                    tiles,
                                    note: join(&note, &t.note(plan.runs)),
                                    ..base.clone()
                                }
                            }
                            Ok((t, (_, tiles))) => SpeedRow {
                                focus: Some(q.0),
                                time_ms: Some(t.ms),
                                runs: Some(t.runs),
                                tiles,
                                note: join(&note, &t.note(plan.runs)),
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

pub fn table(rows: &[SpeedRow]) -> Table {
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
            r.runs.map_or(String::new(), |n| n.to_string()),
            num(r.tiles, 3),
            r.note.clone(),
        ]);
    }
    t
}
