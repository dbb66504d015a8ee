//! The training loop: data, Adam, checkpoints every N steps, resume, export.

use super::data::{
    load_or_render, load_or_render_views, sample_batch, scene_foci, DataSpec, SceneData,
};
use super::model::{Adam, CandleNet};
use super::retina::Retina;
use super::{loss, LossKind};
use crate::arch::{Arch, Task};
use crate::error::NetError;
use crate::weights::{SplitMix, Weights};
use candle_core::{Device, Tensor};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Debug, Clone)]
pub struct TrainConfig {
    pub arch: Arch,
    /// Total optimisation steps (a resumed run continues up to this count).
    pub steps: u64,
    pub batch: usize,
    /// Patch side, pixels (a multiple of the interleave rate).
    pub patch: usize,
    pub lr: f64,
    /// Training scenes: seeds `first_seed .. first_seed + scenes` (all training seeds).
    pub scenes: u64,
    pub first_seed: u64,
    /// Targets per scene for C1 (random foci).
    pub foci_per_scene: usize,
    pub data: DataSpec,
    pub out: PathBuf,
    pub cache: PathBuf,
    pub checkpoint_every: u64,
    /// Seed of initialisation and patch sampling.
    pub seed: u64,
}

impl TrainConfig {
    pub fn new(arch: Arch, out: PathBuf) -> TrainConfig {
        TrainConfig {
            arch,
            steps: 20_000,
            batch: 8,
            patch: 128,
            lr: 1e-4,
            scenes: 64,
            first_seed: 0,
            foci_per_scene: 8,
            data: DataSpec::default(),
            cache: out.join("cache"),
            out,
            checkpoint_every: 100,
            seed: 1,
        }
    }
}

#[derive(Debug, Clone)]
pub enum TrainEvent {
    Data { done: u64, total: u64 },
    Resumed { step: u64 },
    Step { step: u64, loss: f32 },
    Checkpoint { step: u64 },
    Exported { path: PathBuf },
}

const CKPT: &str = "checkpoint.safetensors";
const OPT: &str = "optimizer.safetensors";

fn io(path: &Path) -> impl Fn(std::io::Error) -> NetError + '_ {
    move |source| NetError::Io {
        path: path.display().to_string(),
        source,
    }
}

fn save_optimizer(path: &Path, adam: &Adam, step: u64) -> Result<(), NetError> {
    let st = adam.state()?;
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = st
        .into_iter()
        .map(|(n, s, d)| (n, s, d.iter().flat_map(|v| v.to_le_bytes()).collect()))
        .collect();
    let views = bytes
        .iter()
        .map(|(n, s, d)| TensorView::new(Dtype::F32, s.clone(), d).map(|v| (n.clone(), v)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| NetError::Corrupt(e.to_string()))?;
    let meta: HashMap<String, String> = [("step".to_string(), step.to_string())].into();
    let data =
        safetensors::serialize(views, Some(meta)).map_err(|e| NetError::Corrupt(e.to_string()))?;
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, data).map_err(io(path))?;
    std::fs::rename(&tmp, path).map_err(io(path))
}

type Named = HashMap<String, (Vec<usize>, Vec<f32>)>;

fn load_optimizer(path: &Path) -> Result<(u64, Named), NetError> {
    let raw = std::fs::read(path).map_err(io(path))?;
    let (_, meta) =
        SafeTensors::read_metadata(&raw).map_err(|e| NetError::Corrupt(e.to_string()))?;
    let step = meta
        .metadata()
        .as_ref()
        .and_then(|m| m.get("step"))
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| NetError::MissingMetadata(format!("{}: no step", path.display())))?;
    let st = SafeTensors::deserialize(&raw).map_err(|e| NetError::Corrupt(e.to_string()))?;
    let mut out = HashMap::new();
    for (n, v) in st.tensors() {
        let d = v
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        out.insert(n, (v.shape().to_vec(), d));
    }
    Ok((step, out))
}

/// Loads (rendering on first use) every training scene of `cfg`.
pub fn load_scenes(
    cfg: &TrainConfig,
    on: &mut dyn FnMut(TrainEvent),
) -> Result<Vec<SceneData>, NetError> {
    (0..cfg.scenes)
        .map(|i| {
            let seed = cfg.first_seed + i;
            let s = match &cfg.arch.task {
                Task::C5 { grid, .. } | Task::Fv { grid, .. } => {
                    load_or_render_views(&cfg.cache, seed, *grid, &cfg.data)
                }
                task => {
                    let foci = scene_foci(task, seed, cfg.foci_per_scene);
                    load_or_render(&cfg.cache, seed, &foci, &cfg.data)
                }
            };
            on(TrainEvent::Data {
                done: i + 1,
                total: cfg.scenes,
            });
            s
        })
        .collect()
}

/// One step's loss on a batch (the forward pass and, for C4, the retinal model).
fn batch_loss(
    net: &CandleNet,
    retina: Option<&Retina>,
    b: &super::data::Batch,
    dev: &Device,
) -> Result<Tensor, NetError> {
    let x = Tensor::from_vec(b.input.clone(), (b.n, b.in_channels, b.patch, b.patch), dev)?;
    let t = Tensor::from_vec(
        b.target.clone(),
        (b.n, b.target_channels, b.patch, b.patch),
        dev,
    )?;
    let y = net.forward(&x)?;
    let kind = LossKind::for_task(&net.arch.task);
    Ok(match retina {
        Some(r) => loss(&r.interior(&r.apply(&y)?)?, &r.interior(&t)?, kind)?,
        None => loss(&y, &t, kind)?,
    })
}

/// Trains (or resumes training in `cfg.out`) and exports `<config>.safetensors` there.
pub fn train(cfg: &TrainConfig, on: &mut dyn FnMut(TrainEvent)) -> Result<Weights, NetError> {
    cfg.arch.validate()?;
    let align = cfg.arch.size_multiple();
    if cfg.patch == 0 || cfg.patch % align != 0 || cfg.batch == 0 || cfg.scenes == 0 {
        return Err(NetError::Input(format!(
            "patch {} must be a positive multiple of {align} (the rate{}), batch and scenes positive",
            cfg.patch,
            if align > cfg.arch.rate { " x 4 for the U-Net" } else { "" }
        )));
    }
    std::fs::create_dir_all(&cfg.out).map_err(io(&cfg.out))?;
    let dev = Device::Cpu;
    let started = Instant::now();
    let scenes = load_scenes(cfg, on)?;
    let eye = cfg.data.eye()?;
    let retina = match &cfg.arch.task {
        Task::C4 { planes, foci } => Some(Retina::new(planes, foci, &eye, &dev)?),
        _ => None,
    };
    if let Some(r) = &retina {
        if cfg.patch <= 2 * r.radius + 2 {
            return Err(NetError::Input(format!(
                "patch {} is too small for the retinal kernels (radius {})",
                cfg.patch, r.radius
            )));
        }
    }
    let (ckpt, opt_path) = (cfg.out.join(CKPT), cfg.out.join(OPT));
    let (init, mut step) = if ckpt.exists() {
        let w = Weights::load(&ckpt)?;
        if w.arch != cfg.arch {
            return Err(NetError::BadArch(format!(
                "{} holds a different architecture ({}); use another --out or delete it",
                ckpt.display(),
                w.arch.to_json()
            )));
        }
        let step: u64 = w
            .provenance
            .get("step")
            .and_then(|s| s.parse().ok())
            .unwrap_or(0);
        (w, step)
    } else {
        (Weights::random(&cfg.arch, cfg.seed)?, 0)
    };
    let net = CandleNet::from_weights(&init, &dev)?;
    let vars = net.vars();
    let mut adam = Adam::new(&vars, cfg.lr)?;
    if step > 0 {
        let (s, state) = load_optimizer(&opt_path)?;
        if s != step {
            return Err(NetError::Corrupt(format!(
                "{} is at step {s} but the checkpoint at step {step}; delete {} to restart",
                opt_path.display(),
                cfg.out.display()
            )));
        }
        adam.restore(&state)?;
        on(TrainEvent::Resumed { step });
    }
    let checkpoint = |net: &CandleNet, adam: &Adam, step: u64| -> Result<(), NetError> {
        let mut w = net.to_weights()?;
        w.provenance.insert("step".into(), step.to_string());
        save_optimizer(&opt_path, adam, step)?;
        w.save(&ckpt)
    };
    while step < cfg.steps {
        // Batches depend only on (seed, step): a resumed run sees the same data.
        let mut rng =
            SplitMix(cfg.seed.wrapping_mul(0x9e37_79b9) ^ step.wrapping_mul(0x2545_f491_4f6c_dd1d));
        let b = sample_batch(
            &cfg.arch.task,
            &scenes,
            &eye,
            &mut rng,
            cfg.batch,
            cfg.patch,
            align,
        )?;
        let l = batch_loss(&net, retina.as_ref(), &b, &dev)?;
        let lv = l.to_scalar::<f32>()?;
        if !lv.is_finite() {
            return Err(NetError::Data(format!(
                "loss became {lv} at step {step}; lower --lr and resume from the last checkpoint"
            )));
        }
        adam.step(&vars, &l.backward()?)?;
        step += 1;
        on(TrainEvent::Step { step, loss: lv });
        if step % cfg.checkpoint_every.max(1) == 0 || step == cfg.steps {
            checkpoint(&net, &adam, step)?;
            on(TrainEvent::Checkpoint { step });
        }
    }
    let mut w = net.to_weights()?;
    let p = &mut w.provenance;
    p.insert("steps".into(), step.to_string());
    p.insert(
        "train_seeds".into(),
        format!("{}..{}", cfg.first_seed, cfg.first_seed + cfg.scenes),
    );
    let data = match &cfg.arch.task {
        Task::C5 { grid, .. } | Task::Fv { grid, .. } => format!(
            "{}px pinhole views on a {grid}x{grid} grid over the {} mm pupil, {}x{} supersampled, fov {} deg{}",
            cfg.data.size, cfg.data.pupil_mm, cfg.data.supersample, cfg.data.supersample, cfg.data.fov_deg,
            if matches!(cfg.arch.task, Task::Fv { .. }) {
                "; inputs foveated per sample at S = 4 (40 %), S = 2 (40 %) or every pixel (20 %), gaze one of 9"
            } else {
                ""
            }
        ),
        _ => format!(
            "{}px renders, pinhole colour {}x{} supersampled, thin-lens targets {} rays/px, fov {} deg, pupil {} mm, {} foci per scene",
            cfg.data.size, cfg.data.supersample, cfg.data.supersample, cfg.data.samples, cfg.data.fov_deg, cfg.data.pupil_mm, cfg.foci_per_scene
        ),
    };
    p.insert("data".into(), data);
    p.insert(
        "optimiser".into(),
        format!(
            "Adam lr {} batch {} patch {} seed {}",
            cfg.lr, cfg.batch, cfg.patch, cfg.seed
        ),
    );
    p.insert(
        "wall_time_s_this_session".into(),
        format!("{:.0}", started.elapsed().as_secs_f64()),
    );
    let path = cfg
        .out
        .join(format!("{}.safetensors", cfg.arch.task.name()));
    w.save(&path)?;
    on(TrainEvent::Exported { path });
    Ok(w)
}
