//! The training loop: data, Adam, checkpoints every N steps, resume, export.

use super::data::{
    load_or_render, load_or_render_views, sample_batch, scene_foci, Batch, DataSpec, SceneData,
};
use super::model::{Adam, CandleNet};
use super::refine_data::{
    prepare_c1r, prepare_c4r, prepare_c5r, sample_c1r_batch, sample_c4r_batch, sample_c5r_batch,
    C5rView, RefineScene, TileSampler, DISTILL_ITERATIONS,
};
use super::retina::Retina;
use super::{log_mse, loss, srgb, LossKind};
use crate::arch::{Arch, ClassicalLayers, Task};
use crate::error::NetError;
use crate::refine::TILE;
use crate::weights::{SplitMix, Weights};
use candle_core::{Device, Tensor};
use dioptra_render::SpectralParams;
use dioptra_sim::scene::{Family, Scene};
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
    /// Fields of view (degrees) the training scenes are rendered with, scene `i` with
    /// `fovs[i % len]` (empty: `data.fov_deg` only). A narrower field at the same size has
    /// larger blur in pixels: 10 degrees on 256 px blurs as 20 degrees on 512 px.
    pub fovs: Vec<f32>,
    /// C4R: steps that distil optimized blending's layers before the retinal loss.
    pub distill_steps: u64,
    /// With it, the learning rate falls from `lr` to this by a cosine over the run's steps
    /// (step `s` of `steps` uses `lr_final + (lr - lr_final) (1 + cos(pi s / steps)) / 2`;
    /// it depends only on the step, so a resumed run keeps to it).
    pub lr_final: Option<f64>,
    /// C1R: the fraction of patches centred on tiles drawn by the classical render's error
    /// there (the rest uniformly over the tiles that run).
    pub error_weighted: f64,
    /// C1R: the error map's own-blur threshold (CoC diameter, pixels) for the training
    /// patches and loss ([`crate::refine::error_tiles_with`]; inference uses
    /// [`crate::refine::MIN_OWN_BLUR_PX`], the default).
    pub own_blur_px: f32,
    /// C1R: weight of the "no worse than classical" term: the squared error added in the
    /// 16 x 16 tiles the net made worse, over the batch's classical error (0: off).
    pub no_worse: f64,
    /// Scenes of the occluder family ([`dioptra_sim::scene::Scene::generate_occluders`],
    /// seeds `first_seed ..`) after the `scenes` random ones; for C1 and C1R one focus of
    /// each is its wall's.
    pub occluder_scenes: u64,
    /// Scenes of the wide family ([`dioptra_sim::scene::Scene::generate_wide`], seeds
    /// `first_seed ..`) after the occluder scenes.
    pub wide_scenes: u64,
    /// C5R: novel views per training light field (drawn from `seed`).
    pub novel_views: usize,
}

/// C5R's training light fields span this square (metres): DeepFocus's 9 x 9 over 1 cm, the
/// default of `dioptra lightfield --span`.
pub const C5R_SPAN_M: f32 = 0.01;

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
            fovs: Vec::new(),
            distill_steps: 0,
            lr_final: None,
            error_weighted: 0.5,
            own_blur_px: crate::refine::MIN_OWN_BLUR_PX,
            no_worse: 0.0,
            occluder_scenes: 0,
            wide_scenes: 0,
            novel_views: 16,
        }
    }

    /// The learning rate of step `step` (see [`TrainConfig::lr_final`]).
    pub fn lr_at(&self, step: u64) -> f64 {
        match self.lr_final {
            None => self.lr,
            Some(lo) => {
                let t = step as f64 / self.steps.max(1) as f64;
                lo + (self.lr - lo) * 0.5 * (1.0 + (std::f64::consts::PI * t.min(1.0)).cos())
            }
        }
    }

    /// Random scenes plus occluder and wide scenes.
    pub fn total_scenes(&self) -> u64 {
        self.scenes + self.occluder_scenes + self.wide_scenes
    }

    /// The family and seed of training scene `i`: the random scenes, then the occluder
    /// family's, then the wide family's, each family numbering its seeds from `first_seed`
    /// (different generators, so no scene repeats).
    pub fn scene_of(&self, i: u64) -> (Family, u64) {
        let (family, k) = if i < self.scenes {
            (Family::Random, i)
        } else if i < self.scenes + self.occluder_scenes {
            (Family::Occluders, i - self.scenes)
        } else {
            (Family::Wide, i - self.scenes - self.occluder_scenes)
        };
        (family, self.first_seed + k)
    }

    /// The render settings of training scene `i` (its family, its field of view from `fovs`).
    pub fn spec_of(&self, i: u64) -> DataSpec {
        let mut spec = self.data.clone();
        spec.family = self.scene_of(i).0;
        if !self.fovs.is_empty() {
            spec.fov_deg = self.fovs[(i % self.fovs.len() as u64) as usize];
        }
        spec
    }

    /// The distinct fields of view of the training scenes, in order of first use.
    pub fn distinct_fovs(&self) -> Vec<f32> {
        if self.fovs.is_empty() {
            return vec![self.data.fov_deg];
        }
        let mut out: Vec<f32> = Vec::new();
        for &f in &self.fovs {
            if !out.contains(&f) {
                out.push(f);
            }
        }
        out
    }
}

/// Where one training step's time went, seconds.
#[derive(Debug, Clone, Copy, Default)]
pub struct StepTimes {
    /// Sampling the batch from the cached renders.
    pub data: f64,
    /// The forward pass and the loss.
    pub forward: f64,
    pub backward: f64,
    pub optimiser: f64,
}

#[derive(Debug, Clone)]
pub enum TrainEvent {
    Data {
        done: u64,
        total: u64,
    },
    Resumed {
        step: u64,
    },
    Step {
        step: u64,
        loss: f32,
        times: StepTimes,
    },
    /// Preparing the refinement nets' classical results: scenes done of total.
    Prepare {
        done: u64,
        total: u64,
    },
    Checkpoint {
        step: u64,
    },
    Exported {
        path: PathBuf,
    },
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
    let total = cfg.total_scenes();
    (0..total)
        .map(|i| {
            let (_, seed) = cfg.scene_of(i);
            let spec = cfg.spec_of(i);
            let s = match &cfg.arch.task {
                Task::C5 { grid, .. } | Task::Fv { grid, .. } => {
                    load_or_render_views(&cfg.cache, seed, *grid, spec.pupil_mm * 1e-3, &spec)
                }
                Task::C5r { grid, .. } => {
                    load_or_render_views(&cfg.cache, seed, *grid, C5R_SPAN_M, &spec)
                }
                task => {
                    let mut foci = scene_foci(task, seed, cfg.foci_per_scene);
                    if spec.family == Family::Occluders
                        && matches!(task, Task::C1 | Task::C1r { .. })
                    {
                        // Looking through the occluders at the wall behind them (a fence, a
                        // grid) is the commonest way to meet them and the hardest for C1R, so
                        // one focus of each such scene is its wall's; the rest stay random.
                        if let Some(f) = foci.first_mut() {
                            *f = 1.0 / Scene::generate_occluders(seed).wall_depth;
                        }
                        foci.sort_by(f32::total_cmp);
                    }
                    load_or_render(&cfg.cache, seed, &foci, &spec)
                }
            };
            on(TrainEvent::Data { done: i + 1, total });
            s
        })
        .collect()
}

/// The training data of each kind of net.
enum Data {
    Plain(Vec<SceneData>),
    C1r(Vec<RefineScene>, TileSampler),
    /// The scenes grouped by field of view ([`TrainConfig::distinct_fovs`]'s order), each
    /// group trained through its own retinal model.
    C4r(Vec<Vec<RefineScene>>),
    C5r(Vec<C5rView>, TileSampler),
}

/// One step's loss on a batch (the forward pass and, for C4 and C4R, the retinal model).
///
/// The refinement nets are scored on what inference shows: the classical result plus the
/// correction, clamped to [0, 1]. C1R's loss is the sRGB mean squared error (the PSNR it is
/// judged by) over the tiles that run; C4R's distils optimized blending's layers for
/// `distill_steps`, then is the sRGB error of the retinal focal stack.
fn batch_loss(
    net: &CandleNet,
    retina: Option<&Retina>,
    b: &Batch,
    distilling: bool,
    no_worse: f64,
    dev: &Device,
) -> Result<Tensor, NetError> {
    let shape = |c: usize| (b.n, c, b.patch, b.patch);
    let x = Tensor::from_vec(b.input.clone(), shape(b.in_channels), dev)?;
    let t = Tensor::from_vec(b.target.clone(), shape(b.target_channels), dev)?;
    let y = net.forward(&x)?;
    Ok(match &net.arch.task {
        // Refined pixels against the target on the map's pixels; the classical result is
        // input channels 5..8 of C1R's, 0..3 of C5R's.
        task @ (Task::C1r { .. } | Task::C5r { .. }) => {
            let at = if matches!(task, Task::C1r { .. }) {
                5
            } else {
                0
            };
            let pred = (x.narrow(1, at, 3)? + &y)?.clamp(0f32, 1f32)?;
            let mask = match &b.mask {
                Some(m) => Some(Tensor::from_vec(m.clone(), shape(1), dev)?),
                None => None,
            };
            let (pred, t) = (srgb(&pred)?, srgb(&t)?);
            let l = log_mse(&pred, &t, mask.as_ref())?;
            if no_worse > 0.0 {
                let base = srgb(&x.narrow(1, at, 3)?.clamp(0f32, 1f32)?)?;
                (l + (no_worse_penalty(&pred, &base, &t, mask.as_ref())? * no_worse)?)?
            } else {
                l
            }
        }
        Task::C4r { planes, .. } => {
            let m3 = 3 * planes.len();
            let layers = (x.narrow(1, 4, m3)? + &y)?.clamp(0f32, 1f32)?;
            match (&b.distill, retina, distilling) {
                (Some(d), _, true) => {
                    let d = Tensor::from_vec(d.clone(), shape(m3), dev)?;
                    log_mse(&layers, &d, None)?
                }
                (_, Some(r), _) => {
                    let (seen, t) = match &b.foci {
                        Some(f) => {
                            let ch: Vec<u32> = f
                                .iter()
                                .flat_map(|&j| [3 * j, 3 * j + 1, 3 * j + 2])
                                .collect();
                            let ch = Tensor::from_slice(&ch, ch.len(), dev)?;
                            (r.apply_foci(&layers, Some(f))?, t.index_select(&ch, 1)?)
                        }
                        None => (r.apply(&layers)?, t),
                    };
                    log_mse(&srgb(&r.interior(&seen)?)?, &srgb(&r.interior(&t)?)?, None)?
                }
                _ => {
                    return Err(NetError::Data(
                        "a C4R batch needs optimized layers or the retinal model".into(),
                    ))
                }
            }
        }
        task => {
            let kind = LossKind::for_task(task);
            match retina {
                Some(r) => loss(&r.interior(&r.apply(&y)?)?, &r.interior(&t)?, kind)?,
                None => loss(&y, &t, kind)?,
            }
        }
    })
}

/// How much error the refinement adds where it does harm, relative to the classical error:
/// over the batch's 16 x 16 tiles (the error map's; whole patches when their side is not a
/// multiple), `sum max(0, e(pred) - e(base)) / sum e(base)`, each tile's `e` its summed
/// squared error over its masked pixels (all pixels without a mask). Tiles it improves add
/// nothing, so a gain elsewhere cannot pay for a tile made worse; the harm is weighed in
/// absolute terms (a tile the classical render already gets right weighs no more than its
/// error), so the net is not pushed to give up the tiles where it helps.
fn no_worse_penalty(
    pred: &Tensor,
    base: &Tensor,
    target: &Tensor,
    mask: Option<&Tensor>,
) -> candle_core::Result<Tensor> {
    let (n, c, h, w) = pred.dims4()?;
    let per_tile = |img: &Tensor| -> candle_core::Result<Tensor> {
        let e2 = (img - target)?.sqr()?;
        let e2 = match mask {
            Some(m) => e2.broadcast_mul(m)?,
            None => e2,
        };
        if h % TILE == 0 && w % TILE == 0 {
            e2.reshape((n, c, h / TILE, TILE, w / TILE, TILE))?
                .sum((1, 3, 5))
        } else {
            e2.sum((1, 2, 3))
        }
    };
    let (p, b) = (per_tile(pred)?, per_tile(base)?);
    (p - &b)?.relu()?.sum_all()? / (b.sum_all()? + 1e-6)?
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
    let halo = cfg.arch.layers * cfg.arch.rate;
    if matches!(cfg.arch.task, Task::C1r { .. } | Task::C5r { .. }) && cfg.patch < 2 * halo + TILE {
        return Err(NetError::Input(format!(
            "patch {} leaves no room for a {TILE} px tile inside the net's {halo} px halo ({} layers x rate {}): use at least {}",
            cfg.patch,
            cfg.arch.layers,
            cfg.arch.rate,
            2 * halo + TILE
        )));
    }
    std::fs::create_dir_all(&cfg.out).map_err(io(&cfg.out))?;
    let dev = Device::Cpu;
    let started = Instant::now();
    let scenes = load_scenes(cfg, on)?;
    let eye = cfg.data.eye()?;
    // C4: one retinal model (the data's eye); C4R: one per field of view, the scenes of each
    // trained through their own.
    let retinas = match &cfg.arch.task {
        Task::C4 { planes, foci } => vec![Retina::new(planes, foci, &eye, &dev)?],
        Task::C4r { planes, foci, .. } => cfg
            .distinct_fovs()
            .iter()
            .map(|&f| {
                let eye = DataSpec {
                    fov_deg: f,
                    ..cfg.data.clone()
                }
                .eye()?;
                Ok(Retina::new(planes, foci, &eye, &dev)?)
            })
            .collect::<Result<Vec<_>, NetError>>()?,
        _ => Vec::new(),
    };
    let with_eyes =
        |scenes: Vec<SceneData>| -> Result<Vec<(SceneData, dioptra_core::EyeModel)>, NetError> {
            scenes
                .into_iter()
                .enumerate()
                .map(|(i, s)| Ok((s, cfg.spec_of(i as u64).eye()?)))
                .collect()
        };
    let mut prep = |done: usize, total: usize| {
        on(TrainEvent::Prepare {
            done: done as u64,
            total: total as u64,
        })
    };
    let data = match &cfg.arch.task {
        Task::C1r { classical } => {
            let (s, sampler) = prepare_c1r(
                with_eyes(scenes)?,
                *classical,
                cfg.error_weighted,
                cfg.own_blur_px,
                &mut prep,
            )?;
            Data::C1r(s, sampler)
        }
        Task::C4r { .. } => {
            let fovs = cfg.distinct_fovs();
            let mut groups: Vec<Vec<RefineScene>> = fovs.iter().map(|_| Vec::new()).collect();
            for s in prepare_c4r(
                with_eyes(scenes)?,
                &cfg.arch.task,
                &cfg.cache,
                cfg.distill_steps > 0,
                &mut prep,
            )? {
                let g = fovs
                    .iter()
                    .position(|&f| f == s.eye.fov_horizontal_deg)
                    .ok_or_else(|| {
                        NetError::Data(format!(
                            "scene {}: a field of view not in --fovs",
                            s.data.seed
                        ))
                    })?;
                groups[g].push(s);
            }
            if let Some(g) = groups.iter().position(|g| g.is_empty()) {
                return Err(NetError::Input(format!(
                    "no training scene has the field of view {} degrees: use at least as many scenes as fields of view",
                    fovs[g]
                )));
            }
            Data::C4r(groups)
        }
        Task::C5r { .. } => {
            let (v, sampler) = prepare_c5r(
                with_eyes(scenes)?,
                &cfg.arch.task,
                C5R_SPAN_M,
                cfg.novel_views,
                cfg.error_weighted,
                cfg.seed,
                &mut prep,
            )?;
            Data::C5r(v, sampler)
        }
        _ => Data::Plain(scenes),
    };
    for r in &retinas {
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
        let group = match &data {
            Data::C4r(groups) => (step % groups.len() as u64) as usize,
            _ => 0,
        };
        let t0 = Instant::now();
        let b = match &data {
            Data::Plain(scenes) => sample_batch(
                &cfg.arch.task,
                scenes,
                &eye,
                &mut rng,
                cfg.batch,
                cfg.patch,
                align,
            )?,
            Data::C1r(scenes, sampler) => {
                sample_c1r_batch(scenes, sampler, &mut rng, cfg.batch, cfg.patch, align, halo)?
            }
            // The fields of view take turns, step by step.
            Data::C4r(groups) => {
                sample_c4r_batch(&groups[group], &mut rng, cfg.batch, cfg.patch, align)?
            }
            Data::C5r(views, sampler) => {
                sample_c5r_batch(views, sampler, &mut rng, cfg.batch, cfg.patch, align, halo)?
            }
        };
        let t1 = Instant::now();
        let distilling = step < cfg.distill_steps;
        let retina = retinas.get(group);
        let l = batch_loss(&net, retina, &b, distilling, cfg.no_worse, &dev)?;
        let lv = l.to_scalar::<f32>()?;
        if !lv.is_finite() {
            return Err(NetError::Data(format!(
                "loss became {lv} at step {step}; lower --lr and resume from the last checkpoint"
            )));
        }
        let t2 = Instant::now();
        let grads = l.backward()?;
        let t3 = Instant::now();
        adam.lr = cfg.lr_at(step);
        adam.step(&vars, &grads)?;
        let t4 = Instant::now();
        step += 1;
        let times = StepTimes {
            data: (t1 - t0).as_secs_f64(),
            forward: (t2 - t1).as_secs_f64(),
            backward: (t3 - t2).as_secs_f64(),
            optimiser: (t4 - t3).as_secs_f64(),
        };
        on(TrainEvent::Step {
            step,
            loss: lv,
            times,
        });
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
    if cfg.wide_scenes > 0 {
        p.insert(
            "train_wide_seeds".into(),
            format!(
                "{}..{} (Scene::generate_wide)",
                cfg.first_seed,
                cfg.first_seed + cfg.wide_scenes
            ),
        );
    }
    if cfg.occluder_scenes > 0 {
        // Only C1 and C1R put a focus at the wall (see `load_scenes`).
        let wall_focus = if matches!(cfg.arch.task, Task::C1 | Task::C1r { .. }) {
            ", one focus at the wall"
        } else {
            ""
        };
        p.insert(
            "train_occluder_seeds".into(),
            format!(
                "{}..{} (Scene::generate_occluders{wall_focus})",
                cfg.first_seed,
                cfg.first_seed + cfg.occluder_scenes
            ),
        );
    }
    let data = match &cfg.arch.task {
        Task::C5r { grid, views } => format!(
            "{}px pinhole light fields on a {grid}x{grid} grid over {C5R_SPAN_M} m, {}x{} supersampled, fovs {:?} deg; {} novel views per scene synthesised from {views} inputs",
            cfg.data.size, cfg.data.supersample, cfg.data.supersample, cfg.distinct_fovs(), cfg.novel_views.min(grid * grid - views)
        ),
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
            cfg.data.size,
            cfg.data.supersample,
            cfg.data.supersample,
            cfg.data.samples,
            if cfg.fovs.is_empty() {
                cfg.data.fov_deg.to_string()
            } else {
                format!("{:?}", cfg.fovs)
            },
            cfg.data.pupil_mm,
            cfg.foci_per_scene
        ),
    };
    p.insert("data".into(), data);
    if !cfg.fovs.is_empty() {
        p.insert(
            "fovs".into(),
            format!(
                "{:?} deg, scene i rendered with fovs[i % {}]",
                cfg.fovs,
                cfg.fovs.len()
            ),
        );
    }
    // C1R and C5R: the loss on the map's pixels, the tiles they sample.
    let tile_loss = format!(
        "loss: sRGB MSE (log10) of clamp(classical + net) on the pixels {}{}, patches centred on its tiles ({:.0} % drawn by the classical error there, the rest uniformly)",
        match &cfg.arch.task {
            Task::C1r { .. } => format!("the error map corrects (own-blur threshold {} px)", cfg.own_blur_px),
            _ => "the warp's error map marks".to_string(),
        },
        if cfg.no_worse > 0.0 {
            format!(", plus {} x the error added in the 16 x 16 tiles made worse, over the classical error", cfg.no_worse)
        } else {
            String::new()
        },
        100.0 * cfg.error_weighted
    );
    match &cfg.arch.task {
        Task::C1r { classical } => {
            p.insert(
                "refines".into(),
                format!("{} at the target focus; {tile_loss}", classical.label()),
            );
        }
        Task::C5r { .. } => {
            p.insert(
                "refines".into(),
                format!("dioptra_render::views' forward-warp synthesis; {tile_loss}"),
            );
        }
        Task::C4r { classical, .. } => {
            let input = match classical {
                ClassicalLayers::Linear => "linear blending's layers".to_string(),
                ClassicalLayers::Spectral => format!(
                    "the spectral decomposition's layers (trained on {:?})",
                    SpectralParams::default()
                ),
            };
            let distill = if cfg.distill_steps > 0 {
                format!(
                    "MSE (log10) against optimized blending's layers ({DISTILL_ITERATIONS} iterations fitting the thin-lens stack) for the first {} steps, then ",
                    cfg.distill_steps
                )
            } else {
                String::new()
            };
            p.insert(
                "refines".into(),
                format!(
                    "{input}; loss: {distill}sRGB MSE (log10) of the retinal focal stack{}",
                    if cfg.distinct_fovs().len() > 1 {
                        ", the fields of view taking turns step by step, each through its own retinal model"
                    } else {
                        ""
                    }
                ),
            );
        }
        _ => {}
    }
    p.insert(
        "optimiser".into(),
        format!(
            "Adam lr {}{} batch {} patch {} seed {}",
            cfg.lr,
            cfg.lr_final.map_or(String::new(), |f| format!(
                " cosine to {f} over {} steps",
                cfg.steps
            )),
            cfg.batch,
            cfg.patch,
            cfg.seed
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

#[cfg(test)]
mod tests {
    use super::*;

    fn t(v: &[f32]) -> Tensor {
        Tensor::from_slice(v, (v.len() / 4, 1, 2, 2), &Device::Cpu).unwrap()
    }

    #[test]
    fn no_worse_penalty_counts_only_tiles_made_worse() {
        let target = t(&[0.5; 8]);
        // Patch 0: classical off by 0.1 everywhere (squared error 0.04 per patch), refined off
        // by 0.2 (0.16: a rise of 0.12). Patch 1: refined exact, better than classical (adds
        // nothing, and does not pay for patch 0). Classical error over both: 0.08.
        let base = t(&[0.6, 0.6, 0.6, 0.6, 0.4, 0.4, 0.4, 0.4]);
        let pred = t(&[0.7, 0.7, 0.7, 0.7, 0.5, 0.5, 0.5, 0.5]);
        let p = no_worse_penalty(&pred, &base, &target, None)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!((p - 1.5).abs() < 1e-3, "{p}");
        // Equal to the classical render: nothing.
        let p = no_worse_penalty(&base, &base, &target, None)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert_eq!(p, 0.0);
        // A mask restricts each patch to its pixels: patch 0 worse only outside the mask.
        let pred = t(&[0.6, 0.6, 0.6, 0.9, 0.4, 0.4, 0.4, 0.4]);
        let mask = t(&[1.0, 1.0, 1.0, 0.0, 1.0, 1.0, 1.0, 1.0]);
        let p = no_worse_penalty(&pred, &base, &target, Some(&mask))
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert_eq!(p, 0.0);
        // A 32 x 32 patch is four tiles of equal classical error: one made 4x worse (a rise
        // of 3 tiles' worth), three made exact. The patch as a whole improves, yet the worse
        // tile counts: 3 / 4 of the classical error.
        let size = 2 * TILE;
        let target = Tensor::full(0.5f32, (1, 1, size, size), &Device::Cpu).unwrap();
        let base = Tensor::full(0.6f32, (1, 1, size, size), &Device::Cpu).unwrap();
        let pred: Vec<f32> = (0..size * size)
            .map(|i| {
                if i / size < TILE && i % size < TILE {
                    0.7
                } else {
                    0.5
                }
            })
            .collect();
        let pred = Tensor::from_vec(pred, (1, 1, size, size), &Device::Cpu).unwrap();
        let p = no_worse_penalty(&pred, &base, &target, None)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!((p - 0.75).abs() < 1e-3, "{p}");
    }
}
