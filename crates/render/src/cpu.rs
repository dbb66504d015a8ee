//! The CPU backend (rayon): every [`Backend`] method on the CPU implementation of its module,
//! the reference every other backend is checked against.

use crate::backend::{Backend, DefocusMethod, Foveated, Progress};
use crate::error::RenderError;
use crate::foveate::{interpolate, log_polar_mask, LogPolar};
use crate::hybrid::{hybrid_blend, HybridParams, HybridReport};
use crate::metrics::{quality, Quality};
use crate::multifocal::{linear_blend, optimized_blend, Layers, OptimizeParams, OptimizeReport};
use crate::retina::{retina_lightfield, retina_multifocal, retina_varifocal, LfView};
use crate::spectral::{spectral_blend, SpectralParams, SpectralReport};
use crate::views::{synthesize_light_field, RgbdView};
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};

/// The CPU backend (rayon): the reference every other backend is checked against.
#[derive(Debug, Clone, Copy, Default)]
pub struct Cpu;

impl Backend for Cpu {
    fn name(&self) -> &'static str {
        "cpu"
    }

    fn defocus(
        &self,
        input: &Rgbd,
        foci: &[Diopters],
        eye: &EyeModel,
        method: DefocusMethod,
        progress: Progress,
    ) -> Result<Vec<RgbImage>, RenderError> {
        crate::defocus::defocus(input, foci, eye, method, progress)
    }

    fn linear_blend(&self, input: &Rgbd, planes: &[Diopters]) -> Result<Layers, RenderError> {
        linear_blend(input, planes)
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
        optimized_blend(targets, foci, planes, eye, init, params, progress)
    }

    fn spectral_blend(
        &self,
        input: &Rgbd,
        planes: &[Diopters],
        eye: &EyeModel,
        params: SpectralParams,
    ) -> Result<(Layers, SpectralReport), RenderError> {
        spectral_blend(input, planes, eye, params)
    }

    fn hybrid_blend(
        &self,
        input: &Rgbd,
        planes: &[Diopters],
        eye: &EyeModel,
        gaze: Option<[f32; 2]>,
        params: &HybridParams,
    ) -> Result<(Layers, HybridReport), RenderError> {
        hybrid_blend(input, planes, eye, gaze, params)
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

    fn retina_lightfield(
        &self,
        views: &[LfView],
        spacing: f32,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<RgbImage, RenderError> {
        retina_lightfield(views, spacing, focus, eye)
    }

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

    fn foveate(&self, img: &RgbImage, p: &LogPolar) -> Result<Foveated, RenderError> {
        let (mask, fraction) = log_polar_mask(img.width(), img.height(), p)?;
        Ok(Foveated {
            image: interpolate(img, &mask)?,
            mask,
            fraction,
        })
    }

    fn foveate_interpolate(&self, img: &RgbImage, mask: &Plane) -> Result<RgbImage, RenderError> {
        interpolate(img, mask)
    }

    fn quality(
        &self,
        a: &RgbImage,
        b: &RgbImage,
        mask: Option<&Plane>,
    ) -> Result<Quality, RenderError> {
        quality(a, b, mask)
    }
}
