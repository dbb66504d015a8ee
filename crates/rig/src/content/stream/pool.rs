//! Memory for frames: the planes of frames done with, kept for the next ones.

use std::sync::{Arc, Mutex};

use dioptra_core::{lock, Rgbd};

/// Spare planes of one frame size, reused from frame to frame: a fresh allocation each frame
/// costs a page fault and the kernel's zeroing per page (a 1920 x 1080 frame is 33 MB).
pub(crate) struct Planes {
    len: usize,
    pub(super) spare: Mutex<Vec<Vec<f32>>>,
}

/// Spare planes kept: two frames' worth.
const SPARE_PLANES: usize = 8;

impl Planes {
    pub(crate) fn new(len: usize) -> Planes {
        Planes {
            len,
            spare: Mutex::new(Vec::new()),
        }
    }
    /// A plane of `len` values (its contents are to be overwritten).
    pub(crate) fn take(&self) -> Vec<f32> {
        lock(&self.spare)
            .pop()
            .unwrap_or_else(|| vec![0.0; self.len])
    }
    pub(crate) fn give(&self, v: Vec<f32>) {
        let mut spare = lock(&self.spare);
        if v.len() == self.len && spare.len() < SPARE_PLANES {
            spare.push(v);
        }
    }
    /// A frame no one else holds: its planes are kept for the next ones.
    pub(crate) fn give_frame(&self, frame: Arc<Rgbd>) {
        if let Ok(Rgbd { color, depth }) = Arc::try_unwrap(frame) {
            let [r, g, b] = color.channels;
            for p in [r, g, b, depth.into_plane()] {
                self.give(p.into_vec());
            }
        }
    }
}
