//! Choosing a backend by name (`--backend`): the one module that knows every backend.

use crate::backend::Backend;
use crate::cpu::Cpu;
use crate::error::{invalid, RenderError};
use crate::gpu::Gpu;

/// The backend named `name`: `cpu`, or `gpu` (alias `wgpu`) on the first hardware adapter.
pub fn backend(name: &str) -> Result<Box<dyn Backend>, RenderError> {
    backend_on(name, None)
}

/// The backend named `name`; for `gpu`, on the adapter whose name contains `adapter`.
pub fn backend_on(name: &str, adapter: Option<&str>) -> Result<Box<dyn Backend>, RenderError> {
    match name {
        "cpu" => Ok(Box::new(Cpu)),
        "wgpu" | "gpu" => Ok(Box::new(Gpu::new(adapter)?)),
        _ => Err(invalid(format!(
            "unknown backend {name:?}: expected cpu or gpu"
        ))),
    }
}
