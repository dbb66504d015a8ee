//! Image quality metrics on sRGB-encoded [0, 1] images: PSNR and SSIM (Wang et al. 2004,
//! 11 x 11 Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03), optionally inside a mask.

use crate::error::{invalid, mismatch, RenderError};
use crate::kernel::{gaussian_taps, separable_blur};
use dioptra_core::image::linear_to_srgb;
use dioptra_core::{DepthMap, Plane, RgbImage};
use rayon::prelude::*;

/// PSNR and SSIM of one comparison.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Quality {
    /// dB; infinite for identical images.
    pub psnr: f64,
    pub ssim: f64,
}

pub(crate) fn check(a: &RgbImage, b: &RgbImage, mask: Option<&Plane>) -> Result<(), RenderError> {
    if (a.width(), a.height()) != (b.width(), b.height()) {
        return Err(mismatch(format!(
            "images are {}x{} and {}x{}",
            a.width(),
            a.height(),
            b.width(),
            b.height()
        )));
    }
    if a.width() == 0 || a.height() == 0 {
        return Err(invalid("images are empty"));
    }
    if let Some(m) = mask {
        if (m.width(), m.height()) != (a.width(), a.height()) {
            return Err(mismatch(format!(
                "mask is {}x{} but images are {}x{}",
                m.width(),
                m.height(),
                a.width(),
                a.height()
            )));
        }
        if !m.data().iter().any(|&v| v > 0.5) {
            return Err(invalid("mask selects no pixel (no value > 0.5)"));
        }
    }
    Ok(())
}

fn encode(p: &Plane) -> Vec<f32> {
    p.data().par_iter().map(|&v| linear_to_srgb(v)).collect()
}

fn selected(mask: Option<&Plane>, i: usize) -> bool {
    mask.is_none_or(|m| m.data()[i] > 0.5)
}

/// PSNR (dB) of two linear images after sRGB encoding, peak 1, over all channels; inside
/// `mask` (pixels where it is > 0.5) when given.
pub fn psnr(a: &RgbImage, b: &RgbImage, mask: Option<&Plane>) -> Result<f64, RenderError> {
    check(a, b, mask)?;
    let mut se = 0.0f64;
    let mut n = 0usize;
    for c in 0..3 {
        let (x, y) = (encode(&a.channels[c]), encode(&b.channels[c]));
        for i in 0..x.len() {
            if selected(mask, i) {
                se += ((x[i] - y[i]) as f64).powi(2);
                n += 1;
            }
        }
    }
    let mse = se / n as f64;
    Ok(if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    })
}

/// Mean SSIM over channels and (masked) pixels, on sRGB-encoded values.
pub fn ssim(a: &RgbImage, b: &RgbImage, mask: Option<&Plane>) -> Result<f64, RenderError> {
    check(a, b, mask)?;
    let (w, h) = (a.width(), a.height());
    let taps = gaussian_taps(1.5);
    // 3 sigma of 1.5 rounds up to 5: the 11-tap window of the paper.
    debug_assert_eq!(taps.len(), 11);
    let (c1, c2) = (0.01f32 * 0.01, 0.03f32 * 0.03);
    let mut total = 0.0f64;
    let mut n = 0usize;
    for c in 0..3 {
        let x = encode(&a.channels[c]);
        let y = encode(&b.channels[c]);
        let mk = |v: Vec<f32>| Plane::from_vec(w, h, v).map_err(RenderError::from);
        let xy: Vec<f32> = x.iter().zip(&y).map(|(p, q)| p * q).collect();
        let xx: Vec<f32> = x.iter().map(|p| p * p).collect();
        let yy: Vec<f32> = y.iter().map(|p| p * p).collect();
        let blur = |p: Plane| separable_blur(&p, &taps);
        let (mx, my) = (blur(mk(x)?), blur(mk(y)?));
        let (sxx, syy, sxy) = (blur(mk(xx)?), blur(mk(yy)?), blur(mk(xy)?));
        for i in 0..w * h {
            if !selected(mask, i) {
                continue;
            }
            let (ux, uy) = (mx.data()[i], my.data()[i]);
            let vx = sxx.data()[i] - ux * ux;
            let vy = syy.data()[i] - uy * uy;
            let cov = sxy.data()[i] - ux * uy;
            let s = ((2.0 * ux * uy + c1) * (2.0 * cov + c2))
                / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
            total += s as f64;
            n += 1;
        }
    }
    Ok(total / n as f64)
}

/// PSNR and SSIM together.
pub fn quality(a: &RgbImage, b: &RgbImage, mask: Option<&Plane>) -> Result<Quality, RenderError> {
    Ok(Quality {
        psnr: psnr(a, b, mask)?,
        ssim: ssim(a, b, mask)?,
    })
}

/// Pixels within `radius` of a depth step larger than `step` diopters: the occlusion
/// boundaries where defocus methods fail first. 1 inside, 0 outside.
pub fn depth_edge_mask(depth: &DepthMap, step: f32, radius: usize) -> Plane {
    let (w, h) = (depth.width(), depth.height());
    let d = depth.data();
    let mut m = Plane::new(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let c = d[y * w + x];
            let edge = (x + 1 < w && (d[y * w + x + 1] - c).abs() > step)
                || (y + 1 < h && (d[(y + 1) * w + x] - c).abs() > step);
            if edge {
                for yy in y.saturating_sub(radius)..(y + radius + 1).min(h) {
                    m.data_mut()
                        [yy * w + x.saturating_sub(radius)..yy * w + (x + radius + 1).min(w)]
                        .fill(1.0);
                }
            }
        }
    }
    m
}

/// A disk mask (1 inside) of `radius` pixels around `centre`: the fovea. Its complement
/// ([`invert_mask`]) is the periphery.
pub fn disk_mask(width: usize, height: usize, centre: [f32; 2], radius: f32) -> Plane {
    let mut p = Plane::new(width, height, 0.0);
    for (i, v) in p.data_mut().iter_mut().enumerate() {
        let dx = (i % width) as f32 + 0.5 - centre[0];
        let dy = (i / width) as f32 + 0.5 - centre[1];
        if dx * dx + dy * dy <= radius * radius {
            *v = 1.0;
        }
    }
    p
}

/// The radial regions Thumuluri & Sharma 2020 (sec. 6) report quality in, centred on the
/// gaze: with L the image diagonal, the fovea is the disk of diameter 0.1 L, periphery 1 the
/// ring out to diameter 0.4 L and periphery 2 the ring out to diameter L. The paper draws
/// only the boundaries; rings (not nested disks) keep each figure from being dominated by the
/// regions inside it. Pixels beyond 0.5 L (an off-centre gaze) belong to no region.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FovealRegion {
    Fovea,
    Periphery1,
    Periphery2,
}

impl FovealRegion {
    pub const ALL: [FovealRegion; 3] = [
        FovealRegion::Fovea,
        FovealRegion::Periphery1,
        FovealRegion::Periphery2,
    ];

    /// Inner and outer diameters as fractions of the image diagonal.
    pub fn diameters(self) -> (f32, f32) {
        match self {
            FovealRegion::Fovea => (0.0, 0.1),
            FovealRegion::Periphery1 => (0.1, 0.4),
            FovealRegion::Periphery2 => (0.4, 1.0),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            FovealRegion::Fovea => "fovea",
            FovealRegion::Periphery1 => "periphery 1",
            FovealRegion::Periphery2 => "periphery 2",
        }
    }

    /// The region's mask (1 inside) for a `width` x `height` image and gaze `centre` (pixels).
    pub fn mask(self, width: usize, height: usize, centre: [f32; 2]) -> Plane {
        let diag = ((width * width + height * height) as f32).sqrt();
        let (inner, outer) = self.diameters();
        let (r0, r1) = (0.5 * inner * diag, 0.5 * outer * diag);
        let mut p = Plane::new(width, height, 0.0);
        for (i, v) in p.data_mut().iter_mut().enumerate() {
            let dx = (i % width.max(1)) as f32 + 0.5 - centre[0];
            let dy = (i / width.max(1)) as f32 + 0.5 - centre[1];
            let r = (dx * dx + dy * dy).sqrt();
            // The fovea includes its centre; each ring excludes its inner boundary.
            if (r > r0 || inner == 0.0) && r <= r1 {
                *v = 1.0;
            }
        }
        p
    }
}

/// PSNR and SSIM in each [`FovealRegion`] around `centre`; `None` for a region with no pixel
/// in the image (a gaze far off-centre on a small image).
pub fn quality_by_region(
    a: &RgbImage,
    b: &RgbImage,
    centre: [f32; 2],
) -> Result<[(FovealRegion, Option<Quality>); 3], RenderError> {
    check(a, b, None)?;
    let (w, h) = (a.width(), a.height());
    let mut out = FovealRegion::ALL.map(|r| (r, None));
    for slot in out.iter_mut() {
        let m = slot.0.mask(w, h, centre);
        if m.data().iter().any(|&v| v > 0.5) {
            slot.1 = Some(quality(a, b, Some(&m))?);
        }
    }
    Ok(out)
}

/// 1 where `m` is not selected and 0 where it is.
pub fn invert_mask(m: &Plane) -> Plane {
    let mut p = m.clone();
    p.data_mut()
        .iter_mut()
        .for_each(|v| *v = if *v > 0.5 { 0.0 } else { 1.0 });
    p
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: usize, h: usize, k: f32) -> RgbImage {
        let d: Vec<f32> = (0..w * h * 3)
            .map(|i| ((i as f32 * k).sin() * 0.5 + 0.5) * 0.8)
            .collect();
        RgbImage::from_interleaved(w, h, &d).unwrap()
    }

    #[test]
    fn foveal_regions_partition_the_central_disk() {
        let (w, h) = (64, 48);
        let c = [32.0, 24.0];
        let masks = FovealRegion::ALL.map(|r| r.mask(w, h, c));
        let diag = ((w * w + h * h) as f32).sqrt();
        for i in 0..w * h {
            let dx = (i % w) as f32 + 0.5 - c[0];
            let dy = (i / w) as f32 + 0.5 - c[1];
            let r = (dx * dx + dy * dy).sqrt();
            let hits: Vec<usize> = (0..3).filter(|&k| masks[k].data()[i] > 0.5).collect();
            // Every pixel within half the diagonal is in exactly one region, by radius.
            let expect = if r <= 0.05 * diag {
                0
            } else if r <= 0.2 * diag {
                1
            } else {
                2
            };
            assert_eq!(hits, vec![expect], "pixel {i} at radius {r}");
        }
    }

    #[test]
    fn quality_by_region_sees_where_the_error_is() {
        let a = ramp(64, 64, 0.21);
        let mut b = a.clone();
        // Damage only the corners: the fovea stays perfect, periphery 2 does not.
        for ch in b.channels.iter_mut() {
            for (i, v) in ch.data_mut().iter_mut().enumerate() {
                let (x, y) = (i % 64, i / 64);
                if !(8..56).contains(&x) && !(8..56).contains(&y) {
                    *v = 1.0 - *v;
                }
            }
        }
        let q = quality_by_region(&a, &b, [32.0, 32.0]).unwrap();
        let fovea = q[0].1.unwrap();
        let p2 = q[2].1.unwrap();
        assert_eq!(fovea.psnr, f64::INFINITY);
        assert!(p2.psnr < 30.0 && p2.ssim < 0.99, "{p2:?}");
        // A gaze far outside the image leaves the fovea empty, not an error.
        let off = quality_by_region(&a, &b, [1000.0, 1000.0]).unwrap();
        assert!(off[0].1.is_none());
    }

    #[test]
    fn psnr_of_known_error() {
        // sRGB 0.5 vs 0.6 everywhere: MSE 0.01 -> 20 dB.
        let lin = dioptra_core::image::srgb_to_linear;
        let a = RgbImage::new(8, 8, [lin(0.5); 3]);
        let b = RgbImage::new(8, 8, [lin(0.6); 3]);
        assert!((psnr(&a, &b, None).unwrap() - 20.0).abs() < 1e-3);
        assert_eq!(psnr(&a, &a, None).unwrap(), f64::INFINITY);
    }

    #[test]
    fn ssim_is_one_for_identical_and_drops_with_noise() {
        let a = ramp(32, 32, 0.37);
        assert!((ssim(&a, &a, None).unwrap() - 1.0).abs() < 1e-5);
        let mut b = a.clone();
        for ch in b.channels.iter_mut() {
            for (i, v) in ch.data_mut().iter_mut().enumerate() {
                *v = (*v + if (i + i / 32) % 2 == 0 { 0.1 } else { -0.1 }).clamp(0.0, 1.0);
            }
        }
        let s = ssim(&a, &b, None).unwrap();
        assert!(s < 0.9 && s > 0.0, "{s}");
    }

    #[test]
    fn mask_restricts_the_comparison() {
        let a = RgbImage::new(16, 16, [0.2; 3]);
        let mut b = a.clone();
        b.channels[0].data_mut()[0] = 0.9; // error only at the corner
        let fovea = disk_mask(16, 16, [8.0, 8.0], 4.0);
        assert_eq!(psnr(&a, &b, Some(&fovea)).unwrap(), f64::INFINITY);
        assert!(psnr(&a, &b, Some(&invert_mask(&fovea)))
            .unwrap()
            .is_finite());
        assert!(psnr(&a, &b, Some(&Plane::new(16, 16, 0.0))).is_err());
        assert!(psnr(&a, &RgbImage::new(15, 16, [0.2; 3]), None).is_err());
    }

    #[test]
    fn depth_edge_mask_marks_both_sides_of_a_step() {
        // A 6x3 map with a 1 D step between columns 2 and 3.
        let mut v = vec![0.5f32; 18];
        for y in 0..3 {
            for x in 3..6 {
                v[y * 6 + x] = 1.5;
            }
        }
        let depth = DepthMap::from_diopters(Plane::from_vec(6, 3, v).unwrap()).unwrap();
        let m = depth_edge_mask(&depth, 0.3, 1);
        for y in 0..3 {
            assert_eq!(m.row(y), &[0.0, 1.0, 1.0, 1.0, 0.0, 0.0]);
        }
        assert!(depth_edge_mask(&depth, 2.0, 1)
            .data()
            .iter()
            .all(|&v| v == 0.0));
    }
}
