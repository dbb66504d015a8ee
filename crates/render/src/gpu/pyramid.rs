//! Host side of the pyramid-spread defocus (CPU twin: [`crate::pyramid`]): per focus, one
//! frame that aggregates and spreads every level's kinds of cells, then composes the output.

use std::sync::Arc;

use super::context::{BufRef, Frame, FrameStats, GpuContext, Kernel, WG};
use super::image::{ImageLayout, RgbdInput};
use super::kernels::{dim, Keep, Output, Outputs};
use crate::backend::Progress;
use crate::error::RenderError;
use crate::foveated::{Foveation, FoveationPlan};
use crate::pyramid::{exact_offsets, LevelGrid, Region, Setup, BANDS, KINDS, MAX_LEVELS};
use bytemuck::{Pod, Zeroable};
use dioptra_core::{Diopters, EyeModel};

/// The uniform of shaders/pyramid.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct PyramidP {
    pub(super) w: u32,
    pub(super) h: u32,
    pub(super) top: u32,
    pub(super) level: u32,
    pub(super) k: f32,
    pub(super) q: f32,
    pub(super) kind: u32,
    pub(super) n_off: u32,
    pub(super) region: [u32; 4],
    pub(super) annulus: [f32; 4],
    pub(super) rec: [u32; 4],
    pub(super) out: [u32; 4],
    pub(super) edges: [[f32; 4]; 4],
    pub(super) levels: [[u32; 4]; 8],
}

fn groups(w: usize, h: usize) -> Result<[u32; 3], RenderError> {
    Ok([
        dim(w, "width")?.div_ceil(WG),
        dim(h, "height")?.div_ceil(WG),
        1,
    ])
}

/// The annulus as the shader takes it: an unbounded outer radius becomes a finite one no
/// image reaches (WGSL need not keep infinities).
fn annulus(r: &Region) -> [f32; 4] {
    [r.centre[0], r.centre[1], r.inner, r.outer.min(1e18)]
}

/// Pyramid defocus of `region` (every pixel when it covers the image), one frame per focus;
/// colour, depth and the exact pass's offsets are uploaded once.
pub(super) fn pyramid<'a>(
    ctx: &Arc<GpuContext>,
    input: impl Into<RgbdInput<'a>>,
    foci: &[Diopters],
    eye: &EyeModel,
    region: &Region,
    progress: Progress,
    keep: Keep,
) -> Result<(Vec<Output>, FrameStats), RenderError> {
    let input: RgbdInput = input.into();
    input.check()?;
    let (w, h) = (input.width(), input.height());
    let n = (w * h) as u64;
    let setups = foci
        .iter()
        .map(|&q| Setup::for_size(w, h, input.depth_range(), q, eye))
        .collect::<Result<Vec<_>, _>>()?;
    let offsets: Vec<[f32; 4]> = exact_offsets()
        .into_iter()
        .map(|(dx, dy, d)| [dx as f32, dy as f32, d, 0.0])
        .collect();
    let mut total = FrameStats::default();
    let mut out = Vec::with_capacity(foci.len());
    let mut inputs: Option<[BufRef; 3]> = None;
    for setup in &setups {
        let mut f = Frame::new(ctx)?;
        let [color, depth, off] = match &inputs {
            Some(b) => b.clone(),
            None => {
                let (color, depth) = input.buffers(ctx, &mut f)?;
                let b = [color, depth, f.upload("exact pass offsets", &offsets)?];
                inputs = Some(b.clone());
                b
            }
        };
        let dst = f.scratch("output image", 12 * n)?;
        // Black outside the region, as the CPU leaves it.
        f.clear(&dst);
        let region = Region {
            x1: region.x1.min(w),
            y1: region.y1.min(h),
            ..*region
        };
        if region.x0 < region.x1 && region.y0 < region.y1 {
            record(
                &mut f,
                setup,
                &region,
                [&color, &depth, &off, &dst],
                offsets.len(),
            )?;
        }
        let o = Outputs::record(&mut f, keep, &dst, ImageLayout::packed(w, h, 0), 0, 1);
        let (rb, s) = f.finish()?;
        total.add(&s);
        out.extend(o.take(ctx, &rb)?);
        progress(out.len());
    }
    Ok((out, total))
}

/// The uniform of shaders/foveated.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct FoveatedP {
    pub(super) w: u32,
    pub(super) h: u32,
    pub(super) a: u32,
    pub(super) b: u32,
    pub(super) top: u32,
    pub(super) present: u32,
    pub(super) _pad0: u32,
    pub(super) _pad1: u32,
    pub(super) offsets: [[u32; 4]; 2],
}

/// Foveated pyramid defocus ([`crate::foveated`]): per focus one frame that halves the input
/// layer by layer, renders each layer's region, and blends the layers.
pub(super) fn foveated<'a>(
    ctx: &Arc<GpuContext>,
    input: impl Into<RgbdInput<'a>>,
    foci: &[Diopters],
    eye: &EyeModel,
    fov: &Foveation,
    progress: Progress,
    keep: Keep,
) -> Result<(Vec<Output>, FrameStats), RenderError> {
    let input: RgbdInput = input.into();
    input.check()?;
    let (w, h) = (input.width(), input.height());
    let n = w * h;
    let plan = FoveationPlan::new(w, h, eye, fov)?;
    // Each layer's setup sized by the full image's depth range, as the CPU twin's.
    let range = input.depth_range();
    let sizes: Vec<(usize, usize)> = (0..=plan.top)
        .map(|k| (w.div_ceil(1 << k), h.div_ceil(1 << k)))
        .collect();
    let offsets: Vec<[f32; 4]> = exact_offsets()
        .into_iter()
        .map(|(dx, dy, d)| [dx as f32, dy as f32, d, 0.0])
        .collect();
    let mut layer_off = [[0u32; 4]; 2];
    let mut layers_len = 0usize;
    let mut present = 0u32;
    for l in &plan.layers {
        layer_off[l.level / 4][l.level % 4] = dim(layers_len, "layer offset")?;
        let (lw, lh) = sizes[l.level];
        layers_len += 3 * lw * lh;
        present |= 1 << l.level;
    }
    let mut total = FrameStats::default();
    let mut out = Vec::with_capacity(foci.len());
    for &q in foci {
        let mut f = Frame::new(ctx)?;
        let off = f.upload("exact pass offsets", &offsets)?;
        let grid = f.upload("acuity levels", &plan.levels)?;
        // The layers' inputs: the image, then each halved from the one before.
        let (color, depth) = input.buffers(ctx, &mut f)?;
        let mut inputs: Vec<[BufRef; 2]> = vec![[color, depth]];
        let deepest = plan.layers.last().map_or(0, |l| l.level);
        for k in 1..=deepest {
            let ((sw, sh), (dw, dh)) = (sizes[k - 1], sizes[k]);
            let next = [
                f.scratch("layer colour", 12 * (dw * dh) as u64)?,
                f.scratch("layer depth", 4 * (dw * dh) as u64)?,
            ];
            let p = FoveatedP {
                w: dim(sw, "width")?,
                h: dim(sh, "height")?,
                a: dim(dw, "width")?,
                b: dim(dh, "height")?,
                top: 0,
                present: 0,
                _pad0: 0,
                _pad1: 0,
                offsets: [[0; 4]; 2],
            };
            let [c, d] = &inputs[k - 1];
            let bufs = [c, d, &next[0], &next[1]];
            f.dispatch(Kernel::FvDownsample, &p, &bufs, groups(dw, dh)?)?;
            inputs.push(next);
        }
        let layers = f.scratch("foveated layers", 4 * layers_len.max(1) as u64)?;
        for l in &plan.layers {
            let (lw, lh) = sizes[l.level];
            let setup = Setup::for_size(lw, lh, range, q, eye)?;
            let dst = f.scratch("layer image", 12 * (lw * lh) as u64)?;
            f.clear(&dst);
            let [c, d] = &inputs[l.level];
            record(&mut f, &setup, &l.region, [c, d, &off, &dst], offsets.len())?;
            let at = layer_off[l.level / 4][l.level % 4] as u64;
            f.copy(&dst, 0, &layers, 4 * at, 12 * (lw * lh) as u64);
        }
        let dst = f.scratch("output image", 12 * n as u64)?;
        let p = FoveatedP {
            w: dim(w, "width")?,
            h: dim(h, "height")?,
            a: dim(plan.gw, "grid width")?,
            b: dim(plan.gh, "grid height")?,
            top: dim(plan.top, "layer count")?,
            present,
            _pad0: 0,
            _pad1: 0,
            offsets: layer_off,
        };
        f.dispatch(Kernel::FvBlend, &p, &[&grid, &layers, &dst], groups(w, h)?)?;
        let o = Outputs::record(&mut f, keep, &dst, ImageLayout::packed(w, h, 0), 0, 1);
        let (rb, s) = f.finish()?;
        total.add(&s);
        out.extend(o.take(ctx, &rb)?);
        progress(out.len());
    }
    Ok((out, total))
}

/// Records one focus's dispatches: per level and kind, aggregate then spread; then compose.
fn record(
    f: &mut Frame,
    setup: &Setup,
    region: &Region,
    [color, depth, off, dst]: [&BufRef; 4],
    n_off: usize,
) -> Result<(), RenderError> {
    let (w, h) = (setup.w, setup.h);
    let grids: Vec<LevelGrid> = (0..setup.top)
        .map(|m| LevelGrid::new(m, w, h, region))
        .collect();
    let mut levels = [[0u32; 4]; 8];
    let mut img_len = 0usize;
    let mut rec_len = 0usize;
    for (li, g) in grids.iter().enumerate() {
        levels[li] = [
            dim(g.lw, "level width")?,
            dim(g.lh, "level height")?,
            dim(g.scale, "level scale")?,
            dim(img_len, "level image offset")?,
        ];
        img_len += KINDS * g.lw * g.lh;
        rec_len = rec_len.max((g.rec[2] - g.rec[0]) * (g.rec[3] - g.rec[1]));
    }
    debug_assert!(grids.len() <= MAX_LEVELS);
    let mut edges = [[0.0f32; 4]; 4];
    for (b, &e) in setup.edges.iter().enumerate().take(BANDS + 1) {
        edges[b / 4][b % 4] = e;
    }
    let base = PyramidP {
        w: dim(w, "width")?,
        h: dim(h, "height")?,
        top: dim(setup.top, "level count")?,
        level: 0,
        k: setup.k,
        q: setup.q,
        kind: 0,
        n_off: dim(n_off, "offset count")?,
        region: [
            dim(region.x0, "region")?,
            dim(region.y0, "region")?,
            dim(region.x1, "region")?,
            dim(region.y1, "region")?,
        ],
        annulus: annulus(region),
        rec: [0; 4],
        out: [0; 4],
        edges,
        levels,
    };
    // At least one texel each, so an image with no level still binds valid buffers.
    let images = f.scratch("pyramid level images", 16 * img_len.max(1) as u64)?;
    let recs = f.scratch("pyramid cell records", 32 * rec_len.max(1) as u64)?;
    for (li, g) in grids.iter().enumerate() {
        let to_u32 = |r: [usize; 4]| -> Result<[u32; 4], RenderError> {
            Ok([
                dim(r[0], "cell")?,
                dim(r[1], "cell")?,
                dim(r[2], "cell")?,
                dim(r[3], "cell")?,
            ])
        };
        for kind in 0..KINDS {
            let p = PyramidP {
                level: dim(li, "level")?,
                kind: kind as u32,
                rec: to_u32(g.rec)?,
                out: to_u32(g.out)?,
                ..base
            };
            let rg = groups(g.rec[2] - g.rec[0], g.rec[3] - g.rec[1])?;
            f.dispatch(Kernel::PyAggregate, &p, &[color, depth, &recs], rg)?;
            let og = groups(g.out[2] - g.out[0], g.out[3] - g.out[1])?;
            f.dispatch(Kernel::PySpread, &p, &[&recs, &images], og)?;
        }
    }
    let cg = groups(region.x1 - region.x0, region.y1 - region.y0)?;
    f.dispatch(
        Kernel::PyCompose,
        &base,
        &[color, depth, off, &images, dst],
        cg,
    )?;
    Ok(())
}
