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

/// The pixels `x0..x1` of output row `y` of a 3x3 "same" convolution (the row's other
/// pixels are left as they are). `padded` is the input with a one-pixel zero border:
/// `(h + 2) x (w + 2) x cin`, HWC. `row` holds the row's `w x cout` values.
///
/// # Safety
/// The CPU must support AVX2 and FMA ([`available`]); `padded` must hold `(h + 2) * (w + 2) * cin`
/// values with `y < h`, `row` exactly `w * k.cout`, and `x0 <= x1 <= w`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
pub unsafe fn conv_span(
    padded: &[f32],
    w: usize,
    y: usize,
    x0: usize,
    x1: usize,
    k: &DirectWeights,
    elu: bool,
    row: &mut [f32],
) {
    let mut x = x0;
    while x + PX <= x1 {
        tile::<PX>(padded, w, y, x, k, elu, row);
        x += PX;
    }
    match x1 - x {
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
            let (v0, v1) = if elu {
                (elu8(a[0]), elu8(a[1]))
            } else {
                (a[0], a[1])
            };
            let dst = (x0 + p) * cout + blk * CO_BLOCK;
            if n == CO_BLOCK {
                let out = row[dst..dst + CO_BLOCK].as_mut_ptr();
                _mm256_storeu_ps(out, v0);
                _mm256_storeu_ps(out.add(8), v1);
            } else {
                let mut lanes = [0.0f32; CO_BLOCK];
                _mm256_storeu_ps(lanes.as_mut_ptr(), v0);
                _mm256_storeu_ps(lanes.as_mut_ptr().add(8), v1);
                row[dst..dst + n].copy_from_slice(&lanes[..n]);
            }
        }
    }
}

/// ELU on 8 lanes: `x` where `x >= 0`, `exp(x) - 1` below. The exponential is range-reduced
/// (`x = n ln 2 + r`, `|r| <= ln 2 / 2`) and its degree-6 Taylor polynomial in `r` (truncation
/// below 2e-7 relative) scaled by `2^n`; an absolute error near 1e-7, where scalar `exp_m1`
/// per value cost a fifth of the network's time.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn elu8(v: std::arch::x86_64::__m256) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    // Below -87 exp(x) - 1 is -1 in f32 anyway; the clamp keeps 2^n a normal number.
    let x = _mm256_max_ps(v, _mm256_set1_ps(-87.0));
    let n = _mm256_round_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(_mm256_mul_ps(
        x,
        _mm256_set1_ps(std::f32::consts::LOG2_E),
    ));
    // ln 2 in two parts, so n * ln2_hi is exact.
    let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(0.693_145_75), x);
    let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(1.428_606_8e-6), r);
    let mut p = _mm256_set1_ps(1.0 / 720.0);
    for c in [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0] {
        p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(c));
    }
    let two_n = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(
        _mm256_cvtps_epi32(n),
        _mm256_set1_epi32(127),
    )));
    let em1 = _mm256_sub_ps(_mm256_mul_ps(p, two_n), _mm256_set1_ps(1.0));
    let negative = _mm256_cmp_ps::<_CMP_LT_OQ>(v, _mm256_setzero_ps());
    _mm256_blendv_ps(v, em1, negative)
}

/// The input with a one-pixel zero border, `(h + 2) x (w + 2) x c`, written into `out`
/// (resized; the border zeroed, the interior copied: no value of its past use survives).
pub fn pad_zero_into(data: &[f32], h: usize, w: usize, c: usize, out: &mut Vec<f32>) {
    let (pw, row) = (w + 2, (w + 2) * c);
    out.resize((h + 2) * row, 0.0);
    out[..row].fill(0.0);
    out[(h + 1) * row..].fill(0.0);
    for y in 0..h {
        let dst = &mut out[(y + 1) * row..][..row];
        dst[..c].fill(0.0);
        dst[(pw - 1) * c..].fill(0.0);
        dst[c..(w + 1) * c].copy_from_slice(&data[y * w * c..][..w * c]);
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;

    #[test]
    fn vector_elu_matches_exp_m1() {
        if !available() {
            eprintln!("skipped: this CPU has no AVX2 + FMA");
            return;
        }
        let mut xs: Vec<f32> = (0..20_000).map(|i| -20.0 + i as f32 * 0.0011).collect();
        xs.extend([-1e3, -100.0, -87.5, -87.0, -1e-8, -0.0, 0.0, 1e-8, 3.0, 1e6]);
        let mut worst = 0.0f32;
        for chunk in xs.chunks(8) {
            let mut lanes = [0.0f32; 8];
            lanes[..chunk.len()].copy_from_slice(chunk);
            let mut out = [0.0f32; 8];
            // SAFETY: AVX2 + FMA checked above; both arrays hold 8 values.
            unsafe {
                use std::arch::x86_64::*;
                _mm256_storeu_ps(out.as_mut_ptr(), elu8(_mm256_loadu_ps(lanes.as_ptr())));
            }
            for (&x, &y) in lanes.iter().zip(&out) {
                let want = if x < 0.0 { x.exp_m1() } else { x };
                worst = worst.max((y - want).abs());
                assert!((y - want).abs() <= 3e-7, "elu({x}) = {y}, want {want}");
            }
        }
        eprintln!("max |elu8 - exp_m1| = {worst:e}");
    }
}
