//! The gaze-contingent hybrid multifocal decomposition (after Yu et al. 2019, "A
//! Perception-driven Hybrid Decomposition for Multi-layer Accommodative Displays", IEEE VR):
//! the expensive optimised decomposition only where it is perceptually superior, "depth
//! discontinuities at the fovea" in the paper's words, and linear blending everywhere else.
//!
//! What is taken from the paper is that split, not its perceptual model (which predicts per
//! region from contrast and eccentricity which strategy a viewer prefers; we have no such
//! model): here the region is a disk of `fovea_deg` around the gaze, and the optimisation runs
//! there only when a blurred depth step reaches it (the depth-edge scan of
//! [`crate::composite::step_reach`] at the spectral decomposition's foci). The optimisation is
//! [`crate::spectral`] on a window around the gaze; linear blending (Akeley 2004) is exact on
//! the planes and, away from occlusions, what the paper's users could not tell apart from the
//! optimisation outside the fovea.
//!
//! The window: the fovea, plus the widest blur's reach (so that what the eye sees in the fovea
//! comes from spectral layers alone), plus a cross-fade of `blend_deg` to linear blending, plus
//! context for the solve (twice the widest blur, which the solve's own padding would
//! otherwise replace by replicated edges). It keeps its size as the gaze moves (shifted to
//! stay inside the image), so the spectral plan is built once per panel size.
//!
//! At a panel's resolution (48 px per degree at 960 px over 20 degrees) the blur kernels are
//! large in pixels and the solve costs more than a frame: with `scale` = s > 1 the window is
//! solved at 1/s resolution (the colour and depth box-averaged), and the layers there are the
//! solve's, upsampled (bilinear), plus linear blending's detail above that resolution
//! (`L - up(down(L))`, computed as `L + up(Y - down(L))`). Detail finer than the low-resolution grid is seen sharply only by a
//! focus near its own plane, where linear blending is exact; what that costs in accuracy is
//! measured against full-resolution spectral (docs/eval/README.md, `examples/hybrid_accuracy`).
//! With no depth step in the fovea, or `scale` making a pure linear result
//! (`L - up(down(L)) + up(down(L))`), the output is linear blending exactly.

use crate::common::{check_rgbd, eye_for};
use crate::composite::step_reach;
use crate::error::{invalid, RenderError};
use crate::multifocal::{check_planes, linear_blend, Layers};
use crate::spectral::{SpectralParams, SpectralReport};
use crate::spectral_coarse::{
    auto_scale, box_down, down_rgbd, eye_with_pitch, up_taps, widest_blur_px,
};
use dioptra_core::{DepthMap, Diopters, EyeModel, Plane, RgbImage, Rgbd};
use rayon::prelude::*;

/// Settings of the hybrid decomposition.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HybridParams {
    /// Radius (degrees) around the gaze where the layers are the spectral solution's (the
    /// fovea: 2.5 degrees, a 5 degree disk).
    pub fovea_deg: f32,
    /// Width (degrees) of the cross-fade from spectral to linear layers outside it.
    pub blend_deg: f32,
    /// The spectral solve's resolution in the window: 1 full, s > 1 a 1/s grid plus linear
    /// blending's detail above it; 0 chooses (see [`HybridParams::scale_for`]).
    pub scale: usize,
    /// Optimise only when a blurred depth step reaches the fovea (Yu et al.'s depth
    /// discontinuities); otherwise the whole frame is linear blending.
    pub edges_only: bool,
    /// The spectral decomposition's own settings in the window.
    pub spectral: SpectralParams,
}

impl Default for HybridParams {
    fn default() -> Self {
        HybridParams {
            fovea_deg: 2.5,
            blend_deg: 0.5,
            scale: 0,
            edges_only: true,
            spectral: SpectralParams::default(),
        }
    }
}

/// With `scale` = 0, the solve's grid is coarsened until the widest blur (CoC diameter of a
/// plane at a focal sample) is at most this many of its pixels: below it the coarse grid
/// would no longer hold the kernels that tell the planes apart.
pub const AUTO_MIN_BLUR_PX: f32 = 8.0;

impl HybridParams {
    pub fn check(&self) -> Result<(), RenderError> {
        if !(self.fovea_deg.is_finite() && (0.0..=180.0).contains(&self.fovea_deg)) {
            return Err(invalid(format!(
                "hybrid fovea radius {} deg: expected 0 to 180",
                self.fovea_deg
            )));
        }
        if !(self.blend_deg.is_finite() && (0.0..=90.0).contains(&self.blend_deg)) {
            return Err(invalid(format!(
                "hybrid blend width {} deg: expected 0 to 90",
                self.blend_deg
            )));
        }
        if self.scale > 16 {
            return Err(invalid(format!(
                "hybrid scale {}: expected 0 (automatic) to 16",
                self.scale
            )));
        }
        self.spectral.check()
    }

    /// The solve's grid divisor for a widest blur of `max_blur_px` (full-resolution pixels):
    /// `scale` if set, else the largest s with `max_blur_px / s >= AUTO_MIN_BLUR_PX` (1 at
    /// least).
    pub fn scale_for(&self, max_blur_px: f32) -> usize {
        if self.scale > 0 {
            return self.scale;
        }
        auto_scale(max_blur_px, AUTO_MIN_BLUR_PX)
    }
}

/// Where the hybrid solved, in full-resolution pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HybridWindow {
    pub x0: usize,
    pub y0: usize,
    pub width: usize,
    pub height: usize,
    /// The solve's grid divisor.
    pub scale: usize,
    /// Radius (pixels) of full spectral weight around the gaze, and where linear takes over.
    pub inner_px: f32,
    pub outer_px: f32,
}

/// What [`hybrid_blend`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct HybridReport {
    /// The gaze point used (pixels).
    pub gaze: [f32; 2],
    /// The window solved (`None`: linear blending everywhere, no depth step reached the
    /// fovea).
    pub window: Option<HybridWindow>,
    /// The spectral solve's report, when it ran.
    pub spectral: Option<SpectralReport>,
    /// Wall time of each stage, milliseconds: linear blending of the whole image, the
    /// depth-edge scan of the fovea, the window's spectral solve (its input prepared, its
    /// target stack included), and composing the window into the layers.
    pub stages_ms: HybridStages,
}

/// Wall time of [`hybrid_blend_with`]'s stages, milliseconds (0 for a stage not run).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct HybridStages {
    pub linear: f64,
    pub scan: f64,
    pub solve: f64,
    pub compose: f64,
}

/// The window's geometry for an image, a gaze and the settings (before any solve).
pub fn window_for(
    width: usize,
    height: usize,
    eye: &EyeModel,
    planes: &[Diopters],
    gaze: [f32; 2],
    params: &HybridParams,
) -> Result<HybridWindow, RenderError> {
    let eye = eye_for(eye, width)?;
    let pitch = eye.pixel_pitch_tan();
    let px_per_deg = 1.0f32.to_radians().tan() / pitch;
    let max_blur = widest_blur_px(&eye, planes, params.spectral.focal_range);
    let reach = 0.5 * max_blur + 1.0;
    let inner = params.fovea_deg * px_per_deg + reach;
    let outer = inner + params.blend_deg * px_per_deg;
    let half = outer + 2.0 * reach;
    let s = params.scale_for(max_blur);
    // A side that is a multiple of s, no larger than the image's (rounded down to s).
    let side = |full: usize| -> usize {
        let want = (2.0 * half).ceil() as usize;
        let cap = (full / s * s).max(s.min(full));
        want.div_ceil(s).saturating_mul(s).min(cap).max(1)
    };
    let (w, h) = (side(width), side(height));
    // A window smaller than the scale (a tiny image) is solved at full resolution.
    let s = if w < s || h < s { 1 } else { s };
    let place = |g: f32, side: usize, full: usize| -> usize {
        let x0 = (g - 0.5 * side as f32).round();
        (x0.max(0.0) as usize).min(full - side)
    };
    Ok(HybridWindow {
        x0: place(gaze[0], w, width),
        y0: place(gaze[1], h, height),
        width: w,
        height: h,
        scale: s,
        inner_px: inner,
        outer_px: outer,
    })
}

fn crop_plane(p: &Plane, x0: usize, y0: usize, w: usize, h: usize) -> Result<Plane, RenderError> {
    let mut out = Vec::with_capacity(w * h);
    for y in y0..y0 + h {
        out.extend_from_slice(&p.row(y)[x0..x0 + w]);
    }
    Ok(Plane::from_vec(w, h, out)?)
}

/// The window of `input`, at 1/s resolution.
fn window_input(input: &Rgbd, win: &HybridWindow) -> Result<Rgbd, RenderError> {
    let cut = |p: &Plane| crop_plane(p, win.x0, win.y0, win.width, win.height);
    let [r, g, b] = &input.color.channels;
    let color = RgbImage::from_planes(cut(r)?, cut(g)?, cut(b)?)?;
    let window = Rgbd::new(color, DepthMap::from_diopters(cut(input.depth.plane())?)?)?;
    if win.scale == 1 {
        Ok(window)
    } else {
        down_rgbd(&window, win.scale)
    }
}

/// Whether a blurred depth step reaches within `radius` pixels of `gaze` at any of `foci`
/// (the scan run on the window only).
fn step_in_fovea(
    input: &Rgbd,
    win: &HybridWindow,
    eye: &EyeModel,
    foci: &[Diopters],
    gaze: [f32; 2],
    radius: f32,
) -> Result<bool, RenderError> {
    let depth = DepthMap::from_diopters(crop_plane(
        input.depth.plane(),
        win.x0,
        win.y0,
        win.width,
        win.height,
    )?)?;
    let weye = eye_with_pitch(eye, eye.pixel_pitch_tan(), win.width)?;
    let (gx, gy) = (gaze[0] - win.x0 as f32, gaze[1] - win.y0 as f32);
    let r2 = radius * radius;
    for &q in foci {
        let reach = step_reach(&depth, q, &weye, 0.0)?;
        let hit = reach.reached.iter().enumerate().any(|(i, &r)| {
            let dx = (i % win.width) as f32 + 0.5 - gx;
            let dy = (i / win.width) as f32 + 0.5 - gy;
            r && dx * dx + dy * dy <= r2
        });
        if hit {
            return Ok(true);
        }
    }
    Ok(false)
}

/// The hybrid decomposition of `input` onto `planes` with the gaze at `gaze` (pixels; `None`:
/// the image centre). `spectral` solves the window (an RGB-D, its eye): the CPU's
/// [`crate::spectral::spectral_blend`], or a backend's.
pub fn hybrid_blend_with(
    input: &Rgbd,
    planes: &[Diopters],
    eye: &EyeModel,
    gaze: Option<[f32; 2]>,
    params: &HybridParams,
    spectral: impl FnOnce(
        &Rgbd,
        &EyeModel,
        SpectralParams,
    ) -> Result<(Layers, SpectralReport), RenderError>,
) -> Result<(Layers, HybridReport), RenderError> {
    check_rgbd(input)?;
    check_planes(planes)?;
    params.check()?;
    let (w, h) = (input.width(), input.height());
    let gaze = gaze.unwrap_or([0.5 * w as f32, 0.5 * h as f32]);
    if !(gaze[0].is_finite() && gaze[1].is_finite()) {
        return Err(invalid(format!(
            "gaze point ({}, {}) px is not finite",
            gaze[0], gaze[1]
        )));
    }
    let eye = eye_for(eye, w)?;
    let ms = |t: std::time::Instant| t.elapsed().as_secs_f64() * 1e3;
    let mut stages = HybridStages::default();
    let t = std::time::Instant::now();
    let mut layers = linear_blend(input, planes)?;
    stages.linear = ms(t);
    let win = window_for(w, h, &eye, planes, gaze, params)?;
    let mut report = HybridReport {
        gaze,
        window: None,
        spectral: None,
        stages_ms: stages,
    };
    if params.edges_only {
        let t = std::time::Instant::now();
        let step = step_in_fovea(
            input,
            &win,
            &eye,
            &params.spectral.foci(),
            gaze,
            win.inner_px,
        )?;
        report.stages_ms.scan = ms(t);
        if !step {
            return Ok((layers, report));
        }
    }
    let t = std::time::Instant::now();
    let s = win.scale;
    let small = window_input(input, &win)?;
    let seye = eye_with_pitch(&eye, eye.pixel_pitch_tan() * s as f32, small.width())?;
    // The window is solved on its own grid (the hybrid's `scale`), not coarsened again.
    let (solved, rep) = spectral(
        &small,
        &seye,
        SpectralParams {
            scale: 1,
            ..params.spectral
        },
    )?;
    report.stages_ms.solve = ms(t);
    let t = std::time::Instant::now();
    if solved.images.len() != planes.len()
        || solved.width() != small.width()
        || solved.height() != small.height()
    {
        return Err(crate::error::mismatch(
            "the window's spectral layers do not match its planes and size",
        ));
    }
    // Per plane and channel: the window's layer (the solve's, upsampled, plus linear
    // blending's detail above its grid), faded into linear blending by distance to the gaze.
    let (gx, gy) = (gaze[0], gaze[1]);
    let (inner, outer) = (win.inner_px, win.outer_px);
    let weight = |x: usize, y: usize| -> f32 {
        let dx = x as f32 + 0.5 - gx;
        let dy = y as f32 + 0.5 - gy;
        let r = (dx * dx + dy * dy).sqrt();
        if outer <= inner {
            return if r <= inner { 1.0 } else { 0.0 };
        }
        let t = ((outer - r) / (outer - inner)).clamp(0.0, 1.0);
        t * t * (3.0 - 2.0 * t)
    };
    // The fade once for every plane and channel, with each row's columns of non-zero weight.
    let fade: Vec<f32> = (0..win.width * win.height)
        .into_par_iter()
        .map(|i| weight(win.x0 + i % win.width, win.y0 + i / win.width))
        .collect();
    let spans: Vec<(usize, usize)> = fade
        .chunks(win.width)
        .map(|row| {
            let a = row.iter().position(|&k| k > 0.0).unwrap_or(0);
            let b = row.len() - row.iter().rev().position(|&k| k > 0.0).unwrap_or(row.len());
            (a, b.max(a))
        })
        .collect();
    // Bilinear upsampling's taps per window column and row.
    let (tx, ty) = (
        up_taps(win.width, win.width / s, s),
        up_taps(win.height, win.height / s, s),
    );
    let jobs: Vec<(&mut Plane, &Plane)> = layers
        .images
        .iter_mut()
        .zip(&solved.images)
        .flat_map(|(l, y)| l.channels.iter_mut().zip(y.channels.iter()))
        .collect();
    jobs.into_par_iter()
        .try_for_each(|(lin, sol)| -> Result<(), RenderError> {
            // With s > 1: up(sol) + (lin - up(down(lin))) as one upsampling (bilinear is
            // linear): the solve's change to the coarse linear layer, upsampled, added to the
            // fine one.
            let change = if s == 1 {
                None
            } else {
                let mut change =
                    box_down(&crop_plane(lin, win.x0, win.y0, win.width, win.height)?, s)?;
                for (c, &y) in change.data_mut().iter_mut().zip(sol.data()) {
                    *c = y - *c;
                }
                Some(change)
            };
            let lw = lin.width();
            let data = lin.data_mut();
            for (y, &(xa, xb)) in spans.iter().enumerate() {
                let row = &mut data[(win.y0 + y) * lw + win.x0..][..win.width];
                let k_row = &fade[y * win.width..(y + 1) * win.width];
                match &change {
                    None => {
                        let src = sol.row(y);
                        for x in xa..xb {
                            let k = k_row[x];
                            if k > 0.0 {
                                row[x] += k * (src[x] - row[x]);
                            }
                        }
                    }
                    Some(change) => {
                        let (i0, i1, t) = ty[y];
                        let (r0, r1) = (change.row(i0), change.row(i1));
                        for x in xa..xb {
                            let k = k_row[x];
                            if k > 0.0 {
                                let (a, b, u) = tx[x];
                                let top = r0[a] + (r0[b] - r0[a]) * u;
                                let bot = r1[a] + (r1[b] - r1[a]) * u;
                                let v = (top + (bot - top) * t + row[x]).clamp(0.0, 1.0);
                                row[x] += k * (v - row[x]);
                            }
                        }
                    }
                }
            }
            Ok(())
        })?;
    report.stages_ms.compose = ms(t);
    report.window = Some(win);
    report.spectral = Some(rep);
    Ok((layers, report))
}

/// [`hybrid_blend_with`] on the CPU (the CPU backend's [`crate::Backend::hybrid_blend`]).
pub fn hybrid_blend(
    input: &Rgbd,
    planes: &[Diopters],
    eye: &EyeModel,
    gaze: Option<[f32; 2]>,
    params: &HybridParams,
) -> Result<(Layers, HybridReport), RenderError> {
    hybrid_blend_with(input, planes, eye, gaze, params, |rgbd, e, p| {
        crate::spectral::spectral_blend(rgbd, planes, e, p)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::multifocal::{MultifocalRetina, DEFAULT_PLANES};
    use crate::spectral::tests::rgbd;
    use crate::spectral::{spectral_blend, SpectralTargets};
    use crate::DefocusMethod;

    fn planes() -> Vec<Diopters> {
        DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect()
    }

    /// 3 degrees over 96 px: blur kernels of several pixels, as at a panel's pitch.
    fn eye() -> EyeModel {
        EyeModel {
            fov_horizontal_deg: 3.0,
            ..EyeModel::default()
        }
    }

    /// Gather targets keep these tests quick; the window logic is the same for any.
    fn params(scale: usize, fovea_deg: f32) -> HybridParams {
        HybridParams {
            fovea_deg,
            blend_deg: 0.1,
            scale,
            edges_only: false,
            spectral: SpectralParams {
                targets: SpectralTargets::Defocus(DefocusMethod::Gather),
                // Full spectral, which the tests hold the hybrid to, at full resolution.
                scale: 1,
                ..SpectralParams::default()
            },
        }
    }

    #[test]
    fn the_window_holds_the_fovea_and_keeps_its_size_inside_the_image() {
        let (w, h) = (200, 150);
        let e = eye().with_width(w as u32);
        let p = params(2, 0.4);
        let px_per_deg = 1.0f32.to_radians().tan() / e.pixel_pitch_tan();
        let centre = window_for(w, h, &e, &planes(), [100.0, 75.0], &p).unwrap();
        assert_eq!(centre.scale, 2);
        assert!(centre.inner_px > 0.4 * px_per_deg, "{centre:?}");
        assert!(centre.outer_px > centre.inner_px, "{centre:?}");
        for gaze in [[0.0, 0.0], [199.0, 149.0], [-50.0, 400.0], [37.5, 120.2]] {
            let win = window_for(w, h, &e, &planes(), gaze, &p).unwrap();
            assert_eq!((win.width, win.height), (centre.width, centre.height));
            assert_eq!(win.width % 2, 0);
            assert_eq!(win.height % 2, 0);
            assert!(
                win.x0 + win.width <= w && win.y0 + win.height <= h,
                "{win:?}"
            );
        }
        // The window covers the fade's outer edge around a central gaze.
        assert!(centre.x0 as f32 <= 100.0 - centre.outer_px, "{centre:?}");
        assert!((centre.x0 + centre.width) as f32 >= 100.0 + centre.outer_px);
        // Larger than the image: the image (its sides rounded down to the scale).
        let win = window_for(31, 17, &e, &planes(), [3.0, 3.0], &params(2, 20.0)).unwrap();
        assert_eq!((win.x0, win.y0, win.width, win.height), (0, 0, 30, 16));
        // The automatic scale coarsens as the pixels get finer.
        let auto = HybridParams::default();
        assert_eq!(auto.scale_for(5.0), 1);
        assert_eq!(auto.scale_for(21.8), 2);
        assert_eq!(auto.scale_for(33.0), 4);
    }

    #[test]
    fn without_a_depth_step_in_the_fovea_it_is_linear_blending() {
        // A step far from the gaze: the default (edges only) does not optimise.
        let input = rgbd(96, 80, |x, _| if x < 6 { 2.0 } else { 0.5 });
        let p = HybridParams {
            edges_only: true,
            ..params(1, 0.3)
        };
        let (layers, rep) =
            hybrid_blend(&input, &planes(), &eye(), Some([70.0, 40.0]), &p).unwrap();
        assert_eq!(rep.window, None);
        assert_eq!(rep.spectral, None);
        assert_eq!(layers, linear_blend(&input, &planes()).unwrap());
        // Looking at it, it does.
        let (_, rep) = hybrid_blend(&input, &planes(), &eye(), Some([8.0, 40.0]), &p).unwrap();
        assert!(rep.window.is_some() && rep.spectral.is_some(), "{rep:?}");
    }

    #[test]
    fn the_fovea_sees_the_spectral_layers() {
        // Full resolution: inside the fovea (and the widest blur around it) the layers are the
        // window's spectral solution, which away from the window's edge is the whole image's;
        // what the eye sees there matches full spectral's, and far outside it is linear's.
        let (w, h) = (96, 96);
        let input = rgbd(w, h, |x, y| if (x + 2 * y) % 40 < 20 { 1.9 } else { 0.3 });
        let e = eye();
        let p = params(1, 0.5);
        let (hyb, rep) = hybrid_blend(&input, &planes(), &e, None, &p).unwrap();
        let win = rep.window.unwrap();
        let (full, _) = spectral_blend(&input, &planes(), &e, p.spectral).unwrap();
        let lin = linear_blend(&input, &planes()).unwrap();
        let foci = p.spectral.foci();
        let (lo, hi) = (foci[0], foci[foci.len() - 1]);
        let seen = |l: &Layers| MultifocalRetina::new(l, &e, (lo, hi)).unwrap();
        let (sh, sf, sl) = (seen(&hyb), seen(&full), seen(&lin));
        let px_per_deg = 1.0f32.to_radians().tan() / e.with_width(w as u32).pixel_pitch_tan();
        let mask = crate::metrics::disk_mask(w, h, [48.0, 48.0], 0.5 * px_per_deg);
        for &q in &foci {
            let (a, b) = (sh.render(q).unwrap(), sf.render(q).unwrap());
            let near = crate::metrics::psnr(&a, &b, Some(&mask)).unwrap();
            assert!(
                near > 45.0,
                "focus {q}: hybrid {near} dB from spectral in the fovea"
            );
            let far = crate::metrics::psnr(&a, &sl.render(q).unwrap(), Some(&mask)).unwrap();
            assert!(far < near, "focus {q}: {far} dB from linear in the fovea");
        }
        // Beyond the fade the layers are linear blending's, untouched.
        for (x, y) in [(0, 0), (95, 95), (0, 95)] {
            let r = ((x as f32 + 0.5 - 48.0).powi(2) + (y as f32 + 0.5 - 48.0).powi(2)).sqrt();
            assert!(r > win.outer_px, "{win:?}");
            for (a, b) in hyb.images.iter().zip(&lin.images) {
                for ch in 0..3 {
                    assert_eq!(a.channels[ch].get(x, y), b.channels[ch].get(x, y));
                }
            }
        }
    }

    #[test]
    fn a_coarse_solve_stays_near_full_spectral_in_the_fovea() {
        // What the panel-size default does (the window solved on a 1/2 grid plus linear
        // blending's detail above it), at blur kernels of up to about 16 px, as the auto scale
        // chooses 2 for: what the eye sees in the fovea, at every focal sample, against full
        // resolution spectral's. Measured 25.8 dB at 0.1 D (the texture here is a period-13
        // pattern, finer than the coarse grid, seen sharply at the far plane) and 36.6 to 43.2
        // dB at the other five foci, mean 36.3; linear blending is 18.3 to 32.8 dB from it,
        // 7.5 dB further at the least. The bounds leave about 3 dB for rounding and solver
        // changes.
        let (w, h) = (128, 128);
        let input = rgbd(w, h, |x, y| if (x + 2 * y) % 48 < 24 { 1.9 } else { 0.3 });
        let e = EyeModel {
            fov_horizontal_deg: 2.5,
            ..EyeModel::default()
        };
        let p = params(2, 0.4);
        let (hyb, rep) = hybrid_blend(&input, &planes(), &e, None, &p).unwrap();
        assert_eq!(rep.window.unwrap().scale, 2, "{rep:?}");
        let (full, _) = spectral_blend(&input, &planes(), &e, p.spectral).unwrap();
        let lin = linear_blend(&input, &planes()).unwrap();
        let foci = p.spectral.foci();
        let (lo, hi) = (foci[0], foci[foci.len() - 1]);
        let seen = |l: &Layers| MultifocalRetina::new(l, &e, (lo, hi)).unwrap();
        let (sh, sf, sl) = (seen(&hyb), seen(&full), seen(&lin));
        let px_per_deg = 1.0f32.to_radians().tan() / e.with_width(w as u32).pixel_pitch_tan();
        let mask = crate::metrics::disk_mask(w, h, [64.0, 64.0], 0.4 * px_per_deg);
        let mut got = Vec::new();
        for &q in &foci {
            let truth = sf.render(q).unwrap();
            let near = crate::metrics::psnr(&sh.render(q).unwrap(), &truth, Some(&mask)).unwrap();
            let lin = crate::metrics::psnr(&sl.render(q).unwrap(), &truth, Some(&mask)).unwrap();
            eprintln!("focus {q}: hybrid {near:.2} dB, linear {lin:.2} dB from full spectral");
            got.push((q, near, lin));
        }
        for &(q, near, lin) in &got {
            assert!(
                near > 23.0,
                "focus {q}: hybrid {near} dB from spectral in the fovea"
            );
            assert!(
                near > lin + 5.0,
                "focus {q}: hybrid {near} dB, linear {lin} dB"
            );
        }
        let mean = got.iter().map(|g| g.1).sum::<f64>() / got.len() as f64;
        assert!(
            mean > 33.0,
            "hybrid {mean} dB from spectral in the fovea, mean over foci"
        );
    }

    #[test]
    fn a_coarse_solve_that_returns_linear_blending_gives_linear_blending() {
        // The detail band is linear blending's above the coarse grid: a solve that returns the
        // coarse input's linear blending (which is the box average of the fine one's on flat
        // depth) leaves linear blending unchanged.
        let input = rgbd(64, 48, |_, _| 1.1);
        let p = params(2, 5.0);
        let (layers, rep) =
            hybrid_blend_with(&input, &planes(), &eye(), None, &p, |small, _, _| {
                Ok((
                    linear_blend(small, &planes())?,
                    SpectralReport {
                        objective_clamped: 0.0,
                        objective_final: 0.0,
                        iterations: 0,
                        refined: false,
                    },
                ))
            })
            .unwrap();
        assert_eq!(rep.window.unwrap().scale, 2);
        let lin = linear_blend(&input, &planes()).unwrap();
        for (a, b) in layers.images.iter().zip(&lin.images) {
            for (p, q) in a.channels.iter().zip(&b.channels) {
                for (u, v) in p.data().iter().zip(q.data()) {
                    assert!((u - v).abs() < 1e-5, "{u} vs {v}");
                }
            }
        }
    }

    #[test]
    fn bad_settings_and_input_are_errors() {
        let input = rgbd(32, 32, |_, _| 1.0);
        for p in [
            HybridParams {
                fovea_deg: f32::NAN,
                ..HybridParams::default()
            },
            HybridParams {
                blend_deg: -1.0,
                ..HybridParams::default()
            },
            HybridParams {
                scale: 17,
                ..HybridParams::default()
            },
            HybridParams {
                spectral: SpectralParams {
                    prior: 0.0,
                    ..SpectralParams::default()
                },
                ..HybridParams::default()
            },
        ] {
            assert!(
                hybrid_blend(&input, &planes(), &eye(), None, &p).is_err(),
                "{p:?}"
            );
        }
        let p = HybridParams::default();
        assert!(hybrid_blend(&input, &planes(), &eye(), Some([f32::NAN, 1.0]), &p).is_err());
        assert!(hybrid_blend(&input, &[], &eye(), None, &p).is_err());
        // A solve that returns the wrong size is an error, not a panic.
        let r = hybrid_blend_with(
            &input,
            &planes(),
            &eye(),
            None,
            &params(1, 1.0),
            |_, _, _| {
                Ok((
                    linear_blend(&rgbd(8, 8, |_, _| 1.0), &planes())?,
                    SpectralReport {
                        objective_clamped: 0.0,
                        objective_final: 0.0,
                        iterations: 0,
                        refined: false,
                    },
                ))
            },
        );
        assert!(r.is_err());
    }
}
