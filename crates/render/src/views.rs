//! A light field from sparse RGB-D views (5 or 9): each novel view is a forward warp of every
//! input with a depth test, blended by closeness of the input to the novel view, with holes
//! filled from the background side.

use crate::common::eye_for;
use crate::error::{invalid, mismatch, RenderError};
use crate::lightfield::{resolve, splat};
use crate::retina::{bilinear, LfView};
use dioptra_core::{EyeModel, RgbImage, Rgbd};
use rayon::prelude::*;

/// An input view: a pinhole RGB-D image seen from `position` (metres in the eye's lens
/// plane), looking straight ahead.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbdView {
    pub position: [f32; 2],
    pub rgbd: Rgbd,
}

/// Candidates within this many diopters of the nearest one are the same surface.
pub(crate) const SAME_SURFACE_D: f32 = 0.03;

/// The view from `target` synthesised from `inputs`.
pub fn synthesize_view(
    inputs: &[RgbdView],
    target: [f32; 2],
    eye: &EyeModel,
) -> Result<RgbImage, RenderError> {
    let (w, h, px, _) = warp_to::<false>(inputs, target, eye)?;
    let colour: Vec<[f32; 3]> = px.iter().map(|p| p.0).collect();
    Ok(RgbImage::from_interleaved(w, h, colour.as_flattened())?)
}

/// The view from `target` synthesised from `inputs`, with its depth: a stereo eye's RGB-D
/// made from one central view (`target` an eye's position, IPD / 2 from the centre), which
/// the eye's own render then defocuses. A hole with nothing on its row or column is black at
/// infinity (0 D).
pub fn synthesize_rgbd_view(
    inputs: &[RgbdView],
    target: [f32; 2],
    eye: &EyeModel,
) -> Result<Rgbd, RenderError> {
    let (w, h, px, _) = warp_to::<false>(inputs, target, eye)?;
    rgbd_of(w, h, &px)
}

fn rgbd_of(w: usize, h: usize, px: &[([f32; 3], f32)]) -> Result<Rgbd, RenderError> {
    let colour: Vec<[f32; 3]> = px.iter().map(|p| p.0).collect();
    let depth: Vec<f32> = px.iter().map(|p| p.1).collect();
    Ok(Rgbd::new(
        RgbImage::from_interleaved(w, h, colour.as_flattened())?,
        dioptra_core::DepthMap::from_diopters(dioptra_core::Plane::from_vec(w, h, depth)?)?,
    )?)
}

/// A depth step whose sides move apart by this much parallax (pixels) between the nearest
/// input and the target is where the warp's depth test and hole filling guess.
pub const EDGE_MIN_PX: f32 = 0.5;
/// Pixels within this many of such a step are marked (the splat's crack fill and bilinear
/// reads reach about this far).
pub const EDGE_RADIUS: usize = 2;
/// Inputs whose colours on one surface spread (RMS, linear) by this much disagree: a
/// specular surface, a misregistered edge or a surface some inputs see occluded.
pub const SPREAD_MIN: f32 = 0.03;

/// Where a synthesised view is likely wrong, per pixel (row-major), from the warp itself.
#[derive(Debug, Clone, PartialEq)]
pub struct WarpErrors {
    pub width: usize,
    pub height: usize,
    /// No input saw the pixel: its value was filled from the background side.
    pub hole: Vec<bool>,
    /// The warped depth's range (diopters) within [`EDGE_RADIUS`] px, as parallax in pixels
    /// from the nearest input: how far the two sides of a discontinuity moved apart.
    pub edge_px: Vec<f32>,
    /// RMS colour spread (linear, over the channels) of the inputs blended on the pixel's
    /// surface; 0 where one input or none saw it.
    pub spread: Vec<f32>,
    /// The target's position minus its nearest input's over the pixel pitch: the parallax
    /// (pixels, x and y) per diopter between them.
    pub offset_px: [f32; 2],
    /// The pixels the map marks: a hole, `edge_px >= EDGE_MIN_PX` or `spread >= SPREAD_MIN`.
    pub marked: Vec<bool>,
}

/// [`synthesize_rgbd_view`] and where it is likely wrong ([`WarpErrors`]): the same view,
/// bit for bit.
pub fn synthesize_view_with_errors(
    inputs: &[RgbdView],
    target: [f32; 2],
    eye: &EyeModel,
) -> Result<(Rgbd, WarpErrors), RenderError> {
    let (w, h, px, raw) = warp_to::<true>(inputs, target, eye)?;
    let (hole, spread) = raw.into_iter().unzip::<_, _, Vec<bool>, Vec<f32>>();
    let pitch = eye_for(eye, w)?.pixel_pitch_tan();
    let nearest = inputs
        .iter()
        .map(|v| [target[0] - v.position[0], target[1] - v.position[1]])
        .min_by(|a, b| a[0].hypot(a[1]).total_cmp(&b[0].hypot(b[1])))
        .unwrap_or([0.0; 2]);
    let offset_px = nearest.map(|d| d / pitch);
    let depth: Vec<f32> = px.iter().map(|p| p.1).collect();
    let scale = offset_px[0].hypot(offset_px[1]);
    let edge_px: Vec<f32> = local_range(&depth, w, h, EDGE_RADIUS)
        .into_iter()
        .map(|r| r * scale)
        .collect();
    let marked = (0..w * h)
        .map(|i| hole[i] || edge_px[i] >= EDGE_MIN_PX || spread[i] >= SPREAD_MIN)
        .collect();
    Ok((
        rgbd_of(w, h, &px)?,
        WarpErrors {
            width: w,
            height: h,
            hole,
            edge_px,
            spread,
            offset_px,
            marked,
        },
    ))
}

/// Per pixel, max - min of `v` over the (2r + 1)^2 window around it (clipped to the image):
/// separable, O(r) per pixel.
fn local_range(v: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    let pass = |src: &[(f32, f32)], along_x: bool| -> Vec<(f32, f32)> {
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let (c, len) = if along_x { (x, w) } else { (y, h) };
                (c.saturating_sub(r)..(c + r + 1).min(len))
                    .map(|k| src[if along_x { y * w + k } else { k * w + x }])
                    .fold((f32::INFINITY, f32::NEG_INFINITY), |a, b| {
                        (a.0.min(b.0), a.1.max(b.1))
                    })
            })
            .collect()
    };
    let ends: Vec<(f32, f32)> = v.iter().map(|&d| (d, d)).collect();
    pass(&pass(&ends, true), false)
        .into_iter()
        .map(|(lo, hi)| hi - lo)
        .collect()
}

/// The size the sparse RGB-D `inputs` share: there is one at least, all are the same size
/// and not empty, and their positions are finite (the CPU's and the GPU's check).
pub(crate) fn check_inputs(inputs: &[RgbdView]) -> Result<(usize, usize), RenderError> {
    let first = inputs.first().ok_or_else(|| invalid("no input views"))?;
    let (w, h) = (first.rgbd.width(), first.rgbd.height());
    if w == 0
        || h == 0
        || inputs
            .iter()
            .any(|v| (v.rgbd.width(), v.rgbd.height()) != (w, h))
    {
        return Err(mismatch("input views are empty or differ in size"));
    }
    if !inputs
        .iter()
        .flat_map(|v| v.position.iter())
        .all(|p| p.is_finite())
    {
        return Err(invalid("view positions must be finite"));
    }
    Ok((w, h))
}

/// Every input warped to `target` and blended, holes filled: width, height and per pixel the
/// colour and depth (diopters); with `ERRORS`, per pixel also whether it was a hole and the
/// blended inputs' colour spread ([`WarpErrors`]), else nothing.
#[allow(clippy::type_complexity)]
fn warp_to<const ERRORS: bool>(
    inputs: &[RgbdView],
    target: [f32; 2],
    eye: &EyeModel,
) -> Result<(usize, usize, Vec<([f32; 3], f32)>, Vec<(bool, f32)>), RenderError> {
    let (w, h) = check_inputs(inputs)?;
    if !target.iter().all(|p| p.is_finite()) {
        return Err(invalid("view positions must be finite"));
    }
    let pitch = eye_for(eye, w)?.pixel_pitch_tan();
    let n = w * h;
    let shifts: Vec<[f32; 2]> = inputs
        .iter()
        .map(|v| {
            [
                -(target[0] - v.position[0]) / pitch,
                -(target[1] - v.position[1]) / pitch,
            ]
        })
        .collect();
    // Each input warped to the target: (exact, wide) nearest-source buffers.
    let warped: Vec<(Vec<u64>, Vec<u64>)> = inputs
        .par_iter()
        .zip(shifts.par_iter())
        .map(|(v, &shift)| {
            let (mut e, mut wd) = (vec![0u64; n], vec![0u64; n]);
            splat(v.rgbd.depth.data(), w, h, shift, 0.0, &mut e, &mut wd);
            (e, wd)
        })
        .collect();
    let closeness: Vec<f32> = inputs
        .iter()
        .map(|v| 1.0 / ((v.position[0] - target[0]).hypot(v.position[1] - target[1]) + 1e-4))
        .collect();
    // Per pixel: colour and depth, or None for a hole; and the colour spread.
    let px: Vec<(Option<([f32; 3], f32)>, f32)> = (0..n)
        .into_par_iter()
        .map(|j| {
            let cands: Vec<(usize, usize, bool)> = warped
                .iter()
                .enumerate()
                .filter_map(|(i, (e, wd))| resolve(e, wd, j).map(|s| (i, s, e[j] != 0)))
                .collect();
            let nearest = cands
                .iter()
                .map(|&(i, s, _)| inputs[i].rgbd.depth.data()[s])
                .fold(f32::NEG_INFINITY, f32::max);
            let mut acc = [0.0f32; 3];
            let mut acc2 = [0.0f32; 3];
            let mut wsum = 0.0f32;
            let (x, y) = ((j % w) as f32 + 0.5, (j / w) as f32 + 0.5);
            for &(i, s, exact) in &cands {
                let d = inputs[i].rgbd.depth.data()[s];
                if d < nearest - SAME_SURFACE_D {
                    continue; // hidden behind a nearer surface seen by another input
                }
                // Crack fills are guesses: they count a quarter.
                let wt = closeness[i] * if exact { 1.0 } else { 0.25 };
                // Read the input where the target ray really lands (sub-pixel), not at the
                // rounded splat position: rounding alone costs several dB on fine texture.
                let shift = shifts[i];
                let (sx, sy) = (x - shift[0] * d, y - shift[1] * d);
                for (c, a) in acc.iter_mut().enumerate() {
                    let v = bilinear(&inputs[i].rgbd.color.channels[c], sx, sy);
                    *a += wt * v;
                    if ERRORS {
                        acc2[c] += wt * v * v;
                    }
                }
                wsum += wt;
            }
            let spread = if ERRORS && wsum > 0.0 {
                let var: f32 = (0..3)
                    .map(|c| (acc2[c] / wsum - (acc[c] / wsum).powi(2)).max(0.0))
                    .sum();
                (var / 3.0).sqrt()
            } else {
                0.0
            };
            (
                (wsum > 0.0).then(|| (acc.map(|v| v / wsum), nearest)),
                spread,
            )
        })
        .collect();
    let (px, spread): (Vec<_>, Vec<f32>) = px.into_iter().unzip();
    let errors = if ERRORS {
        px.iter().map(Option::is_none).zip(spread).collect()
    } else {
        Vec::new()
    };
    Ok((w, h, fill_holes(&px, w, h), errors))
}

/// Fills each hole with the farther (background) of the nearest valid pixels to its left and
/// right on its row, or from above and below when a row has none.
fn fill_holes(px: &[Option<([f32; 3], f32)>], w: usize, h: usize) -> Vec<([f32; 3], f32)> {
    let mut out: Vec<Option<([f32; 3], f32)>> = px.to_vec();
    for y in 0..h {
        let row = &px[y * w..(y + 1) * w];
        for x in 0..w {
            if row[x].is_some() {
                continue;
            }
            let left = row[..x].iter().rev().flatten().next();
            let right = row[x + 1..].iter().flatten().next();
            out[y * w + x] = match (left, right) {
                (Some(a), Some(b)) => Some(if a.1 <= b.1 { *a } else { *b }),
                (Some(a), None) | (None, Some(a)) => Some(*a),
                (None, None) => None,
            };
        }
    }
    let rows = out.clone();
    for y in 0..h {
        for x in 0..w {
            if rows[y * w + x].is_some() {
                continue;
            }
            let up = (0..y).rev().find_map(|k| rows[k * w + x]);
            let down = (y + 1..h).find_map(|k| rows[k * w + x]);
            out[y * w + x] = match (up, down) {
                (Some(a), Some(b)) => Some(if a.1 <= b.1 { a } else { b }),
                (Some(a), None) | (None, Some(a)) => Some(a),
                (None, None) => None,
            };
        }
    }
    out.into_iter()
        .map(|p| p.unwrap_or(([0.0; 3], 0.0)))
        .collect()
}

/// The view positions of a `grid` x `grid` light field over a `span` metres square,
/// row-major from the top-left.
pub fn light_field_positions(grid: usize, span: f32) -> Result<Vec<[f32; 2]>, RenderError> {
    if grid == 0 || grid > 64 || !(span.is_finite() && span >= 0.0) {
        return Err(invalid(format!(
            "grid {grid} (expected 1..=64) or span {span} m is invalid"
        )));
    }
    let step = if grid > 1 {
        span / (grid - 1) as f32
    } else {
        0.0
    };
    let half = (grid - 1) as f32 * 0.5;
    Ok((0..grid * grid)
        .map(|k| {
            [
                ((k % grid) as f32 - half) * step,
                ((k / grid) as f32 - half) * step,
            ]
        })
        .collect())
}

/// A `grid` x `grid` light field over a `span` metres square (row-major from the top-left),
/// every view synthesised from `inputs`; `progress` is called with the views done.
pub fn synthesize_light_field(
    inputs: &[RgbdView],
    grid: usize,
    span: f32,
    eye: &EyeModel,
    mut progress: impl FnMut(usize),
) -> Result<Vec<LfView>, RenderError> {
    let mut out = Vec::with_capacity(grid * grid);
    for (k, position) in light_field_positions(grid, span)?.into_iter().enumerate() {
        out.push(LfView {
            position,
            image: synthesize_view(inputs, position, eye)?,
        });
        progress(k + 1);
    }
    Ok(out)
}

/// The depth (diopters) of the view from each of `positions`, as [`synthesize_rgbd_view`]
/// makes it: what a foveated light field reprojects its samples by.
pub fn light_field_depths(
    inputs: &[RgbdView],
    positions: &[[f32; 2]],
    eye: &EyeModel,
) -> Result<Vec<dioptra_core::Plane>, RenderError> {
    positions
        .iter()
        .map(|&p| Ok(synthesize_rgbd_view(inputs, p, eye)?.depth.into_plane()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_core::Rgbd;
    use dioptra_sim::scene::{render_light_field, Camera, Scene, Split};

    /// A test scene's 9 x 9 light field over 1 cm at 64 px (DeepFocus's C5 setting) and its
    /// nine inputs (corners, edge middles, centre).
    fn scene() -> (Vec<RgbdView>, Vec<[f32; 2]>, EyeModel) {
        let eye = EyeModel::default();
        let cam = Camera::square(eye, 64);
        let truth =
            render_light_field(&Scene::generate(Split::Test.seed(4)), &cam, 9, 0.01, 1).unwrap();
        let inputs = [0, 4, 8, 36, 40, 44, 72, 76, 80]
            .map(|k| RgbdView {
                position: truth[k].position,
                rgbd: Rgbd::new(truth[k].color.clone(), truth[k].depth.clone()).unwrap(),
            })
            .to_vec();
        (inputs, truth.iter().map(|v| v.position).collect(), eye)
    }

    /// FNV-1a over the views' bits.
    fn checksum(views: &[RgbImage]) -> u64 {
        views
            .iter()
            .flat_map(|v| v.channels.iter().flat_map(|p| p.data().iter()))
            .flat_map(|v| v.to_bits().to_le_bytes())
            .fold(0xcbf2_9ce4_8422_2325, |h, b| {
                (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
            })
    }

    #[test]
    fn the_error_map_leaves_the_classical_views_unchanged() {
        let (inputs, positions, eye) = scene();
        let plain: Vec<RgbImage> = positions
            .iter()
            .map(|&p| synthesize_view(&inputs, p, &eye).unwrap())
            .collect();
        // The views the warp made before the error map existed (main at 03b8604).
        assert_eq!(
            checksum(&plain),
            0xc52b_673a_a8c5_0a80,
            "the classical synthesis changed"
        );
        for (&p, view) in positions.iter().zip(&plain) {
            let (rgbd, errors) = synthesize_view_with_errors(&inputs, p, &eye).unwrap();
            assert_eq!(&rgbd.color, view);
            assert_eq!(rgbd, synthesize_rgbd_view(&inputs, p, &eye).unwrap());
            assert_eq!(errors.marked.len(), 64 * 64);
        }
        let lf = synthesize_light_field(&inputs, 9, 0.01, &eye, |_| {}).unwrap();
        for ((v, p), img) in lf.iter().zip(&positions).zip(&plain) {
            assert_eq!((&v.position, &v.image), (p, img));
        }
    }

    /// A box at 4 D over columns 24..40 before a wall at 0.25 D, seen from `p` (metres,
    /// horizontal): a point at column x of the view from 0 lies at x - p / pitch * depth.
    fn box_view(eye: &EyeModel, p: f32, gain: f32) -> RgbdView {
        let (w, h) = (64, 16);
        let pitch = eye_for(eye, w).unwrap().pixel_pitch_tan();
        let mut colour = Vec::with_capacity(3 * w * h);
        let mut depth = Vec::with_capacity(w * h);
        for i in 0..w * h {
            let x = (i % w) as f32 + 0.5;
            let xb = x + p / pitch * 4.0;
            let (c, d) = if (24.0..40.0).contains(&xb) {
                (0.8, 4.0)
            } else {
                (0.1 + 0.3 * ((x + p / pitch * 0.25) / 8.0).sin().abs(), 0.25)
            };
            colour.extend([c * gain, 0.5 * c * gain, 0.2]);
            depth.push(d);
        }
        RgbdView {
            position: [p, 0.0],
            rgbd: Rgbd::new(
                RgbImage::from_interleaved(w, h, &colour).unwrap(),
                dioptra_core::DepthMap::from_diopters(
                    dioptra_core::Plane::from_vec(w, h, depth).unwrap(),
                )
                .unwrap(),
            )
            .unwrap(),
        }
    }

    #[test]
    fn the_error_map_marks_holes_depth_edges_and_disagreeing_inputs() {
        let eye = EyeModel::default();
        let pitch = eye_for(&eye, 64).unwrap().pixel_pitch_tan();
        // One input at 0, the target 1 pitch right: the box moves 4 px left, the wall 0.25,
        // uncovering the wall at the box's right edge.
        let one = [box_view(&eye, 0.0, 1.0)];
        let (_, e) = synthesize_view_with_errors(&one, [pitch, 0.0], &eye).unwrap();
        assert_eq!(e.offset_px, [1.0, 0.0]);
        let cols = |v: &[bool]| -> Vec<usize> {
            (0..64)
                .filter(|&x| (0..16).any(|y| v[y * 64 + x]))
                .collect()
        };
        let holes = cols(&e.hole);
        assert!(!holes.is_empty(), "no disocclusion");
        assert!(holes.iter().all(|x| (35..41).contains(x)), "{holes:?}");
        let marked = cols(&e.marked);
        // Within EDGE_RADIUS of either warped box edge (columns 20 and 36) or a hole.
        assert!(marked.contains(&20) && marked.contains(&36), "{marked:?}");
        assert!(
            marked
                .iter()
                .all(|x| (17..24).contains(x) || (33..42).contains(x)),
            "{marked:?}"
        );
        assert!(
            e.spread.iter().all(|&s| s < 1e-3),
            "one input cannot disagree"
        );
        // At the input's own position nothing is guessed.
        let (_, e) = synthesize_view_with_errors(&one, [0.0, 0.0], &eye).unwrap();
        assert!(!e.marked.contains(&true));
        // Two inputs whose colours disagree by half: marked where both see the same surface.
        let two = [box_view(&eye, 0.0, 1.0), box_view(&eye, 2.0 * pitch, 1.5)];
        let (_, e) = synthesize_view_with_errors(&two, [pitch, 0.0], &eye).unwrap();
        assert!(e.spread[8 * 64 + 4] >= SPREAD_MIN && e.marked[8 * 64 + 4]);
    }
}
