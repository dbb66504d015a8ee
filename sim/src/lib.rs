//! Device simulators that speak the real wire bytes, with physical models; procedural scenes and ground-truth renders. Filled by the device and renderer issues.

pub mod dlpc350;
pub mod gaze;
pub mod lens_controller;
pub mod lens_model;
pub mod optotune;
pub mod protocol_device;
pub mod scene;
pub mod sync_board;
pub mod tokio_clock;
