//! The rendering half of the failure-case suite: every method on the scenes of
//! `dioptra_sim::scene::failure`, scored overall and inside each scene's failure region, for
//! temporal stability over a short animated sequence, and for finite, in-range output.

use anyhow::{Context, Result};
use dioptra_core::{Diopters, Plane, RgbImage, Rgbd};
use dioptra_render::metrics::{quality, Quality};
use dioptra_render::views::{synthesize_view, RgbdView};
use dioptra_render::{Backend, Cpu};
use dioptra_sim::scene::failure::{
    disoccluded, failure_cases, novel_views, sparse_views, FailureCase,
};
use dioptra_sim::scene::{render_pinhole, render_thin_lens, render_thin_lens_stack};
use indicatif::ProgressBar;

use super::methods::{self, out_of_range, Method, MultifocalTargets, Nets};
use super::report::{num, Table};

/// Settings of the failure suite.
pub struct FailurePlan {
    pub size: usize,
    pub truth_samples: u32,
    /// Frames of the animated sequence (at least 2).
    pub frames: usize,
    /// Foci of the ground-truth stack optimized blending fits (the case's focus is added).
    pub stack_foci: Vec<Diopters>,
    pub optimized_iterations: usize,
}

/// One method on one case.
#[derive(Debug, Clone)]
pub struct FailureRow {
    pub case: &'static str,
    pub method: String,
    pub all: Option<Quality>,
    pub region: Option<Quality>,
    /// Mean absolute frame-to-frame change (linear RGB) of the output and of the truth, and
    /// the mean absolute difference of the two changes (0 = exactly the truth's motion).
    pub change_out: Option<f64>,
    pub change_truth: Option<f64>,
    pub temporal_error: Option<f64>,
    pub nonfinite: usize,
    pub out_of_range: usize,
    pub note: String,
}

pub const HEADER: [&str; 13] = [
    "case",
    "method",
    "psnr_all_db",
    "ssim_all",
    "psnr_region_db",
    "ssim_region",
    "change_out",
    "change_truth",
    "temporal_error",
    "nonfinite",
    "out_of_range",
    "region_px",
    "note",
];

/// Mean absolute per-pixel change between consecutive frames, and of the changes' difference.
fn temporal(out: &[RgbImage], truth: &[RgbImage]) -> (f64, f64, f64) {
    let (mut co, mut ct, mut te, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
    for k in 1..out.len().min(truth.len()) {
        for c in 0..3 {
            let (o0, o1) = (out[k - 1].channels[c].data(), out[k].channels[c].data());
            let (t0, t1) = (truth[k - 1].channels[c].data(), truth[k].channels[c].data());
            for i in 0..o0.len().min(t0.len()) {
                let (d_o, d_t) = (f64::from(o1[i] - o0[i]), f64::from(t1[i] - t0[i]));
                co += d_o.abs();
                ct += d_t.abs();
                te += (d_o - d_t).abs();
                n += 1;
            }
        }
    }
    let n = n.max(1) as f64;
    (co / n, ct / n, te / n)
}

fn region_px(m: &Plane) -> usize {
    m.data().iter().filter(|&&v| v > 0.5).count()
}

/// The methods of the suite: the varifocal ones at the case's focus, the multifocal ones as
/// the eye sees their layers at that focus.
pub fn suite_methods(optimized_iterations: usize, c1_rate: usize) -> Vec<Method> {
    vec![
        Method::Gather,
        Method::LightField { views: 36 },
        Method::NetworkC1 { rate: c1_rate },
        Method::Linear,
        Method::Optimized {
            iterations: optimized_iterations,
        },
        Method::Spectral,
        Method::NetworkC4,
        Method::RefineC1,
        Method::RefineC4,
    ]
}

/// Runs every case; returns the rows and the cases (for the report).
pub fn run(
    plan: &FailurePlan,
    nets: &Nets,
    bar: &ProgressBar,
) -> Result<(Vec<FailureRow>, Vec<FailureCase>)> {
    let cases = failure_cases(plan.size).context("cannot build the failure scenes")?;
    let methods = suite_methods(plan.optimized_iterations, nets.c1_rate().unwrap_or(2));
    let mut rows = Vec::new();
    for case in &cases {
        bar.set_message(format!("failure case {}: ground truth", case.name));
        let eye = case.camera.eye;
        let q = case.focus;
        let mut inputs = Vec::with_capacity(plan.frames);
        let mut truth = Vec::with_capacity(plan.frames);
        for k in 0..plan.frames.max(2) {
            let scene = case.frame(k);
            let (color, depth) = case.input(&scene)?;
            inputs.push(Rgbd::new(color, depth)?);
            truth.push(render_thin_lens(
                &scene,
                &case.camera,
                q,
                plan.truth_samples,
            )?);
        }
        let mut stack_foci = plan.stack_foci.clone();
        if !stack_foci.iter().any(|f| (f.0 - q.0).abs() < 1e-4) {
            stack_foci.push(q);
        }
        let stack = render_thin_lens_stack(
            &case.scene,
            &case.camera,
            &stack_foci,
            plan.truth_samples,
            |_| {},
        )?;
        let linear_init = Cpu.linear_blend(&inputs[0], &methods::planes())?;
        let targets = MultifocalTargets {
            stack: &stack,
            foci: &stack_foci,
            linear_init: &linear_init,
        };
        bar.inc(1);
        for &m in &methods {
            bar.set_message(format!("failure case {}: {}", case.name, m.label()));
            let choice = if m.network() {
                Some(nets.choose(m)?)
            } else {
                None
            };
            let mut row = FailureRow {
                case: case.name,
                method: m.label(),
                all: None,
                region: None,
                change_out: None,
                change_truth: None,
                temporal_error: None,
                nonfinite: 0,
                out_of_range: 0,
                note: String::new(),
            };
            if let Some(c) = &choice {
                if !c.trained {
                    row.note = c.note.clone();
                    rows.push(row);
                    bar.inc(1);
                    continue;
                }
            }
            let net = choice.as_ref().map(|c| methods::NetOn::Cpu(c.net.as_ref()));
            // Optimized blending fits a ground-truth stack, which only frame 0 has.
            let frames = if matches!(m, Method::Optimized { .. }) {
                1
            } else {
                inputs.len()
            };
            let mut outs = Vec::with_capacity(frames);
            let mut failed = None;
            for input in inputs.iter().take(frames) {
                let r = if m.multifocal() {
                    methods::decompose(&Cpu, m, net, input, &targets, &eye).and_then(|l| {
                        Cpu.retina_multifocal(&l, &[q], &eye)?
                            .pop()
                            .context("no retinal image")
                    })
                } else {
                    methods::defocus(&Cpu, m, net, input, q, &eye).map(|(img, _)| img)
                };
                match r {
                    Ok(img) => outs.push(img),
                    Err(e) => {
                        failed = Some(format!("failed: {e:#}"));
                        break;
                    }
                }
            }
            if let Some(f) = failed {
                row.note = f;
                rows.push(row);
                bar.inc(1);
                continue;
            }
            let refs: Vec<&RgbImage> = outs.iter().collect();
            (row.nonfinite, row.out_of_range) = out_of_range(&refs);
            row.all = Some(quality(&outs[0], &truth[0], None)?);
            row.region = Some(quality(&outs[0], &truth[0], Some(&case.mask))?);
            if outs.len() > 1 {
                let (co, ct, te) = temporal(&outs, &truth);
                row.change_out = Some(co);
                row.change_truth = Some(ct);
                row.temporal_error = Some(te);
            } else {
                row.note = "temporal: not measured (fits a ground-truth focal stack, which only frame 0 has)".into();
            }
            rows.push(row);
            bar.inc(1);
        }
        if case.view_synthesis {
            rows.extend(view_synthesis(case, plan)?);
        }
    }
    Ok((rows, cases))
}

/// Novel views synthesised from the case's sparse RGB-D views against true pinhole views:
/// overall and inside each view's disocclusion mask; temporal stability of the first novel
/// view over the animated sequence.
fn view_synthesis(case: &FailureCase, plan: &FailurePlan) -> Result<Vec<FailureRow>> {
    let eye = case.camera.eye;
    let mut rows = Vec::new();
    for (name, positions) in [
        ("views (5 sparse)", sparse_views()),
        ("views (centre only)", vec![[0.0, 0.0]]),
    ] {
        let (mut all, mut region) = (Vec::new(), Vec::new());
        let (mut outs_seq, mut truth_seq) = (Vec::new(), Vec::new());
        let mut imgs = Vec::new();
        for k in 0..plan.frames.max(2) {
            let scene = case.frame(k);
            let mut inputs = Vec::new();
            for &p in &positions {
                let (c, d) = render_pinhole(&scene, &case.camera, p, 4)?;
                inputs.push(RgbdView {
                    position: p,
                    rgbd: Rgbd::new(c, d)?,
                });
            }
            for (i, &target) in novel_views().iter().enumerate() {
                // Frame 0 is scored on every novel view, later frames on the first only.
                if k > 0 && i > 0 {
                    break;
                }
                let out = synthesize_view(&inputs, target, &eye)?;
                let (truth, _) = render_pinhole(&scene, &case.camera, target, 4)?;
                if k == 0 {
                    let mask = disoccluded(&scene, &case.camera, target)?;
                    all.push(quality(&out, &truth, None)?);
                    if region_px(&mask) > 0 {
                        region.push(quality(&out, &truth, Some(&mask))?);
                    }
                }
                if i == 0 {
                    outs_seq.push(out.clone());
                    truth_seq.push(truth);
                }
                imgs.push(out);
            }
        }
        let mean = |v: &[Quality]| {
            (!v.is_empty()).then(|| Quality {
                psnr: v.iter().map(|q| q.psnr).sum::<f64>() / v.len() as f64,
                ssim: v.iter().map(|q| q.ssim).sum::<f64>() / v.len() as f64,
            })
        };
        let refs: Vec<&RgbImage> = imgs.iter().collect();
        let (nonfinite, outside) = out_of_range(&refs);
        let (co, ct, te) = temporal(&outs_seq, &truth_seq);
        rows.push(FailureRow {
            case: case.name,
            method: name.into(),
            all: mean(&all),
            region: mean(&region),
            change_out: Some(co),
            change_truth: Some(ct),
            temporal_error: Some(te),
            nonfinite,
            out_of_range: outside,
            note: "novel pinhole views 5 mm off centre against true views; region: what the centre view cannot see".into(),
        });
    }
    Ok(rows)
}

pub fn table(rows: &[FailureRow], cases: &[FailureCase]) -> Table {
    let mut t = Table::new(&HEADER);
    for r in rows {
        let px = cases
            .iter()
            .find(|c| c.name == r.case)
            .map_or(0, |c| region_px(&c.mask));
        t.push(vec![
            r.case.into(),
            r.method.clone(),
            num(r.all.map(|q| q.psnr), 3),
            num(r.all.map(|q| q.ssim), 5),
            num(r.region.map(|q| q.psnr), 3),
            num(r.region.map(|q| q.ssim), 5),
            num(r.change_out, 6),
            num(r.change_truth, 6),
            num(r.temporal_error, 6),
            r.nonfinite.to_string(),
            r.out_of_range.to_string(),
            px.to_string(),
            r.note.clone(),
        ]);
    }
    t
}
