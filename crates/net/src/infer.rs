//! What the image-level tasks need of a loaded net: CPU ([`CpuNet`]) and GPU
//! ([`crate::gpu::GpuNet`]) inference differ only in how they evaluate it, so each task
//! ([`crate::tasks`], [`crate::refine`]) is written once over this trait.

use crate::arch::Arch;
use crate::cpu::{Act, CpuNet};
use crate::error::NetError;
use crate::tiles::TileMap;

pub(crate) trait Infer {
    fn arch(&self) -> &Arch;

    /// The net's output for a full-resolution HWC input.
    fn forward(&self, x: &Act) -> Result<Act, NetError>;

    /// The net's output, exact at least on the pixels `tiles` corrects (elsewhere it may be
    /// anything): the CPU evaluates only those tiles and the halo they need, the GPU the
    /// whole image.
    fn forward_on(&self, x: &Act, tiles: &TileMap) -> Result<Act, NetError>;
}

impl Infer for CpuNet {
    fn arch(&self) -> &Arch {
        CpuNet::arch(self)
    }

    fn forward(&self, x: &Act) -> Result<Act, NetError> {
        CpuNet::forward(self, x)
    }

    fn forward_on(&self, x: &Act, tiles: &TileMap) -> Result<Act, NetError> {
        self.forward_tiles(x, tiles)
    }
}
