//! The backend seam. Callers hold a `&dyn Backend`; every method has a CPU default. The GPU
//! backend ([`crate::gpu::Gpu`]) overrides every method, returning
//! [`RenderError::Unsupported`] for those without a kernel yet: a new method added here must
//! be overridden there too, or it would run on the CPU behind a `--backend gpu`.

use crate::error::{invalid, RenderError};
use crate::foveate::{interpolate, log_polar_mask, LogPolar};
use crate::gather::gather;
use crate::lightfield::{LightFieldParams, LightFieldPrep};
use crate::metrics::{quality, Quality};
use crate::multifocal::{linear_blend, optimized_blend, Layers, OptimizeParams, OptimizeReport};
use crate::retina::{retina_lightfield, retina_multifocal, retina_varifocal, LfView};
use crate::spectral::{plan_for, SpectralParams, SpectralReport, SpectralTargets};
use crate::views::{synthesize_light_field, RgbdView};
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};
use std::str::FromStr;

/// A defocus method for RGB-D input.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DefocusMethod {
    Gather,
    /// Gather's sums with every blur of 4 px or more spread at the resolution it leaves:
    /// bounded work per pixel (see [`crate::pyramid`]); foveated around a gaze when asked.
    Pyramid(crate::pyramid::PyramidParams),
    LightField(LightFieldParams),
}

impl FromStr for DefocusMethod {
    type Err = RenderError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "gather" => Ok(DefocusMethod::Gather),
            "pyramid" => Ok(DefocusMethod::Pyramid(Default::default())),
            "lightfield" => Ok(DefocusMethod::LightField(LightFieldParams::default())),
            _ => Err(invalid(format!(
                "unknown defocus method {s:?}: expected gather, pyramid or lightfield"
            ))),
        }
    }
}

/// A foveated image: log-polar samples kept, the rest interpolated.
#[derive(Debug, Clone)]
pub struct Foveated {
    pub image: RgbImage,
    /// 1 where a sample was kept, 0 where the pixel was interpolated.
    pub mask: Plane,
    /// Fraction of pixels sampled.
    pub fraction: f64,
}

/// Progress callback: called with the number of units (slices, iterations) done.
pub type Progress<'a> = &'a (dyn Fn(usize) + Sync);

pub trait Backend: Send + Sync {
    /// The name `--backend` selects this backend by.
    fn name(&self) -> &'static str;

    /// Depth-of-field images of `input` at every focus in `foci` (a focal stack; one slice for
    /// a single render). Work that does not depend on focus is done once.
    fn defocus(
        &self,
        input: &Rgbd,
        foci: &[Diopters],
        eye: &EyeModel,
        method: DefocusMethod,
        progress: Progress,
    ) -> Result<Vec<RgbImage>, RenderError> {
        let mut out = Vec::with_capacity(foci.len());
        match method {
            DefocusMethod::Gather => {
                for &q in foci {
                    out.push(gather(input, q, eye)?);
                    progress(out.len());
                }
            }
            DefocusMethod::Pyramid(p) => {
                for &q in foci {
                    out.push(match p.foveation {
                        None => crate::pyramid::pyramid(input, q, eye)?,
                        Some(f) => crate::foveated::foveated(input, q, eye, &f)?.image,
                    });
                    progress(out.len());
                }
            }
            DefocusMethod::LightField(p) => {
                let prep = LightFieldPrep::new(input, eye, p)?;
                for &q in foci {
                    out.push(prep.render(q)?);
                    progress(out.len());
                }
            }
        }
        Ok(out)
    }

    fn linear_blend(&self, input: &Rgbd, planes: &[Diopters]) -> Result<Layers, RenderError> {
        linear_blend(input, planes)
    }

    #[allow(clippy::too_many_arguments)]
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
        optimized_blend(targets, foci, planes, eye, init, params, progress)
    }

    /// Spectral decomposition of `input` onto `planes`: the per-frequency least squares of
    /// the retinal images (see [`crate::spectral`]), its matrices built once per settings.
    fn spectral_blend(
        &self,
        input: &Rgbd,
        planes: &[Diopters],
        eye: &EyeModel,
        params: SpectralParams,
    ) -> Result<(Layers, SpectralReport), RenderError> {
        crate::common::check_rgbd(input)?;
        let plan = plan_for(eye, planes, input.width(), input.height(), params)?;
        let t = match params.targets {
            SpectralTargets::Defocus(m) => {
                let stack = self.defocus(input, &params.foci(), eye, m, &|_| {})?;
                plan.targets_stack(input, &stack)?
            }
            SpectralTargets::Composite(lp) => {
                let stack = crate::composite::composite_stack(input, &params.foci(), eye, lp)?;
                plan.targets_stack(input, &stack)?
            }
            SpectralTargets::Slices | SpectralTargets::NormalizedSlices => {
                plan.targets_rgbd(input)?
            }
        };
        plan.solve(&t)
    }

    fn retina_multifocal(
        &self,
        layers: &Layers,
        foci: &[Diopters],
        eye: &EyeModel,
    ) -> Result<Vec<RgbImage>, RenderError> {
        retina_multifocal(layers, foci, eye)
    }

    fn retina_varifocal(
        &self,
        image: &RgbImage,
        display: Diopters,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<RgbImage, RenderError> {
        retina_varifocal(image, display, focus, eye)
    }

    /// A light-field display seen focusing at `focus` (shift-and-add over the pupil).
    fn retina_lightfield(
        &self,
        views: &[LfView],
        spacing: f32,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<RgbImage, RenderError> {
        retina_lightfield(views, spacing, focus, eye)
    }

    /// A `grid` x `grid` light field over a `span` metres square synthesised from sparse RGB-D
    /// views; `progress` is called with the views done.
    fn synthesize_light_field(
        &self,
        inputs: &[RgbdView],
        grid: usize,
        span: f32,
        eye: &EyeModel,
        progress: Progress,
    ) -> Result<Vec<LfView>, RenderError> {
        synthesize_light_field(inputs, grid, span, eye, progress)
    }

    /// Log-polar sampling of `img` (Thumuluri & Sharma eq. 3-8) and inverse-distance
    /// interpolation of every other pixel from its four nearest samples (eq. 9).
    fn foveate(&self, img: &RgbImage, p: &LogPolar) -> Result<Foveated, RenderError> {
        let (mask, fraction) = log_polar_mask(img.width(), img.height(), p)?;
        Ok(Foveated {
            image: interpolate(img, &mask)?,
            mask,
            fraction,
        })
    }

    /// The interpolation step of [`Backend::foveate`] with a given mask (1 = sampled).
    fn foveate_interpolate(&self, img: &RgbImage, mask: &Plane) -> Result<RgbImage, RenderError> {
        interpolate(img, mask)
    }

    /// PSNR and SSIM of `a` against `b`, inside `mask` when given.
    fn quality(
        &self,
        a: &RgbImage,
        b: &RgbImage,
        mask: Option<&Plane>,
    ) -> Result<Quality, RenderError> {
        quality(a, b, mask)
    }
}

/// The CPU backend (rayon): the reference every other backend is checked against.
#[derive(Debug, Clone, Copy, Default)]
pub struct Cpu;

impl Backend for Cpu {
    fn name(&self) -> &'static str {
        "cpu"
    }
}

/// The backend named `name`: `cpu`, or `gpu` (alias `wgpu`) on the first hardware adapter.
pub fn backend(name: &str) -> Result<Box<dyn Backend>, RenderError> {
    backend_on(name, None)
}

/// The backend named `name`; for `gpu`, on the adapter whose name contains `adapter`.
pub fn backend_on(name: &str, adapter: Option<&str>) -> Result<Box<dyn Backend>, RenderError> {
    match name {
        "cpu" => Ok(Box::new(Cpu)),
        "wgpu" | "gpu" => Ok(Box::new(crate::gpu::Gpu::new(adapter)?)),
        _ => Err(invalid(format!(
            "unknown backend {name:?}: expected cpu or gpu"
        ))),
    }
}
