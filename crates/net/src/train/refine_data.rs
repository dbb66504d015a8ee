//! Training data of the refinement nets (C1R, C4R): the classical results they correct,
//! computed once per scene and focus, and where to sample patches.
//!
//! C1R: the classical render at every training focus, and the error map's tiles
//! ([`crate::refine::error_tiles_with`], the map inference uses, at the trainer's own-blur
//! threshold). Patches are drawn around tiles that run, a set fraction of them in proportion
//! to the classical render's squared error there against the thin-lens target (the issue's
//! "where the classical method errs") and the rest uniformly; the loss covers the pixels of
//! those tiles the map corrects (its pixel gate, as inference composes). C4R: the layers of
//! its classical decomposition (linear blending, or the spectral decomposition, cached on
//! disk), and, when it distils, optimized blending's layers (fitting the thin-lens focal
//! stack, 100 iterations from linear) to distil before fine-tuning through the retina, cached
//! on disk too.

use super::data::{fnv, Batch, SceneData};
use crate::arch::{Classical, ClassicalLayers, Task, COC_NORM, DEPTH_NORM};
use crate::cpu::Act;
use crate::error::NetError;
use crate::fv::grid_positions;
use crate::refine::{
    c4r_input, classical_defocus, classical_layers, error_tiles_with, refine_view_input,
    view_tiles, TileMap, TILE,
};
use crate::weights::SplitMix;
use dioptra_core::image::linear_to_srgb;
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage};
use dioptra_render::multifocal::{linear_blend, optimized_blend};
use dioptra_render::views::{synthesize_view_with_errors, RgbdView};
use dioptra_render::{Cpu, OptimizeParams, SpectralParams};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::path::Path;

/// Iterations of the optimized blending C4R distils.
pub const DISTILL_ITERATIONS: usize = 100;

/// A training scene with what its refinement net corrects.
pub struct RefineScene {
    pub data: SceneData,
    /// The eye the scene was rendered for (its field spread over the render's width).
    pub eye: EyeModel,
    /// C1R: the classical render at each of `data.foci`; C4R: its classical layers.
    pub base: Vec<RgbImage>,
    /// C1R: the error map at each focus.
    pub tiles: Vec<TileMap>,
    /// C4R: optimized blending's layers (when it distils them).
    pub distill: Vec<RgbImage>,
}

/// Tiles to centre C1R patches on: (scene, focus, tile), with cumulative weights.
pub struct TileSampler {
    entries: Vec<(usize, usize, usize)>,
    cumulative: Vec<f64>,
}

impl TileSampler {
    /// Tiles `entries` (sample, slot, tile) with the classical result's squared error
    /// `errors` there: drawn uniformly, and `error_weighted` of the draws in proportion to
    /// the error.
    fn new(
        entries: Vec<(usize, usize, usize)>,
        errors: &[f64],
        error_weighted: f64,
    ) -> Result<TileSampler, NetError> {
        if entries.is_empty() {
            return Err(NetError::Data(
                "no training sample has a tile the error map marks: nothing to refine".into(),
            ));
        }
        let (n, sum) = (entries.len() as f64, errors.iter().sum::<f64>().max(1e-12));
        let k = error_weighted.clamp(0.0, 1.0);
        let mut acc = 0.0;
        let cumulative = errors
            .iter()
            .map(|e| {
                acc += (1.0 - k) / n + k * e / sum;
                acc
            })
            .collect();
        Ok(TileSampler {
            entries,
            cumulative,
        })
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
    fn pick(&self, rng: &mut SplitMix) -> (usize, usize, usize) {
        let total = self.cumulative.last().copied().unwrap_or(0.0);
        let u = (0.5 + 0.5 * rng.uniform() as f64) * total;
        let i = self.cumulative.partition_point(|&c| c <= u);
        self.entries[i.min(self.entries.len() - 1)]
    }
}

fn sq_err_srgb(a: &RgbImage, b: &RgbImage, x0: usize, y0: usize, x1: usize, y1: usize) -> f64 {
    let w = a.width();
    let mut s = 0.0f64;
    for (pa, pb) in a.channels.iter().zip(&b.channels) {
        for y in y0..y1 {
            for x in x0..x1 {
                let e = linear_to_srgb(pa.data()[y * w + x]) - linear_to_srgb(pb.data()[y * w + x]);
                s += f64::from(e * e);
            }
        }
    }
    s
}

/// C1R: the classical renders and error maps of every scene, and the tile sampler.
pub fn prepare_c1r(
    scenes: Vec<(SceneData, EyeModel)>,
    classical: Classical,
    error_weighted: f64,
    own_blur_px: f32,
    on: &mut dyn FnMut(usize, usize),
) -> Result<(Vec<RefineScene>, TileSampler), NetError> {
    let total = scenes.len();
    let mut out = Vec::with_capacity(total);
    let (mut entries, mut errors) = (Vec::new(), Vec::new());
    for (si, (data, eye)) in scenes.into_iter().enumerate() {
        let mut base = Vec::with_capacity(data.foci.len());
        let mut tiles = Vec::with_capacity(data.foci.len());
        for (k, &q) in data.foci.iter().enumerate() {
            let img = classical_defocus(&Cpu, classical, &data.rgbd, Diopters(q), &eye)?;
            let map = error_tiles_with(&data.rgbd.depth, Diopters(q), &eye, own_blur_px)?;
            for (t, _) in map.on.iter().enumerate().filter(|(_, &on)| on) {
                let (tx, ty) = ((t % map.cols) * TILE, (t / map.cols) * TILE);
                let (x1, y1) = ((tx + TILE).min(map.width), (ty + TILE).min(map.height));
                entries.push((si, k, t));
                errors.push(sq_err_srgb(&img, &data.stack[k], tx, ty, x1, y1));
            }
            base.push(img);
            tiles.push(map);
        }
        out.push(RefineScene {
            data,
            eye,
            base,
            tiles,
            distill: Vec::new(),
        });
        on(si + 1, total);
    }
    if entries.is_empty() {
        return Err(NetError::Data(
            "no training scene has a depth discontinuity inside the blur: nothing to refine".into(),
        ));
    }
    Ok((out, TileSampler::new(entries, &errors, error_weighted)?))
}

/// C5R: one novel view of a training light field with what the net sees of it.
pub struct C5rView {
    /// The net's input ([`refine_view_input`]: the classical view, its warped depth, the
    /// warp's error map, the offset from the nearest input), HWC.
    pub input: Act,
    /// The view rendered (the target).
    pub target: RgbImage,
    /// The tiles the error map marks.
    pub tiles: TileMap,
}

/// C5R: `novel_views` novel views of each scene's light field (its `views`, a grid over
/// `span` metres; drawn from `seed`, the same on every run), each synthesised from the
/// task's input views with its error map, and the tile sampler over them.
pub fn prepare_c5r(
    scenes: Vec<(SceneData, EyeModel)>,
    task: &Task,
    span: f32,
    novel_views: usize,
    error_weighted: f64,
    seed: u64,
    on: &mut dyn FnMut(usize, usize),
) -> Result<(Vec<C5rView>, TileSampler), NetError> {
    let Task::C5r { grid, .. } = task else {
        return Err(NetError::Input(format!("{} is not c5r", task.name())));
    };
    let picks = task.input_views();
    let positions = grid_positions(*grid, span);
    let total = scenes.len();
    let mut out = Vec::new();
    let (mut entries, mut errors) = (Vec::new(), Vec::new());
    for (si, (data, eye)) in scenes.into_iter().enumerate() {
        if data.views.len() != positions.len() {
            return Err(NetError::Data(format!(
                "scene {} has {} views for a {grid}x{grid} grid",
                data.seed,
                data.views.len()
            )));
        }
        let inputs: Vec<RgbdView> = picks
            .iter()
            .map(|&k| RgbdView {
                position: positions[k],
                rgbd: data.views[k].clone(),
            })
            .collect();
        // A partial Fisher-Yates shuffle of the novel views, from the scene's seed.
        let mut novel: Vec<usize> = (0..positions.len())
            .filter(|k| !picks.contains(k))
            .collect();
        let mut rng = SplitMix(seed ^ data.seed.wrapping_mul(0x9e37_79b9_7f4a_7c15));
        let m = novel_views.min(novel.len());
        for i in 0..m {
            let r = i + (rng.next_u64() % (novel.len() - i) as u64) as usize;
            novel.swap(i, r);
        }
        for &k in &novel[..m] {
            let (view, map) = synthesize_view_with_errors(&inputs, positions[k], &eye)?;
            let tiles = view_tiles(&map)?;
            let target = data.views[k].color.clone();
            for (t, _) in tiles.on.iter().enumerate().filter(|(_, &on)| on) {
                let (tx, ty) = ((t % tiles.cols) * TILE, (t / tiles.cols) * TILE);
                let (x1, y1) = ((tx + TILE).min(tiles.width), (ty + TILE).min(tiles.height));
                entries.push((out.len(), 0, t));
                errors.push(sq_err_srgb(&view.color, &target, tx, ty, x1, y1));
            }
            out.push(C5rView {
                input: refine_view_input(&view, &map)?,
                target,
                tiles,
            });
        }
        on(si + 1, total);
    }
    Ok((out, TileSampler::new(entries, &errors, error_weighted)?))
}

fn images_to_bytes(images: &[RgbImage]) -> Vec<u8> {
    images
        .iter()
        .flat_map(|img| img.channels.iter().flat_map(|p| p.data().iter()))
        .flat_map(|v| v.to_le_bytes())
        .collect()
}

fn write_images(path: &Path, images: &[RgbImage]) -> Result<(), NetError> {
    let (w, h) = images.first().map_or((0, 0), |i| (i.width(), i.height()));
    let bytes = images_to_bytes(images);
    let view = TensorView::new(Dtype::F32, vec![images.len(), 3, h, w], &bytes)
        .map_err(|e| NetError::Data(e.to_string()))?;
    let data = safetensors::serialize([("images".to_string(), view)], None)
        .map_err(|e| NetError::Data(e.to_string()))?;
    let io = |e: std::io::Error| NetError::Io {
        path: path.display().to_string(),
        source: e,
    };
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, data).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

fn read_images(path: &Path, n: usize, w: usize, h: usize) -> Result<Vec<RgbImage>, NetError> {
    let raw = std::fs::read(path).map_err(|e| NetError::Io {
        path: path.display().to_string(),
        source: e,
    })?;
    let st = SafeTensors::deserialize(&raw).map_err(|e| NetError::Data(e.to_string()))?;
    let t = st
        .tensor("images")
        .map_err(|e| NetError::Data(e.to_string()))?;
    if t.shape() != [n, 3, h, w] {
        return Err(NetError::Data(format!(
            "{}: cached images of shape {:?}",
            path.display(),
            t.shape()
        )));
    }
    let v: Vec<f32> = t
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let plane = |k: usize| Plane::from_vec(w, h, v[k * w * h..][..w * h].to_vec());
    (0..n)
        .map(|i| {
            Ok(RgbImage::from_planes(
                plane(3 * i)?,
                plane(3 * i + 1)?,
                plane(3 * i + 2)?,
            )?)
        })
        .collect()
}

/// C4R: the classical layers of every scene (the net's classical decomposition: linear
/// blending, or the spectral decomposition at [`SpectralParams::default`], read from `cache`
/// or computed and cached), and with `distill` optimized blending's (likewise).
pub fn prepare_c4r(
    scenes: Vec<(SceneData, EyeModel)>,
    task: &Task,
    cache: &Path,
    distill: bool,
    on: &mut dyn FnMut(usize, usize),
) -> Result<Vec<RefineScene>, NetError> {
    let (planes, classical) = c4r_input(task)?;
    let key: String = planes
        .iter()
        .map(|p| format!("{:.2}", p.0))
        .collect::<Vec<_>>()
        .join("-");
    // The spectral settings are part of the key: a change of the defaults recomputes.
    let spectral = SpectralParams::default();
    let spectral_key = fnv(format!("{spectral:?}").into_bytes());
    let total = scenes.len();
    scenes
        .into_iter()
        .enumerate()
        .map(|(i, (data, eye))| {
            let (w, h) = (data.rgbd.width(), data.rgbd.height());
            let name = |what: &str, tail: &str| {
                cache.join(format!(
                    "{what}-{}-{}-{w}px-fov{}-{key}-{tail}.safetensors",
                    data.family.name(),
                    data.seed,
                    eye.fov_horizontal_deg
                ))
            };
            let cached = |path: &Path, make: &dyn Fn() -> Result<Vec<RgbImage>, NetError>| {
                match read_images(path, planes.len(), w, h) {
                    Ok(v) => Ok(v),
                    // A missing or corrupt entry is recomputed.
                    Err(_) => {
                        let v = make()?;
                        write_images(path, &v)?;
                        Ok::<_, NetError>(v)
                    }
                }
            };
            let base = match classical {
                ClassicalLayers::Linear => linear_blend(&data.rgbd, &planes)?.images,
                ClassicalLayers::Spectral => {
                    cached(&name("spectral", &format!("{spectral_key:016x}")), &|| {
                        Ok(classical_layers(&Cpu, classical, &data.rgbd, &planes, &eye)?.images)
                    })?
                }
            };
            let distill = if distill {
                cached(
                    &name("distill", &format!("{DISTILL_ITERATIONS}it")),
                    &|| {
                        let foci: Vec<Diopters> = data.foci.iter().map(|&q| Diopters(q)).collect();
                        let linear = linear_blend(&data.rgbd, &planes)?;
                        let (l, _) = optimized_blend(
                            &data.stack,
                            &foci,
                            &planes,
                            &eye,
                            Some(&linear),
                            OptimizeParams {
                                iterations: DISTILL_ITERATIONS,
                                tolerance: 0.0,
                            },
                            |_| {},
                        )?;
                        Ok(l.images)
                    },
                )?
            } else {
                Vec::new()
            };
            on(i + 1, total);
            Ok(RefineScene {
                data,
                eye,
                base,
                tiles: Vec::new(),
                distill,
            })
        })
        .collect()
}

/// Copies the `patch` x `patch` window at `(x0, y0)` of `p`, mapped by `f`, into `out`.
fn crop(p: &Plane, x0: usize, y0: usize, patch: usize, out: &mut Vec<f32>, f: impl Fn(f32) -> f32) {
    for y in y0..y0 + patch {
        out.extend(p.row(y)[x0..x0 + patch].iter().map(|&v| f(v)));
    }
}

/// A batch of C1R patches centred (with jitter) on sampled tiles: inputs (8 channels), the
/// thin-lens targets (3) and the loss mask (1: pixels of tiles that run, away from the patch
/// edges the zero padding reaches, `halo` pixels, except where the patch edge is the image's).
#[allow(clippy::too_many_arguments)]
pub fn sample_c1r_batch(
    scenes: &[RefineScene],
    sampler: &TileSampler,
    rng: &mut SplitMix,
    n: usize,
    patch: usize,
    align: usize,
    halo: usize,
) -> Result<Batch, NetError> {
    check_tile_patch(patch, halo)?;
    let mut input = Vec::with_capacity(n * 8 * patch * patch);
    let mut target = Vec::with_capacity(n * 3 * patch * patch);
    let mut mask = Vec::with_capacity(n * patch * patch);
    for _ in 0..n {
        let (si, k, t) = sampler.pick(rng);
        let s = &scenes[si];
        let (w, h) = (s.data.rgbd.width(), s.data.rgbd.height());
        if w < patch || h < patch {
            return Err(NetError::Data(format!(
                "patch {patch} is larger than the {w}x{h} renders"
            )));
        }
        let map = &s.tiles[k];
        let (x0, y0) = tile_patch_origin(map, t, rng, patch, align, halo);
        let q = Diopters(s.data.foci[k]);
        let rgbd = &s.data.rgbd;
        for c in &rgbd.color.channels {
            crop(c, x0, y0, patch, &mut input, |v| v);
        }
        crop(rgbd.depth.plane(), x0, y0, patch, &mut input, |d| {
            d / DEPTH_NORM
        });
        crop(rgbd.depth.plane(), x0, y0, patch, &mut input, |d| {
            s.eye.coc_px(Diopters(d), q) / COC_NORM
        });
        for c in &s.base[k].channels {
            crop(c, x0, y0, patch, &mut input, |v| v);
        }
        for c in &s.data.stack[k].channels {
            crop(c, x0, y0, patch, &mut target, |v| v);
        }
        push_tile_mask(map, x0, y0, patch, halo, &mut mask);
    }
    Ok(Batch {
        input,
        in_channels: 8,
        target,
        target_channels: 3,
        n,
        patch,
        mask: Some(mask),
        distill: None,
        foci: None,
    })
}

/// Refuses a patch with no room for a tile inside the net's `halo`.
fn check_tile_patch(patch: usize, halo: usize) -> Result<(), NetError> {
    if patch < 2 * halo + TILE {
        return Err(NetError::Input(format!(
            "patch {patch} leaves no room for a {TILE} px tile inside the net's {halo} px halo: use at least {}",
            2 * halo + TILE
        )));
    }
    Ok(())
}

/// The origin of a `patch` window holding tile `t` of `map` anywhere inside its interior
/// (`halo` px from its edges), drawn from `rng` (x, then y), on the `align` grid. The caller
/// checks that the patch fits the image and `patch >= 2 halo + TILE`.
fn tile_patch_origin(
    map: &TileMap,
    t: usize,
    rng: &mut SplitMix,
    patch: usize,
    align: usize,
    halo: usize,
) -> (usize, usize) {
    let (tx, ty) = ((t % map.cols) * TILE, (t / map.cols) * TILE);
    let slack = patch - 2 * halo - TILE;
    let mut origin = |c: usize, size: usize| {
        let j = (rng.next_u64() % (slack as u64 + 1)) as usize;
        let o = (c + TILE + halo + j).saturating_sub(patch);
        (o.min(size - patch) / align) * align
    };
    let x0 = origin(tx, map.width);
    (x0, origin(ty, map.height))
}

/// Appends the loss mask of the `patch` window at `(x0, y0)`: the pixels `map` corrects, away
/// from the patch edges the zero padding reaches (`halo` px) except where the patch edge is
/// the image's.
fn push_tile_mask(
    map: &TileMap,
    x0: usize,
    y0: usize,
    patch: usize,
    halo: usize,
    mask: &mut Vec<f32>,
) {
    let lo = |o: usize| if o == 0 { 0 } else { halo };
    let hi = |o: usize, size: usize| {
        if o + patch == size {
            patch
        } else {
            patch - halo
        }
    };
    let (xa, xb, ya, yb) = (lo(x0), hi(x0, map.width), lo(y0), hi(y0, map.height));
    for py in 0..patch {
        for px in 0..patch {
            let inside = (xa..xb).contains(&px) && (ya..yb).contains(&py);
            mask.push(f32::from(u8::from(
                inside && map.corrects(x0 + px, y0 + py),
            )));
        }
    }
}

/// A batch of C5R patches centred (with jitter) on sampled tiles, as C1R's: inputs (9
/// channels), the rendered views (3) and the loss mask (the pixels the error map marks,
/// inside the halo).
pub fn sample_c5r_batch(
    views: &[C5rView],
    sampler: &TileSampler,
    rng: &mut SplitMix,
    n: usize,
    patch: usize,
    align: usize,
    halo: usize,
) -> Result<Batch, NetError> {
    check_tile_patch(patch, halo)?;
    let cin = 9;
    let mut input = Vec::with_capacity(n * cin * patch * patch);
    let mut target = Vec::with_capacity(n * 3 * patch * patch);
    let mut mask = Vec::with_capacity(n * patch * patch);
    for _ in 0..n {
        let (vi, _, t) = sampler.pick(rng);
        let v = &views[vi];
        let (w, h) = (v.input.w, v.input.h);
        if w < patch || h < patch || v.input.c != cin {
            return Err(NetError::Data(format!(
                "patch {patch} of a {w}x{h}x{} input",
                v.input.c
            )));
        }
        let (x0, y0) = tile_patch_origin(&v.tiles, t, rng, patch, align, halo);
        for c in 0..cin {
            for y in y0..y0 + patch {
                let row = &v.input.data[(y * w + x0) * cin..(y * w + x0 + patch) * cin];
                input.extend(row.iter().skip(c).step_by(cin));
            }
        }
        for c in &v.target.channels {
            crop(c, x0, y0, patch, &mut target, |v| v);
        }
        push_tile_mask(&v.tiles, x0, y0, patch, halo, &mut mask);
    }
    Ok(Batch {
        input,
        in_channels: cin,
        target,
        target_channels: 3,
        n,
        patch,
        mask: Some(mask),
        distill: None,
        foci: None,
    })
}

/// C4R's retinal loss is scored at this many of the foci per step, drawn afresh each step
/// (the retinal model at all 22 costs more than the net).
pub const C4R_FOCI_PER_STEP: usize = 8;

/// A batch of random C4R patches: inputs (RGB, depth, classical layers), the thin-lens focal
/// stack (3 per focus), optimized blending's layers (3 per plane, when distilling) and the
/// foci scored.
pub fn sample_c4r_batch(
    scenes: &[RefineScene],
    rng: &mut SplitMix,
    n: usize,
    patch: usize,
    align: usize,
) -> Result<Batch, NetError> {
    let m = scenes.first().map_or(0, |s| s.base.len());
    let j = scenes.first().map_or(0, |s| s.data.stack.len());
    let cin = 4 + 3 * m;
    let mut input = Vec::with_capacity(n * cin * patch * patch);
    let mut target = Vec::with_capacity(n * 3 * j * patch * patch);
    let mut distill = Vec::with_capacity(n * 3 * m * patch * patch);
    for _ in 0..n {
        let s = &scenes[(rng.next_u64() % scenes.len() as u64) as usize];
        let (w, h) = (s.data.rgbd.width(), s.data.rgbd.height());
        if w < patch || h < patch || s.base.len() != m || s.data.stack.len() != j {
            return Err(NetError::Data(format!(
                "scene {}: patch {patch} of a {w}x{h} render, {} layers and {} slices (expected {m} and {j})",
                s.data.seed,
                s.base.len(),
                s.data.stack.len()
            )));
        }
        let mut pick =
            |size: usize| ((rng.next_u64() % ((size - patch) / align + 1) as u64) as usize) * align;
        let (x0, y0) = (pick(w), pick(h));
        let rgbd = &s.data.rgbd;
        for c in &rgbd.color.channels {
            crop(c, x0, y0, patch, &mut input, |v| v);
        }
        crop(rgbd.depth.plane(), x0, y0, patch, &mut input, |d| {
            d / DEPTH_NORM
        });
        for img in &s.base {
            for c in &img.channels {
                crop(c, x0, y0, patch, &mut input, |v| v);
            }
        }
        for img in &s.data.stack {
            for c in &img.channels {
                crop(c, x0, y0, patch, &mut target, |v| v);
            }
        }
        for img in &s.distill {
            for c in &img.channels {
                crop(c, x0, y0, patch, &mut distill, |v| v);
            }
        }
    }
    // A partial Fisher-Yates shuffle: the first k of a permutation of the foci.
    let mut order: Vec<u32> = (0..j as u32).collect();
    let k = C4R_FOCI_PER_STEP.min(j);
    for i in 0..k {
        let r = i + (rng.next_u64() % (j - i) as u64) as usize;
        order.swap(i, r);
    }
    order.truncate(k);
    Ok(Batch {
        input,
        in_channels: cin,
        target,
        target_channels: 3 * j,
        n,
        patch,
        mask: None,
        distill: Some(distill),
        foci: Some(order),
    })
}
