//! Host side of the spectral decomposition on the GPU (CPU twin: [`crate::spectral`]).
//!
//! The formulation: the CPU's own, on the GPU. The per-frequency matrices (the costly part,
//! built once per settings by [`SpectralPlan`] on the CPU) are uploaded once and kept; a frame
//! is FFTs plus one small matrix apply per frequency, both of which a GPU does well. The FFT is
//! a Stockham autosort FFT in WGSL (mixed radix 2, 3, 4 and 5, one dispatch per pass, roots
//! from a table computed in f64 on the host) on exactly the CPU's padded grid, so that every
//! product is the CPU's circular convolution and the two agree to rounding. Real images go
//! two to a complex FFT (x + i y, separated after the rows), which halves the work of a
//! complex transform as realfft does on the CPU.

use std::sync::{Arc, Mutex};

use super::context::{BufRef, Frame, FrameStats, GpuContext, Kernel, WG1};
use super::kernels::{self, dim, planar, Keep, Output, Outputs};
use super::GpuError;
use crate::common::check_rgbd;
use crate::defocus::DefocusMethod;
use crate::error::{invalid, mismatch, RenderError};
use crate::fft2::FFT_PRIMES;
use crate::spectral::{SpectralParams, SpectralPlan, SpectralReport, SpectralTargets};
use bytemuck::{Pod, Zeroable};
use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};

/// The uniform every spectral kernel reads (see shaders/spectral.wgsl for each field's use).
#[repr(C)]
#[derive(Clone, Copy, Default, Pod, Zeroable)]
pub(super) struct SpecP {
    pub(super) n: u32,
    pub(super) lines: u32,
    pub(super) ns: u32,
    pub(super) radix: u32,
    pub(super) tw_off: u32,
    pub(super) inverse: u32,
    pub(super) pw: u32,
    pub(super) ph: u32,
    pub(super) hw: u32,
    pub(super) count: u32,
    pub(super) w: u32,
    pub(super) h: u32,
    pub(super) margin: u32,
    pub(super) rows: u32,
    pub(super) cols: u32,
    pub(super) off: u32,
    pub(super) row_pitch: u32,
    pub(super) plane_pitch: u32,
    pub(super) dst: u32,
    pub(super) img_pitch: u32,
    pub(super) scale: f32,
    pub(super) step: f32,
    pub(super) mom: f32,
    pub(super) flag: u32,
}

/// Workgroups of 256 for `total` invocations, over two dimensions past 32768.
fn groups1(total: usize) -> Result<[u32; 3], RenderError> {
    let groups = total.div_ceil(WG1 as usize).max(1);
    let gx = groups.min(32768);
    let gy = groups.div_ceil(gx);
    Ok([gx as u32, dim(gy, "spectral workgroup rows")?, 1])
}

/// The radices of a length's Stockham passes: 4s first, then the primes of the grid.
fn radices(n: usize) -> Result<Vec<u32>, RenderError> {
    let mut m = n;
    let mut out = Vec::new();
    for r in std::iter::once(4).chain(FFT_PRIMES) {
        while m.is_multiple_of(r) {
            out.push(r as u32);
            m /= r;
        }
    }
    if m != 1 || n == 0 {
        return Err(invalid(format!(
            "FFT length {n} has a prime factor above 5: the GPU's FFT has radices 2, 3, 4, 5"
        )));
    }
    Ok(out)
}

/// One FFT length: its passes and where its roots start in the table.
#[derive(Debug, Clone)]
struct Length {
    n: u32,
    radices: Vec<u32>,
    tw_off: u32,
}

/// A plan's matrices and the FFT's roots in GPU memory, uploaded once per plan.
pub(super) struct GpuPlan {
    plan: Arc<SpectralPlan>,
    ctx: usize,
    r: BufRef,
    fit: BufRef,
    ainv: BufRef,
    a: BufRef,
    nodes: BufRef,
    roots: BufRef,
    rows: Length,
    cols: Length,
}

static PLANS: Mutex<Vec<Arc<GpuPlan>>> = Mutex::new(Vec::new());
const PLANS_KEPT: usize = 4;

impl GpuPlan {
    /// The resident copy of `plan` on `ctx`, uploaded now unless kept from an earlier call.
    fn of(ctx: &GpuContext, plan: &Arc<SpectralPlan>) -> Result<Arc<GpuPlan>, RenderError> {
        let key = ctx as *const GpuContext as usize;
        if let Ok(list) = PLANS.lock() {
            if let Some(g) = list
                .iter()
                .find(|g| Arc::ptr_eq(&g.plan, plan) && g.ctx == key)
            {
                return Ok(g.clone());
            }
        }
        let (pw, ph) = (plan.fft.pw, plan.fft.ph);
        let mut roots: Vec<[f32; 2]> = Vec::with_capacity(pw + ph);
        for n in [pw, ph] {
            roots.extend((0..n).map(|k| {
                let a = -std::f64::consts::TAU * k as f64 / n as f64;
                [a.cos() as f32, a.sin() as f32]
            }));
        }
        let g = Arc::new(GpuPlan {
            plan: plan.clone(),
            ctx: key,
            r: ctx.upload_resident("spectral slice matrices", &plan.r)?,
            fit: ctx.upload_resident("spectral fit matrices", &plan.fit)?,
            ainv: ctx.upload_resident("spectral inverse matrices", &plan.ainv)?,
            a: ctx.upload_resident("spectral normal matrices", &plan.a)?,
            nodes: ctx.upload_resident("depth nodes", &plan.nodes)?,
            roots: ctx.upload_resident("FFT roots", bytemuck::cast_slice(&roots))?,
            rows: Length {
                n: dim(pw, "FFT width")?,
                radices: radices(pw)?,
                tw_off: 0,
            },
            cols: Length {
                n: dim(ph, "FFT height")?,
                radices: radices(ph)?,
                tw_off: dim(pw, "FFT width")?,
            },
        });
        if let Ok(mut list) = PLANS.lock() {
            if list.len() >= PLANS_KEPT {
                list.remove(0);
            }
            list.push(g.clone());
        }
        Ok(g)
    }

    /// The uniform's grid fields.
    fn base(&self) -> SpecP {
        let p = &self.plan;
        SpecP {
            pw: p.fft.pw as u32,
            ph: p.fft.ph as u32,
            hw: p.fft.hw as u32,
            w: p.width as u32,
            h: p.height as u32,
            margin: p.margin as u32,
            ..SpecP::default()
        }
    }

    fn pn(&self) -> usize {
        self.plan.fft.pw * self.plan.fft.ph
    }

    fn hn(&self) -> usize {
        self.plan.fft.len()
    }
}

/// The complex work buffers of one call, sized for its largest batch.
struct Work {
    c: [BufRef; 3],
}

impl Work {
    fn new(f: &mut Frame, g: &GpuPlan, count: usize) -> Result<Work, RenderError> {
        let len = (count.div_ceil(2) * g.pn()).max(count * g.hn());
        let bytes = 8 * len as u64;
        Ok(Work {
            c: [
                f.scratch("FFT work", bytes)?,
                f.scratch("FFT work", bytes)?,
                f.scratch("FFT work", bytes)?,
            ],
        })
    }
}

/// The Stockham passes of a transform of `lines` contiguous lines of `len` from `src` into
/// `dst` (`tmp` the other ping-pong buffer; `src` is only read).
#[allow(clippy::too_many_arguments)]
fn passes(
    f: &mut Frame,
    g: &GpuPlan,
    len: &Length,
    lines: usize,
    inverse: bool,
    src: &BufRef,
    dst: &BufRef,
    tmp: &BufRef,
) -> Result<(), RenderError> {
    let k = len.radices.len();
    let mut p = SpecP {
        n: len.n,
        lines: dim(lines, "FFT lines")?,
        tw_off: len.tw_off,
        inverse: inverse as u32,
        ns: 1,
        ..g.base()
    };
    let mut from = src;
    for (i, &r) in len.radices.iter().enumerate() {
        let to = if (k - 1 - i).is_multiple_of(2) {
            dst
        } else {
            tmp
        };
        p.radix = r;
        let groups = groups1(lines * (len.n / r) as usize)?;
        f.dispatch(Kernel::SpFftPass, &p, &[from, &g.roots, to], groups)?;
        p.ns *= r;
        from = to;
    }
    if k == 0 {
        f.copy(src, 0, dst, 0, 8 * (lines * len.n as usize) as u64);
    }
    Ok(())
}

/// Half spectra (`count` of them, into `out`) of `count` real padded images in `src`.
fn forward(
    f: &mut Frame,
    g: &GpuPlan,
    w: &Work,
    src: &BufRef,
    count: usize,
    out: &BufRef,
) -> Result<(), RenderError> {
    let pairs = count.div_ceil(2);
    let p = SpecP {
        count: dim(count, "FFT batch")?,
        ..g.base()
    };
    let [c0, c1, c2] = &w.c;
    f.dispatch(Kernel::SpPack, &p, &[src, c0], groups1(pairs * g.pn())?)?;
    passes(f, g, &g.rows, pairs * g.plan.fft.ph, false, c0, c1, c2)?;
    f.dispatch(
        Kernel::SpRowsToHalf,
        &p,
        &[c1, c0],
        groups1(pairs * g.hn())?,
    )?;
    passes(f, g, &g.cols, count * g.plan.fft.hw, false, c0, out, c2)
}

/// The real images of `count` half spectra in `spec` (kept): each value v, clamped when
/// `clamp`, becomes x and y = v + mom (v - x before).
#[allow(clippy::too_many_arguments)]
fn inverse(
    f: &mut Frame,
    g: &GpuPlan,
    w: &Work,
    spec: &BufRef,
    count: usize,
    clamp: bool,
    mom: f32,
    x: &BufRef,
    y: &BufRef,
) -> Result<(), RenderError> {
    let pairs = count.div_ceil(2);
    let p = SpecP {
        count: dim(count, "FFT batch")?,
        scale: 1.0 / g.pn() as f32,
        mom,
        flag: clamp as u32,
        ..g.base()
    };
    let [c0, c1, c2] = &w.c;
    passes(f, g, &g.cols, count * g.plan.fft.hw, true, spec, c1, c2)?;
    f.dispatch(
        Kernel::SpHalfToRows,
        &p,
        &[c1, c0],
        groups1(pairs * g.pn())?,
    )?;
    passes(f, g, &g.rows, pairs * g.plan.fft.ph, true, c0, c1, c2)?;
    f.dispatch(
        Kernel::SpRowsToReal,
        &p,
        &[c1, x, y],
        groups1(count * g.pn())?,
    )?;
    Ok(())
}

/// `out[c rows + a] (+)= scale sum_d mat[a][d] inp[off + c cols + d]` per frequency.
#[allow(clippy::too_many_arguments)]
fn apply(
    f: &mut Frame,
    g: &GpuPlan,
    inp: &BufRef,
    off: usize,
    mat: &BufRef,
    rows: usize,
    cols: usize,
    scale: f32,
    add: bool,
    out: &BufRef,
) -> Result<(), RenderError> {
    let p = SpecP {
        n: dim(g.hn(), "spectrum length")?,
        rows: rows as u32,
        cols: dim(cols, "spectral inputs")?,
        off: dim(off, "spectral input offset")?,
        scale,
        flag: add as u32,
        ..g.base()
    };
    f.dispatch(
        Kernel::SpApply,
        &p,
        &[inp, mat, out],
        groups1(3 * rows * g.hn())?,
    )?;
    Ok(())
}

/// A gradient step on `spec` in place; the objective's per-workgroup partial sums (read
/// back with the frame).
fn grad_step(
    f: &mut Frame,
    g: &GpuPlan,
    spec: &BufRef,
    y0: &BufRef,
) -> Result<super::Readback, RenderError> {
    let np = g.plan.planes.len();
    let groups = groups1(3 * g.hn())?;
    let p = SpecP {
        n: dim(g.hn(), "spectrum length")?,
        rows: np as u32,
        step: g.plan.step,
        ..g.base()
    };
    let nparts = (groups[0] * groups[1]) as u64;
    let part = f.scratch("objective partial sums", 4 * nparts)?;
    f.dispatch(Kernel::SpGradStep, &p, &[y0, &g.a, spec, &part], groups)?;
    Ok(f.read(&part, 4 * nparts))
}

/// Where the targets come from.
pub(super) enum Targets<'a> {
    /// From the input, as the settings say: rendered on the GPU by their defocus method, or
    /// the input's depth slices.
    Input,
    /// Given: one image per focal sample (the settings' targets must be rendered ones).
    Stack(&'a [RgbImage]),
}

/// The spectral decomposition on the GPU: the layers (padded; see [`Outputs`]) and the report.
pub(super) fn spectral_blend(
    ctx: &Arc<GpuContext>,
    input: &Rgbd,
    planes: &[Diopters],
    eye: &EyeModel,
    params: SpectralParams,
    targets: Targets,
    keep: Keep,
) -> Result<((Vec<Output>, SpectralReport), FrameStats), RenderError> {
    check_rgbd(input)?;
    if params.targets == SpectralTargets::NormalizedSlices {
        return Err(RenderError::Unsupported {
            backend: "gpu",
            method: "spectral blending with normalized-slice targets (use --backend cpu, or lightfield, gather or slices targets)",
        });
    }
    let plan = crate::spectral::plan_for(eye, planes, input.width(), input.height(), params)?;
    let g = GpuPlan::of(ctx, &plan)?;
    let (w, h) = (input.width(), input.height());
    let (np, nf) = (planes.len(), params.focal_samples);
    let (pn, hn) = (g.pn(), g.hn());
    let mut total = FrameStats::default();
    let slices = params.targets == SpectralTargets::Slices;
    if slices && matches!(targets, Targets::Stack(_)) {
        return Err(invalid(
            "a given target stack needs spectral settings with rendered targets (gather or lightfield), not slices",
        ));
    }
    // The targets' images on the GPU (rendered there, or uploaded), each with its layout.
    // The rendered images stay alive (held here) until the frame that reads them has run.
    let mut rendered: Vec<Output> = Vec::new();
    if let (Targets::Input, SpectralTargets::Defocus(m)) = (&targets, params.targets) {
        let (out, s) = match m {
            DefocusMethod::Gather => {
                kernels::gather(ctx, input, &params.foci(), eye, &|_| {}, Keep::Gpu)?
            }
            DefocusMethod::Pyramid(p) => {
                let foci = params.foci();
                match p.foveation {
                    None => {
                        let all = crate::pyramid::Region::full(input.width(), input.height());
                        super::pyramid::pyramid(ctx, input, &foci, eye, &all, &|_| {}, Keep::Gpu)?
                    }
                    Some(f) => {
                        super::pyramid::foveated(ctx, input, &foci, eye, &f, &|_| {}, Keep::Gpu)?
                    }
                }
            }
            DefocusMethod::LightField(lp) => {
                kernels::lightfield(ctx, input, &params.foci(), eye, lp, &|_| {}, Keep::Gpu)?
            }
        };
        total.add(&s);
        rendered = out;
    }
    // Composite targets: the light field rendered here (only at the foci a blurred step
    // reaches), read back and composed with the smooth disk blur on the CPU, then uploaded as
    // a given stack. The composite has no WGSL twin yet: its mask and smooth blur run on the
    // CPU, as C1R's composite does (crates/net/src/gpu.rs).
    let composed: Vec<RgbImage>;
    let targets = match (targets, params.targets) {
        (Targets::Input, SpectralTargets::Composite(lp)) => {
            composed =
                crate::composite::composite_stack_with(input, &params.foci(), eye, |need, _| {
                    let (out, s) =
                        kernels::lightfield(ctx, input, need, eye, lp, &|_| {}, Keep::Host)?;
                    total.add(&s);
                    kernels::on_host(out)
                })?;
            Targets::Stack(&composed)
        }
        (t, _) => t,
    };
    let batch = if slices {
        3 * plan.nodes().len()
    } else {
        3 * nf + 3 * np
    };
    let mut f = Frame::new(ctx)?;
    let work = Work::new(&mut f, &g, batch.max(3 * np))?;
    let real = f.scratch("padded images", 4 * (batch * pn) as u64)?;
    let spectra = f.scratch("spectra", 8 * (batch * hn) as u64)?;
    let y0 = f.scratch("unconstrained layers", 8 * (3 * np * hn) as u64)?;
    let color = f.upload("colour image", &planar(&input.color))?;
    let base = g.base();
    if slices {
        let nd = plan.nodes().len();
        let depth = f.upload("depth map", input.depth.data())?;
        let p = SpecP {
            cols: dim(nd, "depth nodes")?,
            row_pitch: w as u32,
            ..base
        };
        f.dispatch(
            Kernel::SpSlices,
            &p,
            &[&color, &depth, &g.nodes, &real],
            groups1(pn)?,
        )?;
        forward(&mut f, &g, &work, &real, batch, &spectra)?;
        apply(&mut f, &g, &spectra, 0, &g.r, np, nd, 1.0, false, &y0)?;
    } else {
        let stack: Vec<(BufRef, usize, usize, usize)> = match targets {
            Targets::Stack(s) => {
                if s.len() != nf || s.iter().any(|t| (t.width(), t.height()) != (w, h)) {
                    return Err(mismatch(format!(
                        "{} target slices for {nf} focal samples of {w}x{h}",
                        s.len()
                    )));
                }
                s.iter()
                    .map(|t| Ok((f.upload("target slice", &planar(t))?, 0, w, w * h)))
                    .collect::<Result<_, RenderError>>()?
            }
            Targets::Input => rendered
                .iter()
                .map(|o| match o {
                    Output::Gpu(img) => {
                        let l = img.layout();
                        Ok((img.buf().clone(), l.offset, l.row_pitch, l.plane_pitch))
                    }
                    Output::Host(_) => Err(GpuError::Validation(
                        "a target slice was read back though asked to stay in GPU memory".into(),
                    )
                    .into()),
                })
                .collect::<Result<_, RenderError>>()?,
        };
        // Targets: image c nf + j; the linear blend's layers after them, 3 nf + c np + a.
        for (j, (buf, off, row, plane)) in stack.iter().enumerate() {
            let p = SpecP {
                rows: 1,
                off: dim(*off, "image offset")?,
                row_pitch: *row as u32,
                plane_pitch: dim(*plane, "image plane")?,
                dst: j as u32,
                cols: nf as u32,
                ..base
            };
            f.dispatch(Kernel::SpPad, &p, &[buf, &real], groups1(3 * pn)?)?;
        }
        let depth = f.upload("depth map", input.depth.data())?;
        let pl: Vec<f32> = planes.iter().map(|p| p.0).collect();
        let pbuf = f.upload("planes", &pl)?;
        let linear = f.scratch("linear blend", 12 * (w * h * np) as u64)?;
        kernels::linear_blend_into(&mut f, [&color, &depth, &pbuf, &linear], w, h, np)?;
        let p = SpecP {
            rows: np as u32,
            off: 0,
            img_pitch: dim(3 * w * h, "layer size")?,
            row_pitch: w as u32,
            plane_pitch: dim(w * h, "layer plane")?,
            dst: dim(3 * nf, "targets")?,
            cols: np as u32,
            ..base
        };
        f.dispatch(Kernel::SpPad, &p, &[&linear, &real], groups1(3 * np * pn)?)?;
        forward(&mut f, &g, &work, &real, batch, &spectra)?;
        // Y0 = FIT T + lambda AINV L
        apply(&mut f, &g, &spectra, 0, &g.fit, np, nf, 1.0, false, &y0)?;
        apply(
            &mut f,
            &g,
            &spectra,
            3 * nf,
            &g.ainv,
            np,
            np,
            params.prior,
            true,
            &y0,
        )?;
    }
    // The clamp, then the projected steps (FISTA), as the CPU's solve.
    let lbytes = 4 * (3 * np * pn) as u64;
    let x = f.scratch("layers", lbytes)?;
    let y = f.scratch("layers", lbytes)?;
    inverse(&mut f, &g, &work, &y0, 3 * np, true, 0.0, &x, &y)?;
    let mut report = SpectralReport {
        objective_clamped: f64::NAN,
        objective_final: f64::NAN,
        iterations: 0,
        refined: false,
    };
    let mut result = x.clone();
    if params.iterations > 0 {
        let clamped = f.scratch("clamped layers", lbytes)?;
        f.copy(&x, 0, &clamped, 0, lbytes);
        let spec = f.scratch("layer spectra", 8 * (3 * np * hn) as u64)?;
        let mut first = None;
        let mut t_k = 1.0f64;
        for it in 0..params.iterations {
            forward(&mut f, &g, &work, &y, 3 * np, &spec)?;
            let r = grad_step(&mut f, &g, &spec, &y0)?;
            if it == 0 {
                first = Some(r);
            }
            let t_next = 0.5 * (1.0 + (1.0 + 4.0 * t_k * t_k).sqrt());
            let mom = ((t_k - 1.0) / t_next) as f32;
            inverse(&mut f, &g, &work, &spec, 3 * np, true, mom, &x, &y)?;
            t_k = t_next;
            report.iterations = it + 1;
        }
        forward(&mut f, &g, &work, &x, 3 * np, &spec)?;
        let fin = grad_step(&mut f, &g, &spec, &y0)?;
        let (rb, s) = f.finish()?;
        total.add(&s);
        let npix = pn as f64;
        let objective = |r| rb.f32s(r).iter().map(|&v| v as f64).sum::<f64>() / (npix * npix);
        report.objective_clamped = first.map_or(f64::NAN, objective);
        let fin = objective(fin);
        if fin < report.objective_clamped {
            report.objective_final = fin;
            report.refined = true;
        } else {
            report.objective_final = report.objective_clamped;
            result = clamped;
        }
        f = Frame::new(ctx)?;
    }
    // Each layer's planes on the padded grid: layer a's channel c is image c np + a.
    let m = plan.margin;
    let first = super::ImageLayout {
        width: w,
        height: h,
        offset: m * plan.fft.pw + m,
        row_pitch: plan.fft.pw,
        plane_pitch: np * pn,
    };
    let o = Outputs::record(&mut f, keep, &result, first, pn, np);
    let (rb, s) = f.finish()?;
    total.add(&s);
    Ok(((o.take(ctx, &rb)?, report), total))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::multifocal::DEFAULT_PLANES;

    /// A plan's matrices go to the GPU once: the second call finds them resident.
    #[test]
    fn a_plan_is_uploaded_once() {
        let ctx = match GpuContext::shared(None) {
            Ok(c) => c,
            Err(GpuError::NoAdapter)
                if std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1") =>
            {
                eprintln!("skipped: no GPU adapter");
                return;
            }
            Err(e) => panic!("GPU required (DIOPTRA_REQUIRE_GPU=1) or failed to open: {e}"),
        };
        let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
        let params = SpectralParams {
            focal_range: (0.3, 1.9),
            ..SpectralParams::default()
        };
        let plan =
            crate::spectral::plan_for(&EyeModel::default(), &planes, 33, 21, params).unwrap();
        let a = GpuPlan::of(&ctx, &plan).unwrap();
        let b = GpuPlan::of(&ctx, &plan).unwrap();
        assert!(Arc::ptr_eq(&a, &b));
        assert_eq!(a.rows.n as usize, plan.grid().0);
        assert_eq!(
            a.rows.radices.iter().product::<u32>() as usize,
            plan.grid().0
        );
        assert_eq!(radices(60).unwrap(), vec![4, 3, 5]);
        assert_eq!(radices(8).unwrap(), vec![4, 2]);
        assert!(radices(14).is_err());
    }
}
