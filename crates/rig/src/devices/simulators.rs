//! The simulated devices of a rig (`port = "sim"`): what each simulator is set up with
//! ([`SimSpec`], from the rig config), the plug that pulls and restores its cable
//! ([`SimPlug`]), and the handles the API and the simulated-rig builder look at
//! ([`SimDevices`]). The simulators are dioptra-sim's, speaking the real bytes over in-memory
//! links, so the real drivers run on them.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::{lock, Clock, LinkError, Side, Timestamp};
use dioptra_sim::gaze::generator::{SampleSource, TruthSample};
use dioptra_sim::gaze::hid_tracker::HidTrackerSetup;
use dioptra_sim::gaze::{GazeGenerator, GeneratorConfig, Scene};
use dioptra_sim::lens_model::{LensModel, LensModelConfig};
use dioptra_sim::panel::{PanelConfig, SharedPanel};
use dioptra_sim::photodiode::SerialPhotodiodeSimConfig;
use dioptra_sim::serve::ByteDevice;
use dioptra_transport::{memory, AnyByteLink, AnyHidLink};

use super::config::{Lenses, SyncDevice};
use crate::config::{ConfigError, RigConfig};
use crate::display::config::Display;

/// How the simulated devices of a rig are set up. [`SimSpec::from_config`] is what `dioptra
/// serve` runs; the simulated-rig builder starts from the same and may change it (a scripted
/// gaze scene, injected faults).
#[derive(Debug, Clone)]
pub struct SimSpec {
    /// The varifocal lens (Lens Driver 4 or dioptra lens controller simulator): the one
    /// lens, or the left eye's.
    pub lens: LensModelConfig,
    /// Where the simulated lens sits: the display's image reaches the simulated eye through
    /// `[optics.layout]` and the viewer's prescription (identity without a layout). A
    /// calibration table is the rig's belief, not this: a wrong one shows as a focus error.
    /// The one lens's, or the left eye's.
    pub optics: dioptra_core::OpticsMap,
    /// The right eye's lens and where it sits, on a rig with a lens per eye.
    pub lens_right: Option<(LensModelConfig, dioptra_core::OpticsMap)>,
    /// The sync board simulator, with the lens it steps through the planes.
    pub board: dioptra_sim::sync_board::SyncBoardSimConfig,
    pub dlpc350: dioptra_sim::dlpc350::Dlpc350SimConfig,
    /// What the viewer looks at, and how the eyes move.
    pub gaze_scene: Scene,
    pub gaze: GeneratorConfig,
    /// Delay from exposure to delivery of each gaze report, µs: minimum and uniform jitter
    /// (USB polling and the tracker's processing).
    pub gaze_latency_us: (u64, u64),
    /// The simulated HID usage page 0x12 tracker's setup.
    pub hid_tracker: HidTrackerSetup,
    /// Keep the generator's ground truth (what the eyes really did) in
    /// [`SimDevices::gaze_truth`]; off in the daemon, where it would grow without bound.
    pub record_gaze_truth: bool,
    /// The simulated panel whose marker patch a simulated photodiode sees (with a simulated
    /// photodiode): the display presents to it.
    pub panel: Option<SharedPanel>,
    /// The simulated serial-line photodiode.
    pub serial_photodiode: SerialPhotodiodeSimConfig,
    /// A recorded gaze trace the simulated trackers replay instead of `gaze_scene` (`dioptra
    /// gaze --device sim:TRACE.csv`).
    pub gaze_trace: Option<Arc<Vec<dioptra_protocol::BinocularSample>>>,
}

impl SimSpec {
    /// The simulators' own defaults, for a device command that runs one in this process
    /// (`dioptra gaze --device sim:SCENARIO`, `dioptra sync --device dlpc350:sim`): no rig
    /// config, no simulated panel, gaze reports delivered with no added latency, the
    /// `fixation` scene.
    pub fn standalone() -> SimSpec {
        let range = dioptra_core::PowerRange::new(
            dioptra_core::Diopters(-10.0),
            dioptra_core::Diopters(10.0),
        )
        .expect("a non-empty range");
        SimSpec {
            lens: LensModelConfig::default(),
            optics: dioptra_core::OpticsMap::identity(range),
            lens_right: None,
            board: Default::default(),
            dlpc350: Default::default(),
            gaze_scene: Scene::named("fixation").expect("a scenario of the simulator"),
            gaze: GeneratorConfig::default(),
            gaze_latency_us: (0, 0),
            hid_tracker: HidTrackerSetup::default(),
            record_gaze_truth: false,
            panel: None,
            serial_photodiode: SerialPhotodiodeSimConfig::default(),
            gaze_trace: None,
        }
    }

    /// The simulated lens of lens `index` (0: the one lens or the left; 1: the right).
    pub fn lens_of(&self, index: usize) -> LensModelConfig {
        match (index, &self.lens_right) {
            (1, Some((l, _))) => *l,
            _ => self.lens,
        }
    }

    /// Where simulated lens `index` sits (see [`SimSpec::optics`]).
    pub fn optics_of(&self, index: usize) -> &dioptra_core::OpticsMap {
        match (index, &self.lens_right) {
            (1, Some((_, o))) => o,
            _ => &self.optics,
        }
    }

    /// The simulators a rig config describes (its `sim_*` keys); a simulated panel's light
    /// comes `display_latency` after its vsync unless `display.sim_photon_latency_ms` says
    /// otherwise (the scheduler's assumed display latency).
    pub fn from_config(cfg: &RigConfig, display_latency: Duration) -> Result<SimSpec, ConfigError> {
        let l = cfg.devices.lens.first();
        let g = &cfg.devices.gaze;
        let ms = |v: f64| Duration::from_secs_f64(v / 1000.0);
        let gaze_scene = Scene::named(&g.sim_scenario).ok_or_else(|| ConfigError::Invalid {
            key: "devices.gaze.sim_scenario".into(),
            message: format!("unknown scenario {:?}", g.sim_scenario),
        })?;
        let board_settle = cfg
            .devices
            .sync
            .as_ref()
            .map_or(SyncDevice::DEFAULT_SIM_SETTLE_MS, |s| s.sim_settle_ms);
        Ok(SimSpec {
            optics: cfg.simulated_optics(match cfg.devices.lens {
                Lenses::One(_) => None,
                Lenses::PerEye { .. } => Some(Side::Left),
            })?,
            lens: LensModelConfig {
                settle_time: ms(l.sim_settle_ms),
                ..Default::default()
            },
            lens_right: match &cfg.devices.lens {
                Lenses::PerEye { right, .. } => Some((
                    LensModelConfig {
                        settle_time: ms(right.sim_settle_ms),
                        ..Default::default()
                    },
                    cfg.simulated_optics(Some(Side::Right))?,
                )),
                Lenses::One(_) => None,
            },
            board: dioptra_sim::sync_board::SyncBoardSimConfig {
                lens: LensModelConfig {
                    settle_time: ms(board_settle),
                    ..Default::default()
                },
                ..Default::default()
            },
            dlpc350: dioptra_sim::dlpc350::Dlpc350SimConfig {
                vsync_hz: cfg
                    .devices
                    .sync
                    .as_ref()
                    .and_then(|s| s.video_hz)
                    .unwrap_or(SyncDevice::DEFAULT_VIDEO_HZ),
                ..Default::default()
            },
            gaze_scene,
            gaze: GeneratorConfig {
                rate_hz: g.sim_rate_hz,
                seed: g.sim_seed,
                ipd_mm: f64::from(cfg.eye.ipd_mm),
                ..Default::default()
            },
            gaze_latency_us: (1500, 500),
            hid_tracker: HidTrackerSetup::default(),
            record_gaze_truth: false,
            panel: cfg
                .devices
                .photodiode_simulated()
                .then(|| sim_panel(&cfg.display, display_latency)),
            serial_photodiode: SerialPhotodiodeSimConfig::default(),
            gaze_trace: None,
        })
    }
}

/// The simulated panel of `display`'s `sim_*` keys: its light `sim_photon_latency_ms` after
/// each vsync (default: `assumed`, the display latency the scheduler assumes), held or pulsed
/// (`sim_persistence_ms`), with `sim_dropped_refreshes` dropped.
pub fn sim_panel(d: &Display, assumed: Duration) -> SharedPanel {
    let ms = |v: f64| Duration::from_secs_f64(v / 1000.0);
    let panel = SharedPanel::new(PanelConfig {
        persistence: d.sim_persistence_ms.map(ms),
        ..PanelConfig::new(
            Duration::from_secs_f64(1.0 / d.frame_hz),
            d.sim_photon_latency_ms.map_or(assumed, ms),
        )
    });
    for n in &d.sim_dropped_refreshes {
        panel.lock().drop_refresh(*n);
    }
    panel
}

/// Plugs and unplugs a simulated device, as its cable would.
#[derive(Default)]
pub struct SimPlug {
    plugged: AtomicBool,
    /// Cuts the current connection.
    current: Mutex<Option<Cut>>,
    opened: std::sync::atomic::AtomicU32,
}

/// Breaks one open link to a simulator.
pub(crate) type Cut = Box<dyn FnOnce() + Send>;

impl std::fmt::Debug for SimPlug {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimPlug")
            .field("plugged", &self.is_plugged())
            .finish_non_exhaustive()
    }
}

impl SimPlug {
    pub(crate) fn new() -> Arc<Self> {
        Arc::new(SimPlug {
            plugged: AtomicBool::new(true),
            ..Default::default()
        })
    }
    pub fn is_plugged(&self) -> bool {
        self.plugged.load(Ordering::Acquire)
    }
    /// How many links were opened to the device (1 + reconnects).
    pub fn opened(&self) -> u32 {
        self.opened.load(Ordering::Acquire)
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
    /// Opens a link through `open` if plugged in, and keeps the way to cut it.
    pub(crate) fn open<L>(
        &self,
        what: &str,
        open: impl FnOnce() -> Result<(L, Cut), LinkError>,
    ) -> Result<L, LinkError> {
        if !self.is_plugged() {
            return Err(LinkError::Unavailable(format!(
                "the simulated {what} is unplugged"
            )));
        }
        let (link, cut) = open()?;
        if let Some(old) = lock(&self.current).replace(cut) {
            old();
        }
        self.opened.fetch_add(1, Ordering::AcqRel);
        Ok(link)
    }
}

/// The simulated lens of a rig, for tests and the API to look at.
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
    /// The lens model advanced to `now`: where the lens really is.
    pub fn at(&self, now: Timestamp) -> LensModel {
        match self {
            SimLens::Optotune(d) => {
                let mut d = lock(d);
                d.advance_to(now);
                d.lens().clone()
            }
            SimLens::Controller(d) => {
                let mut d = lock(d);
                d.advance_to(now);
                d.lens().clone()
            }
        }
    }
}

/// One simulated device of a rig.
#[derive(Clone)]
pub struct SimSlot {
    pub plug: Arc<SimPlug>,
    /// The lens, for the lens slot.
    pub lens: Option<SimLens>,
    /// The simulated Pupil Capture, for a gaze slot with `driver = "pupil"`.
    pub pupil: Option<SimPupilCapture>,
}

/// Makes the gaze a new simulated Capture publishes.
pub(crate) type MakeGaze = Box<dyn FnMut() -> Result<Box<dyn SampleSource>, LinkError> + Send>;

/// The simulated Pupil Capture of a rig (`driver = "pupil"`, `port = "sim"`): a separate
/// "process" on loopback TCP that the driver reaches by address, as it would a real one.
/// Connecting starts it if it is not running; unplugging quits it; [`SimPupilCapture::restart`]
/// quits it and starts a new one on the same Pupil Remote port (new IPC ports, new time
/// base), as a lab restarting Capture does.
#[derive(Clone)]
pub struct SimPupilCapture(Arc<Mutex<PupilSlot>>);

struct PupilSlot {
    running: Option<dioptra_sim::gaze::pupil_capture::PupilCaptureSim>,
    /// Pupil Remote's port, kept across restarts (0 until the first start).
    port: u16,
    /// Starts so far; each start gets its own Pupil time base.
    starts: u32,
    /// The connection that may quit the running Capture when its link is cut.
    owner: u64,
    opened: u64,
    gaze: MakeGaze,
}

impl SimPupilCapture {
    pub(crate) fn new(gaze: MakeGaze) -> Self {
        SimPupilCapture(Arc::new(Mutex::new(PupilSlot {
            running: None,
            port: 0,
            starts: 0,
            owner: 0,
            opened: 0,
            gaze,
        })))
    }

    /// Pupil Remote's port once started.
    pub fn remote_port(&self) -> Option<u16> {
        let s = lock(&self.0);
        (s.port != 0).then_some(s.port)
    }

    /// The running Capture's IPC publisher port (`SUB_PORT`), if running.
    pub fn sub_port(&self) -> Option<u16> {
        lock(&self.0).running.as_ref().map(|c| c.sub_port())
    }

    /// Times Capture was started.
    pub fn starts(&self) -> u32 {
        lock(&self.0).starts
    }

    fn start(slot: &mut PupilSlot) -> Result<(), LinkError> {
        use dioptra_sim::gaze::pupil_capture::{PupilCaptureConfig, PupilCaptureSim};
        let source = (slot.gaze)()?;
        let cfg = PupilCaptureConfig {
            remote_port: slot.port,
            // Each Capture has its own arbitrary clock base.
            pupil_time_at_start_s: 3000.0 + 1000.0 * f64::from(slot.starts),
            ..Default::default()
        };
        let sim = PupilCaptureSim::spawn(cfg, source).map_err(|e| {
            LinkError::Unavailable(format!(
                "the simulated Pupil Capture cannot bind port {}: {e}",
                slot.port
            ))
        })?;
        slot.port = sim.remote_addr().port();
        slot.starts += 1;
        slot.running = Some(sim);
        Ok(())
    }

    /// Quits Capture and starts a new one on the same Pupil Remote port, waiting (up to 5 s)
    /// for the old port to close.
    pub async fn restart(&self) -> Result<(), LinkError> {
        let old = lock(&self.0).running.take();
        if let Some(old) = old {
            old.shutdown().await;
        }
        let mut last = None;
        for _ in 0..250 {
            match Self::start(&mut lock(&self.0)) {
                Ok(()) => return Ok(()),
                Err(e) => last = Some(e),
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        Err(last.unwrap_or_else(|| LinkError::Unavailable("no restart attempted".into())))
    }

    /// A link for a new connection: Pupil Remote's address (Capture started if need be), and
    /// the cut that quits Capture while this connection is the newest.
    pub(crate) fn open(&self) -> Result<(SimLink, Cut), LinkError> {
        let mut s = lock(&self.0);
        if s.running.is_none() {
            Self::start(&mut s)?;
        }
        s.opened += 1;
        s.owner = s.opened;
        let (me, addr) = (s.opened, format!("127.0.0.1:{}", s.port));
        let slot = self.0.clone();
        let cut: Cut = Box::new(move || {
            let mut s = lock(&slot);
            if s.owner == me {
                // Dropping it stops its tasks; the ports close as they end.
                s.running = None;
            }
        });
        Ok((SimLink::Net(addr), cut))
    }
}

/// What the generator of the simulated tracker really did, on the rig's clock.
pub type GazeTruth = Arc<Mutex<Vec<TruthSample>>>;

/// Handles on the simulated devices of a rig (empty for hardware).
#[derive(Clone, Default)]
pub struct SimDevices {
    /// Each lens's simulator (by lens id), where it is simulated.
    pub lenses: Vec<Option<SimSlot>>,
    pub gaze: Option<SimSlot>,
    pub sync: Option<SimSlot>,
    pub photodiode: Option<SimSlot>,
    /// The simulated panel a simulated photodiode watches: what it showed, refresh by refresh.
    pub panel: Option<SharedPanel>,
    /// With [`SimSpec::record_gaze_truth`].
    pub gaze_truth: Option<GazeTruth>,
}

/// A link to a simulator: the kind its driver talks over.
pub enum SimLink {
    Byte(AnyByteLink),
    Hid(AnyHidLink),
    /// A network address ("host:port") the simulator serves on.
    Net(String),
}

/// Opens links to one simulated device, each time it is (re)connected.
pub(crate) struct SimEndpoint {
    pub open: Box<dyn FnMut() -> Result<(SimLink, Cut), LinkError> + Send>,
    pub lens: Option<SimLens>,
    pub gaze_truth: Option<GazeTruth>,
    pub pupil: Option<SimPupilCapture>,
    /// The simulated DLPC350 of the newest link.
    pub projector: Option<SimProjector>,
}

impl Default for SimEndpoint {
    /// No simulator: every open fails.
    fn default() -> Self {
        SimEndpoint {
            open: Box::new(|| Err(LinkError::Unavailable("no simulator".into()))),
            lens: None,
            gaze_truth: None,
            pupil: None,
            projector: None,
        }
    }
}

/// The simulated DLPC350 of a device's newest link (each link gets a new projector).
pub(crate) type SimProjector = Arc<Mutex<Option<Arc<dioptra_sim::dlpc350::Dlpc350Sim>>>>;

/// A byte-speaking simulator shared by every link opened to it, served on `clock`.
pub(crate) fn byte_endpoint<D: ByteDevice + Send + 'static>(
    what: &'static str,
    device: Arc<Mutex<D>>,
    clock: Arc<dyn Clock>,
) -> impl FnMut() -> Result<(SimLink, Cut), LinkError> + Send {
    move || {
        let (host, mut end) = memory::pair(4096);
        let faults = end.faults();
        let mut device = device.clone();
        let clock = clock.clone();
        tokio::spawn(async move {
            let _ = dioptra_sim::serve::serve(&mut end, &mut device, clock.as_ref()).await;
        });
        let cut: Cut = Box::new(move || faults.disconnect("unplugged"));
        Ok((
            SimLink::Byte(host.named(format!("simulated {what}")).into()),
            cut,
        ))
    }
}

/// A gaze generator that also records what the eyes really did, on the rig's clock.
pub(crate) struct RecordedGaze {
    pub gen: GazeGenerator,
    pub truth: GazeTruth,
    /// Rig time of the generator's first sample.
    pub origin_us: u64,
}

impl SampleSource for RecordedGaze {
    fn next_sample(&mut self) -> Option<(u64, dioptra_protocol::BinocularSample)> {
        let mut s = self.gen.next_truth();
        let reported = (s.time_us, s.reported);
        s.time_us += self.origin_us;
        lock(&self.truth).push(s);
        Some(reported)
    }
    fn rate_hz(&self) -> f64 {
        self.gen.rate_hz()
    }
}
