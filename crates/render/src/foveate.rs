//! Foveated sampling (Thumuluri & Sharma 2020, sec. 4.1-4.2): log-polar sampling masks
//! (eq. 3-8) and inverse-distance interpolation of the unsampled pixels from the four
//! nearest samples (eq. 9).

use crate::error::{invalid, mismatch, RenderError};
use dioptra_core::{Plane, RgbImage};
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
    let rr = (width as f32 / p.scale).round().clamp(1.0, 1e5) as usize;
    let big_theta = rr;
    let mut mask = Plane::new(width, height, 0.0);
    for r in 0..rr {
        // eq. 5-6: rho = r' exp(r^(1/K) log L / R)
        let rho = p.r_offset * ((r as f32).powf(1.0 / p.kernel) * l.ln() / rr as f32).exp();
        for t in 0..big_theta {
            let a = std::f32::consts::TAU * t as f32 / big_theta as f32 + p.theta_offset;
            let x = (p.centre[0] + rho * a.cos()).floor();
            let y = (p.centre[1] + rho * a.sin()).floor();
            if x >= 0.0 && y >= 0.0 && (x as usize) < width && (y as usize) < height {
                mask.data_mut()[y as usize * width + x as usize] = 1.0;
            }
        }
    }
    let fraction =
        mask.data().iter().filter(|&&v| v > 0.5).count() as f64 / (width * height) as f64;
    Ok((mask, fraction))
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
}
