//! Varifocal lens drivers behind core's [`dioptra_core::VarifocalLens`] trait:
//! [`optotune::Optotune`] for the Optotune Lens Driver 4 and [`controller::LensController`] for
//! dioptra's own lens controller. Both enforce [`limits::LensLimits`] and reopen a lost link
//! through a [`reconnect::Opener`].

pub mod controller;
pub mod ids;
pub mod limits;
pub mod optotune;
pub mod reconnect;

pub use controller::{ControllerConfig, LensController};
pub use limits::{LensLimits, OutOfRange};
pub use optotune::{Optotune, OptotuneConfig, OptotuneInfo};
pub use reconnect::Opener;
