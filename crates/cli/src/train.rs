//! `dioptra train`: trains a DeepFocus-family network on scenes from the simulator (training
//! seeds only), with checkpoints and resume, and exports safetensors weights.

use anyhow::{bail, Context, Result};
use clap::Args as ClapArgs;
use dioptra_net::train::data::DataSpec;
use dioptra_net::train::trainer::StepTimes;
use dioptra_net::train::{train, TrainConfig, TrainEvent};
use dioptra_net::{Arch, Classical, ClassicalLayers, Task};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

#[derive(ClapArgs, Debug)]
pub struct Args {
    /// Configuration: c1 (defocus), c3 (focal stack), c4 (multifocal), c5 (light field from
    /// RGB-D views), fv (foveated view synthesis), c1r (defocus refinement of a classical
    /// render), c4r (multifocal refinement of a classical decomposition), c5r (light-field
    /// refinement of the forward-warp synthesis).
    #[arg(long)]
    config: String,
    /// Total steps; rerunning with a larger count resumes and continues.
    #[arg(long, default_value_t = 20_000)]
    steps: u64,
    /// Output directory: checkpoints, the render cache and the exported weights.
    #[arg(long, default_value = "train-out")]
    out: PathBuf,
    /// Hidden layers' channels (default: the configuration's preset, 32 for most).
    #[arg(long)]
    channels: Option<usize>,
    /// Convolution layers, the last included (default: the preset's, 8 for most).
    #[arg(long)]
    layers: Option<usize>,
    /// Interleave rate: 1, 2 or 4 (default: the preset's, 2).
    #[arg(long)]
    rate: Option<usize>,
    #[arg(long, default_value_t = 8)]
    batch: usize,
    /// Training patch side, pixels.
    #[arg(long, default_value_t = 128)]
    patch: usize,
    #[arg(long, default_value_t = 1e-4)]
    lr: f64,
    /// Training scenes (seeds 0..N).
    #[arg(long, default_value_t = 64)]
    scenes: u64,
    /// Render size of the training scenes, pixels.
    #[arg(long, default_value_t = 256)]
    size: usize,
    /// Thin-lens rays per pixel of the targets.
    #[arg(long, default_value_t = 64)]
    samples: u32,
    /// C1: target foci per scene.
    #[arg(long, default_value_t = 8)]
    foci_per_scene: usize,
    #[arg(long, default_value_t = 100)]
    checkpoint_every: u64,
    /// Render cache (default OUT/cache).
    #[arg(long)]
    cache: Option<PathBuf>,
    /// C5/FV/C5R: side of the view grid (odd, 3 to 9; default 9 for c5 and c5r, 3 for fv).
    #[arg(long)]
    grid: Option<usize>,
    /// C5/FV/C5R: input views, 5 (corners + centre) or 9 (+ edge midpoints).
    #[arg(long)]
    views: Option<usize>,
    /// c5r: novel views per training light field (drawn once from --seed's stream).
    #[arg(long)]
    novel_views: Option<usize>,
    /// FV: channels of the U-Net's first level.
    #[arg(long)]
    unet_channels: Option<usize>,
    /// Supersampling (per side) of the pinhole colour.
    #[arg(long, default_value_t = 4)]
    supersample: usize,
    /// Fields of view of the training scenes, degrees, comma-separated: scene i uses the
    /// (i mod n)-th (default: 20 for all; c1r and c5r: 20,10, so the net sees the blur sizes
    /// and parallax of views twice as wide).
    #[arg(long, value_delimiter = ',')]
    fovs: Option<Vec<f32>>,
    /// c4r: steps distilling optimized blending's layers before the retinal loss.
    #[arg(long, default_value_t = 0)]
    distill_steps: u64,
    /// c1r: the classical render refined: gather, or lightfield:N (N views). c4r: the
    /// classical decomposition refined: linear (the default) or spectral (the spectral
    /// decomposition at its default settings).
    #[arg(long)]
    classical: Option<String>,
    /// Lower the learning rate from --lr to this by a cosine over --steps.
    #[arg(long)]
    lr_final: Option<f64>,
    /// c1r and c5r: fraction of patches drawn by the classical render's error (the rest
    /// uniformly over the tiles the net runs on).
    #[arg(long, default_value_t = 0.5)]
    error_weighted: f64,
    /// c1r: the error map's own-blur threshold for training, CoC diameter in pixels (default:
    /// the one inference uses; the shipped C1R trained under 2 px).
    #[arg(long)]
    own_blur_px: Option<f32>,
    /// c1r and c5r: weight of a penalty on patches the net makes worse than its classical
    /// input (their relative rise in squared error; 0: off).
    #[arg(long, default_value_t = 0.0)]
    no_worse: f64,
    /// Training scenes of the occluder family (thin rods and large boxes before a far
    /// wall, training seeds), after the --scenes random ones.
    #[arg(long, default_value_t = 0)]
    occluder_scenes: u64,
    /// Training scenes of the wide family (large slanted and flat textured planes, spheres
    /// of mixed sizes, thin rods, small boxes, at mixed scales; training seeds), after the
    /// occluder scenes.
    #[arg(long, default_value_t = 0)]
    wide_scenes: u64,
}

/// `gather` or `lightfield:N`.
fn parse_classical(s: &str) -> Result<Classical> {
    match s.split_once(':') {
        None if s == "gather" => Ok(Classical::Gather),
        Some(("lightfield", n)) => Ok(Classical::Lightfield {
            views: n
                .parse()
                .with_context(|| format!("--classical {s}: N of lightfield:N is a view count"))?,
        }),
        _ => bail!("--classical {s}: expected gather or lightfield:N"),
    }
}

pub fn run(a: Args) -> Result<()> {
    let mut arch = Arch::preset(&a.config)
        .with_context(|| "--config: choose c1, c3, c4, c5, fv, c1r, c4r or c5r".to_string())?;
    match &mut arch.task {
        Task::C5 { views, grid } | Task::Fv { views, grid } | Task::C5r { views, grid } => {
            *grid = a.grid.unwrap_or(*grid);
            *views = a.views.unwrap_or(*views);
        }
        _ if a.grid.is_some() || a.views.is_some() => {
            bail!("--grid and --views apply to c5, fv and c5r only")
        }
        _ => {}
    }
    let c5r = matches!(arch.task, Task::C5r { .. });
    if a.novel_views.is_some() && !c5r {
        bail!("--novel-views applies to c5r only");
    }
    if a.novel_views == Some(0) {
        bail!("--novel-views 0: expected at least one novel view per light field");
    }
    if let Some(c) = &a.classical {
        match &mut arch.task {
            Task::C1r { classical } => *classical = parse_classical(c)?,
            Task::C4r { classical, .. } => {
                *classical = match c.as_str() {
                    "linear" => ClassicalLayers::Linear,
                    "spectral" => ClassicalLayers::Spectral,
                    _ => bail!("--classical {c}: c4r refines linear or spectral"),
                }
            }
            _ => bail!("--classical applies to c1r and c4r only"),
        }
    }
    if a.distill_steps > 0 && !matches!(arch.task, Task::C4r { .. }) {
        bail!("--distill-steps applies to c4r only");
    }
    if let Some(u) = a.unet_channels {
        if !matches!(arch.task, Task::Fv { .. }) {
            bail!("--unet-channels applies to fv only");
        }
        arch.unet_channels = u;
    }
    arch.channels = a.channels.unwrap_or(arch.channels);
    arch.layers = a.layers.unwrap_or(arch.layers);
    arch.rate = a.rate.unwrap_or(arch.rate);
    arch.validate()?;
    let arch_task_is_c1r = matches!(arch.task, Task::C1r { .. });
    let mut cfg = TrainConfig::new(arch, a.out.clone());
    cfg.steps = a.steps;
    cfg.batch = a.batch;
    cfg.patch = a.patch;
    cfg.lr = a.lr;
    cfg.scenes = a.scenes;
    cfg.foci_per_scene = a.foci_per_scene;
    cfg.checkpoint_every = a.checkpoint_every;
    cfg.distill_steps = a.distill_steps;
    cfg.lr_final = a.lr_final;
    if !(0.0..=1.0).contains(&a.error_weighted) {
        bail!("--error-weighted {}: expected 0 to 1", a.error_weighted);
    }
    cfg.error_weighted = a.error_weighted;
    if let Some(px) = a.own_blur_px {
        if !(px.is_finite() && (0.0..=64.0).contains(&px)) {
            bail!("--own-blur-px {px}: expected 0 to 64 pixels");
        }
        if !arch_task_is_c1r {
            bail!("--own-blur-px applies to c1r only");
        }
        cfg.own_blur_px = px;
    }
    if !(a.no_worse.is_finite() && a.no_worse >= 0.0) {
        bail!("--no-worse {}: expected a weight of 0 or more", a.no_worse);
    }
    if a.no_worse > 0.0 && !(arch_task_is_c1r || c5r) {
        bail!("--no-worse applies to c1r and c5r only");
    }
    cfg.no_worse = a.no_worse;
    cfg.novel_views = a.novel_views.unwrap_or(cfg.novel_views);
    cfg.occluder_scenes = a.occluder_scenes;
    cfg.wide_scenes = a.wide_scenes;
    cfg.fovs = match (&a.fovs, arch_task_is_c1r || c5r) {
        (Some(f), _) => f.clone(),
        (None, true) => vec![20.0, 10.0],
        (None, false) => Vec::new(),
    };
    if cfg
        .fovs
        .iter()
        .any(|f| !(f.is_finite() && *f > 0.0 && *f < 180.0))
    {
        bail!(
            "--fovs {:?}: expected angles between 0 and 180 degrees",
            cfg.fovs
        );
    }
    cfg.data = DataSpec {
        size: a.size,
        samples: a.samples,
        supersample: a.supersample,
        ..DataSpec::default()
    };
    if let Some(c) = a.cache {
        cfg.cache = c;
    }
    let data_bar = ProgressBar::new(cfg.total_scenes());
    data_bar.set_style(
        ProgressStyle::with_template("scenes [{bar:40}] {pos}/{len} {elapsed_precise}")?
            .progress_chars("=> "),
    );
    let step_bar = ProgressBar::new(cfg.steps);
    step_bar.set_style(
        ProgressStyle::with_template(
            "train [{bar:40}] {pos}/{len} {elapsed_precise} eta {eta} {msg}",
        )?
        .progress_chars("=> "),
    );
    let mut ema: Option<f32> = None;
    let mut timed = StepTimes::default();
    let mut timed_steps = 0u32;
    let w = train(&cfg, &mut |e| match e {
        TrainEvent::Prepare { done, total } => {
            if done == 1 || done == total || done % 10 == 0 {
                step_bar.suspend(|| println!("classical results: scene {done}/{total}"));
            }
        }
        TrainEvent::Data { done, .. } => {
            data_bar.set_position(done);
            if done == cfg.total_scenes() {
                data_bar.finish();
            }
        }
        TrainEvent::Resumed { step } => {
            step_bar.set_position(step);
            step_bar.println(format!("resumed at step {step}"));
        }
        TrainEvent::Step { step, loss, times } => {
            let m = ema.map_or(loss, |m| 0.98 * m + 0.02 * loss);
            ema = Some(m);
            step_bar.set_position(step);
            step_bar.set_message(format!("loss {loss:.4} (avg {m:.4})"));
            timed.data += times.data;
            timed.forward += times.forward;
            timed.backward += times.backward;
            timed.optimiser += times.optimiser;
            timed_steps += 1;
            // Plain lines too, for logs when stdout is not a terminal; with where the steps'
            // time went since the last line.
            if step % 50 == 0 || step <= 3 {
                let k = 1e3 / f64::from(timed_steps.max(1));
                step_bar.suspend(|| {
                    println!(
                        "step {step} loss {loss:.5} avg {m:.5} | ms/step: data {:.1} forward {:.1} backward {:.1} optimiser {:.1}",
                        timed.data * k,
                        timed.forward * k,
                        timed.backward * k,
                        timed.optimiser * k
                    )
                });
                timed = StepTimes::default();
                timed_steps = 0;
            }
        }
        TrainEvent::Checkpoint { step } => {
            step_bar.suspend(|| println!("checkpoint at step {step}"));
        }
        TrainEvent::Exported { path } => {
            step_bar.finish();
            println!("exported {}", path.display());
        }
    })?;
    println!(
        "{} parameters; architecture {}",
        w.parameters(),
        w.arch.to_json()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: Args,
    }

    fn refused(extra: &[&str]) -> String {
        let mut argv = vec!["train", "--out", "/nonexistent/dioptra-train-test"];
        argv.extend_from_slice(extra);
        let a = Cli::try_parse_from(argv).expect("parses").args;
        run(a).expect_err("refused").to_string()
    }

    #[test]
    fn a_bad_own_blur_threshold_is_refused_before_any_work() {
        for px in ["-1", "NaN", "100"] {
            let flag = format!("--own-blur-px={px}");
            let e = refused(&["--config", "c1r", &flag]);
            assert!(
                e.contains("--own-blur-px") && e.contains("0 to 64"),
                "{px}: {e}"
            );
        }
        let e = refused(&["--config", "c1", "--own-blur-px", "2"]);
        assert!(e.contains("c1r only"), "{e}");
        // C5R's own flag elsewhere, or asking for no novel views.
        let e = refused(&["--config", "c1r", "--novel-views", "4"]);
        assert!(e.contains("c5r only"), "{e}");
        let e = refused(&["--config", "c5r", "--novel-views", "0"]);
        assert!(e.contains("--novel-views 0"), "{e}");
    }
}
