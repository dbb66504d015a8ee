//! `dioptra demo`: the whole loop in one process, on the rig runtime `dioptra serve` runs
//! (dioptra-rig): the example rig of simulated devices (`crates/cli/examples/rig-sim.toml`: a
//! Lens Driver 4, an eye tracker and a sync board, each driven by its real driver over an
//! in-memory link), an animated procedural scene, the CPU renderer, and the scheduler between
//! them. Runs in simulated time (tokio's paused clock): as fast as this machine computes it,
//! with each frame's render taking the simulated time it really took here. Prints a summary
//! and writes frames and charts. `--eyes 2` runs the binocular example rig instead (a lens
//! per eye, the binocular tracker, side-by-side stereo) and prints and writes per eye.

#[cfg(feature = "simulated")]
mod frames;
pub(crate) mod plots;
#[cfg(feature = "simulated")]
mod run;

use std::path::PathBuf;

use anyhow::Result;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// varifocal, multifocal or lightfield.
    #[arg(long, default_value = "varifocal")]
    pub(crate) mode: String,
    /// Varifocal render method: gather, or auto (the planner chooses per frame: no blur,
    /// gather, or the light-field method with as few views as the scene needs).
    #[arg(long, default_value = "gather")]
    pub(crate) method: String,
    /// Simulated seconds to run.
    #[arg(long, default_value_t = 10.0)]
    pub(crate) seconds: f64,
    /// Where to write frames and charts.
    #[arg(long, default_value = "demo-out")]
    pub(crate) out: PathBuf,
    /// Image size, pixels (square, over the eye model's 20 degree field).
    #[arg(long, default_value_t = 256)]
    pub(crate) size: usize,
    /// Procedural scene seed (test seeds are 1000000-1999999).
    #[arg(long, default_value_t = 1_000_007)]
    pub(crate) seed: u64,
    /// Rays per pixel of the thin-lens ground truth the shown frames are scored against.
    #[arg(long, default_value_t = 48)]
    pub(crate) truth_samples: u32,
    /// Frames scored against ground truth (each costs a thin-lens render).
    #[arg(long, default_value_t = 3)]
    pub(crate) scored: usize,
    /// 1: the one-lens example rig. 2: the binocular example rig
    /// (`crates/cli/examples/rig-sim-binocular.toml`): a lens per eye driven from the
    /// binocular tracker, each eye's view ray cast from its own position and rendered at its
    /// own lens's focus, shown side by side (varifocal).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=2))]
    pub(crate) eyes: u8,
}

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
