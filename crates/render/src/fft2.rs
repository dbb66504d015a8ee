//! Real 2-D FFTs on a padded grid (realfft along rows, rustfft along columns) for the
//! spectral decomposition: a real `pw` x `ph` image has a half spectrum of `hw = pw / 2 + 1`
//! columns by `ph` rows, stored column-major (`kx * ph + ky`) so that the column transforms
//! run on contiguous memory and the inverse starts where the forward ended.

use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};
use std::sync::Arc;

/// The prime factors the padded grid's sides may have: fast for rustfft, and the radices the
/// GPU's FFT has (with 4: shaders/spectral.wgsl has a butterfly for each, checked in a test).
pub(crate) const FFT_PRIMES: [usize; 3] = [2, 3, 5];

/// Smallest n >= `min` whose only prime factors are [`FFT_PRIMES`].
pub(crate) fn fft_size(min: usize) -> usize {
    let mut n = min.max(1);
    loop {
        let mut m = n;
        for f in FFT_PRIMES {
            while m.is_multiple_of(f) {
                m /= f;
            }
        }
        if m == 1 {
            return n;
        }
        n += 1;
    }
}

thread_local! {
    /// The row transforms' output before the transpose, kept per thread: a fresh one per
    /// transform was a measurable part of the spectral solve (its zeroing).
    static ROWS: std::cell::RefCell<Vec<Complex32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// A half spectrum, `hw * ph` values, column-major.
pub type HalfSpectrum = Vec<Complex32>;

/// Forward and inverse real 2-D transforms of one grid size. Each call is single-threaded:
/// callers run many images in parallel.
pub struct Fft2 {
    pub pw: usize,
    pub ph: usize,
    /// Columns of the half spectrum: `pw / 2 + 1`.
    pub hw: usize,
    r2c: Arc<dyn RealToComplex<f32>>,
    c2r: Arc<dyn ComplexToReal<f32>>,
    col_fwd: Arc<dyn Fft<f32>>,
    col_inv: Arc<dyn Fft<f32>>,
}

impl Fft2 {
    pub fn new(pw: usize, ph: usize) -> Fft2 {
        let mut real = RealFftPlanner::<f32>::new();
        let mut cplx = FftPlanner::<f32>::new();
        Fft2 {
            pw,
            ph,
            hw: pw / 2 + 1,
            r2c: real.plan_fft_forward(pw),
            c2r: real.plan_fft_inverse(pw),
            col_fwd: cplx.plan_fft_forward(ph),
            col_inv: cplx.plan_fft_inverse(ph),
        }
    }

    /// Number of values in a half spectrum.
    pub fn len(&self) -> usize {
        self.hw * self.ph
    }

    /// The half spectrum of a `pw * ph` row-major real image (which is used as scratch).
    pub fn forward(&self, img: &mut [f32]) -> HalfSpectrum {
        let (pw, ph, hw) = (self.pw, self.ph, self.hw);
        debug_assert_eq!(img.len(), pw * ph);
        let mut spec = Vec::with_capacity(hw * ph);
        ROWS.with_borrow_mut(|rows| {
            rows.resize(hw * ph, Complex32::default());
            let mut scratch = self.r2c.make_scratch_vec();
            for (row, out) in img.chunks_exact_mut(pw).zip(rows.chunks_exact_mut(hw)) {
                // Lengths are the plan's, so this cannot fail.
                let _ = self.r2c.process_with_scratch(row, out, &mut scratch);
            }
            for kx in 0..hw {
                spec.extend(rows[kx..].iter().step_by(hw).take(ph));
            }
        });
        let mut cs = vec![Complex32::default(); self.col_fwd.get_inplace_scratch_len()];
        self.col_fwd.process_with_scratch(&mut spec, &mut cs);
        spec
    }

    /// The real `pw * ph` image of a half spectrum (consumed), scaled so that
    /// `inverse(forward(x)) == x`.
    pub fn inverse(&self, mut spec: HalfSpectrum) -> Vec<f32> {
        let (pw, ph, hw) = (self.pw, self.ph, self.hw);
        debug_assert_eq!(spec.len(), hw * ph);
        let mut cs = vec![Complex32::default(); self.col_inv.get_inplace_scratch_len()];
        self.col_inv.process_with_scratch(&mut spec, &mut cs);
        let scale = 1.0 / (pw * ph) as f32;
        let mut out = vec![0.0f32; pw * ph];
        let mut row = vec![Complex32::default(); hw];
        let mut scratch = self.c2r.make_scratch_vec();
        for (y, o) in out.chunks_exact_mut(pw).enumerate() {
            for (kx, v) in row.iter_mut().enumerate() {
                *v = spec[kx * ph + y] * scale;
            }
            // The DC (and Nyquist) bins of a real row are real; rounding leaves a trace.
            row[0].im = 0.0;
            if pw.is_multiple_of(2) {
                row[hw - 1].im = 0.0;
            }
            let _ = self.c2r.process_with_scratch(&mut row, o, &mut scratch);
        }
        out
    }

    /// The (real) half spectrum of an even kernel given by its taps at offsets (dx, dy),
    /// placed centred on the origin with wrap-around.
    pub fn kernel(&self, taps: impl Iterator<Item = (isize, isize, f32)>) -> Vec<f32> {
        let (pw, ph) = (self.pw as isize, self.ph as isize);
        let mut img = vec![0.0f32; self.pw * self.ph];
        for (dx, dy, w) in taps {
            img[(dy.rem_euclid(ph) * pw + dx.rem_euclid(pw)) as usize] += w;
        }
        self.forward(&mut img).into_iter().map(|c| c.re).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_dft() {
        let (pw, ph) = (12, 10);
        let f = Fft2::new(pw, ph);
        let img: Vec<f32> = (0..pw * ph)
            .map(|i| ((i * 37) % 11) as f32 / 11.0)
            .collect();
        let spec = f.forward(&mut img.clone());
        // A direct DFT at a few bins.
        for (kx, ky) in [(0, 0), (1, 0), (3, 7), (6, 9)] {
            let mut acc = (0.0f64, 0.0f64);
            for y in 0..ph {
                for x in 0..pw {
                    let a = -std::f64::consts::TAU
                        * (kx as f64 * x as f64 / pw as f64 + ky as f64 * y as f64 / ph as f64);
                    acc.0 += img[y * pw + x] as f64 * a.cos();
                    acc.1 += img[y * pw + x] as f64 * a.sin();
                }
            }
            let s = spec[kx * ph + ky];
            assert!((s.re as f64 - acc.0).abs() < 1e-3, "{kx},{ky}");
            assert!((s.im as f64 - acc.1).abs() < 1e-3, "{kx},{ky}");
        }
        let back = f.inverse(spec);
        for (a, b) in img.iter().zip(&back) {
            assert!((a - b).abs() < 1e-5);
        }
        assert_eq!(fft_size(266), 270);
    }
}
