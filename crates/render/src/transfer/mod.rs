//! The panel's transfer function as an image pass: the renderer's linear light (above the
//! panel's black, see `dioptra_core::transfer`) to the code values the panel is driven with.
//!
//! Both twins read one look-up table ([`EncodeLut`]) built once from the transfer function:
//! [`EncodeLut::LEN`] points evenly spaced in `sqrt(v)` (dense near black, where a power
//! law's inverse is steep), read linearly between them. [`EncodeLut::encode_image`] is the CPU
//! pass (the headless sink's); [`gpu::encode_on_gpu`] the GPU's (`shaders/transfer.wgsl`),
//! and the warp's fragment shader encodes through the same table when it draws for a panel.

pub mod gpu;

use dioptra_core::transfer::Transfer;
use dioptra_core::{Plane, RgbImage};
use rayon::prelude::*;

/// A transfer function's inverse, tabulated.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodeLut {
    values: Vec<f32>,
    describe: String,
}

impl EncodeLut {
    /// Points in the table: the code value is within 2e-5 of the exact inverse for sRGB and
    /// for power laws from 1.8 to 2.6 (a test checks), far below a 10-bit step (1e-3).
    pub const LEN: usize = 4096;

    /// The table of `transfer`'s inverse ([`Transfer::encode`]).
    pub fn new(transfer: &Transfer) -> EncodeLut {
        let n = Self::LEN;
        let values = (0..n)
            .map(|i| {
                let t = i as f64 / (n - 1) as f64;
                transfer.encode(t * t) as f32
            })
            .collect();
        EncodeLut {
            values,
            describe: transfer.describe(),
        }
    }

    /// The table's values (code values at `(i / (LEN - 1))²`).
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    /// What it encodes for, for people.
    pub fn describe(&self) -> &str {
        &self.describe
    }

    /// One value: as `lut_encode` in `shaders/transfer_lut.wgsl`, in f32.
    pub fn encode(&self, v: f32) -> f32 {
        let lut = &self.values;
        let n = lut.len() as u32;
        // NaN and below 0: black; above 1: white.
        if v.is_nan() || v <= 0.0 {
            return lut[0];
        }
        let t = v.min(1.0).sqrt() * (n - 1) as f32;
        let i = (t as u32).min(n - 2) as usize;
        let f = t - i as f32;
        lut[i] + (lut[i + 1] - lut[i]) * f
    }

    /// The image pass: every channel of `image` encoded.
    pub fn encode_image(&self, image: &RgbImage) -> RgbImage {
        let (w, h) = (image.width(), image.height());
        let planes = image.channels.clone().map(|p| {
            let data: Vec<f32> = p.data().par_iter().map(|&v| self.encode(v)).collect();
            Plane::from_vec(w, h, data).expect("same size")
        });
        let [r, g, b] = planes;
        RgbImage::from_planes(r, g, b).expect("same size")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_follows_the_exact_inverse() {
        for (t, tol) in [
            (Transfer::Srgb, 2e-5),
            (Transfer::gamma(1.8, 0.0).unwrap(), 2e-5),
            (Transfer::gamma(2.2, 0.0).unwrap(), 2e-5),
            (Transfer::gamma(2.6, 0.0).unwrap(), 2e-5),
            (Transfer::gamma(2.4, 0.005).unwrap(), 2e-5),
            (Transfer::linear(), 1e-6),
        ] {
            let lut = EncodeLut::new(&t);
            let mut worst = 0.0f64;
            for i in 0..=100_000 {
                let v = i as f64 / 100_000.0;
                worst = worst.max((f64::from(lut.encode(v as f32)) - t.encode(v)).abs());
            }
            assert!(worst < tol, "{}: {worst}", t.describe());
        }
        let lut = EncodeLut::new(&Transfer::Srgb);
        assert_eq!(lut.encode(f32::NAN), 0.0);
        assert_eq!(lut.encode(-1.0), 0.0);
        assert_eq!(lut.encode(5.0), 1.0);
    }
}
