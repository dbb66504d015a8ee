//! Depth of field by dynamic light-field generation and filtering (Yu, Wang, Yu 2010).
//!
//! The reference (pinhole) RGB-D view is warped to N virtual cameras on the pupil disk,
//! Halton-jittered. A point at depth d seen at reference pixel x appears, in the camera at lens
//! position L sheared to focus at q, at x - L (d - q) / pitch (the eye model's CoC geometry).
//! Visibility is resolved by keeping the nearest source per target pixel (Yu's atomic min on
//! disparity; here each view is warped by one thread, so a plain max over
//! (diopters, source index) keys gives the same deterministic result the GPU's atomicMax will).
//! Rounding holes are filled by a widened (3 x 3) write footprint that only fills pixels no
//! exact write reached, keeping the farthest candidate, so silhouettes are not dilated into
//! disocclusions. Synthesis sums the views with
//! cos^4 weights, skipping invalid (disoccluded) rays; each ray's colour is read from a Gaussian
//! pyramid at the level of its blur per view spacing (Yu eq. 8), which turns the N discrete
//! copies of a defocused point into a smooth disk.

use crate::common::{check_focus, check_rgbd, eye_for, max_coc};
use crate::error::{invalid, RenderError};
use crate::kernel::{gaussian_taps, separable_blur};
use dioptra_core::sampling::radical_inverse;
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};
use rayon::prelude::*;
use std::sync::OnceLock;

/// Parameters of the light-field method.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightFieldParams {
    /// Number of virtual lens cameras (Yu et al. use 36; 12 to 64 is sensible).
    pub views: usize,
    /// Prefilter rays by their blur size (Gaussian pyramid).
    pub mip: bool,
}

impl Default for LightFieldParams {
    fn default() -> Self {
        LightFieldParams {
            views: 36,
            mip: true,
        }
    }
}

/// Standard deviations (pixels) of the pyramid levels; level 0 is the image itself. The GPU
/// host code uses these, and every shader gets them from here (`gpu::context::shared_wgsl`).
pub(crate) const LEVEL_SIGMA: [f32; 7] = [0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0];
/// Gaussian sigma per pixel of spacing between adjacent views' copies of a point (shared as
/// [`LEVEL_SIGMA`] is).
pub(crate) const PREFILTER: f32 = 0.35;

/// Work shared by every focus for one input: the Gaussian pyramid and the lens samples.
pub struct LightFieldPrep<'a> {
    input: &'a Rgbd,
    eye: EyeModel,
    params: LightFieldParams,
    /// Levels x channels, full resolution (exact Gaussians rather than decimated mips). Built
    /// on first use: a focus near the content reads only the fine levels, and the coarse ones
    /// (97-tap blurs) cost most.
    levels: Vec<OnceLock<[Plane; 3]>>,
    lens: Vec<[f32; 2]>,
}

/// `n` lens positions on the unit disk from the Halton (2, 3) sequence, area-preserving.
pub fn halton_disk(n: usize) -> Vec<[f32; 2]> {
    (1..=n as u32)
        .map(|i| {
            let (u, v) = (radical_inverse(i, 2), radical_inverse(i, 3));
            let (r, phi) = (u.sqrt(), std::f32::consts::TAU * v);
            [r * phi.cos(), r * phi.sin()]
        })
        .collect()
}

/// Forward-warps every source pixel `i` (depth `d` diopters) to `x + shift (d - q)` pixels,
/// keeping per target pixel the nearest source (max of (diopter bits, index + 1) keys; 0 is
/// empty) in `exact`. Yu et al. widen each write to fill rounding cracks; here the fill is
/// read on demand by [`wide_key`] for the pixels no exact write reached.
pub(crate) fn splat_exact(
    depth: &[f32],
    w: usize,
    h: usize,
    shift: [f32; 2],
    q: f32,
    exact: &mut [u64],
) {
    exact.fill(0);
    let (wf, hf) = (w as f32, h as f32);
    // Per row, the target pixels first (branch-free in i32, so it vectorises), then the
    // scattered writes: the splat is the light field's costliest part.
    let mut tcol = vec![-1i32; w];
    let mut trow = vec![-1i32; w];
    for (y, row) in depth.chunks(w).enumerate().take(h) {
        let fy = y as f32 + 0.5;
        for (x, ((&d, cx), cy)) in row.iter().zip(&mut tcol).zip(&mut trow).enumerate() {
            let tx = x as f32 + 0.5 + shift[0] * (d - q);
            let ty = fy + shift[1] * (d - q);
            let inside = tx >= 0.0 && ty >= 0.0 && tx < wf && ty < hf;
            // Inside, truncation is the floor.
            *cx = if inside { tx as i32 } else { -1 };
            *cy = ty as i32;
        }
        let first = (y * w) as u64 + 1;
        for (x, ((&d, &cx), &cy)) in row.iter().zip(&tcol).zip(&trow).enumerate() {
            if cx >= 0 {
                let v = &mut exact[cy as usize * w + cx as usize];
                *v = (*v).max(((d.to_bits() as u64) << 32) | (first + x as u64));
            }
        }
    }
}

/// The widened-write key of an empty target pixel `(x, y)`: the farthest key among its 3 x 3
/// neighbours in `exact` (0 if none), since a crack inside a surface is surrounded by that
/// surface while a disocclusion should show background, not dilated foreground. Equivalent
/// to Yu et al.'s eight extra writes per source, done once per empty pixel.
#[inline]
pub(crate) fn wide_key(exact: &[u64], w: usize, h: usize, x: usize, y: usize) -> u64 {
    let mut best = u64::MAX;
    for ny in y.saturating_sub(1)..(y + 2).min(h) {
        for &k in &exact[ny * w + x.saturating_sub(1)..ny * w + (x + 2).min(w)] {
            if k != 0 && k < best {
                best = k;
            }
        }
    }
    if best == u64::MAX {
        0
    } else {
        best
    }
}

/// The source pixel a splat key names, if any.
#[inline]
pub(crate) fn key_source(key: u64) -> Option<usize> {
    (key != 0).then(|| (key & 0xffff_ffff) as usize - 1)
}

/// Checks the light-field method's inputs (both backends).
pub(crate) fn check_lightfield_inputs(
    input: &Rgbd,
    params: &LightFieldParams,
) -> Result<(), RenderError> {
    check_rgbd(input)?;
    check_lightfield_params(params)
}

pub(crate) fn check_lightfield_params(params: &LightFieldParams) -> Result<(), RenderError> {
    if !(1..=1024).contains(&params.views) {
        return Err(invalid(format!(
            "views = {} is invalid: expected 1 to 1024",
            params.views
        )));
    }
    Ok(())
}

impl<'a> LightFieldPrep<'a> {
    pub fn new(
        input: &'a Rgbd,
        eye: &EyeModel,
        params: LightFieldParams,
    ) -> Result<Self, RenderError> {
        check_lightfield_inputs(input, &params)?;
        let eye = eye_for(eye, input.width())?;
        let nlev = if params.mip { LEVEL_SIGMA.len() } else { 1 };
        let levels = (0..nlev).map(|_| OnceLock::new()).collect();
        let radius = 0.5 * eye.pupil_diameter.to_meters().0;
        let lens = halton_disk(params.views)
            .into_iter()
            .map(|p| [p[0] * radius, p[1] * radius])
            .collect();
        Ok(LightFieldPrep {
            input,
            eye,
            params,
            levels,
            lens,
        })
    }

    /// Colour of source pixel `i` prefiltered to Gaussian sigma `sigma`. (Reading at the exact
    /// sub-pixel position instead costs accuracy: bilinear taps mix across depth edges, while
    /// the rounding error averages out over the views.)
    fn fetch(&self, i: usize, sigma: f32) -> [f32; 3] {
        let l = self.level_below(sigma);
        if l == self.levels.len() - 1 {
            return self.level(l).each_ref().map(|p| p.data()[i]);
        }
        let (s0, s1) = (LEVEL_SIGMA[l], LEVEL_SIGMA[l + 1]);
        let t = ((sigma - s0) / (s1 - s0)).clamp(0.0, 1.0);
        let (a, b) = (self.level(l), self.level(l + 1));
        [0, 1, 2].map(|c| a[c].data()[i] * (1.0 - t) + b[c].data()[i] * t)
    }

    /// The finest level whose successor is at least `sigma` (or the top level).
    fn level_below(&self, sigma: f32) -> usize {
        let top = self.levels.len() - 1;
        let mut l = 0;
        while l < top && LEVEL_SIGMA[l + 1] < sigma {
            l += 1;
        }
        l
    }

    fn level(&self, l: usize) -> &[Plane; 3] {
        self.levels[l].get_or_init(|| {
            self.input.color.channels.each_ref().map(|p| {
                if l == 0 {
                    p.clone()
                } else {
                    separable_blur(p, &gaussian_taps(LEVEL_SIGMA[l]))
                }
            })
        })
    }

    /// The image seen focusing at `focus`.
    pub fn render(&self, focus: Diopters) -> Result<RgbImage, RenderError> {
        self.render_masked(focus, None)
    }

    /// [`Self::render`] on the pixels where `mask` is true; the rest keep the input colour
    /// (for callers that replace them, as [`crate::composite`] does: the splats still cover
    /// the whole image, the views' sum only the masked pixels).
    pub fn render_masked(
        &self,
        focus: Diopters,
        mask: Option<&[bool]>,
    ) -> Result<RgbImage, RenderError> {
        check_focus(focus)?;
        let (w, h) = (self.input.width(), self.input.height());
        let n = w * h;
        if mask.is_some_and(|m| m.len() != n) {
            return Err(crate::error::mismatch(format!(
                "a mask of {} pixels for a {w}x{h} light field",
                mask.map_or(0, |m| m.len())
            )));
        }
        let depth = self.input.depth.data();
        let pitch = self.eye.pixel_pitch_tan();
        let f = self.eye.lens_to_retina.to_meters().0;
        let spacing = 1.0 / (self.lens.len() as f32).sqrt();
        let q = focus.0;
        // Build the levels this focus reads before the parallel fetch, so no worker waits on
        // another's lazy build.
        let max_sigma = PREFILTER * max_coc(self.input, &self.eye, focus) * spacing;
        let needed = (self.level_below(max_sigma) + 1).min(self.levels.len() - 1);
        (0..=needed).for_each(|l| {
            self.level(l);
        });
        // A ray's prefilter depends only on its source pixel's depth and the focus, not on the
        // view: prefilter every source pixel once per focus instead of once per ray. The CoC
        // per diopter once (coc_px evaluates a tangent per call).
        let sigma_per_d = PREFILTER * self.eye.coc_px(Diopters(1.0), Diopters(0.0)) * spacing;
        let pre: Vec<[f32; 3]> = (0..n)
            .into_par_iter()
            .map(|i| self.fetch(i, sigma_per_d * (depth[i] - q).abs()))
            .collect();
        // Per-thread accumulators: [r, g, b, weight] per pixel.
        let acc = self
            .lens
            .par_iter()
            // One accumulator set per thread, not per view: each is several MB at 512^2.
            .with_min_len(
                self.lens
                    .len()
                    .div_ceil(rayon::current_num_threads().max(1)),
            )
            .fold(
                || (vec![[0.0f32; 4]; n], vec![0u64; n]),
                |(mut acc, mut exact), l| {
                    let (sx, sy) = (-l[0] / pitch, -l[1] / pitch);
                    splat_exact(depth, w, h, [sx, sy], q, &mut exact);
                    for (y, row) in acc.chunks_mut(w).enumerate() {
                        let ry = (y as f32 + 0.5 - 0.5 * h as f32) * pitch + l[1] / f;
                        let used = mask.map(|m| &m[y * w..(y + 1) * w]);
                        for (x, a) in row.iter_mut().enumerate() {
                            if used.is_some_and(|u| !u[x]) {
                                continue;
                            }
                            let mut key = exact[y * w + x];
                            if key == 0 {
                                key = wide_key(&exact, w, h, x, y);
                            }
                            let Some(src) = key_source(key) else {
                                continue; // invalid ray: disoccluded in this view
                            };
                            let c = pre[src];
                            // cos^4 of the ray from the lens point to the retinal point of (x, y).
                            let rx = (x as f32 + 0.5 - 0.5 * w as f32) * pitch + l[0] / f;
                            let c2 = 1.0 / (1.0 + rx * rx + ry * ry);
                            let wgt = c2 * c2;
                            for k in 0..3 {
                                a[k] += wgt * c[k];
                            }
                            a[3] += wgt;
                        }
                    }
                    (acc, exact)
                },
            )
            .map(|(acc, _)| acc)
            .reduce(
                || vec![[0.0f32; 4]; n],
                |mut a, b| {
                    a.iter_mut()
                        .zip(&b)
                        .for_each(|(x, y)| (0..4).for_each(|k| x[k] += y[k]));
                    a
                },
            );
        // cos^4 vignetting is relative: normalise by the weight so a uniform field stays uniform.
        let src = &self.input.color.channels;
        let planes = [0, 1, 2].map(|c| {
            let data = acc
                .iter()
                .enumerate()
                .map(|(j, a)| {
                    if a[3] > 0.0 {
                        a[c] / a[3]
                    } else {
                        src[c].data()[j]
                    }
                })
                .collect();
            Plane::from_vec(w, h, data).unwrap_or_else(|_| Plane::new(w, h, 0.0))
        });
        let [r, g, b] = planes;
        Ok(RgbImage::from_planes(r, g, b)?)
    }

    pub fn params(&self) -> LightFieldParams {
        self.params
    }
}

/// One-shot light-field depth of field.
pub fn lightfield(
    input: &Rgbd,
    focus: Diopters,
    eye: &EyeModel,
    params: LightFieldParams,
) -> Result<RgbImage, RenderError> {
    LightFieldPrep::new(input, eye, params)?.render(focus)
}
