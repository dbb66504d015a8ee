//! The planner: per frame, the cheapest method and settings predicted to meet an accuracy
//! target in the fovea ("model no more than the scene needs").
//!
//! [`FrameStats`] summarises a frame for it: depth histograms (whole frame, and the region
//! that matters: the fovea around the gaze widened by how far blur can reach into it), the
//! depth range there against the eye's depth of field at the current focus, and the largest
//! disparity across the pupil between the depths there. [`Planner::plan`] picks among no blur
//! (pass the pinhole image through), gather and the light-field method with 12 to 48 views;
//! [`Planner::plan_planes`] picks how many multifocal planes (linear blending) and where,
//! placing them at the depth histogram's mass (weighted k-means in diopters, inside the lens
//! range); [`Planner::foveation`] picks a log-polar sampling density for the periphery.
//!
//! Predictions come from a small table measured on sim test scenes (see [`calibration`]): per
//! method, a conservative fovea PSNR against the frame's blur figure, and a cost model in
//! milliseconds. The planner is pure and deterministic; it does no I/O.

use crate::defocus::{DefocusMethod, PyramidParams};
use crate::error::{invalid, RenderError};
use crate::foveated::{Foveation as Layered, FoveationPlan};
use crate::lightfield::LightFieldParams;
use crate::pyramid::EXACT_RADIUS;
use dioptra_core::{Diopters, EyeModel, Rgbd};
use std::fmt;

/// A depth histogram in diopters: `counts[i]` pixels lie in `[lo + i w, lo + (i + 1) w)`.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthHistogram {
    pub lo: f32,
    pub bin_width: f32,
    pub counts: Vec<u32>,
}

impl DepthHistogram {
    /// Bins of 0.02 D from 0 D to `max` (the last bin takes everything beyond).
    fn new(max: f32) -> DepthHistogram {
        let bin_width = 0.02;
        let n = ((max.max(bin_width) / bin_width).ceil() as usize).clamp(1, 2000) + 1;
        DepthHistogram {
            lo: 0.0,
            bin_width,
            counts: vec![0; n],
        }
    }

    fn add(&mut self, d: f32) {
        if !d.is_finite() {
            return;
        }
        let i = ((d - self.lo) / self.bin_width).floor().max(0.0) as usize;
        let last = self.counts.len() - 1;
        self.counts[i.min(last)] += 1;
    }

    /// Number of pixels counted.
    pub fn total(&self) -> u64 {
        self.counts.iter().map(|&c| u64::from(c)).sum()
    }

    /// Centre of bin `i`, diopters.
    pub fn centre(&self, i: usize) -> f32 {
        self.lo + (i as f32 + 0.5) * self.bin_width
    }

    /// (bin centre, count) of the non-empty bins.
    pub fn mass(&self) -> impl Iterator<Item = (f32, u32)> + '_ {
        self.counts
            .iter()
            .enumerate()
            .filter(|(_, &c)| c > 0)
            .map(|(i, &c)| (self.centre(i), c))
    }
}

/// What the planner knows of a frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameStats {
    pub width: usize,
    pub height: usize,
    /// Gaze point, pixels.
    pub gaze: [f32; 2],
    /// The eye's focus (the lens's power in varifocal mode).
    pub focus: Diopters,
    /// The eye model at this frame's width.
    pub eye: EyeModel,
    /// Depths of the whole frame.
    pub frame_histogram: DepthHistogram,
    /// Depths in the region that matters: the fovea's pixels, and those around it whose blur
    /// disk at `focus` reaches into it and that are not behind all of its content. The fovea
    /// is the disk of `fovea_radius_deg` around the gaze.
    pub region_histogram: DepthHistogram,
    /// Nearest-to-eye and farthest depth in that region (largest and smallest diopters).
    pub region_range: (Diopters, Diopters),
    /// Largest circle of confusion in the region at `focus`, pixels.
    pub region_coc_px: f32,
    /// Largest disparity across the pupil between depths in the region, pixels (the CoC of
    /// the region's depth span): how far apart the pupil's edge views see its surfaces move.
    pub region_disparity_px: f32,
    /// Largest circle of confusion anywhere in the frame, pixels (sets gather's reach).
    pub frame_coc_px: f32,
    /// Texture in the region: the mean over its pixels and colour channels of the squared
    /// forward differences (x and y summed) of the pinhole image. A method's error in the
    /// fovea grows with it, so the predictions are scaled by it (see [`calibration`]).
    pub region_gradient: f32,
    /// The fovea's radius, degrees.
    pub fovea_radius_deg: f32,
}

/// The fovea's radius, degrees of the eye's field: the region the accuracy target is for, and
/// the foveated render's full-resolution radius ([`crate::foveated::DEFAULT_RADIUS_DEG`]) unless
/// a rig sets its own ([`FrameStats::from_rgbd_around`]).
pub const FOVEA_RADIUS_DEG: f32 = crate::foveated::DEFAULT_RADIUS_DEG;
/// `radius_deg` of `eye`'s field in pixels at the centre of the image.
fn fovea_px(eye: &EyeModel, radius_deg: f32) -> f32 {
    radius_deg / eye.pixel_angle_rad().to_degrees()
}

/// Blur radius beyond which the widened region stops growing, pixels.
const REACH_CAP_PX: f32 = 48.0;

/// What [`FrameStats`] takes from the whole frame: it depends on the frame alone (not the
/// gaze, the focus or the fovea), so a rig computes it once per content frame and eye and
/// gives it to [`FrameStats::around`] for each render of that frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameWide {
    width: usize,
    height: usize,
    /// The largest finite depth (0 D for none): the histograms' span.
    dmax: f32,
    /// The smallest and largest depth (`None`: an empty frame).
    range: Option<(f32, f32)>,
    /// Depths of the whole frame.
    histogram: DepthHistogram,
    /// The squared forward differences of the colour summed over the frame, and how many.
    gradient: (f64, u64),
}

impl FrameWide {
    /// The whole-frame statistics of `input`.
    pub fn of(input: &Rgbd) -> FrameWide {
        let (w, h) = (input.width(), input.height());
        let depth = input.depth.data();
        let dmax = depth
            .iter()
            .copied()
            .filter(|d| d.is_finite())
            .fold(0.0f32, f32::max);
        let mut histogram = DepthHistogram::new(dmax);
        let mut gradient = (0.0f64, 0u64);
        for y in 0..h {
            for &d in &depth[y * w..(y + 1) * w] {
                histogram.add(d);
            }
            if let Some(rows) = colour_rows(input, y) {
                for x in 0..w.saturating_sub(1) {
                    gradient = (gradient.0 + colour_gradient(&rows, x), gradient.1 + 3);
                }
            }
        }
        FrameWide {
            width: w,
            height: h,
            dmax,
            range: input.depth.range().map(|(a, b)| (a.0, b.0)),
            histogram,
            gradient,
        }
    }

    /// Whether these are `input`'s statistics as far as its size tells.
    fn fits(&self, input: &Rgbd) -> bool {
        (self.width, self.height) == (input.width(), input.height())
    }
}

/// Row `y` and the next of each colour channel of `input` (`None` on the last row).
type ColourRows<'a> = [(&'a [f32], &'a [f32]); 3];

fn colour_rows(input: &Rgbd, y: usize) -> Option<ColourRows<'_>> {
    let c = &input.color.channels;
    (y + 1 < input.height()).then(|| [0, 1, 2].map(|k| (c[k].row(y), c[k].row(y + 1))))
}

/// The squared forward differences (x and y) of the colour at column `x` of `rows`, summed
/// over the channels: the pixel must have a right neighbour.
fn colour_gradient(rows: &ColourRows<'_>, x: usize) -> f64 {
    rows.iter()
        .map(|(row, below)| {
            let v = row[x];
            let (gx, gy) = (row[x + 1] - v, below[x] - v);
            f64::from(gx * gx + gy * gy)
        })
        .sum::<f64>()
}

impl FrameStats {
    /// The statistics of `input` for a viewer looking at `gaze` (pixels) focused at `focus`,
    /// the fovea [`FOVEA_RADIUS_DEG`] around the gaze.
    pub fn from_rgbd(input: &Rgbd, gaze: [f32; 2], focus: Diopters, eye: &EyeModel) -> FrameStats {
        Self::from_rgbd_around(input, gaze, FOVEA_RADIUS_DEG, focus, eye)
    }

    /// [`FrameStats::from_rgbd`] with a fovea of `fovea_radius_deg` around the gaze (a rig's
    /// foveation radius).
    pub fn from_rgbd_around(
        input: &Rgbd,
        gaze: [f32; 2],
        fovea_radius_deg: f32,
        focus: Diopters,
        eye: &EyeModel,
    ) -> FrameStats {
        Self::around(
            &FrameWide::of(input),
            input,
            gaze,
            fovea_radius_deg,
            focus,
            eye,
        )
    }

    /// [`FrameStats::from_rgbd_around`] from `input`'s whole-frame statistics `wide` (kept
    /// from an earlier call on the same frame; recomputed if they are not of its size): only
    /// the pixels near the gaze are read.
    pub fn around(
        wide: &FrameWide,
        input: &Rgbd,
        gaze: [f32; 2],
        fovea_radius_deg: f32,
        focus: Diopters,
        eye: &EyeModel,
    ) -> FrameStats {
        let fresh;
        let wide = if wide.fits(input) {
            wide
        } else {
            fresh = FrameWide::of(input);
            &fresh
        };
        let (w, h) = (input.width(), input.height());
        let eye = eye.with_width(w.min(u32::MAX as usize) as u32);
        let depth = input.depth.data();
        let (lo, hi) = wide.range.unwrap_or((focus.0, focus.0));
        let frame_coc_px = eye
            .coc_px(Diopters(lo), focus)
            .max(eye.coc_px(Diopters(hi), focus));
        let fovea = fovea_px(&eye, fovea_radius_deg);
        let mut region_histogram = DepthHistogram::new(wide.dmax);
        let dist2 = |x: usize, y: usize| {
            let dx = x as f32 + 0.5 - gaze[0];
            let dy = y as f32 + 0.5 - gaze[1];
            dx * dx + dy * dy
        };
        // The rows or columns within `radius` of the gaze's `c` (of `n`), a pixel to spare: a
        // pixel beyond them is farther from the gaze than `radius` (none for a gaze not finite).
        let near = |c: f32, n: usize, radius: f32| -> std::ops::Range<usize> {
            let lo = (c - radius - 1.0).floor().max(0.0) as usize;
            let hi = ((c + radius + 1.0).ceil().max(0.0) as usize).min(n);
            lo.min(hi)..hi
        };
        // The farthest depth inside the fovea: content beyond it outside the fovea is hidden
        // behind the fovea's content and cannot blur into it.
        let mut farthest_in_fovea = f32::INFINITY;
        for y in near(gaze[1], h, fovea) {
            for x in near(gaze[0], w, fovea) {
                let d = depth[y * w + x];
                if d.is_finite() && dist2(x, y) <= fovea * fovea {
                    farthest_in_fovea = farthest_in_fovea.min(d);
                }
            }
        }
        // A pixel joins the region within its blur's reach of the fovea, at most
        // REACH_CAP_PX beyond it: only these rows and columns are read.
        let (mut rlo, mut rhi) = (f32::INFINITY, f32::NEG_INFINITY);
        let mut region_g = (0.0f64, 0u64);
        for y in near(gaze[1], h, fovea + REACH_CAP_PX) {
            let rows = colour_rows(input, y);
            for x in near(gaze[0], w, fovea + REACH_CAP_PX) {
                let d = depth[y * w + x];
                if !d.is_finite() {
                    continue;
                }
                // Outside the fovea, a pixel matters when its blur disk reaches into the
                // fovea and it is not behind everything there.
                let r2 = dist2(x, y);
                let within_reach = || {
                    let reach = fovea + (0.5 * eye.coc_px(Diopters(d), focus)).min(REACH_CAP_PX);
                    r2 <= reach * reach
                };
                if r2 <= fovea * fovea || (d >= farthest_in_fovea && within_reach()) {
                    region_histogram.add(d);
                    if let (Some(rows), true) = (&rows, x + 1 < w) {
                        region_g = (region_g.0 + colour_gradient(rows, x), region_g.1 + 3);
                    }
                    rlo = rlo.min(d);
                    rhi = rhi.max(d);
                }
            }
        }
        if rlo > rhi {
            // A gaze off the image: the region is empty; judge by the whole frame.
            (rlo, rhi) = (lo, hi);
            region_histogram = wide.histogram.clone();
            region_g = wide.gradient;
        }
        if region_g.1 == 0 {
            // A region of one row or column: the frame's texture stands in.
            region_g = wide.gradient;
        }
        let region_gradient = (region_g.0 / region_g.1.max(1) as f64) as f32;
        let region_coc_px = eye
            .coc_px(Diopters(rlo), focus)
            .max(eye.coc_px(Diopters(rhi), focus));
        let region_disparity_px = eye.coc_px(Diopters(rhi), Diopters(rlo));
        FrameStats {
            width: w,
            height: h,
            gaze,
            focus,
            eye,
            frame_histogram: wide.histogram.clone(),
            region_histogram,
            region_range: (Diopters(rhi), Diopters(rlo)),
            region_coc_px,
            region_disparity_px,
            frame_coc_px,
            // Non-finite colour: beyond any real image's texture, so no method is trusted.
            region_gradient: if region_gradient.is_finite() {
                region_gradient
            } else {
                100.0
            },
            fovea_radius_deg,
        }
    }

    /// Megapixels in the frame.
    fn megapixels(&self) -> f64 {
        (self.width * self.height) as f64 / 1e6
    }

    /// A frame the planner has not seen: `width` x `height` seen by `eye`, its depths spread
    /// evenly over `depths` (nearest, farthest), the gaze at the centre, the viewer focused at
    /// `focus`, the texture at the calibration's reference. For predictions before content
    /// arrives ([`predict_frame_cost`]).
    pub fn typical(
        width: usize,
        height: usize,
        eye: &EyeModel,
        depths: (Diopters, Diopters),
        focus: Diopters,
    ) -> FrameStats {
        let eye = eye.with_width(width.min(u32::MAX as usize) as u32);
        let (near, far) = (depths.0 .0.max(depths.1 .0), depths.0 .0.min(depths.1 .0));
        let (near, far) = (near.max(0.0), far.max(0.0));
        let mut hist = DepthHistogram::new(near);
        let (lo, hi) = (
            ((far / hist.bin_width) as usize).min(hist.counts.len() - 1),
            ((near / hist.bin_width) as usize).min(hist.counts.len() - 1),
        );
        let per_bin = ((width * height) / (hi - lo + 1)).clamp(1, u32::MAX as usize) as u32;
        for c in &mut hist.counts[lo..=hi] {
            *c = per_bin;
        }
        let coc = eye
            .coc_px(Diopters(near), focus)
            .max(eye.coc_px(Diopters(far), focus));
        FrameStats {
            width,
            height,
            gaze: [0.5 * width as f32, 0.5 * height as f32],
            focus,
            eye,
            frame_histogram: hist.clone(),
            region_histogram: hist,
            region_range: (Diopters(near), Diopters(far)),
            region_coc_px: coc,
            region_disparity_px: eye.coc_px(Diopters(near), Diopters(far)),
            frame_coc_px: coc,
            region_gradient: calibration::GRADIENT_REFERENCE,
            fovea_radius_deg: FOVEA_RADIUS_DEG,
        }
    }

    /// The same frame `2^level` times coarser (a foveated layer): its size and eye scaled,
    /// its depths, gaze and focus kept.
    pub fn scaled(&self, level: usize) -> FrameStats {
        let s = 1usize << level.min(16);
        let width = self.width.div_ceil(s);
        FrameStats {
            width,
            height: self.height.div_ceil(s),
            gaze: self.gaze.map(|g| g / s as f32),
            eye: self.eye.with_width(width.min(u32::MAX as usize) as u32),
            frame_coc_px: self.frame_coc_px / s as f32,
            region_coc_px: self.region_coc_px / s as f32,
            region_disparity_px: self.region_disparity_px / s as f32,
            ..self.clone()
        }
    }
}

/// What the pyramid method's cost depends on, from a frame's depth histogram: the exact pass's
/// mean taps per pixel (`pi (r + 0.5)^2` for a blur radius `r` from half a pixel to
/// [`EXACT_RADIUS`], none below, none above where only edges need it) and the fraction of
/// pixels spread on the pyramid's levels (radius [`EXACT_RADIUS`] or more).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PyramidFeatures {
    pub taps: f64,
    pub spread: f64,
}

/// [`PyramidFeatures`] of `stats`'s whole frame at its focus.
pub fn pyramid_features(stats: &FrameStats) -> PyramidFeatures {
    let per_d = 0.5 * stats.eye.coc_px(Diopters(1.0), Diopters(0.0));
    let h = &stats.frame_histogram;
    let total = h.total().max(1) as f64;
    let (mut taps, mut spread) = (0.0f64, 0.0f64);
    for (d, n) in h.mass() {
        let r = per_d * (d - stats.focus.0).abs();
        if r >= EXACT_RADIUS {
            spread += f64::from(n);
        } else if r >= 0.5 {
            taps += f64::from(n) * std::f64::consts::PI * f64::from(r + 0.5).powi(2);
        }
    }
    PyramidFeatures {
        taps: taps / total,
        spread: spread / total,
    }
}

/// What the plan must achieve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Target {
    /// PSNR in the fovea against the thin-lens ground truth, dB.
    pub fovea_psnr_db: f64,
    /// PSNR the foveated periphery may drop to (periphery 1 ring), dB; `None`: no foveation.
    pub periphery_psnr_db: Option<f64>,
}

/// The default fovea target, dB. The issue's example is 38 dB; on the calibration scenes at
/// 160 px no CPU method's 10th-percentile fovea PSNR reaches it (the light field's is 35.0), so
/// a 38 dB target would always fall back to the most accurate method. 35 dB is what the best
/// methods reach there.
pub const DEFAULT_FOVEA_PSNR_DB: f64 = 35.0;

impl Default for Target {
    fn default() -> Self {
        Target {
            fovea_psnr_db: DEFAULT_FOVEA_PSNR_DB,
            periphery_psnr_db: None,
        }
    }
}

/// A defocus method with its settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Choice {
    /// No blur: the pinhole image passes through (everything that matters is in focus).
    None,
    Gather,
    LightField {
        views: usize,
    },
}

impl Choice {
    /// Every choice the planner considers, cheapest kind first.
    pub fn all() -> Vec<Choice> {
        let mut v = vec![Choice::None, Choice::Gather];
        v.extend(LF_VIEWS.iter().map(|&views| Choice::LightField { views }));
        v
    }
    /// The most expensive setting (the "always use the best" baseline).
    pub const MOST_EXPENSIVE: Choice = Choice::LightField { views: 48 };
}

impl fmt::Display for Choice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Choice::None => write!(f, "none"),
            Choice::Gather => write!(f, "gather"),
            Choice::LightField { views } => write!(f, "lightfield-{views}"),
        }
    }
}

/// The planner's answer for a frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    pub choice: Choice,
    /// Predicted PSNR in the fovea, dB (conservative: the 10th percentile measured).
    pub predicted_psnr: f64,
    /// Predicted CPU time of the render, ms.
    pub predicted_cost_ms: f64,
    /// Whether the prediction meets the target (false: the best available was chosen).
    pub meets_target: bool,
    /// One line on why, for logs and status.
    pub why: String,
}

/// The planner's answer for a multifocal frame: linear blending into these planes.
#[derive(Debug, Clone, PartialEq)]
pub struct PlanePlan {
    pub planes: Vec<Diopters>,
    pub predicted_psnr: f64,
    pub predicted_cost_ms: f64,
    pub meets_target: bool,
    pub why: String,
}

/// A log-polar sampling density for the periphery ([`crate::foveate::LogPolar::scale`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Foveation {
    /// Log-buffer scale S (larger: sparser periphery).
    pub scale: f32,
    pub predicted_periphery_psnr: f64,
    pub why: String,
}

/// Calibration: measured tables and cost coefficients.
///
/// Measured by `cargo run --release -p dioptra-render --example planner_calibration -- 160 64
/// 512` (73 s on the 2-core development host, otherwise idle): sim test scenes 1 000 100 to
/// 1 000 163 at 160 x 160 px (every other one with 6 objects instead of 24, and each seed's
/// wall alone), gaze at the centre, foci 0.1, 0.5, 1, 2, 3.5 D, the gazed depth and 0.15 D
/// beyond it (the wall: 0 to 0.7 D from it); PSNR in the fovea against a 512-ray thin-lens
/// reference of the fovea. That fovea was the metrics' (diameter 0.1 of the image diagonal:
/// 1.4 degrees at 160 px over 20); the planner's region is now [`FOVEA_RADIUS_DEG`] around the
/// gaze, which holds it, so a frame's blur figure is at least the one the tables were indexed
/// by and the prediction errs low (the held-out check in tests/planner.rs still measures in the
/// metrics' fovea).
///
/// The PSNR tables are for a region of texture [`GRADIENT_REFERENCE`]: each measurement is
/// first normalised by adding [`texture_db`] of its frame's region gradient (a method's error
/// grows with the texture it has to blur; this halved the spread within a bin, from about 9
/// to 6 dB sd). Each entry is the 20th percentile of the normalised PSNRs with the blur
/// figure in that bin; a bin with fewer than 8 measurements takes the next measured bin's
/// value (larger blur), beyond the last one less 3 dB per bin; then the table is made
/// non-increasing. A prediction is the entry less [`texture_db`] of the frame's gradient.
/// Split by scene (fit on half the scenes, checked on the other half), this rule promised
/// 35 dB on 568 of 704 frames and kept the promise on 538 (95 %); the 10th percentile
/// promised it on 350 (kept 97 %), so more frames fell back to the costliest method.
/// Held-out scenes check it in tests/planner.rs.
pub mod calibration {
    /// The region gradient ([`super::FrameStats::region_gradient`]) the tables are for.
    pub const GRADIENT_REFERENCE: f32 = 0.01;
    /// Gradients below this count as this (a flat region gains at most 20 dB).
    pub const GRADIENT_FLOOR: f32 = 1e-4;

    /// How far a region's texture lowers the PSNR from the tables', dB: a method's squared
    /// error in the fovea grows in proportion to the region's squared gradient.
    pub fn texture_db(region_gradient: f32) -> f64 {
        10.0 * f64::from(region_gradient.max(GRADIENT_FLOOR) / GRADIENT_REFERENCE).log10()
    }

    /// A region CoC under this is in focus: nothing a pixel shows is blurred.
    pub const IN_FOCUS_COC_PX: f32 = 0.1;
    /// No blur with the region in focus, whatever its texture: the pass-through differs from
    /// the reference only by their sampling (20th percentile of the raw PSNRs of 22 frames,
    /// region gradients up to 0.086).
    pub const PSNR_NONE_IN_FOCUS: f64 = 42.6;

    /// Upper edges of the blur-figure bins, pixels.
    pub const BIN_EDGES_PX: [f32; 12] = [
        0.5,
        1.0,
        1.5,
        2.0,
        3.0,
        4.0,
        5.0,
        6.0,
        8.0,
        12.0,
        16.0,
        f32::INFINITY,
    ];
    /// No blur, by the region's largest CoC. Samples per bin: 173, 129, 31, 19, 80, 50, 62,
    /// 121, 39.
    pub const PSNR_NONE: [f64; 12] = [
        45.9, 39.3, 37.8, 34.6, 30.9, 29.9, 27.9, 26.6, 25.0, 22.0, 19.0, 16.0,
    ];
    /// Gather, by the region's largest disparity across the pupil. Samples per bin: 331, 30,
    /// 21, 29, 49, 29, 74, 105, 36 (the same for the light field).
    pub const PSNR_GATHER: [f64; 12] = [
        43.0, 43.0, 36.2, 36.2, 36.2, 33.4, 33.4, 31.1, 31.1, 31.1, 29.3, 26.3,
    ];
    /// The light-field method with 12, 24, 36 and 48 views, by the same figure.
    pub const PSNR_LIGHTFIELD: [[f64; 12]; 4] = [
        [
            42.6, 38.9, 36.2, 36.2, 36.2, 36.2, 36.2, 36.2, 36.2, 34.5, 31.5, 28.5,
        ],
        [
            43.6, 42.2, 36.2, 36.2, 36.2, 36.2, 36.2, 36.2, 36.2, 35.3, 32.3, 29.3,
        ],
        [
            44.0, 44.0, 36.2, 36.2, 36.2, 36.2, 36.2, 36.2, 36.2, 35.6, 32.6, 29.6,
        ],
        [
            43.8, 43.8, 36.2, 36.2, 36.2, 36.2, 36.2, 36.2, 36.2, 35.5, 32.5, 29.5,
        ],
    ];
    /// Linear multifocal blending, by the region's largest distance to the nearest plane
    /// expressed as a CoC in pixels (the eye focused on the gazed depth): raw PSNRs, not
    /// texture-normalised. This figure explains little of linear blending's error (its median
    /// moves only 31-40 dB across the bins, its blends at depth edges dominate), and scaling by
    /// texture shifts every plane count of a frame alike, so it would not change which count
    /// wins. Samples per bin: 124, 55, 32, 24, 43, 34, 6, 2.
    pub const PSNR_LINEAR: [f64; 12] = [
        28.1, 27.8, 27.8, 27.8, 27.7, 27.7, 25.5, 22.5, 19.5, 16.5, 13.5, 10.5,
    ];
    /// Foveated interpolation: periphery 1 PSNR (10th percentile) by log-polar scale S.
    pub const PERIPHERY_BY_SCALE: [(f32, f64); 4] =
        [(1.5, 24.5), (2.0, 22.8), (3.0, 21.2), (4.0, 20.4)];

    /// Cost per megapixel, ms: gather = a + b r^2 (r = frame's largest blur radius, px).
    pub const GATHER_MS_PER_MP: (f64, f64) = (34.0, 3.816);
    /// Light field = a + b views.
    pub const LIGHTFIELD_MS_PER_MP: (f64, f64) = (103.7, 3.80);
    /// Pass-through (a copy).
    pub const NONE_MS_PER_MP: f64 = 1.27;
    /// Linear blending, per plane.
    pub const LINEAR_MS_PER_MP_PER_PLANE: f64 = 6.89;

    /// The pyramid method's CPU time per megapixel, `a + b taps + c spread`
    /// ([`super::PyramidFeatures`]), CPU milliseconds (all threads' time together, so a
    /// frame's wall time is this over the cores). Least-squares fit over 48 frames (3 sim test
    /// scenes x 4 foci at 480 x 540 and 960 x 1080 over 20 and 60 degrees; predicted over
    /// measured 0.79 to 1.55) by `cargo run --release -p dioptra-render --example
    /// pyramid_cost` on the 2-core development host at load average 9 to 11: the process's
    /// user time, which other work inflates less than wall time, but still some.
    pub const PYRAMID_CPU_MS_PER_MP: (f64, f64, f64) = (56.39, 1.3795, 142.13);
    /// The foveated variant's downsampling, per-layer setup and blend, CPU ms per megapixel
    /// of the image: the median over the same frames (range 20 to 126) after the row-wise
    /// blend (commit d3e18eb), from a run at load average 19 to 20, where the same run's
    /// pyramid fit came out about 20 % above the one above (71.38, 1.2510, 175.35): an upper
    /// estimate. Before the row-wise blend: 65.36 at load 9 to 11.
    pub const FOVEATED_BLEND_CPU_MS_PER_MP: f64 = 56.94;
    /// The pyramid method's largest loss against gather on one frame of the test scenes at a
    /// panel's pixel density (0.27 dB, tests/accuracy.rs): taken off gather's prediction.
    pub const PYRAMID_MARGIN_DB: f64 = 0.3;
    /// The development host the classical methods' costs were measured on had 2 cores: their
    /// wall times are CPU time spread over that many.
    pub const CALIBRATION_CORES: f64 = 2.0;
}

/// Light-field view counts considered.
pub const LF_VIEWS: [usize; 4] = [12, 24, 36, 48];

fn bin(px: f32) -> usize {
    calibration::BIN_EDGES_PX
        .iter()
        .position(|&e| px < e)
        .unwrap_or(calibration::BIN_EDGES_PX.len() - 1)
}

/// The planner (stateless; a struct so callers can hold one and its limits can grow).
#[derive(Debug, Clone, Copy, Default)]
pub struct Planner;

impl Planner {
    /// Predicted fovea PSNR of `choice` for `stats`.
    pub fn predict_psnr(&self, stats: &FrameStats, choice: Choice) -> f64 {
        use calibration::*;
        let at_reference = match choice {
            // In focus, the pass-through is the reference up to sampling, whatever the texture.
            Choice::None if stats.region_coc_px < IN_FOCUS_COC_PX => return PSNR_NONE_IN_FOCUS,
            Choice::None => PSNR_NONE[bin(stats.region_coc_px)],
            Choice::Gather => PSNR_GATHER[bin(stats.region_disparity_px)],
            Choice::LightField { views } => {
                let k = LF_VIEWS
                    .iter()
                    .position(|&v| v >= views)
                    .unwrap_or(LF_VIEWS.len() - 1);
                PSNR_LIGHTFIELD[k][bin(stats.region_disparity_px)]
            }
        };
        at_reference - texture_db(stats.region_gradient)
    }

    /// Predicted CPU cost of `choice` for `stats`, ms.
    pub fn predict_cost_ms(&self, stats: &FrameStats, choice: Choice) -> f64 {
        use calibration::*;
        let mp = stats.megapixels();
        match choice {
            Choice::None => NONE_MS_PER_MP * mp,
            Choice::Gather => {
                let r = f64::from((0.5 * stats.frame_coc_px).min(256.0));
                (GATHER_MS_PER_MP.0 + GATHER_MS_PER_MP.1 * r * r) * mp
            }
            Choice::LightField { views } => {
                (LIGHTFIELD_MS_PER_MP.0 + LIGHTFIELD_MS_PER_MP.1 * views as f64) * mp
            }
        }
    }

    /// The cheapest choice predicted to meet `target`; the costliest one if none is.
    pub fn plan(&self, stats: &FrameStats, target: &Target) -> Plan {
        let mut scored: Vec<(Choice, f64, f64)> = Choice::all()
            .into_iter()
            .map(|c| {
                (
                    c,
                    self.predict_psnr(stats, c),
                    self.predict_cost_ms(stats, c),
                )
            })
            .collect();
        scored.sort_by(|a, b| a.2.total_cmp(&b.2));
        let ok = scored.iter().find(|s| s.1 >= target.fovea_psnr_db).copied();
        let dof = stats.eye.dof_half_width(1.0).0;
        let context = format!(
            "fovea depths {:.2}-{:.2} D, focus {:.2} D (DoF +-{:.2} D at 1 px), CoC {:.1} px, disparity {:.1} px",
            stats.region_range.1 .0,
            stats.region_range.0 .0,
            stats.focus.0,
            dof,
            stats.region_coc_px,
            stats.region_disparity_px
        );
        match ok {
            Some((choice, psnr, cost)) => {
                let reason = match choice {
                    Choice::None => "everything there is inside the depth of field",
                    Choice::Gather => "gather suffices for this disparity range",
                    Choice::LightField { .. } => "fewest light-field views for this disparity",
                };
                Plan {
                    choice,
                    predicted_psnr: psnr,
                    predicted_cost_ms: cost,
                    meets_target: true,
                    why: format!(
                        "{choice}: {reason} ({context}; predicted {psnr:.1} dB >= {:.1})",
                        target.fovea_psnr_db
                    ),
                }
            }
            None => {
                // Nothing is predicted to meet the target: the costliest setting, which is the
                // most accurate on average (the tables' percentiles cannot rank methods whose
                // spreads overlap).
                let choice = Choice::MOST_EXPENSIVE;
                let (psnr, cost) = (
                    self.predict_psnr(stats, choice),
                    self.predict_cost_ms(stats, choice),
                );
                Plan {
                    choice,
                    predicted_psnr: psnr,
                    predicted_cost_ms: cost,
                    meets_target: false,
                    why: format!(
                        "{choice}: no method is predicted to reach {:.1} dB ({context}); the costliest predicts {psnr:.1}",
                        target.fovea_psnr_db
                    ),
                }
            }
        }
    }

    /// Predicted fovea PSNR of linear blending into `planes` with the eye focused on the
    /// fovea's content.
    pub fn predict_planes_psnr(&self, stats: &FrameStats, planes: &[Diopters]) -> f64 {
        let worst = stats
            .region_histogram
            .mass()
            .map(|(d, _)| {
                planes
                    .iter()
                    .map(|p| (p.0 - d).abs())
                    .fold(f32::INFINITY, f32::min)
            })
            .fold(0.0f32, f32::max);
        let px = stats.eye.coc_px(Diopters(worst), Diopters(0.0));
        calibration::PSNR_LINEAR[bin(px)]
    }

    /// The fewest multifocal planes (1 to `max_planes`, within `lens_range`) predicted to meet
    /// `target`, placed at the depth histogram's mass.
    pub fn plan_planes(
        &self,
        stats: &FrameStats,
        target: &Target,
        lens_range: (Diopters, Diopters),
        max_planes: usize,
    ) -> PlanePlan {
        let max_planes = max_planes.max(1);
        let mut best: Option<PlanePlan> = None;
        for k in 1..=max_planes {
            let planes = place_planes(stats, k, lens_range);
            let psnr = self.predict_planes_psnr(stats, &planes);
            let cost =
                calibration::LINEAR_MS_PER_MP_PER_PLANE * planes.len() as f64 * stats.megapixels();
            let meets = psnr >= target.fovea_psnr_db;
            let list = planes
                .iter()
                .map(|p| format!("{:.2}", p.0))
                .collect::<Vec<_>>()
                .join(", ");
            let plan = PlanePlan {
                why: format!(
                    "{} plane(s) at {list} D placed at the depth histogram's mass (content {:.2}-{:.2} D in the fovea); predicted {psnr:.1} dB {} {:.1}",
                    planes.len(),
                    stats.region_range.1 .0,
                    stats.region_range.0 .0,
                    if meets { ">=" } else { "<" },
                    target.fovea_psnr_db
                ),
                planes,
                predicted_psnr: psnr,
                predicted_cost_ms: cost,
                meets_target: meets,
            };
            if meets {
                return plan;
            }
            if best
                .as_ref()
                .is_none_or(|b| plan.predicted_psnr > b.predicted_psnr)
            {
                best = Some(plan);
            }
        }
        best.unwrap_or_else(|| PlanePlan {
            planes: vec![lens_range.0],
            predicted_psnr: 0.0,
            predicted_cost_ms: 0.0,
            meets_target: false,
            why: "no plane could be placed".into(),
        })
    }

    /// The sparsest log-polar sampling of the periphery predicted to keep periphery 1 at
    /// `target.periphery_psnr_db`; `None` when the target asks for no foveation.
    pub fn foveation(&self, target: &Target) -> Option<Foveation> {
        let want = target.periphery_psnr_db?;
        let pick = calibration::PERIPHERY_BY_SCALE
            .iter()
            .rev()
            .find(|(_, p)| *p >= want)
            .copied();
        Some(match pick {
            Some((scale, p)) => Foveation {
                scale,
                predicted_periphery_psnr: p,
                why: format!("log-polar scale {scale}: sparsest predicted to keep periphery 1 at {p:.1} >= {want:.1} dB"),
            },
            None => {
                let (scale, p) = calibration::PERIPHERY_BY_SCALE[0];
                Foveation {
                    scale,
                    predicted_periphery_psnr: p,
                    why: format!("log-polar scale {scale}: densest measured ({p:.1} dB) misses {want:.1} dB"),
                }
            }
        })
    }
}

/// `k` planes at the depth histogram's mass: weighted k-means (Lloyd) in diopters over the
/// frame's histogram plus the fovea region's (weighted to carry as much mass as the whole
/// frame), initialised at the mass quantiles, clamped to `lens_range` and kept at least
/// 0.05 D apart (strictly increasing, as the blending needs).
pub fn place_planes(
    stats: &FrameStats,
    k: usize,
    lens_range: (Diopters, Diopters),
) -> Vec<Diopters> {
    let (lo, hi) = (
        lens_range.0 .0.min(lens_range.1 .0),
        lens_range.0 .0.max(lens_range.1 .0),
    );
    let ft = stats.frame_histogram.total().max(1) as f64;
    let rt = stats.region_histogram.total().max(1) as f64;
    let mut pts: Vec<(f32, f64)> = stats
        .frame_histogram
        .mass()
        .map(|(d, c)| (d, f64::from(c) / ft))
        .chain(
            stats
                .region_histogram
                .mass()
                .map(|(d, c)| (d, f64::from(c) / rt)),
        )
        .map(|(d, w)| (d.clamp(lo, hi), w))
        .collect();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    let k = k.max(1);
    if pts.is_empty() {
        return vec![Diopters(0.5 * (lo + hi))];
    }
    let total: f64 = pts.iter().map(|p| p.1).sum();
    // Initial centres at the mass quantiles (k + 1 equal parts' midpoints).
    let mut centres: Vec<f32> = (0..k)
        .map(|j| {
            let want = total * (j as f64 + 0.5) / k as f64;
            let mut acc = 0.0;
            for &(d, w) in &pts {
                acc += w;
                if acc >= want {
                    return d;
                }
            }
            pts[pts.len() - 1].0
        })
        .collect();
    for _ in 0..50 {
        let mut sum = vec![(0.0f64, 0.0f64); k];
        for &(d, w) in &pts {
            let j = nearest(&centres, d);
            sum[j].0 += w * f64::from(d);
            sum[j].1 += w;
        }
        let next: Vec<f32> = sum
            .iter()
            .zip(&centres)
            .map(|(&(s, w), &c)| if w > 0.0 { (s / w) as f32 } else { c })
            .collect();
        let moved = next
            .iter()
            .zip(&centres)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        centres = next;
        if moved < 1e-4 {
            break;
        }
    }
    centres.sort_by(f32::total_cmp);
    let mut out: Vec<f32> = Vec::with_capacity(k);
    for c in centres {
        let c = c.clamp(lo, hi);
        match out.last() {
            Some(&p) if c < p + MIN_PLANE_GAP => {
                if p + MIN_PLANE_GAP <= hi {
                    out.push(p + MIN_PLANE_GAP);
                }
            }
            _ => out.push(c),
        }
    }
    out.into_iter().map(Diopters).collect()
}

/// Smallest spacing between planes, diopters.
const MIN_PLANE_GAP: f32 = 0.05;

fn nearest(centres: &[f32], d: f32) -> usize {
    let mut best = 0;
    for (j, &c) in centres.iter().enumerate() {
        if (c - d).abs() < (centres[best] - d).abs() {
            best = j;
        }
    }
    best
}

/// A setting the deadline-aware planner ([`Planner::plan_within`]) chooses among: the
/// classical choices, and the pyramid method at full resolution or foveated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Setting {
    Classic(Choice),
    Pyramid,
    Foveated(Layered),
}

impl Setting {
    /// The defocus method to run; `None`: pass the pinhole image through.
    pub fn method(&self) -> Option<DefocusMethod> {
        match *self {
            Setting::Classic(Choice::None) => None,
            Setting::Classic(Choice::Gather) => Some(DefocusMethod::Gather),
            Setting::Classic(Choice::LightField { views }) => {
                Some(DefocusMethod::LightField(LightFieldParams {
                    views,
                    mip: true,
                }))
            }
            Setting::Pyramid => Some(DefocusMethod::Pyramid(PyramidParams::default())),
            Setting::Foveated(f) => {
                Some(DefocusMethod::Pyramid(PyramidParams { foveation: Some(f) }))
            }
        }
    }
}

impl fmt::Display for Setting {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Setting::Classic(c) => write!(f, "{c}"),
            Setting::Pyramid => write!(f, "pyramid"),
            Setting::Foveated(v) => write!(
                f,
                "pyramid-foveated ({:.1} deg, slope {:.4})",
                v.radius_deg, v.mar_slope
            ),
        }
    }
}

/// The time a frame may take: the display period (or the content period in multifocal mode)
/// less a margin, and the cores the render runs on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Deadline {
    pub budget_ms: f64,
    pub cores: usize,
}

impl Deadline {
    /// A frame every `period_ms` (the display's refresh period in varifocal mode, the content
    /// frame period in multifocal mode), less `margin_ms` for the rest of the frame's work
    /// (compose, present), rendered on `cores` cores.
    pub fn from_period(period_ms: f64, margin_ms: f64, cores: usize) -> Deadline {
        Deadline {
            budget_ms: (period_ms - margin_ms).max(0.0),
            cores: cores.max(1),
        }
    }
}

/// How much coarser than the rig's the planner may make the periphery under a short budget:
/// multiples of the rig's acuity slope (the fovea's full-resolution radius is kept).
pub const COARSER_PERIPHERY: [f32; 2] = [2.0, 4.0];
/// The largest acuity slope a foveation takes ([`crate::foveated`] checks it).
const MAX_MAR_SLOPE: f32 = 10.0;

/// The rig's foveation settings: full resolution within `radius_deg` of the gaze, acuity
/// falling by `mar_slope` degrees per degree beyond ([`crate::foveated`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FoveationSettings {
    pub radius_deg: f32,
    pub mar_slope: f32,
}

/// The deadline-aware planner's answer.
#[derive(Debug, Clone, PartialEq)]
pub struct TimedPlan {
    pub setting: Setting,
    /// Predicted PSNR in the fovea, dB.
    pub predicted_psnr: f64,
    /// Predicted wall time of the render on the deadline's cores, ms.
    pub predicted_ms: f64,
    pub meets_target: bool,
    pub meets_deadline: bool,
    pub why: String,
}

impl Planner {
    /// Predicted fovea PSNR of `setting`; `None` where the setting cannot promise the fovea
    /// (a foveation whose full-resolution radius is smaller than the fovea the target is for).
    pub fn predict_setting_psnr(&self, stats: &FrameStats, setting: &Setting) -> Option<f64> {
        use calibration::PYRAMID_MARGIN_DB;
        let pyramid = self.predict_psnr(stats, Choice::Gather) - PYRAMID_MARGIN_DB;
        match setting {
            Setting::Classic(c) => Some(self.predict_psnr(stats, *c)),
            Setting::Pyramid => Some(pyramid),
            Setting::Foveated(f) => (f.radius_deg >= stats.fovea_radius_deg).then_some(pyramid),
        }
    }

    /// Predicted wall time of `setting` on `cores` cores, ms.
    pub fn predict_setting_ms(&self, stats: &FrameStats, setting: &Setting, cores: usize) -> f64 {
        use calibration::*;
        let cores = cores.max(1) as f64;
        let pyramid_cpu = |s: &FrameStats, pixels: f64| {
            let f = pyramid_features(s);
            let (a, b, c) = PYRAMID_CPU_MS_PER_MP;
            pixels / 1e6 * (a + b * f.taps + c * f.spread)
        };
        match setting {
            Setting::Classic(c) => self.predict_cost_ms(stats, *c) * CALIBRATION_CORES / cores,
            Setting::Pyramid => pyramid_cpu(stats, (stats.width * stats.height) as f64) / cores,
            Setting::Foveated(f) => {
                let Ok(plan) = FoveationPlan::new(stats.width, stats.height, &stats.eye, f) else {
                    return f64::INFINITY;
                };
                let layers: f64 = plan
                    .layers
                    .iter()
                    .map(|l| pyramid_cpu(&stats.scaled(l.level), l.pixels as f64))
                    .sum();
                (layers + FOVEATED_BLEND_CPU_MS_PER_MP * stats.megapixels()) / cores
            }
        }
    }

    /// The cheapest setting predicted to meet `target` within `deadline`; if none does, the
    /// most accurate one that fits the deadline; if none fits, the cheapest (and says so).
    /// `foveation`: the rig's foveation settings, offered around the frame's gaze.
    pub fn plan_within(
        &self,
        stats: &FrameStats,
        target: &Target,
        deadline: &Deadline,
        foveation: Option<FoveationSettings>,
    ) -> TimedPlan {
        let mut settings: Vec<Setting> = Choice::all().into_iter().map(Setting::Classic).collect();
        settings.push(Setting::Pyramid);
        let at_gaze = |f: FoveationSettings, coarser: f32| {
            Setting::Foveated(Layered {
                gaze: stats.gaze,
                radius_deg: f.radius_deg,
                mar_slope: (f.mar_slope * coarser).min(MAX_MAR_SLOPE),
            })
        };
        if let Some(f) = foveation {
            settings.push(at_gaze(f, 1.0));
        }
        let score = |settings: &[Setting]| {
            let mut scored: Vec<(Setting, f64, f64)> = settings
                .iter()
                .filter_map(|s| {
                    let psnr = self.predict_setting_psnr(stats, s)?;
                    Some((*s, psnr, self.predict_setting_ms(stats, s, deadline.cores)))
                })
                .collect();
            scored.sort_by(|a, b| a.2.total_cmp(&b.2));
            scored
        };
        let fits = |s: &&(Setting, f64, f64)| s.2 <= deadline.budget_ms;
        let meets = |s: &&(Setting, f64, f64)| s.1 >= target.fovea_psnr_db;
        let mut scored = score(&settings);
        // The rig's own settings first; a periphery coarser than the rig's only when none of
        // them meets the target in time and the target leaves the periphery free.
        let mut coarsened = false;
        if !scored.iter().filter(fits).any(|s| meets(&s)) && target.periphery_psnr_db.is_none() {
            if let Some(f) = foveation {
                settings.extend(COARSER_PERIPHERY.iter().map(|&m| at_gaze(f, m)));
                scored = score(&settings);
                coarsened = true;
            }
        }
        let (pick, reason) = if let Some(s) = scored.iter().filter(fits).find(meets) {
            (
                *s,
                if coarsened {
                    "the cheapest predicted to meet the target in time, the periphery coarser than the rig's"
                } else {
                    "the cheapest predicted to meet the target in time"
                },
            )
        } else if let Some(s) = scored
            .iter()
            .filter(fits)
            .max_by(|a, b| a.1.total_cmp(&b.1))
        {
            (
                *s,
                "none meets the target in time: the most accurate that fits",
            )
        } else {
            (scored[0], "none fits the deadline: the cheapest")
        };
        let (setting, psnr, ms) = pick;
        let meets_target = psnr >= target.fovea_psnr_db;
        let meets_deadline = ms <= deadline.budget_ms;
        TimedPlan {
            setting,
            predicted_psnr: psnr,
            predicted_ms: ms,
            meets_target,
            meets_deadline,
            why: format!(
                "{setting}: {reason} (predicted {psnr:.1} dB in the fovea against {:.1}, {ms:.1} ms against a budget of {:.1} ms on {} cores)",
                target.fovea_psnr_db, deadline.budget_ms, deadline.cores
            ),
        }
    }
}

/// What [`predict_frame_cost`] is asked about: one frame of the rig's render.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameSpec {
    /// Each eye's image, pixels.
    pub width: usize,
    pub height: usize,
    /// Eyes rendered per frame (2 on a binocular rig).
    pub eyes: usize,
    /// The eye model (its field of view sets the blur in pixels; its width is taken from
    /// `width`).
    pub eye: EyeModel,
    pub method: DefocusMethod,
    /// The rig's foveation, applied to the pyramid method around the image's centre (where
    /// the method has none of its own); `None`: every pixel at full resolution.
    pub foveation: Option<FoveationSettings>,
    /// `cpu`, or `gpu` (alias `wgpu`), as [`crate::backend`] names them.
    pub backend: String,
    /// Cores the CPU backend renders on.
    pub cores: usize,
    /// The depths the content is assumed to spread over (nearest, farthest): the prediction is
    /// the worst over foci across that range.
    pub depths: (Diopters, Diopters),
}

impl FrameSpec {
    /// One eye, `width` x `height`, the pyramid method on the CPU's cores (as many as the
    /// machine has), content from 4 D to 0 D.
    pub fn new(width: usize, height: usize, eye: EyeModel) -> FrameSpec {
        FrameSpec {
            width,
            height,
            eyes: 1,
            eye,
            method: DefocusMethod::Pyramid(PyramidParams::default()),
            foveation: None,
            backend: "cpu".into(),
            cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
            depths: (Diopters(4.0), Diopters(0.0)),
        }
    }
}

/// A frame's predicted render cost ([`predict_frame_cost`]).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameCost {
    /// The render's wall time on the spec's cores, all eyes, ms.
    pub wall_ms: f64,
    /// Its CPU time, all threads and eyes, ms.
    pub cpu_ms: f64,
    /// The focus the prediction is for (the costliest across the content's depths).
    pub worst_focus: Diopters,
    /// The setting predicted.
    pub setting: Setting,
    /// One line for a log: what was predicted and on what assumptions.
    pub summary: String,
}

impl FrameCost {
    /// Whether the predicted wall time fits `deadline`'s budget.
    pub fn fits(&self, deadline: &Deadline) -> bool {
        self.wall_ms <= deadline.budget_ms
    }
}

/// The predicted cost of rendering one frame as `spec` describes, before any content has
/// arrived: for a daemon to print at start against its display period (or content period in
/// multifocal mode) and to warn when it does not fit, e.g.
///
/// ```
/// use dioptra_core::EyeModel;
/// use dioptra_render::planner::{predict_frame_cost, Deadline, FrameSpec};
/// let mut spec = FrameSpec::new(960, 1080, EyeModel::default());
/// spec.eyes = 2;
/// let cost = predict_frame_cost(&spec).unwrap();
/// let deadline = Deadline::from_period(1000.0 / 60.0, 2.0, spec.cores);
/// println!("{} (budget {:.1} ms: {})", cost.summary, deadline.budget_ms,
///     if cost.fits(&deadline) { "fits" } else { "late" });
/// ```
///
/// The model ([`calibration`]) was measured on the CPU backend; the GPU backend has none yet
/// and is an error, as are a foveation asked of a method other than the pyramid, an unknown
/// backend and an empty size.
pub fn predict_frame_cost(spec: &FrameSpec) -> Result<FrameCost, RenderError> {
    match spec.backend.as_str() {
        "cpu" => {}
        "gpu" | "wgpu" => {
            return Err(invalid(
                "no cost model for the gpu backend yet (the planner's calibration is the CPU backend's); measure it with `cargo bench -p dioptra-render --bench gpu`",
            ))
        }
        other => {
            return Err(invalid(format!(
                "unknown backend {other:?}: expected cpu or gpu"
            )))
        }
    }
    if spec.width == 0 || spec.height == 0 || spec.eyes == 0 {
        return Err(invalid(format!(
            "a frame of {} x {} px x {} eyes has nothing to render",
            spec.width, spec.height, spec.eyes
        )));
    }
    let centre = [0.5 * spec.width as f32, 0.5 * spec.height as f32];
    let setting = match (spec.method, spec.foveation) {
        (DefocusMethod::Pyramid(PyramidParams { foveation: Some(f) }), _) => Setting::Foveated(f),
        (DefocusMethod::Pyramid(_), Some(f)) => Setting::Foveated(Layered {
            gaze: centre,
            radius_deg: f.radius_deg,
            mar_slope: f.mar_slope,
        }),
        (DefocusMethod::Pyramid(_), None) => Setting::Pyramid,
        (m, Some(_)) => {
            return Err(invalid(format!(
                "foveation needs the pyramid method, not {m:?}"
            )))
        }
        (DefocusMethod::Gather, None) => Setting::Classic(Choice::Gather),
        (DefocusMethod::LightField(p), None) => {
            Setting::Classic(Choice::LightField { views: p.views })
        }
    };
    if let Setting::Foveated(f) = setting {
        FoveationPlan::new(spec.width, spec.height, &spec.eye, &f)?;
    }
    let (near, far) = spec.depths;
    if !(near.0.is_finite() && far.0.is_finite()) {
        return Err(invalid(format!(
            "content depths {near:?} to {far:?} are not finite"
        )));
    }
    let cores = spec.cores.max(1);
    // The costliest focus over the content's range (its ends, its middle and between).
    let (worst_focus, per_eye) = (0..=4)
        .map(|i| {
            let q = Diopters(far.0 + (near.0 - far.0) * i as f32 / 4.0);
            let stats = FrameStats::typical(spec.width, spec.height, &spec.eye, spec.depths, q);
            (q, Planner.predict_setting_ms(&stats, &setting, cores))
        })
        .fold((far, 0.0f64), |a, b| if b.1 > a.1 { b } else { a });
    let wall_ms = per_eye * spec.eyes as f64;
    let cpu_ms = wall_ms * cores as f64;
    Ok(FrameCost {
        wall_ms,
        cpu_ms,
        worst_focus,
        setting,
        summary: format!(
            "predicted render: {setting}, {} eye(s) of {} x {} px over {} deg on {cores} CPU core(s): {wall_ms:.1} ms a frame (content {:.1} to {:.1} D, focus {:.1} D)",
            spec.eyes,
            spec.width,
            spec.height,
            spec.eye.fov_horizontal_deg,
            near.0,
            far.0,
            worst_focus.0
        ),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_core::{DepthMap, Plane, RgbImage};

    /// A `w` x `h` frame: a texture over a depth step (near left, far right) with a ramp.
    fn frame(w: usize, h: usize) -> Rgbd {
        let plane = |f: &dyn Fn(usize, usize) -> f32| {
            Plane::from_vec(w, h, (0..w * h).map(|i| f(i % w, i / w)).collect()).unwrap()
        };
        let tex = |k: usize| move |x: usize, y: usize| ((x / 3 + y / 5 + k) % 2) as f32 * 0.4 + 0.1;
        let color = RgbImage::from_planes(plane(&tex(0)), plane(&tex(1)), plane(&tex(0))).unwrap();
        let depth = plane(&|x, y| {
            if x < w / 2 {
                3.0
            } else {
                0.2 + 0.01 * y as f32
            }
        });
        Rgbd::new(color, DepthMap::from_diopters(depth).unwrap()).unwrap()
    }

    /// One frame's whole-frame statistics serve every gaze, focus and fovea: the statistics
    /// made from them are those made from the frame alone; statistics of a frame of another
    /// size are not used.
    #[test]
    fn whole_frame_statistics_kept_give_the_statistics_of_any_gaze_and_focus() {
        let input = frame(120, 90);
        let eye = EyeModel::default();
        let wide = FrameWide::of(&input);
        let other = FrameWide::of(&frame(60, 90));
        for gaze in [
            [60.0, 45.0],
            [0.0, 0.0],
            [119.5, 89.5],
            [300.0, -5.0],
            [f32::NAN, 1.0],
        ] {
            for focus in [0.0, 0.5, 3.0] {
                for fovea in [1.0, FOVEA_RADIUS_DEG] {
                    let fresh =
                        FrameStats::from_rgbd_around(&input, gaze, fovea, Diopters(focus), &eye);
                    for kept in [&wide, &other] {
                        let st =
                            FrameStats::around(kept, &input, gaze, fovea, Diopters(focus), &eye);
                        // Debug, so that a NaN gaze compares equal to itself.
                        assert_eq!(format!("{st:?}"), format!("{fresh:?}"), "{gaze:?} {focus}");
                    }
                }
            }
        }
        assert_eq!(wide.histogram.total(), 120 * 90);
        assert_eq!(wide.range, Some((0.2, 3.0)));
    }
}
