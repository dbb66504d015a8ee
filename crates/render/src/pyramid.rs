//! Defocus whose work per pixel does not grow with the blur: gather's scatter-as-gather, with
//! every blur of [`EXACT_RADIUS`] px or more spread at the resolution it leaves.
//!
//! Why this method. [`crate::gather`] sums, for each pixel, every neighbour whose circle of
//! confusion covers it: O(r^2) per pixel, so a panel's blur of 20-50 px costs hundreds to
//! thousands of taps. The literature's bounded-cost answers are (a) a fixed number of taps read
//! from a mip level matched to the blur (Yu et al. 2010's prefilter; game engines' half-res
//! ring gathers), which is cheap but leaves the blur's shape to the taps' placement; (b) depth
//! layers blurred separately, in the frequency domain or with constant-time filters (Kosloff,
//! Tao & Barsky 2009's rectangle spreading; Kraus & Strengert 2007's pyramidal layers), whose
//! compositing differs from gather's occlusion rule; (c) **pyramid spreading** (Kosloff & Barsky,
//! "Two new approaches to depth-of-field post-processing: pyramid spreading and tensor
//! filtering", 2008): each source spreads its PSF into the pyramid level where that PSF is a
//! few texels wide, so a source costs O(1) whatever its blur, and the pyramid is collapsed at
//! the end. We take (c), because it keeps gather's arithmetic (each source's own disk, weighted
//! 1 / r^2, normalised by the weights that reach the pixel) and therefore its accuracy, and
//! add what gather's occlusion rule needs, which a plain spreading cannot know (it depends on
//! the receiving pixel):
//!
//! - A source of radius `r < EXACT_RADIUS` (and any source clamped to such a radius) is
//!   gathered exactly at full resolution, as [`crate::gather`] does it (reach
//!   `EXACT_RADIUS + 0.5`, bounded).
//! - A larger source spreads its disk at level `m` (scale `2^m`), where `r / 2^m` lies in
//!   `[EXACT_RADIUS / 2, EXACT_RADIUS)`: each level-`m` cell sums its sources (colour x weight,
//!   weight, weighted centroid and radius) and spreads one ramped disk of the cell's radius
//!   around the centroid, corrected for the spread's resolution (the disk's second moment plus
//!   the bilinear read-back's equals gather's disk's). A pixel reads each level bilinearly.
//! - Gather's rule: a neighbour behind the pixel spreads no further than the pixel's own
//!   radius. A source nearer than the focus (front) is never clamped by it: a pixel it is behind
//!   is nearer still and blurrier. A source beyond the focus (back) of radius `r_j` is clamped
//!   for exactly the pixels of radius `r_x < r_j`. So back sources spread into half-octave bands
//!   of their own radius (`Own_b`, radii in `[rho_b, rho_{b+1})`), and also into `Clamp_b`: every
//!   back source of radius above `rho_b`, spread with radius `rho_b` and weight `1 / rho_b^2`.
//!   A pixel of radius `r_x` in `[rho_b, rho_{b+1})` reads the bands below its own, and
//!   `Clamp_b` / `Clamp_{b+1}` (with `Own_b`) interpolated at `r_x`; a pixel below
//!   `EXACT_RADIUS` gets every clamped source from the exact pass.
//! - In-focus pixels that no blur reaches (the exact pass's max filter below half a pixel and
//!   no level present) pass through untouched, as in gather.
//!
//! The work per pixel is bounded: the exact pass's taps (`EXACT_RADIUS + 0.5` px), the cells'
//! spreads (a disk of under `EXACT_RADIUS` texels per cell, a cell per `4^m` pixels), and one
//! bilinear read per level and band present. Everything is deterministic (fixed order, no
//! atomics); the GPU twin (`shaders/pyramid.wgsl`) computes the same sums by gathering over
//! the cells instead of scattering them.
//!
//! [`render_region`] computes only the pixels of a [`Region`] (a rectangle, optionally an
//! annulus around a gaze point): the foveated render ([`crate::foveated`]) runs it per
//! eccentricity layer so that the work the periphery drops is never done.

use crate::common::{check_focus, check_rgbd, eye_for};
use crate::error::{invalid, RenderError};
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};
use rayon::prelude::*;

/// Radius (px) below which sources are gathered exactly at full resolution. Level `m` takes
/// radii in `[EXACT_RADIUS 2^m, EXACT_RADIUS 2^(m+1))`: it sums cells of `2^(m+1)` pixels a side
/// and spreads them on a grid of that scale, where they are `EXACT_RADIUS / 2` to
/// `EXACT_RADIUS` texels in radius. (Measured on the test scenes at a panel's pixel density:
/// 4 loses up to 0.7 dB against gather on a frame, 6 at most 0.26; summing 2 x 2 cells spread
/// at full resolution for 3 to 6 px instead loses 0.9.)
pub(crate) const EXACT_RADIUS: f32 = 6.0;
/// Bands per octave of radius for the sources beyond the focus (the clamp's resolution).
pub(crate) const BANDS_PER_OCTAVE: usize = 2;
/// Pyramid levels (grid scales 2, 4 ... 2^MAX_LEVELS).
pub(crate) const MAX_LEVELS: usize = 6;
/// Blur radii are capped here, px (gather's reach is capped at 256 px too).
pub(crate) const MAX_RADIUS: f32 = 256.0;
/// Kinds of cells per level: front sources, then the back bands' own-radius spreads, then the
/// back bands' clamped spreads.
pub(crate) const KINDS: usize = 1 + 2 * BANDS_PER_OCTAVE;
/// Bands of radius in all: band `b` holds radii in `[rho_b, rho_{b+1})`.
pub(crate) const BANDS: usize = BANDS_PER_OCTAVE * MAX_LEVELS;
/// How far (in texels of its level's grid) a cell's spread reaches from the cell: the radius
/// (below `EXACT_RADIUS` texels), its half-texel ramp, and the centroid's offset within the
/// cell.
pub(crate) const SPREAD_REACH: usize = EXACT_RADIUS as usize + 2;
/// A record of one cell: centroid (x, y, level texels), radius (texels), unused, then the
/// weighted colour (r, g, b) and the weight.
pub(crate) type Rec = [f32; 8];

/// This module's constants as WGSL, for shaders/pyramid.wgsl (prepended by the GPU context).
pub(crate) fn shared_wgsl() -> String {
    format!(
        "const EXACT_RADIUS: f32 = {EXACT_RADIUS:?};\nconst BANDS_PER_OCTAVE: u32 = {BANDS_PER_OCTAVE}u;\nconst BANDS: u32 = {BANDS}u;\nconst KINDS: u32 = {KINDS}u;\nconst MAX_RADIUS: f32 = {MAX_RADIUS:?};\nconst SPREAD_REACH: u32 = {SPREAD_REACH}u;\n"
    )
}

/// `rho_b = EXACT_RADIUS * 2^(b / BANDS_PER_OCTAVE)`, b = 0..=BANDS: the band edges.
pub(crate) fn band_edges() -> [f32; BANDS + 1] {
    std::array::from_fn(|b| EXACT_RADIUS * (b as f32 / BANDS_PER_OCTAVE as f32).exp2())
}

/// The band of a radius `r >= EXACT_RADIUS`: the largest `b < BANDS` with `edges[b] <= r`.
#[inline]
pub(crate) fn band_of(r: f32, edges: &[f32; BANDS + 1]) -> usize {
    let mut b = 0;
    while b + 1 < BANDS && edges[b + 1] <= r {
        b += 1;
    }
    b
}

/// Level of band `b`.
#[inline]
pub(crate) fn level_of_band(b: usize) -> usize {
    b / BANDS_PER_OCTAVE
}

/// Side of level `m`'s grid texels and of its cells, pixels.
#[inline]
pub(crate) fn level_scales(m: usize) -> (usize, usize) {
    let grid = 2usize << m;
    (grid, grid)
}

/// Per-axis second moment (px^2) of gather's ramped disk `clamp(r + 0.5 - d, 0, 1)` of radius
/// `r >= 0.5`, as a continuous density.
fn ramp_disk_m2(r: f32) -> f32 {
    let r2 = r * r;
    0.15 * (5.0 * r2 * r2 + 2.5 * r2 + 0.0625) / (3.0 * r2 + 0.25)
}

/// The radius (texels of a grid of scale `grid` px) of the one ramped disk that stands for a
/// cell of `cell` x `cell` sources of radius `r` px, with the second moment of gather's sum over
/// the cell: `m2(R) grid^2 + tent = m2(r) + (cell^2 - 1) / 12`, where `tent = grid^2 / 6` is
/// the bilinear read-back's (none at full resolution).
pub(crate) fn spread_radius(r: f32, cell: f32, grid: f32) -> f32 {
    let tent = if grid > 1.0 { grid * grid / 6.0 } else { 0.0 };
    let m = (ramp_disk_m2(r) + (cell * cell - 1.0) / 12.0 - tent) / (grid * grid);
    // Inverse of ramp_disk_m2 (a quadratic in R^2).
    let b = 3.0 * m - 0.375;
    let u = (b + (b * b - 3.0 * (0.009375 - 0.25 * m)).max(0.0).sqrt()) / 1.5;
    u.max(0.25).sqrt()
}

/// The pixels to compute: a rectangle, and within it an annulus around `centre` (pixel
/// centres at distance `inner <= d < outer`; `inner < 0` and `outer = inf` take them all).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Region {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
    pub centre: [f32; 2],
    pub inner: f32,
    pub outer: f32,
}

impl Region {
    /// Every pixel of a `w` x `h` image.
    pub fn full(w: usize, h: usize) -> Region {
        Region {
            x0: 0,
            y0: 0,
            x1: w,
            y1: h,
            centre: [0.0, 0.0],
            inner: -1.0,
            outer: f32::INFINITY,
        }
    }

    /// Whether pixel `(x, y)` is computed (inside the rectangle and the annulus).
    #[inline]
    pub fn contains(&self, x: usize, y: usize) -> bool {
        if x < self.x0 || x >= self.x1 || y < self.y0 || y >= self.y1 {
            return false;
        }
        let dx = x as f32 + 0.5 - self.centre[0];
        let dy = y as f32 + 0.5 - self.centre[1];
        let d2 = dx * dx + dy * dy;
        d2 >= self.inner * self.inner.abs() && d2 < self.outer * self.outer
    }

    /// The pixels of row `y` that [`Region::contains`]: at most two runs of columns
    /// `[a, b)` (the annulus's hole splits the row), either possibly empty. The same test
    /// decides each run's ends, so the runs hold exactly the pixels it accepts.
    pub fn row_runs(&self, y: usize) -> [(usize, usize); 2] {
        const NONE: [(usize, usize); 2] = [(0, 0), (0, 0)];
        if y < self.y0 || y >= self.y1 || self.x0 >= self.x1 {
            return NONE;
        }
        let dy = y as f32 + 0.5 - self.centre[1];
        let d2 = |x: usize| {
            let dx = x as f32 + 0.5 - self.centre[0];
            dx * dx + dy * dy
        };
        let (outer2, inner2) = (self.outer * self.outer, self.inner * self.inner.abs());
        // The columns within [x0, x1) where `d2 < bound` (an interval: d2 falls, then rises).
        let below = |bound: f32| -> (usize, usize) {
            if bound == f32::INFINITY {
                return (self.x0, self.x1);
            }
            let half = (bound - dy * dy).max(0.0).sqrt();
            let at = |v: f32| (v.max(self.x0 as f32).min(self.x1 as f32)) as usize;
            let (mut a, mut b) = (
                at((self.centre[0] - half - 0.5).ceil()),
                at((self.centre[0] + half - 0.5).floor() + 1.0),
            );
            // The estimate is off by rounding at most: settle each end on the test itself.
            while a > self.x0 && d2(a - 1) < bound {
                a -= 1;
            }
            while a < b && d2(a) >= bound {
                a += 1;
            }
            while b < self.x1 && d2(b) < bound {
                b += 1;
            }
            while b > a && d2(b - 1) >= bound {
                b -= 1;
            }
            (a, b)
        };
        let (a, b) = below(outer2);
        if a >= b {
            return NONE;
        }
        if inner2 <= 0.0 {
            return [(a, b), (b, b)];
        }
        let (ha, hb) = below(inner2);
        if ha >= hb {
            return [(a, b), (b, b)];
        }
        [(a, ha.clamp(a, b)), (hb.clamp(a, b), b)]
    }

    /// The rectangle clipped to a `w` x `h` image; `None` when empty.
    fn clipped(&self, w: usize, h: usize) -> Option<Region> {
        let r = Region {
            x1: self.x1.min(w),
            y1: self.y1.min(h),
            ..*self
        };
        (r.x0 < r.x1 && r.y0 < r.y1).then_some(r)
    }
}

/// Pyramid-spread defocus of `input` seen by `eye` focused at `focus` (every pixel).
pub fn pyramid(input: &Rgbd, focus: Diopters, eye: &EyeModel) -> Result<RgbImage, RenderError> {
    render_region(
        input,
        focus,
        eye,
        &Region::full(input.width(), input.height()),
    )
}

/// What one render needs of its input: per pixel the signed radius (px, positive nearer than
/// the focus) and its class (the band of a radius of at least `EXACT_RADIUS`, else none).
pub(crate) struct Setup {
    pub w: usize,
    pub h: usize,
    /// Signed radius per diopter of depth minus focus, px.
    pub k: f32,
    pub q: f32,
    pub edges: [f32; BANDS + 1],
    /// Levels with sources: `0..top` (0: no source of `EXACT_RADIUS` or more).
    pub top: usize,
}

impl Setup {
    pub fn new(input: &Rgbd, focus: Diopters, eye: &EyeModel) -> Result<Setup, RenderError> {
        Setup::with_range(input, input.depth.range(), focus, eye)
    }

    /// [`Setup::new`] with the levels sized for depths in `range` (nearest, farthest) rather
    /// than the input's own.
    pub fn with_range(
        input: &Rgbd,
        range: Option<(Diopters, Diopters)>,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<Setup, RenderError> {
        check_rgbd(input)?;
        Setup::for_size(input.width(), input.height(), range, focus, eye)
    }

    /// [`Setup::with_range`] for a `w` x `h` image (not empty).
    pub fn for_size(
        w: usize,
        h: usize,
        range: Option<(Diopters, Diopters)>,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<Setup, RenderError> {
        check_focus(focus)?;
        let eye = eye_for(eye, w)?;
        let k = 0.5 * eye.coc_px(Diopters(1.0), Diopters(0.0));
        if !k.is_finite() {
            return Err(invalid(format!(
                "the eye model {eye:?} gives a non-finite circle of confusion"
            )));
        }
        let edges = band_edges();
        let rmax = match range {
            Some((lo, hi)) => (k * (lo.0 - focus.0))
                .abs()
                .max((k * (hi.0 - focus.0)).abs())
                .min(MAX_RADIUS),
            None => 0.0,
        };
        let top = if rmax >= EXACT_RADIUS {
            level_of_band(band_of(rmax, &edges)) + 1
        } else {
            0
        };
        Ok(Setup {
            w,
            h,
            k,
            q: focus.0,
            edges,
            top,
        })
    }

    /// Signed radius of depth `d`, capped at `MAX_RADIUS`.
    #[inline]
    pub fn signed(&self, d: f32) -> f32 {
        (self.k * (d - self.q)).clamp(-MAX_RADIUS, MAX_RADIUS)
    }
}

/// A level's grid and cells, and the parts of them that are computed.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LevelGrid {
    /// Side of a grid texel and of a cell, pixels; `ratio` texels per cell side.
    pub scale: usize,
    pub cell: usize,
    pub ratio: usize,
    pub lw: usize,
    pub lh: usize,
    /// Cells whose records are built: `[cx0, cy0, cx1, cy1)`.
    pub rec: [usize; 4],
    /// Texels whose spread is computed (what the region's pixels read): `[x0, y0, x1, y1)`.
    pub out: [usize; 4],
}

impl LevelGrid {
    pub fn new(m: usize, w: usize, h: usize, region: &Region) -> LevelGrid {
        let (s, cell) = level_scales(m);
        let ratio = cell / s;
        let (lw, lh) = (w.div_ceil(s), h.div_ceil(s));
        let (cw, ch) = (w.div_ceil(cell), h.div_ceil(cell));
        // Bilinear reads of the region's pixels touch these texels.
        let out = [
            (region.x0 / s).saturating_sub(1),
            (region.y0 / s).saturating_sub(1),
            (region.x1.div_ceil(s) + 1).min(lw),
            (region.y1.div_ceil(s) + 1).min(lh),
        ];
        let rec = [
            out[0].saturating_sub(SPREAD_REACH) / ratio,
            out[1].saturating_sub(SPREAD_REACH) / ratio,
            (out[2] + SPREAD_REACH).div_ceil(ratio).min(cw),
            (out[3] + SPREAD_REACH).div_ceil(ratio).min(ch),
        ];
        LevelGrid {
            scale: s,
            cell,
            ratio,
            lw,
            lh,
            rec,
            out,
        }
    }
}

/// One level's cells of one kind: per record row, the non-empty cells (column, record),
/// columns ascending.
pub(crate) type KindCells = Vec<Vec<(usize, Rec)>>;

/// A pixel's class: `SMALL` below `EXACT_RADIUS`, else its band, with `BACK` set beyond the
/// focus.
const SMALL: u8 = 0xff;
const BACK: u8 = 0x80;

/// Per pixel of a band of the input's rows (those the render reads): the blur radius (px) and
/// the class. The pixel of image index `j` is at `j - base` in each array.
pub(crate) struct Pixels {
    /// The image index of the band's first pixel (its first row, column 0).
    pub base: usize,
    pub radius: Vec<f32>,
    /// Gather's weight per unit of cover, `1 / max(radius, 0.5)^2`.
    pub inv_area: Vec<f32>,
    pub class: Vec<u8>,
    /// The signed radius (positive nearer than the focus). Gather's clamp (a source behind the
    /// receiver and wider than it) holds exactly when the source's is below minus the
    /// receiver's radius: the signed radius grows with the depth in diopters, so it is
    /// negative and below the receiver's for such a source, and for no other.
    pub signed: Vec<f32>,
    /// The radius where it is below `EXACT_RADIUS`, else [`NOT_EXACT`]: the exact pass's
    /// sources, whose cover is then 0 without a test.
    pub exact: Vec<f32>,
}

/// A radius that gives no cover at any distance (the exact pass's stand-in for "not mine").
const NOT_EXACT: f32 = -1e30;

impl Pixels {
    /// The pixels of rows `y0..y1`.
    pub fn new(setup: &Setup, input: &Rgbd, [y0, y1]: [usize; 2]) -> Pixels {
        let w = setup.w;
        let depth = &input.depth.data()[y0 * w..y1 * w];
        let n = depth.len();
        let mut px = Pixels {
            base: y0 * w,
            radius: vec![0.0; n],
            inv_area: vec![0.0; n],
            class: vec![0; n],
            signed: vec![0.0; n],
            exact: vec![0.0; n],
        };
        let chunk = setup.w.max(1) * 16;
        px.radius
            .par_chunks_mut(chunk)
            .zip(px.inv_area.par_chunks_mut(chunk))
            .zip(px.class.par_chunks_mut(chunk))
            .zip(px.signed.par_chunks_mut(chunk))
            .zip(px.exact.par_chunks_mut(chunk))
            .zip(depth.par_chunks(chunk))
            .for_each(|(((((radius, inv_area), class), signed), exact), depth)| {
                for (i, &d) in depth.iter().enumerate() {
                    let sr = setup.signed(d);
                    let r = sr.abs();
                    let rr = r.max(0.5);
                    radius[i] = r;
                    signed[i] = sr;
                    inv_area[i] = 1.0 / (rr * rr);
                    (class[i], exact[i]) = if r < EXACT_RADIUS {
                        (SMALL, r)
                    } else {
                        (
                            band_of(r, &setup.edges) as u8 | if sr < 0.0 { BACK } else { 0 },
                            NOT_EXACT,
                        )
                    };
                }
            });
        px
    }
}

/// The record of one cell of `kind` at level `m` (band `first` is the level's first) from its
/// sums `a` (sum w c (3), sum w, sum w x, sum w y, sum w r); `None` when empty.
pub(crate) fn finish_record(
    a: &[f32; 7],
    kind: usize,
    first: usize,
    (cell, grid): (f32, f32),
    edges: &[f32; BANDS + 1],
) -> Option<Rec> {
    if a[3] <= 0.0 {
        return None;
    }
    let inv = 1.0 / a[3];
    let (radius, weight) = if kind <= BANDS_PER_OCTAVE {
        (a[6] * inv, 1.0)
    } else {
        // Every clamped source weighs 1 / rho_b^2 at radius rho_b.
        let rho = edges[first + kind - 1 - BANDS_PER_OCTAVE];
        (rho, 1.0 / (rho * rho))
    };
    Some([
        a[4] * inv / grid,
        a[5] * inv / grid,
        spread_radius(radius, cell, grid),
        0.0,
        a[0] * weight,
        a[1] * weight,
        a[2] * weight,
        a[3] * weight,
    ])
}

/// The cells of level `m` (scale `2^m`) over the grid's record rectangle, per kind.
pub(crate) fn aggregate_level(
    setup: &Setup,
    input: &Rgbd,
    px: &Pixels,
    m: usize,
    g: &LevelGrid,
) -> [KindCells; KINDS] {
    let (w, h, s) = (setup.w, setup.h, g.cell);
    let ch = input.color.channels.each_ref().map(|p| p.data());
    let edges = &setup.edges;
    let [cx0, cy0, cx1, cy1] = g.rec;
    let first = BANDS_PER_OCTAVE * m;
    let scales = (g.cell as f32, g.scale as f32);
    let rows: Vec<[Vec<(usize, Rec)>; KINDS]> = (cy0..cy1)
        .into_par_iter()
        .map(|cy| {
            let mut out: [Vec<(usize, Rec)>; KINDS] = Default::default();
            for cx in cx0..cx1 {
                let mut acc = [[0.0f32; 7]; KINDS];
                let mut any = false;
                for y in cy * s..((cy + 1) * s).min(h) {
                    let fy = y as f32 + 0.5;
                    let (row0, row1) = (y * w + cx * s, y * w + ((cx + 1) * s).min(w));
                    let band = &px.class[row0 - px.base..row1 - px.base];
                    for (j, &c) in (row0..row1).zip(band) {
                        if c == SMALL {
                            continue;
                        }
                        let b = (c & !BACK) as usize;
                        let own = level_of_band(b) == m;
                        let back = c & BACK != 0;
                        // Front sources spread at their own level only; back ones also
                        // into the clamped spreads of the bands at or below their own.
                        if !(own || back && b >= first) {
                            continue;
                        }
                        any = true;
                        let r = px.radius[j - px.base];
                        let (fx, col) = ((j - y * w) as f32 + 0.5, [ch[0][j], ch[1][j], ch[2][j]]);
                        let mut add = |kind: usize, wt: f32| {
                            let a = &mut acc[kind];
                            a[0] += wt * col[0];
                            a[1] += wt * col[1];
                            a[2] += wt * col[2];
                            a[3] += wt;
                            a[4] += wt * fx;
                            a[5] += wt * fy;
                            a[6] += wt * r;
                        };
                        if !back {
                            add(0, 1.0 / (r * r));
                            continue;
                        }
                        if own {
                            add(1 + b - first, 1.0 / (r * r));
                        }
                        for k in 0..BANDS_PER_OCTAVE {
                            if first + k <= b {
                                add(1 + BANDS_PER_OCTAVE + k, 1.0);
                            }
                        }
                    }
                }
                if !any {
                    continue;
                }
                for (kind, a) in acc.iter().enumerate() {
                    if let Some(rec) = finish_record(a, kind, first, scales, edges) {
                        out[kind].push((cx, rec));
                    }
                }
            }
            out
        })
        .collect();
    let mut kinds: [KindCells; KINDS] = Default::default();
    for row in rows {
        for (k, cells) in row.into_iter().enumerate() {
            kinds[k].push(cells);
        }
    }
    kinds
}

/// Side of the square tiles of texels that are spread (or skipped) together.
const TILE: usize = 8;
/// The receivers' bit for radii below `EXACT_RADIUS` in a tile's band mask.
const SMALL_BIT: u32 = 1 << 31;

/// Per tile of 8 x 8 image pixels, which receivers it holds: bit `b` for radii in band `b`,
/// `SMALL_BIT` for radii below `EXACT_RADIUS` (pixels of `region` only).
fn receiver_blocks(px: &Pixels, w: usize, h: usize, region: &Region) -> (Vec<u32>, usize) {
    let (bw, bh) = (w.div_ceil(TILE), h.div_ceil(TILE));
    let mut blocks = vec![0u32; bw * bh];
    blocks.par_chunks_mut(bw).enumerate().for_each(|(by, row)| {
        for y in by * TILE..((by + 1) * TILE).min(h) {
            for (a, b) in region.row_runs(y) {
                if a >= b {
                    continue;
                }
                let at = y * w - px.base;
                for (x, &c) in (a..b).zip(&px.class[at + a..at + b]) {
                    row[x / TILE] |= if c == SMALL {
                        SMALL_BIT
                    } else {
                        1 << (c & !BACK)
                    };
                }
            }
        }
    });
    (blocks, bw)
}

/// The bands whose receivers read `kind` of level `m` (front: every receiver).
fn readers(kind: usize, m: usize) -> u32 {
    let first = BANDS_PER_OCTAVE * m;
    if kind == 0 {
        return u32::MAX;
    }
    if kind <= BANDS_PER_OCTAVE {
        // Own band b: the receivers of band b (partly) and every band above.
        let b = first + kind - 1;
        return !((1u32 << b) - 1) & !SMALL_BIT;
    }
    // Clamped band b: the receivers of bands b - 1 and b.
    let b = first + kind - 1 - BANDS_PER_OCTAVE;
    (1 << b) | if b > 0 { 1 << (b - 1) } else { 0 }
}

/// A spread level image: r, g, b, weight per texel over the level's grid (zero where not
/// spread), and per tile of texels whether any weight is there.
pub(crate) struct LevelImage {
    /// `1 / scale` of the level's texels (px), exact (the scale is a power of two): a pixel's
    /// texel coordinate is the same product as the quotient.
    inv_scale: f32,
    pub lw: usize,
    pub lh: usize,
    pub data: Vec<[f32; 4]>,
    tw: usize,
    nonzero: Vec<bool>,
}

impl LevelImage {
    /// Bilinear read at full-resolution pixel `(x, y)`, edges clamped.
    #[inline]
    pub fn read(&self, x: usize, y: usize) -> [f32; 4] {
        let (x0, x1, fx) = self.axis(x, self.lw);
        let (y0, y1, fy) = self.axis(y, self.lh);
        let a = self.data[y0 * self.lw + x0];
        let b = self.data[y0 * self.lw + x1];
        let c = self.data[y1 * self.lw + x0];
        let d = self.data[y1 * self.lw + x1];
        std::array::from_fn(|k| {
            let top = a[k] + fx * (b[k] - a[k]);
            let bot = c[k] + fx * (d[k] - c[k]);
            top + fy * (bot - top)
        })
    }

    /// The two texels a pixel coordinate reads along an axis of `n` texels, and the weight of
    /// the second.
    #[inline]
    fn axis(&self, x: usize, n: usize) -> (usize, usize, f32) {
        let u = ((x as f32 + 0.5) * self.inv_scale - 0.5).clamp(0.0, (n - 1) as f32);
        let x0 = u as usize;
        (x0, (x0 + 1).min(n - 1), u - x0 as f32)
    }

    /// Whether any texel read by pixels `[x0, x1) x [y0, y1)` has weight.
    fn any_in(&self, x0: usize, x1: usize, y0: usize, y1: usize) -> bool {
        let (tx0, tx1) = (
            self.axis(x0, self.lw).0 / TILE,
            self.axis(x1 - 1, self.lw).1 / TILE,
        );
        let (ty0, ty1) = (
            self.axis(y0, self.lh).0 / TILE,
            self.axis(y1 - 1, self.lh).1 / TILE,
        );
        (ty0..=ty1).any(|ty| (tx0..=tx1).any(|tx| self.nonzero[ty * self.tw + tx]))
    }
}

/// Spreads one kind's cells over the tiles of the grid's output rectangle that `need` marks
/// (per row of tiles, each run of adjacent needed tiles as one span).
fn spread_kind(rows: &KindCells, g: &LevelGrid, need: &[bool], tw: usize) -> LevelImage {
    let [_, cy0, _, cy1] = g.rec;
    let [ox0, oy0, ox1, oy1] = g.out;
    let (lw, lh) = (g.lw, g.lh);
    // How far this kind's disks reach, in texels: radius, ramp, centroid within its cell.
    let widest = rows.iter().flatten().map(|c| c.1[2]).fold(0.0f32, f32::max);
    let ratio = g.ratio;
    let reach = (widest + 0.5).ceil() as usize + ratio;
    let mut data = vec![[0.0f32; 4]; lw * lh];
    let mut nonzero = vec![false; need.len()];
    data.par_chunks_mut(lw * TILE)
        .zip(nonzero.par_chunks_mut(tw))
        .enumerate()
        .for_each(|(ty, (band, nz))| {
            let (y0, y1) = ((ty * TILE).max(oy0), ((ty + 1) * TILE).min(oy1));
            let mut tx = 0;
            let mut diff = Vec::new();
            while tx < tw {
                if !need[ty * tw + tx] {
                    tx += 1;
                    continue;
                }
                let start = tx;
                while tx < tw && need[ty * tw + tx] {
                    tx += 1;
                }
                let (x0, x1) = ((start * TILE).max(ox0), (tx * TILE).min(ox1));
                if x0 >= x1 || y0 >= y1 {
                    continue;
                }
                for y in y0..y1 {
                    diff.clear();
                    diff.resize(x1 - x0 + 1, [0.0f32; 4]);
                    let row = &mut band[(y - ty * TILE) * lw + x0..(y - ty * TILE) * lw + x1];
                    // Cells whose texels lie within `reach` of this row and of the span.
                    let lo = (y.saturating_sub(reach) / ratio).max(cy0);
                    let hi = ((y + reach) / ratio + 1).min(cy1);
                    let near = TexelRow {
                        cells: &rows[lo.min(hi) - cy0..hi.max(lo) - cy0],
                        ratio,
                        reach,
                        y,
                        x0,
                        x1,
                    };
                    near.spread(row, &mut diff);
                }
                for (t, nz) in nz.iter_mut().enumerate().take(tx).skip(start) {
                    let (a, b) = ((t * TILE).max(x0), ((t + 1) * TILE).min(x1));
                    *nz = a < b
                        && (y0..y1).any(|y| {
                            band[(y - ty * TILE) * lw + a..(y - ty * TILE) * lw + b]
                                .iter()
                                .any(|v| v[3] > 0.0)
                        });
                }
            }
        });
    debug_assert!(g.scale.is_power_of_two());
    LevelImage {
        inv_scale: 1.0 / g.scale as f32,
        lw,
        lh,
        data,
        tw,
        nonzero,
    }
}

/// The cells near one texel row `y` of a level (within `reach` texels of the row and of its
/// columns `[x0, x1)`), rows of cells `ratio` texels a side.
struct TexelRow<'a> {
    cells: &'a [Vec<(usize, Rec)>],
    ratio: usize,
    reach: usize,
    y: usize,
    x0: usize,
    x1: usize,
}

impl TexelRow<'_> {
    /// Adds the cells' disks to `row` (columns `[x0, x1)`) through `diff` (zero, one longer).
    fn spread(&self, row: &mut [[f32; 4]], diff: &mut [[f32; 4]]) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx") {
                // SAFETY: the CPU has AVX (checked just above).
                return unsafe { self.spread_avx(row, diff) };
            }
        }
        self.spread_any(row, diff)
    }

    /// [`TexelRow::spread_any`] compiled for AVX: the disks' bounds are rounded by single
    /// instructions (SSE4.1's) instead of calls to the C library; the same IEEE operations
    /// otherwise, so the same sums bit for bit.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    unsafe fn spread_avx(&self, row: &mut [[f32; 4]], diff: &mut [[f32; 4]]) {
        self.spread_any(row, diff)
    }

    #[inline(always)]
    fn spread_any(&self, row: &mut [[f32; 4]], diff: &mut [[f32; 4]]) {
        let &TexelRow {
            cells,
            ratio,
            reach,
            y,
            x0,
            x1,
        } = self;
        let fy = y as f32 + 0.5;
        for cells in cells {
            if cells.is_empty() {
                continue;
            }
            let a = cells.partition_point(|c| (c.0 + 1) * ratio + reach <= x0);
            let b = cells.partition_point(|c| c.0 * ratio < x1 + reach);
            for (_, r) in &cells[a..b] {
                spread_row(r, fy, x0, x1, row, diff);
            }
        }
        let mut run = [0.0f32; 4];
        for (o, d) in row.iter_mut().zip(diff.iter()) {
            for c in 0..4 {
                run[c] += d[c];
                o[c] += run[c];
            }
        }
    }
}

/// One cell's disk on the texel row at height `fy`, within columns `[x0, x1)` (`row` and
/// `diff` start at column `x0`): the full-weight span as two differences in `diff`, the ramp
/// texels directly in `row`.
#[inline(always)]
fn spread_row(r: &Rec, fy: f32, x0: usize, x1: usize, row: &mut [[f32; 4]], diff: &mut [[f32; 4]]) {
    let dy = fy - r[1];
    let outer = r[2] + 0.5;
    if dy.abs() >= outer {
        return;
    }
    let v = [r[4], r[5], r[6], r[7]];
    let cx = r[0];
    let half = (outer * outer - dy * dy).sqrt();
    // Texels whose centre lies within `half` of the centroid.
    let xa = (cx - half - 0.5).ceil().max(x0 as f32);
    let xb = (cx + half - 0.5).floor().min(x1 as f32 - 1.0);
    if xb < xa {
        return;
    }
    let (xa, xb) = (xa as usize, xb as usize);
    // Full weight where the distance is at most radius - 0.5: one span.
    let inner = r[2] - 0.5;
    let (mut fa, mut fb) = (xa, xa);
    if inner >= 0.0 && dy.abs() <= inner {
        let hi = (inner * inner - dy * dy).sqrt();
        let a = (cx - hi - 0.5).ceil().max(xa as f32);
        let b = (cx + hi - 0.5).floor().min(xb as f32);
        if b >= a {
            (fa, fb) = (a as usize, b as usize + 1);
            for c in 0..4 {
                diff[fa - x0][c] += v[c];
                diff[fb - x0][c] -= v[c];
            }
        }
    }
    for x in (xa..fa).chain(fb.max(xa)..xb + 1) {
        let dx = x as f32 + 0.5 - cx;
        let cover = (outer - (dx * dx + dy * dy).sqrt()).clamp(0.0, 1.0);
        let o = &mut row[x - x0];
        for c in 0..4 {
            o[c] += cover * v[c];
        }
    }
}

/// Offsets within the exact pass's reach, nearest first (ties in generation order), with their
/// distances: gather's tap order.
pub(crate) fn exact_offsets() -> Vec<(isize, isize, f32)> {
    let reach = (EXACT_RADIUS + 0.5).ceil() as isize;
    let mut o: Vec<(isize, isize, f32)> = (-reach..=reach)
        .flat_map(|dy| {
            (-reach..=reach).map(move |dx| (dx, dy, ((dx * dx + dy * dy) as f32).sqrt()))
        })
        .filter(|o| o.2 <= EXACT_RADIUS + 0.5)
        .collect();
    o.sort_by(|a, b| a.2.total_cmp(&b.2));
    o
}

/// [`pyramid`] on the pixels of `region` only; every other pixel is black. The levels are
/// spread only where the region's pixels read them.
pub fn render_region(
    input: &Rgbd,
    focus: Diopters,
    eye: &EyeModel,
    region: &Region,
) -> Result<RgbImage, RenderError> {
    render_with(&Setup::new(input, focus, eye)?, input, region)
}

/// [`render_region`] with its setup given.
pub(crate) fn render_with(
    setup: &Setup,
    input: &Rgbd,
    region: &Region,
) -> Result<RgbImage, RenderError> {
    let (w, h) = (setup.w, setup.h);
    // Planar, as the image is kept: no interleaved copy to convert.
    let mut out = [
        vec![0.0f32; w * h],
        vec![0.0f32; w * h],
        vec![0.0f32; w * h],
    ];
    render_into(setup, input, region, &mut out);
    let [r, g, b] = out.map(|v| Plane::from_vec(w, h, v));
    Ok(RgbImage::from_planes(r?, g?, b?)?)
}

/// [`render_with`] into `out`, three `w` x `h` planes: writes the pixels of `region` and no
/// others.
pub(crate) fn render_into(setup: &Setup, input: &Rgbd, region: &Region, out: &mut [Vec<f32>; 3]) {
    let (w, h) = (setup.w, setup.h);
    let Some(region) = region.clipped(w, h) else {
        return;
    };
    // The rows read: the exact pass's reach around the region's, and the levels' cells.
    let reach = (EXACT_RADIUS + 0.5).ceil() as usize;
    let grids: Vec<LevelGrid> = (0..setup.top)
        .map(|m| LevelGrid::new(m, w, h, &region))
        .collect();
    let rows = grids.iter().fold(
        [region.y0.saturating_sub(reach), (region.y1 + reach).min(h)],
        |[a, b], g| [a.min(g.rec[1] * g.cell), b.max((g.rec[3] * g.cell).min(h))],
    );
    let px = Pixels::new(setup, input, rows);
    let (blocks, bw) = receiver_blocks(&px, w, h, &region);
    let bh = blocks.len() / bw.max(1);
    // Levels: per level, per kind, the spread image if any cell has weight.
    let mut levels: Vec<[Option<LevelImage>; KINDS]> = Vec::with_capacity(setup.top);
    for (m, g) in grids.iter().enumerate() {
        let g = *g;
        let cells = aggregate_level(setup, input, &px, m, &g);
        // Per texel tile, the receivers whose bilinear reads touch it (through the 8 x 8
        // pixel blocks around its pixels).
        let s = g.scale;
        let (tw, th) = (g.lw.div_ceil(TILE), g.lh.div_ceil(TILE));
        let mask: Vec<u32> = (0..tw * th)
            .into_par_iter()
            .map(|t| {
                let (tx, ty) = (t % tw, t / tw);
                // Pixels reading texels [X0, X1) lie in [(X0 - 1) s, (X1 + 1) s).
                let px0 = (tx * TILE * s).saturating_sub(s) / TILE;
                let px1 = ((((tx + 1) * TILE + 1) * s).div_ceil(TILE)).min(bw);
                let py0 = (ty * TILE * s).saturating_sub(s) / TILE;
                let py1 = ((((ty + 1) * TILE + 1) * s).div_ceil(TILE)).min(bh);
                let mut acc = 0u32;
                for by in py0..py1 {
                    for &b in &blocks[by * bw + px0..by * bw + px1] {
                        acc |= b;
                    }
                }
                acc
            })
            .collect();
        let imgs: [Option<LevelImage>; KINDS] = std::array::from_fn(|kind| {
            if cells[kind].iter().all(|r| r.is_empty()) {
                return None;
            }
            let who = readers(kind, m);
            let need: Vec<bool> = mask.iter().map(|&b| b & who != 0).collect();
            need.iter()
                .any(|&n| n)
                .then(|| spread_kind(&cells[kind], &g, &need, tw))
        });
        levels.push(imgs);
    }
    compose(setup, input, &px, &region, &levels, out);
}

/// Receivers processed together by the exact pass (one row, consecutive pixels).
const GROUP: usize = 8;

/// The exact pass and the levels' reads for every pixel of `region`, normalised.
fn compose(
    setup: &Setup,
    input: &Rgbd,
    px: &Pixels,
    region: &Region,
    levels: &[[Option<LevelImage>; KINDS]],
    out: &mut [Vec<f32>; 3],
) {
    let (w, h) = (setup.w, setup.h);
    let depth = input.depth.data();
    let ch = input.color.channels.each_ref().map(|p| p.data());
    let edges = &setup.edges;
    let radius = |j: usize| px.radius[j - px.base];
    let offsets = exact_offsets();
    let reach = (EXACT_RADIUS + 0.5).ceil() as usize;
    // Per pixel, the largest radius an exact-pass source within reach can have: sources
    // below EXACT_RADIUS at their own, larger ones only clamped to the pixel's own radius.
    let small = |i: usize| {
        let r = radius(i);
        if r < EXACT_RADIUS {
            r
        } else {
            0.0
        }
    };
    let (mx0, my0) = (region.x0.saturating_sub(GROUP), region.y0);
    let (mx1, my1) = ((region.x1 + GROUP).min(w), region.y1);
    let local_max = window_max(small, w, h, [mx0, my0, mx1, my1], reach);
    let mw = mx1 - mx0;
    // Where every source within reach shares the pixel's depth, the exact pass is the mean
    // over one ramped disk: per-row prefix sums give it in O(radius). Flat groups lie within
    // the region and their disks within `reach` of it.
    let flat = flat_depth(depth, w, h, [mx0, my0, mx1, my1], reach);
    let prefix = RowPrefix::new(
        ch,
        w,
        [my0.saturating_sub(reach), (my1 + reach).min(h)],
        (mx1 + reach).min(w),
    );
    let bound = |x: usize, y: usize| {
        let rc = radius(y * w + x);
        local_max[(y - my0) * mw + (x - mx0)].max(if rc < EXACT_RADIUS { rc } else { 0.0 }) + 0.5
    };
    // The exact pass's taps as index offsets (interior groups).
    let taps = ExactTaps::new(&offsets, w);
    let [r_out, g_out, b_out] = out;
    r_out
        .par_chunks_mut(w)
        .zip(g_out.par_chunks_mut(w))
        .zip(b_out.par_chunks_mut(w))
        .map(|((r, g), b)| [r, g, b])
        .enumerate()
        .skip(region.y0)
        .take(region.y1 - region.y0)
        .for_each_init(FlatDisks::default, |disks, (y, mut row)| {
            let runs = region.row_runs(y);
            let inside = |x: usize| runs.iter().any(|&(a, b)| a <= x && x < b);
            let mut x0 = region.x0;
            while x0 < region.x1 {
                let x1 = (x0 + GROUP).min(region.x1);
                if !runs.iter().any(|&(a, b)| a < b && a < x1 && x0 < b) {
                    // A group in the annulus's hole or the rectangle's corners.
                    x0 = x1;
                    continue;
                }
                let limit = (x0..x1).map(|x| bound(x, y)).fold(0.0f32, f32::max);
                let interior = x1 - x0 == GROUP
                    && x0 >= reach
                    && x1 + reach <= w
                    && y >= reach
                    && y + reach < h;
                let flat_group = interior && (x0..x1).all(|x| flat[(y - my0) * mw + (x - mx0)]);
                let Exact { acc, wsum, reached } = if flat_group {
                    // One depth over the group and its reach: one radius.
                    let r = radius(y * w + x0);
                    if r < EXACT_RADIUS {
                        let inv = px.inv_area[y * w + x0 - px.base];
                        disks.get(r).sum_group(&prefix, ch, w, x0, y, inv)
                    } else {
                        Exact::default()
                    }
                } else if interior {
                    exact_group(&taps, limit, y * w + x0, px, ch)
                } else {
                    let mut e = Exact::default();
                    for (i, x) in (x0..x1).enumerate() {
                        exact_pixel(
                            &offsets,
                            limit,
                            x,
                            y,
                            w,
                            h,
                            px,
                            depth,
                            ch,
                            &mut e.acc[i],
                            &mut e.wsum[i],
                            &mut e.reached[i],
                        );
                    }
                    e
                };
                // The levels' reads: a kind is read where its tiles have weight.
                let mut lacc = [[0.0f32; 4]; GROUP];
                let bands: [Option<(usize, f32)>; GROUP] = std::array::from_fn(|i| {
                    let x = x0 + i;
                    let rc = if x < x1 { radius(y * w + x) } else { 0.0 };
                    (rc >= EXACT_RADIUS).then(|| {
                        let b = band_of(rc, edges);
                        (
                            b,
                            ((rc - edges[b]) / (edges[b + 1] - edges[b])).clamp(0.0, 1.0),
                        )
                    })
                });
                for (li, kinds) in levels.iter().enumerate() {
                    for (kind, img) in kinds.iter().enumerate() {
                        let Some(img) = img else { continue };
                        if !img.any_in(x0, x1, y, y + 1) {
                            continue;
                        }
                        for (i, x) in (x0..x1).enumerate() {
                            let f = read_factor(kind, li, bands[i]);
                            if f > 0.0 {
                                let v = img.read(x, y);
                                for c in 0..4 {
                                    lacc[i][c] += f * v[c];
                                }
                            }
                        }
                    }
                }
                for (i, x) in (x0..x1).enumerate() {
                    if !inside(x) {
                        continue;
                    }
                    let j = y * w + x;
                    let own = [ch[0][j], ch[1][j], ch[2][j]];
                    let l = lacc[i];
                    let v = if l[3] <= 0.0 && !reached[i] {
                        // Only the pixel itself reached it: unchanged, as gather leaves it.
                        own
                    } else {
                        let total = wsum[i] + l[3];
                        if total > 0.0 {
                            [0, 1, 2].map(|c| (acc[i][c] + l[c]) / total)
                        } else {
                            own
                        }
                    };
                    for (o, v) in row.iter_mut().zip(v) {
                        o[x] = v;
                    }
                }
                x0 = x1;
            }
        });
}

/// How much of `kind` of level index `li` a pixel of band and band fraction `own` (`None`
/// below `EXACT_RADIUS`) reads: front sources fully; the back bands below its own fully, its
/// own band by the fraction; the clamped spreads of its band and the next interpolated.
#[inline]
fn read_factor(kind: usize, li: usize, own: Option<(usize, f32)>) -> f32 {
    if kind == 0 {
        return 1.0;
    }
    let Some((b, t)) = own else { return 0.0 };
    if kind <= BANDS_PER_OCTAVE {
        let band = BANDS_PER_OCTAVE * li + kind - 1;
        if band < b {
            1.0
        } else if band == b {
            t
        } else {
            0.0
        }
    } else {
        let band = BANDS_PER_OCTAVE * li + kind - 1 - BANDS_PER_OCTAVE;
        if band == b {
            1.0 - t
        } else if band == b + 1 {
            t
        } else {
            0.0
        }
    }
}

/// The exact pass for the `GROUP` pixels from image index `at` (one row), all sources inside
/// the image: the same sums as [`exact_pixel`], lane by lane, branch-free so that it
/// vectorises (8 lanes at once where the CPU has AVX). `taps` are [`exact_offsets`] as index
/// offsets, nearest first; those beyond `limit` are not read.
fn exact_group(taps: &ExactTaps, limit: f32, at: usize, px: &Pixels, ch: [&[f32]; 3]) -> Exact {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX (checked just above).
            return unsafe { exact_group_avx(taps, limit, at, px, ch) };
        }
    }
    exact_group_lanes(&taps.taps, limit, at, px, ch)
}

/// [`exact_group_lanes`] in AVX intrinsics (LLVM turns the lanes' selects into branches).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn exact_group_avx(
    ExactTaps { taps, span }: &ExactTaps,
    limit: f32,
    at: usize,
    px: &Pixels,
    ch: [&[f32]; 3],
) -> Exact {
    use std::arch::x86_64::*;
    const _: () = assert!(GROUP == 8);
    // Every tap's eight lanes lie inside every plane (the colour's from `at`, the pixels'
    // from `at - px.base`): checked once here, not per load.
    let (n, nc) = (px.radius.len(), ch[0].len());
    let pat = at.wrapping_sub(px.base);
    let inside = [&px.signed, &px.exact, &px.inv_area]
        .iter()
        .all(|v| v.len() == n)
        && ch.iter().all(|v| v.len() == nc)
        && at >= px.base
        && pat >= *span
        && pat + span + GROUP <= n
        && at >= *span
        && at + span + GROUP <= nc;
    if !inside {
        return exact_group_lanes(taps, limit, at, px, ch);
    }
    // Eight lanes from `v[j..]`.
    macro_rules! lanes {
        ($v:expr, $j:expr) => {
            // SAFETY: `$j` is `at` (`pat`) or `at` (`pat`) plus a tap's offset for a colour
            // plane (an array of `px`), and `inside` holds.
            _mm256_loadu_ps($v.as_ptr().add($j))
        };
    }
    let zero = _mm256_setzero_ps();
    let (half, one) = (_mm256_set1_ps(0.5), _mm256_set1_ps(1.0));
    let neg_rc = _mm256_sub_ps(zero, lanes!(px.radius, pat));
    let rc = lanes!(px.exact, pat);
    let ic = lanes!(px.inv_area, pat);
    let (mut a0, mut a1, mut a2, mut ws, mut far) = (zero, zero, zero, zero, zero);
    for (t, &(off, dist)) in taps.iter().enumerate() {
        if dist > limit {
            break;
        }
        let (j, pj) = (at.wrapping_add_signed(off), pat.wrapping_add_signed(off));
        let clamp = _mm256_cmp_ps::<_CMP_LT_OQ>(lanes!(px.signed, pj), neg_rc);
        let r = _mm256_blendv_ps(lanes!(px.exact, pj), rc, clamp);
        let inv = _mm256_blendv_ps(lanes!(px.inv_area, pj), ic, clamp);
        let c = _mm256_sub_ps(_mm256_add_ps(r, half), _mm256_set1_ps(dist));
        let cover = _mm256_max_ps(_mm256_min_ps(c, one), zero);
        let wgt = _mm256_mul_ps(cover, inv);
        a0 = _mm256_add_ps(a0, _mm256_mul_ps(wgt, lanes!(ch[0], j)));
        a1 = _mm256_add_ps(a1, _mm256_mul_ps(wgt, lanes!(ch[1], j)));
        a2 = _mm256_add_ps(a2, _mm256_mul_ps(wgt, lanes!(ch[2], j)));
        ws = _mm256_add_ps(ws, wgt);
        if t > 0 {
            far = _mm256_max_ps(far, wgt);
        }
    }
    let store = |v: __m256| -> [f32; GROUP] {
        let mut o = [0.0f32; GROUP];
        // SAFETY: `o` holds GROUP = 8 floats; the store is unaligned.
        unsafe { _mm256_storeu_ps(o.as_mut_ptr(), v) };
        o
    };
    let (a0, a1, a2, far) = (store(a0), store(a1), store(a2), store(far));
    Exact {
        acc: std::array::from_fn(|i| [a0[i], a1[i], a2[i]]),
        wsum: store(ws),
        reached: far.map(|f| f > 0.0),
    }
}

/// [`exact_offsets`] as index offsets into a `w`-wide image, and the largest of them.
struct ExactTaps {
    taps: Vec<(isize, f32)>,
    span: usize,
}

impl ExactTaps {
    fn new(offsets: &[(isize, isize, f32)], w: usize) -> ExactTaps {
        let taps: Vec<(isize, f32)> = offsets
            .iter()
            .map(|&(dx, dy, d)| (dy * w as isize + dx, d))
            .collect();
        let span = taps.iter().map(|t| t.0.unsigned_abs()).max().unwrap_or(0);
        ExactTaps { taps, span }
    }
}

/// The exact pass's sums for a group of pixels: colour x weight, weight, and whether a source
/// other than the pixel itself reached it.
#[derive(Default)]
struct Exact {
    acc: [[f32; 3]; GROUP],
    wsum: [f32; GROUP],
    reached: [bool; GROUP],
}

#[inline(always)]
fn exact_group_lanes(
    taps: &[(isize, f32)],
    limit: f32,
    at: usize,
    px: &Pixels,
    ch: [&[f32]; 3],
) -> Exact {
    let lanes = |v: &[f32], j: usize| -> [f32; GROUP] {
        v[j..j + GROUP].try_into().unwrap_or([0.0; GROUP])
    };
    // The receivers: minus their radius (the clamp's test), the radius a clamped source takes
    // (none at or above EXACT_RADIUS) and its weight.
    let pat = at - px.base;
    let neg_rc = lanes(&px.radius, pat).map(|r| -r);
    let rc = lanes(&px.exact, pat);
    let ic = lanes(&px.inv_area, pat);
    let (mut a0, mut a1, mut a2) = ([0.0f32; GROUP], [0.0f32; GROUP], [0.0f32; GROUP]);
    let mut ws = [0.0f32; GROUP];
    // The largest weight from a source other than the pixel (the first tap, at distance 0).
    let mut far = [0.0f32; GROUP];
    for (t, &(off, dist)) in taps.iter().enumerate() {
        if dist > limit {
            break;
        }
        let (j, pj) = (at.wrapping_add_signed(off), pat.wrapping_add_signed(off));
        let (ss, rs, is) = (
            lanes(&px.signed, pj),
            lanes(&px.exact, pj),
            lanes(&px.inv_area, pj),
        );
        let (c0, c1, c2) = (lanes(ch[0], j), lanes(ch[1], j), lanes(ch[2], j));
        for i in 0..GROUP {
            let clamp = ss[i] < neg_rc[i];
            let r = if clamp { rc[i] } else { rs[i] };
            let inv = if clamp { ic[i] } else { is[i] };
            let c = r + 0.5 - dist;
            let c = if c > 1.0 { 1.0 } else { c };
            let cover = if c > 0.0 { c } else { 0.0 };
            let wgt = cover * inv;
            a0[i] += wgt * c0[i];
            a1[i] += wgt * c1[i];
            a2[i] += wgt * c2[i];
            ws[i] += wgt;
            if t > 0 && wgt > far[i] {
                far[i] = wgt;
            }
        }
    }
    Exact {
        acc: std::array::from_fn(|i| [a0[i], a1[i], a2[i]]),
        wsum: ws,
        reached: far.map(|f| f > 0.0),
    }
}

/// The exact pass for pixel `(x, y)`: gather's sum over the sources within `limit` whose
/// (clamped) radius is below `EXACT_RADIUS`.
#[allow(clippy::too_many_arguments)]
fn exact_pixel(
    offsets: &[(isize, isize, f32)],
    limit: f32,
    x: usize,
    y: usize,
    w: usize,
    h: usize,
    px: &Pixels,
    depth: &[f32],
    ch: [&[f32]; 3],
    acc: &mut [f32; 3],
    wsum: &mut f32,
    reached: &mut bool,
) {
    let i = y * w + x;
    let b = px.base;
    let (dc, rc) = (depth[i], px.radius[i - b]);
    for &(dx, dy, dist) in offsets {
        if dist > limit {
            break;
        }
        let (sx, sy) = (x as isize + dx, y as isize + dy);
        if sx < 0 || sy < 0 || sx >= w as isize || sy >= h as isize {
            continue;
        }
        let j = sy as usize * w + sx as usize;
        let clamp = depth[j] < dc && px.radius[j - b] > rc;
        let (r, inv) = if clamp {
            (rc, px.inv_area[i - b])
        } else {
            (px.radius[j - b], px.inv_area[j - b])
        };
        if r >= EXACT_RADIUS {
            continue;
        }
        let cover = (r + 0.5 - dist).clamp(0.0, 1.0);
        if cover > 0.0 {
            let wgt = cover * inv;
            for c in 0..3 {
                acc[c] += wgt * ch[c][j];
            }
            *wsum += wgt;
            *reached |= dist > 0.0;
        }
    }
}

/// Per pixel of `rect`, whether every depth within the `(2r+1)^2` window around it (inside the
/// image) equals its own; `rect`-sized. Runs of equal depth along rows, then along columns.
fn flat_depth(depth: &[f32], w: usize, h: usize, rect: [usize; 4], r: usize) -> Vec<bool> {
    let [x0, y0, x1, y1] = rect;
    let rw = x1 - x0;
    let (ty0, ty1) = (y0.saturating_sub(r), (y1 + r).min(h));
    // Rows: the pixel's depth holds over [x - r, x + r] (clipped to the image). The runs are
    // counted within columns [c0, c1) only: a run cut there is still at least r long.
    let (c0, c1) = (x0.saturating_sub(r), (x1 + r).min(w));
    let mut rows = vec![false; rw * (ty1 - ty0)];
    rows.par_chunks_mut(rw.max(1)).enumerate().for_each_init(
        || (vec![0usize; c1 - c0], vec![0usize; c1 - c0]),
        |(left, rights), (i, o)| {
            let d = &depth[(ty0 + i) * w + c0..(ty0 + i) * w + c1];
            let n = d.len();
            // left[x - c0]: pixels before x (up to r) equal to d[x]; likewise right.
            for x in 1..n {
                left[x] = if d[x - 1] == d[x] { left[x - 1] + 1 } else { 0 };
            }
            let mut right = 0usize;
            for x in (0..n).rev() {
                right = if x + 1 < n && d[x + 1] == d[x] {
                    right + 1
                } else {
                    0
                };
                rights[x] = right;
            }
            for (k, o) in o.iter_mut().enumerate() {
                let x = x0 + k;
                *o = left[x - c0] >= r.min(x) && rights[x - c0] >= r.min(w - 1 - x);
            }
        },
    );
    // Columns: flat rows over [y - r, y + r] (clipped to the image) with the same depth. Per
    // row of `rows`, how many rows above (`up`) and below (`down`) are flat with the same
    // depth in an unbroken run, capped at r; in strips of columns, row after row.
    const STRIP: usize = 64;
    let th = ty1 - ty0;
    let mut out = vec![false; rw * (y1 - y0)];
    let strips: Vec<(usize, Vec<bool>)> = (0..rw.div_ceil(STRIP))
        .into_par_iter()
        .map(|sx| {
            let (c0, c1) = (sx * STRIP, ((sx + 1) * STRIP).min(rw));
            let sw = c1 - c0;
            let run = |t: usize, k: usize, prev: usize, count: u16| -> u16 {
                let same = rows[prev * rw + c0 + k]
                    && depth[(ty0 + prev) * w + x0 + c0 + k] == depth[(ty0 + t) * w + x0 + c0 + k];
                if same {
                    (count + 1).min(r as u16)
                } else {
                    0
                }
            };
            let mut up = vec![0u16; sw * th];
            for t in 1..th {
                for k in 0..sw {
                    up[t * sw + k] = run(t, k, t - 1, up[(t - 1) * sw + k]);
                }
            }
            let mut down = vec![0u16; sw * th];
            for t in (0..th.saturating_sub(1)).rev() {
                for k in 0..sw {
                    down[t * sw + k] = run(t, k, t + 1, down[(t + 1) * sw + k]);
                }
            }
            let mut o = vec![false; sw * (y1 - y0)];
            for y in y0..y1 {
                let t = y - ty0;
                let (need_up, need_down) = ((y - ty0).min(r), (ty1 - 1 - y).min(r));
                for k in 0..sw {
                    o[(y - y0) * sw + k] = rows[t * rw + c0 + k]
                        && up[t * sw + k] as usize >= need_up
                        && down[t * sw + k] as usize >= need_down;
                }
            }
            (c0, o)
        })
        .collect();
    for (c0, o) in strips {
        let sw = o.len() / (y1 - y0).max(1);
        for y in 0..y1 - y0 {
            out[y * rw + c0..y * rw + c0 + sw].copy_from_slice(&o[y * sw..(y + 1) * sw]);
        }
    }
    out
}

/// Running sums along rows `y0..y1` of the colour planes over columns `0..x1`, from column 0
/// whatever part is read (so a sum is the same whichever rows and columns were asked for).
struct RowPrefix {
    /// Per channel, per row, `x1 + 1` sums: the sum over `[a, b)` of row `y`, channel `c`
    /// is `sums[c][(y - y0) stride + b] - sums[c][.. + a]`.
    sums: [Vec<f32>; 3],
    y0: usize,
    stride: usize,
}

impl RowPrefix {
    fn new(ch: [&[f32]; 3], w: usize, [y0, y1]: [usize; 2], x1: usize) -> RowPrefix {
        let stride = x1 + 1;
        let n = (y1 - y0) * stride;
        let mut sums = [vec![0.0f32; n], vec![0.0f32; n], vec![0.0f32; n]];
        let [r, g, b] = &mut sums;
        // The three channels in one pass: three independent chains of additions.
        r.par_chunks_mut(stride)
            .zip(g.par_chunks_mut(stride))
            .zip(b.par_chunks_mut(stride))
            .enumerate()
            .for_each(|(i, ((r, g), b))| {
                let at = (y0 + i) * w;
                let src = [0, 1, 2].map(|c| &ch[c][at..at + x1]);
                let mut run = [0.0f32; 3];
                for x in 0..x1 {
                    run[0] += src[0][x];
                    run[1] += src[1][x];
                    run[2] += src[2][x];
                    r[x + 1] = run[0];
                    g[x + 1] = run[1];
                    b[x + 1] = run[2];
                }
            });
        RowPrefix { sums, y0, stride }
    }
}

/// Gather's ramped disk of radius `r` as full-weight row spans `(dy, half width)` and ramp
/// taps `(dx, dy, weight)`, with its total weight: the exact pass where every source within
/// reach shares the pixel's depth (as [`crate::gather::gather_smooth`] sums it).
struct FlatDisk {
    radius: f32,
    spans: Vec<(isize, usize)>,
    ramps: Vec<(isize, isize, f32)>,
    total: f32,
}

impl FlatDisk {
    fn new(r: f32) -> FlatDisk {
        let outer = r + 0.5;
        let (mut spans, mut ramps, mut total) = (Vec::new(), Vec::new(), 0.0f32);
        let reach = outer.floor() as isize;
        for dy in -reach..=reach {
            let dyf = dy as f32;
            // Full weight out to distance outer - 1, as a span; the ramp beyond.
            let inner = (outer - 1.0).max(0.0).powi(2) - dyf * dyf;
            let mut k = 0usize;
            if outer >= 1.0 && inner >= 0.0 {
                let f = inner.sqrt().floor() as usize;
                spans.push((dy, f));
                total += (2 * f + 1) as f32;
                k = f + 1;
            }
            loop {
                let wt = (outer - ((k * k) as f32 + dyf * dyf).sqrt()).min(1.0);
                if wt <= 0.0 {
                    break;
                }
                for dx in if k == 0 {
                    vec![0]
                } else {
                    vec![-(k as isize), k as isize]
                } {
                    ramps.push((dx, dy, wt));
                    total += wt;
                }
                k += 1;
            }
        }
        FlatDisk {
            radius: r,
            spans,
            ramps,
            total,
        }
    }

    /// The exact pass's sums for the `GROUP` pixels from `(x0, y)` (the disk inside the image),
    /// gather's weight `1 / max(r, 0.5)^2` per unit of cover: the group's lanes side by side.
    #[allow(clippy::too_many_arguments)]
    fn sum_group(
        &self,
        prefix: &RowPrefix,
        ch: [&[f32]; 3],
        w: usize,
        x0: usize,
        y: usize,
        inv: f32,
    ) -> Exact {
        let mut a = [[0.0f32; GROUP]; 3];
        for &(dy, f) in &self.spans {
            let base = ((y as isize + dy) as usize - prefix.y0) * prefix.stride + x0;
            for (a, sums) in a.iter_mut().zip(&prefix.sums) {
                let hi: &[f32; GROUP] = sums[base + f + 1..base + f + 1 + GROUP]
                    .try_into()
                    .unwrap_or(&[0.0; GROUP]);
                let lo: &[f32; GROUP] = sums[base - f..base - f + GROUP]
                    .try_into()
                    .unwrap_or(&[0.0; GROUP]);
                for i in 0..GROUP {
                    a[i] += hi[i] - lo[i];
                }
            }
        }
        for &(dx, dy, wt) in &self.ramps {
            let j = ((y as isize + dy) as usize * w + x0).wrapping_add_signed(dx);
            for c in 0..3 {
                let v: &[f32; GROUP] = ch[c][j..j + GROUP].try_into().unwrap_or(&[0.0; GROUP]);
                for i in 0..GROUP {
                    a[c][i] += wt * v[i];
                }
            }
        }
        Exact {
            acc: std::array::from_fn(|i| [0, 1, 2].map(|c| a[c][i] * inv)),
            wsum: [self.total * inv; GROUP],
            reached: [self.radius > 0.5; GROUP],
        }
    }
}

/// The disks of the flat groups met so far, by radius (a frame has few distinct ones).
#[derive(Default)]
struct FlatDisks(Vec<(f32, FlatDisk)>);

impl FlatDisks {
    fn get(&mut self, r: f32) -> &FlatDisk {
        let i = match self.0.iter().position(|d| d.0 == r) {
            Some(i) => i,
            None => {
                if self.0.len() >= 64 {
                    self.0.clear();
                }
                self.0.push((r, FlatDisk::new(r)));
                self.0.len() - 1
            }
        };
        &self.0[i].1
    }
}

/// Maximum of `v` (a `w` x `h` image by pixel index, values >= 0) over the `(2r+1)^2` window around each pixel
/// of `rect` (`[x0, y0, x1, y1)`), rows then columns; the result is `rect`-sized. Each pass
/// takes the maximum of windows doubling in length (1, 2, 4 ... the largest power of two
/// `p <= 2r + 1`), and a window of `2r + 1` is then the maximum of two of length `p`: a few
/// element-wise maxima per pixel, which vectorise.
fn window_max(
    v: impl Fn(usize) -> f32 + Sync,
    w: usize,
    h: usize,
    rect: [usize; 4],
    r: usize,
) -> Vec<f32> {
    let [x0, y0, x1, y1] = rect;
    let (rw, rh) = (x1 - x0, y1 - y0);
    let len = 2 * r + 1;
    // Rows y0 - r .. y1 + r (zero outside the image), each the maximum over its row's window.
    let mut tmp = vec![0.0f32; rw * (rh + 2 * r)];
    tmp.par_chunks_mut(rw.max(1)).enumerate().for_each_init(
        Vec::new,
        |buf: &mut Vec<f32>, (t, o)| {
            let Some(y) = (y0 + t).checked_sub(r).filter(|&y| y < h) else {
                return;
            };
            // Source columns x0 - r .. x1 + r, zero outside the image.
            buf.clear();
            buf.extend((0..rw + 2 * r).map(|i| {
                (x0 + i)
                    .checked_sub(r)
                    .filter(|&x| x < w)
                    .map_or(0.0, |x| v(y * w + x))
            }));
            let p = doubling_max(buf, len, |m, step| {
                for i in 0..m.len() - step {
                    m[i] = if m[i + step] > m[i] {
                        m[i + step]
                    } else {
                        m[i]
                    };
                }
            });
            for (i, o) in o.iter_mut().enumerate() {
                let (a, b) = (buf[i], buf[i + len - p]);
                *o = if a > b { a } else { b };
            }
        },
    );
    // Columns: the same over whole rows of `tmp`, in strips of columns.
    const STRIP: usize = 64;
    let mut out = vec![0.0f32; rw * rh];
    let strips: Vec<(usize, Vec<f32>)> = (0..rw.div_ceil(STRIP))
        .into_par_iter()
        .map(|sx| {
            let (c0, c1) = (sx * STRIP, ((sx + 1) * STRIP).min(rw));
            let sw = c1 - c0;
            let mut m: Vec<f32> = tmp
                .chunks(rw.max(1))
                .flat_map(|row| row[c0..c1].iter().copied())
                .collect();
            let p = doubling_max(&mut m, len, |m, step| {
                let n = m.len() - step * sw;
                for i in 0..n {
                    let b = m[i + step * sw];
                    m[i] = if b > m[i] { b } else { m[i] };
                }
            });
            let mut o = vec![0.0f32; sw * rh];
            for y in 0..rh {
                let (a, b) = (&m[y * sw..(y + 1) * sw], &m[(y + len - p) * sw..][..sw]);
                for ((o, &a), &b) in o[y * sw..(y + 1) * sw].iter_mut().zip(a).zip(b) {
                    *o = if a > b { a } else { b };
                }
            }
            (c0, o)
        })
        .collect();
    for (c0, o) in strips {
        let sw = o.len() / rh.max(1);
        for y in 0..rh {
            out[y * rw + c0..y * rw + c0 + sw].copy_from_slice(&o[y * sw..(y + 1) * sw]);
        }
    }
    out
}

/// Runs `pass(m, step)` (which sets element `i` to the maximum of `i` and `i + step`, in
/// `m`'s own units) for steps 1, 2, 4 ... while the window stays within `len`; returns the
/// window length reached, the largest power of two at most `len`.
fn doubling_max(m: &mut [f32], len: usize, pass: impl Fn(&mut [f32], usize)) -> usize {
    let mut p = 1;
    while 2 * p <= len {
        pass(m, p);
        p *= 2;
    }
    p
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The O(1) sliding maximum equals the brute-force window maximum, inner rectangles and
    /// edges alike.
    #[test]
    fn window_max_is_the_brute_force_maximum() {
        let (w, h) = (23usize, 17usize);
        let v: Vec<f32> = (0..w * h)
            .map(|i| ((i * 7919 + 13) % 101) as f32 * 0.1)
            .collect();
        for r in [0usize, 1, 3, 7, 30] {
            for rect in [[0, 0, w, h], [3, 2, 19, 15], [10, 16, 11, 17], [0, 5, 5, 6]] {
                let got = window_max(|i| v[i], w, h, rect, r);
                let [x0, y0, x1, y1] = rect;
                for y in y0..y1 {
                    for x in x0..x1 {
                        let mut want = 0.0f32;
                        for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                            for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                                want = want.max(v[yy * w + xx]);
                            }
                        }
                        assert_eq!(
                            got[(y - y0) * (x1 - x0) + x - x0],
                            want,
                            "r {r} {rect:?} ({x},{y})"
                        );
                    }
                }
            }
        }
    }
    /// A row's runs hold exactly the pixels `contains` accepts, for annuli, disks, rectangles
    /// and centres on pixel edges.
    #[test]
    fn row_runs_are_the_contained_pixels() {
        let rects = [(0, 0, 64, 48), (5, 3, 40, 30), (20, 20, 21, 21)];
        let annuli = [
            ([30.0f32, 22.0f32], 6.0f32, 18.0f32),
            ([30.5, 22.5], -1.0, f32::INFINITY),
            ([0.0, 0.0], 10.0, 10.5),
            ([64.0, 48.0], 0.0, 30.0),
            ([17.0, 9.0], 3.0, 4.0),
            ([-20.0, 60.0], 5.0, 1e9),
        ];
        for (x0, y0, x1, y1) in rects {
            for (centre, inner, outer) in annuli {
                let r = Region {
                    x0,
                    y0,
                    x1,
                    y1,
                    centre,
                    inner,
                    outer,
                };
                for y in 0..50 {
                    let runs = r.row_runs(y);
                    for x in 0..66 {
                        let inside = runs.iter().any(|&(a, b)| (a..b).contains(&x));
                        assert_eq!(inside, r.contains(x, y), "{r:?} ({x},{y}) {runs:?}");
                    }
                }
            }
        }
    }

    /// The run-length flatness test equals the brute-force one: every depth within the window
    /// (clipped to the image) equal to the pixel's.
    #[test]
    fn flat_depth_is_the_brute_force_test() {
        let (w, h) = (70usize, 41usize);
        // Patches of equal depth of several sizes, and a ramp.
        let depth: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if x > 50 {
                    0.01 * (x + y) as f32
                } else {
                    ((x / 9 + 3 * (y / 6)) % 4) as f32
                }
            })
            .collect();
        for r in [0usize, 1, 3, 7] {
            for rect in [[0, 0, w, h], [5, 3, 66, 40], [64, 0, 70, 2], [0, 39, 3, 41]] {
                let got = flat_depth(&depth, w, h, rect, r);
                let [x0, y0, x1, y1] = rect;
                for y in y0..y1 {
                    for x in x0..x1 {
                        let d = depth[y * w + x];
                        let want = (y.saturating_sub(r)..(y + r + 1).min(h)).all(|yy| {
                            (x.saturating_sub(r)..(x + r + 1).min(w))
                                .all(|xx| depth[yy * w + xx] == d)
                        });
                        assert_eq!(
                            got[(y - y0) * (x1 - x0) + x - x0],
                            want,
                            "r {r} {rect:?} ({x},{y})"
                        );
                    }
                }
            }
        }
    }

    use crate::gather::gather;
    use crate::metrics::psnr;
    use dioptra_core::{DepthMap, Plane};

    fn noise(i: usize, c: usize) -> f32 {
        let x = (i * 3 + c) as u32;
        (x.wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32
    }

    /// A smooth texture (blurred noise would do; sums of sines are cheaper) and a depth map.
    fn rgbd(w: usize, h: usize, depth: impl Fn(usize, usize) -> f32) -> Rgbd {
        let plane = |c: usize| {
            Plane::from_vec(
                w,
                h,
                (0..w * h)
                    .map(|i| {
                        let (x, y) = ((i % w) as f32, (i / w) as f32);
                        0.5 + 0.2 * (0.21 * x + 1.3 * c as f32).sin() * (0.17 * y).cos()
                            + 0.1 * noise(i, c)
                    })
                    .collect(),
            )
            .unwrap()
        };
        let color = RgbImage::from_planes(plane(0), plane(1), plane(2)).unwrap();
        let d: Vec<f32> = (0..w * h).map(|i| depth(i % w, i / w)).collect();
        Rgbd::new(
            color,
            DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap(),
        )
        .unwrap()
    }

    fn eye(fov: f32) -> EyeModel {
        EyeModel {
            fov_horizontal_deg: fov,
            ..EyeModel::default()
        }
    }

    fn max_diff(a: &RgbImage, b: &RgbImage) -> f32 {
        (0..3)
            .flat_map(|c| {
                a.channels[c]
                    .data()
                    .iter()
                    .zip(b.channels[c].data())
                    .map(|(x, y)| (x - y).abs())
            })
            .fold(0.0, f32::max)
    }

    #[test]
    fn band_edges_and_radius_correction() {
        let e = band_edges();
        assert_eq!(e[0], EXACT_RADIUS);
        assert!((e[2] - 2.0 * EXACT_RADIUS).abs() < 1e-5);
        assert_eq!(band_of(EXACT_RADIUS, &e), 0);
        assert_eq!(band_of(e[3], &e), 3);
        assert_eq!(band_of(e[3] - 1e-3, &e), 2);
        assert_eq!(band_of(1e9, &e), BANDS - 1);
        assert!(e[BANDS] > MAX_RADIUS);
        // The radius that keeps gather's second moment: at full resolution a 2 x 2 cell's
        // disk grows a little (the cell's spread), on a coarser grid it shrinks (the read-back's).
        for r in [3.0f32, 4.0, 5.9] {
            let rho = spread_radius(r, 2.0, 1.0);
            assert!(rho > r && rho < 1.1 * r, "{r} -> {rho}");
            assert!((ramp_disk_m2(rho) - ramp_disk_m2(r) - 0.25).abs() < 1e-3);
        }
        for s in [2.0f32, 4.0, 16.0] {
            for f in [3.0f32, 4.5, 5.99] {
                let rho = spread_radius(f * s, s, s);
                let lhs = ramp_disk_m2(rho) * s * s + s * s / 6.0;
                let rhs = ramp_disk_m2(f * s) + (s * s - 1.0) / 12.0;
                assert!(
                    (lhs - rhs).abs() < 1e-3 * rhs,
                    "s {s} r {}: {lhs} vs {rhs}",
                    f * s
                );
                assert!(rho < f && rho > 0.9 * f, "{rho} texels for {f}");
            }
        }
    }

    #[test]
    fn small_blur_is_gather_exactly() {
        // Every radius below EXACT_RADIUS: only the exact pass runs, and it is gather's sum.
        let (w, h) = (40, 36);
        let e = eye(20.0).with_width(w as u32);
        let input = rgbd(w, h, |x, y| {
            if x + y < 40 {
                2.0
            } else {
                0.3 + 0.02 * x as f32
            }
        });
        for q in [0.3f32, 1.0, 2.5] {
            let s = Setup::new(&input, Diopters(q), &e).unwrap();
            assert_eq!(s.top, 0, "focus {q}");
            let a = gather(&input, Diopters(q), &e).unwrap();
            let b = pyramid(&input, Diopters(q), &e).unwrap();
            assert!(max_diff(&a, &b) < 1e-6, "focus {q}: {}", max_diff(&a, &b));
        }
    }

    #[test]
    fn in_focus_passes_through() {
        let (w, h) = (30, 20);
        let input = rgbd(w, h, |_, _| 1.0);
        let out = pyramid(&input, Diopters(1.0), &eye(20.0)).unwrap();
        assert_eq!(out, input.color);
    }

    #[test]
    fn large_blur_of_a_plane_is_close_to_gather() {
        // A fronto-parallel plane blurred by 6 to 40 px radius: the levels alone.
        let (w, h) = (96, 80);
        for (fov, q) in [(1.0f32, 1.55), (1.0, 2.4), (1.0, 4.6)] {
            let e = eye(fov).with_width(w as u32);
            let input = rgbd(w, h, |_, _| 1.0);
            let s = Setup::new(&input, Diopters(q), &e).unwrap();
            assert!(s.top >= 1, "fov {fov}: no level");
            let a = gather(&input, Diopters(q), &e).unwrap();
            let b = pyramid(&input, Diopters(q), &e).unwrap();
            let p = psnr(&b, &a, None).unwrap();
            eprintln!(
                "plane at radius {:.1} px: {p:.1} dB against gather",
                s.signed(1.0).abs()
            );
            assert!(p > 40.0, "fov {fov} focus {q}: {p:.1} dB");
        }
    }

    #[test]
    fn occlusion_rule_holds_at_panel_blur() {
        // A sharp near square over a far textured wall blurred by ~15 px, and the reverse.
        let (w, h) = (96, 96);
        let e = eye(3.0).with_width(w as u32);
        let square = |x: usize, y: usize| (30..66).contains(&x) && (30..66).contains(&y);
        let input = rgbd(w, h, |x, y| if square(x, y) { 3.0 } else { 0.5 });
        let sharp_near = pyramid(&input, Diopters(3.0), &e).unwrap();
        // The sharp square's interior is untouched by the blurred wall.
        for y in 32..64 {
            for x in 32..64 {
                let i = y * w + x;
                for c in 0..3 {
                    let (a, b) = (
                        sharp_near.channels[c].data()[i],
                        input.color.channels[c].data()[i],
                    );
                    assert!((a - b).abs() < 1e-6, "({x},{y}): {a} vs {b}");
                }
            }
        }
        // Against gather, both ways round.
        for q in [3.0f32, 0.5] {
            let a = gather(&input, Diopters(q), &e).unwrap();
            let b = pyramid(&input, Diopters(q), &e).unwrap();
            let p = psnr(&b, &a, None).unwrap();
            eprintln!("square at focus {q}: {p:.1} dB against gather");
            assert!(p > 35.0, "focus {q}: {p:.1} dB");
        }
    }

    #[test]
    fn region_matches_the_full_render_inside_and_is_black_outside() {
        let (w, h) = (64, 48);
        let e = eye(3.0).with_width(w as u32);
        let input = rgbd(w, h, |x, _| if x < 30 { 2.5 } else { 0.4 });
        let q = Diopters(1.0);
        let full = pyramid(&input, q, &e).unwrap();
        let region = Region {
            x0: 10,
            y0: 5,
            x1: 50,
            y1: 40,
            centre: [30.0, 22.0],
            inner: 6.0,
            outer: 18.0,
        };
        let part = render_region(&input, q, &e, &region).unwrap();
        let mut inside = 0;
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                for c in 0..3 {
                    let (a, b) = (part.channels[c].data()[i], full.channels[c].data()[i]);
                    if region.contains(x, y) {
                        assert!((a - b).abs() < 1e-5, "({x},{y}): {a} vs {b}");
                    } else {
                        assert_eq!(a, 0.0, "({x},{y})");
                    }
                }
                inside += region.contains(x, y) as usize;
            }
        }
        assert!(inside > 500, "{inside} pixels inside");
    }

    #[test]
    fn deterministic() {
        let (w, h) = (50, 40);
        let e = eye(2.0).with_width(w as u32);
        let input = rgbd(w, h, |x, y| 0.2 + 0.05 * ((x * 7 + y * 3) % 50) as f32);
        let a = pyramid(&input, Diopters(1.0), &e).unwrap();
        let b = pyramid(&input, Diopters(1.0), &e).unwrap();
        assert_eq!(a, b);
    }
}
