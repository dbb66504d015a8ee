//! One task per device. Each task connects (retrying with exponential backoff while the rest
//! of the daemon runs), then serves its device until it is lost (back to connecting) or the
//! daemon stops (the lens is parked first). Every task reports its state to the
//! [`Registry`] the API shows: connecting, ok or lost, with the last error.
//!
//! With `port = "sim"` the device is a dioptra-sim simulator run in-process and reached
//! through `dioptra_transport::memory` links, so the real driver runs on the real bytes.
//! A [`SimPlug`] can unplug and replug it, as a cable would.

use std::collections::BTreeMap;
use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use dioptra_core::{
    Clock, DeviceError, Diopters, GazeSample, GazeSource, LensState, LinkError, PlaneSchedule,
    PlaneSequencer, PowerRange, SequencerEvent, Timestamp, VarifocalLens,
};
use dioptra_lens::{
    ControllerConfig, LensController, LensLimits, Opener, Optotune, OptotuneConfig,
};
use dioptra_sim::lens_model::{LensModel, LensModelConfig};
use dioptra_sim::serve::ByteDevice;
use dioptra_transport::memory::{self, MemoryLink};
use serde::Serialize;
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

use super::config::{GazeDriver, LensDriver, Port, RigConfig, SyncDriver};

pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Every critical section leaves the data consistent, so a poisoned lock is still usable.
    m.lock().unwrap_or_else(|p| p.into_inner())
}

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
    fn add(self: &Arc<Self>, name: &str, driver: &str, port: &Port) -> DeviceHandle {
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
    /// An error that did not cost the connection (a refusal, a timeout).
    fn error(&self, e: &DeviceError) {
        self.update(|s| s.last_error = Some(e.to_string()));
        tracing::warn!(device = %self.name, error = %e, "device error");
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

pub const BACKOFF_MIN: Duration = Duration::from_millis(100);
pub const BACKOFF_MAX: Duration = Duration::from_secs(5);
/// A connect attempt that takes longer than this is abandoned and retried.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// How often the lens task reads the lens's state.
const LENS_POLL: Duration = Duration::from_millis(10);
/// How long parking may take before shutdown goes on without it.
const PARK_TIMEOUT: Duration = Duration::from_secs(1);

/// Connects, retrying with backoff; `None` when cancelled first.
async fn connect_retrying<D, F, Fut>(
    dev: &DeviceHandle,
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
        let attempt = tokio::time::timeout(CONNECT_TIMEOUT, connect());
        let r = tokio::select! {
            _ = cancel.cancelled() => return None,
            r = attempt => r,
        };
        let r = r.unwrap_or_else(|_| {
            Err(DeviceError::Link(LinkError::Timeout {
                ms: CONNECT_TIMEOUT.as_millis() as u64,
            }))
        });
        match r {
            Ok(d) => {
                dev.ok();
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

/// What a device task tells the loop.
#[derive(Debug, Clone, PartialEq)]
pub enum DeviceInput {
    Gaze(GazeSample),
    LensState(LensState),
    /// Lens command `id` (for `requested`) went on the wire at `wire_time`.
    LensWire {
        id: u64,
        requested: Diopters,
        wire_time: Timestamp,
    },
    /// The lens link came up (true) or went down (false).
    LensLink(bool),
    Sync(SequencerEvent),
}

/// Whether an error means the device must be reconnected.
fn is_lost(e: &DeviceError) -> bool {
    e.needs_reconnect() || matches!(e, DeviceError::Link(LinkError::Unavailable(_)))
}

/// How the lens was left at shutdown.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ParkReport {
    pub park_power: f32,
    /// Power the lens reported after parking, when it answered.
    pub reported_power: Option<f32>,
    pub error: Option<String>,
}

/// The lens task: applies the newest commanded power, reads the state every [`LENS_POLL`],
/// and parks the lens at `park` when cancelled.
///
/// Commands come first: one waiting is sent before a poll starts, and one that arrives while
/// a state read is in flight cancels the read (dropping its future) and goes out at once, so
/// a command never waits behind a read. Drivers tolerate a dropped read: the Optotune driver
/// expects no reply to a set-power command and drains stray input before every exchange, and
/// the lens controller's client matches replies to requests by id.
pub async fn lens_task<D, F, Fut>(
    mut connect: F,
    dev: DeviceHandle,
    mut commands: watch::Receiver<Option<(u64, Diopters)>>,
    out: mpsc::Sender<DeviceInput>,
    park: Diopters,
    cancel: CancellationToken,
) -> ParkReport
where
    D: VarifocalLens,
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<D, DeviceError>>,
{
    let mut backoff = Backoff::new(BACKOFF_MIN, BACKOFF_MAX);
    loop {
        let Some(mut lens) = connect_retrying(&dev, &cancel, &mut backoff, &mut connect).await
        else {
            return ParkReport {
                park_power: park.0,
                reported_power: None,
                error: Some("the lens was not connected at shutdown, so it was not parked".into()),
            };
        };
        // The scheduler sends its current target again when told the link is back.
        let _ = out.send(DeviceInput::LensLink(true)).await;
        let mut poll = tokio::time::interval(LENS_POLL);
        poll.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let lost = loop {
            tokio::select! {
                biased;
                _ = cancel.cancelled() => return park_lens(&mut lens, park).await,
                r = commands.changed() => {
                    if r.is_err() {
                        // The loop is gone: nothing more will be commanded.
                        cancel.cancelled().await;
                        continue;
                    }
                    if let Err(e) = apply_command(&mut lens, &mut commands, &out, &dev).await {
                        break e;
                    }
                }
                _ = poll.tick() => {
                    // A command that arrives during the read preempts it: the read is dropped
                    // and the command goes out at once (see the doc of `lens_task`).
                    let read = tokio::select! {
                        biased;
                        _ = cancel.cancelled() => return park_lens(&mut lens, park).await,
                        r = commands.changed() => {
                            if r.is_ok() {
                                if let Err(e) = apply_command(&mut lens, &mut commands, &out, &dev).await {
                                    break e;
                                }
                            }
                            continue;
                        }
                        r = lens.state() => r,
                    };
                    match read {
                        Ok(s) => {
                            let _ = out.try_send(DeviceInput::LensState(s));
                        }
                        Err(e) if is_lost(&e) => break e,
                        Err(e) => dev.error(&e),
                    }
                }
            }
        };
        dev.lost(&lost);
        let _ = out.send(DeviceInput::LensLink(false)).await;
    }
}

/// Sends the newest commanded power; `Err` when the link is lost.
async fn apply_command<D: VarifocalLens>(
    lens: &mut D,
    commands: &mut watch::Receiver<Option<(u64, Diopters)>>,
    out: &mpsc::Sender<DeviceInput>,
    dev: &DeviceHandle,
) -> Result<(), DeviceError> {
    let Some((id, p)) = *commands.borrow_and_update() else {
        return Ok(());
    };
    match lens.set_power(p).await {
        Ok(t) => {
            let _ = out.try_send(DeviceInput::LensWire {
                id,
                requested: p,
                wire_time: t,
            });
            Ok(())
        }
        Err(e) if is_lost(&e) => Err(e),
        Err(e) => {
            dev.error(&e);
            Ok(())
        }
    }
}

/// Commands `park` and waits (up to [`PARK_TIMEOUT`]) until the lens reports it.
async fn park_lens<D: VarifocalLens>(lens: &mut D, park: Diopters) -> ParkReport {
    let mut report = ParkReport {
        park_power: park.0,
        reported_power: None,
        error: None,
    };
    if let Err(e) = lens.set_power(park).await {
        report.error = Some(format!("parking the lens failed: {e}"));
        return report;
    }
    let wait = async {
        loop {
            match lens.state().await {
                Ok(s) => {
                    report.reported_power = Some(s.power.0);
                    let close = (s.power.0 - park.0).abs() <= 0.02;
                    if close && s.settled != Some(false) {
                        return;
                    }
                }
                Err(e) => {
                    report.error = Some(format!("reading the parked lens failed: {e}"));
                    return;
                }
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    };
    if tokio::time::timeout(PARK_TIMEOUT, wait).await.is_err() {
        report.error = Some(format!(
            "the lens did not report {} D within {PARK_TIMEOUT:?} of the park command",
            park.0
        ));
    }
    report
}

/// The gaze task: forwards every sample to the loop.
pub async fn gaze_task<G, F, Fut>(
    mut connect: F,
    dev: DeviceHandle,
    out: mpsc::Sender<DeviceInput>,
    cancel: CancellationToken,
) where
    G: GazeSource,
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<G, DeviceError>>,
{
    let mut backoff = Backoff::new(BACKOFF_MIN, BACKOFF_MAX);
    loop {
        let Some(mut g) = connect_retrying(&dev, &cancel, &mut backoff, &mut connect).await else {
            return;
        };
        let lost = loop {
            let r = tokio::select! {
                _ = cancel.cancelled() => return,
                r = g.next_sample() => r,
            };
            match r {
                Ok(s) => {
                    if out.send(DeviceInput::Gaze(s)).await.is_err() {
                        return;
                    }
                }
                Err(e) if is_lost(&e) => break e,
                Err(e) => dev.error(&e),
            }
        };
        dev.lost(&lost);
    }
}

/// The sync task: runs `schedule` while the mode is multifocal, forwards its events, and
/// stops the sequence when the mode changes or the daemon stops.
pub async fn sync_task<S, F, Fut>(
    mut connect: F,
    dev: DeviceHandle,
    schedule: PlaneSchedule,
    mut multifocal: watch::Receiver<bool>,
    out: mpsc::Sender<DeviceInput>,
    cancel: CancellationToken,
) where
    S: PlaneSequencer,
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<S, DeviceError>>,
{
    let mut backoff = Backoff::new(BACKOFF_MIN, BACKOFF_MAX);
    loop {
        let Some(mut s) = connect_retrying(&dev, &cancel, &mut backoff, &mut connect).await else {
            return;
        };
        let mut running = false;
        multifocal.mark_changed();
        let lost: DeviceError = loop {
            tokio::select! {
                biased;
                _ = cancel.cancelled() => {
                    if running {
                        if let Err(e) = s.stop().await {
                            dev.error(&e);
                        }
                    }
                    return;
                }
                r = multifocal.changed() => {
                    if r.is_err() {
                        cancel.cancelled().await;
                        continue;
                    }
                    let want = *multifocal.borrow_and_update();
                    let r = if want && !running {
                        match s.program(&schedule).await {
                            Ok(()) => s.start().await,
                            Err(e) => Err(e),
                        }
                    } else if !want && running {
                        s.stop().await
                    } else {
                        Ok(())
                    };
                    match r {
                        Ok(()) => running = want,
                        Err(e) if is_lost(&e) => break e,
                        Err(e) => dev.error(&e),
                    }
                }
                r = s.next_event(), if running => match r {
                    Ok(ev) => {
                        let _ = out.try_send(DeviceInput::Sync(ev));
                    }
                    Err(e) if is_lost(&e) => break e,
                    Err(e) => dev.error(&e),
                },
            }
        };
        dev.lost(&lost);
    }
}

/// Plugs and unplugs a simulated device, as its cable would.
#[derive(Default)]
pub struct SimPlug {
    plugged: AtomicBool,
    /// Cuts the current connection.
    current: Mutex<Option<Box<dyn FnOnce() + Send>>>,
}

impl std::fmt::Debug for SimPlug {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimPlug")
            .field("plugged", &self.is_plugged())
            .finish_non_exhaustive()
    }
}

impl SimPlug {
    fn new() -> Arc<Self> {
        Arc::new(SimPlug {
            plugged: AtomicBool::new(true),
            current: Mutex::new(None),
        })
    }
    pub fn is_plugged(&self) -> bool {
        self.plugged.load(Ordering::Acquire)
    }
    /// Cuts the link and refuses new ones until [`SimPlug::replug`].
    pub fn unplug(&self) {
        self.plugged.store(false, Ordering::Release);
        if let Some(cut) = lock(&self.current).take() {
            cut();
        }
    }
    pub fn replug(&self) {
        self.plugged.store(true, Ordering::Release);
    }
    fn check(&self, what: &str) -> Result<(), LinkError> {
        if self.is_plugged() {
            Ok(())
        } else {
            Err(LinkError::Unavailable(format!(
                "the simulated {what} is unplugged"
            )))
        }
    }
    fn set_current(&self, cut: impl FnOnce() + Send + 'static) {
        if let Some(old) = lock(&self.current).replace(Box::new(cut)) {
            old();
        }
    }
}

/// A byte-speaking simulator shared between its serve tasks (one per connection) and the
/// test or API that inspects it.
struct Shared<D>(Arc<Mutex<D>>);

impl<D: ByteDevice> ByteDevice for Shared<D> {
    fn wait(&self, now: Timestamp) -> Duration {
        lock(&self.0).wait(now)
    }
    fn advance_to(&mut self, now: Timestamp, out: &mut Vec<u8>) {
        lock(&self.0).advance_to(now, out)
    }
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        lock(&self.0).receive(bytes, out)
    }
    fn idle(&mut self, out: &mut Vec<u8>) {
        lock(&self.0).idle(out)
    }
}

/// Opens a new in-memory link to a shared simulator, served on `clock`.
fn sim_opener<D: ByteDevice + Send + 'static>(
    what: &'static str,
    device: Arc<Mutex<D>>,
    plug: Arc<SimPlug>,
    clock: Arc<dyn Clock>,
) -> Opener<MemoryLink> {
    Opener::new(move || {
        let device = device.clone();
        let plug = plug.clone();
        let clock = clock.clone();
        async move {
            plug.check(what)?;
            let (host, mut end) = memory::pair(4096);
            let faults = end.faults();
            plug.set_current(move || faults.disconnect("unplugged"));
            tokio::spawn(async move {
                let mut shared = Shared(device);
                let _ = dioptra_sim::serve::serve(&mut end, &mut shared, clock.as_ref()).await;
            });
            Ok(host.named(format!("simulated {what}")))
        }
    })
}

/// The simulated lens of a `sim` rig, for tests and the API to look at.
#[derive(Clone)]
pub enum SimLens {
    Optotune(Arc<Mutex<dioptra_sim::optotune::OptotuneSim>>),
    Controller(Arc<Mutex<dioptra_sim::lens_controller::LensControllerSim>>),
}

impl SimLens {
    /// The lens model as the simulator last advanced it.
    pub fn model(&self) -> LensModel {
        match self {
            SimLens::Optotune(d) => lock(d).lens().clone(),
            SimLens::Controller(d) => lock(d).lens().clone(),
        }
    }
}

/// Handles on the simulated devices of a rig (empty for hardware).
#[derive(Clone, Default)]
pub struct SimDevices {
    pub lens: Option<(SimLens, Arc<SimPlug>)>,
    pub gaze: Option<Arc<SimPlug>>,
    pub sync: Option<Arc<SimPlug>>,
}

/// Channels between the device tasks and the loop.
pub struct DeviceLinks {
    /// The newest lens command: (scheduler's command id, power).
    pub lens_commands: watch::Sender<Option<(u64, Diopters)>>,
    pub multifocal: watch::Sender<bool>,
}

/// Spawned device tasks: the lens task's park report comes back through `lens`.
pub struct DeviceTasks {
    pub lens: tokio::task::JoinHandle<ParkReport>,
    pub others: Vec<tokio::task::JoinHandle<()>>,
}

fn lens_limits(cfg: &RigConfig) -> Result<LensLimits, DeviceError> {
    let r = cfg.optics.lens_range;
    PowerRange::new(Diopters(r.min), Diopters(r.max))
        .map(LensLimits::new)
        .ok_or_else(|| DeviceError::Invalid("optics.lens_range is empty".into()))
}

fn lens_model_cfg(cfg: &RigConfig) -> LensModelConfig {
    LensModelConfig {
        settle_time: Duration::from_secs_f64(cfg.devices.lens.sim_settle_ms / 1000.0),
        ..Default::default()
    }
}

fn serial(path: &std::path::Path) -> Result<dioptra_transport::serial::SerialLink, LinkError> {
    dioptra_transport::serial::SerialLink::open(
        path,
        dioptra_transport::serial::SerialSettings::baud(115_200),
    )
}

fn unsupported_port(what: &str, port: &Port) -> DeviceError {
    DeviceError::Link(LinkError::Unavailable(format!(
        "the {what} cannot be reached at {port}: give its device path (e.g. /dev/ttyACM0), its USB VID:PID or \"sim\""
    )))
}

/// The HID link at a device's port: a hidraw path, or the first HID interface with that VID:PID.
fn hid_at(what: &str, port: &Port) -> Result<dioptra_transport::hid::HidapiLink, DeviceError> {
    Ok(match port {
        Port::VidPid(v, p) => dioptra_transport::hid::HidapiLink::open(*v, *p, None)?,
        Port::Path(p) => dioptra_transport::hid::HidapiLink::open_path(&p.display().to_string())?,
        Port::Sim => return Err(unsupported_port(what, port)),
    })
}

/// The serial link at a device's port: a path, or the one USB serial port with that VID:PID
/// (looked up in sysfs at every attempt, so a replugged device that moved is found again).
fn serial_at(
    what: &str,
    port: &Port,
) -> Result<dioptra_transport::serial::SerialLink, DeviceError> {
    let path = match port {
        Port::Path(p) => p.clone(),
        Port::VidPid(v, p) => {
            dioptra_transport::discovery::serial_port_by_id(std::path::Path::new("/sys"), *v, *p)
                .map_err(|e| {
                    DeviceError::Link(LinkError::Unavailable(format!("the {what} at {port}: {e}")))
                })?
        }
        Port::Sim => return Err(unsupported_port(what, port)),
    };
    Ok(serial(&path)?)
}

/// Starts every device task of `cfg`. Returns the sim handles, the channels and the tasks.
pub fn spawn_devices(
    cfg: &RigConfig,
    registry: &Arc<Registry>,
    clock: Arc<dyn Clock>,
    out: mpsc::Sender<DeviceInput>,
    cancel: &CancellationToken,
) -> Result<(SimDevices, DeviceLinks, DeviceTasks), DeviceError> {
    let mut sims = SimDevices::default();
    let (lens_tx, lens_rx) = watch::channel(None);
    let (mf_tx, mf_rx) = watch::channel(cfg.mode == super::config::Mode::Multifocal);
    let limits = lens_limits(cfg)?;
    let park = Diopters(cfg.devices.lens.park_power);
    let l = &cfg.devices.lens;
    let lens_dev = registry.add(
        "lens",
        match l.driver {
            LensDriver::Optotune => "optotune",
            LensDriver::Lens => "lens",
        },
        &l.port,
    );
    let c = cancel.clone();
    let out_l = out.clone();
    let lens = match (&l.driver, &l.port) {
        (LensDriver::Optotune, Port::Sim) => {
            let dev = Arc::new(Mutex::new(dioptra_sim::optotune::OptotuneSim::new(
                dioptra_sim::optotune::OptotuneSimConfig {
                    lens: lens_model_cfg(cfg),
                    ..Default::default()
                },
            )));
            let plug = SimPlug::new();
            sims.lens = Some((SimLens::Optotune(dev.clone()), plug.clone()));
            let opener = Arc::new(tokio::sync::Mutex::new(sim_opener(
                "Lens Driver 4",
                dev,
                plug,
                clock.clone(),
            )));
            let clock = clock.clone();
            tokio::spawn(lens_task(
                move || {
                    let (opener, clock) = (opener.clone(), clock.clone());
                    async move {
                        let link = opener.lock().await.open().await?;
                        Optotune::connect(link, OptotuneConfig::new(limits), clock).await
                    }
                },
                lens_dev,
                lens_rx,
                out_l,
                park,
                c,
            ))
        }
        (LensDriver::Lens, Port::Sim) => {
            let dev = Arc::new(Mutex::new(
                dioptra_sim::lens_controller::LensControllerSim::new(
                    dioptra_sim::lens_controller::LensControllerSimConfig {
                        lens: lens_model_cfg(cfg),
                        ..Default::default()
                    },
                ),
            ));
            let plug = SimPlug::new();
            sims.lens = Some((SimLens::Controller(dev.clone()), plug.clone()));
            let opener = Arc::new(tokio::sync::Mutex::new(sim_opener(
                "lens controller",
                dev,
                plug,
                clock.clone(),
            )));
            let clock = clock.clone();
            tokio::spawn(lens_task(
                move || {
                    let (opener, clock) = (opener.clone(), clock.clone());
                    async move {
                        let link = opener.lock().await.open().await?;
                        LensController::connect(link, ControllerConfig::new(limits), clock).await
                    }
                },
                lens_dev,
                lens_rx,
                out_l,
                park,
                c,
            ))
        }
        (LensDriver::Optotune, port) => {
            let port = port.clone();
            let clock = clock.clone();
            tokio::spawn(lens_task(
                move || {
                    let (port, clock) = (port.clone(), clock.clone());
                    async move {
                        let link = serial_at("Lens Driver 4", &port)?;
                        Optotune::connect(link, OptotuneConfig::new(limits), clock).await
                    }
                },
                lens_dev,
                lens_rx,
                out_l,
                park,
                c,
            ))
        }
        (LensDriver::Lens, port) => {
            let port = port.clone();
            let clock = clock.clone();
            tokio::spawn(lens_task(
                move || {
                    let (port, clock) = (port.clone(), clock.clone());
                    async move {
                        let link = serial_at("lens controller", &port)?;
                        LensController::connect(link, ControllerConfig::new(limits), clock).await
                    }
                },
                lens_dev,
                lens_rx,
                out_l,
                park,
                c,
            ))
        }
    };

    let mut others = Vec::new();
    let g = &cfg.devices.gaze;
    let gaze_dev = registry.add(
        "gaze",
        match g.driver {
            GazeDriver::DioptraTracker => "dioptra-tracker",
            GazeDriver::Hid => "hid",
        },
        &g.port,
    );
    let tracker_cfg = dioptra_gaze::dioptra_tracker::DioptraTrackerConfig::default;
    match (&g.driver, &g.port) {
        (_, Port::Sim) => {
            let plug = SimPlug::new();
            sims.gaze = Some(plug.clone());
            let gen_cfg = dioptra_sim::gaze::GeneratorConfig {
                rate_hz: g.sim_rate_hz,
                seed: g.sim_seed,
                ipd_mm: f64::from(cfg.eye.ipd_mm),
                ..Default::default()
            };
            let scenario = g.sim_scenario.clone();
            let clock = clock.clone();
            others.push(tokio::spawn(gaze_task(
                move || {
                    let (plug, clock, scenario) = (plug.clone(), clock.clone(), scenario.clone());
                    async move {
                        plug.check("eye tracker")?;
                        let scene =
                            dioptra_sim::gaze::Scene::named(&scenario).ok_or_else(|| {
                                DeviceError::Invalid(format!("unknown gaze scenario {scenario:?}"))
                            })?;
                        let generator = dioptra_sim::gaze::GazeGenerator::new(scene, gen_cfg)
                            .map_err(DeviceError::Invalid)?;
                        let (link, tracker) =
                            dioptra_sim::gaze::dioptra_tracker::spawn(Box::new(generator));
                        plug.set_current(move || {
                            tracker.disconnect("unplugged");
                            drop(tracker);
                        });
                        dioptra_gaze::dioptra_tracker::DioptraTracker::connect(
                            link,
                            tracker_cfg(),
                            clock,
                        )
                        .await
                    }
                },
                gaze_dev,
                out.clone(),
                cancel.clone(),
            )));
        }
        (driver, port) => {
            let (driver, port) = (*driver, port.clone());
            let clock = clock.clone();
            let open = |port: &Port| hid_at("eye tracker", port);
            match driver {
                GazeDriver::DioptraTracker => others.push(tokio::spawn(gaze_task(
                    move || {
                        let (link, clock) = (open(&port), clock.clone());
                        async move {
                            dioptra_gaze::dioptra_tracker::DioptraTracker::connect(
                                link?,
                                tracker_cfg(),
                                clock,
                            )
                            .await
                        }
                    },
                    gaze_dev,
                    out.clone(),
                    cancel.clone(),
                ))),
                GazeDriver::Hid => others.push(tokio::spawn(gaze_task(
                    move || {
                        let (link, clock) = (open(&port), clock.clone());
                        async move {
                            dioptra_gaze::eye_hid::HidEyeTracker::connect(
                                link?,
                                dioptra_gaze::eye_hid::HidTrackerConfig::default(),
                                clock,
                            )
                            .await
                        }
                    },
                    gaze_dev,
                    out.clone(),
                    cancel.clone(),
                ))),
            }
        }
    }

    if let Some(s) = &cfg.devices.sync {
        let driver_name = match s.driver {
            SyncDriver::Sync => "sync",
            SyncDriver::Dlpc350 => "dlpc350",
        };
        let sync_dev = registry.add("sync", driver_name, &s.port);
        let schedule = cfg
            .plane_schedule()
            .map_err(|e| DeviceError::Invalid(e.to_string()))?;
        let clock = clock.clone();
        let task = match (s.driver, &s.port) {
            (SyncDriver::Sync, Port::Sim) => {
                let dev = Arc::new(Mutex::new(dioptra_sim::sync_board::SyncBoardSim::new(
                    dioptra_sim::sync_board::SyncBoardSimConfig {
                        lens: lens_model_cfg(cfg),
                        ..Default::default()
                    },
                )));
                let plug = SimPlug::new();
                sims.sync = Some(plug.clone());
                let opener = Arc::new(tokio::sync::Mutex::new(sim_opener(
                    "sync board",
                    dev,
                    plug,
                    clock.clone(),
                )));
                tokio::spawn(sync_task(
                    move || {
                        let (opener, clock) = (opener.clone(), clock.clone());
                        async move {
                            let link = opener.lock().await.open().await?;
                            dioptra_sync::board::SyncBoard::connect(link, clock).await
                        }
                    },
                    sync_dev,
                    schedule,
                    mf_rx,
                    out.clone(),
                    cancel.clone(),
                ))
            }
            (SyncDriver::Sync, port) => {
                let port = port.clone();
                tokio::spawn(sync_task(
                    move || {
                        let (port, clock) = (port.clone(), clock.clone());
                        async move {
                            let link = serial_at("sync board", &port)?;
                            dioptra_sync::board::SyncBoard::connect(link, clock).await
                        }
                    },
                    sync_dev,
                    schedule,
                    mf_rx,
                    out.clone(),
                    cancel.clone(),
                ))
            }
            (SyncDriver::Dlpc350, Port::Sim) => {
                let driver_cfg = s.dlpc350_config();
                let plug = SimPlug::new();
                sims.sync = Some(plug.clone());
                tokio::spawn(sync_task(
                    move || {
                        let (plug, clock) = (plug.clone(), clock.clone());
                        async move {
                            plug.check("DLPC350")?;
                            let (link, projector) =
                                dioptra_sim::dlpc350::new(dioptra_sim::dlpc350::Dlpc350SimConfig {
                                    vsync_hz: driver_cfg.vsync_hz,
                                    ..Default::default()
                                });
                            plug.set_current(move || projector.unplug("unplugged"));
                            Ok(dioptra_sync::dlpc350::Dlpc350::new(link, clock, driver_cfg))
                        }
                    },
                    sync_dev,
                    schedule,
                    mf_rx,
                    out.clone(),
                    cancel.clone(),
                ))
            }
            (SyncDriver::Dlpc350, port) => {
                let driver_cfg = s.dlpc350_config();
                let port = port.clone();
                tokio::spawn(sync_task(
                    move || {
                        let link = hid_at("DLPC350", &port);
                        let clock = clock.clone();
                        async move {
                            Ok(dioptra_sync::dlpc350::Dlpc350::new(
                                link?, clock, driver_cfg,
                            ))
                        }
                    },
                    sync_dev,
                    schedule,
                    mf_rx,
                    out.clone(),
                    cancel.clone(),
                ))
            }
        };
        others.push(task);
    }
    Ok((
        sims,
        DeviceLinks {
            lens_commands: lens_tx,
            multifocal: mf_tx,
        },
        DeviceTasks { lens, others },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_serial_device_by_vid_pid_that_is_absent_is_a_link_error_naming_it() {
        // No machine has feed:beef; without sysfs the error still names the port.
        let e = serial_at("lens controller", &Port::VidPid(0xfeed, 0xbeef)).unwrap_err();
        assert!(matches!(e, DeviceError::Link(_)), "{e:?}");
        let text = e.to_string();
        assert!(text.contains("lens controller at feed:beef"), "{text}");
    }

    #[test]
    fn backoff_doubles_to_its_cap_and_resets() {
        let mut b = Backoff::new(Duration::from_millis(100), Duration::from_millis(500));
        let waits: Vec<_> = (0..5).map(|_| b.next_wait().as_millis()).collect();
        assert_eq!(waits, [100, 200, 400, 500, 500]);
        b.reset();
        assert_eq!(b.next_wait().as_millis(), 100);
    }

    #[test]
    fn a_link_that_is_gone_needs_a_reconnect_and_a_refusal_does_not() {
        assert!(is_lost(&DeviceError::Link(LinkError::Disconnected(
            "x".into()
        ))));
        assert!(is_lost(&DeviceError::Link(LinkError::Unavailable(
            "x".into()
        ))));
        assert!(!is_lost(&DeviceError::Refused {
            code: 2,
            detail: "no".into()
        }));
    }

    /// `driver = "dlpc350"` on the simulator: multifocal mode programs and starts the
    /// projector's pattern sequence, its sub-frames arrive in plane order, and after its cable
    /// is pulled and plugged back the sequence is reprogrammed and runs again.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_dlpc350_runs_the_plane_schedule_and_comes_back_after_an_unplug() {
        let text = super::super::config::tests::SIM_RIG
            .replace("driver = \"sync\"", "driver = \"dlpc350\"");
        let cfg = RigConfig::parse(&text).unwrap();
        let clock: Arc<dyn Clock> = Arc::new(dioptra_sim::tokio_clock::TokioClock::new());
        let registry = Arc::new(Registry::default());
        let (out, mut inputs) = mpsc::channel(4096);
        let cancel = CancellationToken::new();
        let (sims, links, tasks) = spawn_devices(&cfg, &registry, clock, out, &cancel).unwrap();
        let planes = cfg.optics.planes.len() as u8;
        // The next `n` sub-frame starts (other devices' inputs skipped), within 5 s.
        async fn subframes(inputs: &mut mpsc::Receiver<DeviceInput>, n: usize) -> Vec<u8> {
            let mut got = Vec::new();
            let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
            while got.len() < n {
                match tokio::time::timeout_at(deadline, inputs.recv()).await {
                    Ok(Some(DeviceInput::Sync(SequencerEvent::SubframeStart {
                        plane_index,
                        ..
                    }))) => got.push(plane_index),
                    Ok(Some(_)) => {}
                    Ok(None) | Err(_) => break,
                }
            }
            got
        }
        links.multifocal.send_replace(true);
        let first = subframes(&mut inputs, 8).await;
        assert_eq!(first.len(), 8, "sub-frames before the unplug: {first:?}");
        for w in first.windows(2) {
            assert_eq!(w[1], (w[0] + 1) % planes, "out of plane order: {first:?}");
        }
        let plug = sims.sync.clone().expect("the simulated DLPC350's plug");
        plug.unplug();
        // Lost is brief between retries; the failure count stays.
        tokio::time::timeout(Duration::from_secs(5), async {
            while registry.snapshot()["sync"].failures == 0 {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
        .await
        .expect("the unplugged DLPC350 was never reported lost");
        plug.replug();
        // Drop what came before the loss, then the sequence must run again.
        while inputs.try_recv().is_ok() {}
        let after = subframes(&mut inputs, 8).await;
        assert_eq!(after.len(), 8, "sub-frames after the replug: {after:?}");
        let sync = registry.snapshot()["sync"].clone();
        assert_eq!(
            (sync.driver.as_str(), sync.state),
            ("dlpc350", State::Ok),
            "{sync:?}"
        );
        assert!(sync.connects >= 2, "{sync:?}");
        cancel.cancel();
        for t in tasks.others {
            t.await.unwrap();
        }
        tasks.lens.await.unwrap();
    }

    /// Commands sent at every phase of the state poll, to the simulated Lens Driver 4 with 1 ms
    /// replies: each one
    /// reaches the wire in order, and the driver keeps working after the reads a command cut
    /// short (no error, no reconnect, state reports keep coming and end at the last command,
    /// parking works). Prints the
    /// command -> wire delay (a figure, not a check: timing is the machine's).
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn commands_during_state_reads_all_reach_the_lens() {
        let clock: Arc<dyn Clock> = Arc::new(dioptra_sim::tokio_clock::TokioClock::new());
        let sim = Arc::new(Mutex::new(dioptra_sim::optotune::OptotuneSim::new(
            Default::default(),
        )));
        // Replies take 1 ms, as over a USB serial adapter: a state read (three exchanges)
        // takes about 3 ms, long enough for commands to arrive during it.
        let (sim2, c1) = (sim.clone(), clock.clone());
        let opener = Arc::new(tokio::sync::Mutex::new(Opener::new(move || {
            let (sim, clock) = (sim2.clone(), c1.clone());
            async move {
                let (host, mut end) = memory::pair(4096);
                host.faults().set_latency(Duration::from_millis(1));
                tokio::spawn(async move {
                    let _ =
                        dioptra_sim::serve::serve(&mut end, &mut Shared(sim), clock.as_ref()).await;
                });
                Ok::<_, LinkError>(host)
            }
        })));
        let registry = Arc::new(Registry::default());
        let dev = registry.add("lens", "optotune", &Port::Sim);
        let range = PowerRange::new(Diopters(-1.0), Diopters(4.0)).unwrap();
        let (tx, rx) = watch::channel(None);
        let (out, mut inputs) = mpsc::channel(4096);
        let cancel = CancellationToken::new();
        let c2 = clock.clone();
        let task = tokio::spawn(lens_task(
            move || {
                let (opener, clock) = (opener.clone(), c2.clone());
                async move {
                    let link = opener.lock().await.open().await?;
                    Optotune::connect(link, OptotuneConfig::new(LensLimits::new(range)), clock)
                        .await
                }
            },
            dev,
            rx,
            out,
            Diopters(0.5),
            cancel.clone(),
        ));
        loop {
            if let Some(DeviceInput::LensLink(true)) = inputs.recv().await {
                break;
            }
        }
        const N: u64 = 200;
        let mut sent = Vec::new();
        let power = |i: u64| Diopters(-0.5 + (i % 9) as f32 * 0.5);
        for i in 1..=N {
            // 3.0 to 8.9 ms apart: every phase of the 10 ms poll and of a read.
            tokio::time::sleep(Duration::from_micros(3_000 + (i * 2_971) % 5_900)).await;
            sent.push(clock.now());
            tx.send_replace(Some((i, power(i))));
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
        cancel.cancel();
        let park = task.await.unwrap();
        assert_eq!(park.error, None, "{park:?}");
        let (mut wired, mut states, mut delays) = (Vec::new(), 0, Vec::new());
        let mut last_state = None;
        while let Ok(i) = inputs.try_recv() {
            match i {
                DeviceInput::LensWire {
                    id,
                    requested,
                    wire_time,
                } => {
                    assert_eq!(requested, power(id));
                    delays.push(wire_time.saturating_since(sent[id as usize - 1]));
                    wired.push(id);
                }
                DeviceInput::LensState(s) => {
                    states += 1;
                    last_state = Some(s);
                }
                _ => {}
            }
        }
        assert_eq!(wired, (1..=N).collect::<Vec<_>>(), "a command was lost");
        // Commands every 6 ms on average cut most 3 ms reads short (a real scheduler commands a
        // few times a second); some still complete.
        assert!(states > 10, "state reads stopped: {states}");
        // Read 100 ms after the last command: the lens is there, and the reads say so.
        let last = last_state.unwrap();
        assert!((last.power.0 - power(N).0).abs() < 0.05, "{last:?}");
        let lens = registry.snapshot()["lens"].clone();
        assert_eq!(lens.last_error, None, "{lens:?}");
        assert_eq!(lens.failures, 0, "{lens:?}");
        delays.sort();
        let q = |p: f64| delays[((delays.len() - 1) as f64 * p) as usize];
        eprintln!(
            "command -> wire: p50 {:?}, p99 {:?}, max {:?} (n = {}, {states} state reads)",
            q(0.5),
            q(0.99),
            delays[delays.len() - 1],
            delays.len()
        );
    }
}
