//! Optics methods (defocus, focal stacks, multifocal decomposition, retina, light fields,
//! foveation, metrics) behind a [`Backend`] seam, with the CPU backend as the reference.
//! All colour maths is in linear light; sRGB appears only in [`io`] and in the metrics.
//!
//! # Layers
//!
//! A module imports only modules of its own layer or lower ones, and no two modules import
//! each other (`python3 scripts/check_layers.py crates/render/src --layers crates/render/LAYERS`
//! checks both in CI; `LAYERS` is this list). Lowest first:
//!
//! 1. [`error`] (the GPU's errors too, so that everything below the backends can return them);
//! 2. `alloc`, `common`, `fft2`, [`io`], [`timing`]: support with no optics method in it; [`transfer`]: the
//!    panel's transfer function as a table (its CPU pass);
//! 3. [`kernel`]: blur kernels and convolution;
//! 4. [`gather`], [`lightfield`], [`metrics`], [`pyramid`]: methods on one image; [`warp`]: the
//!    eyepiece pre-warp's mesh and its CPU twin;
//! 5. [`composite`], [`defocus`], [`multifocal`], [`retina`], [`views`], [`foveate`],
//!    [`foveated`]: methods built on those; [`planner`], which predicts them;
//!    [`spectral_coarse`]: a decomposition solved on a coarser grid, linear blending's detail
//!    above it;
//! 6. [`spectral`]: the spectral decomposition, whose targets are rendered by the methods below;
//!    [`hybrid`]: spectral near the gaze, linear blending elsewhere;
//! 7. [`backend`]: the [`Backend`] trait and the types of its methods;
//! 8. [`cpu`] and [`gpu`]: the two backends; `transfer::gpu` and `warp::gpu`: those two
//!    passes on the GPU;
//! 9. [`factory`]: a backend chosen by name.

pub mod alloc;
pub mod backend;
mod common;
pub mod composite;
pub mod cpu;
pub mod defocus;
pub mod error;
pub mod factory;
mod fft2;
pub mod foveate;
pub mod foveated;
pub mod gather;
pub mod gpu;
pub mod hybrid;
pub mod io;
pub mod kernel;
pub mod lightfield;
pub mod metrics;
pub mod multifocal;
pub mod planner;
pub mod pyramid;
pub mod retina;
pub mod spectral;
pub mod spectral_coarse;
pub mod timing;
pub mod transfer;
pub mod views;
pub mod warp;

pub use backend::{Backend, Foveated};
pub use common::{check_focus, eye_for};
pub use cpu::Cpu;
pub use defocus::DefocusMethod;
pub use error::{GpuError, RenderError};
pub use factory::{backend, backend_on};
pub use gpu::Gpu;
pub use lightfield::LightFieldParams;
pub use multifocal::{Layers, OptimizeParams, OptimizeReport};
pub use spectral::{SpectralParams, SpectralPlan, SpectralReport};
