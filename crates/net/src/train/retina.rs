//! The multifocal retinal model as a differentiable convolution (C4 training): the retinal
//! image at focus q_j is sum_i k_ij * y_i, k_ij the disk PSF of diameter coc(p_i, q_j)
//! (DeepFocus eq. 2), here one conv2d from the 3M layer channels to 3J focal-stack channels.

use candle_core::{Device, Result, Tensor};
use dioptra_core::{Diopters, EyeModel};
use dioptra_render::kernel::disk_kernel;

pub struct Retina {
    /// [J, M, side, side]: the disk of (plane i, focus j); the same for every colour, so the
    /// colours are convolved as separate samples (a third of a [3J, 3M] kernel's work).
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
        let mut w = vec![0.0f32; j * m * side * side];
        for (jj, ks) in kernels.iter().enumerate() {
            for (ii, k) in ks.iter().enumerate() {
                let r = k.radius as isize;
                for dy in -r..=r {
                    for dx in -r..=r {
                        let (y, x) = (
                            (dy + radius as isize) as usize,
                            (dx + radius as isize) as usize,
                        );
                        // The convolution is a correlation: flip the (symmetric) kernel anyway.
                        w[((jj * m + ii) * side + y) * side + x] = k.at(-dx, -dy);
                    }
                }
            }
        }
        Ok(Retina {
            weight: Tensor::from_vec(w, (j, m, side, side), dev)?,
            radius,
        })
    }

    /// NCHW layers (3M channels, plane-major: plane i's R, G, B at 3i..3i+3) -> NCHW retinal
    /// focal stack (3J channels, focus-major).
    pub fn apply(&self, layers: &Tensor) -> Result<Tensor> {
        self.apply_foci(layers, None)
    }

    /// [`Retina::apply`] at the foci `only` (indices into the foci), when given: 3 x their
    /// count channels in that order.
    pub fn apply_foci(&self, layers: &Tensor, only: Option<&[u32]>) -> Result<Tensor> {
        let (n, c, h, w) = layers.dims4()?;
        let m = self.weight.dim(1)?;
        if c != 3 * m {
            candle_core::bail!("retina: {c} layer channels for {m} planes");
        }
        let weight = match only {
            Some(idx) => {
                let i = Tensor::from_slice(idx, idx.len(), self.weight.device())?;
                self.weight.index_select(&i, 0)?
            }
            None => self.weight.clone(),
        };
        let j = weight.dim(0)?;
        // (N, M, 3, H, W) -> (N * 3, M, H, W): colours as samples.
        let by_colour = layers
            .reshape((n, m, 3, h, w))?
            .permute((0, 2, 1, 3, 4))?
            .reshape((n * 3, m, h, w))?;
        let seen = super::conv::conv_fixed(&by_colour, &weight)?;
        seen.reshape((n, 3, j, h, w))?
            .permute((0, 2, 1, 3, 4))?
            .reshape((n, 3 * j, h, w))
    }

    /// Drops the unreliable border of an NCHW tensor.
    pub fn interior(&self, t: &Tensor) -> Result<Tensor> {
        let (_, _, h, w) = t.dims4()?;
        let r = self.radius;
        t.narrow(2, r, h - 2 * r)?.narrow(3, r, w - 2 * r)
    }
}
