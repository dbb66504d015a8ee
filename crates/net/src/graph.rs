//! The network graph, written once over a backend's tensor operations: CPU inference, the
//! training framework and (later) the GPU all run this same function, so they cannot drift.

use crate::arch::Arch;

/// The operations a backend supplies. Tensors are at interleaved resolution except the input
/// to `space_to_depth` and the output of `depth_to_space`.
pub trait Ops {
    type T: Clone;
    type E;
    /// 3x3 "same" convolution with bias of layer `layer`, then ELU when `elu`.
    fn conv(&self, x: &Self::T, layer: usize, elu: bool) -> Result<Self::T, Self::E>;
    fn add(&self, a: &Self::T, b: &Self::T) -> Result<Self::T, Self::E>;
    /// Channel concatenation, `a`'s channels first.
    fn concat(&self, a: &Self::T, b: &Self::T) -> Result<Self::T, Self::E>;
    /// (tanh x + 1) / 2.
    fn tanh01(&self, x: &Self::T) -> Result<Self::T, Self::E>;
    fn space_to_depth(&self, x: &Self::T, r: usize) -> Result<Self::T, Self::E>;
    fn depth_to_space(&self, x: &Self::T, r: usize) -> Result<Self::T, Self::E>;
    /// 2x2 average pooling, stride 2 (the U-Net's downsampling; sizes are even).
    fn avg_pool2(&self, x: &Self::T) -> Result<Self::T, Self::E>;
    /// Nearest-neighbour 2x upsampling (the U-Net's).
    fn upsample2(&self, x: &Self::T) -> Result<Self::T, Self::E>;
}

/// The FV U-Net on the interleaved input `x0`: its pre-`tanh` output, added to the chain's.
fn unet<O: Ops>(arch: &Arch, ops: &O, x0: &O::T) -> Result<O::T, O::E> {
    let k = arch.layers;
    let e0 = ops.conv(&ops.conv(x0, k, true)?, k + 1, true)?;
    let e1 = ops.conv(&ops.avg_pool2(&e0)?, k + 2, true)?;
    let bottom = ops.conv(&ops.avg_pool2(&e1)?, k + 3, true)?;
    let d1 = ops.conv(&ops.concat(&ops.upsample2(&bottom)?, &e1)?, k + 4, true)?;
    let d0 = ops.conv(&ops.concat(&ops.upsample2(&d1)?, &e0)?, k + 5, true)?;
    ops.conv(&d0, k + 6, false)
}

/// Runs the network on a full-resolution input (its size a multiple of
/// [`Arch::size_multiple`]).
pub fn forward<O: Ops>(arch: &Arch, ops: &O, input: &O::T) -> Result<O::T, O::E> {
    let x0 = ops.space_to_depth(input, arch.rate)?;
    let last = arch.layers - 1;
    let mut h: Vec<O::T> = Vec::with_capacity(last);
    for i in 0..arch.layers {
        // Each layer reads the previous one (plus a residual) by reference: on the CPU an
        // activation is megabytes, and copying it per layer cost a tenth of a frame.
        let (sum, cat);
        let mut x: &O::T = if i == 0 { &x0 } else { &h[i - 1] };
        if let Some(j) = arch.residual_from(i).filter(|_| i > 0) {
            sum = ops.add(x, &h[j])?;
            x = &sum;
        }
        if i == last {
            if arch.concat_input {
                cat = ops.concat(x, &x0)?;
                x = &cat;
            }
            let mut y = ops.conv(x, i, false)?;
            if arch.unet_channels > 0 {
                y = ops.add(&y, &unet(arch, ops, &x0)?)?;
            }
            if !arch.task.residual() {
                y = ops.tanh01(&y)?;
            }
            return ops.depth_to_space(&y, arch.rate);
        }
        let y = ops.conv(x, i, true)?;
        h.push(y);
    }
    // arch.layers >= 2 is validated, so the loop always returns.
    ops.depth_to_space(h.last().unwrap_or(&x0), arch.rate)
}
