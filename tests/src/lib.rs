//! The whole-loop tests live in `tests/`; the rig they run is `dioptra-rig`'s, through its
//! simulated-rig builder (`dioptra_rig::simulated_rig`), so they test the code `dioptra serve`
//! runs.
