//! Foveated sampling (Thumuluri & Sharma 2020, sec. 4.1-4.2): log-polar sampling masks
//! (eq. 3-8) and inverse-distance interpolation of the unsampled pixels from the four
//! nearest samples (eq. 9); for a light field, the samples of every view reprojected into
//! each view first ([`interpolate_across_views`]).

use crate::common::eye_for;
use crate::error::{invalid, mismatch, RenderError};
use crate::views::SAME_SURFACE_D;
use dioptra_core::{EyeModel, Plane, RgbImage};
use rayon::prelude::*;

/// Pixels per side of the cells the interpolation buckets samples in: the CPU's, the GPU
/// host code's and (through `gpu::context::shared_wgsl`) shaders/foveate.wgsl's.
pub(crate) const FOV_CELL: usize = 8;

/// The smallest log-buffer scale S a mask takes (a W/S x W/S buffer).
pub const MIN_SCALE: f32 = 0.05;

/// Parameters of a log-polar mask.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LogPolar {
    /// Fovea centre (gaze), pixels.
    pub centre: [f32; 2],
    /// Log-buffer scale S: the buffer is W/S x W/S (S = 2 samples about 10 %, S = 4 about 4 %).
    pub scale: f32,
    /// Kernel parameter K (eq. 5-6): K > 1 packs more samples near the fovea.
    pub kernel: f32,
    /// Per-view radial offset r' (eq. 5-6); 1 for the plain mapping.
    pub r_offset: f32,
    /// Per-view angular offset theta' in radians (eq. 5-6).
    pub theta_offset: f32,
}

impl LogPolar {
    pub fn centred(width: usize, height: usize, scale: f32) -> LogPolar {
        LogPolar {
            centre: [width as f32 * 0.5, height as f32 * 0.5],
            scale,
            kernel: 1.0,
            r_offset: 1.0,
            theta_offset: 0.0,
        }
    }
}

/// The binary sampling mask (1 = sampled) for a `width` x `height` image, and the fraction of
/// pixels it samples.
pub fn log_polar_mask(
    width: usize,
    height: usize,
    p: &LogPolar,
) -> Result<(Plane, f64), RenderError> {
    let (rho, dir) = log_polar_tables(width, height, p)?;
    let mut mask = Plane::new(width, height, 0.0);
    for &rho in &rho {
        for &[cos, sin] in &dir {
            let x = (p.centre[0] + rho * cos).floor();
            let y = (p.centre[1] + rho * sin).floor();
            if x >= 0.0 && y >= 0.0 && (x as usize) < width && (y as usize) < height {
                mask.data_mut()[y as usize * width + x as usize] = 1.0;
            }
        }
    }
    let fraction =
        mask.data().iter().filter(|&&v| v > 0.5).count() as f64 / (width * height) as f64;
    Ok((mask, fraction))
}

/// The log-polar sampling pattern of a `width` x `height` image, after the parameters'
/// checks: rho (pixels from the fovea) per ring and (cos, sin) per angle, in f32. The one
/// definition the CPU's mask and the GPU's mask kernel both sample (the GPU takes the tables
/// so that its reduced-precision transcendentals never move a sample).
pub(crate) fn log_polar_tables(
    width: usize,
    height: usize,
    p: &LogPolar,
) -> Result<(Vec<f32>, Vec<[f32; 2]>), RenderError> {
    if width == 0 || height == 0 {
        return Err(invalid("mask size is empty"));
    }
    let finite = [
        p.centre[0],
        p.centre[1],
        p.scale,
        p.kernel,
        p.r_offset,
        p.theta_offset,
    ]
    .iter()
    .all(|v| v.is_finite());
    if !finite || p.scale < MIN_SCALE || p.kernel <= 0.0 || p.r_offset <= 0.0 {
        return Err(invalid(format!(
            "log-polar parameters {p:?} are invalid: need finite values, S >= {MIN_SCALE}, K > 0, r' > 0"
        )));
    }
    // L: the farthest image corner from the fovea.
    let corners = [
        [0.0, 0.0],
        [width as f32, 0.0],
        [0.0, height as f32],
        [width as f32, height as f32],
    ];
    let l = corners
        .iter()
        .map(|c| (c[0] - p.centre[0]).hypot(c[1] - p.centre[1]))
        .fold(1.0f32, f32::max);
    // R rings and as many angles (Theta = R).
    let rr = (width as f32 / p.scale).round().clamp(1.0, 1e5) as usize;
    // eq. 5-6: rho = r' exp(r^(1/K) log L / R)
    let rho = (0..rr)
        .map(|r| p.r_offset * ((r as f32).powf(1.0 / p.kernel) * l.ln() / rr as f32).exp())
        .collect();
    let dir = (0..rr)
        .map(|t| {
            let a = std::f32::consts::TAU * t as f32 / rr as f32 + p.theta_offset;
            [a.cos(), a.sin()]
        })
        .collect();
    Ok((rho, dir))
}

/// Keeps the masked pixels of `img` and fills every other pixel by inverse-distance weighting
/// of its four nearest sampled pixels (eq. 9).
pub fn interpolate(img: &RgbImage, mask: &Plane) -> Result<RgbImage, RenderError> {
    let (w, h) = (img.width(), img.height());
    if (mask.width(), mask.height()) != (w, h) {
        return Err(mismatch(format!(
            "mask is {}x{} but the image is {w}x{h}",
            mask.width(),
            mask.height()
        )));
    }
    // Samples bucketed on a coarse grid so the nearest four are found by growing rings.
    const CELL: usize = FOV_CELL;
    let (gw, gh) = (w.div_ceil(CELL), h.div_ceil(CELL));
    let mut grid: Vec<Vec<u32>> = vec![Vec::new(); gw * gh];
    for (i, &m) in mask.data().iter().enumerate() {
        if m > 0.5 {
            grid[(i / w / CELL) * gw + (i % w) / CELL].push(i as u32);
        }
    }
    if grid.iter().all(|c| c.is_empty()) {
        return Err(invalid("the mask samples no pixel"));
    }
    let ch = img.channels.each_ref().map(|p| p.data());
    let out: Vec<[f32; 3]> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            if mask.data()[i] > 0.5 {
                return [ch[0][i], ch[1][i], ch[2][i]];
            }
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            let (cx, cy) = (x / CELL as isize, y / CELL as isize);
            let mut best: [(f32, u32); 4] = [(f32::INFINITY, 0); 4];
            for ring in 0..(gw.max(gh) as isize + 1) {
                // Every sample in this ring or beyond is at least (ring - 1) * CELL away.
                if best[3].0.is_finite() && ((ring - 1).max(0) * CELL as isize) as f32 > best[3].0 {
                    break;
                }
                for gy in (cy - ring)..=(cy + ring) {
                    for gx in (cx - ring)..=(cx + ring) {
                        let on_ring = (gy - cy).abs() == ring || (gx - cx).abs() == ring;
                        if !on_ring || gx < 0 || gy < 0 || gx >= gw as isize || gy >= gh as isize {
                            continue;
                        }
                        for &s in &grid[gy as usize * gw + gx as usize] {
                            let (sx, sy) = ((s as usize % w) as f32, (s as usize / w) as f32);
                            let d = (sx - x as f32).hypot(sy - y as f32);
                            if d < best[3].0 {
                                best[3] = (d, s);
                                best.sort_by(|a, b| a.0.total_cmp(&b.0));
                            }
                        }
                    }
                }
            }
            let mut acc = [0.0f32; 3];
            let mut wsum = 0.0f32;
            for &(d, s) in best.iter().filter(|b| b.0.is_finite()) {
                let wt = 1.0 / d;
                for c in 0..3 {
                    acc[c] += wt * ch[c][s as usize];
                }
                wsum += wt;
            }
            acc.map(|v| v / wsum)
        })
        .collect();
    Ok(RgbImage::from_interleaved(w, h, out.as_flattened())?)
}

/// One view of a foveated light field: where it was seen from (metres on the lens plane, as
/// [`crate::views::light_field_positions`]), its colour and depth (diopters) and which
/// pixels it sampled (1); only the sampled pixels are read.
#[derive(Debug, Clone, Copy)]
pub struct SampledView<'a> {
    pub position: [f32; 2],
    pub image: &'a RgbImage,
    pub depth: &'a Plane,
    pub mask: &'a Plane,
}

/// A sampled ray: its pixel centre, diopters and colour.
type Sample = ([f32; 2], f32, [f32; 3]);

/// Sub-pixel spread (pixels) of the weight a reprojected sample gets by its distance from
/// the pixel centre it lands in: the nearest landings dominate.
const REPROJECT_SIGMA_PX: f32 = 0.2;

/// Every unsampled pixel of every view filled from the samples of all views: each view's
/// samples are reprojected into the others by their depth (the light field's parallax,
/// `eye`'s pixel pitch), the nearest surface landing on a pixel wins and its samples are
/// averaged by how close they land to the pixel centre; what no sample reaches is
/// interpolated within the view ([`interpolate`]). A view's own samples are kept exactly.
/// FVS's per-view offsets make the views sample different rays, so near the gaze the union
/// is far denser than one view's samples.
pub fn interpolate_across_views(
    views: &[SampledView],
    eye: &EyeModel,
) -> Result<Vec<RgbImage>, RenderError> {
    let first = views
        .first()
        .ok_or_else(|| invalid("no views to interpolate"))?;
    let (w, h) = (first.image.width(), first.image.height());
    for v in views {
        let sizes = [
            (v.image.width(), v.image.height()),
            (v.depth.width(), v.depth.height()),
            (v.mask.width(), v.mask.height()),
        ];
        if sizes.iter().any(|&s| s != (w, h)) {
            return Err(mismatch(format!(
                "every view's image, depth and mask must be {w}x{h}, got {sizes:?}"
            )));
        }
        if !v.position.iter().all(|p| p.is_finite()) {
            return Err(invalid("view positions must be finite"));
        }
    }
    let pitch = eye_for(eye, w)?.pixel_pitch_tan();
    // Each view's samples.
    let samples: Vec<Vec<Sample>> = views
        .iter()
        .map(|v| {
            let ch = v.image.channels.each_ref().map(|p| p.data());
            (0..w * h)
                .filter(|&i| v.mask.data()[i] > 0.5 && v.depth.data()[i].is_finite())
                .map(|i| {
                    let centre = [(i % w) as f32 + 0.5, (i / w) as f32 + 0.5];
                    (centre, v.depth.data()[i], [ch[0][i], ch[1][i], ch[2][i]])
                })
                .collect()
        })
        .collect();
    let weight_scale = 1.0 / (2.0 * REPROJECT_SIGMA_PX * REPROJECT_SIGMA_PX);
    views
        .par_iter()
        .map(|t| {
            let n = w * h;
            // Parallax per diopter, pixels, from each view to this one (the warp's sign).
            let shifts: Vec<[f32; 2]> = views
                .iter()
                .map(|u| {
                    [
                        -(t.position[0] - u.position[0]) / pitch,
                        -(t.position[1] - u.position[1]) / pitch,
                    ]
                })
                .collect();
            let land = |centre: [f32; 2], d: f32, shift: [f32; 2]| {
                let (x, y) = (centre[0] + shift[0] * d, centre[1] + shift[1] * d);
                let inside = x >= 0.0 && y >= 0.0 && x < w as f32 && y < h as f32;
                inside.then(|| {
                    let (fx, fy) = (x.fract() - 0.5, y.fract() - 0.5);
                    (y as usize * w + x as usize, fx * fx + fy * fy)
                })
            };
            let mut nearest = vec![f32::NEG_INFINITY; n];
            for (ss, &shift) in samples.iter().zip(&shifts) {
                for &(c, d, _) in ss {
                    if let Some((j, _)) = land(c, d, shift) {
                        nearest[j] = nearest[j].max(d);
                    }
                }
            }
            let mut acc = vec![[0.0f32; 4]; n];
            for (ss, &shift) in samples.iter().zip(&shifts) {
                for &(c, d, rgb) in ss {
                    if let Some((j, dist2)) = land(c, d, shift) {
                        if d >= nearest[j] - SAME_SURFACE_D {
                            let wt = (-dist2 * weight_scale).exp();
                            let a = &mut acc[j];
                            for k in 0..3 {
                                a[k] += wt * rgb[k];
                            }
                            a[3] += wt;
                        }
                    }
                }
            }
            let own = t.image.channels.each_ref().map(|p| p.data());
            let mut mask = Plane::new(w, h, 0.0);
            let colour: Vec<[f32; 3]> = (0..n)
                .map(|j| {
                    if t.mask.data()[j] > 0.5 {
                        mask.data_mut()[j] = 1.0;
                        [own[0][j], own[1][j], own[2][j]]
                    } else if acc[j][3] > 0.0 {
                        mask.data_mut()[j] = 1.0;
                        let a = acc[j];
                        [a[0] / a[3], a[1] / a[3], a[2] / a[3]]
                    } else {
                        [0.0; 3]
                    }
                })
                .collect();
            interpolate(
                &RgbImage::from_interleaved(w, h, colour.as_flattened())?,
                &mask,
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn density_falls_with_eccentricity_and_scale() {
        let (w, h) = (128, 128);
        let (m2, f2) = log_polar_mask(w, h, &LogPolar::centred(w, h, 2.0)).unwrap();
        let (_, f4) = log_polar_mask(w, h, &LogPolar::centred(w, h, 4.0)).unwrap();
        assert!(f4 < f2 && f2 < 0.5 && f4 > 0.005, "S=2 {f2}, S=4 {f4}");
        let count = |x0: usize, y0: usize| {
            (0..16)
                .flat_map(|y| (0..16).map(move |x| (x, y)))
                .filter(|&(x, y)| m2.data()[(y0 + y) * w + x0 + x] > 0.5)
                .count()
        };
        assert!(
            count(56, 56) > 4 * count(0, 0),
            "fovea {} periphery {}",
            count(56, 56),
            count(0, 0)
        );
        // Per-view offsets move the samples but keep the density.
        let moved = LogPolar {
            theta_offset: 0.3,
            r_offset: 1.1,
            ..LogPolar::centred(w, h, 2.0)
        };
        let (m3, f3) = log_polar_mask(w, h, &moved).unwrap();
        assert_ne!(m2, m3);
        assert!((f3 - f2).abs() < 0.3 * f2, "{f2} {f3}");
        assert!(log_polar_mask(
            w,
            h,
            &LogPolar {
                kernel: 0.0,
                ..moved
            }
        )
        .is_err());
    }

    #[test]
    fn interpolation_keeps_samples_and_is_exact_on_constants() {
        let (w, h) = (64, 48);
        let img = RgbImage::new(w, h, [0.2, 0.4, 0.6]);
        let (mask, _) = log_polar_mask(w, h, &LogPolar::centred(w, h, 4.0)).unwrap();
        let out = interpolate(&img, &mask).unwrap();
        for c in 0..3 {
            assert!(out.channels[c]
                .data()
                .iter()
                .zip(img.channels[c].data())
                .all(|(a, b)| (a - b).abs() < 1e-6));
        }
        // A ramp is reproduced exactly at samples and within its range elsewhere.
        let ramp: Vec<f32> = (0..w * h * 3)
            .map(|i| ((i / 3) % w) as f32 / w as f32)
            .collect();
        let img = RgbImage::from_interleaved(w, h, &ramp).unwrap();
        let out = interpolate(&img, &mask).unwrap();
        for i in 0..w * h {
            let v = out.channels[0].data()[i];
            assert!((0.0..=1.0).contains(&v));
            if mask.data()[i] > 0.5 {
                assert_eq!(v, img.channels[0].data()[i]);
            }
        }
        assert!(interpolate(&img, &Plane::new(w, h, 0.0)).is_err());
    }

    /// A test scene's true 9 x 9 light field (96 px, over 1 cm), each view sampled at S = 2.5
    /// with its own offsets: filling across views recovers the fovea far better than within
    /// each view, and keeps every view's own samples.
    #[test]
    fn filling_across_views_beats_filling_within_each_view() {
        use crate::metrics::{psnr, FovealRegion};
        use dioptra_sim::scene::{render_light_field, Camera, Scene, Split};
        let eye = EyeModel::default();
        let size = 96;
        let truth = render_light_field(
            &Scene::generate(Split::Test.seed(4)),
            &Camera::square(eye, size),
            9,
            0.01,
            1,
        )
        .unwrap();
        let centre = [48.0, 40.0];
        let masks: Vec<Plane> = (0..truth.len())
            .map(|k| {
                let p = LogPolar {
                    centre,
                    r_offset: 1.0 + 0.07 * k as f32,
                    theta_offset: 0.13 * k as f32,
                    ..LogPolar::centred(size, size, 2.5)
                };
                log_polar_mask(size, size, &p).unwrap().0
            })
            .collect();
        let views: Vec<SampledView> = truth
            .iter()
            .zip(&masks)
            .map(|(v, mask)| SampledView {
                position: v.position,
                image: &v.color,
                depth: v.depth.plane(),
                mask,
            })
            .collect();
        let across = interpolate_across_views(&views, &eye).unwrap();
        let fovea = FovealRegion::Fovea.mask(size, size, centre);
        // Mean squared errors in the fovea (peak 1), summed over the views.
        let mse =
            |a: &RgbImage, b: &RgbImage| 10f64.powf(-psnr(a, b, Some(&fovea)).unwrap() / 10.0);
        let (mut within_sum, mut across_sum, mut worse) = (0.0, 0.0, 0);
        for ((v, mask), filled) in views.iter().zip(&masks).zip(&across) {
            let (e_within, e_across) = (
                mse(&interpolate(v.image, mask).unwrap(), v.image),
                mse(filled, v.image),
            );
            within_sum += e_within;
            across_sum += e_across;
            worse += usize::from(e_across > e_within);
            for i in (0..size * size).filter(|&i| mask.data()[i] > 0.5) {
                for c in 0..3 {
                    assert_eq!(filled.channels[c].data()[i], v.image.channels[c].data()[i]);
                }
            }
        }
        let gain = 10.0 * (within_sum / across_sum).log10();
        assert!(
            gain > 3.0 && worse == 0,
            "fovea gain {gain:.2} dB, {worse} views worse"
        );
        // Sizes that disagree are refused.
        let small = Plane::new(8, 8, 1.0);
        let bad = SampledView {
            mask: &small,
            ..views[0]
        };
        assert!(interpolate_across_views(&[views[0], bad], &eye).is_err());
        assert!(interpolate_across_views(&[], &eye).is_err());
    }
}
