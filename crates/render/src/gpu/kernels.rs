//! Host side of each GPU method: the same checks as its CPU twin, uploads, dispatches and
//! readbacks through one [`Frame`] per output slice (a handful of submissions per call).

use std::sync::Arc;

use super::context::{BufRef, Frame, FrameStats, GpuContext, Kernel, Readback, Readbacks, WG, WG1};
pub(super) use super::image::planar;
use super::image::{GpuImage, GpuRgbd, ImageLayout, RgbdInput};
use super::GpuError;
use crate::backend::Foveated;
use crate::backend::Progress;
use crate::common::{check_focus, check_rgbd, coc_over, eye_for};
use crate::error::{invalid, mismatch, RenderError};
use crate::foveate::{log_polar_tables, LogPolar, FOV_CELL};
use crate::kernel::{disk_kernel, gaussian_taps, FftConv};
use crate::lightfield::{halton_disk, LightFieldParams, LEVEL_SIGMA, PREFILTER};
use crate::metrics::Quality;
use crate::multifocal::{
    check_optimize_inputs, check_planes, Layers, OptimizeParams, OptimizeReport,
};
use crate::retina::LfView;
use crate::views::{check_inputs, light_field_positions, RgbdView};
use bytemuck::{Pod, Zeroable};
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};

type Out<T> = Result<(T, FrameStats), RenderError>;

pub(super) fn dim(v: usize, what: &str) -> Result<u32, RenderError> {
    u32::try_from(v).map_err(|_| invalid(format!("{what} {v} is too large for the GPU backend")))
}

fn groups2(w: u32, h: u32, z: u32) -> [u32; 3] {
    [w.div_ceil(WG), h.div_ceil(WG), z]
}

fn image(data: &[f32], w: usize, h: usize) -> Result<RgbImage, RenderError> {
    Ok(ImageLayout::packed(w, h, 0).image(data)?)
}

/// Where a method leaves its output images: read back to the host, or in GPU memory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Keep {
    Host,
    Gpu,
}

/// An output image, where [`Keep`] put it.
pub(super) enum Output {
    Host(RgbImage),
    Gpu(GpuImage),
}

/// `count` output images in one buffer, the first at `first`, each `pitch` values after the
/// one before: read back when they go to the host (recorded in the frame that writes them).
pub(super) struct Outputs {
    dst: BufRef,
    first: ImageLayout,
    pitch: usize,
    count: usize,
    read: Option<Readback>,
}

impl Outputs {
    pub(super) fn record(
        f: &mut Frame,
        keep: Keep,
        dst: &BufRef,
        first: ImageLayout,
        pitch: usize,
        count: usize,
    ) -> Outputs {
        let end = first.offset + count.saturating_sub(1) * pitch + first.span();
        let read = (keep == Keep::Host).then(|| f.read(dst, 4 * end as u64));
        Outputs {
            dst: dst.clone(),
            first,
            pitch,
            count,
            read,
        }
    }

    /// The images, once the frame has finished.
    pub(super) fn take(
        self,
        ctx: &Arc<GpuContext>,
        rb: &Readbacks,
    ) -> Result<Vec<Output>, RenderError> {
        let data = self.read.map(|r| rb.f32s(r));
        (0..self.count)
            .map(|k| {
                let l = ImageLayout {
                    offset: self.first.offset + k * self.pitch,
                    ..self.first
                };
                Ok(match &data {
                    Some(d) => Output::Host(l.image(d.get(l.offset..).unwrap_or(&[]))?),
                    None => Output::Gpu(GpuImage::new(ctx, self.dst.clone(), l)),
                })
            })
            .collect()
    }
}

/// Output images as host images (reading back any left in GPU memory).
pub(super) fn on_host(out: Vec<Output>) -> Result<Vec<RgbImage>, RenderError> {
    out.into_iter()
        .map(|o| match o {
            Output::Host(i) => Ok(i),
            Output::Gpu(g) => Ok(g.read()?),
        })
        .collect()
}

/// Output images as images in GPU memory (each one kept with [`Keep::Gpu`]), their readbacks
/// counted in `reads`.
pub(super) fn on_gpu(
    out: Vec<Output>,
    reads: &Arc<std::sync::atomic::AtomicU64>,
) -> Result<Vec<GpuImage>, RenderError> {
    out.into_iter()
        .map(|o| match o {
            Output::Gpu(g) => Ok(g.counted_by(reads)),
            Output::Host(_) => Err(GpuError::Validation(
                "an output image was read back though asked to stay in GPU memory".into(),
            )
            .into()),
        })
        .collect()
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct GatherP {
    pub(super) w: u32,
    pub(super) h: u32,
    pub(super) n_off: u32,
    pub(super) reach: u32,
    pub(super) focus: f32,
    pub(super) pupil_m: f32,
    pub(super) pitch: f32,
    pub(super) _pad: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct SizeP {
    pub(super) w: u32,
    pub(super) h: u32,
    pub(super) k: u32,
    pub(super) _pad: u32,
}

/// Gather blur, one frame per focus; colour and depth are uploaded once.
pub(super) fn gather<'a>(
    ctx: &Arc<GpuContext>,
    input: impl Into<RgbdInput<'a>>,
    foci: &[Diopters],
    eye: &EyeModel,
    progress: Progress,
    keep: Keep,
) -> Out<Vec<Output>> {
    let input: RgbdInput = input.into();
    input.check()?;
    foci.iter().try_for_each(|&q| check_focus(q))?;
    let eye = eye_for(eye, input.width())?;
    let (w, h) = (input.width(), input.height());
    let (wu, hu) = (dim(w, "width")?, dim(h, "height")?);
    let n = (w * h) as u64;
    let mut total = FrameStats::default();
    let mut out = Vec::with_capacity(foci.len());
    let mut inputs: Option<(BufRef, BufRef)> = None;
    for &q in foci {
        let reach = (0.5 * coc_over(input.depth_range(), &eye, q) + 0.5)
            .ceil()
            .min(256.0) as isize;
        // The CPU's tap order exactly: distance, ties in generation order (stable sort).
        let mut offsets: Vec<[f32; 4]> = (-reach..=reach)
            .flat_map(|dy| {
                (-reach..=reach).map(move |dx| {
                    [
                        dx as f32,
                        dy as f32,
                        ((dx * dx + dy * dy) as f32).sqrt(),
                        0.0,
                    ]
                })
            })
            .filter(|o| o[2] <= reach as f32 + 0.5)
            .collect();
        offsets.sort_by(|a, b| a[2].total_cmp(&b[2]));
        let mut f = Frame::new(ctx)?;
        let (color, depth) = match &inputs {
            Some(b) => b.clone(),
            None => {
                let b = input.buffers(ctx, &mut f)?;
                inputs = Some(b.clone());
                b
            }
        };
        let off = f.upload("gather offsets", &offsets)?;
        let tex = f.scratch("packed texels", 16 * n)?;
        let radius = f.scratch("radius", 4 * n)?;
        let tmp = f.scratch("max filter", 4 * n)?;
        let lmax = f.scratch("max filter", 4 * n)?;
        let dst = f.scratch("output image", 12 * n)?;
        let p = GatherP {
            w: wu,
            h: hu,
            n_off: dim(offsets.len(), "offset count")?,
            reach: reach as u32,
            focus: q.0,
            pupil_m: eye.pupil_diameter.to_meters().0,
            pitch: eye.pixel_pitch_tan(),
            _pad: 0,
        };
        let g = groups2(wu, hu, 1);
        f.dispatch(Kernel::GatherPrep, &p, &[&color, &depth, &tex, &radius], g)?;
        f.dispatch(Kernel::MaxH, &p, &[&radius, &tmp], g)?;
        f.dispatch(Kernel::MaxV, &p, &[&tmp, &lmax], g)?;
        f.dispatch(Kernel::Gather, &p, &[&tex, &depth, &lmax, &off, &dst], g)?;
        let o = Outputs::record(&mut f, keep, &dst, ImageLayout::packed(w, h, 0), 0, 1);
        let (rb, s) = f.finish()?;
        total.add(&s);
        out.extend(o.take(ctx, &rb)?);
        progress(out.len());
    }
    Ok((out, total))
}

/// Linear blending in one dispatch: one output image per plane.
pub(super) fn linear_blend<'a>(
    ctx: &Arc<GpuContext>,
    input: impl Into<RgbdInput<'a>>,
    planes: &[Diopters],
    keep: Keep,
) -> Out<Vec<Output>> {
    let input: RgbdInput = input.into();
    check_planes(planes)?;
    input.check()?;
    let (w, h) = (input.width(), input.height());
    let (n, np) = ((w * h) as u64, planes.len());
    let mut f = Frame::new(ctx)?;
    let (color, depth) = input.buffers(ctx, &mut f)?;
    let pl: Vec<f32> = planes.iter().map(|p| p.0).collect();
    let pbuf = f.upload("planes", &pl)?;
    let bytes = 12 * n * np as u64;
    let dst = f.scratch("layer stack", bytes)?;
    linear_blend_into(&mut f, [&color, &depth, &pbuf, &dst], w, h, np)?;
    let layout = ImageLayout::packed(w, h, 0);
    let o = Outputs::record(&mut f, keep, &dst, layout, 3 * w * h, np);
    let (rb, s) = f.finish()?;
    Ok((o.take(ctx, &rb)?, s))
}

/// Records linear blending of a `w` x `h` input (planar colour, depth, `np` planes) into
/// `bufs[3]`: plane-major, then channel, planar.
pub(super) fn linear_blend_into(
    f: &mut Frame,
    bufs: [&BufRef; 4],
    w: usize,
    h: usize,
    np: usize,
) -> Result<(), RenderError> {
    let (wu, hu) = (dim(w, "width")?, dim(h, "height")?);
    let p = SizeP {
        w: wu,
        h: hu,
        k: dim(np, "plane count")?,
        _pad: 0,
    };
    f.dispatch(Kernel::LinearBlend, &p, &bufs, groups2(wu, hu, 1))?;
    Ok(())
}

/// Convolves `layers` (same size) with per-focus, per-layer disk kernels and sums over the
/// layers: `kernels[f][l]` is the diameter for focus f and layer l. Foci are batched per
/// dispatch as far as the output buffer limit allows.
fn convolve_sum(
    ctx: &GpuContext,
    layers: &[&RgbImage],
    diameters: &[Vec<f32>],
) -> Out<Vec<RgbImage>> {
    let (w, h) = (layers[0].width(), layers[0].height());
    let (wu, hu) = (dim(w, "width")?, dim(h, "height")?);
    let n = (w * h) as u64;
    let nl = layers.len();
    let mut kinfo: Vec<[u32; 4]> = Vec::new();
    let mut weights: Vec<f32> = Vec::new();
    for row in diameters {
        for &d in row {
            let k = disk_kernel(d);
            kinfo.push([dim(weights.len(), "kernel size")?, k.radius as u32, 0, 0]);
            weights.extend_from_slice(&k.weights);
        }
    }
    let mut f = Frame::new(ctx)?;
    let mut all = Vec::with_capacity(3 * w * h * nl);
    for l in layers {
        all.extend_from_slice(&planar(l));
    }
    let lbuf = f.upload("layer images", &all)?;
    let kbuf = f.upload("kernel table", &kinfo)?;
    let wbuf = f.upload("kernel weights", &weights)?;
    let max = ctx.max_binding();
    let per = ((max / (12 * n)) as usize).clamp(1, 1024);
    let mut reads = Vec::new();
    for (c, chunk) in diameters.chunks(per).enumerate() {
        let nf = chunk.len();
        // The chunk's kernel rows start at c * per * nl: pass them as their own table.
        let rows: Vec<[u32; 4]> = kinfo[c * per * nl..(c * per + nf) * nl].to_vec();
        let kb = if c == 0 && nf == diameters.len() {
            kbuf.clone()
        } else {
            f.upload("kernel table", &rows)?
        };
        let dst = f.scratch("retinal images", 12 * n * nf as u64)?;
        let p = SizeP {
            w: wu,
            h: hu,
            k: nl as u32,
            _pad: 0,
        };
        f.dispatch(
            Kernel::Convolve,
            &p,
            &[&lbuf, &kb, &wbuf, &dst],
            groups2(wu, hu, nf as u32),
        )?;
        reads.push((f.read(&dst, 12 * n * nf as u64), nf));
    }
    let (rb, s) = f.finish()?;
    let mut out = Vec::with_capacity(diameters.len());
    for (r, nf) in reads {
        let data = rb.f32s(r);
        for k in 0..nf {
            out.push(image(data.get(k * 3 * w * h..).unwrap_or(&[]), w, h)?);
        }
    }
    Ok((out, s))
}

pub(super) fn retina_varifocal(
    ctx: &GpuContext,
    image: &RgbImage,
    display: Diopters,
    focus: Diopters,
    eye: &EyeModel,
) -> Out<RgbImage> {
    let eye = crate::retina::check_varifocal_inputs(image, display, focus, eye)?;
    let d = eye.coc_px(display, focus);
    let (mut v, s) = convolve_sum(ctx, &[image], &[vec![d]])?;
    let img = v
        .pop()
        .ok_or_else(|| GpuError::Validation("no image".into()))?;
    Ok((img, s))
}

pub(super) fn retina_multifocal(
    ctx: &GpuContext,
    layers: &Layers,
    foci: &[Diopters],
    eye: &EyeModel,
) -> Out<Vec<RgbImage>> {
    if foci.is_empty() {
        return Ok((Vec::new(), FrameStats::default()));
    }
    layers.check()?;
    foci.iter().try_for_each(|&q| check_focus(q))?;
    let eye = eye_for(eye, layers.width())?;
    let diameters: Vec<Vec<f32>> = foci
        .iter()
        .map(|&q| layers.planes.iter().map(|&p| eye.coc_px(p, q)).collect())
        .collect();
    let imgs: Vec<&RgbImage> = layers.images.iter().collect();
    convolve_sum(ctx, &imgs, &diameters)
}

pub(super) fn retina_lightfield(
    ctx: &GpuContext,
    views: &[LfView],
    spacing: f32,
    focus: Diopters,
    eye: &EyeModel,
) -> Out<RgbImage> {
    let crate::retina::LightFieldInputs {
        w,
        h,
        eye,
        weights,
        total,
    } = crate::retina::check_lightfield_inputs(views, spacing, focus, eye)?;
    let (wu, hu) = (dim(w, "width")?, dim(h, "height")?);
    let pitch = eye.pixel_pitch_tan();
    // Views outside the pupil carry no weight: they are never uploaded.
    let used: Vec<(&LfView, [f32; 4])> = views
        .iter()
        .zip(&weights)
        .filter(|(_, &wt)| wt != 0.0)
        .map(|(v, &wt)| {
            let sx = v.position[0] * focus.0 / pitch;
            let sy = v.position[1] * focus.0 / pitch;
            (v, [sx, sy, wt / total, 0.0])
        })
        .collect();
    let n = (w * h) as u64;
    let max = ctx.max_binding();
    // Batches of at most 16 views keep uploads and compute overlapping on a real GPU.
    let per = ((max / (12 * n)) as usize).clamp(1, 16);
    let mut f = Frame::new(ctx)?;
    let dst = f.zeroed("retinal image", 12 * n)?;
    for batch in used.chunks(per) {
        let mut data = Vec::with_capacity(batch.len() * 3 * w * h);
        for (v, _) in batch {
            data.extend_from_slice(&planar(&v.image));
        }
        let vb = f.upload("light-field views", &data)?;
        let params: Vec<[f32; 4]> = batch.iter().map(|b| b.1).collect();
        let pb = f.upload("view shifts", &params)?;
        let p = SizeP {
            w: wu,
            h: hu,
            k: batch.len() as u32,
            _pad: 0,
        };
        f.dispatch(Kernel::ShiftAdd, &p, &[&vb, &pb, &dst], groups2(wu, hu, 1))?;
    }
    let r = f.read(&dst, 12 * n);
    let (rb, s) = f.finish()?;
    Ok((image(&rb.f32s(r), w, h)?, s))
}

/// Separable blur of `planes` planes of `src` into a fresh buffer (rows, then columns).
fn blur(
    f: &mut Frame,
    src: &BufRef,
    planes: u32,
    w: u32,
    h: u32,
    taps: &[f32],
) -> Result<BufRef, RenderError> {
    let bytes = 4 * (w as u64) * (h as u64) * planes as u64;
    let tb = f.upload("blur taps", taps)?;
    let tmp = f.scratch("blur", bytes)?;
    let dst = f.scratch("blur", bytes)?;
    let p = SizeP {
        w,
        h,
        k: taps.len() as u32,
        _pad: 0,
    };
    f.dispatch(Kernel::BlurH, &p, &[src, &tb, &tmp], groups2(w, h, planes))?;
    f.dispatch(Kernel::BlurV, &p, &[&tmp, &tb, &dst], groups2(w, h, planes))?;
    Ok(dst)
}

/// PSNR and SSIM in one frame: per-workgroup partial sums, added on the host in f64.
pub(super) fn quality(
    ctx: &GpuContext,
    a: &RgbImage,
    b: &RgbImage,
    mask: Option<&Plane>,
) -> Out<Quality> {
    crate::metrics::check(a, b, mask)?;
    let (w, h) = (a.width(), a.height());
    let (wu, hu) = (dim(w, "width")?, dim(h, "height")?);
    let n = w * h;
    let groups = dim(n.div_ceil(WG1 as usize), "pixel count")?;
    let ones;
    let m = match mask {
        Some(m) => m.data(),
        None => {
            ones = vec![1.0f32; n];
            &ones[..]
        }
    };
    let selected = m.iter().filter(|&&v| v > 0.5).count() * 3;
    let mut f = Frame::new(ctx)?;
    let ab = f.upload("image a", &planar(a))?;
    let bb = f.upload("image b", &planar(b))?;
    let mb = f.upload("mask", m)?;
    let p = SizeP {
        w: wu,
        h: hu,
        k: 0,
        _pad: 0,
    };
    let se = f.scratch("partial sums", 4 * groups as u64)?;
    f.dispatch(Kernel::PsnrSum, &p, &[&ab, &bb, &mb, &se], [groups, 1, 1])?;
    let q = f.scratch("ssim terms", 4 * 15 * n as u64)?;
    f.dispatch(Kernel::SsimPrep, &p, &[&ab, &bb, &q], groups2(wu, hu, 1))?;
    let qb = blur(&mut f, &q, 15, wu, hu, &gaussian_taps(1.5))?;
    let ss = f.scratch("partial sums", 4 * groups as u64)?;
    f.dispatch(Kernel::SsimSum, &p, &[&qb, &mb, &ss], [groups, 1, 1])?;
    let (r1, r2) = (
        f.read(&se, 4 * groups as u64),
        f.read(&ss, 4 * groups as u64),
    );
    let (rb, s) = f.finish()?;
    let sum = |v: Vec<f32>| v.iter().map(|&x| x as f64).sum::<f64>();
    let mse = sum(rb.f32s(r1)) / selected as f64;
    let psnr = if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    };
    Ok((
        Quality {
            psnr,
            ssim: sum(rb.f32s(r2)) / selected as f64,
        },
        s,
    ))
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct LfP {
    pub(super) w: u32,
    pub(super) h: u32,
    pub(super) nv: u32,
    pub(super) v0: u32,
    pub(super) focus: f32,
    pub(super) pupil_m: f32,
    pub(super) pitch: f32,
    pub(super) spacing: f32,
    pub(super) lens_f: f32,
    pub(super) top: u32,
    pub(super) nlev: u32,
    /// Stride between the splat kernels' depth maps: 0 (one map) or w * h (one per view).
    pub(super) dstride: u32,
}

/// Light-field depth of field: the pyramid once per call, then one frame per focus.
pub(super) fn lightfield<'a>(
    ctx: &Arc<GpuContext>,
    input: impl Into<RgbdInput<'a>>,
    foci: &[Diopters],
    eye: &EyeModel,
    params: LightFieldParams,
    progress: Progress,
    keep: Keep,
) -> Out<Vec<Output>> {
    let input: RgbdInput = input.into();
    input.check()?;
    crate::lightfield::check_lightfield_params(&params)?;
    foci.iter().try_for_each(|&q| check_focus(q))?;
    let eye = eye_for(eye, input.width())?;
    let (w, h) = (input.width(), input.height());
    let (wu, hu) = (dim(w, "width")?, dim(h, "height")?);
    let n = (w * h) as u64;
    let pitch = eye.pixel_pitch_tan();
    let radius = 0.5 * eye.pupil_diameter.to_meters().0;
    let views: Vec<[f32; 4]> = halton_disk(params.views)
        .into_iter()
        .map(|p| {
            let l = [p[0] * radius, p[1] * radius];
            [-l[0] / pitch, -l[1] / pitch, l[0], l[1]]
        })
        .collect();
    let spacing = 1.0 / (params.views as f32).sqrt();
    let top = if params.mip { LEVEL_SIGMA.len() - 1 } else { 0 };
    let level_below = |sigma: f32| {
        let mut l = 0;
        while l < top && LEVEL_SIGMA[l + 1] < sigma {
            l += 1;
        }
        l
    };
    // The levels the sharpest-to-blurriest focus of this call reads, built once.
    let nlev = foci
        .iter()
        .map(|&q| {
            let coc = coc_over(input.depth_range(), &eye, q);
            (level_below(PREFILTER * coc * spacing) + 1).min(top) + 1
        })
        .max()
        .unwrap_or(1);
    let max = ctx.max_binding();
    let chunk = ((max / (4 * n)) as usize).clamp(1, params.views);
    let mut total = FrameStats::default();
    let mut out = Vec::with_capacity(foci.len());
    let mut shared: Option<(BufRef, BufRef, BufRef, BufRef)> = None;
    for &q in foci {
        let mut f = Frame::new(ctx)?;
        let (color, depth, levels, vbuf) = match &shared {
            Some(s) => s.clone(),
            None => {
                let (color, depth) = input.buffers(ctx, &mut f)?;
                let vbuf = f.upload("lens samples", &views)?;
                let levels = f.scratch("Gaussian pyramid", 12 * n * nlev as u64)?;
                f.copy(&color, 0, &levels, 0, 12 * n);
                for (l, &sigma) in LEVEL_SIGMA.iter().enumerate().take(nlev).skip(1) {
                    let b = blur(&mut f, &color, 3, wu, hu, &gaussian_taps(sigma))?;
                    f.copy(&b, 0, &levels, 12 * n * l as u64, 12 * n);
                }
                let s = (color, depth, levels, vbuf);
                shared = Some(s.clone());
                s
            }
        };
        let mut p = LfP {
            w: wu,
            h: hu,
            nv: 0,
            v0: 0,
            focus: q.0,
            pupil_m: eye.pupil_diameter.to_meters().0,
            pitch,
            spacing,
            lens_f: eye.lens_to_retina.to_meters().0,
            top: top as u32,
            nlev: nlev as u32,
            dstride: 0,
        };
        let g = groups2(wu, hu, 1);
        let pre = f.scratch("prefiltered colour", 16 * n)?;
        f.dispatch(Kernel::LfPrefilter, &p, &[&levels, &depth, &pre], g)?;
        let acc = f.zeroed("accumulator", 16 * n)?;
        let dkey = f.scratch("depth keys", 4 * n * chunk as u64)?;
        let ikey = f.scratch("index keys", 4 * n * chunk as u64)?;
        for v0 in (0..params.views).step_by(chunk) {
            let nv = chunk.min(params.views - v0);
            p.v0 = v0 as u32;
            p.nv = nv as u32;
            f.clear(&dkey);
            f.clear(&ikey);
            let gz = groups2(wu, hu, nv as u32);
            f.dispatch(Kernel::LfSplatDepth, &p, &[&depth, &vbuf, &dkey], gz)?;
            f.dispatch(Kernel::LfSplatIndex, &p, &[&depth, &vbuf, &dkey, &ikey], gz)?;
            f.dispatch(
                Kernel::LfAccumulate,
                &p,
                &[&dkey, &ikey, &pre, &vbuf, &acc],
                g,
            )?;
        }
        let dst = f.scratch("output image", 12 * n)?;
        f.dispatch(Kernel::LfFinish, &p, &[&acc, &color, &dst], g)?;
        let o = Outputs::record(&mut f, keep, &dst, ImageLayout::packed(w, h, 0), 0, 1);
        let (rb, s) = f.finish()?;
        total.add(&s);
        out.extend(o.take(ctx, &rb)?);
        progress(out.len());
    }
    Ok((out, total))
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct OptP {
    pub(super) pw: u32,
    pub(super) ph: u32,
    pub(super) np: u32,
    pub(super) nf: u32,
    pub(super) step: f32,
    pub(super) mom: f32,
    pub(super) len: u32,
    pub(super) _pad: u32,
}

/// Adds `len` squared values of `src` into per-workgroup partials and reads them back.
fn sq_sum(f: &mut Frame, p: &OptP, src: &BufRef, len: u64) -> Result<Readback, RenderError> {
    let groups = len.div_ceil(WG1 as u64);
    let gx = groups.min(32768);
    let gy = groups.div_ceil(gx);
    let out = f.scratch("partial sums", 4 * gx * gy)?;
    let q = OptP {
        len: dim(len as usize, "residual length")?,
        ..*p
    };
    f.dispatch(
        Kernel::OptSqSum,
        &q,
        &[src, &out],
        [gx as u32, gy as u32, 1],
    )?;
    Ok(f.read(&out, 4 * gx * gy))
}

/// Optimized blending: the CPU's FISTA on the CPU's padded grid, step 1 / L with the same
/// Gershgorin bound (computed on the host from the kernel spectra). One submission for the
/// RMS every 10 iterations and one for the 10 iterations themselves.
#[allow(clippy::too_many_arguments)]
pub(super) fn optimized_blend(
    ctx: &Arc<GpuContext>,
    targets: &[RgbImage],
    foci: &[Diopters],
    planes: &[Diopters],
    eye: &EyeModel,
    init: Option<&Layers>,
    params: OptimizeParams,
    progress: Progress,
    keep: Keep,
) -> Out<(Vec<Output>, OptimizeReport)> {
    let (w, h) = check_optimize_inputs(targets, foci, planes, init, &params)?;
    let eye = eye_for(eye, w)?;
    let (np, nf) = (planes.len(), foci.len());
    let ks: Vec<Vec<crate::kernel::Kernel>> = foci
        .iter()
        .map(|&q| {
            planes
                .iter()
                .map(|&p| disk_kernel(eye.coc_px(p, q)))
                .collect()
        })
        .collect();
    let max_r = ks.iter().flatten().map(|k| k.radius).max().unwrap_or(0);
    let conv = FftConv::new(w, h, max_r);
    let (pw, ph) = (conv.pw, conv.ph);
    let pn = pw * ph;
    // Lipschitz bound exactly as the CPU builds it: kernel spectra in pairs, M(f) summed over
    // the focal samples, Gershgorin over rows.
    let tri = |a: usize, b: usize| if a <= b { a * np + b } else { b * np + a };
    let mut m = vec![vec![0.0f32; pn]; np * np];
    for row in &ks {
        let mut spectra = Vec::with_capacity(np);
        for pair in row.chunks(2) {
            let b = pair.get(1).cloned().unwrap_or_else(|| disk_kernel(0.0));
            let (sa, sb) = conv.kernel_spectra(&pair[0], &b);
            spectra.push(sa);
            if pair.len() == 2 {
                spectra.push(sb);
            }
        }
        for a in 0..np {
            for b in a..np {
                for (f, v) in m[tri(a, b)].iter_mut().enumerate() {
                    *v += spectra[a][f] * spectra[b][f];
                }
            }
        }
    }
    let lipschitz = (0..pn)
        .map(|f| {
            (0..np)
                .map(|a| (0..np).map(|b| m[tri(a, b)][f].abs()).sum::<f32>())
                .fold(0.0f32, f32::max)
        })
        .fold(0.0f32, f32::max)
        .max(1e-6);
    drop(m);
    let mut kinfo: Vec<[u32; 4]> = Vec::with_capacity(nf * np);
    let mut weights: Vec<f32> = Vec::new();
    for k in ks.iter().flatten() {
        kinfo.push([dim(weights.len(), "kernel size")?, k.radius as u32, 0, 0]);
        weights.extend_from_slice(&k.weights);
    }
    let mut tpad = Vec::with_capacity(nf * 3 * pn);
    for t in targets {
        for c in &t.channels {
            tpad.extend_from_slice(&conv.pad(c));
        }
    }
    let mut start = Vec::with_capacity(np * 3 * pn);
    for i in 0..np {
        for c in 0..3 {
            let plane = match init {
                Some(l) => l.images[i].channels[c].clone(),
                None => {
                    let mean: Vec<f32> = (0..w * h)
                        .map(|p| {
                            targets.iter().map(|t| t.channels[c].data()[p]).sum::<f32>()
                                / (nf * np) as f32
                        })
                        .collect();
                    Plane::from_vec(w, h, mean).unwrap_or_else(|_| Plane::new(w, h, 0.0))
                }
            };
            start.extend_from_slice(&conv.pad(&plane));
        }
    }
    let (pwu, phu) = (dim(pw, "padded width")?, dim(ph, "padded height")?);
    let mut p = OptP {
        pw: pwu,
        ph: phu,
        np: np as u32,
        nf: nf as u32,
        step: 1.0 / lipschitz,
        mom: 0.0,
        len: 0,
        _pad: 0,
    };
    let rlen = (nf * 3 * pn) as u64;
    let samples = rlen as f64;
    let mut total = FrameStats::default();
    let mut f = Frame::new(ctx)?;
    let tb = f.upload("padded targets", &tpad)?;
    let kb = f.upload("kernel table", &kinfo)?;
    let wb = f.upload("kernel weights", &weights)?;
    let xb = f.upload("layers", &start)?;
    let yb = f.scratch("layers", 4 * start.len() as u64)?;
    f.copy(&xb, 0, &yb, 0, 4 * start.len() as u64);
    let rb = f.scratch("residuals", 4 * rlen)?;
    let gres = groups2(pwu, phu, nf as u32);
    let gstep = groups2(pwu, phu, np as u32);
    let rms_of = |v: Vec<f32>| (v.iter().map(|&x| x as f64).sum::<f64>() / samples).sqrt();
    let mut report = OptimizeReport {
        iterations: 0,
        rms: Vec::new(),
        converged: false,
    };
    let mut t_k = 1.0f64;
    let mut last_rms = f64::INFINITY;
    let mut it = 0;
    while it < params.iterations {
        // The RMS at y before this block's first step (the CPU samples it every 10).
        f.dispatch(Kernel::OptResidual, &p, &[&yb, &tb, &kb, &wb, &rb], gres)?;
        let r = sq_sum(&mut f, &p, &rb, rlen)?;
        let (res, s) = f.finish()?;
        total.add(&s);
        let rms = rms_of(res.f32s(r));
        report.rms.push((it, rms));
        if params.tolerance > 0.0
            && last_rms.is_finite()
            && (last_rms - rms) <= params.tolerance * last_rms
        {
            report.converged = true;
            report.iterations = it;
            f = Frame::new(ctx)?;
            break;
        }
        last_rms = rms;
        f = Frame::new(ctx)?;
        let end = (it + 10).min(params.iterations);
        for k in it..end {
            if k > it {
                f.dispatch(Kernel::OptResidual, &p, &[&yb, &tb, &kb, &wb, &rb], gres)?;
            }
            let t_next = 0.5 * (1.0 + (1.0 + 4.0 * t_k * t_k).sqrt());
            p.mom = ((t_k - 1.0) / t_next) as f32;
            f.dispatch(Kernel::OptStep, &p, &[&rb, &kb, &wb, &xb, &yb], gstep)?;
            t_k = t_next;
        }
        let (_, s) = f.finish()?;
        total.add(&s);
        for k in it..end {
            report.iterations = k + 1;
            progress(k + 1);
        }
        it = end;
        f = Frame::new(ctx)?;
    }
    // Final objective at the returned (projected) layers.
    f.dispatch(Kernel::OptResidual, &p, &[&xb, &tb, &kb, &wb, &rb], gres)?;
    let r = sq_sum(&mut f, &p, &rb, rlen)?;
    // Each layer's planes on the padded grid, the image `margin` in from its corner.
    let first = ImageLayout {
        width: w,
        height: h,
        offset: conv.margin * pw + conv.margin,
        row_pitch: pw,
        plane_pitch: pn,
    };
    let o = Outputs::record(&mut f, keep, &xb, first, 3 * pn, np);
    let (res, s) = f.finish()?;
    total.add(&s);
    report.rms.push((report.iterations, rms_of(res.f32s(r))));
    Ok(((o.take(ctx, &res)?, report), total))
}

/// Sparse RGB-D inputs in GPU memory, for synthesising views from them ([`SynthInputs::view`]).
struct SynthInputs<'a> {
    inputs: &'a [RgbdView],
    w: usize,
    h: usize,
    pitch: f32,
    depths: BufRef,
    colors: BufRef,
}

impl<'a> SynthInputs<'a> {
    /// `inputs` checked and uploaded by `f`.
    fn upload(
        f: &mut Frame,
        inputs: &'a [RgbdView],
        eye: &EyeModel,
    ) -> Result<SynthInputs<'a>, RenderError> {
        let (w, h) = check_inputs(inputs)?;
        let pitch = eye_for(eye, w)?.pixel_pitch_tan();
        let mut depths = Vec::with_capacity(inputs.len() * w * h);
        let mut colors = Vec::with_capacity(3 * inputs.len() * w * h);
        for v in inputs {
            depths.extend_from_slice(v.rgbd.depth.data());
            colors.extend_from_slice(&planar(&v.rgbd.color));
        }
        Ok(SynthInputs {
            inputs,
            w,
            h,
            pitch,
            depths: f.upload("input depth maps", &depths)?,
            colors: f.upload("input colour images", &colors)?,
        })
    }

    /// Records the view from `target` (splat, resolve, hole filling by rows then columns):
    /// a buffer of four planes, red, green, blue and depth (diopters).
    fn view(&self, f: &mut Frame, target: [f32; 2]) -> Result<BufRef, RenderError> {
        if !target.iter().all(|p| p.is_finite()) {
            return Err(invalid("view positions must be finite"));
        }
        let (w, h, ni) = (self.w, self.h, self.inputs.len());
        let (wu, hu) = (dim(w, "width")?, dim(h, "height")?);
        let n = (w * h) as u64;
        let pitch = self.pitch;
        let shifts: Vec<[f32; 4]> = self
            .inputs
            .iter()
            .map(|v| {
                [
                    -(target[0] - v.position[0]) / pitch,
                    -(target[1] - v.position[1]) / pitch,
                    1.0 / ((v.position[0] - target[0]).hypot(v.position[1] - target[1]) + 1e-4),
                    0.0,
                ]
            })
            .collect();
        let sb = f.upload("view shifts", &shifts)?;
        let dkey = f.zeroed("depth keys", 4 * n * ni as u64)?;
        let ikey = f.zeroed("index keys", 4 * n * ni as u64)?;
        let p = LfP {
            w: wu,
            h: hu,
            nv: ni as u32,
            v0: 0,
            focus: 0.0,
            pupil_m: 0.0,
            pitch,
            spacing: 0.0,
            lens_f: 0.0,
            top: 0,
            nlev: 1,
            dstride: n as u32,
        };
        let gz = groups2(wu, hu, ni as u32);
        let g = groups2(wu, hu, 1);
        let db = &self.depths;
        f.dispatch(Kernel::LfSplatDepth, &p, &[db, &sb, &dkey], gz)?;
        f.dispatch(Kernel::LfSplatIndex, &p, &[db, &sb, &dkey, &ikey], gz)?;
        let sp = SizeP {
            w: wu,
            h: hu,
            k: ni as u32,
            _pad: 0,
        };
        let px = f.scratch("synthesised pixels", 16 * n)?;
        f.dispatch(
            Kernel::ViewResolve,
            &sp,
            &[&dkey, &ikey, db, &self.colors, &sb, &px],
            g,
        )?;
        let rows = f.scratch("row-filled pixels", 16 * n)?;
        f.dispatch(Kernel::FillRows, &sp, &[&px, &rows], g)?;
        let dst = f.scratch("synthesised RGB-D", 16 * n)?;
        f.dispatch(Kernel::FillCols, &sp, &[&rows, &dst], g)?;
        Ok(dst)
    }
}

/// A `grid` x `grid` light field synthesised from sparse RGB-D `inputs`: inputs uploaded once,
/// then one frame per view (splat, resolve, hole filling by rows then columns).
pub(super) fn synthesize_light_field(
    ctx: &GpuContext,
    inputs: &[RgbdView],
    grid: usize,
    span: f32,
    eye: &EyeModel,
    progress: Progress,
) -> Out<Vec<LfView>> {
    let positions = light_field_positions(grid, span)?;
    let mut total = FrameStats::default();
    let mut out = Vec::with_capacity(grid * grid);
    let mut uploaded: Option<SynthInputs> = None;
    for (k, target) in positions.into_iter().enumerate() {
        let mut f = Frame::new(ctx)?;
        let synth = match uploaded.take() {
            Some(s) => s,
            None => SynthInputs::upload(&mut f, inputs, eye)?,
        };
        let (w, h) = (synth.w, synth.h);
        let dst = synth.view(&mut f, target)?;
        let r = f.read(&dst, 12 * (w * h) as u64);
        let (rb, s) = f.finish()?;
        total.add(&s);
        out.push(LfView {
            position: target,
            image: image(&rb.f32s(r), w, h)?,
        });
        uploaded = Some(synth);
        progress(k + 1);
    }
    Ok((out, total))
}

/// Host images in GPU memory, each its own buffer of three packed planes, one submission.
pub(super) fn upload_images(ctx: &Arc<GpuContext>, images: &[RgbImage]) -> Out<Vec<GpuImage>> {
    let mut f = Frame::new(ctx)?;
    let bufs = images
        .iter()
        .map(|img| f.upload("image", &planar(img)))
        .collect::<Result<Vec<_>, _>>()?;
    let (_, s) = f.finish()?;
    let out = bufs
        .into_iter()
        .zip(images)
        .map(|(buf, img)| {
            GpuImage::new(ctx, buf, ImageLayout::packed(img.width(), img.height(), 0))
        })
        .collect();
    Ok((out, s))
}

/// `input` in GPU memory: colour planes and depth in one buffer, one submission.
pub(super) fn upload_rgbd(ctx: &Arc<GpuContext>, input: &Rgbd) -> Out<GpuRgbd> {
    check_rgbd(input)?;
    let mut data = planar(&input.color);
    data.extend_from_slice(input.depth.data());
    let mut f = Frame::new(ctx)?;
    let buf = f.upload("RGB-D", &data)?;
    let (_, s) = f.finish()?;
    let range = input
        .depth
        .range()
        .unwrap_or((Diopters(0.0), Diopters(0.0)));
    let size = (input.width(), input.height());
    Ok((GpuRgbd::new(ctx, buf, size, range), s))
}

/// The RGB-D view from each of `targets` synthesised from `inputs` (the GPU twin of
/// [`crate::views::synthesize_rgbd_view`]): the inputs uploaded once, every view made in one
/// submission and left in GPU memory.
pub(super) fn synthesize_rgbd_views(
    ctx: &Arc<GpuContext>,
    inputs: &[RgbdView],
    targets: &[[f32; 2]],
    eye: &EyeModel,
) -> Out<Vec<GpuRgbd>> {
    let mut f = Frame::new(ctx)?;
    let synth = SynthInputs::upload(&mut f, inputs, eye)?;
    // Every synthesised depth is one of an input's, or 0 D where nothing was seen on the
    // pixel's row or column.
    let bound = inputs
        .iter()
        .filter_map(|v| v.rgbd.depth.range())
        .fold((Diopters(0.0), Diopters(0.0)), |(lo, hi), (l, h)| {
            (Diopters(lo.0.min(l.0)), Diopters(hi.0.max(h.0)))
        });
    let views = targets
        .iter()
        .map(|&t| synth.view(&mut f, t))
        .collect::<Result<Vec<_>, _>>()?;
    let (_, s) = f.finish()?;
    let size = (synth.w, synth.h);
    Ok((
        views
            .into_iter()
            .map(|b| GpuRgbd::new(ctx, b, size, bound))
            .collect(),
        s,
    ))
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct LensletP {
    pub(super) w: u32,
    pub(super) h: u32,
    pub(super) vw: u32,
    pub(super) vh: u32,
    pub(super) grid: u32,
    pub(super) _pad0: u32,
    pub(super) _pad1: u32,
    pub(super) _pad2: u32,
}

/// Where each column and each row of a lenslet display's panel reads its light field, as
/// dioptra-sched's `lenslet::sampling` gives it: per column (row) `[first view, its weight,
/// the next view's weight, position in a view (pixels)]`.
#[derive(Debug, Clone, PartialEq)]
pub struct PanelSampling {
    pub cols: Vec<[f32; 4]>,
    pub rows: Vec<[f32; 4]>,
}

impl PanelSampling {
    /// Every entry finite, its views on a `grid` x `grid` lattice (the next view only with a
    /// weight), weights not negative.
    fn check(&self, grid: usize) -> Result<(), RenderError> {
        let ok = |e: &[f32; 4]| {
            e.iter().all(|v| v.is_finite())
                && e[0] >= 0.0
                && e[0].fract() == 0.0
                && e[1] >= 0.0
                && e[2] >= 0.0
                && ((e[0] as usize) < grid)
                && ((e[0] as usize) + 1 < grid || e[2] == 0.0)
        };
        if self.cols.is_empty() || self.rows.is_empty() {
            return Err(invalid("a lenslet panel of no pixels"));
        }
        if !self.cols.iter().chain(&self.rows).all(ok) {
            return Err(invalid(format!(
                "a lenslet panel's sampling reads outside its {grid}x{grid} views"
            )));
        }
        Ok(())
    }
}

/// A lenslet display's panel, in GPU memory, of the `grid` x `grid` light field over a `span`
/// metres square synthesised from `inputs`: the views made in GPU memory (one frame each, as
/// [`synthesize_light_field`]) and resampled there by `sampling` (the GPU twin of
/// dioptra-sched's `lenslet::elemental_images`).
pub(super) fn lenslet_panel(
    ctx: &Arc<GpuContext>,
    inputs: &[RgbdView],
    grid: usize,
    span: f32,
    eye: &EyeModel,
    sampling: &PanelSampling,
) -> Out<GpuImage> {
    let positions = light_field_positions(grid, span)?;
    sampling.check(grid)?;
    let mut total = FrameStats::default();
    let mut uploaded: Option<SynthInputs> = None;
    let mut stack: Option<BufRef> = None;
    for (k, target) in positions.iter().enumerate() {
        let mut f = Frame::new(ctx)?;
        let synth = match uploaded.take() {
            Some(s) => s,
            None => SynthInputs::upload(&mut f, inputs, eye)?,
        };
        let bytes = 12 * (synth.w * synth.h) as u64;
        let views = match stack.take() {
            Some(b) => b,
            None => f.scratch("light-field views", bytes * positions.len() as u64)?,
        };
        let view = synth.view(&mut f, *target)?;
        f.copy(&view, 0, &views, bytes * k as u64, bytes);
        let (_, s) = f.finish()?;
        total.add(&s);
        stack = Some(views);
        uploaded = Some(synth);
    }
    let (Some(views), Some(synth)) = (stack, uploaded) else {
        return Err(invalid("no light-field views"));
    };
    let mut f = Frame::new(ctx)?;
    let (panel, layout) = record_lenslet(&mut f, &views, (synth.w, synth.h), grid, sampling)?;
    let (_, s) = f.finish()?;
    total.add(&s);
    Ok((GpuImage::new(ctx, panel, layout), total))
}

/// A lenslet display's panel, in GPU memory, of the `grid` x `grid` light field `views` (on
/// the host, row-major from the top-left, one size): uploaded once and resampled by
/// `sampling` in one submission.
pub(super) fn lenslet_panel_of_views(
    ctx: &Arc<GpuContext>,
    views: &[RgbImage],
    grid: usize,
    sampling: &PanelSampling,
) -> Out<GpuImage> {
    sampling.check(grid)?;
    let first = views
        .first()
        .ok_or_else(|| invalid("no light-field views"))?;
    let size = (first.width(), first.height());
    if views.len() != grid * grid
        || size.0 == 0
        || size.1 == 0
        || views.iter().any(|v| (v.width(), v.height()) != size)
    {
        return Err(mismatch(format!(
            "a {grid}x{grid} light field needs {} views of one size, not empty",
            grid * grid
        )));
    }
    let mut data = Vec::with_capacity(3 * views.len() * size.0 * size.1);
    for v in views {
        data.extend_from_slice(&planar(v));
    }
    let mut f = Frame::new(ctx)?;
    let stack = f.upload("light-field views", &data)?;
    let (panel, layout) = record_lenslet(&mut f, &stack, size, grid, sampling)?;
    let (_, s) = f.finish()?;
    Ok((GpuImage::new(ctx, panel, layout), s))
}

/// Records the lenslet resampling of the `grid` x `grid` views in `views` (each `vw` x `vh`,
/// planar, one after the other) by `sampling`: the buffer the panel will be in, and where.
fn record_lenslet(
    f: &mut Frame,
    views: &BufRef,
    (vw, vh): (usize, usize),
    grid: usize,
    sampling: &PanelSampling,
) -> Result<(BufRef, ImageLayout), RenderError> {
    let (w, h) = (sampling.cols.len(), sampling.rows.len());
    let p = LensletP {
        w: dim(w, "panel width")?,
        h: dim(h, "panel height")?,
        vw: dim(vw, "view width")?,
        vh: dim(vh, "view height")?,
        grid: dim(grid, "view grid")?,
        _pad0: 0,
        _pad1: 0,
        _pad2: 0,
    };
    let cols = f.upload("panel columns' sampling", &sampling.cols)?;
    let rows = f.upload("panel rows' sampling", &sampling.rows)?;
    let panel = f.scratch("lenslet panel", 12 * (w * h) as u64)?;
    f.dispatch(
        Kernel::Lenslet,
        &p,
        &[views, &cols, &rows, &panel],
        groups2(p.w, p.h, 1),
    )?;
    Ok((panel, ImageLayout::packed(w, h, 0)))
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct FovP {
    pub(super) w: u32,
    pub(super) h: u32,
    pub(super) rings: u32,
    pub(super) angles: u32,
    pub(super) cx: f32,
    pub(super) cy: f32,
    pub(super) gw: u32,
    pub(super) gh: u32,
}

/// Where a foveation frame's sampling mask comes from.
enum MaskFrom<'a> {
    LogPolar(&'a LogPolar),
    Given(&'a Plane),
}

/// One frame: (mask), cell lists, interpolation; returns the image and the mask (1 = sampled).
fn foveate_frame(ctx: &GpuContext, img: &RgbImage, from: MaskFrom) -> Out<(RgbImage, Vec<u32>)> {
    let (w, h) = (img.width(), img.height());
    if w == 0 || h == 0 {
        return Err(invalid("image is empty"));
    }
    if w > 1 << 15 || h > 1 << 15 {
        return Err(invalid(format!(
            "{w}x{h} is too large for GPU foveation (at most 32768 per side)"
        )));
    }
    let (wu, hu) = (dim(w, "width")?, dim(h, "height")?);
    let n = (w * h) as u64;
    let cell = FOV_CELL as u32;
    let (gw, gh) = (wu.div_ceil(cell), hu.div_ceil(cell));
    let mut p = FovP {
        w: wu,
        h: hu,
        rings: 0,
        angles: 0,
        cx: 0.0,
        cy: 0.0,
        gw,
        gh,
    };
    let mut f = Frame::new(ctx)?;
    let image_buf = f.upload("colour image", &planar(img))?;
    let mask = match from {
        MaskFrom::LogPolar(lp) => {
            let (rho, dir) = log_polar_tables(w, h, lp)?;
            p.rings = dim(rho.len(), "rings")?;
            p.angles = dim(dir.len(), "angles")?;
            p.cx = lp.centre[0];
            p.cy = lp.centre[1];
            let rb = f.upload("log-polar radii", &rho)?;
            let db = f.upload("log-polar directions", &dir)?;
            let m = f.zeroed("sampling mask", 4 * n)?;
            f.dispatch(
                Kernel::FovMask,
                &p,
                &[&rb, &db, &m],
                groups2(p.angles, p.rings, 1),
            )?;
            m
        }
        MaskFrom::Given(m) => {
            if (m.width(), m.height()) != (w, h) {
                return Err(mismatch(format!(
                    "mask is {}x{} but the image is {w}x{h}",
                    m.width(),
                    m.height()
                )));
            }
            let bits: Vec<u32> = m.data().iter().map(|&v| (v > 0.5) as u32).collect();
            if !bits.contains(&1) {
                return Err(invalid("the mask samples no pixel"));
            }
            f.upload("sampling mask", &bits)?
        }
    };
    let ncell = (gw * gh) as u64;
    let counts = f.scratch("cell counts", 4 * ncell)?;
    let entries = f.scratch("cell samples", 4 * (FOV_CELL * FOV_CELL) as u64 * ncell)?;
    f.dispatch(
        Kernel::FovCells,
        &p,
        &[&mask, &counts, &entries],
        [gw, gh, 1],
    )?;
    let dst = f.scratch("output image", 12 * n)?;
    f.dispatch(
        Kernel::FovInterp,
        &p,
        &[&image_buf, &mask, &counts, &entries, &dst],
        groups2(wu, hu, 1),
    )?;
    let ro = f.read(&dst, 12 * n);
    let rm = f.read(&mask, 4 * n);
    let (rb, s) = f.finish()?;
    let bits = rb.u32s(rm);
    if !bits.contains(&1) {
        // The CPU's interpolation refuses an empty mask too.
        return Err(invalid("the mask samples no pixel"));
    }
    Ok(((image(&rb.f32s(ro), w, h)?, bits), s))
}

/// Log-polar sampling and interpolation in one frame: the interpolated image, the mask and
/// the fraction of pixels sampled.
pub(super) fn foveate(ctx: &GpuContext, img: &RgbImage, p: &LogPolar) -> Out<Foveated> {
    let (w, h) = (img.width(), img.height());
    let ((out, bits), s) = foveate_frame(ctx, img, MaskFrom::LogPolar(p))?;
    let sampled = bits.iter().filter(|&&b| b != 0).count();
    let mask = Plane::from_vec(w, h, bits.iter().map(|&b| b as f32).collect())?;
    Ok((
        Foveated {
            image: out,
            mask,
            fraction: sampled as f64 / (w * h) as f64,
        },
        s,
    ))
}

/// Inverse-distance interpolation of the pixels `mask` leaves out.
pub(super) fn interpolate(ctx: &GpuContext, img: &RgbImage, mask: &Plane) -> Out<RgbImage> {
    let ((out, _), s) = foveate_frame(ctx, img, MaskFrom::Given(mask))?;
    Ok((out, s))
}
