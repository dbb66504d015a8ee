//! The backend seam: the [`Backend`] trait and the types of its methods. Callers hold a
//! `&dyn Backend`. Every method is required: the CPU backend ([`crate::cpu::Cpu`], the
//! reference) and the GPU backend ([`crate::gpu::Gpu`]) each implement all of them, the GPU
//! returning [`RenderError::Unsupported`] for a method without a kernel, so a method added here
//! cannot run on the CPU behind a `--backend gpu` unnoticed. Choosing a backend by name is
//! [`crate::factory`]'s.

pub use crate::defocus::DefocusMethod;
use crate::error::RenderError;
use crate::foveate::LogPolar;
use crate::hybrid::{HybridParams, HybridReport};
use crate::metrics::Quality;
use crate::multifocal::{Layers, OptimizeParams, OptimizeReport};
use crate::retina::LfView;
use crate::spectral::{SpectralParams, SpectralReport};
use crate::views::RgbdView;
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};

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
    ) -> Result<Vec<RgbImage>, RenderError>;

    fn linear_blend(&self, input: &Rgbd, planes: &[Diopters]) -> Result<Layers, RenderError>;

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
    ) -> Result<(Layers, OptimizeReport), RenderError>;

    /// Spectral decomposition of `input` onto `planes`: the per-frequency least squares of
    /// the retinal images (see [`crate::spectral`]), its matrices built once per settings.
    fn spectral_blend(
        &self,
        input: &Rgbd,
        planes: &[Diopters],
        eye: &EyeModel,
        params: SpectralParams,
    ) -> Result<(Layers, SpectralReport), RenderError>;

    /// The gaze-contingent hybrid ([`crate::hybrid`], after Yu et al. 2019): spectral layers in
    /// a window around `gaze` (pixels; `None`: the image centre) when a blurred depth step
    /// reaches the fovea, linear blending elsewhere.
    fn hybrid_blend(
        &self,
        input: &Rgbd,
        planes: &[Diopters],
        eye: &EyeModel,
        gaze: Option<[f32; 2]>,
        params: &HybridParams,
    ) -> Result<(Layers, HybridReport), RenderError>;

    fn retina_multifocal(
        &self,
        layers: &Layers,
        foci: &[Diopters],
        eye: &EyeModel,
    ) -> Result<Vec<RgbImage>, RenderError>;

    fn retina_varifocal(
        &self,
        image: &RgbImage,
        display: Diopters,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<RgbImage, RenderError>;

    /// A light-field display seen focusing at `focus` (shift-and-add over the pupil).
    fn retina_lightfield(
        &self,
        views: &[LfView],
        spacing: f32,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<RgbImage, RenderError>;

    /// A `grid` x `grid` light field over a `span` metres square synthesised from sparse RGB-D
    /// views; `progress` is called with the views done.
    fn synthesize_light_field(
        &self,
        inputs: &[RgbdView],
        grid: usize,
        span: f32,
        eye: &EyeModel,
        progress: Progress,
    ) -> Result<Vec<LfView>, RenderError>;

    /// Log-polar sampling of `img` (Thumuluri & Sharma eq. 3-8) and inverse-distance
    /// interpolation of every other pixel from its four nearest samples (eq. 9).
    fn foveate(&self, img: &RgbImage, p: &LogPolar) -> Result<Foveated, RenderError>;

    /// The interpolation step of [`Backend::foveate`] with a given mask (1 = sampled).
    fn foveate_interpolate(&self, img: &RgbImage, mask: &Plane) -> Result<RgbImage, RenderError>;

    /// PSNR and SSIM of `a` against `b`, inside `mask` when given.
    fn quality(
        &self,
        a: &RgbImage,
        b: &RgbImage,
        mask: Option<&Plane>,
    ) -> Result<Quality, RenderError>;
}
