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
const SAME_SURFACE_D: f32 = 0.03;

/// The view from `target` synthesised from `inputs`.
pub fn synthesize_view(
    inputs: &[RgbdView],
    target: [f32; 2],
    eye: &EyeModel,
) -> Result<RgbImage, RenderError> {
    let (w, h, px) = warp_to(inputs, target, eye)?;
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
    let (w, h, px) = warp_to(inputs, target, eye)?;
    let colour: Vec<[f32; 3]> = px.iter().map(|p| p.0).collect();
    let depth: Vec<f32> = px.iter().map(|p| p.1).collect();
    Ok(Rgbd::new(
        RgbImage::from_interleaved(w, h, colour.as_flattened())?,
        dioptra_core::DepthMap::from_diopters(dioptra_core::Plane::from_vec(w, h, depth)?)?,
    )?)
}

/// Every input warped to `target` and blended, holes filled: width, height and per pixel the
/// colour and depth (diopters).
#[allow(clippy::type_complexity)]
fn warp_to(
    inputs: &[RgbdView],
    target: [f32; 2],
    eye: &EyeModel,
) -> Result<(usize, usize, Vec<([f32; 3], f32)>), RenderError> {
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
    if !target
        .iter()
        .chain(inputs.iter().flat_map(|v| v.position.iter()))
        .all(|p| p.is_finite())
    {
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
    // Per pixel: colour and depth, or None for a hole.
    let px: Vec<Option<([f32; 3], f32)>> = (0..n)
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
                    *a += wt * bilinear(&inputs[i].rgbd.color.channels[c], sx, sy);
                }
                wsum += wt;
            }
            (wsum > 0.0).then(|| (acc.map(|v| v / wsum), nearest))
        })
        .collect();
    Ok((w, h, fill_holes(&px, w, h)))
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

/// A `grid` x `grid` light field over a `span` metres square (row-major from the top-left),
/// every view synthesised from `inputs`; `progress` is called with the views done.
pub fn synthesize_light_field(
    inputs: &[RgbdView],
    grid: usize,
    span: f32,
    eye: &EyeModel,
    mut progress: impl FnMut(usize),
) -> Result<Vec<LfView>, RenderError> {
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
    let mut out = Vec::with_capacity(grid * grid);
    for k in 0..grid * grid {
        let position = [
            ((k % grid) as f32 - half) * step,
            ((k / grid) as f32 - half) * step,
        ];
        out.push(LfView {
            position,
            image: synthesize_view(inputs, position, eye)?,
        });
        progress(k + 1);
    }
    Ok(out)
}
