//! The drivers' table: for each device kind, one row per driver the rig config can name,
//! saying how its device is reached (serial, HID, the network; USB bulk endpoints for a driver
//! that has them), how its simulator is made for `port = "sim"`, and the one constructor that
//! connects the driver over a link: typed per kind (a lens row gives a [`BoxLens`] from a
//! [`LensSetup`], a sync row a [`BoxSequencer`] from a [`SyncSetup`], ...). The rig's device
//! tasks and the device commands (`dioptra lens|gaze|sync --device DRIVER:PORT`) both open
//! devices here: the rig makes each setup from its config, a command from its flags; the
//! driver enforces the setup's limits whatever it is asked. What users may type besides a
//! driver's name ([`Alias`]), the `hid` port and which driver a VID:PID belongs to
//! ([`known_devices`], the driver crates' match tables) are data here too, so the command line
//! reaches whatever a rig config can name, by the same code.

use std::future::Future;
use std::sync::{Arc, Mutex};

use dioptra_core::{
    Clock, DeviceError, Diopters, LinkError, PlaneSchedule, PlaneSequencer, PowerRange,
    SequencerEvent,
};
use dioptra_gaze::dioptra_tracker::{DioptraTracker, DioptraTrackerConfig};
use dioptra_gaze::eye_hid::{HidEyeTracker, HidTrackerConfig};
use dioptra_gaze::pupil::{PupilCapture, PupilConfig};
use dioptra_lens::{
    ControllerConfig, LensController, LensLimits, Opener, Optotune, OptotuneConfig,
};
use dioptra_photodiode::SerialPhotodiode;
use dioptra_sim::serve::ByteDevice;
use dioptra_sync::board::{BoardEvent, PhotodiodeBand, SyncBoard};
use dioptra_sync::dlpc350::{Dlpc350, Dlpc350Config};
use dioptra_transport::discovery::{Interface, KnownDevice};
use dioptra_transport::AnyByteLink;

use super::boxed::{
    About, BoxFuture, BoxGaze, BoxLens, BoxPhotodiode, BoxSequencer, Facts, Resume,
};
use super::input::DeviceInput;
use crate::config::{GazeDriver, LensDriver, PhotodiodeDriver, Port, RigConfig, SyncDriver};
use crate::devices::simulators::{
    byte_endpoint, Cut, GazeTruth, RecordedGaze, SimEndpoint, SimLens, SimLink, SimPlug,
    SimProjector, SimPupilCapture, SimSlot, SimSpec,
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

pub use super::boxed::Link;

impl From<SimLink> for Link {
    fn from(l: SimLink) -> Link {
        match l {
            SimLink::Byte(l) => Link::Byte(l),
            SimLink::Hid(l) => Link::Hid(l),
            SimLink::Net(a) => Link::Net(a),
        }
    }
}

/// Opens a device's link again after an unplug (see [`Context::reopen`]).
pub type Reopen = Arc<dyn Fn() -> BoxFuture<'static, Result<Link, DeviceError>> + Send + Sync>;

/// What a driver's connect gets besides its link: the clock, its kind's setup (what the caller
/// decided about the device: a lens's limits, a sequencer's trigger edge, ...) and, for a
/// driver that reopens its own link, how.
#[derive(Clone)]
pub struct Context<S> {
    pub clock: Arc<dyn Clock>,
    pub setup: S,
    /// How to open the link again after an unplug, for a driver that reopens its own (the
    /// lens drivers, under a device command). `None` in a rig: its device tasks reconnect.
    pub reopen: Option<Reopen>,
}

impl<S> Context<S> {
    pub fn new(clock: Arc<dyn Clock>, setup: S) -> Self {
        Context {
            clock,
            setup,
            reopen: None,
        }
    }
    /// The driver reopens its link with `open` after an unplug.
    pub fn reopening<F, Fut>(self, open: F) -> Self
    where
        F: Fn() -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Link, DeviceError>> + Send + 'static,
    {
        Context {
            reopen: Some(Arc::new(move || Box::pin(open()))),
            ..self
        }
    }
}

/// What a lens driver is connected with. The driver keeps every command within `limits`
/// (clamped or refused, as `limits.policy` says), whatever the caller asks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensSetup {
    pub limits: LensLimits,
    /// The temperature limits a Lens Driver 4 is given (it derives its focal-power range from
    /// them); `None`: its default.
    pub temperature_limits_c: Option<[f32; 2]>,
}

impl LensSetup {
    pub fn new(limits: LensLimits) -> Self {
        LensSetup {
            limits,
            temperature_limits_c: None,
        }
    }
    /// Lens `index` of `cfg` (its index in `devices.lens.each()`): the rig's
    /// `optics.lens_range` and the lens's own keys.
    pub fn from_rig(cfg: &RigConfig, index: usize) -> Result<Self, DeviceError> {
        let r = cfg.optics.lens_range;
        let limits = PowerRange::new(Diopters(r.min), Diopters(r.max))
            .map(LensLimits::new)
            .ok_or_else(|| DeviceError::Invalid("optics.lens_range is empty".into()))?;
        let lens = cfg.devices.lens.each();
        Ok(LensSetup {
            limits,
            temperature_limits_c: lens.get(index).and_then(|l| l.temperature_limits_c),
        })
    }
}

/// What an eye-tracker driver is connected with (Pupil Capture's; the HID trackers take none).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct GazeSetup {
    /// Datums below this confidence are dropouts; `None`: the driver's recommendation.
    pub min_confidence: Option<f32>,
    /// The gaze rate to expect, Hz; `None`: the driver's default.
    pub rate_hz: Option<f32>,
}

impl GazeSetup {
    pub fn from_rig(cfg: &RigConfig) -> Self {
        let g = &cfg.devices.gaze;
        GazeSetup {
            min_confidence: Some(g.min_confidence),
            rate_hz: (g.port == Port::Sim).then_some(g.sim_rate_hz as f32),
        }
    }
}

/// What a sync driver is connected with.
#[derive(Debug, Clone)]
pub struct SyncSetup {
    /// The sync board's frames start on the rising vsync edge (else the falling one).
    pub trigger_rising: bool,
    /// How the DLPC350 is wired into the rig.
    pub dlpc350: Dlpc350Config,
    /// The rig's photodiode on the sync board's input: its band, and where its light goes.
    pub light: Option<BoardLight>,
}

impl Default for SyncSetup {
    fn default() -> Self {
        SyncSetup {
            trigger_rising: true,
            dlpc350: Dlpc350Config::default(),
            light: None,
        }
    }
}

/// A photodiode on the sync board's input, whose light goes straight to the rig's loop.
#[derive(Debug, Clone)]
pub struct BoardLight {
    pub band: PhotodiodeBand,
    pub inputs: tokio::sync::mpsc::Sender<DeviceInput>,
}

impl SyncSetup {
    /// `cfg`'s `[devices.sync]`, its photodiode's light sent to `inputs` when it is on the
    /// board.
    pub fn from_rig(cfg: &RigConfig, inputs: tokio::sync::mpsc::Sender<DeviceInput>) -> Self {
        let d = &cfg.devices;
        SyncSetup {
            trigger_rising: true,
            dlpc350: d
                .sync
                .as_ref()
                .map(|s| s.dlpc350_config())
                .unwrap_or_default(),
            light: d
                .photodiode
                .as_ref()
                .filter(|p| p.on_sync_board())
                .map(|p| BoardLight {
                    band: p.band(),
                    inputs,
                }),
        }
    }
}

/// What a photodiode driver is connected with: the sync board's comparator band (the
/// serial-line photodiode's is its own trimmer).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PhotodiodeSetup {
    pub band: PhotodiodeBand,
}

impl PhotodiodeSetup {
    pub fn from_rig(cfg: &RigConfig) -> Self {
        PhotodiodeSetup {
            band: cfg
                .devices
                .photodiode
                .as_ref()
                .map(|p| p.band())
                .unwrap_or_default(),
        }
    }
}

/// Connects a row's driver over a link: typed per kind (the boxed driver `D`, its setup `S`).
pub type Connect<D, S> = fn(Link, Context<S>) -> BoxFuture<'static, Result<D, DeviceError>>;
type MakeSim<S> = fn(&SimSpec, &Context<S>) -> SimEndpoint;

/// Another name users give a driver on the command line: `NAME[:REST]` stands for
/// `DRIVER:PORT[:REST]` (`sim-hid:pursuit` for `hid:sim:pursuit`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Alias {
    pub name: &'static str,
    pub port: &'static str,
}

/// One driver of a device kind.
pub struct Row<K: 'static, D: 'static, S: 'static> {
    pub driver: K,
    /// The driver's name in the rig config and the API.
    pub name: &'static str,
    /// The device, for messages ("Lens Driver 4").
    pub what: &'static str,
    pub transport: Transport,
    /// The VID and PID of the device's USB bulk interface, for a driver that also talks over
    /// one (`port = "usb"` or `"usb:SERIAL"`).
    pub usb: Option<(u16, u16)>,
    /// Other names for the driver on the command line.
    pub aliases: &'static [Alias],
    pub(crate) sim: MakeSim<S>,
    /// The driver's one constructor: connects it over a link with a setup.
    pub connect: Connect<D, S>,
}

pub type LensRow = Row<LensDriver, BoxLens, LensSetup>;
pub type GazeRow = Row<GazeDriver, BoxGaze, GazeSetup>;
pub type SyncRow = Row<SyncDriver, BoxSequencer, SyncSetup>;
pub type PhotodiodeRow = Row<PhotodiodeDriver, BoxPhotodiode, PhotodiodeSetup>;

pub static LENS: [LensRow; 2] = [
    Row {
        driver: LensDriver::Optotune,
        name: "optotune",
        what: "Lens Driver 4",
        transport: Transport::Serial,
        usb: None,
        aliases: &[],
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
        aliases: &[],
        sim: sim_lens_controller,
        connect: connect_lens_controller,
    },
];

pub static GAZE: [GazeRow; 3] = [
    Row {
        driver: GazeDriver::DioptraTracker,
        name: "dioptra-tracker",
        what: "dioptra eye tracker",
        transport: Transport::Hid,
        usb: None,
        aliases: &[Alias {
            name: "sim",
            port: "sim",
        }],
        sim: sim_dioptra_tracker,
        connect: connect_dioptra_tracker,
    },
    Row {
        driver: GazeDriver::Hid,
        name: "hid",
        what: "HID eye tracker",
        transport: Transport::Hid,
        usb: None,
        aliases: &[Alias {
            name: "sim-hid",
            port: "sim",
        }],
        sim: sim_hid_tracker,
        connect: connect_hid_tracker,
    },
    Row {
        driver: GazeDriver::Pupil,
        name: "pupil",
        what: "Pupil Capture",
        transport: Transport::Net,
        usb: None,
        aliases: &[],
        sim: sim_pupil_capture,
        connect: connect_pupil,
    },
];

pub static SYNC: [SyncRow; 2] = [
    Row {
        driver: SyncDriver::Sync,
        name: "sync",
        what: "sync board",
        transport: Transport::Serial,
        usb: None,
        aliases: &[],
        sim: sim_sync_board,
        connect: connect_sync_board,
    },
    Row {
        driver: SyncDriver::Dlpc350,
        name: "dlpc350",
        what: "DLPC350",
        transport: Transport::Hid,
        usb: None,
        aliases: &[],
        sim: sim_dlpc350,
        connect: connect_dlpc350,
    },
];

pub static PHOTODIODE: [PhotodiodeRow; 2] = [
    Row {
        driver: PhotodiodeDriver::SerialLine,
        name: "serial-line",
        what: "serial-line photodiode",
        transport: Transport::Serial,
        usb: None,
        aliases: &[],
        sim: sim_serial_photodiode,
        connect: connect_serial_photodiode,
    },
    Row {
        driver: PhotodiodeDriver::Sync,
        name: "sync",
        what: "sync board (its photodiode input)",
        transport: Transport::Serial,
        usb: None,
        aliases: &[],
        sim: sim_photodiode_board,
        connect: connect_photodiode_board,
    },
];

/// The row of `driver` in `rows`.
pub fn row<K: PartialEq + std::fmt::Debug, D, S>(
    rows: &'static [Row<K, D, S>],
    driver: K,
) -> Result<&'static Row<K, D, S>, DeviceError> {
    rows.iter()
        .find(|r| r.driver == driver)
        .ok_or_else(|| DeviceError::Invalid(format!("no driver is registered for {driver:?}")))
}

/// The row of the driver named `name` (its name in the rig config and in `--device
/// DRIVER:PORT`).
pub fn row_named<K, D, S>(
    rows: &'static [Row<K, D, S>],
    name: &str,
) -> Option<&'static Row<K, D, S>> {
    rows.iter().find(|r| r.name == name)
}

/// The names of `rows`' drivers, for messages ("optotune, lens").
pub fn names<K, D, S>(rows: &'static [Row<K, D, S>]) -> String {
    rows.iter().map(|r| r.name).collect::<Vec<_>>().join(", ")
}

/// The aliases of `rows`' drivers, for messages ("sim, sim-hid"; empty without any).
pub fn alias_names<K, D, S>(rows: &'static [Row<K, D, S>]) -> String {
    rows.iter()
        .flat_map(|r| r.aliases.iter().map(|a| a.name))
        .collect::<Vec<_>>()
        .join(", ")
}

/// `spec` with an alias of one of `rows` spelled out: `NAME[:REST]` becomes
/// `DRIVER:PORT[:REST]`; `None` when it starts with no alias.
pub fn unalias<K, D, S>(rows: &'static [Row<K, D, S>], spec: &str) -> Option<String> {
    let (head, rest) = match spec.split_once(':') {
        Some((h, r)) => (h, Some(r)),
        None => (spec, None),
    };
    let (row, alias) = rows
        .iter()
        .find_map(|r| r.aliases.iter().find(|a| a.name == head).map(|a| (r, a)))?;
    Some(match rest {
        Some(rest) => format!("{}:{}:{rest}", row.name, alias.port),
        None => format!("{}:{}", row.name, alias.port),
    })
}

/// Every driver's match table, joined: the devices `dioptra devices` finds and the udev rules
/// grant access to. A new driver crate adds its `ids::KNOWN_DEVICES` here.
pub fn known_devices() -> Vec<KnownDevice> {
    [
        dioptra_lens::ids::KNOWN_DEVICES,
        dioptra_gaze::ids::KNOWN_DEVICES,
        dioptra_sync::ids::KNOWN_DEVICES,
    ]
    .concat()
}

/// The row among `rows` whose driver's match table claims the device at `port` (a VID:PID),
/// if any: a device is driven by its own driver whichever name it was given.
pub fn claimed_by<K, D, S>(
    rows: &'static [Row<K, D, S>],
    port: &Port,
) -> Option<&'static Row<K, D, S>> {
    let Port::VidPid(vid, pid) = *port else {
        return None;
    };
    let name = known_devices()
        .into_iter()
        .find(|k| k.vid == Some(vid) && k.pid == Some(pid))?
        .driver;
    row_named(rows, name)
}

/// The port `text` names for `row`: a rig config port, or `hid`, the first HID device with
/// the VID:PID the driver's match table gives (`dlpc350:hid`).
pub fn port_for<K, D, S>(row: &Row<K, D, S>, text: &str) -> Result<Port, String> {
    if text != "hid" {
        return Port::try_from(text.to_string());
    }
    known_devices()
        .into_iter()
        .find(|k| k.driver == row.name && k.interface == Interface::Hid)
        .and_then(|k| Some(Port::VidPid(k.vid?, k.pid?)))
        .ok_or_else(|| {
            format!(
                "port \"hid\": the {} has no HID VID:PID of its own; give its hidraw path or VID:PID",
                row.what
            )
        })
}

/// The link to `row`'s real device at `port`: a serial port (by path, or the one USB serial
/// port with a VID:PID), a HID device (by hidraw path or VID:PID), the device's USB bulk
/// endpoints (`usb`, `usb:SERIAL`) or a network address. Blocking (a USB or serial open).
/// Not for `port = "sim"`, whose link the device task makes from the simulator.
pub fn device_link<K, D, S>(row: &Row<K, D, S>, port: &Port) -> Result<Link, DeviceError> {
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

/// A simulator of `row`'s device made from `spec`, in this process, with the one link a
/// device command needs: for `DRIVER:sim` on the command line. Keep the [`Simulated`] while
/// the link is used (it holds the simulator).
pub fn simulated<K, D, S>(
    row: &Row<K, D, S>,
    spec: &SimSpec,
    ctx: &Context<S>,
) -> Result<(Link, Simulated), DeviceError> {
    let mut sim = (row.sim)(spec, ctx);
    let (link, cut) = (sim.open)()?;
    let projector = sim.projector.as_ref().and_then(|p| p.lock().ok()?.clone());
    Ok((
        link.into(),
        Simulated {
            _cut: cut,
            projector,
        },
    ))
}

/// A simulator made by [`simulated`], and its handles a device command may show.
pub struct Simulated {
    _cut: Cut,
    /// The simulated DLPC350: the patterns it shows and the commands it received.
    pub projector: Option<Arc<dioptra_sim::dlpc350::Dlpc350Sim>>,
}

/// The connect function a device task retries: opens the link `port` names (a new link to the
/// simulator for `port = "sim"`, whose handles go into `slot`) and connects `row`'s driver.
pub(crate) fn device_connector<K: Sync, D: Send + 'static, S: Clone + Send + Sync + 'static>(
    row: &'static Row<K, D, S>,
    port: &Port,
    ctx: Context<S>,
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
            Box::new(move || Ok(plug.open(what, &mut sim.open)?.into()))
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

/// The opener a driver that reopens its own link is given: `link` first, then `reopen`'s.
fn byte_opener(link: AnyByteLink, what: &'static str, reopen: Reopen) -> Opener<AnyByteLink> {
    let mut first = Some(link);
    Opener::new(move || {
        let first = first.take();
        let reopen = reopen.clone();
        async move {
            match first {
                Some(l) => Ok(l),
                None => reopen()
                    .await
                    .and_then(|l| l.byte(what))
                    .map_err(|e| match e {
                        DeviceError::Link(l) => l,
                        other => LinkError::Unavailable(other.to_string()),
                    }),
            }
        }
    })
}

fn connect_optotune(
    link: Link,
    ctx: Context<LensSetup>,
) -> BoxFuture<'static, Result<BoxLens, DeviceError>> {
    const WHAT: &str = "Lens Driver 4";
    Box::pin(async move {
        let mut cfg = OptotuneConfig::new(ctx.setup.limits);
        if let Some([lo, hi]) = ctx.setup.temperature_limits_c {
            cfg = cfg.with_temperature_limits_c(lo, hi);
        }
        let link = link.byte(WHAT)?;
        let d = match ctx.reopen {
            Some(r) => Optotune::connect_with(byte_opener(link, WHAT, r), cfg, ctx.clock).await?,
            None => Optotune::connect(link, cfg, ctx.clock).await?,
        };
        Ok(BoxLens(Box::new(d)))
    })
}

fn connect_lens_controller(
    link: Link,
    ctx: Context<LensSetup>,
) -> BoxFuture<'static, Result<BoxLens, DeviceError>> {
    const WHAT: &str = "lens controller";
    Box::pin(async move {
        let cfg = ControllerConfig::new(ctx.setup.limits);
        let link = link.byte(WHAT)?;
        let d = match ctx.reopen {
            Some(r) => {
                LensController::connect_with(byte_opener(link, WHAT, r), cfg, ctx.clock).await?
            }
            None => LensController::connect(link, cfg, ctx.clock).await?,
        };
        Ok(BoxLens(Box::new(d)))
    })
}

fn connect_dioptra_tracker(
    link: Link,
    ctx: Context<GazeSetup>,
) -> BoxFuture<'static, Result<BoxGaze, DeviceError>> {
    Box::pin(async move {
        let link = link.hid("dioptra eye tracker")?;
        let d = DioptraTracker::connect(link, DioptraTrackerConfig::default(), ctx.clock).await?;
        Ok(BoxGaze(Box::new(d)))
    })
}

fn connect_hid_tracker(
    link: Link,
    ctx: Context<GazeSetup>,
) -> BoxFuture<'static, Result<BoxGaze, DeviceError>> {
    Box::pin(async move {
        let link = link.hid("HID eye tracker")?;
        let d = HidEyeTracker::connect(link, HidTrackerConfig::default(), ctx.clock).await?;
        Ok(BoxGaze(Box::new(d)))
    })
}

fn connect_pupil(
    link: Link,
    ctx: Context<GazeSetup>,
) -> BoxFuture<'static, Result<BoxGaze, DeviceError>> {
    Box::pin(async move {
        let mut cfg = PupilConfig::new(link.net("Pupil Capture")?);
        if let Some(c) = ctx.setup.min_confidence {
            cfg.min_confidence = c;
        }
        if let Some(r) = ctx.setup.rate_hz {
            cfg.rate_hz = r;
        }
        let d = PupilCapture::connect(cfg, ctx.clock).await?;
        Ok(BoxGaze(Box::new(d)))
    })
}

fn connect_sync_board(
    link: Link,
    ctx: Context<SyncSetup>,
) -> BoxFuture<'static, Result<BoxSequencer, DeviceError>> {
    Box::pin(async move {
        let mut d = SyncBoard::connect(link.byte("sync board")?, ctx.clock)
            .await?
            .with_trigger_rising(ctx.setup.trigger_rising);
        match ctx.setup.light {
            Some(BoardLight { band, inputs }) => {
                d.set_photodiode(Some(band)).await?;
                Ok(BoxSequencer(Box::new(BoardWithLight { board: d, inputs })))
            }
            None => Ok(BoxSequencer(Box::new(d))),
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

impl About for BoardWithLight {
    fn identity(&self) -> String {
        self.board.identity()
    }
    fn about(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        self.board.about()
    }
}

impl Resume for BoardWithLight {
    fn resumes(&self) -> bool {
        self.board.resumes()
    }
    fn resume(&mut self, link: Link) -> BoxFuture<'_, Result<(), DeviceError>> {
        self.board.resume(link)
    }
}

fn connect_serial_photodiode(
    link: Link,
    ctx: Context<PhotodiodeSetup>,
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
    ctx: Context<PhotodiodeSetup>,
) -> BoxFuture<'static, Result<BoxPhotodiode, DeviceError>> {
    Box::pin(async move {
        let mut d = SyncBoard::connect(link.byte("sync board")?, ctx.clock).await?;
        d.set_photodiode(Some(ctx.setup.band)).await?;
        Ok(BoxPhotodiode(Box::new(d)))
    })
}

fn connect_dlpc350(
    link: Link,
    ctx: Context<SyncSetup>,
) -> BoxFuture<'static, Result<BoxSequencer, DeviceError>> {
    Box::pin(async move {
        let d = Dlpc350::new(link.hid("DLPC350")?, ctx.clock, ctx.setup.dlpc350);
        Ok(BoxSequencer(Box::new(d)))
    })
}

fn sim_optotune(spec: &SimSpec, ctx: &Context<LensSetup>) -> SimEndpoint {
    let dev = Arc::new(Mutex::new(dioptra_sim::optotune::OptotuneSim::new(
        dioptra_sim::optotune::OptotuneSimConfig {
            lens: spec.lens,
            ..Default::default()
        },
    )));
    SimEndpoint {
        lens: Some(SimLens::Optotune(dev.clone())),
        open: Box::new(byte_endpoint("Lens Driver 4", dev, ctx.clock.clone())),
        ..SimEndpoint::default()
    }
}

fn sim_lens_controller(spec: &SimSpec, ctx: &Context<LensSetup>) -> SimEndpoint {
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
        ..SimEndpoint::default()
    }
}

fn sim_sync_board(spec: &SimSpec, ctx: &Context<SyncSetup>) -> SimEndpoint {
    let mut sim = dioptra_sim::sync_board::SyncBoardSim::new(spec.board.clone());
    // Its photodiode input sees the simulated panel when the rig's photodiode is on it.
    if let (true, Some(panel)) = (ctx.setup.light.is_some(), &spec.panel) {
        sim = sim.with_light(Arc::new(panel.clone()));
    }
    byte_sim("sync board", sim, &ctx.clock)
}

/// A byte-speaking simulator with no lens, gaze or pupil of its own.
fn byte_sim<D: ByteDevice + Send + 'static>(
    what: &'static str,
    sim: D,
    clock: &Arc<dyn Clock>,
) -> SimEndpoint {
    SimEndpoint {
        open: Box::new(byte_endpoint(
            what,
            Arc::new(Mutex::new(sim)),
            clock.clone(),
        )),
        ..SimEndpoint::default()
    }
}

/// A light source for a simulated photodiode: the simulated panel, or darkness without one.
fn panel_light(spec: &SimSpec) -> Arc<dyn dioptra_sim::light::LightSource> {
    match &spec.panel {
        Some(p) => Arc::new(p.clone()),
        None => Arc::new(dioptra_sim::light::ScriptedLight::new()),
    }
}

fn sim_serial_photodiode(spec: &SimSpec, ctx: &Context<PhotodiodeSetup>) -> SimEndpoint {
    let sim = dioptra_sim::photodiode::SerialPhotodiodeSim::new(spec.serial_photodiode.clone())
        .with_light(panel_light(spec));
    byte_sim("serial-line photodiode", sim, &ctx.clock)
}

fn sim_photodiode_board(spec: &SimSpec, ctx: &Context<PhotodiodeSetup>) -> SimEndpoint {
    let sim = dioptra_sim::sync_board::SyncBoardSim::new(spec.board.clone())
        .with_light(panel_light(spec));
    byte_sim("sync board", sim, &ctx.clock)
}

fn sim_dlpc350(spec: &SimSpec, _ctx: &Context<SyncSetup>) -> SimEndpoint {
    let cfg = spec.dlpc350;
    let newest = SimProjector::default();
    let slot = newest.clone();
    SimEndpoint {
        open: Box::new(move || {
            let (link, projector) = dioptra_sim::dlpc350::new(cfg);
            let projector = Arc::new(projector);
            *dioptra_core::lock(&slot) = Some(projector.clone());
            let cut: Cut = Box::new(move || projector.unplug("unplugged"));
            Ok((SimLink::Hid(link.into()), cut))
        }),
        projector: Some(newest),
        ..SimEndpoint::default()
    }
}

/// A gaze generator for a new connection to a simulated tracker: the spec's scene from its
/// start, recording its truth when asked; or the spec's recorded trace, replayed.
fn gaze_source(
    spec: &SimSpec,
    truth: &Option<GazeTruth>,
    clock: &Arc<dyn Clock>,
) -> Result<Box<dyn dioptra_sim::gaze::SampleSource>, LinkError> {
    if let Some(trace) = &spec.gaze_trace {
        return Ok(Box::new(dioptra_sim::gaze::csv::Replay::new(
            trace.as_ref().clone(),
        )));
    }
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
    clock: &Arc<dyn Clock>,
    spawn: fn(
        Box<dyn dioptra_sim::gaze::SampleSource>,
        &SimSpec,
    ) -> (dioptra_transport::hid::memory::MemoryHidLink, Cut),
) -> SimEndpoint {
    let truth = spec
        .record_gaze_truth
        .then(|| GazeTruth::new(Mutex::new(Vec::new())));
    let (spec, clock, t) = (spec.clone(), clock.clone(), truth.clone());
    SimEndpoint {
        open: Box::new(move || {
            let (link, cut) = spawn(gaze_source(&spec, &t, &clock)?, &spec);
            Ok((SimLink::Hid(link.into()), cut))
        }),
        gaze_truth: truth,
        ..SimEndpoint::default()
    }
}

/// A simulated Pupil Capture on loopback TCP, publishing the spec's gaze scene; each start
/// of Capture plays the scene from its beginning.
fn sim_pupil_capture(spec: &SimSpec, ctx: &Context<GazeSetup>) -> SimEndpoint {
    let truth = spec
        .record_gaze_truth
        .then(|| GazeTruth::new(Mutex::new(Vec::new())));
    let (spec, clock, t) = (spec.clone(), ctx.clock.clone(), truth.clone());
    let capture = SimPupilCapture::new(Box::new(move || gaze_source(&spec, &t, &clock)));
    let c = capture.clone();
    SimEndpoint {
        open: Box::new(move || c.open()),
        gaze_truth: truth,
        pupil: Some(capture),
        ..SimEndpoint::default()
    }
}

fn sim_dioptra_tracker(spec: &SimSpec, ctx: &Context<GazeSetup>) -> SimEndpoint {
    gaze_endpoint(spec, &ctx.clock, |source, spec| {
        let (link, tracker) = dioptra_sim::gaze::dioptra_tracker::spawn(source);
        tracker.set_faults(dioptra_sim::gaze::Faults {
            latency_us: spec.gaze_latency_us,
            ..Default::default()
        });
        (link, Box::new(move || tracker.disconnect("unplugged")))
    })
}

fn sim_hid_tracker(spec: &SimSpec, ctx: &Context<GazeSetup>) -> SimEndpoint {
    gaze_endpoint(spec, &ctx.clock, |source, spec| {
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
    fn the_match_tables_name_the_driver_of_a_vid_pid_and_the_hid_port() {
        let tracker = Port::VidPid(
            dioptra_gaze::ids::DIOPTRA_VID,
            dioptra_gaze::ids::DIOPTRA_TRACKER_PID,
        );
        assert_eq!(
            claimed_by(&GAZE, &tracker).map(|r| r.name),
            Some("dioptra-tracker")
        );
        assert!(claimed_by(&GAZE, &Port::VidPid(0xfeed, 0xbeef)).is_none());
        let dlpc350 = row(&SYNC, SyncDriver::Dlpc350).unwrap();
        assert_eq!(
            port_for(dlpc350, "hid"),
            Ok(Port::VidPid(
                dioptra_sync::ids::TI_VID,
                dioptra_sync::ids::DLPC350_PID
            ))
        );
        let board = row(&SYNC, SyncDriver::Sync).unwrap();
        assert!(port_for(board, "hid").unwrap_err().contains("sync board"));
        assert_eq!(
            unalias(&GAZE, "sim-hid:pursuit").as_deref(),
            Some("hid:sim:pursuit")
        );
        assert_eq!(
            unalias(&GAZE, "sim").as_deref(),
            Some("dioptra-tracker:sim")
        );
        assert_eq!(unalias(&GAZE, "hid:/dev/hidraw0"), None);
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
