//! Stamps each sample with host receive time and maps device time onto the host timeline.

use std::sync::Arc;

use dioptra_core::{Clock, ClockMapper, Timestamp};

/// `timeout` from now, or a year away when that overflows (a caller's `Duration::MAX`).
pub(crate) fn deadline(timeout: std::time::Duration) -> tokio::time::Instant {
    let now = tokio::time::Instant::now();
    now.checked_add(timeout)
        .unwrap_or(now + std::time::Duration::from_secs(365 * 86_400))
}

/// Host stamping shared by the gaze drivers.
pub(crate) struct Stamper {
    clock: Arc<dyn Clock>,
    mapper: ClockMapper,
}

/// The three times every sample carries.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Stamps {
    pub device: Timestamp,
    pub host_receive: Timestamp,
    pub host: Timestamp,
}

impl Stamper {
    pub fn new(clock: Arc<dyn Clock>) -> Self {
        Stamper {
            clock,
            mapper: ClockMapper::new(),
        }
    }

    pub fn now(&self) -> Timestamp {
        self.clock.now()
    }

    /// A sample stamped `device_us` that arrived at `host_receive`.
    pub fn stamp(&mut self, device_us: u64, host_receive: Timestamp) -> Stamps {
        // HID streams have no ping: one-way evidence, least-delayed sample per bucket.
        self.mapper.add_one_way(device_us, host_receive);
        Stamps {
            device: Timestamp::from_micros(device_us),
            host_receive,
            host: self.mapper.to_host(device_us).unwrap_or(host_receive),
        }
    }

    pub fn mapper(&self) -> &ClockMapper {
        &self.mapper
    }
}
