//! Optics methods (defocus, focal stacks, multifocal decomposition, retina, light fields,
//! foveation, metrics) behind a [`Backend`] seam, with the CPU backend as the reference.
//! All colour maths is in linear light; sRGB appears only in [`io`] and in the metrics.

pub mod alloc;
pub mod backend;
mod common;
pub mod composite;
pub mod error;
mod fft2;
pub mod foveate;
pub mod foveated;
pub mod gather;
pub mod gpu;
pub mod io;
pub mod kernel;
pub mod lightfield;
pub mod metrics;
pub mod multifocal;
pub mod planner;
pub mod pyramid;
pub mod retina;
pub mod spectral;
pub mod views;

pub use backend::{backend, backend_on, Backend, Cpu, DefocusMethod, Foveated};
pub use common::eye_for;
pub use error::RenderError;
pub use gpu::{Gpu, GpuError};
pub use lightfield::LightFieldParams;
pub use multifocal::{Layers, OptimizeParams, OptimizeReport};
pub use spectral::{SpectralParams, SpectralPlan, SpectralReport};
