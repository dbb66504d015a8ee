//! Direct 3x3 convolution with an AVX2 + FMA register-blocked micro-kernel (x86-64, detected
//! at run time). A tile of 6 output pixels x 16 output channels stays in 12 registers while
//! the 9 x cin products stream through; the weights of one 16-channel block (9 x cin x 16)
//! fit in L1. The im2col + GEMM path in `cpu.rs` is the fallback and the reference: the
//! two agree to float rounding (tests in `cpu.rs`).

/// Output pixels per micro-tile (6 x 2 accumulators + 2 weights + 1 broadcast = 15 registers).
const PX: usize = 6;
/// Output channels per micro-tile: two 8-lane vectors.
pub const CO_BLOCK: usize = 16;

/// Weights packed for the direct kernel: for each block of 16 output channels,
/// `[(ky * 3 + kx) * cin + ci][16]`, zero-padded past `cout`.
#[derive(Debug, Clone)]
pub struct DirectWeights {
    pub cin: usize,
    pub cout: usize,
    /// `blocks * 9 * cin * 16` values.
    pub wt: Vec<f32>,
    /// `blocks * 16` values, zero-padded.
    pub bias: Vec<f32>,
}

impl DirectWeights {
    /// From PyTorch-layout weights `[cout][cin][3][3]` and bias `[cout]`.
    pub fn pack(cin: usize, cout: usize, weight: &[f32], bias: &[f32]) -> DirectWeights {
        let blocks = cout.div_ceil(CO_BLOCK);
        let mut wt = vec![0.0; blocks * 9 * cin * CO_BLOCK];
        let mut b = vec![0.0; blocks * CO_BLOCK];
        for co in 0..cout {
            let (blk, lane) = (co / CO_BLOCK, co % CO_BLOCK);
            b[co] = bias[co];
            for ci in 0..cin {
                for t in 0..9 {
                    wt[((blk * 9 + t) * cin + ci) * CO_BLOCK + lane] =
                        weight[(co * cin + ci) * 9 + t];
                }
            }
        }
        DirectWeights {
            cin,
            cout,
            wt,
            bias: b,
        }
    }
}

/// Whether this CPU runs the direct kernel.
pub fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// One output row `y` of a 3x3 "same" convolution. `padded` is the input with a one-pixel
/// zero border: `(h + 2) x (w + 2) x cin`, HWC. `row` receives `w x cout` values.
///
/// # Safety
/// The CPU must support AVX2 and FMA ([`available`]); `padded` must hold `(h + 2) * (w + 2) * cin`
/// values with `y < h`, and `row` exactly `w * k.cout`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub unsafe fn conv_row(
    padded: &[f32],
    w: usize,
    y: usize,
    k: &DirectWeights,
    elu: bool,
    row: &mut [f32],
) {
    let mut x = 0;
    while x + PX <= w {
        tile::<PX>(padded, w, y, x, k, elu, row);
        x += PX;
    }
    match w - x {
        0 => {}
        1 => tile::<1>(padded, w, y, x, k, elu, row),
        2 => tile::<2>(padded, w, y, x, k, elu, row),
        3 => tile::<3>(padded, w, y, x, k, elu, row),
        4 => tile::<4>(padded, w, y, x, k, elu, row),
        _ => tile::<5>(padded, w, y, x, k, elu, row),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn tile<const P: usize>(
    padded: &[f32],
    w: usize,
    y: usize,
    x0: usize,
    k: &DirectWeights,
    elu: bool,
    row: &mut [f32],
) {
    use std::arch::x86_64::*;
    let (cin, cout) = (k.cin, k.cout);
    let pw = w + 2;
    let inp = padded.as_ptr();
    for blk in 0..cout.div_ceil(CO_BLOCK) {
        let wb = k.wt.as_ptr().add(blk * 9 * cin * CO_BLOCK);
        let b0 = _mm256_loadu_ps(k.bias.as_ptr().add(blk * CO_BLOCK));
        let b1 = _mm256_loadu_ps(k.bias.as_ptr().add(blk * CO_BLOCK + 8));
        let mut acc = [[b0, b1]; P];
        for ky in 0..3 {
            for kx in 0..3 {
                // Input pixel (x0 + p + kx - 1, y + ky - 1) sits at padded (x0 + p + kx, y + ky).
                let src = inp.add(((y + ky) * pw + x0 + kx) * cin);
                let wt = wb.add((ky * 3 + kx) * cin * CO_BLOCK);
                for ci in 0..cin {
                    let w0 = _mm256_loadu_ps(wt.add(ci * CO_BLOCK));
                    let w1 = _mm256_loadu_ps(wt.add(ci * CO_BLOCK + 8));
                    for (p, a) in acc.iter_mut().enumerate() {
                        let v = _mm256_broadcast_ss(&*src.add(p * cin + ci));
                        a[0] = _mm256_fmadd_ps(v, w0, a[0]);
                        a[1] = _mm256_fmadd_ps(v, w1, a[1]);
                    }
                }
            }
        }
        let n = (cout - blk * CO_BLOCK).min(CO_BLOCK);
        for (p, a) in acc.iter().enumerate() {
            let mut lanes = [0.0f32; CO_BLOCK];
            _mm256_storeu_ps(lanes.as_mut_ptr(), a[0]);
            _mm256_storeu_ps(lanes.as_mut_ptr().add(8), a[1]);
            if elu {
                for v in &mut lanes {
                    if *v < 0.0 {
                        *v = v.exp_m1();
                    }
                }
            }
            let dst = (x0 + p) * cout + blk * CO_BLOCK;
            row[dst..dst + n].copy_from_slice(&lanes[..n]);
        }
    }
}

/// The input with a one-pixel zero border, `(h + 2) x (w + 2) x c`.
pub fn pad_zero(data: &[f32], h: usize, w: usize, c: usize) -> Vec<f32> {
    let pw = w + 2;
    let mut out = vec![0.0; (h + 2) * pw * c];
    for y in 0..h {
        out[((y + 1) * pw + 1) * c..][..w * c].copy_from_slice(&data[y * w * c..][..w * c]);
    }
    out
}
