//! Varifocal lens drivers (Optotune Lens Driver 4; the dioptra lens controller) behind core's VarifocalLens trait. Filled by the lens issue; today it holds the devices' match table (ids.rs).

pub mod ids;
