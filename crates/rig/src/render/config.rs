//! `[render]`: where frames are rendered (CPU or GPU, which adapter) and the network's
//! weights; its defaults and checks.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::config::error::{invalid, ConfigError};

/// Render settings.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
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
}

/// `[render] backend`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
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
