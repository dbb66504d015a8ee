//! An in-memory HID device for tests and simulators.
//!
//! The simulator supplies the report descriptor and a [`HidBehaviour`] that answers
//! feature and output requests, and pushes input reports through a [`HidDeviceHandle`].
//! The driver under test gets a [`MemoryHidLink`], a [`HidLink`] like a real device's.
//! Reports follow the module convention: report id first (0 when the device uses none).
//!
//! ```
//! # async fn demo() -> Result<(), dioptra_transport::LinkError> {
//! use dioptra_transport::hid::memory::{self, HidBehaviour, HidRefusal};
//! use dioptra_transport::HidLink;
//! use std::time::Duration;
//!
//! struct Tracker { mode: u8 }
//! impl HidBehaviour for Tracker {
//!     fn get_feature(&mut self, id: u8, buf: &mut [u8]) -> Result<usize, HidRefusal> {
//!         match (id, buf) {
//!             (3, [_, mode, ..]) => { *mode = self.mode; Ok(2) }
//!             _ => Err(HidRefusal::new(format!("no feature report {id}"))),
//!         }
//!     }
//!     fn set_feature(&mut self, report: &[u8]) -> Result<(), HidRefusal> {
//!         match report {
//!             [3, mode] => { self.mode = *mode; Ok(()) }
//!             _ => Err(HidRefusal::new("unsupported feature report")),
//!         }
//!     }
//! }
//!
//! let (mut host, device) = memory::device(vec![0x05, 0x12], Tracker { mode: 0 }, 64);
//! host.send_feature_report(&[3, 1]).await?;
//! device.send_input(&[1, 0xaa, 0xbb])?;
//! let mut buf = [0u8; 64];
//! let n = host.read_input_report(&mut buf, Duration::from_millis(100)).await?;
//! assert_eq!(&buf[..n], &[1, 0xaa, 0xbb]);
//! # Ok(()) }
//! ```

use std::collections::VecDeque;
use std::fmt;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use dioptra_core::LinkError;
use tokio::sync::Notify;
use tokio::time::{sleep_until, Instant};

use super::hidraw::empty_report;
use super::HidLink;

/// A simulated device declining a request; the host sees [`LinkError::Io`] with this
/// message, as a real device's stalled control transfer shows up.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HidRefusal(pub String);

impl HidRefusal {
    pub fn new(reason: impl Into<String>) -> Self {
        HidRefusal(reason.into())
    }
}

impl fmt::Display for HidRefusal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

/// How a simulated device answers the host's requests. Called on the host's task, so keep
/// each call short; share state with the task that sends input reports through an
/// `Arc<Mutex<..>>` inside the behaviour. Unimplemented requests are refused.
pub trait HidBehaviour: Send + 'static {
    /// Fills feature report `report_id` into `buf`, whose first byte is already the id;
    /// returns the report's length including that byte (at most `buf.len()`).
    fn get_feature(&mut self, report_id: u8, buf: &mut [u8]) -> Result<usize, HidRefusal> {
        let _ = buf;
        Err(HidRefusal::new(format!(
            "feature report {report_id} is not readable"
        )))
    }

    /// Takes a feature report; `report[0]` is its id.
    fn set_feature(&mut self, report: &[u8]) -> Result<(), HidRefusal> {
        let _ = report;
        Err(HidRefusal::new("feature reports are not writable"))
    }

    /// Takes an output report; `report[0]` is its id.
    fn write_output(&mut self, report: &[u8]) -> Result<(), HidRefusal> {
        let _ = report;
        Err(HidRefusal::new("the device takes no output reports"))
    }
}

/// Creates a simulated device. `queue` input reports may wait unread (at least 1; hidraw
/// keeps 64); further ones are dropped and counted, as hidraw drops them.
pub fn device(
    descriptor: Vec<u8>,
    behaviour: impl HidBehaviour,
    queue: usize,
) -> (MemoryHidLink, HidDeviceHandle) {
    let shared = Arc::new(Shared {
        state: Mutex::new(State {
            queue: VecDeque::new(),
            capacity: queue.max(1),
            dropped: 0,
            severed: None,
            host_open: true,
            handles: 1,
        }),
        input: Notify::new(),
    });
    let link = MemoryHidLink {
        shared: shared.clone(),
        behaviour: Box::new(behaviour),
        descriptor,
        name: "in-memory HID device".to_string(),
    };
    (link, HidDeviceHandle { shared })
}

struct Shared {
    state: Mutex<State>,
    /// Wakes the host: an input report arrived or the device went away.
    input: Notify,
}

struct State {
    queue: VecDeque<Vec<u8>>,
    capacity: usize,
    dropped: u64,
    severed: Option<String>,
    host_open: bool,
    /// Live [`HidDeviceHandle`]s; the device is gone when the last one is dropped.
    handles: usize,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        // No invariant spans a panic point, so a poisoned lock is still consistent.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn sever(&self, reason: String) {
        let mut s = self.lock();
        s.severed.get_or_insert(reason);
        s.queue.clear();
        drop(s);
        self.input.notify_one();
    }
}

/// The host's side: what the driver under test talks to.
pub struct MemoryHidLink {
    shared: Arc<Shared>,
    behaviour: Box<dyn HidBehaviour>,
    descriptor: Vec<u8>,
    name: String,
}

impl fmt::Debug for MemoryHidLink {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.name)
    }
}

impl MemoryHidLink {
    /// Names the device in [`HidLink::describe`] and error messages.
    pub fn named(mut self, name: impl Into<String>) -> Self {
        self.name = name.into();
        self
    }

    fn check(&self) -> Result<(), LinkError> {
        match &self.shared.lock().severed {
            Some(reason) => Err(LinkError::Disconnected(format!("{}: {reason}", self.name))),
            None => Ok(()),
        }
    }

    fn refused(&self, what: &str, r: HidRefusal) -> LinkError {
        LinkError::Io(format!("{} refused the {what}: {r}", self.name))
    }
}

impl Drop for MemoryHidLink {
    fn drop(&mut self) {
        self.shared.lock().host_open = false;
    }
}

impl HidLink for MemoryHidLink {
    async fn read_input_report(
        &mut self,
        buf: &mut [u8],
        timeout: Duration,
    ) -> Result<usize, LinkError> {
        if buf.is_empty() {
            return Ok(0);
        }
        let deadline = Instant::now() + timeout;
        loop {
            {
                let mut s = self.shared.lock();
                if let Some(reason) = &s.severed {
                    return Err(LinkError::Disconnected(format!("{}: {reason}", self.name)));
                }
                if let Some(report) = s.queue.pop_front() {
                    let n = report.len().min(buf.len());
                    buf[..n].copy_from_slice(&report[..n]);
                    return Ok(n);
                }
            }
            if Instant::now() >= deadline {
                return Err(crate::timeout_error(timeout));
            }
            tokio::select! {
                _ = self.shared.input.notified() => {}
                _ = sleep_until(deadline) => {}
            }
        }
    }

    async fn write_output_report(&mut self, report: &[u8]) -> Result<(), LinkError> {
        self.check()?;
        if report.is_empty() {
            return Err(empty_report(&self.name));
        }
        self.behaviour
            .write_output(report)
            .map_err(|r| self.refused("output report", r))
    }

    async fn get_feature_report(
        &mut self,
        report_id: u8,
        buf: &mut [u8],
    ) -> Result<usize, LinkError> {
        self.check()?;
        if buf.is_empty() {
            return Err(empty_report(&self.name));
        }
        buf[0] = report_id;
        let n = self
            .behaviour
            .get_feature(report_id, buf)
            .map_err(|r| self.refused(&format!("feature report {report_id} read"), r))?;
        if n == 0 || n > buf.len() {
            return Err(LinkError::Io(format!(
                "{}: simulated device returned {n} bytes for feature report {report_id} \
                 into a {}-byte buffer",
                self.name,
                buf.len()
            )));
        }
        Ok(n)
    }

    async fn send_feature_report(&mut self, report: &[u8]) -> Result<(), LinkError> {
        self.check()?;
        if report.is_empty() {
            return Err(empty_report(&self.name));
        }
        self.behaviour
            .set_feature(report)
            .map_err(|r| self.refused("feature report", r))
    }

    async fn report_descriptor(&mut self) -> Result<Vec<u8>, LinkError> {
        self.check()?;
        Ok(self.descriptor.clone())
    }

    fn describe(&self) -> String {
        self.name.clone()
    }
}

/// The simulator's side: pushes input reports and can unplug the device. Cloneable; the
/// device counts as unplugged when the last clone is dropped.
pub struct HidDeviceHandle {
    shared: Arc<Shared>,
}

impl fmt::Debug for HidDeviceHandle {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("HidDeviceHandle")
    }
}

impl Clone for HidDeviceHandle {
    fn clone(&self) -> Self {
        self.shared.lock().handles += 1;
        HidDeviceHandle {
            shared: self.shared.clone(),
        }
    }
}

impl Drop for HidDeviceHandle {
    fn drop(&mut self) {
        let last = {
            let mut s = self.shared.lock();
            s.handles -= 1;
            s.handles == 0
        };
        if last {
            self.shared
                .sever("the simulated device went away".to_string());
        }
    }
}

impl HidDeviceHandle {
    /// Queues an input report (report id first) for the host. When the host has `queue`
    /// reports unread this one is dropped (see [`HidDeviceHandle::dropped_reports`]), and
    /// still `Ok`: a device cannot tell. Fails with [`LinkError::Disconnected`] once the
    /// host closed the link or the device was unplugged, so a simulator loop knows to stop.
    pub fn send_input(&self, report: &[u8]) -> Result<(), LinkError> {
        let mut s = self.shared.lock();
        if let Some(reason) = &s.severed {
            return Err(LinkError::Disconnected(reason.clone()));
        }
        if !s.host_open {
            return Err(LinkError::Disconnected("the host closed the device".into()));
        }
        if s.queue.len() >= s.capacity {
            s.dropped += 1;
            return Ok(());
        }
        s.queue.push_back(report.to_vec());
        drop(s);
        self.shared.input.notify_one();
        Ok(())
    }

    /// Unplugs the device: every host call fails with [`LinkError::Disconnected`] carrying
    /// `reason`, and queued input reports are lost.
    pub fn disconnect(&self, reason: impl Into<String>) {
        self.shared.sever(reason.into());
    }

    /// Input reports dropped because the host did not read them in time.
    pub fn dropped_reports(&self) -> u64 {
        self.shared.lock().dropped
    }

    /// False once the host dropped its link.
    pub fn host_connected(&self) -> bool {
        self.shared.lock().host_open
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SEC: Duration = Duration::from_secs(1);

    /// Feature 2: 3-byte config (id + 2 bytes), readable and writable. Output reports
    /// are logged. Shares state with the test through an Arc.
    #[derive(Default)]
    struct Sim {
        config: [u8; 2],
        outputs: Arc<Mutex<Vec<Vec<u8>>>>,
    }

    impl HidBehaviour for Sim {
        fn get_feature(&mut self, id: u8, buf: &mut [u8]) -> Result<usize, HidRefusal> {
            if id != 2 || buf.len() < 3 {
                return Err(HidRefusal::new(format!("no feature report {id}")));
            }
            buf[1..3].copy_from_slice(&self.config);
            Ok(3)
        }
        fn set_feature(&mut self, report: &[u8]) -> Result<(), HidRefusal> {
            match report {
                [2, a, b] => {
                    self.config = [*a, *b];
                    Ok(())
                }
                _ => Err(HidRefusal::new("bad feature report")),
            }
        }
        fn write_output(&mut self, report: &[u8]) -> Result<(), HidRefusal> {
            self.outputs.lock().unwrap().push(report.to_vec());
            Ok(())
        }
    }

    const DESCRIPTOR: [u8; 4] = [0x05, 0x12, 0x09, 0x01];

    #[tokio::test(start_paused = true)]
    async fn feature_input_and_output_round_trip() {
        let sim = Sim::default();
        let outputs = sim.outputs.clone();
        let (mut host, device) = device(DESCRIPTOR.to_vec(), sim, 8);

        assert_eq!(host.report_descriptor().await.unwrap(), DESCRIPTOR);

        host.send_feature_report(&[2, 7, 9]).await.unwrap();
        let mut buf = [0xffu8; 16];
        assert_eq!(host.get_feature_report(2, &mut buf).await, Ok(3));
        assert_eq!(&buf[..3], &[2, 7, 9]);

        host.write_output_report(&[0, 0x40, 1]).await.unwrap();
        assert_eq!(*outputs.lock().unwrap(), vec![vec![0, 0x40, 1]]);

        device.send_input(&[1, 10, 20, 30]).unwrap();
        device.send_input(&[1, 11]).unwrap();
        let n = host.read_input_report(&mut buf, SEC).await.unwrap();
        assert_eq!(&buf[..n], &[1, 10, 20, 30]);
        let n = host.read_input_report(&mut buf, SEC).await.unwrap();
        assert_eq!(&buf[..n], &[1, 11]);
    }

    #[tokio::test(start_paused = true)]
    async fn refusals_are_io_errors_with_the_reason() {
        let (mut host, _device) = device(DESCRIPTOR.to_vec(), Sim::default(), 8);
        let mut buf = [0u8; 8];
        let e = host.get_feature_report(5, &mut buf).await.unwrap_err();
        assert!(
            matches!(&e, LinkError::Io(m) if m.contains("no feature report 5")),
            "{e:?}"
        );
        let e = host.send_feature_report(&[2, 1]).await.unwrap_err();
        assert!(matches!(&e, LinkError::Io(m) if m.contains("bad feature report")));
        // A refusal leaves the link usable.
        host.send_feature_report(&[2, 1, 1]).await.unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn default_behaviour_refuses_everything_and_bad_lengths_are_caught() {
        struct Nothing;
        impl HidBehaviour for Nothing {}
        struct Liar;
        impl HidBehaviour for Liar {
            fn get_feature(&mut self, _: u8, _: &mut [u8]) -> Result<usize, HidRefusal> {
                Ok(100)
            }
        }
        let (mut host, _d) = device(vec![], Nothing, 1);
        assert!(host.write_output_report(&[0, 1]).await.is_err());
        assert!(host.send_feature_report(&[0, 1]).await.is_err());
        assert!(host.get_feature_report(0, &mut [0; 4]).await.is_err());
        assert!(host.write_output_report(&[]).await.is_err());

        let (mut host, _d) = device(vec![], Liar, 1);
        let e = host.get_feature_report(1, &mut [0; 4]).await.unwrap_err();
        assert!(
            matches!(&e, LinkError::Io(m) if m.contains("100 bytes")),
            "{e:?}"
        );
        assert!(host.get_feature_report(1, &mut []).await.is_err());
    }

    #[tokio::test(start_paused = true)]
    async fn input_times_out_and_long_reports_are_truncated() {
        let (mut host, device) = device(vec![], Sim::default(), 8);
        let mut small = [0u8; 2];
        assert_eq!(
            host.read_input_report(&mut small, Duration::from_millis(8))
                .await,
            Err(LinkError::Timeout { ms: 8 })
        );
        device.send_input(&[1, 2, 3, 4]).unwrap();
        assert_eq!(host.read_input_report(&mut small, SEC).await, Ok(2));
        assert_eq!(small, [1, 2]);
    }

    #[tokio::test(start_paused = true)]
    async fn a_waiting_reader_gets_a_report_sent_later() {
        let (mut host, device) = device(vec![], Sim::default(), 8);
        let sender = tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(5)).await;
            device.send_input(&[0, 42]).unwrap();
            device
        });
        let mut buf = [0u8; 4];
        assert_eq!(host.read_input_report(&mut buf, SEC).await, Ok(2));
        assert_eq!(&buf[..2], &[0, 42]);
        drop(sender.await.unwrap());
    }

    #[tokio::test(start_paused = true)]
    async fn a_full_queue_drops_and_counts_new_reports() {
        let (mut host, device) = device(vec![], Sim::default(), 2);
        for i in 0..5u8 {
            device.send_input(&[0, i]).unwrap();
        }
        assert_eq!(device.dropped_reports(), 3);
        let mut buf = [0u8; 4];
        host.read_input_report(&mut buf, SEC).await.unwrap();
        assert_eq!(buf[1], 0);
        host.read_input_report(&mut buf, SEC).await.unwrap();
        assert_eq!(buf[1], 1);
    }

    #[tokio::test(start_paused = true)]
    async fn injected_disconnect_fails_every_host_call() {
        let (mut host, device) = device(DESCRIPTOR.to_vec(), Sim::default(), 8);
        device.send_input(&[1, 2]).unwrap();
        let waiter = tokio::spawn(async move {
            let mut buf = [0u8; 4];
            // The queued report is lost with the unplug.
            tokio::time::sleep(Duration::from_millis(1)).await;
            let r = host
                .read_input_report(&mut buf, Duration::from_secs(3600))
                .await;
            (host, r)
        });
        device.disconnect("USB cable pulled");
        let (mut host, r) = waiter.await.unwrap();
        assert!(matches!(&r, Err(LinkError::Disconnected(m)) if m.contains("USB cable pulled")));
        assert!(host
            .report_descriptor()
            .await
            .unwrap_err()
            .needs_reconnect());
        assert!(host.send_feature_report(&[2, 1, 1]).await.is_err());
        assert!(host.get_feature_report(2, &mut [0; 4]).await.is_err());
        assert!(host.write_output_report(&[0, 1]).await.is_err());
        assert!(matches!(
            device.send_input(&[1]),
            Err(LinkError::Disconnected(_))
        ));
    }

    #[tokio::test(start_paused = true)]
    async fn dropping_either_side_is_seen_by_the_other() {
        let (mut host, device) = device(vec![], Sim::default(), 8);
        let second = device.clone();
        drop(device);
        // One handle is still alive: the device is still there.
        second.send_input(&[0, 1]).unwrap();
        drop(second);
        let mut buf = [0u8; 4];
        assert!(matches!(
            host.read_input_report(&mut buf, SEC).await,
            Err(LinkError::Disconnected(_))
        ));

        let (host, device) = super::device(vec![], Sim::default(), 8);
        assert!(device.host_connected());
        drop(host);
        assert!(!device.host_connected());
        assert!(matches!(
            device.send_input(&[0, 1]),
            Err(LinkError::Disconnected(_))
        ));
    }
}
