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
    /// is the disk of diameter 0.1 of the image diagonal around the gaze, as in
    /// [`crate::metrics::FovealRegion`].
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
}

/// The fovea's radius as a fraction of the image diagonal (metrics' fovea: diameter 0.1 L).
const FOVEA_RADIUS: f32 = 0.05;
/// Blur radius beyond which the widened region stops growing, pixels.
const REACH_CAP_PX: f32 = 48.0;

impl FrameStats {
    /// The statistics of `input` for a viewer looking at `gaze` (pixels) focused at `focus`.
    pub fn from_rgbd(input: &Rgbd, gaze: [f32; 2], focus: Diopters, eye: &EyeModel) -> FrameStats {
        let (w, h) = (input.width(), input.height());
        let eye = eye.with_width(w.min(u32::MAX as usize) as u32);
        let depth = input.depth.data();
        let dmax = depth
            .iter()
            .copied()
            .filter(|d| d.is_finite())
            .fold(0.0f32, f32::max);
        let (lo, hi) = input
            .depth
            .range()
            .map(|(a, b)| (a.0, b.0))
            .unwrap_or((focus.0, focus.0));
        let frame_coc_px = eye
            .coc_px(Diopters(lo), focus)
            .max(eye.coc_px(Diopters(hi), focus));
        let diag = ((w * w + h * h) as f32).sqrt();
        let fovea = FOVEA_RADIUS * diag;
        let mut frame_histogram = DepthHistogram::new(dmax);
        let mut region_histogram = DepthHistogram::new(dmax);
        let dist2 = |i: usize| {
            let dx = (i % w) as f32 + 0.5 - gaze[0];
            let dy = (i / w) as f32 + 0.5 - gaze[1];
            dx * dx + dy * dy
        };
        // The farthest depth inside the fovea: content beyond it outside the fovea is hidden
        // behind the fovea's content and cannot blur into it.
        let farthest_in_fovea = depth
            .iter()
            .enumerate()
            .filter(|&(i, d)| d.is_finite() && dist2(i) <= fovea * fovea)
            .map(|(_, &d)| d)
            .fold(f32::INFINITY, f32::min);
        let (mut rlo, mut rhi) = (f32::INFINITY, f32::NEG_INFINITY);
        // Squared forward differences of the colour at pixel i, summed over x, y and the
        // channels (None on the last row and column).
        let gradient = |i: usize| {
            let (x, y) = (i % w, i / w);
            (x + 1 < w && y + 1 < h).then(|| {
                input
                    .color
                    .channels
                    .iter()
                    .map(|c| {
                        let v = c.row(y)[x];
                        let (gx, gy) = (c.row(y)[x + 1] - v, c.row(y + 1)[x] - v);
                        f64::from(gx * gx + gy * gy)
                    })
                    .sum::<f64>()
            })
        };
        let (mut frame_g, mut region_g) = ((0.0f64, 0u64), (0.0f64, 0u64));
        for (i, &d) in depth.iter().enumerate() {
            frame_histogram.add(d);
            let g = gradient(i);
            if let Some(g) = g {
                frame_g = (frame_g.0 + g, frame_g.1 + 3);
            }
            if !d.is_finite() {
                continue;
            }
            // Outside the fovea, a pixel matters when its blur disk reaches into the fovea
            // and it is not behind everything there.
            let reach = fovea + (0.5 * eye.coc_px(Diopters(d), focus)).min(REACH_CAP_PX);
            let r2 = dist2(i);
            if r2 <= fovea * fovea || (r2 <= reach * reach && d >= farthest_in_fovea) {
                region_histogram.add(d);
                if let Some(g) = g {
                    region_g = (region_g.0 + g, region_g.1 + 3);
                }
                rlo = rlo.min(d);
                rhi = rhi.max(d);
            }
        }
        if rlo > rhi {
            // A gaze off the image: the region is empty; judge by the whole frame.
            (rlo, rhi) = (lo, hi);
            region_histogram = frame_histogram.clone();
            region_g = frame_g;
        }
        if region_g.1 == 0 {
            // A region of one row or column: the frame's texture stands in.
            region_g = frame_g;
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
            frame_histogram,
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
        }
    }

    /// Megapixels in the frame.
    fn megapixels(&self) -> f64 {
        (self.width * self.height) as f64 / 1e6
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

/// The default fovea target, dB. The example is 38 dB; on the calibration scenes at
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
/// reference of the fovea.
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
