//! dioptra-sim: device simulators that speak the real wire bytes, with physical models, and
//! procedural scenes with ground-truth renders.
//!
//! - Devices: [`optotune`] (Optotune Lens Driver 4), [`lens_controller`], [`sync_board`],
//!   [`dlpc350`] (TI DLPC350 over the in-memory HID link), [`gaze`] (eye-movement generator and
//!   simulated HID trackers), [`photodiode`] (the serial-line photodiode). Byte-speaking
//!   devices run on any link through [`serve::serve`].
//! - Shared models: [`lens_model`] (tunable-lens physics), [`light`] (light on a photodiode and
//!   its comparator), [`panel`] (a display panel's light: latency, persistence, dropped
//!   refreshes), [`protocol_device`] (the device side of dioptra-protocol), [`tokio_clock`].
//! - The image through the optics: [`eye_camera`] (a camera at the eye behind a simulated
//!   eyepiece, tunable lens and panel; a simulated photometer).
//! - Ground truth: [`scene`] (procedural scenes, pinhole, thin-lens and light-field renders).

pub mod dlpc350;
pub mod eye_camera;
pub mod gaze;
pub mod lens_controller;
pub mod lens_model;
pub mod light;
pub mod optotune;
pub mod panel;
pub mod photodiode;
pub mod protocol_device;
pub mod scene;
pub mod serve;
pub mod sync_board;
pub mod tokio_clock;
