//! CPU inference. Convolutions run as a direct register-blocked kernel where the CPU has
//! AVX2 + FMA (`direct.rs`), else as im2col into row tiles with one GEMM per tile (the `gemm`
//! crate); rows or tiles in parallel with rayon. Activations are HWC so a row is one
//! contiguous slice.

use crate::arch::Arch;
use crate::direct::{self, DirectWeights};
use crate::error::{input, NetError};
use crate::graph::{forward, Ops};
use crate::tiles::{TileMap, TILE};
use crate::weights::Weights;
use rayon::prelude::*;

/// An activation: `h` x `w` pixels of `c` channels, HWC.
#[derive(Debug, Clone, PartialEq)]
pub struct Act {
    pub h: usize,
    pub w: usize,
    pub c: usize,
    pub data: Vec<f32>,
}

impl Act {
    pub fn new(h: usize, w: usize, c: usize, data: Vec<f32>) -> Result<Act, NetError> {
        if h.checked_mul(w).and_then(|n| n.checked_mul(c)) != Some(data.len()) {
            return Err(input(format!(
                "{h}x{w}x{c} activation needs {} values, got {}",
                h.saturating_mul(w).saturating_mul(c),
                data.len()
            )));
        }
        Ok(Act { h, w, c, data })
    }
    pub fn zeros(h: usize, w: usize, c: usize) -> Act {
        Act {
            h,
            w,
            c,
            data: vec![0.0; h * w * c],
        }
    }
    /// The `h` x `w` top-left crop, without a copy when that is all of it.
    pub fn into_crop(self, h: usize, w: usize) -> Act {
        if (h, w) == (self.h, self.w) {
            self
        } else {
            self.crop(h, w)
        }
    }
    /// The `h` x `w` top-left crop.
    pub fn crop(&self, h: usize, w: usize) -> Act {
        let (h, w) = (h.min(self.h), w.min(self.w));
        let mut data = Vec::with_capacity(h * w * self.c);
        for y in 0..h {
            data.extend_from_slice(&self.data[y * self.w * self.c..][..w * self.c]);
        }
        Act {
            h,
            w,
            c: self.c,
            data,
        }
    }
    /// Pads right and bottom by edge replication to a multiple of `r` (borrowed when it is
    /// one already: a 512 x 512 input of 8 channels is 8 MB to copy).
    pub fn pad_to_multiple(&self, r: usize) -> std::borrow::Cow<'_, Act> {
        let (h, w) = (self.h.div_ceil(r) * r, self.w.div_ceil(r) * r);
        if (h, w) == (self.h, self.w) {
            return std::borrow::Cow::Borrowed(self);
        }
        let mut data = Vec::with_capacity(h * w * self.c);
        for y in 0..h {
            let sy = y.min(self.h - 1);
            for x in 0..w {
                let sx = x.min(self.w - 1);
                data.extend_from_slice(&self.data[(sy * self.w + sx) * self.c..][..self.c]);
            }
        }
        std::borrow::Cow::Owned(Act {
            h,
            w,
            c: self.c,
            data,
        })
    }
}

/// Interleave (space-to-depth) at rate `r`; channel order `c * r^2 + dy * r + dx`.
pub fn space_to_depth(x: &Act, r: usize) -> Result<Act, NetError> {
    if r == 0 || x.h % r != 0 || x.w % r != 0 {
        return Err(input(format!(
            "{}x{} is not a multiple of the interleave rate {r}",
            x.w, x.h
        )));
    }
    let (h, w, c, rr) = (x.h / r, x.w / r, x.c, r * r);
    let mut out = vec![0.0; x.data.len()];
    out.par_chunks_mut(w * c * rr)
        .enumerate()
        .for_each(|(y, row)| {
            for xx in 0..w {
                let o = &mut row[xx * c * rr..][..c * rr];
                for dy in 0..r {
                    for dx in 0..r {
                        let src = &x.data[((y * r + dy) * x.w + xx * r + dx) * c..][..c];
                        for (ci, &v) in src.iter().enumerate() {
                            o[ci * rr + dy * r + dx] = v;
                        }
                    }
                }
            }
        });
    Act::new(h, w, c * rr, out)
}

/// De-interleave (depth-to-space), the inverse of [`space_to_depth`].
pub fn depth_to_space(x: &Act, r: usize) -> Result<Act, NetError> {
    let rr = r * r;
    if r == 0 || x.c % rr != 0 {
        return Err(input(format!(
            "{} channels do not divide by r^2 = {rr}",
            x.c
        )));
    }
    let (c, w) = (x.c / rr, x.w * r);
    let mut out = vec![0.0; x.data.len()];
    out.par_chunks_mut(w * c).enumerate().for_each(|(y, row)| {
        let (sy, dy) = (y / r, y % r);
        for xx in 0..w {
            let (sx, dx) = (xx / r, xx % r);
            let src = &x.data[(sy * x.w + sx) * x.c..][..x.c];
            for ci in 0..c {
                row[xx * c + ci] = src[ci * rr + dy * r + dx];
            }
        }
    });
    Act::new(x.h * r, w, c, out)
}

/// A convolution packed for GEMM: `wt[(ky*3 + kx)*cin + ci][co]`.
#[derive(Debug, Clone)]
struct Packed {
    cin: usize,
    cout: usize,
    wt: Vec<f32>,
    bias: Vec<f32>,
    /// The direct kernel's packing, when this CPU runs it.
    direct: Option<DirectWeights>,
}

/// Pixels per GEMM tile: big enough to amortise packing, small enough to stay in cache.
const TILE_PIXELS: usize = 2048;

fn conv3x3(x: &Act, k: &Packed, elu: bool) -> Result<Act, NetError> {
    if x.c != k.cin {
        return Err(input(format!(
            "convolution expects {} input channels, got {}",
            k.cin, x.c
        )));
    }
    match &k.direct {
        Some(d) => Ok(conv3x3_direct(x, d, elu, None)),
        None => conv3x3_gemm(x, k, elu),
    }
}

thread_local! {
    /// The padded input of this thread's last convolution, kept for the next: a fresh
    /// buffer of megabytes per layer costs more in page faults than the copy itself.
    static PADDED: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Padded inputs up to this many values are kept between convolutions (64 MB).
const KEEP_PADDED: usize = 16 << 20;

fn conv3x3_direct(x: &Act, k: &DirectWeights, elu: bool, spans: Option<&Spans>) -> Act {
    // A thread waiting inside rayon may run another convolution: that one gets its own buffer.
    let kept = PADDED.with(|p| p.try_borrow_mut().map(|mut p| std::mem::take(&mut *p)));
    let mut padded = kept.unwrap_or_default();
    direct::pad_zero_into(&x.data, x.h, x.w, x.c, &mut padded);
    let out = conv3x3_direct_padded(x, &padded, k, elu, spans);
    if padded.len() <= KEEP_PADDED {
        PADDED.with(|p| {
            if let Ok(mut p) = p.try_borrow_mut() {
                if p.capacity() < padded.capacity() {
                    *p = padded;
                }
            }
        });
    }
    out
}

fn conv3x3_direct_padded(
    x: &Act,
    padded: &[f32],
    k: &DirectWeights,
    elu: bool,
    spans: Option<&Spans>,
) -> Act {
    let (h, w, cout) = (x.h, x.w, k.cout);
    let mut out = vec![0.0f32; h * w * cout];
    let whole = [(0, w)];
    out.par_chunks_mut(w * cout)
        .enumerate()
        .for_each(|(y, row)| {
            let runs = spans.map_or(&whole[..], |s| &s.rows[y][..]);
            for &(x0, x1) in runs {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `direct` is only set when `direct::available()`; `padded` is the
                // (h + 2) x (w + 2) x cin border copy, y < h, `row` is w x cout and every
                // span lies within 0..w (`Spans::dilated` clamps them).
                unsafe {
                    direct::conv_span(padded, w, y, x0, x1, k, elu, row)
                }
                #[cfg(not(target_arch = "x86_64"))]
                let _ = (y, x0, x1, &row, elu, padded);
            }
        });
    Act {
        h,
        w,
        c: cout,
        data: out,
    }
}

/// The pixels of one activation that must be computed: per row, half-open `[x0, x1)` runs.
#[derive(Debug, Clone)]
struct Spans {
    rows: Vec<Vec<(usize, usize)>>,
}

impl Spans {
    /// The runs of `mask` (`w` x `h`) dilated by `k` pixels (a square).
    fn dilated(mask: &[bool], w: usize, h: usize, k: usize) -> Spans {
        // Rows first (a run per row grown by k), then the union over k rows up and down.
        let grown: Vec<Vec<(usize, usize)>> = (0..h)
            .map(|y| {
                let mut runs: Vec<(usize, usize)> = Vec::new();
                let row = &mask[y * w..][..w];
                let mut x = 0;
                while x < w {
                    if !row[x] {
                        x += 1;
                        continue;
                    }
                    let start = x;
                    while x < w && row[x] {
                        x += 1;
                    }
                    runs.push((start.saturating_sub(k), (x + k).min(w)));
                }
                runs
            })
            .collect();
        let rows = (0..h)
            .map(|y| {
                let mut all: Vec<(usize, usize)> = grown[y.saturating_sub(k)..(y + k + 1).min(h)]
                    .iter()
                    .flatten()
                    .copied()
                    .collect();
                all.sort_unstable();
                let mut merged: Vec<(usize, usize)> = Vec::with_capacity(all.len());
                for (a, b) in all {
                    match merged.last_mut() {
                        Some(last) if a <= last.1 => last.1 = last.1.max(b),
                        _ => merged.push((a, b)),
                    }
                }
                merged
            })
            .collect();
        Spans { rows }
    }
}

fn conv3x3_gemm(x: &Act, k: &Packed, elu: bool) -> Result<Act, NetError> {
    let (h, w, cin, cout) = (x.h, x.w, x.c, k.cout);
    let kdim = 9 * cin;
    let rows = (TILE_PIXELS / w.max(1)).max(1);
    let mut out = vec![0.0f32; h * w * cout];
    out.par_chunks_mut(rows * w * cout)
        .enumerate()
        .for_each_init(Vec::new, |col: &mut Vec<f32>, (t, chunk)| {
            let npix = chunk.len() / cout;
            let y0 = t * rows;
            col.clear();
            col.resize(npix * kdim, 0.0);
            for p in 0..npix {
                let (y, xx) = (y0 + p / w, p % w);
                let dst = &mut col[p * kdim..][..kdim];
                for ky in 0..3 {
                    let sy = y as isize + ky as isize - 1;
                    for kx in 0..3 {
                        let sx = xx as isize + kx as isize - 1;
                        let d = &mut dst[(ky * 3 + kx) * cin..][..cin];
                        if sy < 0 || sx < 0 || sy >= h as isize || sx >= w as isize {
                            d.fill(0.0);
                        } else {
                            d.copy_from_slice(
                                &x.data[(sy as usize * w + sx as usize) * cin..][..cin],
                            );
                        }
                    }
                }
            }
            for px in chunk.chunks_exact_mut(cout) {
                px.copy_from_slice(&k.bias);
            }
            // SAFETY: chunk is npix x cout, col is npix x kdim and wt is kdim x cout, all
            // row-major with the strides given; the buffers do not overlap.
            unsafe {
                gemm::gemm(
                    npix,
                    cout,
                    kdim,
                    chunk.as_mut_ptr(),
                    1,
                    cout as isize,
                    true,
                    col.as_ptr(),
                    1,
                    kdim as isize,
                    k.wt.as_ptr(),
                    1,
                    cout as isize,
                    1.0,
                    1.0,
                    false,
                    false,
                    false,
                    gemm::Parallelism::None,
                );
            }
            if elu {
                for v in chunk.iter_mut() {
                    if *v < 0.0 {
                        *v = v.exp_m1();
                    }
                }
            }
        });
    Act::new(h, w, cout, out)
}

/// A network ready for CPU inference.
#[derive(Debug, Clone)]
pub struct CpuNet {
    weights: Weights,
    packed: Vec<Packed>,
}

impl CpuNet {
    /// Packs `weights` for the fastest kernel this CPU runs.
    pub fn new(weights: Weights) -> Result<CpuNet, NetError> {
        Self::with_kernel(weights, direct::available())
    }

    /// Packs for the direct kernel when `use_direct` (and the CPU runs it), else for GEMM.
    pub fn with_kernel(weights: Weights, use_direct: bool) -> Result<CpuNet, NetError> {
        let use_direct = use_direct && direct::available();
        weights.arch.validate()?;
        if weights.convs.len() != weights.arch.conv_count() {
            return Err(NetError::BadArch(format!(
                "{} convolutions for an architecture of {}",
                weights.convs.len(),
                weights.arch.conv_count()
            )));
        }
        let packed = weights
            .convs
            .iter()
            .map(|c| {
                let mut wt = vec![0.0; 9 * c.cin * c.cout];
                for co in 0..c.cout {
                    for ci in 0..c.cin {
                        for t in 0..9 {
                            wt[(t * c.cin + ci) * c.cout + co] =
                                c.weight[(co * c.cin + ci) * 9 + t];
                        }
                    }
                }
                Packed {
                    cin: c.cin,
                    cout: c.cout,
                    wt,
                    bias: c.bias.clone(),
                    direct: use_direct
                        .then(|| DirectWeights::pack(c.cin, c.cout, &c.weight, &c.bias)),
                }
            })
            .collect();
        Ok(CpuNet { weights, packed })
    }

    pub fn arch(&self) -> &Arch {
        &self.weights.arch
    }
    pub fn weights(&self) -> &Weights {
        &self.weights
    }

    /// Runs the network on a full-resolution HWC input of `in_channels`; any size (padded to
    /// [`Arch::size_multiple`] internally, cropped back).
    pub fn forward(&self, x: &Act) -> Result<Act, NetError> {
        let arch = self.arch();
        check_input(arch, x)?;
        let padded = x.pad_to_multiple(arch.size_multiple());
        let y = forward(arch, self, padded.as_ref())?;
        Ok(y.into_crop(x.h, x.w))
    }
}

impl CpuNet {
    /// [`CpuNet::forward`] computed only where `tiles` needs it: the last layer on the
    /// pixels the map corrects ([`TileMap::corrects`], the only ones composed), each earlier
    /// layer on those grown by the receptive field still ahead of it, so there the output
    /// equals a full-image pass (the same kernel over the same values); elsewhere it is
    /// unspecified. Falls back to a full pass without the direct kernel or with a U-Net.
    pub fn forward_tiles(&self, x: &Act, tiles: &TileMap) -> Result<Act, NetError> {
        let arch = self.arch();
        let r = arch.rate;
        let sparse_ok = arch.unet_channels == 0
            && self.packed.iter().all(|p| p.direct.is_some())
            && TILE % r == 0;
        if !sparse_ok {
            return self.forward(x);
        }
        if (tiles.width, tiles.height) != (x.w, x.h) {
            return Err(input(format!(
                "tile map of {}x{} for a {}x{} input",
                tiles.width, tiles.height, x.w, x.h
            )));
        }
        // The last layer's wanted pixels, at interleaved resolution (padded size).
        let (hp, wp) = (x.h.div_ceil(r), x.w.div_ceil(r));
        let mut last = vec![false; hp * wp];
        for (y, row) in last.chunks_mut(wp).enumerate() {
            for (xx, v) in row.iter_mut().enumerate() {
                // An interleaved pixel holds r x r pixels of the image.
                *v = (0..r).any(|dy| (0..r).any(|dx| tiles.corrects(xx * r + dx, y * r + dy)));
            }
        }
        let needed = (0..arch.layers)
            .map(|i| Spans::dilated(&last, wp, hp, arch.layers - 1 - i))
            .collect();
        let sparse = Sparse { net: self, needed };
        let padded = x.pad_to_multiple(r);
        let y = forward(arch, &sparse, padded.as_ref())?;
        Ok(y.into_crop(x.h, x.w))
    }
}

/// [`CpuNet`]'s operations with each convolution computed on its needed pixels only.
struct Sparse<'a> {
    net: &'a CpuNet,
    /// Per layer, the pixels of its output that later layers read.
    needed: Vec<Spans>,
}

impl Ops for Sparse<'_> {
    type T = Act;
    type E = NetError;
    fn conv(&self, x: &Act, layer: usize, elu: bool) -> Result<Act, NetError> {
        let k = self
            .net
            .packed
            .get(layer)
            .ok_or_else(|| input(format!("no layer {layer}")))?;
        match (&k.direct, self.needed.get(layer)) {
            (Some(d), Some(s)) if x.c == k.cin && s.rows.len() == x.h => {
                Ok(conv3x3_direct(x, d, elu, Some(s)))
            }
            _ => conv3x3(x, k, elu),
        }
    }
    fn add(&self, a: &Act, b: &Act) -> Result<Act, NetError> {
        self.net.add(a, b)
    }
    fn concat(&self, a: &Act, b: &Act) -> Result<Act, NetError> {
        self.net.concat(a, b)
    }
    fn tanh01(&self, x: &Act) -> Result<Act, NetError> {
        self.net.tanh01(x)
    }
    fn space_to_depth(&self, x: &Act, r: usize) -> Result<Act, NetError> {
        space_to_depth(x, r)
    }
    fn depth_to_space(&self, x: &Act, r: usize) -> Result<Act, NetError> {
        depth_to_space(x, r)
    }
    fn avg_pool2(&self, x: &Act) -> Result<Act, NetError> {
        avg_pool2(x)
    }
    fn upsample2(&self, x: &Act) -> Result<Act, NetError> {
        upsample2(x)
    }
}

impl Ops for CpuNet {
    type T = Act;
    type E = NetError;
    fn conv(&self, x: &Act, layer: usize, elu: bool) -> Result<Act, NetError> {
        let k = self
            .packed
            .get(layer)
            .ok_or_else(|| input(format!("no layer {layer}")))?;
        conv3x3(x, k, elu)
    }
    fn add(&self, a: &Act, b: &Act) -> Result<Act, NetError> {
        if (a.h, a.w, a.c) != (b.h, b.w, b.c) {
            return Err(input("residual shapes differ"));
        }
        let data = a.data.par_iter().zip(&b.data).map(|(x, y)| x + y).collect();
        Act::new(a.h, a.w, a.c, data)
    }
    fn concat(&self, a: &Act, b: &Act) -> Result<Act, NetError> {
        if (a.h, a.w) != (b.h, b.w) {
            return Err(input("concatenated sizes differ"));
        }
        let mut data = Vec::with_capacity(a.data.len() + b.data.len());
        for (pa, pb) in a.data.chunks_exact(a.c).zip(b.data.chunks_exact(b.c)) {
            data.extend_from_slice(pa);
            data.extend_from_slice(pb);
        }
        Act::new(a.h, a.w, a.c + b.c, data)
    }
    fn tanh01(&self, x: &Act) -> Result<Act, NetError> {
        let data = x.data.par_iter().map(|v| 0.5 * v.tanh() + 0.5).collect();
        Act::new(x.h, x.w, x.c, data)
    }
    fn space_to_depth(&self, x: &Act, r: usize) -> Result<Act, NetError> {
        space_to_depth(x, r)
    }
    fn depth_to_space(&self, x: &Act, r: usize) -> Result<Act, NetError> {
        depth_to_space(x, r)
    }
    fn avg_pool2(&self, x: &Act) -> Result<Act, NetError> {
        avg_pool2(x)
    }
    fn upsample2(&self, x: &Act) -> Result<Act, NetError> {
        upsample2(x)
    }
}

/// 2x2 average pooling, stride 2.
pub fn avg_pool2(x: &Act) -> Result<Act, NetError> {
    if x.h % 2 != 0 || x.w % 2 != 0 {
        return Err(input(format!("{}x{} cannot be pooled by 2", x.w, x.h)));
    }
    let (h, w, c) = (x.h / 2, x.w / 2, x.c);
    let mut out = vec![0.0; h * w * c];
    out.par_chunks_mut(w * c).enumerate().for_each(|(y, row)| {
        for xx in 0..w {
            let o = &mut row[xx * c..][..c];
            for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                let src = &x.data[((2 * y + dy) * x.w + 2 * xx + dx) * c..][..c];
                for (a, &v) in o.iter_mut().zip(src) {
                    *a += 0.25 * v;
                }
            }
        }
    });
    Act::new(h, w, c, out)
}

/// Nearest-neighbour 2x upsampling.
pub fn upsample2(x: &Act) -> Result<Act, NetError> {
    let (w, c) = (x.w * 2, x.c);
    let mut out = vec![0.0; x.data.len() * 4];
    out.par_chunks_mut(w * c).enumerate().for_each(|(y, row)| {
        for xx in 0..w {
            row[xx * c..][..c].copy_from_slice(&x.data[((y / 2) * x.w + xx / 2) * c..][..c]);
        }
    });
    Act::new(x.h * 2, w, c, out)
}

/// A network input's shape checked against `arch` (CPU and GPU inference alike).
pub(crate) fn check_input(arch: &Arch, x: &Act) -> Result<(), NetError> {
    if x.c != arch.in_channels() || x.h == 0 || x.w == 0 {
        return Err(input(format!(
            "{} network expects a non-empty input of {} channels, got {}x{}x{}",
            arch.task.name(),
            arch.in_channels(),
            x.w,
            x.h,
            x.c
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::weights::SplitMix;

    fn random_act(h: usize, w: usize, c: usize, seed: u64) -> Act {
        let mut r = SplitMix(seed);
        Act::new(h, w, c, (0..h * w * c).map(|_| r.uniform()).collect()).unwrap()
    }

    /// Direct convolution, written independently of the im2col path.
    fn naive_conv(x: &Act, c: &crate::weights::Conv, elu: bool) -> Act {
        let mut out = Act::zeros(x.h, x.w, c.cout);
        for y in 0..x.h {
            for xx in 0..x.w {
                for co in 0..c.cout {
                    let mut s = c.bias[co] as f64;
                    for ci in 0..c.cin {
                        for ky in 0..3 {
                            for kx in 0..3 {
                                let (sy, sx) = (y as isize + ky - 1, xx as isize + kx - 1);
                                if sy >= 0 && sx >= 0 && (sy as usize) < x.h && (sx as usize) < x.w
                                {
                                    let v = x.data[(sy as usize * x.w + sx as usize) * x.c + ci];
                                    let k = c.weight
                                        [((co * c.cin + ci) * 3 + ky as usize) * 3 + kx as usize];
                                    s += (v * k) as f64;
                                }
                            }
                        }
                    }
                    let s = s as f32;
                    out.data[(y * x.w + xx) * c.cout + co] =
                        if elu && s < 0.0 { s.exp_m1() } else { s };
                }
            }
        }
        out
    }

    #[test]
    fn space_to_depth_order_and_inverse() {
        // 1 channel, 2x2 image at r=2: channels are the phases dy*2+dx.
        let x = Act::new(2, 2, 1, vec![1.0, 2.0, 3.0, 4.0]).unwrap();
        assert_eq!(
            space_to_depth(&x, 2).unwrap().data,
            vec![1.0, 2.0, 3.0, 4.0]
        );
        // 2 channels: channel-major, c * 4 + phase.
        let x = Act::new(2, 2, 2, vec![1.0, 10.0, 2.0, 20.0, 3.0, 30.0, 4.0, 40.0]).unwrap();
        let s = space_to_depth(&x, 2).unwrap();
        assert_eq!(s.data, vec![1.0, 2.0, 3.0, 4.0, 10.0, 20.0, 30.0, 40.0]);
        for r in [1, 2, 4] {
            let x = random_act(8, 12, 3, r as u64);
            let back = depth_to_space(&space_to_depth(&x, r).unwrap(), r).unwrap();
            assert_eq!(back, x);
        }
        assert!(space_to_depth(&random_act(5, 4, 1, 0), 2).is_err());
    }

    #[test]
    fn both_kernels_match_a_naive_convolution() {
        // Widths that do and do not fill a 6-pixel micro-tile or a GEMM tile, more rows than
        // one GEMM tile holds, and output channels below, at and across 16-channel blocks.
        for (h, w, cin, cout) in [
            (5, 7, 3, 4),
            (70, 40, 6, 5),
            (3, 2100, 2, 3),
            (9, 13, 32, 32),
            (4, 11, 20, 20),
            (6, 6, 5, 12),
        ] {
            let x = random_act(h, w, cin, 3);
            let mut rng = SplitMix(11);
            let c = crate::weights::Conv {
                cin,
                cout,
                weight: (0..cout * cin * 9).map(|_| rng.uniform()).collect(),
                bias: (0..cout).map(|_| rng.uniform()).collect(),
            };
            let mut arch = Arch::c1_small();
            arch.layers = 2;
            let mut w8 = Weights::random(&arch, 0).unwrap();
            w8.convs[0] = c.clone();
            // Each kernel's packing through CpuNet's own code; the direct kernel only where
            // this CPU runs it.
            for use_direct in [false, true] {
                let net = CpuNet::with_kernel(w8.clone(), use_direct).unwrap();
                assert_eq!(
                    net.packed[0].direct.is_some(),
                    use_direct && direct::available()
                );
                for elu in [false, true] {
                    let got = conv3x3(&x, &net.packed[0], elu).unwrap();
                    let want = naive_conv(&x, &c, elu);
                    assert_eq!((got.h, got.w, got.c), (want.h, want.w, want.c));
                    let err = got
                        .data
                        .iter()
                        .zip(&want.data)
                        .map(|(a, b)| (a - b).abs())
                        .fold(0.0, f32::max);
                    assert!(
                        err < 1e-4,
                        "{h}x{w}x{cin}->{cout} direct={use_direct}: max error {err}"
                    );
                }
            }
        }
    }

    #[test]
    fn pooling_averages_and_upsampling_repeats() {
        let x = Act::new(2, 4, 1, vec![1.0, 3.0, 5.0, 7.0, 3.0, 5.0, 7.0, 9.0]).unwrap();
        assert_eq!(avg_pool2(&x).unwrap().data, vec![3.0, 7.0]);
        let u = upsample2(&Act::new(1, 2, 2, vec![1.0, 2.0, 3.0, 4.0]).unwrap()).unwrap();
        assert_eq!((u.h, u.w, u.c), (2, 4, 2));
        assert_eq!(&u.data[..8], &[1.0, 2.0, 1.0, 2.0, 3.0, 4.0, 3.0, 4.0]);
        assert_eq!(&u.data[8..], &u.data[..8]);
        assert!(avg_pool2(&random_act(3, 4, 1, 0)).is_err());
    }

    #[test]
    fn forward_handles_odd_sizes_and_refuses_wrong_channels() {
        let net = CpuNet::new(Weights::random(&Arch::c1_small(), 1).unwrap()).unwrap();
        let y = net.forward(&random_act(9, 13, 5, 2)).unwrap();
        assert_eq!((y.h, y.w, y.c), (9, 13, 3));
        assert!(y.data.iter().all(|v| (0.0..=1.0).contains(v)));
        assert!(net.forward(&random_act(8, 8, 4, 2)).is_err());
        assert!(net.forward(&Act::zeros(0, 8, 5)).is_err());
    }

    #[test]
    fn the_network_is_translation_equivariant_by_the_rate() {
        // Shifting the input by r pixels shifts the output by r pixels (away from borders):
        // checks the interleave, residual wiring and de-interleave agree with each other.
        let mut arch = Arch::c1_small();
        arch.layers = 5;
        arch.channels = 8;
        let net = CpuNet::new(Weights::random(&arch, 5).unwrap()).unwrap();
        let big = random_act(40, 40, 5, 9);
        let a = net.forward(&big).unwrap();
        let shifted = Act::new(
            40,
            40,
            5,
            (0..40 * 40)
                .flat_map(|p| {
                    let (y, x) = (p / 40, p % 40);
                    let sx = (x + 2).min(39);
                    big.data[(y * 40 + sx) * 5..][..5].to_vec()
                })
                .collect(),
        )
        .unwrap();
        let b = net.forward(&shifted).unwrap();
        // The receptive field is 5 interleaved pixels (10 full); compare the middle.
        for y in 12..28 {
            for x in 12..26 {
                for c in 0..3 {
                    let va = a.data[(y * 40 + x + 2) * 3 + c];
                    let vb = b.data[(y * 40 + x) * 3 + c];
                    assert!((va - vb).abs() < 1e-5, "({x},{y},{c}): {va} vs {vb}");
                }
            }
        }
    }
}
