//! `[render]`: where frames are rendered (CPU or GPU, which adapter), the network's weights
//! and the foveation of the varifocal render; its defaults and checks.

use std::path::PathBuf;

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
