//! `dioptra train`: trains a DeepFocus-family network on scenes from the simulator (training
//! seeds only), with checkpoints and resume, and exports safetensors weights.

use anyhow::{bail, Context, Result};
use clap::Args as ClapArgs;
use dioptra_net::train::data::DataSpec;
use dioptra_net::train::{train, TrainConfig, TrainEvent};
use dioptra_net::{Arch, Task};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

#[derive(ClapArgs, Debug)]
pub struct Args {
    /// Configuration: c1 (defocus), c3 (focal stack), c4 (multifocal), c5 (light field from
    /// RGB-D views), fv (foveated view synthesis).
    #[arg(long)]
    config: String,
    /// Total steps; rerunning with a larger count resumes and continues.
    #[arg(long, default_value_t = 20_000)]
    steps: u64,
    /// Output directory: checkpoints, the render cache and the exported weights.
    #[arg(long, default_value = "train-out")]
    out: PathBuf,
    /// Hidden layers' channels.
    #[arg(long, default_value_t = 32)]
    channels: usize,
    /// Convolution layers, the last included.
    #[arg(long, default_value_t = 8)]
    layers: usize,
    /// Interleave rate: 1, 2 or 4.
    #[arg(long, default_value_t = 2)]
    rate: usize,
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
    /// C5/FV: side of the view grid (odd, 3 to 9; default 9 for c5, 3 for fv).
    #[arg(long)]
    grid: Option<usize>,
    /// C5/FV: input views, 5 (corners + centre) or 9 (+ edge midpoints).
    #[arg(long)]
    views: Option<usize>,
    /// FV: channels of the U-Net's first level.
    #[arg(long)]
    unet_channels: Option<usize>,
    /// Supersampling (per side) of the pinhole colour.
    #[arg(long, default_value_t = 4)]
    supersample: usize,
}

pub fn run(a: Args) -> Result<()> {
    let mut arch = Arch::preset(&a.config)
        .with_context(|| "--config: choose c1, c3, c4, c5 or fv".to_string())?;
    match &mut arch.task {
        Task::C5 { views, grid } | Task::Fv { views, grid } => {
            *grid = a.grid.unwrap_or(*grid);
            *views = a.views.unwrap_or(*views);
        }
        _ if a.grid.is_some() || a.views.is_some() => {
            bail!("--grid and --views apply to c5 and fv only")
        }
        _ => {}
    }
    if let Some(u) = a.unet_channels {
        if !matches!(arch.task, Task::Fv { .. }) {
            bail!("--unet-channels applies to fv only");
        }
        arch.unet_channels = u;
    }
    arch.channels = a.channels;
    arch.layers = a.layers;
    arch.rate = a.rate;
    arch.validate()?;
    let mut cfg = TrainConfig::new(arch, a.out.clone());
    cfg.steps = a.steps;
    cfg.batch = a.batch;
    cfg.patch = a.patch;
    cfg.lr = a.lr;
    cfg.scenes = a.scenes;
    cfg.foci_per_scene = a.foci_per_scene;
    cfg.checkpoint_every = a.checkpoint_every;
    cfg.data = DataSpec {
        size: a.size,
        samples: a.samples,
        supersample: a.supersample,
        ..DataSpec::default()
    };
    if let Some(c) = a.cache {
        cfg.cache = c;
    }
    let data_bar = ProgressBar::new(cfg.scenes);
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
    let w = train(&cfg, &mut |e| match e {
        TrainEvent::Data { done, .. } => {
            data_bar.set_position(done);
            if done == cfg.scenes {
                data_bar.finish();
            }
        }
        TrainEvent::Resumed { step } => {
            step_bar.set_position(step);
            step_bar.println(format!("resumed at step {step}"));
        }
        TrainEvent::Step { step, loss } => {
            let m = ema.map_or(loss, |m| 0.98 * m + 0.02 * loss);
            ema = Some(m);
            step_bar.set_position(step);
            step_bar.set_message(format!("loss {loss:.4} (avg {m:.4})"));
            // Plain lines too, for logs when stdout is not a terminal.
            if step % 50 == 0 || step <= 3 {
                step_bar.suspend(|| println!("step {step} loss {loss:.5} avg {m:.5}"));
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
