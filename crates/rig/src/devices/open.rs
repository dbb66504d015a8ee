//! The drivers' table: for each device kind, one row per driver the rig config can name,
//! saying how its device is reached (serial, HID, the network; USB bulk endpoints for a driver
//! that has them), how its simulator is made for `port = "sim"`, and how the driver connects
//! over a link. A device is opened by looking up its row; the port then decides only where the
//! link comes from. The device commands (`dioptra lens|gaze|sync --device DRIVER:PORT`) open
//! their links through the same rows and ports ([`row_named`], [`device_link`]), so whatever
//! the command line reaches a rig config can name.

use std::sync::{Arc, Mutex};

use dioptra_core::{
    Clock, DeviceError, Diopters, LinkError, PlaneSchedule, PlaneSequencer, PowerRange,
    SequencerEvent,
};
use dioptra_gaze::dioptra_tracker::{DioptraTracker, DioptraTrackerConfig};
use dioptra_gaze::eye_hid::{HidEyeTracker, HidTrackerConfig};
use dioptra_gaze::pupil::{PupilCapture, PupilConfig};
use dioptra_lens::{ControllerConfig, LensController, LensLimits, Optotune, OptotuneConfig};
use dioptra_photodiode::SerialPhotodiode;
use dioptra_sim::serve::ByteDevice;
use dioptra_sync::board::{BoardEvent, SyncBoard};
use dioptra_sync::dlpc350::Dlpc350;
use dioptra_transport::{AnyByteLink, AnyHidLink};

use super::boxed::{BoxFuture, BoxGaze, BoxLens, BoxPhotodiode, BoxSequencer};
use super::input::DeviceInput;
use crate::config::{GazeDriver, LensDriver, PhotodiodeDriver, Port, RigConfig, SyncDriver};
use crate::devices::simulators::{
    byte_endpoint, Cut, GazeTruth, RecordedGaze, SimEndpoint, SimLens, SimLink, SimPlug,
    SimPupilCapture, SimSlot, SimSpec,
};

/// How a driver's real device is reached from its port.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transport {
    /// A serial port (a tty path, or the one USB serial port with a VID:PID).
    Serial,
    /// A HID device (a hidraw path, or the first HID interface with a VID:PID).
    Hid,
    /// A network service at "host:port" (the driver opens its own sockets).
    Net,
}

/// What a driver connects over: a real device's link or a simulator's.
pub enum Link {
    Byte(AnyByteLink),
    Hid(AnyHidLink),
    /// The address of a network service.
    Net(String),
}

impl Link {
    fn kind(&self) -> &'static str {
        match self {
            Link::Byte(_) => "a byte link",
            Link::Hid(_) => "a HID link",
            Link::Net(_) => "a network address",
        }
    }
    /// The byte link, or an error naming `what` (the driver) and the link it was given.
    pub fn byte(self, what: &str) -> Result<AnyByteLink, DeviceError> {
        match self {
            Link::Byte(l) => Ok(l),
            other => Err(DeviceError::Invalid(format!(
                "the {what} driver talks over a byte link, and was given {}",
                other.kind()
            ))),
        }
    }
    /// The HID link, or an error naming `what` and the link it was given.
    pub fn hid(self, what: &str) -> Result<AnyHidLink, DeviceError> {
        match self {
            Link::Hid(l) => Ok(l),
            other => Err(DeviceError::Invalid(format!(
                "the {what} driver talks over HID, and was given {}",
                other.kind()
            ))),
        }
    }
    /// The network address, or an error naming `what` and the link it was given.
    pub fn net(self, what: &str) -> Result<String, DeviceError> {
        match self {
            Link::Net(a) => Ok(a),
            other => Err(DeviceError::Invalid(format!(
                "the {what} driver talks over the network, and was given {}",
                other.kind()
            ))),
        }
    }
}

/// What a driver's connect gets.
#[derive(Clone)]
pub struct Context {
    pub cfg: Arc<RigConfig>,
    pub clock: Arc<dyn Clock>,
    /// The loop's device inputs, for a driver that reports for another device too (the sync
    /// board's photodiode input); `None` outside a rig.
    pub inputs: Option<tokio::sync::mpsc::Sender<DeviceInput>>,
    /// Which of the rig's lenses a lens driver connects to (its index in
    /// `devices.lens.each()`).
    pub lens: usize,
}

type Connect<D> = fn(Link, Context) -> BoxFuture<'static, Result<D, DeviceError>>;
type MakeSim = fn(&SimSpec, &Context) -> SimEndpoint;

/// One driver of a device kind.
pub struct Row<K: 'static, D: 'static> {
    pub driver: K,
    /// The driver's name in the rig config and the API.
    pub name: &'static str,
    /// The device, for messages ("Lens Driver 4").
    pub what: &'static str,
    pub transport: Transport,
    /// The VID and PID of the device's USB bulk interface, for a driver that also talks over
    /// one (`port = "usb"` or `"usb:SERIAL"`).
    pub usb: Option<(u16, u16)>,
    pub(crate) sim: MakeSim,
    pub(crate) connect: Connect<D>,
}

pub static LENS: [Row<LensDriver, BoxLens>; 2] = [
    Row {
        driver: LensDriver::Optotune,
        name: "optotune",
        what: "Lens Driver 4",
        transport: Transport::Serial,
        usb: None,
        sim: sim_optotune,
        connect: connect_optotune,
    },
    Row {
        driver: LensDriver::Lens,
        name: "lens",
        what: "lens controller",
        transport: Transport::Serial,
        usb: Some((
            dioptra_lens::ids::DIOPTRA_VID,
            dioptra_lens::ids::DIOPTRA_LENS_PID,
        )),
        sim: sim_lens_controller,
        connect: connect_lens_controller,
    },
];

pub static GAZE: [Row<GazeDriver, BoxGaze>; 3] = [
    Row {
        driver: GazeDriver::DioptraTracker,
        name: "dioptra-tracker",
        what: "dioptra eye tracker",
        transport: Transport::Hid,
        usb: None,
        sim: sim_dioptra_tracker,
        connect: connect_dioptra_tracker,
    },
    Row {
        driver: GazeDriver::Hid,
        name: "hid",
        what: "HID eye tracker",
        transport: Transport::Hid,
        usb: None,
        sim: sim_hid_tracker,
        connect: connect_hid_tracker,
    },
    Row {
        driver: GazeDriver::Pupil,
        name: "pupil",
        what: "Pupil Capture",
        transport: Transport::Net,
        usb: None,
        sim: sim_pupil_capture,
        connect: connect_pupil,
    },
];

pub static SYNC: [Row<SyncDriver, BoxSequencer>; 2] = [
    Row {
        driver: SyncDriver::Sync,
        name: "sync",
        what: "sync board",
        transport: Transport::Serial,
        usb: None,
        sim: sim_sync_board,
        connect: connect_sync_board,
    },
    Row {
        driver: SyncDriver::Dlpc350,
        name: "dlpc350",
        what: "DLPC350",
        transport: Transport::Hid,
        usb: None,
        sim: sim_dlpc350,
        connect: connect_dlpc350,
    },
];

pub static PHOTODIODE: [Row<PhotodiodeDriver, BoxPhotodiode>; 2] = [
    Row {
        driver: PhotodiodeDriver::SerialLine,
        name: "serial-line",
        what: "serial-line photodiode",
        transport: Transport::Serial,
        usb: None,
        sim: sim_serial_photodiode,
        connect: connect_serial_photodiode,
    },
    Row {
        driver: PhotodiodeDriver::Sync,
        name: "sync",
        what: "sync board (its photodiode input)",
        transport: Transport::Serial,
        usb: None,
        sim: sim_photodiode_board,
        connect: connect_photodiode_board,
    },
];

/// The row of `driver` in `rows`.
pub fn row<K: PartialEq + std::fmt::Debug, D>(
    rows: &'static [Row<K, D>],
    driver: K,
) -> Result<&'static Row<K, D>, DeviceError> {
    rows.iter()
        .find(|r| r.driver == driver)
        .ok_or_else(|| DeviceError::Invalid(format!("no driver is registered for {driver:?}")))
}

/// The row of the driver named `name` (its name in the rig config and in `--device
/// DRIVER:PORT`).
pub fn row_named<K, D>(rows: &'static [Row<K, D>], name: &str) -> Option<&'static Row<K, D>> {
    rows.iter().find(|r| r.name == name)
}

/// The names of `rows`' drivers, for messages ("optotune, lens").
pub fn names<K, D>(rows: &'static [Row<K, D>]) -> String {
    rows.iter().map(|r| r.name).collect::<Vec<_>>().join(", ")
}

/// The link to `row`'s real device at `port`: a serial port (by path, or the one USB serial
/// port with a VID:PID), a HID device (by hidraw path or VID:PID), the device's USB bulk
/// endpoints (`usb`, `usb:SERIAL`) or a network address. Blocking (a USB or serial open).
/// Not for `port = "sim"`, whose link the device task makes from the simulator.
pub fn device_link<K, D>(row: &Row<K, D>, port: &Port) -> Result<Link, DeviceError> {
    let what = row.what;
    match (port, row.transport) {
        (Port::Usb(serial), _) => {
            let Some((vid, pid)) = row.usb else {
                return Err(unsupported_port(what, port));
            };
            let mut sel = dioptra_transport::usb::UsbSelector::new(vid, pid);
            if let Some(s) = serial {
                sel = sel.serial(s.clone());
            }
            let link = dioptra_transport::usb::UsbBulkLink::open(&sel).map_err(|e| {
                DeviceError::Link(LinkError::Unavailable(format!("the {what} at {port}: {e}")))
            })?;
            Ok(Link::Byte(link.into()))
        }
        (_, Transport::Serial) => Ok(Link::Byte(serial_at(what, port)?.into())),
        (_, Transport::Hid) => Ok(Link::Hid(hid_at(what, port)?.into())),
        (_, Transport::Net) => net_at(what, port).map(Link::Net),
    }
}

/// The connect function a device task retries: opens the link `port` names (a new link to the
/// simulator for `port = "sim"`, whose handles go into `slot`) and connects `row`'s driver.
pub(crate) fn device_connector<K: Sync, D: Send + 'static>(
    row: &'static Row<K, D>,
    port: &Port,
    ctx: Context,
    spec: &SimSpec,
    slot: &mut Option<SimSlot>,
    gaze_truth: &mut Option<GazeTruth>,
) -> impl FnMut() -> BoxFuture<'static, Result<D, DeviceError>> + Send + 'static {
    let mut open: Box<dyn FnMut() -> Result<Link, DeviceError> + Send> = match port {
        Port::Sim => {
            let mut sim = (row.sim)(spec, &ctx);
            let plug = SimPlug::new();
            *slot = Some(SimSlot {
                plug: plug.clone(),
                lens: sim.lens.take(),
                pupil: sim.pupil.take(),
            });
            if sim.gaze_truth.is_some() {
                *gaze_truth = sim.gaze_truth.take();
            }
            let what = row.what;
            Box::new(move || {
                let link = plug.open(what, &mut sim.open)?;
                Ok(match link {
                    SimLink::Byte(l) => Link::Byte(l),
                    SimLink::Hid(l) => Link::Hid(l),
                    SimLink::Net(a) => Link::Net(a),
                })
            })
        }
        port => {
            let port = port.clone();
            Box::new(move || device_link(row, &port))
        }
    };
    let connect = row.connect;
    move || {
        let link = open();
        let ctx = ctx.clone();
        Box::pin(async move { connect(link?, ctx).await })
    }
}

fn unsupported_port(what: &str, port: &Port) -> DeviceError {
    DeviceError::Link(LinkError::Unavailable(format!(
        "the {what} cannot be reached at {port}: give its device path (e.g. /dev/ttyACM0), its USB VID:PID or \"sim\""
    )))
}

/// The address at a network device's port.
fn net_at(what: &str, port: &Port) -> Result<String, DeviceError> {
    match port {
        Port::Net(a) => Ok(a.clone()),
        _ => Err(DeviceError::Link(LinkError::Unavailable(format!(
            "the {what} is reached over the network: give its address host:port (e.g. 127.0.0.1:50020) or \"sim\", not {port}"
        )))),
    }
}

/// The HID link at a device's port: a hidraw path, or the first HID interface with that VID:PID.
fn hid_at(what: &str, port: &Port) -> Result<dioptra_transport::hid::HidapiLink, DeviceError> {
    Ok(match port {
        Port::VidPid(v, p) => dioptra_transport::hid::HidapiLink::open(*v, *p, None)?,
        Port::Path(p) => dioptra_transport::hid::HidapiLink::open_path(&p.display().to_string())?,
        Port::Sim | Port::Net(_) | Port::Usb(_) => return Err(unsupported_port(what, port)),
    })
}

/// The serial link at a device's port: a path, or the one USB serial port with that VID:PID
/// (looked up in sysfs at every attempt, so a replugged device that moved is found again).
pub(crate) fn serial_at(
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
        Port::Sim | Port::Net(_) | Port::Usb(_) => return Err(unsupported_port(what, port)),
    };
    Ok(dioptra_transport::serial::SerialLink::open(
        &path,
        dioptra_transport::serial::SerialSettings::baud(115_200),
    )?)
}

/// The rig's lens range as the drivers' limits.
fn lens_limits(cfg: &RigConfig) -> Result<LensLimits, DeviceError> {
    let r = cfg.optics.lens_range;
    PowerRange::new(Diopters(r.min), Diopters(r.max))
        .map(LensLimits::new)
        .ok_or_else(|| DeviceError::Invalid("optics.lens_range is empty".into()))
}

fn connect_optotune(link: Link, ctx: Context) -> BoxFuture<'static, Result<BoxLens, DeviceError>> {
    Box::pin(async move {
        let mut cfg = OptotuneConfig::new(lens_limits(&ctx.cfg)?);
        let lens = ctx.cfg.devices.lens.each();
        let limits = lens.get(ctx.lens).and_then(|l| l.temperature_limits_c);
        if let Some([lo, hi]) = limits {
            cfg = cfg.with_temperature_limits_c(lo, hi);
        }
        let d = Optotune::connect(link.byte("Lens Driver 4")?, cfg, ctx.clock).await?;
        Ok(BoxLens(Box::new(d)))
    })
}

fn connect_lens_controller(
    link: Link,
    ctx: Context,
) -> BoxFuture<'static, Result<BoxLens, DeviceError>> {
    Box::pin(async move {
        let cfg = ControllerConfig::new(lens_limits(&ctx.cfg)?);
        let d = LensController::connect(link.byte("lens controller")?, cfg, ctx.clock).await?;
        Ok(BoxLens(Box::new(d)))
    })
}

fn connect_dioptra_tracker(
    link: Link,
    ctx: Context,
) -> BoxFuture<'static, Result<BoxGaze, DeviceError>> {
    Box::pin(async move {
        let link = link.hid("dioptra eye tracker")?;
        let d = DioptraTracker::connect(link, DioptraTrackerConfig::default(), ctx.clock).await?;
        Ok(BoxGaze(Box::new(d)))
    })
}

fn connect_hid_tracker(
    link: Link,
    ctx: Context,
) -> BoxFuture<'static, Result<BoxGaze, DeviceError>> {
    Box::pin(async move {
        let link = link.hid("HID eye tracker")?;
        let d = HidEyeTracker::connect(link, HidTrackerConfig::default(), ctx.clock).await?;
        Ok(BoxGaze(Box::new(d)))
    })
}

fn connect_pupil(link: Link, ctx: Context) -> BoxFuture<'static, Result<BoxGaze, DeviceError>> {
    Box::pin(async move {
        let g = &ctx.cfg.devices.gaze;
        let mut cfg = PupilConfig::new(link.net("Pupil Capture")?);
        cfg.min_confidence = g.min_confidence;
        if g.port == Port::Sim {
            cfg.rate_hz = g.sim_rate_hz as f32;
        }
        let d = PupilCapture::connect(cfg, ctx.clock).await?;
        Ok(BoxGaze(Box::new(d)))
    })
}

fn connect_sync_board(
    link: Link,
    ctx: Context,
) -> BoxFuture<'static, Result<BoxSequencer, DeviceError>> {
    Box::pin(async move {
        let mut d = SyncBoard::connect(link.byte("sync board")?, ctx.clock).await?;
        let photodiode = ctx.cfg.devices.photodiode.as_ref();
        match (photodiode.filter(|p| p.on_sync_board()), ctx.inputs) {
            (Some(p), Some(inputs)) => {
                d.set_photodiode(Some(p.band())).await?;
                Ok(BoxSequencer(Box::new(BoardWithLight { board: d, inputs })))
            }
            _ => Ok(BoxSequencer(Box::new(d))),
        }
    })
}

/// The sync board when the rig's photodiode is its input: sub-frame events go to the sync
/// task, light straight to the loop (the link is one, so one reader takes both).
struct BoardWithLight {
    board: SyncBoard<AnyByteLink>,
    inputs: tokio::sync::mpsc::Sender<DeviceInput>,
}

impl PlaneSequencer for BoardWithLight {
    async fn program(&mut self, schedule: &PlaneSchedule) -> Result<(), DeviceError> {
        self.board.program(schedule).await
    }
    async fn start(&mut self) -> Result<(), DeviceError> {
        self.board.start().await
    }
    async fn stop(&mut self) -> Result<(), DeviceError> {
        PlaneSequencer::stop(&mut self.board).await
    }
    /// Also while no schedule runs: then only light comes, and this waits for ever (the
    /// board's 1 s time-sync ping fails it if the link breaks).
    async fn next_event(&mut self) -> Result<SequencerEvent, DeviceError> {
        loop {
            match self.board.next_board_event().await? {
                BoardEvent::Sequencer(e) => return Ok(e),
                BoardEvent::Light(l) => {
                    if self.inputs.send(DeviceInput::Light(l)).await.is_err() {
                        return Err(DeviceError::Invalid("the rig's loop has stopped".into()));
                    }
                }
            }
        }
    }
}

fn connect_serial_photodiode(
    link: Link,
    ctx: Context,
) -> BoxFuture<'static, Result<BoxPhotodiode, DeviceError>> {
    Box::pin(async move {
        let d = SerialPhotodiode::connect(link.byte("serial-line photodiode")?, ctx.clock).await?;
        Ok(BoxPhotodiode(Box::new(d)))
    })
}

/// A sync board used only for its photodiode input (`[devices.photodiode] driver = "sync"`
/// with a port of its own).
fn connect_photodiode_board(
    link: Link,
    ctx: Context,
) -> BoxFuture<'static, Result<BoxPhotodiode, DeviceError>> {
    Box::pin(async move {
        let band = ctx
            .cfg
            .devices
            .photodiode
            .as_ref()
            .map(|p| p.band())
            .unwrap_or_default();
        let mut d = SyncBoard::connect(link.byte("sync board")?, ctx.clock).await?;
        d.set_photodiode(Some(band)).await?;
        Ok(BoxPhotodiode(Box::new(d)))
    })
}

fn connect_dlpc350(
    link: Link,
    ctx: Context,
) -> BoxFuture<'static, Result<BoxSequencer, DeviceError>> {
    Box::pin(async move {
        let driver_cfg = ctx
            .cfg
            .devices
            .sync
            .as_ref()
            .map(|s| s.dlpc350_config())
            .unwrap_or_default();
        let d = Dlpc350::new(link.hid("DLPC350")?, ctx.clock, driver_cfg);
        Ok(BoxSequencer(Box::new(d)))
    })
}

fn sim_optotune(spec: &SimSpec, ctx: &Context) -> SimEndpoint {
    let dev = Arc::new(Mutex::new(dioptra_sim::optotune::OptotuneSim::new(
        dioptra_sim::optotune::OptotuneSimConfig {
            lens: spec.lens,
            ..Default::default()
        },
    )));
    SimEndpoint {
        lens: Some(SimLens::Optotune(dev.clone())),
        open: Box::new(byte_endpoint("Lens Driver 4", dev, ctx.clock.clone())),
        gaze_truth: None,
        pupil: None,
    }
}

fn sim_lens_controller(spec: &SimSpec, ctx: &Context) -> SimEndpoint {
    let dev = Arc::new(Mutex::new(
        dioptra_sim::lens_controller::LensControllerSim::new(
            dioptra_sim::lens_controller::LensControllerSimConfig {
                lens: spec.lens,
                ..Default::default()
            },
        ),
    ));
    SimEndpoint {
        lens: Some(SimLens::Controller(dev.clone())),
        open: Box::new(byte_endpoint("lens controller", dev, ctx.clock.clone())),
        gaze_truth: None,
        pupil: None,
    }
}

fn sim_sync_board(spec: &SimSpec, ctx: &Context) -> SimEndpoint {
    let mut sim = dioptra_sim::sync_board::SyncBoardSim::new(spec.board.clone());
    // Its photodiode input sees the simulated panel when the rig's photodiode is on it.
    let on_board = ctx
        .cfg
        .devices
        .photodiode
        .as_ref()
        .is_some_and(|p| p.on_sync_board());
    if let (true, Some(panel)) = (on_board, &spec.panel) {
        sim = sim.with_light(Arc::new(panel.clone()));
    }
    byte_sim("sync board", sim, ctx)
}

/// A byte-speaking simulator with no lens, gaze or pupil of its own.
fn byte_sim<D: ByteDevice + Send + 'static>(
    what: &'static str,
    sim: D,
    ctx: &Context,
) -> SimEndpoint {
    SimEndpoint {
        lens: None,
        open: Box::new(byte_endpoint(
            what,
            Arc::new(Mutex::new(sim)),
            ctx.clock.clone(),
        )),
        gaze_truth: None,
        pupil: None,
    }
}

/// A light source for a simulated photodiode: the simulated panel, or darkness without one.
fn panel_light(spec: &SimSpec) -> Arc<dyn dioptra_sim::light::LightSource> {
    match &spec.panel {
        Some(p) => Arc::new(p.clone()),
        None => Arc::new(dioptra_sim::light::ScriptedLight::new()),
    }
}

fn sim_serial_photodiode(spec: &SimSpec, ctx: &Context) -> SimEndpoint {
    let sim = dioptra_sim::photodiode::SerialPhotodiodeSim::new(spec.serial_photodiode.clone())
        .with_light(panel_light(spec));
    byte_sim("serial-line photodiode", sim, ctx)
}

fn sim_photodiode_board(spec: &SimSpec, ctx: &Context) -> SimEndpoint {
    let sim = dioptra_sim::sync_board::SyncBoardSim::new(spec.board.clone())
        .with_light(panel_light(spec));
    byte_sim("sync board", sim, ctx)
}

fn sim_dlpc350(spec: &SimSpec, _ctx: &Context) -> SimEndpoint {
    let cfg = spec.dlpc350;
    SimEndpoint {
        lens: None,
        open: Box::new(move || {
            let (link, projector) = dioptra_sim::dlpc350::new(cfg);
            let cut: Cut = Box::new(move || projector.unplug("unplugged"));
            Ok((SimLink::Hid(link.into()), cut))
        }),
        gaze_truth: None,
        pupil: None,
    }
}

/// A gaze generator for a new connection to a simulated tracker: the spec's scene from its
/// start, recording its truth when asked.
fn gaze_source(
    spec: &SimSpec,
    truth: &Option<GazeTruth>,
    clock: &Arc<dyn Clock>,
) -> Result<Box<dyn dioptra_sim::gaze::SampleSource>, LinkError> {
    let gen = dioptra_sim::gaze::GazeGenerator::new(spec.gaze_scene.clone(), spec.gaze)
        .map_err(|e| LinkError::Unavailable(format!("the simulated gaze scene: {e}")))?;
    Ok(match truth {
        Some(truth) => Box::new(RecordedGaze {
            gen,
            truth: truth.clone(),
            origin_us: clock.now().as_micros(),
        }),
        None => Box::new(gen),
    })
}

fn gaze_endpoint(
    spec: &SimSpec,
    ctx: &Context,
    spawn: fn(
        Box<dyn dioptra_sim::gaze::SampleSource>,
        &SimSpec,
    ) -> (dioptra_transport::hid::memory::MemoryHidLink, Cut),
) -> SimEndpoint {
    let truth = spec
        .record_gaze_truth
        .then(|| GazeTruth::new(Mutex::new(Vec::new())));
    let (spec, clock, t) = (spec.clone(), ctx.clock.clone(), truth.clone());
    SimEndpoint {
        lens: None,
        open: Box::new(move || {
            let (link, cut) = spawn(gaze_source(&spec, &t, &clock)?, &spec);
            Ok((SimLink::Hid(link.into()), cut))
        }),
        gaze_truth: truth,
        pupil: None,
    }
}

/// A simulated Pupil Capture on loopback TCP, publishing the spec's gaze scene; each start
/// of Capture plays the scene from its beginning.
fn sim_pupil_capture(spec: &SimSpec, ctx: &Context) -> SimEndpoint {
    let truth = spec
        .record_gaze_truth
        .then(|| GazeTruth::new(Mutex::new(Vec::new())));
    let (spec, clock, t) = (spec.clone(), ctx.clock.clone(), truth.clone());
    let capture = SimPupilCapture::new(Box::new(move || gaze_source(&spec, &t, &clock)));
    let c = capture.clone();
    SimEndpoint {
        lens: None,
        open: Box::new(move || c.open()),
        gaze_truth: truth,
        pupil: Some(capture),
    }
}

fn sim_dioptra_tracker(spec: &SimSpec, ctx: &Context) -> SimEndpoint {
    gaze_endpoint(spec, ctx, |source, spec| {
        let (link, tracker) = dioptra_sim::gaze::dioptra_tracker::spawn(source);
        tracker.set_faults(dioptra_sim::gaze::Faults {
            latency_us: spec.gaze_latency_us,
            ..Default::default()
        });
        (link, Box::new(move || tracker.disconnect("unplugged")))
    })
}

fn sim_hid_tracker(spec: &SimSpec, ctx: &Context) -> SimEndpoint {
    gaze_endpoint(spec, ctx, |source, spec| {
        let (link, tracker) = dioptra_sim::gaze::hid_tracker::spawn(source, spec.hid_tracker);
        tracker.set_faults(dioptra_sim::gaze::Faults {
            latency_us: spec.gaze_latency_us,
            ..Default::default()
        });
        (link, Box::new(move || tracker.disconnect("unplugged")))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_driver_the_config_names_has_a_row() {
        for d in [LensDriver::Optotune, LensDriver::Lens] {
            assert!(row(&LENS, d).is_ok(), "{d:?}");
        }
        for d in [
            GazeDriver::DioptraTracker,
            GazeDriver::Hid,
            GazeDriver::Pupil,
        ] {
            assert!(row(&GAZE, d).is_ok(), "{d:?}");
        }
        for d in [SyncDriver::Sync, SyncDriver::Dlpc350] {
            assert!(row(&SYNC, d).is_ok(), "{d:?}");
        }
    }

    #[test]
    fn a_serial_device_by_vid_pid_that_is_absent_is_a_link_error_naming_it() {
        // No machine has feed:beef; without sysfs the error still names the port.
        let e = serial_at("lens controller", &Port::VidPid(0xfeed, 0xbeef)).unwrap_err();
        assert!(matches!(e, DeviceError::Link(_)), "{e:?}");
        let text = e.to_string();
        assert!(text.contains("lens controller at feed:beef"), "{text}");
    }
}
