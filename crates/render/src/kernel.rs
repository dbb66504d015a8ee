//! Convolution kernels and the FFT convolution engine shared by the methods.

use crate::fft2::fft_size;
use dioptra_core::Plane;
use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};
use std::sync::Arc;

/// A square kernel of odd side `2 * radius + 1`, row-major, summing to 1.
#[derive(Debug, Clone, PartialEq)]
pub struct Kernel {
    pub radius: usize,
    pub weights: Vec<f32>,
}

impl Kernel {
    pub fn side(&self) -> usize {
        2 * self.radius + 1
    }
    pub fn at(&self, dx: isize, dy: isize) -> f32 {
        let r = self.radius as isize;
        if dx.abs() > r || dy.abs() > r {
            return 0.0;
        }
        self.weights[((dy + r) * (2 * r + 1) + dx + r) as usize]
    }
}

/// Area of the unit-spaced pixel cell centred at `(cx, cy)` covered by a disk of radius `r`
/// at the origin: the integral over x of the clipped chord, by 256-point midpoint rule for
/// cells the rim crosses (error ~1e-6 of a cell).
fn cell_coverage(cx: f32, cy: f32, r: f32) -> f32 {
    // The disk is symmetric: integrate in one canonical orientation so the kernel is too.
    let (ax, ay) = (cx.abs().max(cy.abs()), cx.abs().min(cy.abs()));
    let (cx, cy) = (ax, ay);
    let near = ((ax - 0.5).max(0.0).powi(2) + (ay - 0.5).max(0.0).powi(2)).sqrt();
    let far = ((ax + 0.5).powi(2) + (ay + 0.5).powi(2)).sqrt();
    if near >= r {
        return 0.0;
    }
    if far <= r {
        return 1.0;
    }
    const N: usize = 256;
    let (y0, y1) = (cy as f64 - 0.5, cy as f64 + 0.5);
    let r = r as f64;
    let mut area = 0.0f64;
    for i in 0..N {
        let x = cx as f64 - 0.5 + (i as f64 + 0.5) / N as f64;
        if x.abs() < r {
            let s = (r * r - x * x).sqrt();
            area += (y1.min(s) - y0.max(-s)).max(0.0);
        }
    }
    (area / N as f64) as f32
}

/// A disk PSF of the given diameter in pixels, like MATLAB's `fspecial('disk', d/2)`: each
/// cell weighted by the area of the disk inside it, normalised. Below one pixel it tends to
/// a single tap; NaN or negative diameters give the identity.
pub fn disk_kernel(diameter: f32) -> Kernel {
    let r = if diameter.is_finite() {
        (0.5 * diameter).max(0.0)
    } else {
        0.0
    };
    // Clamp keeps a hostile diameter from allocating gigabytes.
    let r = r.min(512.0);
    let radius = (r - 0.5).max(0.0).ceil() as usize;
    let side = 2 * radius + 1;
    let mut w = vec![0.0f32; side * side];
    if r < 1e-6 {
        w[radius * side + radius] = 1.0;
    } else {
        for j in 0..side {
            for i in 0..side {
                w[j * side + i] =
                    cell_coverage(i as f32 - radius as f32, j as f32 - radius as f32, r);
            }
        }
    }
    let sum: f32 = w.iter().sum();
    if sum.is_nan() || sum <= 0.0 {
        // A disk too small for the coverage integral's samples (diameter below ~0.004 px)
        // is a point: without this its weights would be 0 / 0.
        w.iter_mut().for_each(|v| *v = 0.0);
        w[radius * side + radius] = 1.0;
        return Kernel { radius, weights: w };
    }
    w.iter_mut().for_each(|v| *v /= sum);
    Kernel { radius, weights: w }
}

/// Normalised 1-D Gaussian taps for standard deviation `sigma` pixels (3 sigma support).
pub fn gaussian_taps(sigma: f32) -> Vec<f32> {
    if sigma.is_nan() || sigma <= 1e-3 || !sigma.is_finite() {
        return vec![1.0];
    }
    let r = (3.0 * sigma).ceil().min(256.0) as isize;
    let mut t: Vec<f32> = (-r..=r)
        .map(|x| (-(x * x) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let s: f32 = t.iter().sum();
    t.iter_mut().for_each(|v| *v /= s);
    t
}

/// Separable convolution with edge clamping (rows, then columns), in parallel over rows.
pub fn separable_blur(p: &Plane, taps: &[f32]) -> Plane {
    let (w, h) = (p.width(), p.height());
    if taps.len() <= 1 || w == 0 || h == 0 {
        return p.clone();
    }
    let r = (taps.len() / 2) as isize;
    let src = p.data();
    let mut tmp = vec![0.0f32; w * h];
    let ru = r as usize;
    tmp.par_chunks_mut(w)
        .enumerate()
        .for_each_init(Vec::new, |pad, (y, row)| {
            // Clamp once into a padded row so the tap loop is branch-free and vectorises;
            // the per-pixel sum order (tap by tap) is unchanged.
            let s = &src[y * w..(y + 1) * w];
            pad.clear();
            pad.extend(std::iter::repeat_n(s[0], ru));
            pad.extend_from_slice(s);
            pad.extend(std::iter::repeat_n(s[w - 1], ru));
            for (k, t) in taps.iter().enumerate() {
                for (o, v) in row.iter_mut().zip(&pad[k..k + w]) {
                    *o += t * v;
                }
            }
        });
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (k, t) in taps.iter().enumerate() {
            let yi = (y as isize + k as isize - r).clamp(0, h as isize - 1) as usize;
            let s = &tmp[yi * w..(yi + 1) * w];
            for (o, v) in row.iter_mut().zip(s) {
                *o += t * v;
            }
        }
    });
    Plane::from_vec(w, h, out).unwrap_or_else(|_| p.clone())
}

/// 2-D FFT convolution on a padded grid. Images are padded by edge replication with a margin
/// of at least the largest kernel radius, so circular wrap-around never reaches the image.
/// Two real planes travel in one complex FFT (real and imaginary parts): the kernels used here
/// are real and even, so their spectra are real and keep the two apart.
pub struct FftConv {
    pub width: usize,
    pub height: usize,
    pub margin: usize,
    pub pw: usize,
    pub ph: usize,
    row_fwd: Arc<dyn Fft<f32>>,
    row_inv: Arc<dyn Fft<f32>>,
    col_fwd: Arc<dyn Fft<f32>>,
    col_inv: Arc<dyn Fft<f32>>,
}

/// A spectrum on the padded grid, row-major, `pw * ph` values.
pub type Spectrum = Vec<Complex32>;

impl FftConv {
    /// An engine for `width` x `height` images and kernels up to `max_radius` pixels.
    pub fn new(width: usize, height: usize, max_radius: usize) -> FftConv {
        let margin = max_radius + 2;
        let pw = fft_size(width + 2 * margin);
        let ph = fft_size(height + 2 * margin);
        let mut planner = FftPlanner::new();
        FftConv {
            width,
            height,
            margin,
            pw,
            ph,
            row_fwd: planner.plan_fft_forward(pw),
            row_inv: planner.plan_fft_inverse(pw),
            col_fwd: planner.plan_fft_forward(ph),
            col_inv: planner.plan_fft_inverse(ph),
        }
    }

    fn fft2(&self, buf: &mut [Complex32], inverse: bool) {
        let (pw, ph) = (self.pw, self.ph);
        let (row, col) = if inverse {
            (&self.row_inv, &self.col_inv)
        } else {
            (&self.row_fwd, &self.col_fwd)
        };
        buf.par_chunks_mut(pw * 16)
            .for_each(|rows| row.process(rows));
        // Columns through a transpose: contiguous FFTs are much faster than strided ones.
        let mut t = vec![Complex32::default(); pw * ph];
        t.par_chunks_mut(ph).enumerate().for_each(|(x, c)| {
            for (y, v) in c.iter_mut().enumerate() {
                *v = buf[y * pw + x];
            }
        });
        t.par_chunks_mut(ph * 16).for_each(|cols| col.process(cols));
        buf.par_chunks_mut(pw).enumerate().for_each(|(y, r)| {
            for (x, v) in r.iter_mut().enumerate() {
                *v = t[x * ph + y];
            }
        });
        if inverse {
            let s = 1.0 / (pw * ph) as f32;
            buf.par_iter_mut().for_each(|v| *v *= s);
        }
    }

    /// Spectrum of planes `a` (real part) and `b` (imaginary part, or zero), edge-replicated
    /// onto the padded grid. Both must be `width` x `height`.
    pub fn forward_pair(&self, a: &Plane, b: Option<&Plane>) -> Spectrum {
        let (pw, ph, m) = (self.pw, self.ph, self.margin as isize);
        let (w, h) = (self.width as isize, self.height as isize);
        let mut buf = vec![Complex32::default(); pw * ph];
        buf.par_chunks_mut(pw).enumerate().for_each(|(py, r)| {
            let y = (py as isize - m).clamp(0, h - 1) as usize;
            for (px, v) in r.iter_mut().enumerate() {
                let x = (px as isize - m).clamp(0, w - 1) as usize;
                let i = y * self.width + x;
                *v = Complex32::new(a.data()[i], b.map_or(0.0, |b| b.data()[i]));
            }
        });
        self.fft2(&mut buf, false);
        buf
    }

    /// Spectrum of raw padded-grid data given as (real, imaginary) planes of `pw * ph` values.
    pub fn forward_padded(&self, re: &[f32], im: &[f32]) -> Spectrum {
        let mut buf: Vec<Complex32> = re
            .iter()
            .zip(im)
            .map(|(&r, &i)| Complex32::new(r, i))
            .collect();
        buf.resize(self.pw * self.ph, Complex32::default());
        self.fft2(&mut buf, false);
        buf
    }

    /// Inverse transform to the padded grid: (real, imaginary) parts, `pw * ph` values each.
    pub fn inverse_padded(&self, mut s: Spectrum) -> (Vec<f32>, Vec<f32>) {
        self.fft2(&mut s, true);
        (
            s.iter().map(|c| c.re).collect(),
            s.iter().map(|c| c.im).collect(),
        )
    }

    /// Inverse transform, cropped back to the image: the two planes carried by `s`.
    pub fn inverse_pair(&self, s: Spectrum) -> (Plane, Plane) {
        let (re, im) = self.inverse_padded(s);
        (self.crop(&re), self.crop(&im))
    }

    /// The image-sized window of a padded-grid plane.
    pub fn crop(&self, padded: &[f32]) -> Plane {
        let (w, h, m) = (self.width, self.height, self.margin);
        let mut out = Vec::with_capacity(w * h);
        for y in 0..h {
            let s = (y + m) * self.pw + m;
            out.extend_from_slice(&padded[s..s + w]);
        }
        Plane::from_vec(w, h, out).unwrap_or_else(|_| Plane::new(w, h, 0.0))
    }

    /// An image-sized plane edge-replicated onto the padded grid.
    pub fn pad(&self, p: &Plane) -> Vec<f32> {
        let (m, w, h) = (
            self.margin as isize,
            self.width as isize,
            self.height as isize,
        );
        let mut out = vec![0.0; self.pw * self.ph];
        for (py, r) in out.chunks_mut(self.pw).enumerate() {
            let y = (py as isize - m).clamp(0, h - 1) as usize;
            for (px, v) in r.iter_mut().enumerate() {
                *v = p.data()[y * self.width + (px as isize - m).clamp(0, w - 1) as usize];
            }
        }
        out
    }

    /// Real spectra of two kernels at once (each centred on the origin with wrap-around).
    /// Kernels wider than the margin allows are clamped to it.
    pub fn kernel_spectra(&self, a: &Kernel, b: &Kernel) -> (Vec<f32>, Vec<f32>) {
        let (pw, ph) = (self.pw, self.ph);
        let mut buf = vec![Complex32::default(); pw * ph];
        let mut put = |k: &Kernel, imag: bool| {
            let r = k.radius.min(self.margin) as isize;
            for dy in -r..=r {
                for dx in -r..=r {
                    let i = (dy.rem_euclid(ph as isize) as usize) * pw
                        + dx.rem_euclid(pw as isize) as usize;
                    if imag {
                        buf[i].im += k.at(dx, dy);
                    } else {
                        buf[i].re += k.at(dx, dy);
                    }
                }
            }
        };
        put(a, false);
        put(b, true);
        self.fft2(&mut buf, false);
        // FFT(a + i b) = A + i B with A, B real for even real kernels; separate them.
        let n = pw * ph;
        let mut ka = vec![0.0; n];
        let mut kb = vec![0.0; n];
        for y in 0..ph {
            for x in 0..pw {
                let i = y * pw + x;
                let j = ((ph - y) % ph) * pw + (pw - x) % pw;
                let (z, zc) = (buf[i], buf[j].conj());
                ka[i] = 0.5 * (z.re + zc.re);
                kb[i] = 0.5 * (z.im - zc.im);
            }
        }
        (ka, kb)
    }

    /// Convolve two planes with the same kernel (edge-replicated borders).
    pub fn convolve_pair(&self, a: &Plane, b: Option<&Plane>, k: &Kernel) -> (Plane, Plane) {
        let (ks, _) = self.kernel_spectra(
            k,
            &Kernel {
                radius: 0,
                weights: vec![1.0],
            },
        );
        let mut s = self.forward_pair(a, b);
        s.par_iter_mut()
            .zip(ks.par_iter())
            .for_each(|(v, k)| *v *= *k);
        self.inverse_pair(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn disk_kernel_matches_fspecial() {
        // MATLAB's fspecial('disk', 1) is [0.0251 0.1453 0.0251; 0.1453 0.3183 0.1453; ...].
        let k = disk_kernel(2.0);
        assert_eq!(k.radius, 1);
        let s: f32 = k.weights.iter().sum();
        assert!((s - 1.0).abs() < 1e-5);
        assert!((k.at(0, 0) - std::f32::consts::FRAC_1_PI).abs() < 1e-3);
        assert!((k.at(1, 0) - 0.1453).abs() < 1e-3, "{}", k.at(1, 0));
        assert!((k.at(1, 1) - 0.0251).abs() < 1e-3, "{}", k.at(1, 1));
        assert!((k.at(1, 0) - k.at(0, -1)).abs() < 1e-6);
        assert_eq!(disk_kernel(0.5).weights, vec![1.0]);
        assert_eq!(disk_kernel(f32::NAN).weights, vec![1.0]);
        // Below the coverage integral's resolution: still a point, not 0 / 0.
        assert_eq!(disk_kernel(0.001).weights, vec![1.0]);
        assert_eq!(disk_kernel(11.0).radius, 5);
    }

    #[test]
    fn fft_convolution_matches_direct() {
        let (w, h) = (23, 17);
        let data: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 11) as f32 / 11.0).collect();
        let p = Plane::from_vec(w, h, data).unwrap();
        let k = disk_kernel(5.3);
        let conv = FftConv::new(w, h, k.radius);
        let (a, b) = conv.convolve_pair(&p, Some(&p), &k);
        let r = k.radius as isize;
        for y in 0..h as isize {
            for x in 0..w as isize {
                let mut acc = 0.0;
                for dy in -r..=r {
                    for dx in -r..=r {
                        let xi = (x - dx).clamp(0, w as isize - 1) as usize;
                        let yi = (y - dy).clamp(0, h as isize - 1) as usize;
                        acc += k.at(dx, dy) * p.data()[yi * w + xi];
                    }
                }
                let i = y as usize * w + x as usize;
                assert!(
                    (a.data()[i] - acc).abs() < 1e-4,
                    "({x},{y}) {} {acc}",
                    a.data()[i]
                );
                assert!((b.data()[i] - acc).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn gaussian_blur_keeps_mean_of_constant() {
        let p = Plane::new(9, 7, 0.25);
        let b = separable_blur(&p, &gaussian_taps(1.7));
        assert!(b.data().iter().all(|v| (v - 0.25).abs() < 1e-6));
    }
}
