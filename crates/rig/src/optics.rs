//! The rig's optics: `[optics]` and `[eye]` ([`config`]), from which each lens's optics map
//! (focus <-> lens command) is made.

pub mod config;
pub mod status;

pub use status::{FocusStatus, OpticsHandle};
