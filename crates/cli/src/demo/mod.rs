//! `dioptra demo`: the whole loop in one process, on the rig runtime `dioptra serve` runs
//! (dioptra-rig): the example rig of simulated devices (`crates/cli/examples/rig-sim.toml`: a
//! Lens Driver 4, an eye tracker and a sync board, each driven by its real driver over an
//! in-memory link), an animated procedural scene, the CPU renderer, and the scheduler between
//! them. Runs in simulated time (tokio's paused clock): as fast as this machine computes it,
//! with each frame's render taking the simulated time it really took here. Prints a summary
//! and writes frames and charts. `--eyes 2` runs the binocular example rig instead (a lens
//! per eye, the binocular tracker, side-by-side stereo) and prints and writes per eye.

mod args;
#[cfg(feature = "simulated")]
mod frames;
mod plots;
#[cfg(feature = "simulated")]
mod render;
#[cfg(feature = "simulated")]
mod run;

use anyhow::Result;

pub use args::Args;

#[cfg(feature = "simulated")]
pub fn run_demo(args: Args) -> Result<()> {
    run::run_demo(args)
}

#[cfg(not(feature = "simulated"))]
pub fn run_demo(_: Args) -> Result<()> {
    anyhow::bail!(
        "the demo runs the rig on simulated time, and this dioptra was built without the \
         `simulated` feature; rebuild with default features (cargo run --release -- demo)"
    )
}
