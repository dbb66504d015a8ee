//! A [`Clock`] on tokio's timer: wall time in a normal runtime, and simulated time under
//! `tokio::time::pause()`, so a simulator served in a test moves only as the test's time does.

use dioptra_core::{Clock, Timestamp};
use tokio::time::Instant;

/// Host time counted from when this value was made, read from tokio's clock.
#[derive(Debug, Clone, Copy)]
pub struct TokioClock {
    origin: Instant,
}

impl TokioClock {
    /// Must be called inside a tokio runtime when time is paused (it reads tokio's clock).
    pub fn new() -> Self {
        TokioClock {
            origin: Instant::now(),
        }
    }
}

impl Default for TokioClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for TokioClock {
    fn now(&self) -> Timestamp {
        Timestamp(self.origin.elapsed().as_nanos().min(u128::from(u64::MAX)) as u64)
    }
}
