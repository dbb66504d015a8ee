//! One task per device. Each task connects (retrying with [`Backoff`] while the rest of the
//! rig runs), then serves its device until the link is lost (back to connecting) or the rig
//! stops (the lens is parked first). Every task reports its state to the [`Registry`] the API
//! shows: connecting, ok or lost, with the last error.
//!
//! Whether an error costs the link is decided in one place, [`LinkHealth`]; how long to wait
//! between attempts in another, [`LinkPolicy`]. Devices are opened through the drivers'
//! table ([`open`]): the rig config's driver and port become a link (a simulator's in-memory
//! link for `port = "sim"`, a serial port or HID device otherwise) and a connected driver.

mod about;
mod boxed;
mod forward;
mod lens;
pub mod open;
pub mod simulators;
mod sync;

use std::collections::BTreeMap;
use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dioptra_core::{
    lock, Clock, DeviceError, Diopters, GazeSample, LensState, LightEvent, LinkError,
    SequencerEvent, Timestamp,
};
use serde::Serialize;
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

pub use boxed::{About, BoxGaze, BoxLens, BoxPhotodiode, BoxSequencer, Facts, Resume};
pub use lens::ParkReport;

use crate::config::{Port, RigConfig};
use crate::devices::simulators::{SimDevices, SimSpec};
pub use dioptra_sched::LensId;

/// A device's connection state, as the API shows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum State {
    Connecting,
    Ok,
    Lost,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DeviceStatus {
    pub driver: String,
    pub port: String,
    pub state: State,
    /// The last error, kept after the device comes back.
    pub last_error: Option<String>,
    /// Successful connects so far (more than one: it was lost and came back).
    pub connects: u64,
    /// Failed connects and losses so far.
    pub failures: u64,
}

/// Every device's status, shared between the device tasks and the API.
#[derive(Debug, Default)]
pub struct Registry(Mutex<BTreeMap<String, DeviceStatus>>);

impl Registry {
    pub fn snapshot(&self) -> BTreeMap<String, DeviceStatus> {
        lock(&self.0).clone()
    }
    pub(crate) fn add(self: &Arc<Self>, name: &str, driver: &str, port: &Port) -> DeviceHandle {
        lock(&self.0).insert(
            name.to_string(),
            DeviceStatus {
                driver: driver.to_string(),
                port: port.to_string(),
                state: State::Connecting,
                last_error: None,
                connects: 0,
                failures: 0,
            },
        );
        DeviceHandle {
            registry: self.clone(),
            name: name.to_string(),
        }
    }
}

/// Waits up to `timeout` for every required device of `devices` to connect. The error names
/// each one that did not: its config key, port, and why (a device path that does not exist
/// fails at once).
pub async fn wait_for_required(
    registry: &Registry,
    devices: &[crate::config::ConfiguredDevice],
    timeout: Duration,
) -> Result<(), String> {
    let required: Vec<_> = devices.iter().filter(|d| d.required).collect();
    let why_required = |d: &crate::config::ConfiguredDevice| {
        format!(
            "the rig requires it ({0}.required, true by default for a real port; set it to \
             false to start without it, or port = \"sim\")",
            d.section
        )
    };
    let absent: Vec<String> = required
        .iter()
        .filter_map(|d| match &d.port {
            Port::Path(p) if !p.exists() => Some(format!(
                "{}.port = \"{}\": the {} device is not present (no such file); {}",
                d.section,
                p.display(),
                d.name,
                why_required(d)
            )),
            _ => None,
        })
        .collect();
    if !absent.is_empty() {
        return Err(absent.join("\n"));
    }
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        let snap = registry.snapshot();
        let missing: Vec<_> = required
            .iter()
            .filter(|d| snap.get(&d.name).is_none_or(|s| s.state != State::Ok))
            .collect();
        if missing.is_empty() {
            return Ok(());
        }
        if tokio::time::Instant::now() >= deadline {
            return Err(missing
                .iter()
                .map(|d| {
                    let s = snap.get(&d.name);
                    format!(
                        "{}.port = \"{}\": the {} device ({} driver) did not connect within {} s: \
                         {}; {}",
                        d.section,
                        d.port,
                        d.name,
                        s.map_or("?", |s| s.driver.as_str()),
                        timeout.as_secs_f64(),
                        s.and_then(|s| s.last_error.as_deref())
                            .unwrap_or("no answer"),
                        why_required(d)
                    )
                })
                .collect::<Vec<_>>()
                .join("\n"));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// One device's entry in the [`Registry`].
#[derive(Debug, Clone)]
pub struct DeviceHandle {
    registry: Arc<Registry>,
    name: String,
}

impl DeviceHandle {
    fn update(&self, f: impl FnOnce(&mut DeviceStatus)) {
        if let Some(s) = lock(&self.registry.0).get_mut(&self.name) {
            f(s);
        }
    }
    fn connecting(&self) {
        self.update(|s| s.state = State::Connecting);
    }
    fn ok(&self) {
        self.update(|s| {
            s.state = State::Ok;
            s.connects += 1;
        });
        tracing::info!(device = %self.name, "connected");
    }
    fn lost(&self, e: &DeviceError) {
        self.update(|s| {
            s.state = State::Lost;
            s.failures += 1;
            s.last_error = Some(e.to_string());
        });
        tracing::warn!(device = %self.name, error = %e, "lost; retrying");
    }
    /// An error that did not cost the connection (a refusal, a single timeout).
    fn error(&self, e: &DeviceError) {
        self.update(|s| s.last_error = Some(e.to_string()));
        tracing::warn!(device = %self.name, error = %e, "device error");
    }
}

/// How the device tasks treat their links: retry waits, connect and park timeouts, and when
/// a run of timeouts counts as a lost link. The same for every device kind and for every
/// command that runs a rig (serve, hil, demo, eval, the loop tests).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LinkPolicy {
    /// First wait after a failed connect or a loss; doubles per failure up to `backoff_max`.
    #[serde(rename = "backoff_min_ms", serialize_with = "as_ms")]
    pub backoff_min: Duration,
    #[serde(rename = "backoff_max_ms", serialize_with = "as_ms")]
    pub backoff_max: Duration,
    /// A connect attempt that takes longer is abandoned and retried.
    #[serde(rename = "connect_timeout_ms", serialize_with = "as_ms")]
    pub connect_timeout: Duration,
    /// This many timeouts in a row mean the device stopped answering: the link is lost.
    pub timeouts_lost: u32,
}

impl Default for LinkPolicy {
    fn default() -> Self {
        LinkPolicy {
            backoff_min: Duration::from_millis(100),
            backoff_max: Duration::from_secs(5),
            connect_timeout: Duration::from_secs(5),
            timeouts_lost: 3,
        }
    }
}

impl LinkPolicy {
    /// The times, counted from a loss, at which the first `n` reconnect attempts start when
    /// each fails at once: the first at once, then after each [`Backoff`] wait.
    pub fn attempts_after_loss(&self, n: usize) -> Vec<Duration> {
        let mut b = Backoff::new(self.backoff_min, self.backoff_max);
        let mut t = Duration::ZERO;
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            out.push(t);
            t += b.next_wait();
        }
        out
    }
}

/// A duration in `/status` and recordings: milliseconds, a plain number (the field's name
/// says the unit), not serde's `{"secs", "nanos"}`.
fn as_ms<S: serde::Serializer>(d: &Duration, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_f64(d.as_secs_f64() * 1e3)
}

/// The device tasks' settings, from the rig config.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DeviceSettings {
    pub link: LinkPolicy,
    /// How often the lens task reads the lens back.
    #[serde(rename = "lens_poll_ms", serialize_with = "as_ms")]
    pub lens_poll: Duration,
    /// How long parking may take at shutdown before the rig stops without it.
    #[serde(rename = "park_timeout_ms", serialize_with = "as_ms")]
    pub park_timeout: Duration,
}

impl DeviceSettings {
    pub fn from_config(cfg: &RigConfig) -> DeviceSettings {
        DeviceSettings {
            link: LinkPolicy::default(),
            lens_poll: Duration::from_secs_f64(cfg.devices.lens.first().poll_ms / 1000.0),
            park_timeout: Duration::from_secs(1),
        }
    }
}

/// Exponential backoff between connection attempts.
#[derive(Debug, Clone)]
pub struct Backoff {
    next: Duration,
    min: Duration,
    max: Duration,
}

impl Backoff {
    pub fn new(min: Duration, max: Duration) -> Self {
        Backoff {
            next: min,
            min,
            max,
        }
    }
    /// The wait before the next attempt; doubles each call up to the maximum.
    pub fn next_wait(&mut self) -> Duration {
        let w = self.next;
        self.next = (self.next * 2).min(self.max);
        w
    }
    pub fn reset(&mut self) {
        self.next = self.min;
    }
}

/// What an error means for a link that was up: the one place that decides "lost".
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Reopen the link (back to connecting).
    Lost,
    /// Report it and keep the link.
    Keep,
}

/// Counts the timeouts in a row of one link and judges each error by [`LinkPolicy`].
#[derive(Debug, Clone)]
pub struct LinkHealth {
    timeouts: u32,
    limit: u32,
}

impl LinkHealth {
    pub fn new(policy: &LinkPolicy) -> Self {
        LinkHealth {
            timeouts: 0,
            limit: policy.timeouts_lost.max(1),
        }
    }
    /// An exchange succeeded.
    pub fn ok(&mut self) {
        self.timeouts = 0;
    }
    pub fn judge(&mut self, e: &DeviceError) -> Verdict {
        if e.needs_reconnect() {
            return Verdict::Lost;
        }
        if matches!(e, DeviceError::Link(LinkError::Timeout { .. })) {
            self.timeouts += 1;
            if self.timeouts >= self.limit {
                return Verdict::Lost;
            }
        }
        Verdict::Keep
    }
}

/// Connects, retrying with backoff; `None` when cancelled first.
async fn connect_retrying<D, F, Fut>(
    dev: &DeviceHandle,
    policy: &LinkPolicy,
    cancel: &CancellationToken,
    backoff: &mut Backoff,
    connect: &mut F,
) -> Option<D>
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<D, DeviceError>>,
{
    loop {
        dev.connecting();
        let attempt = tokio::time::timeout(policy.connect_timeout, connect());
        let r = tokio::select! {
            _ = cancel.cancelled() => return None,
            r = attempt => r,
        };
        let r = r.unwrap_or_else(|_| {
            Err(DeviceError::Link(LinkError::Timeout {
                ms: policy.connect_timeout.as_millis() as u64,
            }))
        });
        match r {
            Ok(d) => {
                backoff.reset();
                return Some(d);
            }
            Err(e) => {
                dev.lost(&e);
                let wait = backoff.next_wait();
                tokio::select! {
                    _ = cancel.cancelled() => return None,
                    _ = tokio::time::sleep(wait) => {}
                }
            }
        }
    }
}

/// A lens command for the lens task: the scheduler's command id, the power, and when the gaze
/// sample that caused it was received (wall clock), for the host-path figure.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensOrder {
    pub id: u64,
    pub power: Diopters,
    pub caused_by_gaze: Option<Instant>,
}

/// What a device task tells the loop. A lens's inputs name it ([`LensId`]: the one lens,
/// or the left eye's, is 0).
#[derive(Debug, Clone, PartialEq)]
pub enum DeviceInput {
    /// A gaze sample, and when the gaze task received it from the driver (wall clock).
    Gaze(GazeSample, Instant),
    LensState(LensId, LensState),
    /// Lens command `id` (for `requested`) went on the wire at `wire_time`. `host_path` is
    /// the wall time from the gaze task receiving the sample that caused it to the driver
    /// having written it.
    LensWire {
        lens: LensId,
        id: u64,
        requested: Diopters,
        wire_time: Timestamp,
        host_path: Option<Duration>,
    },
    /// The lens link came up (true: connected, and the last commanded power re-sent) or went
    /// down (false).
    LensLink(LensId, bool),
    Sync(SequencerEvent),
    /// Light on the photodiode over the marker patch (from its own device, or from the sync
    /// board's input).
    Light(LightEvent),
}

/// Channels from the loop to the device tasks.
pub struct DeviceLinks {
    /// Each lens's newest command (by [`LensId`]); a newer one replaces one not yet sent.
    pub lens_commands: Vec<watch::Sender<Option<LensOrder>>>,
    pub multifocal: watch::Sender<bool>,
}

/// Spawned device tasks: each lens task's park report comes back through `lenses`.
pub struct DeviceTasks {
    pub lenses: Vec<tokio::task::JoinHandle<ParkReport>>,
    pub others: Vec<tokio::task::JoinHandle<()>>,
}

/// Starts every device task of `cfg`: each device opened through the drivers' table
/// ([`open`]), simulators made from `spec` for `port = "sim"`. Device tasks stop on `stop`
/// (the lens is parked first). Returns the simulator handles, the channels and the tasks.
pub fn spawn_devices(
    cfg: &Arc<RigConfig>,
    spec: &SimSpec,
    settings: DeviceSettings,
    registry: &Arc<Registry>,
    clock: Arc<dyn Clock>,
    out: mpsc::Sender<DeviceInput>,
    stop: &CancellationToken,
) -> Result<(SimDevices, DeviceLinks, DeviceTasks), DeviceError> {
    let mut sims = SimDevices::default();
    let (mf_tx, mf_rx) = watch::channel(cfg.mode == crate::config::Mode::Multifocal);
    let lens_setup = |i| open::LensSetup::from_rig(cfg, i);

    // A task per lens, each with its own link, backoff and read-backs.
    let mut lens_commands = Vec::new();
    let mut lenses = Vec::new();
    for (i, l) in cfg.devices.lens.each().into_iter().enumerate() {
        let id = LensId(i as u8);
        let (tx, rx) = watch::channel(None);
        let row = open::row(&open::LENS, l.driver)?;
        let dev = registry.add(&cfg.devices.lens.name(i), row.name, &l.port);
        let mut lens_spec = spec.clone();
        lens_spec.lens = spec.lens_of(i);
        let mut slot = None;
        let connect = open::device_connector(
            row,
            &l.port,
            open::Context::new(clock.clone(), lens_setup(i)?),
            &lens_spec,
            &mut slot,
            &mut sims.gaze_truth,
        );
        sims.lenses.push(slot);
        // Each lens is read back at its own interval.
        let lens_settings = DeviceSettings {
            lens_poll: Duration::from_secs_f64(l.poll_ms / 1000.0),
            ..settings
        };
        lenses.push(tokio::spawn(lens::lens_task(
            connect,
            id,
            dev,
            lens_settings,
            rx,
            out.clone(),
            Diopters(l.park_power),
            stop.clone(),
        )));
        lens_commands.push(tx);
    }

    let mut others = Vec::new();
    let g = &cfg.devices.gaze;
    let row = open::row(&open::GAZE, g.driver)?;
    let dev = registry.add("gaze", row.name, &g.port);
    let connect = open::device_connector(
        row,
        &g.port,
        open::Context::new(clock.clone(), open::GazeSetup::from_rig(cfg)),
        spec,
        &mut sims.gaze,
        &mut sims.gaze_truth,
    );
    others.push(tokio::spawn(forward::forward_task(
        connect,
        dev,
        settings,
        out.clone(),
        stop.clone(),
    )));

    if let Some(s) = &cfg.devices.sync {
        let row = open::row(&open::SYNC, s.driver)?;
        let dev = registry.add("sync", row.name, &s.port);
        let schedule = cfg
            .plane_schedule()
            .map_err(|e| DeviceError::Invalid(e.to_string()))?;
        let connect = open::device_connector(
            row,
            &s.port,
            open::Context::new(clock.clone(), open::SyncSetup::from_rig(cfg, out.clone())),
            spec,
            &mut sims.sync,
            &mut sims.gaze_truth,
        );
        // A photodiode on this board: its light is read whatever the mode.
        let light = cfg
            .devices
            .photodiode
            .as_ref()
            .is_some_and(|p| p.on_sync_board());
        others.push(tokio::spawn(sync::sync_task(
            connect,
            dev,
            settings,
            sync::SyncWork {
                schedule,
                multifocal: mf_rx,
                light,
            },
            out.clone(),
            stop.clone(),
        )));
    }
    if let Some(p) = cfg.devices.photodiode.as_ref() {
        if let Some(port) = &p.port {
            let row = open::row(&open::PHOTODIODE, p.driver)?;
            let dev = registry.add("photodiode", row.name, port);
            let connect = open::device_connector(
                row,
                port,
                open::Context::new(clock.clone(), open::PhotodiodeSetup::from_rig(cfg)),
                spec,
                &mut sims.photodiode,
                &mut sims.gaze_truth,
            );
            others.push(tokio::spawn(forward::forward_task(
                connect,
                dev,
                settings,
                out.clone(),
                stop.clone(),
            )));
        }
    }
    sims.panel = spec.panel.clone();
    Ok((
        sims,
        DeviceLinks {
            lens_commands,
            multifocal: mf_tx,
        },
        DeviceTasks { lenses, others },
    ))
}

#[cfg(test)]
mod tests;
