//! The DeepFocus-family network (Xiao et al. 2018): the architecture ([`arch`]), weights in
//! safetensors with the architecture in their metadata ([`weights`]), the graph written once
//! over a backend's operations ([`graph`]), CPU inference ([`cpu`]), the image-level tasks
//! ([`tasks`]) and, with the `train` feature, training with candle ([`train`]).

pub mod arch;
pub mod cpu;
mod direct;
pub mod error;
pub mod fv;
pub mod gpu;
pub mod graph;
mod infer;
pub mod refine;
pub mod tasks;
pub mod tiles;
#[cfg(feature = "train")]
pub mod train;
pub mod weights;

pub use arch::{Arch, Classical, ClassicalLayers, Task};
pub use cpu::{Act, CpuNet};
pub use error::NetError;
pub use weights::Weights;

use std::path::{Path, PathBuf};

/// Where the shipped weights of `config` (`c1`, `c4`) live in the source tree.
pub fn shipped_weights(config: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("weights")
        .join(format!("{config}.safetensors"))
}

/// Loads `weights` (or the shipped weights of `config`) for CPU inference, checking that they
/// are a `config` network.
pub fn load_net(weights: Option<&Path>, config: &str) -> Result<CpuNet, NetError> {
    let path = weights.map_or_else(|| shipped_weights(config), Path::to_path_buf);
    if weights.is_none() && !path.exists() {
        return Err(NetError::Input(format!(
            "no shipped {config} weights at {}: train them with `dioptra train --config {config}` and pass --weights",
            path.display()
        )));
    }
    let w = Weights::load(&path)?;
    if w.arch.task.name() != config {
        return Err(NetError::WrongConfig {
            expected: w.arch.task.name().into(),
            asked: config.into(),
        });
    }
    CpuNet::new(w)
}
