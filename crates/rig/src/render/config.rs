//! `[render]`: where frames are rendered (CPU or GPU, which adapter), the network's weights,
//! the foveation of the varifocal render and the multifocal hybrid's and spectral settings; its defaults
//! and checks.

use std::path::PathBuf;

use dioptra_render::hybrid::HybridParams;
use dioptra_render::planner::FoveationSettings;
use serde::{Deserialize, Serialize};

use crate::config::error::{invalid, ConfigError};

/// Render settings.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Render {
    /// Directory of the network's weights for `method = "network"`: `c1.safetensors`
    /// (varifocal) and `c4.safetensors` (multifocal). Default: the shipped crates/net/weights.
    pub weights: Option<PathBuf>,
    /// Where gather, light-field defocus and linear blending run: `auto` (the GPU when a
    /// hardware adapter exists), `cpu` or `gpu` (any adapter, a software one included).
    #[serde(default)]
    pub backend: RenderBackend,
    /// `backend = "gpu"`: the adapter whose name contains this (e.g. "nvidia", "llvmpipe").
    pub adapter: Option<String>,
    /// Gaze-contingent resolution of the varifocal render (`method = "pyramid"` or `"auto"`):
    /// `"off"` (every pixel at full resolution), or full resolution within `radius_deg` of
    /// each eye's gaze and coarser beyond as the eye's acuity falls, e.g.
    /// `{ radius_deg = 5.0, falloff_arcmin_per_deg = 1.32 }`. The work it drops is not done.
    /// With `auto` the planner's fovea (the region its accuracy target is for) is this radius.
    #[serde(default)]
    pub foveation: FoveationSetting,
    /// The multifocal hybrid decomposition's settings (`method = "hybrid"`): spectral layers
    /// within `fovea_deg` of each eye's gaze when a blurred depth step reaches it, linear
    /// blending elsewhere, e.g. `{ fovea_deg = 2.5, blend_deg = 0.5, scale = 0 }`.
    #[serde(default)]
    pub hybrid: HybridSetting,
    /// The spectral decomposition's settings (`method = "spectral"`), e.g. `{ scale = 1 }`.
    #[serde(default)]
    pub spectral: SpectralSetting,
}

/// `[render.spectral]`: the spectral multifocal decomposition (Mercier et al. 2017).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SpectralSetting {
    /// The grid it solves on: 1 the image's own pixels (full resolution: about 3 s of CPU a
    /// frame per eye at 960 x 1080); s > 1 a grid s times coarser plus linear blending's
    /// detail above it (faster, less exact); 0 (default) chosen from the widest blur: full
    /// resolution while it is under 10 px, a 1/4 grid at 960 x 1080 over 20 degrees (about
    /// 160 ms, 1 to 2 dB below full resolution against the truth). At most 16.
    #[serde(default)]
    pub scale: u32,
}

impl SpectralSetting {
    /// The decomposition's settings: its defaults with this grid.
    pub fn params(&self) -> dioptra_render::SpectralParams {
        dioptra_render::SpectralParams {
            scale: self.scale as usize,
            ..dioptra_render::SpectralParams::default()
        }
    }

    /// The scale is one the decomposition takes.
    pub fn check(&self) -> Result<(), ConfigError> {
        let max = dioptra_render::spectral_coarse::MAX_SCALE;
        if self.scale as usize > max {
            return Err(invalid(
                "render.spectral.scale",
                format!(
                    "{}: expected 0 (chosen from the blur), 1 (full resolution) or a divisor up to {max}",
                    self.scale
                ),
            ));
        }
        Ok(())
    }
}

/// `[render.hybrid]`: the gaze-contingent hybrid multifocal decomposition (after Yu et al.
/// 2019): the spectral decomposition in a window around each eye's gaze, run only when a
/// blurred depth step reaches the fovea, linear blending everywhere else.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct HybridSetting {
    /// Radius around each eye's gaze where the layers are the spectral solution's, degrees of
    /// the eye's field (default 2.5: a 5 degree fovea).
    #[serde(default = "default_hybrid_fovea_deg")]
    pub fovea_deg: f32,
    /// Width of the cross-fade from spectral to linear layers beyond the fovea, degrees
    /// (default 0.5). A gaze that moves less than this within one content frame keeps the
    /// frame's layers; further, they are made again around it.
    #[serde(default = "default_hybrid_blend_deg")]
    pub blend_deg: f32,
    /// The spectral solve's grid in the window: 1 full resolution, s > 1 a 1/s grid plus
    /// linear blending's detail above it (faster, less exact), 0 automatic (coarsened while
    /// the widest blur stays 8 of its pixels or more). Default 0; at most 16.
    #[serde(default)]
    pub scale: u32,
}

impl Default for HybridSetting {
    fn default() -> Self {
        HybridSetting {
            fovea_deg: default_hybrid_fovea_deg(),
            blend_deg: default_hybrid_blend_deg(),
            scale: 0,
        }
    }
}

fn default_hybrid_fovea_deg() -> f32 {
    HybridParams::default().fovea_deg
}

fn default_hybrid_blend_deg() -> f32 {
    HybridParams::default().blend_deg
}

/// The largest `render.hybrid.scale`: the hybrid's own bound.
const MAX_HYBRID_SCALE: u32 = 16;

impl HybridSetting {
    /// The decomposition's settings (its spectral solve the rig's spectral method's).
    pub fn params(&self) -> HybridParams {
        HybridParams {
            fovea_deg: self.fovea_deg,
            blend_deg: self.blend_deg,
            scale: self.scale as usize,
            ..HybridParams::default()
        }
    }

    /// The fovea and the fade fit in the eye's field (`fov_deg` across) and the scale is one
    /// the hybrid takes.
    pub fn check(&self, fov_deg: f32) -> Result<(), ConfigError> {
        let half = 0.5 * fov_deg;
        if !(self.fovea_deg.is_finite() && self.fovea_deg > 0.0 && self.fovea_deg <= half) {
            return Err(invalid(
                "render.hybrid.fovea_deg",
                format!(
                    "{}: expected more than 0 and at most half the eye's field (eye.fov_deg = {fov_deg})",
                    self.fovea_deg
                ),
            ));
        }
        if !(self.blend_deg.is_finite() && self.blend_deg >= 0.0 && self.blend_deg <= half) {
            return Err(invalid(
                "render.hybrid.blend_deg",
                format!(
                    "{}: expected 0 or more and at most half the eye's field (eye.fov_deg = {fov_deg})",
                    self.blend_deg
                ),
            ));
        }
        if self.scale > MAX_HYBRID_SCALE {
            return Err(invalid(
                "render.hybrid.scale",
                format!(
                    "{}: expected 0 (automatic), 1 (full resolution) or a divisor up to {MAX_HYBRID_SCALE}",
                    self.scale
                ),
            ));
        }
        Ok(())
    }
}

/// `[render] foveation`: `"off"`, or a foveal radius and an acuity fall-off.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(
    untagged,
    expecting = "\"off\", or a table { radius_deg = 5.0, falloff_arcmin_per_deg = 1.32 }"
)]
pub enum FoveationSetting {
    Off(FoveationOff),
    Around(GazeFoveation),
}

impl Default for FoveationSetting {
    fn default() -> Self {
        FoveationSetting::Off(FoveationOff::Off)
    }
}

/// `foveation = "off"`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum FoveationOff {
    Off,
}

/// Full resolution within `radius_deg` of the gaze; beyond it the smallest detail drawn grows
/// by `falloff_arcmin_per_deg` per degree of eccentricity (the eye's minimum angle of
/// resolution grows linearly: Guenter et al. 2012 measured 1.32 to 1.65 arcmin per degree).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct GazeFoveation {
    /// Radius around each eye's gaze rendered at full resolution, degrees of the eye's field
    /// (default 5: the central 10 degrees).
    #[serde(default = "default_radius_deg")]
    pub radius_deg: f32,
    /// How fast the smallest detail drawn grows beyond the radius, arcminutes per degree of
    /// eccentricity (default 1.32; larger: coarser periphery, less work).
    #[serde(default = "default_falloff")]
    pub falloff_arcmin_per_deg: f32,
}

fn default_radius_deg() -> f32 {
    dioptra_render::foveated::DEFAULT_RADIUS_DEG
}

fn default_falloff() -> f32 {
    dioptra_render::foveated::DEFAULT_MAR_SLOPE * 60.0
}

/// The largest fall-off the foveated render takes, arcminutes per degree (its acuity slope's
/// bound, 10 degrees per degree).
const MAX_FALLOFF_ARCMIN_PER_DEG: f32 = 600.0;

impl FoveationSetting {
    /// The foveation the renderer and the planner use; `None`: off.
    pub fn settings(&self) -> Option<FoveationSettings> {
        match *self {
            FoveationSetting::Off(_) => None,
            FoveationSetting::Around(f) => Some(FoveationSettings {
                radius_deg: f.radius_deg,
                mar_slope: f.falloff_arcmin_per_deg / 60.0,
            }),
        }
    }

    /// The radius fits in the eye's field (`fov_deg` across) and the fall-off is one the
    /// renderer takes.
    pub fn check(&self, fov_deg: f32) -> Result<(), ConfigError> {
        let FoveationSetting::Around(f) = self else {
            return Ok(());
        };
        if !(f.radius_deg.is_finite() && f.radius_deg > 0.0 && f.radius_deg <= fov_deg) {
            return Err(invalid(
                "render.foveation.radius_deg",
                format!(
                    "{}: expected more than 0 and at most the eye's field (eye.fov_deg = {fov_deg})",
                    f.radius_deg
                ),
            ));
        }
        let falloff = f.falloff_arcmin_per_deg;
        if !(falloff.is_finite() && falloff > 0.0 && falloff <= MAX_FALLOFF_ARCMIN_PER_DEG) {
            return Err(invalid(
                "render.foveation.falloff_arcmin_per_deg",
                format!(
                    "{falloff}: expected more than 0 and at most {MAX_FALLOFF_ARCMIN_PER_DEG} (the eye's is 1.32 to 1.65)"
                ),
            ));
        }
        Ok(())
    }
}

/// `[render] backend`.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "kebab-case")]
pub enum RenderBackend {
    #[default]
    Auto,
    Cpu,
    Gpu,
}

impl Render {
    /// The weights file of network configuration `config` (`c1`, `c4`).
    pub fn weights_file(&self, config: &str) -> PathBuf {
        match &self.weights {
            Some(dir) => dir.join(format!("{config}.safetensors")),
            None => dioptra_net::shipped_weights(config),
        }
    }
}

impl Render {
    /// An adapter is chosen only for the GPU.
    pub fn check(&self) -> Result<(), ConfigError> {
        if self.adapter.is_some() && self.backend == RenderBackend::Cpu {
            return Err(invalid(
                "render.adapter",
                "an adapter is chosen for the GPU: set render.backend = \"gpu\" or remove it",
            ));
        }
        Ok(())
    }
}
