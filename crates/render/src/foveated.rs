//! Foveated defocus that does less work: full resolution within a foveal radius of the gaze,
//! coarser layers outside as the eye's acuity falls, blended without a seam; the pixels a
//! layer does not cover are never computed.
//!
//! Acuity model: the minimum angle of resolution grows linearly with eccentricity (the
//! standard model Guenter et al. 2012, "Foveated 3D graphics", build their eccentricity layers
//! on; their user study puts the slope at 1.32 to 1.65 arcmin per degree, 0.022 to 0.0275).
//! Here it is anchored at the foveal radius `e_f`: a detail the display can show at the
//! foveal edge (one pixel, `p` degrees at the centre of the field) may grow to
//! `p + m (e - e_f)` at eccentricity `e`, so the image may be sampled `2^l` times coarser with
//! `l(e) = log2(1 + m max(0, e - e_f) / p)`. That asks at least as much resolution as the eye
//! resolves (its MAR at `e_f` is at least the display's pixel on any display that does not
//! out-resolve the fovea), and is continuous at the foveal edge, where Guenter's three fixed
//! layers jump.
//!
//! Layers `k = 0..=L` render the input box-downsampled by `2^k` (colour and diopters averaged)
//! with [`crate::pyramid`] on the part of their grid where their blend weight is non-zero
//! (an annulus around the gaze, widened by two texels for the bilinear read-back). A pixel
//! with `l` between `k` and `k + 1` blends layers `k` and `k + 1` by a smoothstep of the
//! fraction; `l` is evaluated exactly on a grid of nodes every [`GRID`] pixels and
//! interpolated bilinearly between them (it is smooth but for the cone at the gaze, where it
//! is 0). The GPU backend runs the same steps (`shaders/foveated.wgsl` for the downsampling
//! and the blend, `shaders/pyramid.wgsl` for the layers).

use crate::common::{check_focus, check_rgbd, eye_for};
use crate::error::{invalid, RenderError};
use crate::pyramid::{render_into, render_with, Region, Setup};
use dioptra_core::{DepthMap, Diopters, EyeModel, Plane, RgbImage, Rgbd};
use rayon::prelude::*;

/// Spacing of the acuity-level grid's nodes, full-resolution pixels.
pub const GRID: usize = 16;
/// Pixels per run of a row whose levels' range the blend checks before reading a layer there.
const SPAN: usize = 16;
/// The coarsest layer: scale 2^MAX_LAYER.
pub const MAX_LAYER: usize = 4;
/// Width of the blend from one layer to the next, in acuity levels: layer `k + 1` fades in
/// over `l` in `[k + 1, k + 1 + BLEND]`, where acuity already allows it, so no pixel is ever
/// coarser than the model allows.
pub const BLEND: f32 = 0.5;
/// Guenter et al.'s conservative MAR slope: 1.32 arcmin per degree of eccentricity.
pub const DEFAULT_MAR_SLOPE: f32 = 1.32 / 60.0;
/// The default foveal radius, degrees (the central 10 degrees at full resolution).
pub const DEFAULT_RADIUS_DEG: f32 = 5.0;

/// This module's constants as WGSL, for shaders/foveated.wgsl (prepended by the GPU context).
pub(crate) fn shared_wgsl() -> String {
    format!("const GRID: u32 = {GRID}u;\nconst BLEND: f32 = {BLEND:?};\n")
}

/// Where the viewer looks and how fast acuity falls away from it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Foveation {
    /// Gaze point, pixels of the image (pixel centres at +0.5).
    pub gaze: [f32; 2],
    /// Radius around the gaze rendered at full resolution, degrees.
    pub radius_deg: f32,
    /// Growth of the minimum angle of resolution beyond it, degrees per degree.
    pub mar_slope: f32,
}

impl Foveation {
    /// The defaults around `gaze` (pixels).
    pub fn at(gaze: [f32; 2]) -> Foveation {
        Foveation {
            gaze,
            radius_deg: DEFAULT_RADIUS_DEG,
            mar_slope: DEFAULT_MAR_SLOPE,
        }
    }

    fn check(&self) -> Result<(), RenderError> {
        let ok = self.gaze.iter().all(|v| v.is_finite() && v.abs() < 1e7)
            && self.radius_deg.is_finite()
            && (0.0..=180.0).contains(&self.radius_deg)
            && self.mar_slope.is_finite()
            && self.mar_slope > 0.0
            && self.mar_slope <= 10.0;
        if ok {
            Ok(())
        } else {
            Err(invalid(format!(
                "foveation {self:?} is invalid: expected a finite gaze, 0 <= radius <= 180 degrees and 0 < slope <= 10 degrees per degree"
            )))
        }
    }
}

/// One layer of a foveated frame: its scale and the part of its grid it computes.
#[derive(Debug, Clone, PartialEq)]
pub struct Layer {
    /// Level k: the layer is 2^k times coarser than the image.
    pub level: usize,
    pub width: usize,
    pub height: usize,
    /// The pixels computed, in the layer's own pixels.
    pub region: Region,
    /// How many pixels that is.
    pub pixels: usize,
}

/// The layers of a foveated frame and the acuity levels they are blended by.
#[derive(Debug, Clone, PartialEq)]
pub struct FoveationPlan {
    pub width: usize,
    pub height: usize,
    /// Acuity level per grid node (`gw` x `gh`, a node every [`GRID`] pixels).
    pub levels: Vec<f32>,
    pub gw: usize,
    pub gh: usize,
    /// The coarsest layer.
    pub top: usize,
    /// Layers with work to do (level ascending); the others have no weight anywhere.
    pub layers: Vec<Layer>,
}

impl FoveationPlan {
    /// The plan for a `width` x `height` image seen by `eye`.
    pub fn new(
        width: usize,
        height: usize,
        eye: &EyeModel,
        fov: &Foveation,
    ) -> Result<FoveationPlan, RenderError> {
        fov.check()?;
        if width == 0 || height == 0 {
            return Err(invalid("the image to foveate is empty"));
        }
        let eye = eye_for(eye, width)?;
        let pitch = eye.pixel_pitch_tan();
        let pixel_deg = eye.pixel_angle_rad().to_degrees();
        // Layers no smaller than 8 pixels a side.
        let mut top = 0;
        while top < MAX_LAYER && width.min(height) >> (top + 1) >= 8 {
            top += 1;
        }
        let (gw, gh) = (width.div_ceil(GRID) + 1, height.div_ceil(GRID) + 1);
        let dir = |x: f32, y: f32| {
            let v = [
                (x - 0.5 * width as f32) * pitch,
                (y - 0.5 * height as f32) * pitch,
                1.0f32,
            ];
            let n = (v[0] * v[0] + v[1] * v[1] + 1.0).sqrt();
            v.map(|c| c / n)
        };
        let g = dir(fov.gaze[0], fov.gaze[1]);
        let levels: Vec<f32> = (0..gw * gh)
            .map(|i| {
                let v = dir(((i % gw) * GRID) as f32, ((i / gw) * GRID) as f32);
                let cross = [
                    v[1] * g[2] - v[2] * g[1],
                    v[2] * g[0] - v[0] * g[2],
                    v[0] * g[1] - v[1] * g[0],
                ];
                let s = (cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]).sqrt();
                let c = v[0] * g[0] + v[1] * g[1] + v[2] * g[2];
                let e = s.atan2(c).to_degrees();
                let grow = fov.mar_slope * (e - fov.radius_deg).max(0.0) / pixel_deg;
                (1.0 + grow).log2().clamp(0.0, top as f32 + 1.0)
            })
            .collect();
        let mut layers = Vec::new();
        for k in 0..=top {
            // Layer k has weight where the level is in (k, k + 1 + BLEND) (open-ended at the
            // first and last layers).
            let (lo, hi) = (k as f32, k as f32 + 1.0 + BLEND);
            // Grid cells whose level range meets the layer's: their pixels' bounds.
            let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0usize, 0usize);
            let (mut inner, mut outer) = (f32::INFINITY, 0.0f32);
            for cy in 0..gh - 1 {
                for cx in 0..gw - 1 {
                    let v = [
                        levels[cy * gw + cx],
                        levels[cy * gw + cx + 1],
                        levels[(cy + 1) * gw + cx],
                        levels[(cy + 1) * gw + cx + 1],
                    ];
                    let (mn, mx) = (
                        v.iter().copied().fold(f32::INFINITY, f32::min),
                        v.iter().copied().fold(0.0f32, f32::max),
                    );
                    if !((k == 0 || mx > lo) && (k == top || mn < hi)) {
                        continue;
                    }
                    let (px0, py0) = (cx * GRID, cy * GRID);
                    let (px1, py1) = ((px0 + GRID).min(width), (py0 + GRID).min(height));
                    if px0 >= px1 || py0 >= py1 {
                        continue;
                    }
                    x0 = x0.min(px0);
                    y0 = y0.min(py0);
                    x1 = x1.max(px1);
                    y1 = y1.max(py1);
                    // Nearest and farthest points of the cell from the gaze.
                    let nx = (fov.gaze[0].clamp(px0 as f32, px1 as f32)) - fov.gaze[0];
                    let ny = (fov.gaze[1].clamp(py0 as f32, py1 as f32)) - fov.gaze[1];
                    inner = inner.min((nx * nx + ny * ny).sqrt());
                    let fx = (px0 as f32 - fov.gaze[0])
                        .abs()
                        .max((px1 as f32 - fov.gaze[0]).abs());
                    let fy = (py0 as f32 - fov.gaze[1])
                        .abs()
                        .max((py1 as f32 - fov.gaze[1]).abs());
                    outer = outer.max((fx * fx + fy * fy).sqrt());
                }
            }
            if x0 >= x1 {
                continue;
            }
            let s = (1usize << k) as f32;
            let (lw, lh) = (width.div_ceil(1 << k), height.div_ceil(1 << k));
            // Two layer texels of margin for the bilinear read-back.
            let margin = 2.0;
            let region = Region {
                x0: ((x0 as f32 / s).floor() - margin).max(0.0) as usize,
                y0: ((y0 as f32 / s).floor() - margin).max(0.0) as usize,
                x1: (((x1 as f32 / s).ceil() + margin) as usize).min(lw),
                y1: (((y1 as f32 / s).ceil() + margin) as usize).min(lh),
                centre: [fov.gaze[0] / s, fov.gaze[1] / s],
                inner: if k == 0 { -1.0 } else { inner / s - margin },
                outer: if k == top {
                    f32::INFINITY
                } else {
                    outer / s + margin
                },
            };
            let pixels = (region.y0..region.y1)
                .flat_map(|y| region.row_runs(y))
                .map(|(a, b)| b - a)
                .sum();
            layers.push(Layer {
                level: k,
                width: lw,
                height: lh,
                region,
                pixels,
            });
        }
        Ok(FoveationPlan {
            width,
            height,
            levels,
            gw,
            gh,
            top,
            layers,
        })
    }

    /// Pixels computed over all layers as a fraction of the image's.
    pub fn work_fraction(&self) -> f64 {
        self.layers.iter().map(|l| l.pixels).sum::<usize>() as f64
            / (self.width * self.height) as f64
    }

    /// The acuity level at pixel `(x, y)`: the grid's bilinear interpolation.
    #[inline]
    pub fn level_at(&self, x: usize, y: usize) -> f32 {
        level_at(&self.levels, self.gw, self.gh, x, y)
    }
}

/// Bilinear interpolation of the node levels at pixel `(x, y)`'s centre.
#[inline]
pub(crate) fn level_at(levels: &[f32], gw: usize, gh: usize, x: usize, y: usize) -> f32 {
    let inv = 1.0 / GRID as f32;
    let u = ((x as f32 + 0.5) * inv).min((gw - 1) as f32);
    let v = ((y as f32 + 0.5) * inv).min((gh - 1) as f32);
    let (x0, y0) = (u as usize, v as usize);
    let (x1, y1) = ((x0 + 1).min(gw - 1), (y0 + 1).min(gh - 1));
    let (fx, fy) = (u - x0 as f32, v - y0 as f32);
    let a = levels[y0 * gw + x0];
    let b = levels[y0 * gw + x1];
    let c = levels[y1 * gw + x0];
    let d = levels[y1 * gw + x1];
    let top = a + fx * (b - a);
    let bot = c + fx * (d - c);
    top + fy * (bot - top)
}

/// Weight of layer `k` (of `0..=top`) at acuity level `l`: layer `k` fades in over
/// `[k, k + BLEND]` and out over `[k + 1, k + 1 + BLEND]` (smoothsteps); the weights sum to 1.
#[inline]
pub(crate) fn layer_weight(l: f32, k: usize, top: usize) -> f32 {
    let smooth = |t: f32| {
        let t = t.clamp(0.0, 1.0);
        t * t * (3.0 - 2.0 * t)
    };
    let kf = k as f32;
    let rising = if k == 0 {
        1.0
    } else {
        smooth((l - kf) / BLEND)
    };
    let falling = if k == top {
        1.0
    } else {
        1.0 - smooth((l - kf - 1.0) / BLEND)
    };
    rising * falling
}

/// `input` box-downsampled by 2: colour and diopters averaged over each 2 x 2 block (the
/// blocks of an odd edge average the pixels they have).
pub fn downsample(input: &Rgbd) -> Result<Rgbd, RenderError> {
    let (w, h) = (input.width(), input.height());
    let (lw, lh) = (w.div_ceil(2), h.div_ceil(2));
    let half = |p: &[f32]| -> Result<Plane, RenderError> {
        let mut out = vec![0.0f32; lw * lh];
        out.par_chunks_mut(lw).enumerate().for_each(|(y, row)| {
            let top = &p[2 * y * w..(2 * y + 1) * w];
            if 2 * y + 1 < h {
                let bot = &p[(2 * y + 1) * w..(2 * y + 2) * w];
                // Whole blocks, summed in the order (top left, top right, bottom left, bottom
                // right) as the odd edge's are.
                for ((o, t), b) in row
                    .iter_mut()
                    .zip(top.chunks_exact(2))
                    .zip(bot.chunks_exact(2))
                {
                    *o = (t[0] + t[1] + b[0] + b[1]) / 4.0;
                }
                if w % 2 == 1 {
                    row[lw - 1] = (top[w - 1] + bot[w - 1]) / 2.0;
                }
            } else {
                for (o, t) in row.iter_mut().zip(top.chunks_exact(2)) {
                    *o = (t[0] + t[1]) / 2.0;
                }
                if w % 2 == 1 {
                    row[lw - 1] = top[w - 1];
                }
            }
        });
        Ok(Plane::from_vec(lw, lh, out)?)
    };
    let [r, g, b] = input.color.channels.each_ref().map(|c| half(c.data()));
    Ok(Rgbd::new(
        RgbImage::from_planes(r?, g?, b?)?,
        DepthMap::from_diopters(half(input.depth.data())?)?,
    )?)
}

/// A foveated render and what it cost.
#[derive(Debug, Clone)]
pub struct FoveatedImage {
    pub image: RgbImage,
    pub plan: FoveationPlan,
}

/// The pyramid defocus of `input` at `focus`, foveated around `fov.gaze`.
pub fn foveated(
    input: &Rgbd,
    focus: Diopters,
    eye: &EyeModel,
    fov: &Foveation,
) -> Result<FoveatedImage, RenderError> {
    check_rgbd(input)?;
    check_focus(focus)?;
    let (w, h) = (input.width(), input.height());
    let plan = FoveationPlan::new(w, h, eye, fov)?;
    // Each layer's input (downsampled from the one before) and its render; layer 0's straight
    // into the image (black where it is not computed), which the blend then weighs in place.
    let mut inputs: Vec<Rgbd> = Vec::with_capacity(plan.top);
    let mut renders: Vec<Option<RgbImage>> = vec![None; plan.top + 1];
    let mut image = [
        vec![0.0f32; w * h],
        vec![0.0f32; w * h],
        vec![0.0f32; w * h],
    ];
    let mut fovea = false;
    let range = input.depth.range();
    for layer in &plan.layers {
        while inputs.len() < layer.level {
            let next = downsample(inputs.last().unwrap_or(input))?;
            inputs.push(next);
        }
        let src = if layer.level == 0 {
            input
        } else {
            &inputs[layer.level - 1]
        };
        // Every layer's levels from the full image's depth range, as the GPU twin has them.
        let setup = Setup::with_range(src, range, focus, eye)?;
        if layer.level == 0 {
            render_into(&setup, src, &layer.region, &mut image);
            fovea = true;
        } else {
            renders[layer.level] = Some(render_with(&setup, src, &layer.region)?);
        }
    }
    blend(&plan, fovea, &renders, &mut image);
    let [r, g, b] = image.map(|v| Plane::from_vec(w, h, v));
    Ok(FoveatedImage {
        image: RgbImage::from_planes(r?, g?, b?)?,
        plan,
    })
}

/// Every pixel of `out`: the layers with weight there, each read bilinearly, summed. `out`
/// holds layer 0's render where `fovea` (`renders[0]` is not read) and is black elsewhere; the
/// coarser layers are in `renders`. Row by row: the acuity levels first (the grid's bilinear
/// interpolation through per-column and per-row tables), then layer 0 weighed in place, then
/// each coarser layer over the columns where it has weight, its two texel rows interpolated
/// once there and read at each pixel through a per-column table.
fn blend(plan: &FoveationPlan, fovea: bool, renders: &[Option<RgbImage>], out: &mut [Vec<f32>; 3]) {
    let (w, h) = (plan.width, plan.height);
    let top = plan.top;
    let planes: Vec<Option<[&[f32]; 3]>> = renders
        .iter()
        .map(|r| r.as_ref().map(|i| i.channels.each_ref().map(|p| p.data())))
        .collect();
    // Per layer, per column: the two texels a pixel reads and the second's weight.
    let columns: Vec<Vec<(usize, usize, f32)>> = (0..planes.len())
        .map(|k| {
            let s = 1usize << k;
            let lw = w.div_ceil(s);
            (0..w).map(|x| axis(x, s, lw)).collect()
        })
        .collect();
    // The acuity grid's nodes and weight per column and per row, as `level_at` takes them.
    let (gw, gh) = (plan.gw, plan.gh);
    let node_axis = |x: usize, n: usize| {
        let u = ((x as f32 + 0.5) * (1.0 / GRID as f32)).min((n - 1) as f32);
        let i = u as usize;
        (i, (i + 1).min(n - 1), u - i as f32)
    };
    let node_cols: Vec<(usize, usize, f32)> = (0..w).map(|x| node_axis(x, gw)).collect();
    // Layer k has weight where k < l < k + 1 + BLEND (open at the ends), and its full weight
    // where neither fade applies (most pixels).
    let has = |k: usize, l: f32| {
        let kf = k as f32;
        (k == 0 || l > kf) && (k == top || l < kf + 1.0 + BLEND)
    };
    let weight = |k: usize, l: f32| {
        let kf = k as f32;
        if (k == 0 || l >= kf + BLEND) && (k == top || l <= kf + 1.0) {
            1.0
        } else {
            layer_weight(l, k, top)
        }
    };
    let [r_out, g_out, b_out] = out;
    r_out
        .par_chunks_mut(w)
        .zip(g_out.par_chunks_mut(w))
        .zip(b_out.par_chunks_mut(w))
        .enumerate()
        .for_each_init(
            || (Vec::new(), Vec::new(), Vec::new()),
            |(lev, spans, texels): &mut (Vec<f32>, Vec<[f32; 2]>, Vec<[f32; 3]>),
             (y, ((ro, go), bo))| {
                let (y0, y1, fy) = node_axis(y, gh);
                let (top_row, bot_row) = (&plan.levels[y0 * gw..], &plan.levels[y1 * gw..]);
                lev.clear();
                lev.extend(node_cols.iter().map(|&(x0, x1, fx)| {
                    let (a, b) = (top_row[x0], top_row[x1]);
                    let (c, d) = (bot_row[x0], bot_row[x1]);
                    let t = a + fx * (b - a);
                    let u = c + fx * (d - c);
                    t + fy * (u - t)
                }));
                // The levels' range over each run of SPAN pixels: a layer is read only in the
                // runs where some pixel's level gives it weight.
                spans.clear();
                spans.extend(lev.chunks(SPAN).map(|c| {
                    c.iter()
                        .fold([f32::INFINITY, f32::NEG_INFINITY], |[a, b], &l| {
                            [a.min(l), b.max(l)]
                        })
                }));
                let mut row = [ro, go, bo];
                // Layer 0 in place: as a sum from zero of its weight times its read (at scale 1
                // a pixel's own texel, both interpolations' fractions 0), as the coarser
                // layers are added; zero where it has no weight.
                let span0 = if fovea {
                    let xa = lev.iter().position(|&l| has(0, l)).unwrap_or(w);
                    (
                        xa,
                        w - lev.iter().rev().position(|&l| has(0, l)).unwrap_or(w - xa),
                    )
                } else {
                    (w, w)
                };
                for (x, &l) in lev.iter().enumerate() {
                    let wt = if (span0.0..span0.1).contains(&x) {
                        weight(0, l)
                    } else {
                        0.0
                    };
                    for plane in row.iter_mut() {
                        plane[x] = if wt > 0.0 {
                            // The reads of a coarser layer: between texel rows, then across.
                            let texel = lerp(plane[x], plane[x], 0.0);
                            0.0 + wt * lerp(texel, texel, 0.0)
                        } else {
                            0.0
                        };
                    }
                }
                for (k, p) in planes.iter().enumerate().skip(1) {
                    let Some(p) = p else { continue };
                    // Runs where the layer may have weight (a pixel with `has`), and within
                    // the first and last of them, the first and last such pixel.
                    let kf = k as f32;
                    let may = |&[lo, hi]: &[f32; 2]| hi > kf && (k == top || lo < kf + 1.0 + BLEND);
                    let Some(sa) = spans.iter().position(may) else {
                        continue;
                    };
                    let sb = spans.len() - spans.iter().rev().position(may).unwrap_or(0);
                    let (pa, pb) = (sa * SPAN, (sb * SPAN).min(w));
                    let Some(xa) = lev[pa..pb].iter().position(|&l| has(k, l)).map(|x| pa + x)
                    else {
                        continue;
                    };
                    let xb = pb
                        - lev[pa..pb]
                            .iter()
                            .rev()
                            .position(|&l| has(k, l))
                            .unwrap_or(0);
                    let s = 1usize << k;
                    let (lw, lh) = (w.div_ceil(s), h.div_ceil(s));
                    // The layer's row at this pixel row, interpolated between its two texel
                    // rows, over the texels columns xa..xb read.
                    let (ty0, ty1, fy) = axis(y, s, lh);
                    let (ta, tb) = (columns[k][xa].0, columns[k][xb - 1].1 + 1);
                    texels.clear();
                    texels.extend((ta..tb).map(|i| {
                        std::array::from_fn(|c| {
                            let (a, b) = (p[c][ty0 * lw + i], p[c][ty1 * lw + i]);
                            a + fy * (b - a)
                        })
                    }));
                    let mut run = xa;
                    while run < xb {
                        let end = ((run / SPAN + 1) * SPAN).min(xb);
                        // A run where no pixel has weight (`weight` gives none) is skipped.
                        if may(&spans[run / SPAN]) {
                            for x in run..end {
                                let wt = weight(k, lev[x]);
                                if wt <= 0.0 {
                                    continue;
                                }
                                let (x0, x1, fx) = columns[k][x];
                                let (a, b) = (texels[x0 - ta], texels[x1 - ta]);
                                for c in 0..3 {
                                    row[c][x] += wt * (a[c] + fx * (b[c] - a[c]));
                                }
                            }
                        }
                        run = end;
                    }
                }
            },
        );
}

/// `a + t (b - a)`: the layers' interpolation, as the blend computes it.
#[inline(always)]
fn lerp(a: f32, b: f32, t: f32) -> f32 {
    a + t * (b - a)
}

/// The two texels of a layer of scale `s` (`n` texels along the axis) that full-resolution
/// pixel `x` reads bilinearly, edges clamped, and the second's weight: [`crate::pyramid`]'s
/// level read. At scale 1 the pixel's own texel.
#[inline]
fn axis(x: usize, s: usize, n: usize) -> (usize, usize, f32) {
    if s == 1 {
        return (x, x, 0.0);
    }
    let u = ((x as f32 + 0.5) / s as f32 - 0.5).clamp(0.0, (n - 1) as f32);
    let x0 = u as usize;
    (x0, (x0 + 1).min(n - 1), u - x0 as f32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pyramid::pyramid;

    fn rgbd(w: usize, h: usize) -> Rgbd {
        let plane = |c: usize| {
            Plane::from_vec(
                w,
                h,
                (0..w * h)
                    .map(|i| {
                        let (x, y) = ((i % w) as f32, (i / w) as f32);
                        0.5 + 0.3 * (0.3 * x + c as f32).sin() * (0.23 * y).cos()
                    })
                    .collect(),
            )
            .unwrap()
        };
        let d: Vec<f32> = (0..w * h)
            .map(|i| if (i % w) < w / 3 { 2.0 } else { 0.5 })
            .collect();
        Rgbd::new(
            RgbImage::from_planes(plane(0), plane(1), plane(2)).unwrap(),
            DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap(),
        )
        .unwrap()
    }

    #[test]
    fn weights_sum_to_one_and_are_continuous() {
        for top in [0usize, 1, 3, 4] {
            let mut prev: Option<Vec<f32>> = None;
            for i in 0..=500 {
                let l = (i as f32 / 100.0).min(top as f32 + 1.0);
                let w: Vec<f32> = (0..=top).map(|k| layer_weight(l, k, top)).collect();
                let s: f32 = w.iter().sum();
                assert!((s - 1.0).abs() < 1e-5, "top {top} l {l}: {w:?}");
                if let Some(p) = &prev {
                    for (a, b) in w.iter().zip(p) {
                        assert!((a - b).abs() < 0.035, "jump at {l}");
                    }
                }
                prev = Some(w);
            }
        }
        assert_eq!(layer_weight(0.0, 0, 3), 1.0);
        // Layer 1 takes over only where acuity allows its scale (level 1 and beyond).
        assert_eq!(layer_weight(0.99, 1, 3), 0.0);
        assert_eq!(layer_weight(1.0 + BLEND, 1, 3), 1.0);
        assert_eq!(layer_weight(4.0, 3, 3), 1.0);
    }

    #[test]
    fn the_fovea_is_full_resolution_and_the_work_drops() {
        // 5 degrees of a 20 degree field: the fovea is a quarter of the width across.
        let (w, h) = (256, 224);
        let eye = EyeModel::default();
        let fov = Foveation::at([100.0, 120.0]);
        let plan = FoveationPlan::new(w, h, &eye, &fov).unwrap();
        assert!(plan.top >= 3, "{}", plan.top);
        assert_eq!(plan.layers[0].level, 0);
        // At 12.8 px/deg acuity allows little coarsening inside the image: most of it is
        // layer 0, and the blend bands cost a little more than the full render.
        assert!(plan.work_fraction() < 1.2, "work {}", plan.work_fraction());
        // At a panel's pixel density the periphery's saving is large: 960 x 1080 over 20
        // degrees (48 px/deg), gaze off centre.
        let panel = FoveationPlan::new(960, 1080, &eye, &Foveation::at([400.0, 600.0])).unwrap();
        let frac = panel.work_fraction();
        eprintln!(
            "960 x 1080 over 20 degrees: {:.1} % of the pixels computed",
            100.0 * frac
        );
        // Layer 0 is the 5 degree foveal radius and the blend band to layer 1 (6.7 degrees,
        // 35 % of the image); the rest adds under a fifth.
        assert!(frac < 0.55, "work {frac}");
        assert!(panel.layers.len() >= 4, "{:?}", panel.layers);
        // Within the foveal radius the level is 0; at the corner it is positive.
        let ppd = w as f32 / 20.0;
        for (x, y) in [(100usize, 120usize), (100 + (4.0 * ppd) as usize, 120)] {
            assert_eq!(plan.level_at(x, y), 0.0, "({x},{y})");
        }
        assert!(plan.level_at(w - 1, 0) > 1.0);
        let input = rgbd(w, h);
        let q = Diopters(0.5);
        let f = foveated(&input, q, &eye, &fov).unwrap();
        let full = pyramid(&input, q, &eye).unwrap();
        // Bit for bit the full render where only layer 0 has weight.
        let mut checked = 0;
        for y in 0..h {
            for x in 0..w {
                if plan.level_at(x, y) == 0.0 {
                    let i = y * w + x;
                    for c in 0..3 {
                        assert_eq!(
                            f.image.channels[c].data()[i],
                            full.channels[c].data()[i],
                            "({x},{y})"
                        );
                    }
                    checked += 1;
                }
            }
        }
        assert!(checked > 3000, "{checked}");
    }

    #[test]
    fn downsampling_averages_blocks() {
        let input = rgbd(5, 3);
        let d = downsample(&input).unwrap();
        assert_eq!((d.width(), d.height()), (3, 2));
        let c = &input.color.channels[1];
        let want = (c.data()[0] + c.data()[1] + c.data()[5] + c.data()[6]) / 4.0;
        assert!((d.color.channels[1].data()[0] - want).abs() < 1e-6);
        // The last column's blocks are one pixel wide; the last row's one pixel high.
        let want = (c.data()[4] + c.data()[9]) / 2.0;
        assert!((d.color.channels[1].data()[2] - want).abs() < 1e-6);
        assert_eq!(d.color.channels[1].data()[5], c.data()[14]);
    }

    #[test]
    fn bad_foveation_is_an_error() {
        let eye = EyeModel::default();
        for f in [
            Foveation::at([f32::NAN, 1.0]),
            Foveation {
                radius_deg: -1.0,
                ..Foveation::at([1.0, 1.0])
            },
            Foveation {
                mar_slope: 0.0,
                ..Foveation::at([1.0, 1.0])
            },
        ] {
            let e = FoveationPlan::new(64, 64, &eye, &f).unwrap_err();
            assert!(e.to_string().contains("foveation"), "{e}");
        }
    }
}
