//! Refinement nets (C1R, C4R): a classical method everywhere and a small net that learns
//! only its residual (after BokehMe, Peng et al. 2022).
//!
//! C1R runs only where an error map from depth says the classical render is wrong: tiles
//! within the blur radius of a depth discontinuity ([`error_tiles`]). Every other pixel is the
//! classical render, unchanged, and a scene with no discontinuity inside the blur costs
//! nothing beyond the map. The net itself is evaluated only on those tiles plus the halo its
//! receptive field needs ([`crate::CpuNet::forward_tiles`]), so its output there equals a
//! full-image pass exactly.

use crate::arch::{Classical, ClassicalLayers, Task, COC_NORM, DEPTH_NORM, PARALLAX_NORM};
use crate::cpu::{Act, CpuNet};
use crate::error::{input, NetError};
use crate::infer::Infer;
pub use crate::tiles::{TileMap, TILE};
use dioptra_core::{DepthMap, Diopters, EyeModel, RgbImage, Rgbd};
use dioptra_render::composite::{compose, step_reach};
use dioptra_render::retina::LfView;
use dioptra_render::views::{
    light_field_positions, synthesize_view_with_errors, RgbdView, WarpErrors,
};
use dioptra_render::{eye_for, Backend, DefocusMethod, Layers, LightFieldParams, SpectralParams};
use rayon::prelude::*;

pub use dioptra_render::composite::EDGE_BLUR_PX;

/// A pixel whose own blur (CoC diameter, pixels) is below this keeps the classical value even
/// where a blurred step reaches it: it sees itself along nearly every ray through the pupil,
/// so a single view lacks little there and the net's correction was measured to add more
/// error than it removes (validation seeds, not test seeds: see `crates/net/README.md`).
pub const MIN_OWN_BLUR_PX: f32 = 3.0;

/// The error map (BokehMe's, from depth alone): the tiles holding a pixel that
/// [`step_reach`] finds lacking at focus `focus` (reached by a blurred depth step's disk,
/// missing what a single view cannot show, blurred by [`MIN_OWN_BLUR_PX`] or more itself).
/// Those pixels take the net's correction; a tile runs when any of its pixels does.
pub fn error_tiles(depth: &DepthMap, focus: Diopters, eye: &EyeModel) -> Result<TileMap, NetError> {
    error_tiles_with(depth, focus, eye, MIN_OWN_BLUR_PX)
}

/// [`error_tiles`] with another own-blur threshold (CoC diameter, pixels; 0 corrects every
/// pixel a blurred step reaches where a single view lacks something): how the threshold was
/// chosen (`eval_refine ... gate`).
pub fn error_tiles_with(
    depth: &DepthMap,
    focus: Diopters,
    eye: &EyeModel,
    min_own_blur_px: f32,
) -> Result<TileMap, NetError> {
    let reach = step_reach(depth, focus, eye, min_own_blur_px)?;
    let mut map = TileMap::from_pixels(depth.width(), depth.height(), reach.lacking);
    map.reached = reach.reached;
    Ok(map)
}

/// The classical render a C1R net refines.
pub fn classical_defocus(
    backend: &dyn Backend,
    classical: Classical,
    rgbd: &Rgbd,
    focus: Diopters,
    eye: &EyeModel,
) -> Result<RgbImage, NetError> {
    let method = match classical {
        Classical::Gather => DefocusMethod::Gather,
        Classical::Lightfield { views } => {
            DefocusMethod::LightField(LightFieldParams { views, mip: true })
        }
    };
    backend
        .defocus(rgbd, &[focus], eye, method, &|_| {})?
        .pop()
        .ok_or_else(|| input("the classical method made no image"))
}

/// The classical layers a C4R net refines, on `backend`: linear blending, or the spectral
/// decomposition with [`SpectralParams::default`] (the settings the net was trained on when
/// they were the defaults; the weights' provenance names them).
pub fn classical_layers(
    backend: &dyn Backend,
    classical: ClassicalLayers,
    rgbd: &Rgbd,
    planes: &[Diopters],
    eye: &EyeModel,
) -> Result<Layers, NetError> {
    Ok(match classical {
        ClassicalLayers::Linear => backend.linear_blend(rgbd, planes)?,
        ClassicalLayers::Spectral => {
            backend
                .spectral_blend(rgbd, planes, eye, SpectralParams::default())?
                .0
        }
    })
}

/// C1R input: [R, G, B, depth / 4, CoC px / 30, classical R, G, B] per pixel.
pub fn refine_defocus_input(
    rgbd: &Rgbd,
    classical: &RgbImage,
    focus: Diopters,
    eye: &EyeModel,
) -> Result<Act, NetError> {
    let (w, h) = (rgbd.width(), rgbd.height());
    if (classical.width(), classical.height()) != (w, h) {
        return Err(input(format!(
            "the classical render is {}x{}, the RGB-D {w}x{h}",
            classical.width(),
            classical.height()
        )));
    }
    let eye = eye_for(eye, w)?;
    let c = rgbd.color.channels.each_ref().map(|p| p.data());
    let k = classical.channels.each_ref().map(|p| p.data());
    let d = rgbd.depth.data();
    // CoC per diopter of defocus, once (coc_px evaluates a tangent per call).
    let px_per_d = eye.coc_px(Diopters(1.0), Diopters(0.0));
    hwc_input(w, h, |i| {
        [
            c[0][i],
            c[1][i],
            c[2][i],
            d[i] / DEPTH_NORM,
            px_per_d * (d[i] - focus.0).abs() / COC_NORM,
            k[0][i],
            k[1][i],
            k[2][i],
        ]
    })
}

/// A `w` x `h` HWC input of `C` channels, pixel `i` (row-major) holding `pixel(i)`.
fn hwc_input<const C: usize>(
    w: usize,
    h: usize,
    pixel: impl Fn(usize) -> [f32; C] + Sync,
) -> Result<Act, NetError> {
    let mut data = vec![0.0; w * h * C];
    data.par_chunks_mut(w * C).enumerate().for_each(|(y, row)| {
        for (x, px) in row.chunks_exact_mut(C).enumerate() {
            px.copy_from_slice(&pixel(y * w + x));
        }
    });
    Act::new(h, w, C, data)
}

/// C4R input: [R, G, B, depth / 4, then each classical layer's R, G, B] per pixel.
pub fn refine_layers_input(rgbd: &Rgbd, layers: &Layers) -> Result<Act, NetError> {
    let (w, h) = (rgbd.width(), rgbd.height());
    if layers.images.is_empty() || (layers.width(), layers.height()) != (w, h) {
        return Err(input(format!(
            "{} layers of {}x{} for a {w}x{h} RGB-D",
            layers.images.len(),
            layers.width(),
            layers.height()
        )));
    }
    let m = layers.images.len();
    let c = rgbd.color.channels.each_ref().map(|p| p.data());
    let d = rgbd.depth.data();
    let mut data = Vec::with_capacity(w * h * (4 + 3 * m));
    for i in 0..w * h {
        data.extend_from_slice(&[c[0][i], c[1][i], c[2][i], d[i] / DEPTH_NORM]);
        for img in &layers.images {
            data.extend(img.channels.iter().map(|p| p.data()[i]));
        }
    }
    Act::new(h, w, 4 + 3 * m, data)
}

/// C5R input per pixel: the classical view's R, G, B, its warped depth / 4, then the warp's
/// error map (hole 0/1, parallax across a depth step / [`PARALLAX_NORM`], the inputs' colour
/// spread) and the view's parallax per diopter from its nearest input (x, y) /
/// [`PARALLAX_NORM`].
pub fn refine_view_input(view: &Rgbd, errors: &WarpErrors) -> Result<Act, NetError> {
    let (w, h) = (view.width(), view.height());
    if (errors.width, errors.height) != (w, h)
        || [errors.hole.len(), errors.edge_px.len(), errors.spread.len()] != [w * h; 3]
    {
        return Err(input(format!(
            "a {}x{} error map for a {w}x{h} view",
            errors.width, errors.height
        )));
    }
    let c = view.color.channels.each_ref().map(|p| p.data());
    let d = view.depth.data();
    let [ox, oy] = errors.offset_px.map(|o| o / PARALLAX_NORM);
    hwc_input(w, h, |i| {
        [
            c[0][i],
            c[1][i],
            c[2][i],
            d[i] / DEPTH_NORM,
            f32::from(u8::from(errors.hole[i])),
            errors.edge_px[i] / PARALLAX_NORM,
            errors.spread[i],
            ox,
            oy,
        ]
    })
}

/// The tiles C5R runs on: those holding a pixel the warp's error map marks, whose pixels take
/// the correction.
pub fn view_tiles(errors: &WarpErrors) -> Result<TileMap, NetError> {
    if errors.marked.len() != errors.width * errors.height {
        return Err(input(format!(
            "{} marks for a {}x{} error map",
            errors.marked.len(),
            errors.width,
            errors.height
        )));
    }
    Ok(TileMap::from_pixels(
        errors.width,
        errors.height,
        errors.marked.clone(),
    ))
}

/// A `grid` x `grid` light field over a `span` metres square (the positions of
/// [`dioptra_render::views::synthesize_light_field`]), each view synthesised from `inputs`
/// with its error map and then passed to `refine` (a C5R net's `refine_view`); `progress` is
/// called with the views done.
pub fn refine_light_field(
    inputs: &[RgbdView],
    grid: usize,
    span: f32,
    eye: &EyeModel,
    refine: &dyn Fn(&Rgbd, &WarpErrors) -> Result<RgbImage, NetError>,
    progress: &dyn Fn(usize),
) -> Result<Vec<LfView>, NetError> {
    light_field_positions(grid, span)?
        .into_iter()
        .enumerate()
        .map(|(k, position)| {
            let (view, errors) = synthesize_view_with_errors(inputs, position, eye)?;
            let image = refine(&view, &errors)?;
            progress(k + 1);
            Ok(LfView { position, image })
        })
        .collect()
}

/// `clamp(base + correction, 0, 1)` per value, `correction` channels `3k..3k+3` of `y`.
fn corrected(
    base: &RgbImage,
    y: &Act,
    k: usize,
    only: Option<&TileMap>,
) -> Result<RgbImage, NetError> {
    let (w, h) = (base.width(), base.height());
    if 3 * k + 3 > y.c || (y.w, y.h) != (w, h) {
        return Err(input(format!(
            "no RGB correction {k} for a {w}x{h} image in a {}x{}x{} output",
            y.w, y.h, y.c
        )));
    }
    if let Some(t) = only {
        if (t.width, t.height) != (w, h) || t.pixels.len() != w * h {
            return Err(input(format!(
                "a {}x{} tile map for a {w}x{h} image",
                t.width, t.height
            )));
        }
    }
    let mut out = base.clone();
    for (j, o) in out.channels.iter_mut().enumerate() {
        o.data_mut()
            .par_chunks_mut(w)
            .enumerate()
            .for_each(|(row, values)| {
                let fix = &y.data[row * w * y.c..][..w * y.c];
                let gate = only.map(|t| &t.pixels[row * w..][..w]);
                for (x, v) in values.iter_mut().enumerate() {
                    if gate.is_none_or(|g| g[x]) {
                        *v = (*v + fix[x * y.c + 3 * k + j]).clamp(0.0, 1.0);
                    }
                }
            });
    }
    debug_assert_eq!((out.width(), out.height()), (w, h));
    Ok(out)
}

/// The classical result C1R refines, and returns where it does not correct: `classical` (the
/// net's classical method) on the pixels a blurred depth step reaches, gather's value from
/// [`dioptra_render::gather::gather_smooth`] on the rest ([`compose`]). There the depth within
/// each blur disk is smooth, so gather is right and the light field's few views only add their
/// sampling of the pupil (measured: about 2 dB worse there for 12 views, see
/// `crates/net/README.md`).
pub fn classical_composite(
    rgbd: &Rgbd,
    classical: &RgbImage,
    tiles: &TileMap,
    focus: Diopters,
    eye: &EyeModel,
) -> Result<RgbImage, NetError> {
    let (w, h) = (rgbd.width(), rgbd.height());
    if (classical.width(), classical.height()) != (w, h)
        || (tiles.width, tiles.height) != (w, h)
        || tiles.reached.len() != w * h
    {
        return Err(input(format!(
            "a {}x{} classical render and a {}x{} tile map for a {w}x{h} RGB-D",
            classical.width(),
            classical.height(),
            tiles.width,
            tiles.height
        )));
    }
    Ok(compose(rgbd, classical, &tiles.reached, focus, eye)?)
}

/// The refined image: the classical render with the net's correction on the pixels `tiles`
/// corrects (the net's output `y`, channels 0..3); C5R's refined view too.
pub fn compose_defocus(
    classical: &RgbImage,
    y: &Act,
    tiles: &TileMap,
) -> Result<RgbImage, NetError> {
    corrected(classical, y, 0, Some(tiles))
}

/// The refined layers: each of `base`'s layers with its correction, clamped to [0, 1].
pub fn compose_layers(base: &Layers, y: &Act) -> Result<Layers, NetError> {
    Ok(Layers {
        planes: base.planes.clone(),
        images: base
            .images
            .iter()
            .enumerate()
            .map(|(k, img)| corrected(img, y, k, None))
            .collect::<Result<_, _>>()?,
    })
}

/// What a C1R refinement did.
#[derive(Debug, Clone)]
pub struct Refined {
    pub image: RgbImage,
    pub tiles: TileMap,
    /// What the net refines ([`classical_composite`]): `image` without the net's correction.
    pub classical: RgbImage,
}

/// The display planes of a C4R net, checked against the layers it is given.
pub(crate) fn check_planes(task: &Task, layers: &Layers) -> Result<(), NetError> {
    let planes = task.planes().unwrap_or(&[]);
    let given: Vec<f32> = layers.planes.iter().map(|p| p.0).collect();
    if given != planes {
        return Err(input(format!(
            "the net refines layers for planes {planes:?} D, given layers for {given:?} D"
        )));
    }
    Ok(())
}

/// C1R: `classical` (the net's classical method at `focus`, its input) refined on the pixels
/// the error map corrects; every other pixel is [`classical_composite`]'s. The classical
/// composite and the map are computed on the CPU whatever evaluates the net.
pub(crate) fn refine_defocus(
    net: &impl Infer,
    rgbd: &Rgbd,
    classical: &RgbImage,
    focus: Diopters,
    eye: &EyeModel,
) -> Result<Refined, NetError> {
    net.arch().expect_task("c1r")?;
    let tiles = error_tiles(&rgbd.depth, focus, eye)?;
    let base = classical_composite(rgbd, classical, &tiles, focus, eye)?;
    if !tiles.on.contains(&true) {
        return Ok(Refined {
            image: base.clone(),
            tiles,
            classical: base,
        });
    }
    let x = refine_defocus_input(rgbd, classical, focus, eye)?;
    let y = net.forward_on(&x, &tiles)?;
    Ok(Refined {
        image: compose_defocus(&base, &y, &tiles)?,
        tiles,
        classical: base,
    })
}

/// C5R: the classical view `view` (its colour and warped depth, from
/// [`synthesize_view_with_errors`]) refined on the tiles its error map marks; every other
/// pixel keeps the classical value.
pub(crate) fn refine_view(
    net: &impl Infer,
    view: &Rgbd,
    errors: &WarpErrors,
) -> Result<RgbImage, NetError> {
    net.arch().expect_task("c5r")?;
    let tiles = view_tiles(errors)?;
    if !tiles.on.contains(&true) {
        return Ok(view.color.clone());
    }
    let y = net.forward_on(&refine_view_input(view, errors)?, &tiles)?;
    compose_defocus(&view.color, &y, &tiles)
}

/// C4R: `classical` (the layers of the net's classical decomposition for its planes,
/// [`classical_layers`]) refined.
pub(crate) fn refine_decompose(
    net: &impl Infer,
    rgbd: &Rgbd,
    classical: &Layers,
) -> Result<Layers, NetError> {
    net.arch().expect_task("c4r")?;
    check_planes(&net.arch().task, classical)?;
    let y = net.forward(&refine_layers_input(rgbd, classical)?)?;
    compose_layers(classical, &y)
}

impl CpuNet {
    /// C1R: `classical` (the net's classical method at `focus`, its input) refined on the
    /// pixels the error map corrects; every other pixel is [`classical_composite`]'s. The net
    /// is evaluated only on the tiles the map corrects ([`CpuNet::forward_tiles`]).
    pub fn refine_defocus(
        &self,
        rgbd: &Rgbd,
        classical: &RgbImage,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<Refined, NetError> {
        refine_defocus(self, rgbd, classical, focus, eye)
    }

    /// C5R: the classical view `view` (its colour and warped depth, from
    /// [`synthesize_view_with_errors`]) refined on the tiles its error map marks; every other
    /// pixel keeps the classical value.
    pub fn refine_view(&self, view: &Rgbd, errors: &WarpErrors) -> Result<RgbImage, NetError> {
        refine_view(self, view, errors)
    }

    /// C4R: `classical` (the layers of the net's classical decomposition for its planes,
    /// [`classical_layers`]) refined.
    pub fn refine_decompose(&self, rgbd: &Rgbd, classical: &Layers) -> Result<Layers, NetError> {
        refine_decompose(self, rgbd, classical)
    }
}

/// The display planes and the classical decomposition of a C4R net.
pub fn c4r_input(task: &Task) -> Result<(Vec<Diopters>, ClassicalLayers), NetError> {
    match task {
        Task::C4r {
            planes, classical, ..
        } => Ok((planes.iter().map(|&p| Diopters(p)).collect(), *classical)),
        t => Err(NetError::WrongConfig {
            expected: t.name().into(),
            asked: "c4r".into(),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::weights::{SplitMix, Weights};
    use crate::Arch;
    use dioptra_core::Plane;
    use dioptra_render::composite::StepScan;
    use dioptra_render::multifocal::linear_blend;

    /// The default eye with a 5 degree field of view: these small test images then blur by
    /// about 3 px per diopter at 64 px (6 at 128).
    fn eye(w: usize) -> EyeModel {
        EyeModel {
            fov_horizontal_deg: 5.0,
            ..EyeModel::default()
        }
        .with_width(w as u32)
    }

    /// The error map written plainly: serial, one box fill per step (the reference the
    /// parallel [`error_tiles`] must equal).
    fn error_tiles_reference(
        depth: &DepthMap,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<TileMap, NetError> {
        let (w, h) = (depth.width(), depth.height());
        let scan = StepScan::new(depth, focus, eye)?;
        let px_per_d = scan.px_per_d();
        let d = depth.data();
        let q = focus.0;
        let mut map = TileMap::none(w, h);
        // Per pixel: reached by the disk of a nearer side whose farther side blurs too; the
        // smallest step middle (D) among the nearer sides' disks with a sharp farther side
        // reaching it; the largest among the farther sides' disks reaching it.
        let mut near_reach = vec![false; w * h];
        let mut near_middle = vec![f32::INFINITY; w * h];
        let mut far_middle = vec![f32::NEG_INFINITY; w * h];
        for y in 0..h {
            for s in scan.row(y) {
                let (x, y) = (s.x as isize, y as isize);
                if let Some(r) = s.near {
                    let r = r as isize;
                    for_box(w, h, x - r, y - r, x + 1 + r, y + 1 + r, |row| {
                        if s.far.is_some() {
                            near_reach[row].fill(true)
                        } else {
                            for m in &mut near_middle[row] {
                                *m = m.min(s.middle);
                            }
                        }
                    });
                }
                if let Some(r) = s.far {
                    let r = r as isize;
                    for_box(w, h, x - r, y - r, x + 1 + r, y + 1 + r, |row| {
                        for m in &mut far_middle[row] {
                            *m = m.max(s.middle);
                        }
                    });
                }
            }
        }
        for (i, p) in map.pixels.iter_mut().enumerate() {
            map.reached[i] = near_reach[i]
                || near_middle[i] < f32::INFINITY
                || far_middle[i] > f32::NEG_INFINITY;
            *p = (near_reach[i] || d[i] > near_middle[i] || d[i] < far_middle[i])
                && (d[i] - q).abs() * px_per_d >= MIN_OWN_BLUR_PX;
            if *p {
                map.on[(i / w / TILE) * map.cols + (i % w) / TILE] = true;
            }
        }
        Ok(map)
    }

    /// Calls `f` with the index range of each row of the pixel box `[x0, x1] x [y0, y1]`
    /// (inclusive, clamped to the image).
    fn for_box(
        w: usize,
        h: usize,
        x0: isize,
        y0: isize,
        x1: isize,
        y1: isize,
        mut f: impl FnMut(std::ops::Range<usize>),
    ) {
        let clamp = |v: isize, max: usize| v.clamp(0, max as isize - 1) as usize;
        let (x0, x1) = (clamp(x0, w), clamp(x1, w));
        for y in clamp(y0, h)..=clamp(y1, h) {
            f(y * w + x0..y * w + x1 + 1);
        }
    }

    /// Depth `near` D on the left `split` columns, `far` D on the rest; colour random.
    fn step_scene(w: usize, h: usize, split: usize, near: f32, far: f32, seed: u64) -> Rgbd {
        let mut r = SplitMix(seed);
        let mut ch = || {
            Plane::from_vec(w, h, (0..w * h).map(|_| 0.5 + 0.4 * r.uniform()).collect()).unwrap()
        };
        let color = RgbImage::from_planes(ch(), ch(), ch()).unwrap();
        let d = (0..w * h)
            .map(|i| if i % w < split { near } else { far })
            .collect();
        Rgbd::new(
            color,
            DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap(),
        )
        .unwrap()
    }

    /// A C1R net with random weights throughout (its last layer too, so it corrects).
    fn trained_like(arch: &Arch, seed: u64) -> CpuNet {
        let mut w = Weights::random(arch, seed).unwrap();
        let mut r = SplitMix(seed ^ 7);
        for c in &mut w.convs {
            for v in c.weight.iter_mut().chain(c.bias.iter_mut()) {
                if *v == 0.0 {
                    *v = 0.05 * r.uniform();
                }
            }
        }
        CpuNet::new(w).unwrap()
    }

    #[test]
    fn the_parallel_error_map_equals_the_reference() {
        // Random rectangles of random depth (0.1-4 D) over a far wall, 97 x 61 so rows and
        // tiles do not divide evenly.
        let (w, h) = (97, 61);
        let mut r = SplitMix(7);
        // uniform() is in [-1, 1).
        let mut u = || 0.5 + 0.5 * r.uniform();
        let mut d = vec![0.2f32; w * h];
        for _ in 0..25 {
            let (x0, y0) = ((u() * w as f32) as usize, (u() * h as f32) as usize);
            let (bw, bh) = (1 + (u() * 20.0) as usize, 1 + (u() * 20.0) as usize);
            let depth = 0.1 + 3.9 * u();
            for y in y0..(y0 + bh).min(h) {
                d[y * w + x0..y * w + (x0 + bw).min(w)].fill(depth);
            }
        }
        let depth = DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap();
        for q in [0.1, 0.2, 1.0, 2.5, 4.0] {
            let (a, b) = (
                error_tiles(&depth, Diopters(q), &eye(w)).unwrap(),
                error_tiles_reference(&depth, Diopters(q), &eye(w)).unwrap(),
            );
            assert_eq!(a.on, b.on, "tiles at {q} D");
            assert_eq!(a.pixels, b.pixels, "pixels at {q} D");
            assert_eq!(a.reached, b.reached, "reached at {q} D");
            assert!(a.reached.contains(&false), "everything reached at {q} D");
            assert!(a.pixels.contains(&true), "nothing corrected at {q} D");
        }
    }

    #[test]
    fn the_error_map_selects_tiles_within_the_blur_of_a_depth_step_only() {
        let (w, h) = (128, 48);
        let e = eye(w);
        // 1 D step between columns 63 (2 D) and 64 (1 D); each side, out of focus by 1 D,
        // blurs with a disk of radius `r` and reaches `reach` pixels.
        let s = step_scene(w, h, 64, 2.0, 1.0, 1);
        let r = 0.5 * e.with_width(w as u32).coc_px(Diopters(2.0), Diopters(1.0));
        let reach = r.ceil() as usize + 1;
        let tiles_over = |cols: std::ops::RangeInclusive<usize>| -> Vec<bool> {
            (0..h.div_ceil(TILE) * w.div_ceil(TILE))
                .map(|t| {
                    let x0 = (t % w.div_ceil(TILE)) * TILE;
                    x0 <= *cols.end() && x0 + TILE > *cols.start()
                })
                .collect()
        };
        let check = |map: &TileMap, cols: std::ops::RangeInclusive<usize>, what: &str| {
            for x in 0..w {
                assert_eq!(map.corrects(x, 10), cols.contains(&x), "{what}: column {x}");
            }
            assert_eq!(map.on, tiles_over(cols), "{what}: tiles");
            assert!(map.fraction() > 0.0 && map.fraction() < 1.0, "{what}");
        };
        // Focus on the far side: the blurred near side's disk covers the sharp far side too,
        // but a sharp pixel beside a blurred occluder lacks nothing, so only the near side's
        // own pixels are corrected, and only the tiles holding them run.
        let far_focus = error_tiles(&s.depth, Diopters(1.0), &e).unwrap();
        check(&far_focus, 63 - reach..=63, "focus on the far side");
        // Focus on the near side: only the far side blurs, and only its pixels are corrected
        // (the sharp occluder is what every view sees).
        let near_focus = error_tiles(&s.depth, Diopters(2.0), &e).unwrap();
        check(&near_focus, 64..=64 + reach, "focus on the near side");
        // Focus beyond both (at infinity): both blur, and the near side's larger disk (2 D of
        // blur) covers both sides.
        let beyond = error_tiles(&s.depth, Diopters(0.0), &e).unwrap();
        let r_near = 0.5 * e.with_width(w as u32).coc_px(Diopters(2.0), Diopters(0.0));
        let reach_near = r_near.ceil() as usize + 1;
        check(
            &beyond,
            63 - reach_near..=64 + reach_near,
            "focus beyond both",
        );
        // Nothing blurs at a focus between... a step with both sides sharp: none.
        let flat = step_scene(w, h, 64, 1.0, 1.0, 2);
        assert!(!error_tiles(&flat.depth, Diopters(3.0), &e)
            .unwrap()
            .on
            .contains(&true));
        // A step far smaller than a pixel of blur: none.
        let tiny = step_scene(w, h, 64, 1.0, 1.05, 3);
        assert!(!error_tiles(&tiny.depth, Diopters(3.0), &e)
            .unwrap()
            .on
            .contains(&true));
        // A step that counts (its sides' blurs differ by over a pixel) beside a sharp far
        // side, its near side blurred by less than MIN_OWN_BLUR_PX: its disk reaches pixels,
        // but no pixel is corrected and no tile runs.
        let slight = 1.0
            + 0.9 * MIN_OWN_BLUR_PX / e.with_width(w as u32).coc_px(Diopters(1.0), Diopters(0.0));
        let s = step_scene(w, h, 64, slight, 1.0, 4);
        let map = error_tiles(&s.depth, Diopters(1.0), &e).unwrap();
        assert!(
            map.reached.contains(&true),
            "the slight step reaches nothing"
        );
        assert!(!map.pixels.contains(&true) && !map.on.contains(&true));
        // Without the own-blur threshold the same step's near side is corrected; a threshold
        // that is not a number of pixels is refused.
        let ungated = error_tiles_with(&s.depth, Diopters(1.0), &e, 0.0).unwrap();
        assert!(ungated.pixels.contains(&true) && ungated.on.contains(&true));
        for bad in [-1.0, f32::NAN, f32::INFINITY] {
            assert!(error_tiles_with(&s.depth, Diopters(1.0), &e, bad).is_err());
        }
    }

    #[test]
    fn tiled_evaluation_equals_the_full_image_on_the_pixels_it_corrects() {
        for rate in [1, 2, 4] {
            let arch = Arch {
                rate,
                layers: 5,
                channels: 16,
                ..Arch::preset("c1r").unwrap()
            };
            let net = trained_like(&arch, rate as u64);
            let (w, h) = (70, 53);
            let mut r = SplitMix(9);
            let x = Act::new(h, w, 8, (0..w * h * 8).map(|_| r.uniform()).collect()).unwrap();
            let mut tiles = TileMap::none(w, h);
            for (i, t) in tiles.on.iter_mut().enumerate() {
                *t = i % 3 == 1;
            }
            // Corrected: a diagonal band of the tiles that run (pixels of a tile, as the
            // map's are, but not all of them).
            for y in 0..h {
                for xx in 0..w {
                    tiles.pixels[y * w + xx] = tiles.covers(xx, y) && (xx + y) % 11 < 5;
                }
            }
            let full = net.forward(&x).unwrap();
            let part = net.forward_tiles(&x, &tiles).unwrap();
            let mut checked = 0;
            for y in 0..h {
                for xx in 0..w {
                    if tiles.corrects(xx, y) {
                        for c in 0..3 {
                            let i = (y * w + xx) * 3 + c;
                            assert!(
                                (full.data[i] - part.data[i]).abs() <= 1e-5,
                                "r {rate} ({xx}, {y}): {} vs {}",
                                full.data[i],
                                part.data[i]
                            );
                        }
                        checked += 1;
                    }
                }
            }
            assert!(checked > 0);
        }
    }

    #[test]
    fn an_untrained_refinement_net_returns_its_classical_input_exactly() {
        let (w, h) = (64, 40);
        let e = eye(w);
        let s = step_scene(w, h, 30, 3.0, 0.5, 4);
        let c1r = CpuNet::new(Weights::random(&Arch::preset("c1r").unwrap(), 5).unwrap()).unwrap();
        let base = classical_defocus(
            &dioptra_render::Cpu,
            Classical::Lightfield { views: 12 },
            &s,
            Diopters(3.0),
            &e,
        )
        .unwrap();
        let r = c1r.refine_defocus(&s, &base, Diopters(3.0), &e).unwrap();
        assert!(r.tiles.fraction() > 0.0, "the step blurs: the net runs");
        assert_eq!(r.image, r.classical);
        // The composite: the light field where the step's blur reaches, gather elsewhere.
        let smooth: Vec<bool> = r.tiles.reached.iter().map(|v| !v).collect();
        assert!(smooth.contains(&true) && smooth.contains(&false));
        let g = dioptra_render::gather::gather(&s, Diopters(3.0), &e).unwrap();
        for c in 0..3 {
            for (i, &v) in r.classical.channels[c].data().iter().enumerate() {
                let want = if smooth[i] {
                    g.channels[c].data()[i]
                } else {
                    base.channels[c].data()[i]
                };
                assert!((v - want).abs() < 1e-5, "pixel {i}: {v} vs {want}");
            }
        }
        let c4r = CpuNet::new(Weights::random(&Arch::preset("c4r").unwrap(), 6).unwrap()).unwrap();
        let planes: Vec<Diopters> = [0.2, 0.8, 1.4, 2.0].map(Diopters).to_vec();
        let linear = linear_blend(&s, &planes).unwrap();
        assert_eq!(c4r.refine_decompose(&s, &linear).unwrap(), linear);
        // A C4R on the spectral layers: its classical input is the spectral decomposition at
        // the default settings, and untrained it returns those layers exactly.
        let mut arch = Arch::preset("c4r").unwrap();
        let (_, classical) = c4r_input(&arch.task).unwrap();
        assert_eq!(classical, ClassicalLayers::Linear);
        if let Task::C4r { classical, .. } = &mut arch.task {
            *classical = ClassicalLayers::Spectral;
        }
        let spectral_net = CpuNet::new(Weights::random(&arch, 7).unwrap()).unwrap();
        let (p, classical) = c4r_input(&spectral_net.arch().task).unwrap();
        assert_eq!((p, classical), (planes.clone(), ClassicalLayers::Spectral));
        let base = classical_layers(&dioptra_render::Cpu, classical, &s, &planes, &e).unwrap();
        let (spectral, _) =
            dioptra_render::spectral::spectral_blend(&s, &planes, &e, SpectralParams::default())
                .unwrap();
        assert_eq!(base, spectral);
        assert_ne!(
            base, linear,
            "the spectral layers are not linear blending's"
        );
        assert_eq!(spectral_net.refine_decompose(&s, &base).unwrap(), spectral);
        assert_eq!(
            classical_layers(
                &dioptra_render::Cpu,
                ClassicalLayers::Linear,
                &s,
                &planes,
                &e
            )
            .unwrap(),
            linear
        );
        // c4r_input names another task's net.
        let c1r_task = Arch::preset("c1r").unwrap().task;
        assert!(c4r_input(&c1r_task).is_err());
        // Layers for other planes are refused, naming both.
        let other = linear_blend(&s, &[Diopters(0.5), Diopters(1.5)]).unwrap();
        let err = c4r.refine_decompose(&s, &other).unwrap_err().to_string();
        assert!(err.contains("0.5") && err.contains("0.2"), "{err}");
    }

    /// A test scene's nine inputs (corners, edge middles, centre) of a 9 x 9 light field over
    /// 1 cm at `w` px, and its eye.
    fn lf_inputs(w: usize) -> (Vec<RgbdView>, EyeModel) {
        use dioptra_sim::scene::{render_light_field, Camera, Scene, Split};
        let eye = EyeModel::default();
        let truth = render_light_field(
            &Scene::generate(Split::Test.seed(4)),
            &Camera::square(eye, w),
            9,
            0.01,
            1,
        )
        .unwrap();
        let inputs = [0, 4, 8, 36, 40, 44, 72, 76, 80]
            .map(|k| RgbdView {
                position: truth[k].position,
                rgbd: Rgbd::new(truth[k].color.clone(), truth[k].depth.clone()).unwrap(),
            })
            .to_vec();
        (inputs, eye)
    }

    #[test]
    fn an_untrained_c5r_returns_the_classical_light_field_exactly() {
        let (inputs, eye) = lf_inputs(48);
        let classical =
            dioptra_render::views::synthesize_light_field(&inputs, 9, 0.01, &eye, |_| {}).unwrap();
        let c5r = CpuNet::new(Weights::random(&Arch::preset("c5r").unwrap(), 3).unwrap()).unwrap();
        let refine = |v: &Rgbd, e: &WarpErrors| c5r.refine_view(v, e);
        let done = std::cell::Cell::new(0);
        let out = refine_light_field(&inputs, 9, 0.01, &eye, &refine, &|k| done.set(k)).unwrap();
        assert_eq!(out, classical);
        assert_eq!(done.get(), 81);
        // The net did run: some novel view has marked tiles.
        let (v, e) = synthesize_view_with_errors(&inputs, [0.0025, 0.00125], &eye).unwrap();
        let tiles = view_tiles(&e).unwrap();
        assert!(tiles.fraction() > 0.0, "nothing marked");
        // A net with random weights throughout corrects exactly the marked pixels.
        let net = trained_like(&Arch::preset("c5r").unwrap(), 4);
        let r = net.refine_view(&v, &e).unwrap();
        let mut changed = 0;
        for (i, &m) in e.marked.iter().enumerate() {
            for c in 0..3 {
                let (a, b) = (r.channels[c].data()[i], v.color.channels[c].data()[i]);
                assert!(m || a == b, "unmarked pixel {i} changed");
                changed += usize::from(a != b);
            }
        }
        assert!(changed > 0, "the random net corrects nothing");
        // Other nets, and an error map of another size, are refused.
        let c1r = CpuNet::new(Weights::random(&Arch::preset("c1r").unwrap(), 5).unwrap()).unwrap();
        assert!(c1r.refine_view(&v, &e).is_err());
        let (_, small) =
            synthesize_view_with_errors(&lf_inputs(32).0, [0.0025, 0.00125], &eye).unwrap();
        let err = net.refine_view(&v, &small).unwrap_err().to_string();
        assert!(err.contains("32x32") && err.contains("48x48"), "{err}");
    }

    #[test]
    fn corrections_are_clamped_to_the_display_range_and_kept_off_other_tiles() {
        let (w, h) = (48, 32);
        let base = RgbImage::new(w, h, [0.9, 0.5, 0.05]);
        let y = Act::new(h, w, 3, [0.3f32, 0.1, -0.2].repeat(w * h)).unwrap();
        let mut tiles = TileMap::none(w, h);
        tiles.on[1] = true;
        for (i, p) in tiles.pixels.iter_mut().enumerate() {
            *p = (TILE..2 * TILE).contains(&(i % w)) && i / w < TILE;
        }
        // A pixel of a running tile that the map keeps classical.
        tiles.pixels[6 * w + 21] = false;
        let out = compose_defocus(&base, &y, &tiles).unwrap();
        assert_eq!(out.pixel(21, 6), Some([0.9, 0.5, 0.05]));
        assert_eq!(out.pixel(20, 5), Some([1.0, 0.6, 0.0]));
        assert_eq!(out.pixel(5, 5), Some([0.9, 0.5, 0.05]));
    }
}
