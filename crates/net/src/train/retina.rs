//! The multifocal retinal model as a differentiable convolution (C4 training): the retinal
//! image at focus q_j is sum_i k_ij * y_i, k_ij the disk PSF of diameter coc(p_i, q_j)
//! (DeepFocus eq. 2), here one conv2d from the 3M layer channels to 3J focal-stack channels.

use candle_core::{Device, Result, Tensor};
use dioptra_core::{Diopters, EyeModel};
use dioptra_render::kernel::disk_kernel;

pub struct Retina {
    weight: Tensor,
    /// Kernel radius: the border of this width is unreliable (zero padding) and is left out
    /// of the loss.
    pub radius: usize,
}

impl Retina {
    /// `eye` must already have its width set to the training render size.
    pub fn new(planes: &[f32], foci: &[f32], eye: &EyeModel, dev: &Device) -> Result<Retina> {
        let kernels: Vec<Vec<_>> = foci
            .iter()
            .map(|&q| {
                planes
                    .iter()
                    .map(|&p| disk_kernel(eye.plane_kernel_px(Diopters(p), Diopters(q))))
                    .collect()
            })
            .collect();
        let radius = kernels
            .iter()
            .flatten()
            .map(|k| k.radius)
            .max()
            .unwrap_or(0);
        let side = 2 * radius + 1;
        let (m, j) = (planes.len(), foci.len());
        let mut w = vec![0.0f32; 3 * j * 3 * m * side * side];
        for (jj, ks) in kernels.iter().enumerate() {
            for (ii, k) in ks.iter().enumerate() {
                let r = k.radius as isize;
                for c in 0..3 {
                    let (o, i) = (3 * jj + c, 3 * ii + c);
                    for dy in -r..=r {
                        for dx in -r..=r {
                            let (y, x) = (
                                (dy + radius as isize) as usize,
                                (dx + radius as isize) as usize,
                            );
                            // conv2d is a correlation: flip the (symmetric) kernel anyway.
                            w[((o * 3 * m + i) * side + y) * side + x] = k.at(-dx, -dy);
                        }
                    }
                }
            }
        }
        Ok(Retina {
            weight: Tensor::from_vec(w, (3 * j, 3 * m, side, side), dev)?,
            radius,
        })
    }

    /// NCHW layers (3M channels) -> NCHW retinal focal stack (3J channels).
    pub fn apply(&self, layers: &Tensor) -> Result<Tensor> {
        layers.conv2d(&self.weight, self.radius, 1, 1, 1)
    }

    /// Drops the unreliable border of an NCHW tensor.
    pub fn interior(&self, t: &Tensor) -> Result<Tensor> {
        let (_, _, h, w) = t.dims4()?;
        let r = self.radius;
        t.narrow(2, r, h - 2 * r)?.narrow(3, r, w - 2 * r)
    }
}
