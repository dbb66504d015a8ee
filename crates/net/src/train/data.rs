//! Training data from the scene simulator: training seeds only, renders cached on disk as
//! safetensors so a resumed or repeated run does not re-render.
//!
//! C5 and FV train on view grids: pinhole RGB-D renders from `grid` x `grid` lens-plane
//! positions spanning the pupil (the views the eye integrates; 2 mm apart on the default 3x3
//! grid over a 4 mm pupil, about 3 px of disparity at 4 D on 128 px, close to the paper's
//! 2.5 px between adjacent views). FV's inputs are foveated per sample (see [`sample_batch`]).

use crate::arch::{Task, COC_NORM, DEPTH_NORM};
use crate::error::NetError;
use crate::fv::{foveate_view, grid_positions, push_view_pixel, view_mask, FoveatedView};
use crate::weights::SplitMix;
use dioptra_core::{DepthMap, Diopters, EyeModel, Millimeters, Plane, RgbImage, Rgbd};
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Family, Scene, Split};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// How training scenes are rendered.
#[derive(Debug, Clone, PartialEq)]
pub struct DataSpec {
    /// Square render size, pixels (the eye's field spans it).
    pub size: usize,
    /// Supersampling of the pinhole colour (per side).
    pub supersample: usize,
    /// Thin-lens rays per pixel of the targets.
    pub samples: u32,
    pub fov_deg: f32,
    pub pupil_mm: f32,
    /// The generator of the scenes ([`Scene::of_family`]).
    pub family: Family,
}

impl Default for DataSpec {
    fn default() -> Self {
        DataSpec {
            size: 256,
            supersample: 4,
            samples: 64,
            fov_deg: 20.0,
            pupil_mm: 4.0,
            family: Family::Random,
        }
    }
}

impl DataSpec {
    pub fn eye(&self) -> Result<EyeModel, NetError> {
        let w = u32::try_from(self.size).map_err(|_| NetError::Data("size too large".into()))?;
        Ok(EyeModel {
            pupil_diameter: Millimeters(self.pupil_mm),
            fov_horizontal_deg: self.fov_deg,
            ..EyeModel::default()
        }
        .with_width(w)
        .validated()?)
    }
}

/// One rendered training scene: the RGB-D input and thin-lens targets at `foci`.
#[derive(Debug, Clone)]
pub struct SceneData {
    pub seed: u64,
    /// The generator of the scene (seeds are numbered per family).
    pub family: Family,
    pub rgbd: Rgbd,
    pub foci: Vec<f32>,
    pub stack: Vec<RgbImage>,
    /// C5 and FV: every view of the grid, row-major (`rgbd` is the centre view).
    pub views: Vec<Rgbd>,
}

/// The foci a scene's targets are rendered at: the network's own for C3/C4; for C1, `k`
/// foci drawn uniformly over 0.1-4.0 D from the seed.
pub fn scene_foci(task: &Task, seed: u64, k: usize) -> Vec<f32> {
    match task {
        Task::C3 { foci } | Task::C4 { foci, .. } | Task::C4r { foci, .. } => foci.clone(),
        _ => {
            let mut r = SplitMix(seed ^ 0x5eed_f0c1);
            let mut f: Vec<f32> = (0..k)
                .map(|_| 0.1 + 3.9 * (0.5 + 0.5 * r.uniform()))
                .collect();
            f.sort_by(f32::total_cmp);
            f
        }
    }
}

pub(crate) fn fnv(bytes: impl IntoIterator<Item = u8>) -> u64 {
    bytes.into_iter().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
    })
}

fn cache_path(dir: &Path, seed: u64, foci: &[f32], spec: &DataSpec) -> PathBuf {
    let key = fnv(foci
        .iter()
        .chain(&[spec.fov_deg, spec.pupil_mm])
        .flat_map(|f| f.to_le_bytes()));
    dir.join(format!(
        "{}-{seed}-{}px-{}ss-{}spp-{key:016x}.safetensors",
        spec.family.name(),
        spec.size,
        spec.supersample,
        spec.samples
    ))
}

fn planes(img: &RgbImage) -> Vec<f32> {
    img.channels
        .iter()
        .flat_map(|p| p.data().iter().copied())
        .collect()
}

fn image(w: usize, h: usize, d: &[f32]) -> Result<RgbImage, NetError> {
    let n = w * h;
    if d.len() != 3 * n {
        return Err(NetError::Data("cached image has the wrong size".into()));
    }
    let p = |k: usize| Plane::from_vec(w, h, d[k * n..(k + 1) * n].to_vec());
    Ok(RgbImage::from_planes(p(0)?, p(1)?, p(2)?)?)
}

fn write_cache(path: &Path, s: &SceneData) -> Result<(), NetError> {
    let (w, h) = (s.rgbd.width(), s.rgbd.height());
    let mut t: Vec<(String, Vec<usize>, Vec<u8>)> = vec![
        ("color".into(), vec![3, h, w], bytes(&planes(&s.rgbd.color))),
        ("depth".into(), vec![h, w], bytes(s.rgbd.depth.data())),
        ("foci".into(), vec![s.foci.len()], bytes(&s.foci)),
    ];
    for (k, img) in s.stack.iter().enumerate() {
        t.push((format!("slice{k}"), vec![3, h, w], bytes(&planes(img))));
    }
    let views = t
        .iter()
        .map(|(n, sh, d)| TensorView::new(Dtype::F32, sh.clone(), d).map(|v| (n.clone(), v)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| NetError::Data(e.to_string()))?;
    let meta: HashMap<String, String> = [("seed".to_string(), s.seed.to_string())].into();
    let data =
        safetensors::serialize(views, Some(meta)).map_err(|e| NetError::Data(e.to_string()))?;
    let tmp = path.with_extension("tmp");
    let io = |e: std::io::Error| NetError::Io {
        path: path.display().to_string(),
        source: e,
    };
    std::fs::write(&tmp, data).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

fn bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// A cache file's bytes.
fn read_raw(path: &Path) -> Result<Vec<u8>, NetError> {
    std::fs::read(path).map_err(|e| NetError::Io {
        path: path.display().to_string(),
        source: e,
    })
}

/// One f32 tensor of a cached safetensors file: (shape, values).
fn tensor_f32(raw: &[u8], name: &str) -> Result<(Vec<usize>, Vec<f32>), NetError> {
    let st = SafeTensors::deserialize(raw).map_err(|e| NetError::Data(e.to_string()))?;
    let v = st
        .tensor(name)
        .map_err(|e| NetError::Data(format!("{name}: {e}")))?;
    let d = v
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    Ok((v.shape().to_vec(), d))
}

fn read_cache(path: &Path, seed: u64, family: Family, foci: &[f32]) -> Result<SceneData, NetError> {
    let raw = read_raw(path)?;
    let get = |name: &str| tensor_f32(&raw, name);
    let (ds, depth) = get("depth")?;
    let [h, w] = ds[..] else {
        return Err(NetError::Data("cached depth is not 2-D".into()));
    };
    let color = image(w, h, &get("color")?.1)?;
    let depth = DepthMap::from_diopters(Plane::from_vec(w, h, depth)?)?;
    let stack = (0..foci.len())
        .map(|k| image(w, h, &get(&format!("slice{k}"))?.1))
        .collect::<Result<_, _>>()?;
    if get("foci")?.1 != foci {
        return Err(NetError::Data("cached foci differ".into()));
    }
    Ok(SceneData {
        seed,
        family,
        rgbd: Rgbd::new(color, depth)?,
        foci: foci.to_vec(),
        stack,
        views: Vec::new(),
    })
}

/// Renders scene `seed` (a training seed) with targets at `foci`, or reads it from `cache`.
pub fn load_or_render(
    cache: &Path,
    seed: u64,
    foci: &[f32],
    spec: &DataSpec,
) -> Result<SceneData, NetError> {
    if Split::of(seed) == Split::Test {
        return Err(NetError::Data(format!(
            "seed {seed} is a test seed: training uses only training seeds"
        )));
    }
    let path = cache_path(cache, seed, foci, spec);
    if path.exists() {
        // A corrupt cache entry is re-rendered rather than trusted.
        if let Ok(s) = read_cache(&path, seed, spec.family, foci) {
            return Ok(s);
        }
    }
    let cam = Camera::square(spec.eye()?, spec.size);
    let scene = Scene::of_family(spec.family, seed);
    let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], spec.supersample)?;
    let stack = foci
        .iter()
        .map(|&q| render_thin_lens(&scene, &cam, Diopters(q), spec.samples))
        .collect::<Result<Vec<_>, _>>()?;
    let s = SceneData {
        seed,
        family: spec.family,
        rgbd: Rgbd::new(color, depth)?,
        foci: foci.to_vec(),
        stack,
        views: Vec::new(),
    };
    std::fs::create_dir_all(cache).map_err(|e| NetError::Io {
        path: cache.display().to_string(),
        source: e,
    })?;
    write_cache(&path, &s)?;
    Ok(s)
}

/// The grid views of scene `seed` (a training seed of `spec.family`) for a `grid` x `grid`
/// grid over a `span` metres square (C5, FV: the pupil), rendered or read from `cache`, as a
/// [`SceneData`] whose `rgbd` is the centre view.
pub fn load_or_render_views(
    cache: &Path,
    seed: u64,
    grid: usize,
    span: f32,
    spec: &DataSpec,
) -> Result<SceneData, NetError> {
    if Split::of(seed) == Split::Test {
        return Err(NetError::Data(format!(
            "seed {seed} is a test seed: training uses only training seeds"
        )));
    }
    let positions = grid_positions(grid, span);
    let key = fnv(positions
        .iter()
        .flatten()
        .chain(&[spec.fov_deg])
        .flat_map(|f| f.to_le_bytes()));
    // The random family keeps the names it was cached under before the others could train here.
    let family = match spec.family {
        Family::Random => String::new(),
        f => format!("{}-", f.name()),
    };
    let path = cache.join(format!(
        "views-{family}{seed}-{grid}x{grid}-{}px-{}ss-{key:016x}.safetensors",
        spec.size, spec.supersample
    ));
    let views = match read_views(&path, positions.len()) {
        // A missing or corrupt cache entry is re-rendered.
        Ok(v) => v,
        Err(_) => {
            let cam = Camera::square(spec.eye()?, spec.size);
            let scene = Scene::of_family(spec.family, seed);
            let views = positions
                .iter()
                .map(|&p| {
                    let (c, d) = render_pinhole(&scene, &cam, p, spec.supersample)?;
                    Ok(Rgbd::new(c, d)?)
                })
                .collect::<Result<Vec<_>, NetError>>()?;
            std::fs::create_dir_all(cache).map_err(|e| NetError::Io {
                path: cache.display().to_string(),
                source: e,
            })?;
            write_views(&path, seed, &views)?;
            views
        }
    };
    Ok(SceneData {
        seed,
        family: spec.family,
        rgbd: views[views.len() / 2].clone(),
        foci: Vec::new(),
        stack: Vec::new(),
        views,
    })
}

fn write_views(path: &Path, seed: u64, views: &[Rgbd]) -> Result<(), NetError> {
    let mut t: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
    for (k, v) in views.iter().enumerate() {
        let (w, h) = (v.width(), v.height());
        t.push((format!("color{k}"), vec![3, h, w], bytes(&planes(&v.color))));
        t.push((format!("depth{k}"), vec![h, w], bytes(v.depth.data())));
    }
    let tv = t
        .iter()
        .map(|(n, sh, d)| TensorView::new(Dtype::F32, sh.clone(), d).map(|v| (n.clone(), v)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| NetError::Data(e.to_string()))?;
    let meta: HashMap<String, String> = [("seed".to_string(), seed.to_string())].into();
    let data = safetensors::serialize(tv, Some(meta)).map_err(|e| NetError::Data(e.to_string()))?;
    let tmp = path.with_extension("tmp");
    let io = |e: std::io::Error| NetError::Io {
        path: path.display().to_string(),
        source: e,
    };
    std::fs::write(&tmp, data).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

fn read_views(path: &Path, n: usize) -> Result<Vec<Rgbd>, NetError> {
    let raw = read_raw(path)?;
    let get = |name: &str| tensor_f32(&raw, name);
    (0..n)
        .map(|k| {
            let (ds, depth) = get(&format!("depth{k}"))?;
            let [h, w] = ds[..] else {
                return Err(NetError::Data("cached depth is not 2-D".into()));
            };
            let color = image(w, h, &get(&format!("color{k}"))?.1)?;
            let depth = DepthMap::from_diopters(Plane::from_vec(w, h, depth)?)?;
            Ok(Rgbd::new(color, depth)?)
        })
        .collect()
}

/// FV's sampling rates, as in the paper's training (sec. 5): log-buffer scale S = 4 for 40 %
/// of the samples, S = 2 for 40 % and every pixel (S = 0) for the rest.
pub fn fv_training_scale(rng: &mut SplitMix) -> Option<f32> {
    match rng.next_u64() % 10 {
        0..=3 => Some(4.0),
        4..=7 => Some(2.0),
        _ => None,
    }
}

/// The nine predetermined gaze positions of FV's training (sec. 5): a 3 x 3 grid at 1/4,
/// 1/2 and 3/4 of the image.
pub fn fv_gazes(width: usize, height: usize) -> Vec<[f32; 2]> {
    let f = [0.25f32, 0.5, 0.75];
    f.iter()
        .flat_map(|&y| {
            f.iter()
                .map(move |&x| [x * width as f32, y * height as f32])
        })
        .collect()
}

/// A batch of random patches: NCHW inputs and targets as flat vectors.
pub struct Batch {
    pub input: Vec<f32>,
    pub in_channels: usize,
    pub target: Vec<f32>,
    pub target_channels: usize,
    pub n: usize,
    pub patch: usize,
    /// Per pixel (N x 1 x P x P), where the loss counts (C1R); everywhere when `None`.
    pub mask: Option<Vec<f32>>,
    /// C4R: optimized blending's layers (N x 3M x P x P), distilled before the retinal loss.
    pub distill: Option<Vec<f32>>,
    /// C4R: the foci (indices) this step's retinal loss is scored at; all when `None`.
    pub foci: Option<Vec<u32>>,
}

/// A random patch origin on the `align` grid (x drawn first, then y: batches depend on it).
fn patch_origin(
    rng: &mut SplitMix,
    w: usize,
    h: usize,
    patch: usize,
    align: usize,
) -> Result<(usize, usize), NetError> {
    if w < patch || h < patch {
        return Err(NetError::Data(format!(
            "patch {patch} is larger than the {w}x{h} renders"
        )));
    }
    let mut pick = |m: usize| (rng.next_u64() % m.max(1) as u64) as usize;
    let x0 = pick((w - patch) / align + 1) * align;
    let y0 = pick((h - patch) / align + 1) * align;
    Ok((x0, y0))
}

/// Samples `n` patches of side `patch` (a multiple of `align`) from `scenes`.
pub fn sample_batch(
    task: &Task,
    scenes: &[SceneData],
    eye: &EyeModel,
    rng: &mut SplitMix,
    n: usize,
    patch: usize,
    align: usize,
) -> Result<Batch, NetError> {
    let (cin, ct) = match task {
        Task::C1 => (5, 3),
        Task::C3 { foci } | Task::C4 { foci, .. } => (4, 3 * foci.len()),
        Task::C5 { .. } | Task::Fv { .. } => {
            return sample_light_field_batch(task, scenes, rng, n, patch, align)
        }
        Task::C1r { .. } | Task::C4r { .. } | Task::C5r { .. } => {
            return Err(NetError::Data(format!(
                "{} batches come from train::refine_data",
                task.name()
            )))
        }
    };
    let mut input = Vec::with_capacity(n * cin * patch * patch);
    let mut target = Vec::with_capacity(n * ct * patch * patch);
    let pick = |r: &mut SplitMix, m: usize| (r.next_u64() % m.max(1) as u64) as usize;
    for _ in 0..n {
        let s = &scenes[pick(rng, scenes.len())];
        let (w, h) = (s.rgbd.width(), s.rgbd.height());
        let (x0, y0) = patch_origin(rng, w, h, patch, align)?;
        let crop = |p: &Plane, out: &mut Vec<f32>, f: &dyn Fn(f32) -> f32| {
            for y in y0..y0 + patch {
                out.extend(p.row(y)[x0..x0 + patch].iter().map(|&v| f(v)));
            }
        };
        let k = pick(rng, s.foci.len());
        for c in &s.rgbd.color.channels {
            crop(c, &mut input, &|v| v);
        }
        crop(s.rgbd.depth.plane(), &mut input, &|d| d / DEPTH_NORM);
        match task {
            Task::C1 => {
                let q = Diopters(s.foci[k]);
                crop(s.rgbd.depth.plane(), &mut input, &|d| {
                    eye.coc_px(Diopters(d), q) / COC_NORM
                });
                for c in &s.stack[k].channels {
                    crop(c, &mut target, &|v| v);
                }
            }
            _ => {
                for img in &s.stack {
                    for c in &img.channels {
                        crop(c, &mut target, &|v| v);
                    }
                }
            }
        }
    }
    Ok(Batch {
        input,
        in_channels: cin,
        target,
        target_channels: ct,
        n,
        patch,
        mask: None,
        distill: None,
        foci: None,
    })
}

/// C5 and FV batches: the input views (C5: RGB-D; FV: foveated at a rate and gaze drawn per
/// sample, every view with its own mask) -> every grid view.
fn sample_light_field_batch(
    task: &Task,
    scenes: &[SceneData],
    rng: &mut SplitMix,
    n: usize,
    patch: usize,
    align: usize,
) -> Result<Batch, NetError> {
    let inputs = task.input_views();
    let fv = matches!(task, Task::Fv { .. });
    let (cin, ct) = (task.in_channels(), task.out_channels());
    let mut input = Vec::with_capacity(n * cin * patch * patch);
    let mut target = Vec::with_capacity(n * ct * patch * patch);
    let pick = |r: &mut SplitMix, m: usize| (r.next_u64() % m.max(1) as u64) as usize;
    for _ in 0..n {
        let s = &scenes[pick(rng, scenes.len())];
        if s.views.len() * 3 != ct {
            return Err(NetError::Data(format!(
                "scene {} has {} views, the {} network predicts {}",
                s.seed,
                s.views.len(),
                task.name(),
                ct / 3
            )));
        }
        let (w, h) = (s.rgbd.width(), s.rgbd.height());
        let (x0, y0) = patch_origin(rng, w, h, patch, align)?;
        let pixels =
            || (y0..y0 + patch).flat_map(move |y| (x0..x0 + patch).map(move |x| y * w + x));
        if fv {
            let gazes = fv_gazes(w, h);
            let gaze = gazes[pick(rng, gazes.len())];
            let scale = fv_training_scale(rng);
            let views = inputs
                .iter()
                .enumerate()
                .map(|(k, &v)| {
                    let m = scale.map(|sc| view_mask(gaze, w, sc, k));
                    foveate_view(&s.views[v], m.as_ref())
                })
                .collect::<Result<Vec<FoveatedView>, NetError>>()?;
            // NCHW: channel-major, 5 channels per view.
            for v in &views {
                let mut px = Vec::with_capacity(5);
                let mut planes: [Vec<f32>; 5] = Default::default();
                for i in pixels() {
                    px.clear();
                    push_view_pixel(v, i, &mut px);
                    for (p, &x) in planes.iter_mut().zip(&px) {
                        p.push(x);
                    }
                }
                planes.iter().for_each(|p| input.extend_from_slice(p));
            }
        } else {
            for &v in &inputs {
                let view = &s.views[v];
                for c in &view.color.channels {
                    input.extend(pixels().map(|i| c.data()[i]));
                }
                input.extend(pixels().map(|i| view.depth.data()[i] / DEPTH_NORM));
            }
        }
        for view in &s.views {
            for c in &view.color.channels {
                target.extend(pixels().map(|i| c.data()[i]));
            }
        }
    }
    Ok(Batch {
        input,
        in_channels: cin,
        target,
        target_channels: ct,
        n,
        patch,
        mask: None,
        distill: None,
        foci: None,
    })
}
