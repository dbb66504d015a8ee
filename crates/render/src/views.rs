//! A light field from sparse RGB-D views (5 or 9): each novel view is a forward warp of every
//! input with a depth test, blended by closeness of the input to the novel view, with holes
//! filled from the background side.

use crate::common::eye_for;
use crate::error::{invalid, mismatch, RenderError};
use crate::lightfield::{key_source, splat_exact, wide_key};
use crate::retina::{LfView, Taps};
use dioptra_core::{DepthMap, EyeModel, Plane, RgbImage, Rgbd};
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

/// Input pixels whose parallax (pixels, between the input and the target) differs by more
/// than this are on different surfaces: a crack fill (the splat's widened write) whose read
/// lands on none of its own surface's pixels is dropped, or the far surface beside a
/// disocclusion would take the near one's colour at its own depth and the hole filling would
/// spread it over the whole disocclusion.
pub const SURFACE_STEP_PX: f32 = 1.0;

/// A hole is filled from the background pixel this many pixels beyond the nearest one (when
/// they are on its surface): next to a disocclusion lie the input's antialiased edge pixel (a
/// blend of both surfaces that its depth puts on the far one) and the pixel whose read
/// includes it; neither must be spread across the hole. One more for a softer edge.
pub const FILL_SKIP: usize = 3;

/// The view from `target` synthesised from `inputs`.
pub fn synthesize_view(
    inputs: &[RgbdView],
    target: [f32; 2],
    eye: &EyeModel,
) -> Result<RgbImage, RenderError> {
    let warped = warp_to::<false>(inputs, target, eye)?;
    let (w, h) = (warped.width, warped.height);
    let [r, g, b, _] = warped.planes;
    Ok(RgbImage::from_planes(
        Plane::from_vec(w, h, r)?,
        Plane::from_vec(w, h, g)?,
        Plane::from_vec(w, h, b)?,
    )?)
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
    let warped = warp_to::<false>(inputs, target, eye)?;
    rgbd_of(warped.width, warped.height, warped.planes)
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
    let Warped {
        width: w,
        height: h,
        planes,
        hole,
        spread,
    } = warp_to::<true>(inputs, target, eye)?;
    let pitch = eye_for(eye, w)?.pixel_pitch_tan();
    let nearest = inputs
        .iter()
        .map(|v| [target[0] - v.position[0], target[1] - v.position[1]])
        .min_by(|a, b| a[0].hypot(a[1]).total_cmp(&b[0].hypot(b[1])))
        .unwrap_or([0.0; 2]);
    let offset_px = nearest.map(|d| d / pitch);
    let scale = offset_px[0].hypot(offset_px[1]);
    let edge_px: Vec<f32> = local_range(&planes[3], w, h, EDGE_RADIUS)
        .into_iter()
        .map(|r| r * scale)
        .collect();
    let marked = (0..w * h)
        .map(|i| hole[i] || edge_px[i] >= EDGE_MIN_PX || spread[i] >= SPREAD_MIN)
        .collect();
    Ok((
        rgbd_of(w, h, planes)?,
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

/// A view warped from the inputs, holes filled, in row-major planes.
struct Warped {
    width: usize,
    height: usize,
    /// Red, green, blue (linear) and depth (diopters).
    planes: [Vec<f32>; 4],
    /// Whether no input was seen at the pixel (its value filled from the background side).
    hole: Vec<bool>,
    /// With `ERRORS`, the blended inputs' colour spread per pixel ([`WarpErrors::spread`]);
    /// otherwise one zero per row.
    spread: Vec<f32>,
}

/// The RGB-D of `w` x `h` planes: red, green, blue and depth (diopters).
fn rgbd_of(w: usize, h: usize, [r, g, b, d]: [Vec<f32>; 4]) -> Result<Rgbd, RenderError> {
    Ok(Rgbd::new(
        RgbImage::from_planes(
            Plane::from_vec(w, h, r)?,
            Plane::from_vec(w, h, g)?,
            Plane::from_vec(w, h, b)?,
        )?,
        DepthMap::from_diopters(Plane::from_vec(w, h, d)?)?,
    )?)
}

/// One input as the warp reads it.
struct WarpSource<'a> {
    depth: &'a [f32],
    colour: [&'a [f32]; 3],
    /// Parallax from the input to the target, pixels per diopter, and its length.
    shift: [f32; 2],
    per_d: f32,
    /// Blending weight: the inverse of the input's distance from the target.
    closeness: f32,
}

/// An input's read at a target pixel: its blending weight, depth and colour.
#[derive(Clone, Copy)]
struct Read {
    weight: f32,
    depth: f32,
    colour: [f32; 3],
}

/// Every input warped to `target` and blended, holes filled ([`Warped`]); with `ERRORS` the
/// blended inputs' colour spread too.
fn warp_to<const ERRORS: bool>(
    inputs: &[RgbdView],
    target: [f32; 2],
    eye: &EyeModel,
) -> Result<Warped, RenderError> {
    let (w, h) = check_inputs(inputs)?;
    if !target.iter().all(|p| p.is_finite()) {
        return Err(invalid("view positions must be finite"));
    }
    let pitch = eye_for(eye, w)?.pixel_pitch_tan();
    let n = w * h;
    let sources: Vec<WarpSource> = inputs
        .iter()
        .map(|v| {
            let shift = [
                -(target[0] - v.position[0]) / pitch,
                -(target[1] - v.position[1]) / pitch,
            ];
            WarpSource {
                depth: v.rgbd.depth.data(),
                colour: v.rgbd.color.channels.each_ref().map(|p| p.data()),
                shift,
                per_d: shift[0].hypot(shift[1]),
                closeness: 1.0
                    / ((v.position[0] - target[0]).hypot(v.position[1] - target[1]) + 1e-4),
            }
        })
        .collect();
    // Each input splatted onto the target: per target pixel the key of the nearest source
    // pixel landing on it; the crack fill of an empty pixel is read from its neighbours.
    let exact: Vec<Vec<u64>> = sources
        .par_iter()
        .map(|s| {
            let mut e = vec![0u64; n];
            splat_exact(s.depth, w, h, s.shift, 0.0, &mut e);
            e
        })
        .collect();
    let mut planes: [Vec<f32>; 4] = std::array::from_fn(|_| vec![0.0f32; n]);
    let mut hole = vec![false; n];
    // One value per pixel with ERRORS, else one per row (unused): a chunk per row either way.
    let (spread_len, spread_chunk) = if ERRORS { (n, w) } else { (h, 1) };
    let mut spread = vec![0.0f32; spread_len];
    {
        let [r, g, b, d] = &mut planes;
        r.par_chunks_mut(w)
            .zip(g.par_chunks_mut(w))
            .zip(b.par_chunks_mut(w))
            .zip(d.par_chunks_mut(w))
            .zip(hole.par_chunks_mut(w))
            .zip(spread.par_chunks_mut(spread_chunk))
            .enumerate()
            .for_each(|(y, (((((r, g), b), d), hole), spread))| {
                let mut reads: Vec<Read> = Vec::with_capacity(sources.len());
                let yc = y as f32 + 0.5;
                for x in 0..w {
                    let j = y * w + x;
                    let xc = x as f32 + 0.5;
                    // Each input's read where the target ray really lands (sub-pixel), not at
                    // the rounded splat position (rounding alone costs several dB on fine
                    // texture). A crack fill whose ray lands on no pixel of its source's
                    // surface is a disocclusion, not a crack: dropped (it would bring the
                    // other surface's colour at this one's depth, which the hole filling
                    // spreads).
                    reads.clear();
                    for (s, e) in sources.iter().zip(&exact) {
                        let is_exact = e[j] != 0;
                        let key = if is_exact {
                            e[j]
                        } else {
                            wide_key(e, w, h, x, y)
                        };
                        let Some(src) = key_source(key) else {
                            continue;
                        };
                        let depth = s.depth[src];
                        let taps =
                            Taps::new(w, h, xc - s.shift[0] * depth, yc - s.shift[1] * depth);
                        if !is_exact && !lands_on_surface(&taps, s.depth, depth, s.per_d) {
                            continue;
                        }
                        reads.push(Read {
                            // Crack fills are guesses: they count a quarter.
                            weight: s.closeness * if is_exact { 1.0 } else { 0.25 },
                            depth,
                            colour: s.colour.map(|p| taps.read(p)),
                        });
                    }
                    let nearest = reads
                        .iter()
                        .map(|r| r.depth)
                        .fold(f32::NEG_INFINITY, f32::max);
                    let mut acc = [0.0f32; 3];
                    let mut acc2 = [0.0f32; 3];
                    let mut wsum = 0.0f32;
                    for read in &reads {
                        if read.depth < nearest - SAME_SURFACE_D {
                            continue; // hidden behind a nearer surface seen by another input
                        }
                        let (wt, c) = (read.weight, read.colour);
                        for (k, a) in acc.iter_mut().enumerate() {
                            *a += wt * c[k];
                            if ERRORS {
                                acc2[k] += wt * c[k] * c[k];
                            }
                        }
                        wsum += wt;
                    }
                    if wsum > 0.0 {
                        (r[x], g[x], b[x]) = (acc[0] / wsum, acc[1] / wsum, acc[2] / wsum);
                        d[x] = nearest;
                        if ERRORS {
                            let var: f32 = (0..3)
                                .map(|c| (acc2[c] / wsum - (acc[c] / wsum).powi(2)).max(0.0))
                                .sum();
                            spread[x] = (var / 3.0).sqrt();
                        }
                    } else {
                        hole[x] = true;
                    }
                }
            });
    }
    fill_holes(&mut planes, &hole, w, h);
    Ok(Warped {
        width: w,
        height: h,
        planes,
        hole,
        spread,
    })
}

/// Fills each hole from the farther (background) of the nearest valid pixels to its left and
/// right on its row: with the pixel up to [`FILL_SKIP`] beyond it on that side, as far as
/// they are valid and within [`SAME_SURFACE_D`] of it. A row with none is filled from above
/// and below, the farther of the nearest filled pixels; with none at all it stays black at
/// 0 D.
fn fill_holes(planes: &mut [Vec<f32>; 4], hole: &[bool], w: usize, h: usize) {
    let [r, g, b, d] = &mut *planes;
    let filled: Vec<bool> = r
        .par_chunks_mut(w)
        .zip(g.par_chunks_mut(w))
        .zip(b.par_chunks_mut(w))
        .zip(d.par_chunks_mut(w))
        .zip(hole.par_chunks(w))
        .map(|((((r, g), b), d), hole)| fill_row([r, g, b, d], hole))
        .collect();
    for y in (0..h).filter(|&y| !filled[y]) {
        let up = (0..y).rev().find(|&k| filled[k]);
        let down = (y + 1..h).find(|&k| filled[k]);
        for x in 0..w {
            let from = match (up, down) {
                (Some(a), Some(b)) => {
                    if planes[3][a * w + x] <= planes[3][b * w + x] {
                        a
                    } else {
                        b
                    }
                }
                (Some(a), None) | (None, Some(a)) => a,
                (None, None) => break,
            };
            for p in planes.iter_mut() {
                p[y * w + x] = p[from * w + x];
            }
        }
    }
}

/// Fills one row's holes along it ([`fill_holes`]), run by run (a run's pixels share their
/// nearest valid pixels): whether the row has a valid pixel.
fn fill_row(mut row: [&mut [f32]; 4], hole: &[bool]) -> bool {
    let w = hole.len();
    let mut left = None;
    let mut x = 0;
    while x < w {
        if !hole[x] {
            left = Some(x);
            x += 1;
            continue;
        }
        let end = (x..w).find(|&k| !hole[k]).unwrap_or(w);
        let right = (end < w).then_some(end);
        let (k, step) = match (left, right) {
            (Some(a), Some(b)) => {
                if row[3][a] <= row[3][b] {
                    (a, -1)
                } else {
                    (b, 1)
                }
            }
            (Some(a), None) => (a, -1),
            (None, Some(b)) => (b, 1),
            // Nothing valid on the row.
            (None, None) => return false,
        };
        let from = beyond(row[3], hole, k, step);
        for p in row.iter_mut() {
            let v = p[from];
            p[x..end].fill(v);
        }
        x = end;
    }
    true
}

/// The pixel up to [`FILL_SKIP`] beyond valid pixel `k` (in direction `step`) on its row,
/// as far as the pixels on the way are valid and on its surface.
fn beyond(depth: &[f32], hole: &[bool], k: usize, step: isize) -> usize {
    let d = depth[k];
    let mut at = k;
    for _ in 0..FILL_SKIP {
        let Some(next) = at.checked_add_signed(step).filter(|&n| n < depth.len()) else {
            break;
        };
        if !hole[next] && (depth[next] - d).abs() <= SAME_SURFACE_D {
            at = next;
        } else {
            break;
        }
    }
    at
}

/// Whether the bilinear read `taps` takes any input pixel (with a weight above zero) on the
/// surface at depth `d` of `depth`: its parallax at `per_d` pixels per diopter within
/// [`SURFACE_STEP_PX`] of `d`'s.
fn lands_on_surface(taps: &Taps, depth: &[f32], d: f32, per_d: f32) -> bool {
    let (tx, ty) = (taps.tx, taps.ty);
    let weights = [
        (1.0 - tx) * (1.0 - ty),
        tx * (1.0 - ty),
        (1.0 - tx) * ty,
        tx * ty,
    ];
    taps.at
        .iter()
        .zip(weights)
        .any(|(&t, weight)| weight > 0.0 && (depth[t] - d).abs() * per_d <= SURFACE_STEP_PX)
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
        // The views the warp made when this test was last set: since the crack fills that
        // land on no pixel of their surface are dropped and holes are filled from beyond the
        // edge pixels (lab56); before, 0xc52b_673a_a8c5_0a80 (main at 03b8604).
        assert_eq!(
            checksum(&plain),
            0x9790_80b8_0bb3_359d,
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

    /// FNV-1a over a synthesised RGB-D's colour and depth bits and, with them, its error map.
    fn checksum_rgbd(rgbd: &Rgbd, errors: Option<&WarpErrors>) -> u64 {
        let floats = rgbd
            .color
            .channels
            .iter()
            .flat_map(|p| p.data().iter())
            .chain(rgbd.depth.data())
            .chain(
                errors
                    .into_iter()
                    .flat_map(|e| e.edge_px.iter().chain(&e.spread)),
            )
            .chain(errors.iter().flat_map(|e| e.offset_px.iter()))
            .flat_map(|v| v.to_bits().to_le_bytes());
        let flags = errors
            .into_iter()
            .flat_map(|e| e.hole.iter().chain(&e.marked))
            .map(|&b| b as u8);
        floats.chain(flags).fold(0xcbf2_9ce4_8422_2325, |h, b| {
            (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
        })
    }

    /// Pins the synthesis bit for bit (colour, depth, error map) where it guesses most: one
    /// textured RGB-D of a test scene (occluders before a wall, antialiased edges), 96 x 64
    /// over 20 degrees, seen from each eye (31.5 mm: disocclusions a dozen pixels wide), from
    /// above and diagonally (whole rows at the border with nothing on them, filled from the
    /// column), and the nine-input light field's error maps. The values are what the warp made
    /// before its rewrite for flat buffers (cpu54); any change to them is a change of what the
    /// rig shows.
    #[test]
    fn the_synthesis_is_pinned_on_a_textured_scene_with_holes() {
        let eye = EyeModel::default();
        let cam = Camera::new(eye, 96, 64);
        let (c, d) = dioptra_sim::scene::render_pinhole(
            &Scene::generate(Split::Test.seed(7)),
            &cam,
            [0.0, 0.0],
            2,
        )
        .unwrap();
        let one = [RgbdView {
            position: [0.0, 0.0],
            rgbd: Rgbd::new(c, d).unwrap(),
        }];
        let eye96 = eye.with_width(96);
        let targets = [[-0.0315, 0.0], [0.0315, 0.0], [0.0, 0.02], [0.02, -0.03]];
        let mut sums = Vec::new();
        let mut holes = 0;
        for t in targets {
            let (rgbd, errors) = synthesize_view_with_errors(&one, t, &eye96).unwrap();
            assert_eq!(rgbd, synthesize_rgbd_view(&one, t, &eye96).unwrap());
            holes += errors.hole.iter().filter(|&&h| h).count();
            sums.push(checksum_rgbd(&rgbd, Some(&errors)));
        }
        // Enough holes that the filling is exercised (rows and columns).
        assert!(holes > 500, "{holes} holes");
        let (inputs, positions, eye) = scene();
        let nine = positions
            .iter()
            .map(|&p| {
                let (rgbd, errors) = synthesize_view_with_errors(&inputs, p, &eye).unwrap();
                checksum_rgbd(&rgbd, Some(&errors))
            })
            .fold(0u64, |a, s| a.rotate_left(7) ^ s);
        sums.push(nine);
        assert_eq!(
            sums,
            [
                0xc487_c387_65ae_c7fd,
                0x36bb_1eb7_cadb_62fb,
                0xf4a7_acfc_f6d5_76ae,
                0x18c4_68ec_0ebf_40a6,
                0x25c0_235f_ba62_9221
            ],
            "the synthesis changed"
        );
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

    /// The lab's case, by hand: one RGB-D, a red square at 2 D (0.5 m) over columns 48..80
    /// before a wall at 0.5 D (2 m), 128 x 16 px over the default 20 degree field; each eye's
    /// view synthesised IPD / 2 = 31.5 mm beside it. `aa`: the wall pixels next to the square
    /// antialiased as a supersampled render leaves them (71 % square, 29 % wall, the wall's
    /// depth); `texture`: a wall whose green varies along the row. The wall has no red.
    fn square_over_wall(aa: bool, texture: bool) -> (RgbdView, Vec<[f32; 3]>) {
        let (w, h) = (128, 16);
        let wall = |x: usize| {
            let g = if texture {
                0.2 + 0.6 * (x as f32 * 0.37).sin().abs()
            } else {
                0.5
            };
            [0.0, g, 1.0]
        };
        let mut colour = Vec::with_capacity(3 * w * h);
        let mut depth = Vec::with_capacity(w * h);
        for i in 0..w * h {
            let x = i % w;
            let (c, d) = if (48..80).contains(&x) {
                ([1.0, 0.0, 0.0], 2.0)
            } else if aa && (x == 47 || x == 80) {
                let c = wall(x);
                ([0.71, 0.29 * c[1], 0.29 * c[2]], 0.5)
            } else {
                (wall(x), 0.5)
            };
            colour.extend(c);
            depth.push(d);
        }
        let rgbd = Rgbd::new(
            RgbImage::from_interleaved(w, h, &colour).unwrap(),
            dioptra_core::DepthMap::from_diopters(
                dioptra_core::Plane::from_vec(w, h, depth).unwrap(),
            )
            .unwrap(),
        )
        .unwrap();
        (
            RgbdView {
                position: [0.0, 0.0],
                rgbd,
            },
            (0..w).map(wall).collect(),
        )
    }

    #[test]
    fn one_rgbd_each_eye_sees_the_wall_beside_a_near_square_not_a_ghost_of_it() {
        let eye = EyeModel::default();
        // By hand: the pixel pitch on the tangent plane is 2 tan(10 deg) / 128 = 0.0027551,
        // so a point at D diopters seen from 31.5 mm to the left moves 0.0315 D / 0.0027551 =
        // 11.433 D px to the right (to the left from the right eye). The square (2 D) moves
        // 22.867 px, the wall (0.5 D) 5.717: in the left eye's view the wall behind the
        // square's left edge shows over [48 + 5.717, 48 + 22.867) = [53.72, 70.87), a strip
        // 11.433 x 1.5 = 17.15 px wide that the input never saw; in the right eye's over
        // [80 - 22.867, 80 - 5.717) = [57.13, 74.28), at the square's right edge.
        let pitch = eye_for(&eye, 128).unwrap().pixel_pitch_tan();
        let per_d = 0.0315 / pitch;
        assert!((pitch - 0.002_755_1).abs() < 1e-7 && (per_d - 11.433).abs() < 1e-3);
        let strips = [
            (-0.0315, 48.0 + 0.5 * per_d, 48.0 + 2.0 * per_d),
            (0.0315, 80.0 - 2.0 * per_d, 80.0 - 0.5 * per_d),
        ];
        for (aa, texture) in [(false, false), (true, false), (false, true), (true, true)] {
            let (input, wall) = square_over_wall(aa, texture);
            for &(x_eye, from, to) in &strips {
                let (view, errors) =
                    synthesize_view_with_errors(std::slice::from_ref(&input), [x_eye, 0.0], &eye)
                        .unwrap();
                let case = format!("eye at {x_eye} m, aa {aa}, texture {texture}");
                let row = 8;
                let at = |x: usize| {
                    (
                        view.color
                            .channels
                            .each_ref()
                            .map(|c| c.get(x, row).unwrap()),
                        view.depth.plane().get(x, row).unwrap(),
                    )
                };
                // The strip: what no input pixel landed on (the warp's holes; those at the
                // image's border aside), beside it on the square's side the square. Its edges
                // within a pixel of the geometry's (the splat places pixels to the pixel; its
                // crack fill may widen the square by one).
                let holes: Vec<usize> = (16..112).filter(|&x| errors.hole[row * 128 + x]).collect();
                let (first, last) = (holes[0], *holes.last().unwrap());
                assert_eq!(
                    holes.len(),
                    last - first + 1,
                    "{case}: one strip: {holes:?}"
                );
                let square_side = if x_eye < 0.0 { last + 1 } else { first - 1 };
                let (near_edge, far_edge) = if x_eye < 0.0 {
                    (last as f32 + 1.0, first as f32)
                } else {
                    (first as f32, last as f32 + 1.0)
                };
                let (near_geo, far_geo) = if x_eye < 0.0 { (to, from) } else { (from, to) };
                assert!(
                    (near_edge - near_geo).abs() <= 1.0 && (far_edge - far_geo).abs() <= 1.0,
                    "{case}: strip {first}..={last}, the geometry's [{from:.2}, {to:.2})"
                );
                assert_eq!(at(square_side).1, 2.0, "{case}");
                // Filled from the wall: its depth, and no red at all (the square is red, the
                // wall has none); on a flat wall its very colour.
                for x in first..=last {
                    let (c, d) = at(x);
                    assert_eq!(d, 0.5, "{case}: column {x} depth");
                    assert_eq!(
                        c[0], 0.0,
                        "{case}: column {x} is {c:?}: square in the strip"
                    );
                    if !texture {
                        // Flat: one colour all along the wall.
                        assert_eq!(c, wall[0], "{case}: column {x}");
                    } else {
                        // A copy of the wall a few pixels beyond the strip.
                        let beyond: Vec<usize> = if x_eye < 0.0 {
                            (first - FILL_SKIP - 1..first).collect()
                        } else {
                            (last + 1..=last + FILL_SKIP + 1).collect()
                        };
                        assert!(
                            beyond.iter().any(|&k| at(k) == (c, 0.5)),
                            "{case}: column {x} is {c:?}, not the wall beside the strip"
                        );
                    }
                }
            }
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
