//! `dioptra eval`: speed against accuracy for every render method and setting, and the
//! failure-case suite (scenes built to break methods; faults in the control loop). Writes
//! CSV tables, charts (PNG and SVG) and a Markdown report to `--out`.
//!
//! `--suite speed|failure|loop|lightfield|panel|all` (default all) picks the parts (failure
//! includes the control-loop faults; loop is those alone; lightfield: light fields from sparse
//! views; panel: a prototype's panel sizes, each stage timed and the rig run at each); `--quick`
//! is the one-minute version CI runs (one 128 px scene, fewer settings and runs, small panels,
//! every method still present).

mod charts;
mod failure;
mod lightfield;
#[cfg(feature = "simulated")]
mod loop_faults;
mod methods;
mod panel;
mod report;
mod speed;

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use dioptra_core::Diopters;
use dioptra_render::multifocal::linspace;
use dioptra_render::{Backend, Cpu, Gpu};
use indicatif::{ProgressBar, ProgressStyle};

use charts::{Chart, Series};
use methods::{Method, Nets};
use report::{markdown_table, mean, num};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The one-minute version: one 128 px scene, fewer settings and runs, every method.
    #[arg(long)]
    quick: bool,
    /// Where to write eval.csv, failure.csv, loop.csv, the charts and report.md.
    #[arg(long, default_value = "eval-out")]
    out: PathBuf,
    /// Image sizes of the speed/accuracy part, pixels, comma-separated (default 256,512;
    /// --quick 128).
    #[arg(long)]
    sizes: Option<String>,
    /// cpu, gpu or both. With both, a machine without a GPU adapter runs the CPU only.
    #[arg(long, default_value = "both")]
    backend: String,
    /// Timed warm runs per measurement, after one untimed warm-up (default 5; --quick 3).
    #[arg(long)]
    runs: Option<usize>,
    /// Longest the timed runs of one measurement may take together, seconds: past it fewer
    /// runs are timed (the CSV's runs column says how many; 0 = one cold run), and a method
    /// whose single run overruns it skips its costlier settings at that size and backend.
    /// (default 30; --quick 5).
    #[arg(long)]
    budget_s: Option<f64>,
    /// Sizes the GPU backend runs at, comma-separated (default: every --sizes).
    #[arg(long)]
    gpu_sizes: Option<String>,
    /// Test scenes per size (default 2; --quick 1).
    #[arg(long)]
    scenes: Option<usize>,
    /// speed, failure (with the control-loop faults), loop (the control-loop faults only),
    /// lightfield (light fields from sparse views, foveated too), panel (panels of 960 x 1080,
    /// 1440 x 1600 and 2160 x 2160 per eye at 20 and 90 degrees: each stage timed, and the rig
    /// run at each size; --quick: 96 x 108 and 144 x 160) or all.
    #[arg(long, default_value = "all")]
    suite: String,
    /// Thin-lens rays per pixel of the ground truth (default 64; --quick 16).
    #[arg(long)]
    truth_samples: Option<u32>,
    /// Image size of the failure scenes, pixels (default 192; --quick 64).
    #[arg(long)]
    failure_size: Option<usize>,
    /// Simulated seconds per control-loop fault run (default 4; --quick 2.5).
    #[arg(long)]
    loop_seconds: Option<f64>,
    /// Seconds each panel rig run is measured for, on the system clock (default 10; --quick 1).
    #[arg(long)]
    panel_seconds: Option<f64>,
}

fn parse_sizes(s: &str) -> Result<Vec<usize>> {
    let v: Vec<usize> = s
        .split(',')
        .map(|p| {
            p.trim().parse::<usize>().with_context(|| {
                format!("--sizes: {p:?} is not a whole number (expected e.g. --sizes 256,512)")
            })
        })
        .collect::<Result<_>>()?;
    if v.is_empty() || v.iter().any(|&s| !(32..=1024).contains(&s)) {
        bail!("--sizes {s:?}: expected sizes from 32 to 1024 pixels, e.g. --sizes 256,512");
    }
    Ok(v)
}

/// Everything resolved from the flags.
struct Settings {
    speed: Option<speed::SpeedPlan>,
    failure: Option<failure::FailurePlan>,
    lightfield: Option<lightfield::LightFieldPlan>,
    panel: Option<panel::PanelPlan>,
    /// The control-loop faults, for this many simulated seconds each.
    loop_seconds: Option<f64>,
    backends: Vec<String>,
}

fn settings(a: &Args) -> Result<Settings> {
    let (run_speed, run_failure, run_loop, run_lf, run_panel) = match a.suite.as_str() {
        "speed" => (true, false, false, false, false),
        "failure" => (false, true, true, false, false),
        "loop" => (false, false, true, false, false),
        "lightfield" => (false, false, false, true, false),
        "panel" => (false, false, false, false, true),
        "all" => (true, true, true, true, true),
        s => bail!("--suite {s:?}: expected speed, failure, loop, lightfield, panel or all"),
    };
    let backends: Vec<String> = match a.backend.as_str() {
        "cpu" => vec!["cpu".into()],
        "gpu" => vec!["gpu".into()],
        "both" => vec!["cpu".into(), "gpu".into()],
        b => bail!("--backend {b:?}: expected cpu, gpu or both"),
    };
    let runs = a.runs.unwrap_or(if a.quick { 3 } else { 5 });
    if !(1..=1000).contains(&runs) {
        bail!("--runs {runs}: expected 1 to 1000");
    }
    let scenes = a.scenes.unwrap_or(if a.quick { 1 } else { 2 });
    if !(1..=100).contains(&scenes) {
        bail!("--scenes {scenes}: expected 1 to 100");
    }
    let truth_samples = a.truth_samples.unwrap_or(if a.quick { 16 } else { 64 });
    if !(1..=4096).contains(&truth_samples) {
        bail!("--truth-samples {truth_samples}: expected 1 to 4096");
    }
    let sizes = match &a.sizes {
        Some(s) => parse_sizes(s)?,
        None if a.quick => vec![128],
        None => vec![256, 512],
    };
    let budget_s = a.budget_s.unwrap_or(if a.quick { 5.0 } else { 30.0 });
    if !(budget_s > 0.0 && budget_s <= 86_400.0) {
        bail!("--budget-s {budget_s}: expected more than 0 and at most 86400 seconds");
    }
    let gpu_sizes = match &a.gpu_sizes {
        Some(s) => parse_sizes(s).map_err(|e| anyhow::anyhow!("--gpu-sizes: {e}"))?,
        None => sizes.clone(),
    };
    let failure_size = a.failure_size.unwrap_or(if a.quick { 64 } else { 192 });
    if !(32..=1024).contains(&failure_size) {
        bail!("--failure-size {failure_size}: expected 32 to 1024 pixels");
    }
    let loop_seconds = a.loop_seconds.unwrap_or(if a.quick { 2.5 } else { 4.0 });
    if !(2.0..=600.0).contains(&loop_seconds) {
        bail!("--loop-seconds {loop_seconds}: expected 2 to 600 (the unplug fault happens at 0.9-1.3 s)");
    }
    let d = |v: &[f32]| v.iter().map(|&q| Diopters(q)).collect::<Vec<_>>();
    let methods: Vec<Method> = if a.quick {
        vec![
            Method::Gather,
            Method::LightField { views: 12 },
            Method::LightField { views: 36 },
            Method::NetworkC1 { rate: 2 },
            Method::Linear,
            Method::Optimized { iterations: 1 },
            Method::Optimized { iterations: 10 },
            Method::OptimizedGather { iterations: 10 },
            Method::Spectral,
            Method::NetworkC4,
            Method::RefineC1,
            Method::RefineC4,
        ]
    } else {
        let mut m = vec![Method::Gather];
        m.extend([12, 24, 36, 48, 64].map(|views| Method::LightField { views }));
        // Cheapest first: a setting's time predicts the next one's (see --budget-s).
        m.extend([4, 2, 1].map(|rate| Method::NetworkC1 { rate }));
        m.push(Method::RefineC1);
        m.push(Method::Linear);
        m.extend([1, 10, 100].map(|iterations| Method::Optimized { iterations }));
        // 30: the daemon's setting.
        m.extend([10, 30].map(|iterations| Method::OptimizedGather { iterations }));
        m.push(Method::Spectral);
        m.push(Method::NetworkC4);
        m.push(Method::RefineC4);
        m
    };
    let speed = run_speed.then(|| speed::SpeedPlan {
        sizes,
        scenes,
        runs,
        budget_ms: budget_s * 1e3,
        gpu_sizes,
        truth_samples,
        defocus_foci: if a.quick {
            d(&[0.1, 1.0, 4.0])
        } else {
            d(&[0.1, 0.5, 1.0, 1.5, 2.2, 3.0, 4.0])
        },
        // DeepFocus's multifocal foci: 0.1 to 2.2 D (22 in full, 8 in --quick).
        multifocal_foci: linspace(0.1, 2.2, if a.quick { 8 } else { 22 }),
        methods,
    });
    let failure = run_failure.then(|| failure::FailurePlan {
        size: failure_size,
        truth_samples: if a.quick { 12 } else { truth_samples.min(48) },
        frames: if a.quick { 3 } else { 6 },
        stack_foci: linspace(0.1, 2.2, if a.quick { 4 } else { 8 }),
        optimized_iterations: if a.quick { 10 } else { 50 },
    });
    // DeepFocus's light fields: 9 x 9 views over 1 cm; 9 inputs too (5 beside them).
    let lightfield = run_lf.then(|| lightfield::LightFieldPlan {
        size: if a.quick { 64 } else { 256 },
        scenes,
        grid: if a.quick { 5 } else { 9 },
        span: 0.01,
        inputs: vec![5, 9],
        // About 8, 2.4 and 1.4 % of the rays at 256 px.
        foveate: vec![2.5, 5.0, 7.0],
    });
    let panel_seconds = a.panel_seconds.unwrap_or(if a.quick { 1.0 } else { 10.0 });
    if !(0.5..=600.0).contains(&panel_seconds) {
        bail!("--panel-seconds {panel_seconds}: expected 0.5 to 600");
    }
    let panel = run_panel.then(|| panel::PanelPlan {
        sizes: if a.quick {
            vec![[96, 108], [144, 160]]
        } else {
            vec![[960, 1080], [1440, 1600], [2160, 2160]]
        },
        fields_deg: vec![20.0, 90.0],
        budget_ms: budget_s * 1e3,
        // The rig at 20 degrees only: 48 to 108 px per degree, the blur a lab's panel has.
        rig_fields_deg: vec![20.0],
        rig_seconds: panel_seconds,
    });
    Ok(Settings {
        speed,
        failure,
        lightfield,
        panel,
        loop_seconds: run_loop.then_some(loop_seconds),
        backends,
    })
}

fn bar(len: u64) -> Result<ProgressBar> {
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template("[{elapsed_precise}] [{bar:32}] {pos}/{len} {msg}")?
            .progress_chars("=> "),
    );
    Ok(pb)
}

pub fn run(a: Args) -> Result<()> {
    let started = Instant::now();
    let s = settings(&a)?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create the output folder {}", a.out.display()))?;
    let nets = Nets::load();
    let mut md = String::new();
    let _ = writeln!(md, "# dioptra eval\n");
    let _ = writeln!(
        md,
        "Command: `dioptra {}`\n",
        std::env::args().skip(1).collect::<Vec<_>>().join(" ")
    );

    // Backends: the GPU only when an adapter opens; say which.
    let mut gpu_note = String::new();
    let gpu = if s.backends.iter().any(|b| b == "gpu") && s.speed.is_some() {
        match Gpu::new(None) {
            Ok(g) => {
                let ad = g.context().adapter();
                gpu_note = format!(
                    "GPU adapter: {} ({}){}",
                    ad.name,
                    ad.backend,
                    if ad.software {
                        ": a software rasteriser on the CPU, so its rows check the GPU code path and time it on this CPU, not on a GPU"
                    } else {
                        ""
                    }
                );
                Some(g)
            }
            Err(e) if a.backend == "both" => {
                gpu_note = format!("GPU backend not run: {e}");
                None
            }
            Err(e) => return Err(e).context("--backend gpu"),
        }
    } else {
        None
    };
    if !gpu_note.is_empty() {
        println!("{gpu_note}");
    }
    let mut backends: Vec<&dyn Backend> = Vec::new();
    if s.backends.iter().any(|b| b == "cpu") {
        backends.push(&Cpu);
    }
    if let Some(g) = &gpu {
        backends.push(g);
    }

    if let Some(plan) = &s.speed {
        let pb = bar(plan.units(backends.iter().any(|b| b.name() == "cpu"), gpu.is_some()))?;
        let rows = speed::run(plan, &backends, &nets, &pb)?;
        pb.finish_with_message("speed and accuracy done");
        speed::table(&rows).write(&a.out.join("eval.csv"))?;
        speed_charts(&a, plan, &rows)?;
        speed_report(&mut md, plan, &rows, &gpu_note);
    }
    if let Some(plan) = &s.failure {
        let n_cases = 12u64;
        let pb = bar(n_cases * 7)?;
        let (rows, cases) = failure::run(plan, &nets, &pb)?;
        pb.finish_with_message("failure scenes done");
        failure::table(&rows, &cases).write(&a.out.join("failure.csv"))?;
        failure_charts(&a, &rows, &cases)?;
        failure_report(&mut md, plan, &rows, &cases);
    }
    if let Some(seconds) = s.loop_seconds {
        run_loop_faults(&a, &mut md, seconds)?;
    }
    if let Some(plan) = &s.lightfield {
        // Its own backends: the speed part's GPU only opens when that part runs.
        let lf_gpu = if s.backends.iter().any(|b| b == "gpu") && gpu.is_none() {
            Gpu::new(None).ok()
        } else {
            None
        };
        let mut lf_backends = backends.clone();
        if let Some(g) = &lf_gpu {
            lf_backends.push(g);
        }
        let c5r = nets.c5r();
        let pb = bar(plan.units(lf_backends.len(), c5r.is_ok()))?;
        let (rows, foveated) = lightfield::run(plan, &lf_backends, c5r.ok(), &pb)?;
        pb.finish_with_message("light fields done");
        lightfield::table(&rows).write(&a.out.join("lightfield.csv"))?;
        lightfield::foveated_table(&foveated).write(&a.out.join("lightfield_foveated.csv"))?;
        lightfield_report(&mut md, plan, &rows, &foveated, c5r.err());
    }
    if let Some(plan) = &s.panel {
        // Its own GPU, as the light fields' (the speed part's opens only when that part runs).
        let panel_gpu = if s.backends.iter().any(|b| b == "gpu") && gpu.is_none() {
            Gpu::new(None).ok()
        } else {
            None
        };
        let mut panel_backends = backends.clone();
        if let Some(g) = &panel_gpu {
            panel_backends.push(g);
        }
        let pb = bar(plan.units(panel_backends.len()))?;
        let tick = |what: &str| {
            pb.set_message(format!("panel: {what}"));
            pb.inc(1);
        };
        let stage_rows = panel::stages(plan, &panel_backends, &tick)?;
        let rig_rows = panel::rigs(plan, &tick)?;
        pb.finish_with_message("panel sizes done");
        let note = match &panel_gpu {
            Some(g) => format!("GPU adapter: {}.", g.context().adapter().name),
            None if gpu.is_none() && s.backends.iter().any(|b| b == "gpu") => {
                "GPU backend not run: no adapter opened.".to_string()
            }
            None => gpu_note.clone(),
        };
        panel::write(&a.out, &mut md, plan, &stage_rows, &rig_rows, &note)?;
    }
    let _ = writeln!(
        md,
        "\nWall time of this run: {:.0} s.",
        started.elapsed().as_secs_f64()
    );
    let report = a.out.join("report.md");
    std::fs::write(&report, md).with_context(|| format!("cannot write {}", report.display()))?;
    println!(
        "wrote {} (eval.csv, failure.csv, loop.csv, panel_*.csv, charts, report.md) in {:.0} s",
        a.out.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// One method and setting on one backend at one size: means over scenes and foci.
struct Summary {
    label: String,
    backend: &'static str,
    time_ms: Option<f64>,
    psnr: Option<f64>,
    ssim: Option<f64>,
    note: String,
}

/// Per method label and backend at one size: mean time and mean PSNR over scenes and foci.
fn summary(rows: &[speed::SpeedRow], size: usize) -> Vec<Summary> {
    let mut keys: Vec<(Method, &'static str)> = Vec::new();
    for r in rows.iter().filter(|r| r.size == size) {
        if !keys.contains(&(r.method, r.backend)) {
            keys.push((r.method, r.backend));
        }
    }
    keys.into_iter()
        .map(|(m, b)| {
            let sel: Vec<&speed::SpeedRow> = rows
                .iter()
                .filter(|r| r.size == size && r.method == m && r.backend == b)
                .collect();
            let t: Vec<f64> = sel.iter().filter_map(|r| r.time_ms).collect();
            let p: Vec<f64> = sel
                .iter()
                .filter_map(|r| r.psnr)
                .filter(|v| v.is_finite())
                .collect();
            let q: Vec<f64> = sel.iter().filter_map(|r| r.ssim).collect();
            let note = sel
                .iter()
                .map(|r| r.note.as_str())
                .find(|n| !n.is_empty())
                .unwrap_or("")
                .to_string();
            Summary {
                label: m.label(),
                backend: b,
                time_ms: mean(&t),
                psnr: mean(&p),
                ssim: mean(&q),
                note,
            }
        })
        .collect()
}

fn speed_charts(a: &Args, plan: &speed::SpeedPlan, rows: &[speed::SpeedRow]) -> Result<()> {
    for &size in &plan.sizes {
        let sum = summary(rows, size);
        // One series per method (settings are its points), per backend.
        let mut series: Vec<Series> = Vec::new();
        for r in &sum {
            let (Some(t), Some(p)) = (r.time_ms, r.psnr) else {
                continue;
            };
            let (method, setting) = r.label.split_once(' ').unwrap_or((&r.label, ""));
            push_tagged(
                &mut series,
                (method, r.backend == "gpu"),
                (t, p),
                Some(setting.replace(" views", "")),
            );
        }
        charts::write(
            &a.out.join(format!("speed_accuracy_{size}")),
            (1150, 650),
            &Chart::SpeedAccuracy {
                title: &format!(
                    "time per frame against PSNR, {size} x {size} (mean over scenes and foci)"
                ),
                series: &series,
            },
        )?;
        // PSNR by focus: CPU rows, each method and setting, mean over scenes; varifocal and
        // multifocal methods in panels of their own (they are scored on different foci).
        let mut panels: Vec<(String, Vec<Series>)> = vec![
            ("varifocal: the image at each focus".into(), Vec::new()),
            (
                "multifocal: the retinal image of the layers".into(),
                Vec::new(),
            ),
        ];
        for r in rows.iter().filter(|r| r.size == size && r.backend == "cpu") {
            let (Some(f), Some(p)) = (r.focus, r.psnr) else {
                continue;
            };
            let name = r.method.label();
            let group = &mut panels[usize::from(r.method.multifocal())].1;
            let s = match group.iter().position(|s| s.name == name) {
                Some(i) => &mut group[i],
                None => {
                    group.push(Series::new(name));
                    group.last_mut().unwrap_or_else(|| unreachable!())
                }
            };
            s.points.push((f64::from(f), p));
        }
        panels.retain(|p| !p.1.is_empty());
        for s in panels.iter_mut().flat_map(|p| p.1.iter_mut()) {
            // Mean over scenes at each focus.
            let mut acc: Vec<(f64, f64, usize)> = Vec::new();
            for &(f, p) in &s.points {
                match acc.iter_mut().find(|a| (a.0 - f).abs() < 1e-4) {
                    Some(a) => {
                        a.1 += p;
                        a.2 += 1;
                    }
                    None => acc.push((f, p, 1)),
                }
            }
            s.points = acc.into_iter().map(|(f, p, n)| (f, p / n as f64)).collect();
        }
        charts::write(
            &a.out.join(format!("psnr_by_focus_{size}")),
            (1300, 700),
            &Chart::PsnrByFocus {
                title: &format!(
                    "PSNR against focus distance, {size} x {size}, CPU (mean over scenes)"
                ),
                panels: &panels,
            },
        )?;
    }
    Ok(())
}

fn lightfield_report(
    md: &mut String,
    plan: &lightfield::LightFieldPlan,
    rows: &[lightfield::LightFieldRow],
    foveated: &[lightfield::FoveatedRow],
    c5r_missing: Option<&str>,
) {
    let _ = writeln!(
        md,
        "## Light fields from sparse views
"
    );
    let _ = writeln!(
        md,
        "A {g} x {g} light field of {n} px views over {span} mm from {inputs:?} of its views \
         (corners and centre; plus the edge midpoints), on {scenes} test scene(s); PSNR on the \
         novel views (not the inputs) against the scene's own ray-cast pinhole views, of their \
         mean squared error; time: one run, wall clock (`lightfield.csv`). The nearest input, \
         shown in place of each novel view, is what a light field without synthesis gives. \
         DeepFocus reports 33.7 dB in 19.7 ms (C5, 9 inputs; Kalantari et al. 32.6 dB in 338 \
         ms) on its own data and GPU. No C5 weights ship; {refine}\n",
        g = plan.grid,
        n = plan.size,
        span = plan.span * 1e3,
        inputs = plan.inputs,
        scenes = plan.scenes,
        refine = match c5r_missing {
            None => "refine is the shipped C5R on the classical synthesis (the warp and its \
                     error map on the CPU, the net on the backend named)."
                .to_string(),
            Some(why) => format!("no refine rows: C5R {why}."),
        },
    );
    let mut keys: Vec<(&str, &str, usize)> = Vec::new();
    for r in rows {
        if !keys.contains(&(r.method, r.backend, r.inputs)) {
            keys.push((r.method, r.backend, r.inputs));
        }
    }
    let table: Vec<Vec<String>> = keys
        .iter()
        .map(|&(m, b, k)| {
            let of: Vec<&lightfield::LightFieldRow> = rows
                .iter()
                .filter(|r| (r.method, r.backend, r.inputs) == (m, b, k))
                .collect();
            let psnr: Vec<f64> = of.iter().map(|r| r.psnr).collect();
            let ms: Vec<f64> = of.iter().filter_map(|r| r.time_ms).collect();
            let diff = of
                .iter()
                .filter_map(|r| r.max_diff)
                .fold(None, |a: Option<f64>, d| Some(a.map_or(d, |a| a.max(d))));
            vec![
                m.to_string(),
                if b.is_empty() {
                    "-".into()
                } else {
                    b.to_string()
                },
                k.to_string(),
                num(mean(&psnr), 2),
                num(mean(&ms), 0),
                diff.map_or("-".into(), |d| format!("{d:.1e}")),
            ]
        })
        .collect();
    let _ = writeln!(
        md,
        "{}",
        markdown_table(
            &[
                "method",
                "backend",
                "inputs",
                "PSNR novel views (dB)",
                "time (ms)",
                "max |GPU - CPU|"
            ],
            &table
        )
    );
    let _ = writeln!(
        md,
        "Foveated (FV's sampling: each view keeps its own log-polar samples around the image \
         centre at log-buffer scale S; the rest filled within each view by the paper's \
         interpolation, or across views: every view's samples reprojected into each view by \
         their depth, then that interpolation), from the CPU's synthesis with {} \
         inputs, novel views, per region (fovea, periphery 1 and 2: rings of diameter 0.1, 0.4 \
         and 1 image diagonal): PSNR against the truth, and against the full synthesis \
         (`lightfield_foveated.csv`). The target is the fovea within 1 dB of the full \
         synthesis's at 10 % of the rays or fewer; FVS reports 41.8 dB in the fovea at 1.18 % \
         on its data, with its network.\n",
        plan.inputs.iter().max().copied().unwrap_or(0)
    );
    let mut scales: Vec<(Option<f32>, &str)> = Vec::new();
    for r in foveated {
        if !scales.contains(&(r.scale, r.fill)) {
            scales.push((r.scale, r.fill));
        }
    }
    let region = |v: &[(&str, f64)], name: &str| v.iter().find(|(n, _)| *n == name).map(|p| p.1);
    let table: Vec<Vec<String>> = scales
        .iter()
        .map(|&(s, fill)| {
            let of: Vec<&lightfield::FoveatedRow> = foveated
                .iter()
                .filter(|r| (r.scale, r.fill) == (s, fill))
                .collect();
            let avg = |f: &dyn Fn(&lightfield::FoveatedRow) -> Option<f64>| {
                mean(&of.iter().filter_map(|r| f(r)).collect::<Vec<_>>())
            };
            let mut row = vec![
                s.map_or("full synthesis".into(), |s| format!("S = {s}, {fill}")),
                num(avg(&|r| Some(100.0 * r.fraction)), 2),
            ];
            for name in ["fovea", "periphery 1", "periphery 2"] {
                row.push(num(avg(&|r| region(&r.truth, name)), 2));
            }
            row.push(num(avg(&|r| region(&r.full, "fovea")), 2));
            row
        })
        .collect();
    let _ = writeln!(
        md,
        "{}",
        markdown_table(
            &[
                "sampling",
                "rays kept (%)",
                "fovea (dB)",
                "periphery 1 (dB)",
                "periphery 2 (dB)",
                "fovea vs full (dB)"
            ],
            &table
        )
    );
}

fn speed_report(
    md: &mut String,
    plan: &speed::SpeedPlan,
    rows: &[speed::SpeedRow],
    gpu_note: &str,
) {
    let _ = writeln!(md, "## Speed against accuracy\n");
    let _ = writeln!(
        md,
        "Test scenes (seeds {}), sizes {:?} px; ground truth: thin-lens ray casting, {} rays per pixel. \
         Times: median of {} warm runs after one untimed warm-up (fewer where the runs column says so: \
         a measurement's runs may take {} s together), wall clock on this machine; \
         a varifocal method's time is one frame at one focus, a multifocal method's is one set of \
         layers (which serves every focus). Varifocal methods are scored at {:?} D; multifocal \
         methods by the retinal image of their layers at {} foci from 0.1 to 2.2 D against the \
         ground-truth focal stack (`optimized` fits that same stack, as in the accuracy \
         tests, and starts from linear blending, whose time is not included: a best case no rig \
         has; `optimized-gather` fits what a rig can make, a focal stack gathered from the RGB-D \
         at those foci, as the daemon's `method = \"optimized\"` does with 30 iterations, and its \
         time includes the stack and the linear start; `spectral` solves the least squares per \
         spatial frequency with its default settings (a composite stack at 6 foci: the 12-view \
         light field where a blurred depth step reaches, the smooth disk blur elsewhere; prior 0.02, \
         5 projected steps; crates/render/README.md), its time including that stack). PSNR and SSIM are on \
         sRGB-encoded images. Networks are scored with the shipped weights (crates/net/weights); a setting with none (another interleave rate) runs the same architecture with random weights and is timed only. On the GPU backend the networks run the same weights through dioptra-net's wgpu inference.\n",
        (0..plan.scenes).map(|s| dioptra_sim::scene::Split::Test.seed(s as u64).to_string()).collect::<Vec<_>>().join(", "),
        plan.sizes,
        plan.truth_samples,
        plan.runs,
        plan.budget_ms / 1e3,
        plan.defocus_foci.iter().map(|q| q.0).collect::<Vec<_>>(),
        plan.multifocal_foci.len(),
    );
    if !gpu_note.is_empty() {
        let _ = writeln!(
            md,
            "{gpu_note}. GPU rows at sizes {:?} px.\n",
            plan.gpu_sizes
        );
    }
    for &size in &plan.sizes {
        let _ = writeln!(md, "### {size} x {size}\n");
        let _ = writeln!(
            md,
            "![speed against accuracy](speed_accuracy_{size}.png)\n![PSNR by focus](psnr_by_focus_{size}.png)\n"
        );
        let sum = summary(rows, size);
        let table: Vec<Vec<String>> = sum
            .into_iter()
            .map(|r| {
                vec![
                    r.label,
                    r.backend.to_string(),
                    num(r.time_ms, 2),
                    num(r.psnr, 2),
                    num(r.ssim, 4),
                    r.note,
                ]
            })
            .collect();
        md.push_str(&markdown_table(
            &[
                "method",
                "backend",
                "time per frame (ms)",
                "PSNR (dB)",
                "SSIM",
                "note",
            ],
            &table,
        ));
        md.push('\n');
    }
}

fn failure_charts(
    a: &Args,
    rows: &[failure::FailureRow],
    cases: &[dioptra_sim::scene::failure::FailureCase],
) -> Result<()> {
    let mut categories: Vec<String> = cases.iter().map(|c| c.name.to_string()).collect();
    categories.reverse(); // first case at the top
    let row_of = |name: &str| categories.iter().position(|c| c == name).unwrap_or(0) as f64;
    let mut series: Vec<Series> = Vec::new();
    let mut temporal: Vec<Series> = Vec::new();
    for r in rows {
        if let Some(q) = r.region {
            if q.psnr.is_finite() {
                push_point(&mut series, &r.method, (q.psnr, row_of(r.case)));
            }
        }
        if let (Some(te), Some(ct)) = (r.temporal_error, r.change_truth) {
            if ct > 0.0 {
                push_point(&mut temporal, &r.method, (te / ct, row_of(r.case)));
            }
        }
    }
    charts::write(
        &a.out.join("failure_region_psnr"),
        (1250, 700),
        &Chart::Dots {
            title: "PSNR inside each failure region",
            x_desc: "PSNR inside the failure region (dB)",
            categories: &categories,
            series: &series,
        },
    )?;
    charts::write(
        &a.out.join("failure_temporal"),
        (1250, 700),
        &Chart::Dots {
            title: "temporal error over the animated sequence (relative to the truth's own change)",
            x_desc: "mean |output change - truth change| / mean |truth change|",
            categories: &categories,
            series: &temporal,
        },
    )
}

fn push_point(series: &mut Vec<Series>, name: &str, p: (f64, f64)) {
    push_tagged(series, (name, false), p, None);
}

/// Adds point `p` to the series named `key.0` (hollow markers when `key.1`), making it if new.
fn push_tagged(series: &mut Vec<Series>, key: (&str, bool), p: (f64, f64), tag: Option<String>) {
    let (name, hollow) = key;
    let i = match series
        .iter()
        .position(|s| s.name == name && s.hollow == hollow)
    {
        Some(i) => i,
        None => {
            let mut s = Series::new(name);
            s.hollow = hollow;
            series.push(s);
            series.len() - 1
        }
    };
    series[i].points.push(p);
    if let Some(t) = tag {
        series[i].tags.push(t);
    }
}

fn failure_report(
    md: &mut String,
    plan: &failure::FailurePlan,
    rows: &[failure::FailureRow],
    cases: &[dioptra_sim::scene::failure::FailureCase],
) {
    let _ = writeln!(md, "## Where methods fail: scenes\n");
    let _ = writeln!(
        md,
        "{} x {} px, ground truth {} rays per pixel, {} animated frames per case (one object slides \
         {} px per frame), CPU backend. PSNR/SSIM on frame 0, overall and inside the case's failure \
         region; temporal error = mean |output change - truth change| per pixel and channel between \
         consecutive frames (linear light), beside the truth's own mean change; nonfinite and \
         out_of_range count output values that are not finite or outside [0, 1] over all frames. \
         Optimized blending ({} iterations) fits a ground-truth stack at {} foci plus the case's focus.\n",
        plan.size,
        plan.size,
        plan.truth_samples,
        plan.frames,
        cases.first().map_or(0.0, |c| c.step_px),
        plan.optimized_iterations,
        plan.stack_foci.len()
    );
    let _ = writeln!(md, "![PSNR in failure regions](failure_region_psnr.png)\n![temporal error](failure_temporal.png)\n");
    for c in cases {
        let _ = writeln!(
            md,
            "- `{}` (focus {:.2} D, pupil {:.0} mm): {}",
            c.name, c.focus.0, c.camera.eye.pupil_diameter.0, c.description
        );
    }
    md.push('\n');
    let table: Vec<Vec<String>> = rows
        .iter()
        .map(|r| {
            vec![
                r.case.to_string(),
                r.method.clone(),
                num(r.all.map(|q| q.psnr), 2),
                num(r.region.map(|q| q.psnr), 2),
                num(r.region.map(|q| q.ssim), 3),
                match (r.temporal_error, r.change_truth) {
                    (Some(te), Some(ct)) => format!("{:.5} / {:.5}", te, ct),
                    _ => String::new(),
                },
                format!("{} / {}", r.nonfinite, r.out_of_range),
                r.note.clone(),
            ]
        })
        .collect();
    md.push_str(&markdown_table(
        &[
            "case",
            "method",
            "PSNR all",
            "PSNR region",
            "SSIM region",
            "temporal error / truth change",
            "nonfinite / out of range",
            "note",
        ],
        &table,
    ));
    md.push('\n');
}

/// The control-loop faults on the simulated rig (needs the simulated clock).
#[cfg(feature = "simulated")]
fn run_loop_faults(a: &Args, md: &mut String, seconds: f64) -> Result<()> {
    let pb = bar(loop_faults::Fault::ALL.len() as u64)?;
    let results = loop_faults::run_all(seconds, |f| {
        pb.set_message(format!("control loop: {}", f.name()));
        pb.inc(1);
    })?;
    pb.finish_with_message("control-loop faults done");
    loop_faults::table(&results).write(&a.out.join("loop.csv"))?;
    loop_chart(a, &results)?;
    loop_report(md, &results, seconds);
    Ok(())
}

#[cfg(not(feature = "simulated"))]
fn run_loop_faults(_: &Args, _: &mut String, _: f64) -> Result<()> {
    bail!(
        "the control-loop faults run the rig on simulated time, and this dioptra was built \
         without the `simulated` feature; rebuild with default features, or pass --suite speed"
    )
}

#[cfg(feature = "simulated")]
fn loop_chart(a: &Args, results: &[loop_faults::LoopResult]) -> Result<()> {
    let panels: Vec<(String, Vec<Series>)> = results
        .iter()
        .map(|r| {
            (
                r.fault.name().to_string(),
                vec![Series {
                    // Every 5th probe (5 ms) keeps the SVG small.
                    points: r.error.iter().step_by(5).copied().collect(),
                    ..Series::new("focus error")
                }],
            )
        })
        .collect();
    charts::write(
        &a.out.join("loop_focus_error"),
        (1100, 1400),
        &Chart::Panels {
            y_desc: "|lens - target| (D)",
            panels: &panels,
        },
    )
}

#[cfg(feature = "simulated")]
fn loop_report(md: &mut String, results: &[loop_faults::LoopResult], seconds: f64) {
    let _ = writeln!(
        md,
        "## Where the control loop fails: faults on simulated devices\n"
    );
    let _ = writeln!(
        md,
        "Varifocal mode, {seconds} s of simulated time per run (tokio's paused clock), the real lens \
         and eye-tracker drivers against their simulators, the viewer alternating between a surface \
         at {} D and one at {} D every 0.5 s. Focus error = |true lens power - depth of the true \
         gaze target| every 1 ms; the error statistics count only seeing time (eyes open, not in a saccade, \
         after the first 0.1 s); in focus = within {} D. Refocus = saccade landing to in focus; \
         recovery = end of the disturbance (replug, blink end) to in focus (worst case).\n",
        2.0,
        0.5,
        loop_faults::IN_FOCUS_D
    );
    let _ = writeln!(md, "![focus error over time](loop_focus_error.png)\n");
    let table: Vec<Vec<String>> = results
        .iter()
        .map(|r| {
            vec![
                r.fault.name().into(),
                num(r.mean_error, 3),
                num(r.p95_error, 3),
                num(r.out_of_focus.map(|v| v * 100.0), 1),
                num(r.refocus_median_ms, 1),
                num(r.refocus_max_ms, 1),
                num(r.recovery_ms, 1),
                format!("{} / {}", r.misses, r.frames_presented),
                r.lens_link_losses.to_string(),
                r.fault.what().into(),
            ]
        })
        .collect();
    md.push_str(&markdown_table(
        &[
            "fault",
            "mean error (D)",
            "p95 error (D)",
            "seeing time out of focus (%)",
            "refocus median (ms)",
            "refocus max (ms)",
            "recovery (ms)",
            "misses / frames",
            "lens link losses",
            "what",
        ],
        &table,
    ));
    md.push('\n');
}
