//! Multifocal sync hardware drivers (the dioptra sync board; TI DLPC350) behind core's PlaneSequencer trait. Filled by the sync issue; today it holds the devices' match table (ids.rs).

pub mod ids;
