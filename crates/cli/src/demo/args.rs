//! `dioptra demo`'s arguments.

use std::path::PathBuf;

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
