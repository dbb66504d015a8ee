//! Device simulators that speak the real wire bytes, with physical models; procedural scenes and ground-truth renders. Today: the lens physical model and the device side of dioptra-protocol.

pub mod lens_model;
pub mod protocol_device;
