//! The wgpu backend. Every method of [`Backend`] is overridden here with a GPU kernel; a
//! method without one must return [`RenderError::Unsupported`] naming it, never fall back to
//! the CPU default silently.

mod context;
mod image;
mod kernels;
mod pyramid;
mod spectral;
#[cfg(test)]
pub(crate) mod uniforms;

pub use context::{
    hardware_adapter_exists, list_adapters, AdapterSummary, Buf, BufRef, Frame, FrameStats,
    GpuContext, Readback, Readbacks, ShaderKernel,
};
pub use image::{GpuImage, GpuRgbd, ImageLayout, RgbdInput};
use kernels::Keep;
pub use kernels::PanelSampling;

use crate::backend::{Backend, Foveated, Progress};
use crate::defocus::DefocusMethod;
pub use crate::error::GpuError;
use crate::error::RenderError;
use crate::foveate::LogPolar;
use crate::hybrid::{hybrid_blend_with, HybridParams, HybridReport};
use crate::metrics::Quality;
use crate::multifocal::{Layers, OptimizeParams, OptimizeReport};
use crate::retina::LfView;
use crate::spectral::{SpectralParams, SpectralReport};
use crate::views::RgbdView;
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// The wgpu backend on the process's [`GpuContext`].
pub struct Gpu {
    ctx: Arc<GpuContext>,
    last: Mutex<FrameStats>,
    /// Images this backend left in GPU memory that were read back since.
    images_read_back: Arc<AtomicU64>,
}

impl Gpu {
    /// The GPU backend on the adapter whose name contains `adapter`, or the first hardware
    /// adapter (a software one, said on stderr, only when nothing else exists).
    pub fn new(adapter: Option<&str>) -> Result<Gpu, GpuError> {
        Ok(Gpu {
            ctx: GpuContext::shared(adapter)?,
            last: Mutex::new(FrameStats::default()),
            images_read_back: Arc::new(AtomicU64::new(0)),
        })
    }

    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// How many of the images this backend left in GPU memory were read back to the host.
    pub fn images_read_back(&self) -> u64 {
        self.images_read_back.load(Ordering::Relaxed)
    }

    /// Dispatches, bytes moved and GPU time of the last call (all its frames together).
    pub fn last_stats(&self) -> FrameStats {
        self.last.lock().map(|s| s.clone()).unwrap_or_default()
    }

    fn record(&self, s: FrameStats) {
        if let Ok(mut l) = self.last.lock() {
            *l = s;
        }
    }

    fn defocus_to(
        &self,
        input: RgbdInput,
        foci: &[Diopters],
        eye: &EyeModel,
        method: DefocusMethod,
        progress: Progress,
        keep: Keep,
    ) -> Result<Vec<kernels::Output>, RenderError> {
        let (out, s) = match method {
            DefocusMethod::Gather => kernels::gather(&self.ctx, input, foci, eye, progress, keep)?,
            DefocusMethod::Pyramid(p) => match p.foveation {
                None => {
                    let all = crate::pyramid::Region::full(input.width(), input.height());
                    pyramid::pyramid(&self.ctx, input, foci, eye, &all, progress, keep)?
                }
                Some(f) => pyramid::foveated(&self.ctx, input, foci, eye, &f, progress, keep)?,
            },
            DefocusMethod::LightField(p) => {
                kernels::lightfield(&self.ctx, input, foci, eye, p, progress, keep)?
            }
        };
        self.record(s);
        Ok(out)
    }

    /// [`Backend::defocus`] at one focus, the image left in GPU memory; `input` on the host
    /// or already in GPU memory.
    pub fn defocus_on_gpu<'a>(
        &self,
        input: impl Into<RgbdInput<'a>>,
        focus: Diopters,
        eye: &EyeModel,
        method: DefocusMethod,
    ) -> Result<GpuImage, RenderError> {
        let out = self.defocus_to(input.into(), &[focus], eye, method, &|_| {}, Keep::Gpu)?;
        kernels::on_gpu(out, &self.images_read_back)?
            .pop()
            .ok_or_else(|| GpuError::Validation("no image rendered".into()).into())
    }

    /// [`Backend::linear_blend`], one image per plane, left in GPU memory; `input` on the
    /// host or already in GPU memory.
    pub fn linear_blend_on_gpu<'a>(
        &self,
        input: impl Into<RgbdInput<'a>>,
        planes: &[Diopters],
    ) -> Result<Vec<GpuImage>, RenderError> {
        let (out, s) = kernels::linear_blend(&self.ctx, input.into(), planes, Keep::Gpu)?;
        self.record(s);
        kernels::on_gpu(out, &self.images_read_back)
    }

    /// `input` uploaded to GPU memory (one submission), for methods to render from there
    /// again and again.
    pub fn upload_rgbd(&self, input: &Rgbd) -> Result<GpuRgbd, RenderError> {
        let (out, s) = kernels::upload_rgbd(&self.ctx, input)?;
        self.record(s);
        Ok(out.counted_by(&self.images_read_back))
    }

    /// The RGB-D view from each of `targets` synthesised from `inputs`, left in GPU memory:
    /// the GPU twin of [`crate::views::synthesize_rgbd_view`] (a stereo rig's eyes from one
    /// RGB-D), the inputs uploaded once and every view made in one submission.
    pub fn synthesize_rgbd_views_on_gpu(
        &self,
        inputs: &[RgbdView],
        targets: &[[f32; 2]],
        eye: &EyeModel,
    ) -> Result<Vec<GpuRgbd>, RenderError> {
        let (out, s) = kernels::synthesize_rgbd_views(&self.ctx, inputs, targets, eye)?;
        self.record(s);
        Ok(out
            .into_iter()
            .map(|v| v.counted_by(&self.images_read_back))
            .collect())
    }

    /// A lenslet display's panel of the `grid` x `grid` light field over `span` metres
    /// synthesised from `inputs`, left in GPU memory with its views: the GPU twin of
    /// synthesising the views ([`Backend::synthesize_light_field`]) and resampling them by
    /// `sampling` (dioptra-sched's `lenslet::elemental_images`).
    pub fn lenslet_panel_on_gpu(
        &self,
        inputs: &[RgbdView],
        grid: usize,
        span: f32,
        eye: &EyeModel,
        sampling: &PanelSampling,
    ) -> Result<GpuImage, RenderError> {
        let (out, s) = kernels::lenslet_panel(&self.ctx, inputs, grid, span, eye, sampling)?;
        self.record(s);
        Ok(out.counted_by(&self.images_read_back))
    }

    /// A lenslet display's panel of the `grid` x `grid` light field `views` (host images, as
    /// a scene's ray cast or a net's refinement leaves them), left in GPU memory: the views
    /// uploaded once and resampled there by `sampling`.
    pub fn lenslet_panel_of_views_on_gpu(
        &self,
        views: &[RgbImage],
        grid: usize,
        sampling: &PanelSampling,
    ) -> Result<GpuImage, RenderError> {
        let (out, s) = kernels::lenslet_panel_of_views(&self.ctx, views, grid, sampling)?;
        self.record(s);
        Ok(out.counted_by(&self.images_read_back))
    }

    fn spectral_to(
        &self,
        input: &Rgbd,
        planes: &[Diopters],
        eye: &EyeModel,
        params: SpectralParams,
        targets: spectral::Targets,
        keep: Keep,
    ) -> Result<(Vec<kernels::Output>, SpectralReport), RenderError> {
        let ((out, report), s) =
            spectral::spectral_blend(&self.ctx, input, planes, eye, params, targets, keep)?;
        self.record(s);
        Ok((out, report))
    }

    /// The grid [`Backend::spectral_blend`] solves `input` on, as the CPU's
    /// ([`crate::spectral_coarse::scale_for`]).
    fn spectral_scale(
        input: &Rgbd,
        planes: &[Diopters],
        eye: &EyeModel,
        params: &SpectralParams,
    ) -> Result<usize, RenderError> {
        crate::common::check_rgbd(input)?;
        crate::multifocal::check_planes(planes)?;
        params.check()?;
        crate::spectral_coarse::scale_for(
            eye,
            planes,
            input.width(),
            params.scale,
            params.focal_range,
        )
    }

    /// [`Backend::spectral_blend`], one image per plane, left in GPU memory (solved on a
    /// coarser grid, the layers are composed on the host and uploaded).
    pub fn spectral_blend_on_gpu(
        &self,
        input: &Rgbd,
        planes: &[Diopters],
        eye: &EyeModel,
        params: SpectralParams,
    ) -> Result<(Vec<GpuImage>, SpectralReport), RenderError> {
        if Self::spectral_scale(input, planes, eye, &params)? > 1 {
            let (layers, report) = self.spectral_blend(input, planes, eye, params)?;
            let (images, s) = kernels::upload_images(&self.ctx, &layers.images)?;
            self.record(s);
            let images = images
                .into_iter()
                .map(|i| i.counted_by(&self.images_read_back))
                .collect();
            return Ok((images, report));
        }
        let (out, report) = self.spectral_to(
            input,
            planes,
            eye,
            params,
            spectral::Targets::Input,
            Keep::Gpu,
        )?;
        Ok((kernels::on_gpu(out, &self.images_read_back)?, report))
    }

    /// The spectral decomposition fitting a given focal stack (one image per focal sample
    /// of `params`, whose targets must be a rendered kind), the prior toward `input`'s
    /// linear blending: the GPU twin of [`crate::SpectralPlan::targets_stack`] and `solve`.
    pub fn spectral_blend_stack(
        &self,
        input: &Rgbd,
        stack: &[RgbImage],
        planes: &[Diopters],
        eye: &EyeModel,
        params: SpectralParams,
    ) -> Result<(Layers, SpectralReport), RenderError> {
        let (images, report) = self.spectral_to(
            input,
            planes,
            eye,
            params,
            spectral::Targets::Stack(stack),
            Keep::Host,
        )?;
        let layers = Layers {
            planes: planes.to_vec(),
            images: kernels::on_host(images)?,
        };
        Ok((layers, report))
    }

    /// [`Backend::optimized_blend`], one image per plane, left in GPU memory.
    #[allow(clippy::too_many_arguments)]
    pub fn optimized_blend_on_gpu(
        &self,
        targets: &[RgbImage],
        foci: &[Diopters],
        planes: &[Diopters],
        eye: &EyeModel,
        init: Option<&Layers>,
        params: OptimizeParams,
    ) -> Result<(Vec<GpuImage>, OptimizeReport), RenderError> {
        let ((out, report), s) = kernels::optimized_blend(
            &self.ctx,
            targets,
            foci,
            planes,
            eye,
            init,
            params,
            &|_| {},
            Keep::Gpu,
        )?;
        self.record(s);
        Ok((kernels::on_gpu(out, &self.images_read_back)?, report))
    }
}

impl Backend for Gpu {
    fn name(&self) -> &'static str {
        "gpu"
    }

    fn defocus(
        &self,
        input: &Rgbd,
        foci: &[Diopters],
        eye: &EyeModel,
        method: DefocusMethod,
        progress: Progress,
    ) -> Result<Vec<RgbImage>, RenderError> {
        kernels::on_host(self.defocus_to(input.into(), foci, eye, method, progress, Keep::Host)?)
    }

    fn linear_blend(&self, input: &Rgbd, planes: &[Diopters]) -> Result<Layers, RenderError> {
        let (out, s) = kernels::linear_blend(&self.ctx, input, planes, Keep::Host)?;
        self.record(s);
        Ok(Layers {
            planes: planes.to_vec(),
            images: kernels::on_host(out)?,
        })
    }

    fn optimized_blend(
        &self,
        targets: &[RgbImage],
        foci: &[Diopters],
        planes: &[Diopters],
        eye: &EyeModel,
        init: Option<&Layers>,
        params: OptimizeParams,
        progress: Progress,
    ) -> Result<(Layers, OptimizeReport), RenderError> {
        let ((out, report), s) = kernels::optimized_blend(
            &self.ctx,
            targets,
            foci,
            planes,
            eye,
            init,
            params,
            progress,
            Keep::Host,
        )?;
        self.record(s);
        let layers = Layers {
            planes: planes.to_vec(),
            images: kernels::on_host(out)?,
        };
        Ok((layers, report))
    }

    /// On the GPU: its targets rendered there, the plan's matrices resident (uploaded once
    /// per plan), FFTs in WGSL; normalised-slice targets are `Unsupported` here.
    fn spectral_blend(
        &self,
        input: &Rgbd,
        planes: &[Diopters],
        eye: &EyeModel,
        params: SpectralParams,
    ) -> Result<(Layers, SpectralReport), RenderError> {
        let s = Self::spectral_scale(input, planes, eye, &params)?;
        let params = SpectralParams { scale: 1, ..params };
        if s > 1 {
            return crate::spectral_coarse::coarse_blend_with(input, planes, eye, s, |small, e| {
                self.spectral_blend(small, planes, e, params)
            });
        }
        let (images, report) = self.spectral_to(
            input,
            planes,
            eye,
            params,
            spectral::Targets::Input,
            Keep::Host,
        )?;
        let layers = Layers {
            planes: planes.to_vec(),
            images: kernels::on_host(images)?,
        };
        Ok((layers, report))
    }

    /// The window's spectral solve on the GPU ([`Backend::spectral_blend`]); linear blending,
    /// the depth-edge scan and the cross-fade on the host, as the CPU's (they are a small part
    /// of the frame's cost).
    fn hybrid_blend(
        &self,
        input: &Rgbd,
        planes: &[Diopters],
        eye: &EyeModel,
        gaze: Option<[f32; 2]>,
        params: &HybridParams,
    ) -> Result<(Layers, HybridReport), RenderError> {
        hybrid_blend_with(input, planes, eye, gaze, params, |rgbd, e, p| {
            self.spectral_blend(rgbd, planes, e, p)
        })
    }

    fn retina_multifocal(
        &self,
        layers: &Layers,
        foci: &[Diopters],
        eye: &EyeModel,
    ) -> Result<Vec<RgbImage>, RenderError> {
        let (out, s) = kernels::retina_multifocal(&self.ctx, layers, foci, eye)?;
        self.record(s);
        Ok(out)
    }

    fn retina_varifocal(
        &self,
        image: &RgbImage,
        display: Diopters,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<RgbImage, RenderError> {
        let (out, s) = kernels::retina_varifocal(&self.ctx, image, display, focus, eye)?;
        self.record(s);
        Ok(out)
    }

    fn retina_lightfield(
        &self,
        views: &[LfView],
        spacing: f32,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<RgbImage, RenderError> {
        let (out, s) = kernels::retina_lightfield(&self.ctx, views, spacing, focus, eye)?;
        self.record(s);
        Ok(out)
    }

    fn synthesize_light_field(
        &self,
        inputs: &[RgbdView],
        grid: usize,
        span: f32,
        eye: &EyeModel,
        progress: Progress,
    ) -> Result<Vec<LfView>, RenderError> {
        let (out, s) =
            kernels::synthesize_light_field(&self.ctx, inputs, grid, span, eye, progress)?;
        self.record(s);
        Ok(out)
    }

    fn foveate(&self, img: &RgbImage, p: &LogPolar) -> Result<Foveated, RenderError> {
        let (out, s) = kernels::foveate(&self.ctx, img, p)?;
        self.record(s);
        Ok(out)
    }

    fn foveate_interpolate(&self, img: &RgbImage, mask: &Plane) -> Result<RgbImage, RenderError> {
        let (out, s) = kernels::interpolate(&self.ctx, img, mask)?;
        self.record(s);
        Ok(out)
    }

    fn quality(
        &self,
        a: &RgbImage,
        b: &RgbImage,
        mask: Option<&Plane>,
    ) -> Result<Quality, RenderError> {
        let (out, s) = kernels::quality(&self.ctx, a, b, mask)?;
        self.record(s);
        Ok(out)
    }
}
