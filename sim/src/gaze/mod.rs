//! Gaze simulation: an eye-movement generator driven by a scene, replay of recorded CSV
//! traces, and simulated HID eye trackers that serve those samples as real report bytes
//! through the in-memory [`dioptra_transport::hid::memory`] link.

pub mod csv;
pub mod dioptra_tracker;
pub mod generator;
pub mod hid_tracker;
pub mod pupil_capture;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_protocol::BinocularSample;
use dioptra_transport::hid::memory::HidDeviceHandle;
use tokio::task::JoinHandle;
use tokio::time::{sleep_until, Instant};

pub use generator::{GazeGenerator, GeneratorConfig, SampleSource, Scene, SCENARIOS};

/// Faults and link conditions a test can set on a running simulated tracker.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Faults {
    /// Keep time but send nothing (a device that stops sending).
    pub silent: bool,
    /// Cut every report to this many bytes.
    pub truncate_to: Option<usize>,
    /// Delay from exposure to delivery, µs: a minimum plus a uniform jitter up to the second
    /// value (USB polling, device processing). Reports stay in order.
    pub latency_us: (u64, u64),
}

/// State shared between a simulated tracker's request handler and its sample task.
#[derive(Debug)]
pub(crate) struct Streaming<S> {
    pub device: S,
    pub faults: Faults,
    pub sent: u64,
}

pub(crate) use dioptra_core::lock;

/// A running simulated tracker: its device handle and sample task. Dropping it unplugs
/// the device.
pub struct SimTracker<S> {
    pub(crate) shared: Arc<Mutex<Streaming<S>>>,
    pub(crate) device: HidDeviceHandle,
    pub(crate) task: JoinHandle<()>,
}

impl<S> SimTracker<S> {
    pub fn set_faults(&self, faults: Faults) {
        lock(&self.shared).faults = faults;
    }
    /// Reports sent so far.
    pub fn sent(&self) -> u64 {
        lock(&self.shared).sent
    }
    /// Pushes raw bytes as an input report (for malformed-report tests).
    pub fn inject(&self, report: &[u8]) {
        let _ = self.device.send_input(report);
    }
    pub fn disconnect(&self, reason: &str) {
        self.device.disconnect(reason);
    }
    pub fn device_handle(&self) -> &HidDeviceHandle {
        &self.device
    }
}

impl<S> Drop for SimTracker<S> {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// Sends one report per sample at the sample's time (tokio's clock: wall time, or paused
/// test time) while `encode` says the device is streaming; stops at the end of the source or
/// when the host goes away.
pub(crate) fn spawn_serve<S: Send + 'static>(
    device: HidDeviceHandle,
    mut source: Box<dyn SampleSource>,
    shared: Arc<Mutex<Streaming<S>>>,
    encode: impl Fn(&mut S, &BinocularSample) -> Option<Vec<u8>> + Send + 'static,
) -> JoinHandle<()> {
    tokio::spawn(async move {
        let start = Instant::now();
        let mut jitter = generator::Rng::new(0x1a7e);
        while let Some((t_us, sample)) = source.next_sample() {
            let (min, spread) = lock(&shared).faults.latency_us;
            let delay = min.saturating_add((jitter.uniform() * spread as f64) as u64);
            // A trace whose times overflow the clock has nothing more to play.
            let Some(at) = start.checked_add(Duration::from_micros(t_us.saturating_add(delay)))
            else {
                break;
            };
            sleep_until(at).await;
            let report = {
                let mut st = lock(&shared);
                if st.faults.silent {
                    continue;
                }
                let Some(mut r) = encode(&mut st.device, &sample) else {
                    continue;
                };
                if let Some(n) = st.faults.truncate_to {
                    r.truncate(n);
                }
                st.sent += 1;
                r
            };
            if device.send_input(&report).is_err() {
                break;
            }
        }
    })
}
