//! The rig config (`rig.toml`): devices, optics, eye model, mode, method, display, API and
//! recording. Parsing is strict (`deny_unknown_fields`) and every error names the key and the
//! form it expects, e.g. `optics.lens_range: min must be below max`.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use dioptra_core::optics_map::{
    CalibrationTable, OpticsError, OpticsMap, Prescription, ThinLensLayout,
};
use dioptra_core::{Diopters, PowerRange, Side};
use dioptra_sched::RenderMethod;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// What went wrong with a rig config. `key` is the dotted path of the offending key.
#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("cannot read the rig config {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{key}: {message}")]
    Parse { key: String, message: String },
    #[error("{key}: {message}")]
    Invalid { key: String, message: String },
}

impl ConfigError {
    /// The dotted key the error is about (`.` for the whole file).
    #[cfg(test)]
    pub fn key(&self) -> &str {
        match self {
            ConfigError::Read { .. } => ".",
            ConfigError::Parse { key, .. } | ConfigError::Invalid { key, .. } => key,
        }
    }
}

fn invalid(key: &str, message: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        key: key.to_string(),
        message: message.into(),
    }
}

/// How the display shows depth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    Varifocal,
    Multifocal,
    Lightfield,
}

impl Mode {
    pub fn parse(s: &str) -> Option<Mode> {
        match s {
            "varifocal" => Some(Mode::Varifocal),
            "multifocal" => Some(Mode::Multifocal),
            "lightfield" => Some(Mode::Lightfield),
            _ => None,
        }
    }
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Varifocal => "varifocal",
            Mode::Multifocal => "multifocal",
            Mode::Lightfield => "lightfield",
        }
    }
}

impl Mode {
    pub fn from_sched(m: dioptra_sched::Mode) -> Mode {
        match m {
            dioptra_sched::Mode::Varifocal => Mode::Varifocal,
            dioptra_sched::Mode::Multifocal => Mode::Multifocal,
            dioptra_sched::Mode::LightField => Mode::Lightfield,
        }
    }
    /// The scheduler's name for this mode.
    pub fn sched(self) -> dioptra_sched::Mode {
        match self {
            Mode::Varifocal => dioptra_sched::Mode::Varifocal,
            Mode::Multifocal => dioptra_sched::Mode::Multifocal,
            Mode::Lightfield => dioptra_sched::Mode::LightField,
        }
    }
}

/// The render method, by the scheduler's names: gather, lightfield-defocus (varifocal);
/// linear, optimized (multifocal); views (light field); network (any).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct Method(pub RenderMethod);

impl TryFrom<String> for Method {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        Method::parse(&s)
            .ok_or_else(|| {
                format!("unknown method {s:?}: expected one of {}, or auto (varifocal: the planner chooses per frame)", methods())
            })
    }
}

impl From<Method> for String {
    fn from(m: Method) -> String {
        m.as_str().into()
    }
}

/// The methods the daemon renders.
pub const RENDERED: &str = "gather, lightfield-defocus, network or refine (varifocal), linear, \
     optimized, spectral, network or refine (multifocal), views or refine (light field)";

/// Every method's name, for messages.
pub fn methods() -> String {
    RenderMethod::ALL
        .iter()
        .map(|m| m.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

impl Method {
    pub fn parse(s: &str) -> Option<Method> {
        s.parse::<RenderMethod>().ok().map(Method)
    }
    pub fn as_str(self) -> &'static str {
        self.0.as_str()
    }
    /// Whether this method makes images for `mode`.
    pub fn fits(self, mode: Mode) -> bool {
        self.0.suits(mode.sched())
    }
    /// Why the daemon cannot render with this method in `mode`, if it cannot (the network's
    /// weights are checked when the daemon starts: [`crate::render::rgbd::RgbdRenderer::new`]).
    pub fn unavailable(self, mode: Mode) -> Option<String> {
        match (self.0, mode) {
            (RenderMethod::Network, Mode::Lightfield) => Some(format!(
                "{} in lightfield mode (C5 views) is not rendered by `dioptra serve`; use {}",
                self.as_str(),
                RENDERED
            )),
            _ => None,
        }
    }
    /// The methods that fit `mode`, for messages.
    pub fn for_mode(mode: Mode) -> String {
        RenderMethod::ALL
            .iter()
            .filter(|m| m.suits(mode.sched()))
            .map(|m| m.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// A device of the config, as the rig opens it.
#[derive(Debug, Clone, PartialEq)]
pub struct ConfiguredDevice {
    /// Its name in `/status`'s `devices`: lens (lens_left, lens_right), gaze, sync.
    pub name: String,
    /// Its config section: `devices.lens` (`devices.lens.left`, ...), ...
    pub section: String,
    pub port: Port,
    pub required: bool,
}

impl Devices {
    /// The configured devices, lenses first.
    pub fn list(&self) -> Vec<ConfiguredDevice> {
        let dev =
            |name: String, section: String, port: &Port, required: Option<bool>| ConfiguredDevice {
                name,
                section,
                port: port.clone(),
                required: required.unwrap_or(*port != Port::Sim),
            };
        let mut v: Vec<_> = self
            .lens
            .each()
            .into_iter()
            .enumerate()
            .map(|(i, l)| dev(self.lens.name(i), self.lens.key(i), &l.port, l.required))
            .collect();
        v.push(dev(
            "gaze".into(),
            "devices.gaze".into(),
            &self.gaze.port,
            self.gaze.required,
        ));
        if let Some(s) = &self.sync {
            v.push(dev(
                "sync".into(),
                "devices.sync".into(),
                &s.port,
                s.required,
            ));
        }
        v
    }
}

/// Where a device is: simulated in-process, a device path, a USB/HID VID:PID, a USB device's
/// bulk endpoints, or a network address (Pupil Capture's Pupil Remote).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum Port {
    Sim,
    Path(PathBuf),
    VidPid(u16, u16),
    /// "usb" or "usb:SERIAL": the driver's USB device over its bulk endpoints (the dioptra lens
    /// controller), the one plugged in or the one with that serial number.
    Usb(Option<String>),
    /// "host:port": an IP literal (IPv6 in brackets), "localhost", or a host name with a dot.
    Net(String),
}

impl TryFrom<String> for Port {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        if s == "sim" {
            return Ok(Port::Sim);
        }
        if s.starts_with('/') {
            return Ok(Port::Path(PathBuf::from(s)));
        }
        if s == "usb" {
            return Ok(Port::Usb(None));
        }
        if let Some(serial) = s.strip_prefix("usb:") {
            if serial.is_empty() || !serial.bytes().all(|b| b.is_ascii_graphic()) {
                return Err(format!(
                    "invalid port {s:?}: \"usb\" takes the device's serial number after a colon, \"usb:SERIAL\""
                ));
            }
            return Ok(Port::Usb(Some(serial.to_string())));
        }
        if let Some((v, p)) = s.split_once(':') {
            let hex = |x: &str| (x.len() == 4).then(|| u16::from_str_radix(x, 16).ok())?;
            if let (Some(v), Some(p)) = (hex(v), hex(p)) {
                return Ok(Port::VidPid(v, p));
            }
        }
        if is_network_address(&s) {
            return Ok(Port::Net(s));
        }
        Err(format!(
            "invalid port {s:?}: expected \"sim\", a device path such as \"/dev/ttyACM0\", \
             a USB VID:PID in hex such as \"1209:d10a\", \"usb\" or \"usb:SERIAL\" (USB bulk \
             endpoints), or a network address host:port such as \"127.0.0.1:50020\" or \
             \"localhost:50020\""
        ))
    }
}

/// "host:port" with a decimal port: an IP literal, "localhost", or a host name with a dot
/// (so "1209:d10a" stays a VID:PID and a typo of one is not taken for a host).
fn is_network_address(s: &str) -> bool {
    let Some((host, port)) = s.rsplit_once(':') else {
        return false;
    };
    let port_ok = !port.is_empty()
        && port.bytes().all(|b| b.is_ascii_digit())
        && port.parse::<u16>().is_ok_and(|p| p > 0);
    let host_ok = if let Some(v6) = host.strip_prefix('[').and_then(|h| h.strip_suffix(']')) {
        v6.parse::<std::net::Ipv6Addr>().is_ok()
    } else {
        host.parse::<std::net::Ipv4Addr>().is_ok()
            || host == "localhost"
            || (host.contains('.')
                && !host.starts_with('.')
                && !host.ends_with('.')
                && host.split('.').all(|l| {
                    !l.is_empty() && l.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-')
                }))
    };
    port_ok && host_ok
}

impl From<Port> for String {
    fn from(p: Port) -> String {
        match p {
            Port::Sim => "sim".into(),
            Port::Path(p) => p.display().to_string(),
            Port::VidPid(v, p) => format!("{v:04x}:{p:04x}"),
            Port::Usb(None) => "usb".into(),
            Port::Usb(Some(serial)) => format!("usb:{serial}"),
            Port::Net(a) => a,
        }
    }
}

impl std::fmt::Display for Port {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&String::from(self.clone()))
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LensDriver {
    /// Optotune Lens Driver 4.
    Optotune,
    /// The dioptra lens controller.
    Lens,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GazeDriver {
    /// The dioptra binocular tracker.
    DioptraTracker,
    /// A HID usage page 0x12 eye tracker.
    Hid,
    /// Pupil Core, through Pupil Capture's network API (Pupil Remote's address as the port).
    Pupil,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SyncDriver {
    /// The dioptra sync board.
    Sync,
    /// A TI DLPC350 (LightCrafter 4500) in pattern mode on its video port, over USB HID.
    Dlpc350,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LensDevice {
    pub driver: LensDriver,
    pub port: Port,
    /// Power the lens is parked at on shutdown, diopters (inside `optics.lens_range`).
    pub park_power: f32,
    /// Settle time of the simulated lens, ms (sim only).
    #[serde(default = "default_settle_ms")]
    pub sim_settle_ms: f64,
    /// How long the lens takes to settle after a step, ms: the scheduler's model of the lens
    /// (its predicted power, which the renderer's focus follows). Default: `sim_settle_ms`
    /// for a simulated lens, [`LensDevice::DEFAULT_SETTLE_MS`] for a real one.
    pub settle_ms: Option<f64>,
    /// How often the lens is read back, ms.
    #[serde(default = "default_lens_poll_ms")]
    pub poll_ms: f64,
    /// Optotune only: the lens's temperature limits `[lower, upper]`, °C, sent at every
    /// connect (`PwTA`); the device's focal-power range follows from them. Default 20-40 °C.
    pub temperature_limits_c: Option<[f32; 2]>,
    /// Whether the rig needs the device present: `serve` does not start without it, and
    /// while a required lens is down `POST /focus` answers 503. Default: true for a real port,
    /// false for `port = "sim"` (always present).
    pub required: Option<bool>,
}

impl LensDevice {
    /// A real lens's settle time when `settle_ms` is not given: the Optotune EL-10-30's
    /// datasheet settling time (hardware.md); measure yours (`dioptra lens set D --watch-ms`).
    pub const DEFAULT_SETTLE_MS: f64 = 15.0;

    /// The settle time the scheduler models this lens with, ms.
    pub fn model_settle_ms(&self) -> f64 {
        self.settle_ms.unwrap_or(if self.port == Port::Sim {
            self.sim_settle_ms
        } else {
            Self::DEFAULT_SETTLE_MS
        })
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GazeDevice {
    pub driver: GazeDriver,
    pub port: Port,
    /// Scenario of the simulated tracker (sim only): saccades, fixation, pursuit, vergence, blinks.
    #[serde(default = "default_scenario")]
    pub sim_scenario: String,
    /// Whether the rig needs the device present: `serve` does not start without it, and
    /// while a required lens is down `POST /focus` answers 503. Default: true for a real port,
    /// false for `port = "sim"` (always present).
    pub required: Option<bool>,
    /// Sample rate of the simulated tracker, Hz (sim only).
    #[serde(default = "default_gaze_rate")]
    pub sim_rate_hz: f64,
    /// Seed of the simulated tracker (sim only).
    #[serde(default = "default_seed")]
    pub sim_seed: u64,
    /// Pupil only: gaze below this confidence (0 to 1) is a dropout; Pupil Labs recommend 0.6.
    #[serde(default = "default_min_confidence")]
    pub min_confidence: f32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyncDevice {
    pub driver: SyncDriver,
    pub port: Port,
    /// Whether the rig needs the device present: `serve` does not start without it, and
    /// while a required lens is down `POST /focus` answers 503. Default: true for a real port,
    /// false for `port = "sim"` (always present).
    pub required: Option<bool>,
    /// DLPC350 only: frame rate of the video the projector receives, Hz; each VSYNC starts
    /// one pass over the planes (default 60).
    pub video_hz: Option<f64>,
    /// Settle time of the lens the simulated sync board steps through the planes, ms (sim
    /// only; a multifocal lens must settle within a sub-frame's dark allowance).
    #[serde(default = "default_sync_settle_ms")]
    pub sim_settle_ms: f64,
}

impl SyncDevice {
    /// The DLPC350's video rate when none is configured, Hz.
    pub const DEFAULT_VIDEO_HZ: f64 = 60.0;
    /// The simulated multifocal lens's settle time when none is configured, ms: within the
    /// dark quarter of a 240 Hz sub-frame (1.04 ms), with room for the largest plane step.
    pub const DEFAULT_SIM_SETTLE_MS: f64 = 0.8;

    /// The DLPC350 driver's configuration (the video rate; the rest at the driver's defaults).
    pub fn dlpc350_config(&self) -> dioptra_sync::dlpc350::Dlpc350Config {
        dioptra_sync::dlpc350::Dlpc350Config {
            vsync_hz: self.video_hz.unwrap_or(Self::DEFAULT_VIDEO_HZ),
            ..Default::default()
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PhotodiodeDriver {
    /// A microcontroller with a photodiode and a comparator, speaking the serial line protocol
    /// (firmware-protocol/photodiode/README.md).
    SerialLine,
    /// The dioptra sync board's photodiode input.
    Sync,
}

/// A light sensor over the display's marker patch, for `dioptra hil`'s optical figures.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhotodiodeDevice {
    pub driver: PhotodiodeDriver,
    /// `serial-line`: the microcontroller's port, or "sim". `sync`: none to use the input of
    /// the board of `[devices.sync]`; a port for a board used only for its photodiode.
    pub port: Option<Port>,
    /// `sync` only: the comparator's threshold and half band, fractions of the sensor's full
    /// scale (a serial-line board's comparator is set by its own trimmer).
    pub threshold: Option<f32>,
    pub hysteresis: Option<f32>,
}

impl PhotodiodeDevice {
    /// The sync board's comparator band.
    pub fn band(&self) -> dioptra_sync::board::PhotodiodeBand {
        let d = dioptra_sync::board::PhotodiodeBand::default();
        dioptra_sync::board::PhotodiodeBand {
            threshold: self.threshold.unwrap_or(d.threshold),
            hysteresis: self.hysteresis.unwrap_or(d.hysteresis),
        }
    }

    /// Whether it is the input of the `[devices.sync]` board rather than a device of its own.
    pub fn on_sync_board(&self) -> bool {
        self.driver == PhotodiodeDriver::Sync && self.port.is_none()
    }
}

/// An eye (`left`/`right`) in serialized records: core's [`Side`], which has no serde.
pub mod side_serde {
    use dioptra_core::Side;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(side: &Option<Side>, s: S) -> Result<S::Ok, S::Error> {
        side.map(Side::as_str).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Side>, D::Error> {
        match Option::<String>::deserialize(d)? {
            None => Ok(None),
            Some(s) => Side::parse(&s).map(Some).ok_or_else(|| {
                serde::de::Error::custom(format!("{s:?}: expected \"left\" or \"right\""))
            }),
        }
    }
}

/// `[devices.lens]`: one lens (a monocular bench, or one lens both eyes look through), or a
/// lens per eye in `[devices.lens.left]` and `[devices.lens.right]`, each a full lens section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "LensSection", into = "LensSection")]
pub enum Lenses {
    One(LensDevice),
    PerEye { left: LensDevice, right: LensDevice },
}

impl Lenses {
    /// Each lens in the order of the lens tasks and the scheduler's lens ids: the one lens,
    /// or the left then the right.
    pub fn each(&self) -> Vec<&LensDevice> {
        match self {
            Lenses::One(l) => vec![l],
            Lenses::PerEye { left, right } => vec![left, right],
        }
    }
    pub fn count(&self) -> usize {
        match self {
            Lenses::One(_) => 1,
            Lenses::PerEye { .. } => 2,
        }
    }
    /// The one lens, or the left eye's.
    pub fn first(&self) -> &LensDevice {
        match self {
            Lenses::One(l) => l,
            Lenses::PerEye { left, .. } => left,
        }
    }
    /// The one lens, or the left eye's, to change.
    pub fn first_mut(&mut self) -> &mut LensDevice {
        match self {
            Lenses::One(l) => l,
            Lenses::PerEye { left, .. } => left,
        }
    }
    /// The eye lens `index` is in front of (`None`: the one lens, in front of both).
    pub fn side(&self, index: usize) -> Option<Side> {
        match (self, index) {
            (Lenses::PerEye { .. }, 0) => Some(Side::Left),
            (Lenses::PerEye { .. }, _) => Some(Side::Right),
            (Lenses::One(_), _) => None,
        }
    }
    /// Lens `index`'s config key: `devices.lens`, `devices.lens.left` or `devices.lens.right`.
    pub fn key(&self, index: usize) -> String {
        match self.side(index) {
            None => "devices.lens".into(),
            Some(e) => format!("devices.lens.{}", e.as_str()),
        }
    }
    /// Lens `index`'s name in `/status` and the device registry: `lens`, `lens_left`,
    /// `lens_right`.
    pub fn name(&self, index: usize) -> String {
        match self.side(index) {
            None => "lens".into(),
            Some(e) => format!("lens_{}", e.as_str()),
        }
    }
}

/// `[devices.lens]` as written: one lens's keys, or a `left` and a `right` table.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct LensSection {
    #[serde(skip_serializing_if = "Option::is_none")]
    driver: Option<LensDriver>,
    #[serde(skip_serializing_if = "Option::is_none")]
    port: Option<Port>,
    #[serde(skip_serializing_if = "Option::is_none")]
    park_power: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    sim_settle_ms: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    settle_ms: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    poll_ms: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    temperature_limits_c: Option<[f32; 2]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    required: Option<bool>,
    #[serde(skip_serializing_if = "Option::is_none")]
    left: Option<LensDevice>,
    #[serde(skip_serializing_if = "Option::is_none")]
    right: Option<LensDevice>,
}

impl TryFrom<LensSection> for Lenses {
    type Error = String;
    fn try_from(s: LensSection) -> Result<Lenses, String> {
        let one_keys = [
            ("driver", s.driver.is_some()),
            ("port", s.port.is_some()),
            ("park_power", s.park_power.is_some()),
            ("sim_settle_ms", s.sim_settle_ms.is_some()),
            ("settle_ms", s.settle_ms.is_some()),
            ("poll_ms", s.poll_ms.is_some()),
            ("temperature_limits_c", s.temperature_limits_c.is_some()),
            ("required", s.required.is_some()),
        ];
        match (s.left, s.right) {
            (Some(left), Some(right)) => {
                if let Some((k, _)) = one_keys.iter().find(|(_, set)| *set) {
                    return Err(format!(
                        "{k}: with [devices.lens.left] and [devices.lens.right], each lens's keys go in its own table (devices.lens.left.{k}, devices.lens.right.{k})"
                    ));
                }
                Ok(Lenses::PerEye { left, right })
            }
            (None, Some(_)) => Err(
                "right: a right lens without a left one: add [devices.lens.left], or give one lens in [devices.lens] (a monocular bench, or one lens both eyes look through)".into(),
            ),
            (Some(_), None) => Err(
                "left: a left lens without a right one: add [devices.lens.right], or give one lens in [devices.lens] (a monocular bench, or one lens both eyes look through)".into(),
            ),
            (None, None) => {
                let missing = |k: &str| {
                    format!("missing field `{k}` (one lens: driver, port and park_power; a lens per eye: [devices.lens.left] and [devices.lens.right])")
                };
                Ok(Lenses::One(LensDevice {
                    driver: s.driver.ok_or_else(|| missing("driver"))?,
                    port: s.port.ok_or_else(|| missing("port"))?,
                    park_power: s.park_power.ok_or_else(|| missing("park_power"))?,
                    sim_settle_ms: s.sim_settle_ms.unwrap_or_else(default_settle_ms),
                    settle_ms: s.settle_ms,
                    poll_ms: s.poll_ms.unwrap_or_else(default_lens_poll_ms),
                    temperature_limits_c: s.temperature_limits_c,
                    required: s.required,
                }))
            }
        }
    }
}

impl From<Lenses> for LensSection {
    fn from(l: Lenses) -> LensSection {
        match l {
            Lenses::One(l) => LensSection {
                driver: Some(l.driver),
                port: Some(l.port),
                park_power: Some(l.park_power),
                sim_settle_ms: Some(l.sim_settle_ms),
                settle_ms: l.settle_ms,
                poll_ms: Some(l.poll_ms),
                temperature_limits_c: l.temperature_limits_c,
                required: l.required,
                ..LensSection::default()
            },
            Lenses::PerEye { left, right } => LensSection {
                left: Some(left),
                right: Some(right),
                ..LensSection::default()
            },
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Devices {
    /// One lens, or a lens per eye.
    pub lens: Lenses,
    pub gaze: GazeDevice,
    /// Needed for multifocal mode.
    pub sync: Option<SyncDevice>,
    /// A photodiode over `display.marker_patch`: `dioptra hil` measures in photons with it.
    pub photodiode: Option<PhotodiodeDevice>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Range {
    pub min: f32,
    pub max: f32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Optics {
    /// Powers the rig may drive the lens to, diopters.
    pub lens_range: Range,
    /// Multifocal plane powers in display order, diopters.
    #[serde(default = "default_planes")]
    pub planes: Vec<f32>,
    /// Multifocal sub-frame rate, Hz (one plane per sub-frame).
    #[serde(default = "default_subframe_hz")]
    pub subframe_hz: f64,
    /// Where `[optics.layout]`'s `display_distance_m` was before the optics map: it was read
    /// nowhere. Still accepted (and ignored, with a notice at start) so old configs load.
    pub display_distance_m: Option<f32>,
    /// Both eyes' thin-lens layout, unless an eye's section has its own.
    pub layout: Option<Layout>,
    /// Both eyes' calibration table (`dioptra lens calibrate` writes it), relative to the
    /// config file.
    pub calibration: Option<PathBuf>,
    /// Both eyes' spectacle sphere, diopters (a myope's is negative).
    pub prescription_sphere_d: Option<f64>,
    /// Refused unless 0: a spherical lens cannot correct astigmatism.
    pub prescription_cylinder_d: Option<f64>,
    /// The vertex distance the prescription was written for, mm (default 12).
    pub prescription_vertex_mm: Option<f64>,
    /// The left eye's own settings, each overriding the shared one.
    pub left: Option<EyeOptics>,
    pub right: Option<EyeOptics>,
}

/// `[optics.layout]`: where the display, the tunable lens and the eye's pupil are, as thin
/// lenses (the demand is `A = (1/d - P) / (1 + s (1/d - P))`, P = fixed + tunable power).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Layout {
    /// Display to the tunable lens, metres.
    pub display_distance_m: f64,
    /// Tunable lens to the eye's pupil, metres (0: the lens at the pupil, or imaged onto it).
    pub eye_relief_m: f64,
    /// A fixed lens (an eyepiece) at the tunable lens, diopters.
    #[serde(default)]
    pub fixed_power_d: f64,
}

/// `[optics.left]` / `[optics.right]`: one eye's optics, each key overriding `[optics]`'s.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EyeOptics {
    pub layout: Option<Layout>,
    pub calibration: Option<PathBuf>,
    pub prescription_sphere_d: Option<f64>,
    pub prescription_cylinder_d: Option<f64>,
    pub prescription_vertex_mm: Option<f64>,
}

/// One eye's optics settings with where each came from (`optics` or `optics.left`...).
struct ResolvedOptics<'a> {
    layout: Option<(&'a Layout, &'static str)>,
    calibration: Option<(&'a PathBuf, &'static str)>,
    sphere: Option<(f64, &'static str)>,
    cylinder: Option<(f64, &'static str)>,
    vertex_mm: Option<(f64, &'static str)>,
}

impl Optics {
    /// `[optics]`'s own eye settings.
    fn shared(&self) -> EyeOptics {
        EyeOptics {
            layout: self.layout,
            calibration: self.calibration.clone(),
            prescription_sphere_d: self.prescription_sphere_d,
            prescription_cylinder_d: self.prescription_cylinder_d,
            prescription_vertex_mm: self.prescription_vertex_mm,
        }
    }

    fn eye(&self, side: Side) -> Option<&EyeOptics> {
        match side {
            Side::Left => self.left.as_ref(),
            Side::Right => self.right.as_ref(),
        }
    }

    /// The eye whose section stands for a one-lens rig's lens: the one per-eye section given
    /// (a monocular bench), or none (the shared settings).
    pub fn one_lens_eye(&self) -> Option<Side> {
        match (&self.left, &self.right) {
            (Some(_), None) => Some(Side::Left),
            (None, Some(_)) => Some(Side::Right),
            _ => None,
        }
    }
}

fn resolve<'a>(
    shared: &'a EyeOptics,
    eye: Option<(&'a EyeOptics, &'static str)>,
) -> ResolvedOptics<'a> {
    fn pick<'a, T>(
        eye: Option<(&'a EyeOptics, &'static str)>,
        shared: &'a EyeOptics,
        get: impl Fn(&'a EyeOptics) -> Option<T>,
    ) -> Option<(T, &'static str)> {
        eye.and_then(|(e, key)| get(e).map(|v| (v, key)))
            .or_else(|| get(shared).map(|v| (v, "optics")))
    }
    ResolvedOptics {
        layout: pick(eye, shared, |e| e.layout.as_ref()),
        calibration: pick(eye, shared, |e| e.calibration.as_ref()),
        sphere: pick(eye, shared, |e| e.prescription_sphere_d),
        cylinder: pick(eye, shared, |e| e.prescription_cylinder_d),
        vertex_mm: pick(eye, shared, |e| e.prescription_vertex_mm),
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Eye {
    #[serde(default = "default_pupil")]
    pub pupil_mm: f32,
    #[serde(default = "default_fov")]
    pub fov_deg: f32,
    #[serde(default = "default_ipd")]
    pub ipd_mm: f32,
}

impl Default for Eye {
    fn default() -> Self {
        Eye {
            pupil_mm: default_pupil(),
            fov_deg: default_fov(),
            ipd_mm: default_ipd(),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SinkKind {
    /// Frame timing (and optionally PNGs) recorded, nothing shown: tests, CI.
    Headless,
    /// A borderless fullscreen window on `display.monitor`, vsync (rigs).
    Window,
}

/// Where the eyes' images go (`display.layout`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DisplayLayout {
    /// One image: a monocular bench, or one view both eyes see.
    #[default]
    One,
    /// One panel, 2 x `display.width` wide: the left eye's image in the left half.
    SideBySide,
    /// A window per eye (`monitor_left`, `monitor_right`); headless: an image per eye.
    TwoOutputs,
}

impl DisplayLayout {
    pub fn as_str(self) -> &'static str {
        match self {
            DisplayLayout::One => "one",
            DisplayLayout::SideBySide => "side-by-side",
            DisplayLayout::TwoOutputs => "two-outputs",
        }
    }
    /// Whether each eye gets its own image.
    pub fn stereo(self) -> bool {
        self != DisplayLayout::One
    }
}

/// How an eye's image meets panel pixels (`display.scale`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Scale {
    /// 1:1 onto panel pixels, so a stimulus subtends the angle it was rendered for; an image
    /// that does not fit its place is reported and not shown.
    #[default]
    Exact,
    /// Scaled to fit its place, aspect kept (letterboxed).
    Fit,
}

impl Scale {
    pub fn as_str(self) -> &'static str {
        match self {
            Scale::Exact => "exact",
            Scale::Fit => "fit",
        }
    }
}

/// `display.eye_offset_px`: each eye's image moved from the centre of its place, pixels
/// (+x right, +y down).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EyeOffsets {
    #[serde(default)]
    pub left: [i32; 2],
    #[serde(default)]
    pub right: [i32; 2],
}

impl EyeOffsets {
    pub fn of(&self, side: Side) -> [i32; 2] {
        match side {
            Side::Left => self.left,
            Side::Right => self.right,
        }
    }
}

/// Which monitor the window goes on: its name as the system gives it (e.g. `"HDMI-1"`), or
/// its index in the system's list.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(
    untagged,
    expecting = "a monitor name such as \"HDMI-1\" or an index such as 0"
)]
pub enum MonitorChoice {
    Index(usize),
    Name(String),
}

impl std::fmt::Display for MonitorChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MonitorChoice::Index(i) => write!(f, "{i}"),
            MonitorChoice::Name(n) => write!(f, "{n:?}"),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Display {
    /// `headless` or `window` (`sink` is the older name of this key).
    #[serde(default = "default_sink", alias = "sink")]
    pub kind: SinkKind,
    /// The window's monitor: a name such as "HDMI-1" or an index; default the primary.
    pub monitor: Option<MonitorChoice>,
    /// `layout = "two-outputs"`: the left and the right eye's monitors.
    pub monitor_left: Option<MonitorChoice>,
    pub monitor_right: Option<MonitorChoice>,
    /// One eye's image (per eye on a stereo layout), pixels.
    #[serde(default = "default_size")]
    pub width: u32,
    #[serde(default = "default_size")]
    pub height: u32,
    /// Where the eyes' images go: `one` (one image), `side-by-side` (one panel 2 x width
    /// wide, the left eye's image in its left half) or `two-outputs` (a window per monitor).
    #[serde(default)]
    pub layout: DisplayLayout,
    /// `exact` (default): each image drawn 1:1 onto panel pixels, a misfit reported and
    /// refused; `fit`: scaled to its place, aspect kept (letterboxed).
    #[serde(default)]
    pub scale: Scale,
    /// Each eye's image moved from the centre of its place (its half of a side-by-side
    /// panel, its output), pixels right and down: for panels whose lenses are not centred.
    /// `{ left = [x, y], right = [x, y] }`.
    #[serde(default)]
    pub eye_offset_px: EyeOffsets,
    /// Frame rate the renderer runs at, Hz.
    #[serde(default = "default_frame_hz")]
    pub frame_hz: f64,
    /// Write every Nth shown frame as a PNG (0: none).
    #[serde(default)]
    pub png_every: u32,
    /// Where PNGs go (headless sink).
    pub png_dir: Option<PathBuf>,
    /// Seed of the procedural scene the renderer shows.
    #[serde(default = "default_scene_seed")]
    pub scene_seed: u64,
    /// A square in one corner drawn white or black, for a photodiode taped over it.
    pub marker_patch: Option<MarkerPatch>,
    /// The simulated panel (what a simulated photodiode sees): from a frame's vsync to its light,
    /// ms. Default: the display latency the scheduler assumes.
    pub sim_photon_latency_ms: Option<f64>,
    /// The simulated panel's light per refresh, ms (a low-persistence panel); default: held
    /// until the next refresh changes it.
    pub sim_persistence_ms: Option<f64>,
    /// Refreshes (counted from the first frame presented, from 0) the simulated panel drops:
    /// it shows the previous image again and never shows the frame presented for them.
    #[serde(default)]
    pub sim_dropped_refreshes: Vec<u64>,
}

/// Which corner the marker patch is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Corner {
    #[default]
    TopLeft,
    TopRight,
    BottomLeft,
    BottomRight,
}

/// What toggles the marker patch between white and black.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MarkerEvent {
    /// Every presented frame (a repeated one too).
    Frame,
    /// The first frame presented after each lens command.
    LensCommand,
    /// The first frame presented after each mode change.
    ModeChange,
    /// The first frame presented after each marker asked for through the API.
    ApiMarker,
}

impl MarkerEvent {
    pub fn as_str(self) -> &'static str {
        match self {
            MarkerEvent::Frame => "frame",
            MarkerEvent::LensCommand => "lens-command",
            MarkerEvent::ModeChange => "mode-change",
            MarkerEvent::ApiMarker => "api-marker",
        }
    }
}

/// `display.marker_patch = { corner = "top-left", size = 8, toggle_on = ["frame"] }`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MarkerPatch {
    #[serde(default)]
    pub corner: Corner,
    /// Side of the square, pixels.
    pub size: u32,
    /// Default `["frame"]`.
    #[serde(default = "default_toggle_on")]
    pub toggle_on: Vec<MarkerEvent>,
}

fn default_toggle_on() -> Vec<MarkerEvent> {
    vec![MarkerEvent::Frame]
}

impl Default for Display {
    fn default() -> Self {
        Display {
            kind: default_sink(),
            monitor: None,
            monitor_left: None,
            monitor_right: None,
            width: default_size(),
            height: default_size(),
            layout: DisplayLayout::One,
            scale: Scale::Exact,
            eye_offset_px: EyeOffsets::default(),
            frame_hz: default_frame_hz(),
            png_every: 0,
            png_dir: None,
            scene_seed: default_scene_seed(),
            marker_patch: None,
            sim_photon_latency_ms: None,
            sim_persistence_ms: None,
            sim_dropped_refreshes: Vec::new(),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Api {
    /// TCP address; loopback unless `allow_remote` is true.
    pub listen: Option<String>,
    /// Unix socket path (created with 0600 permissions), instead of `listen`.
    pub unix: Option<PathBuf>,
    #[serde(default)]
    pub allow_remote: bool,
    /// A bearer token every request must carry (`Authorization: Bearer ...`); required with
    /// `allow_remote = true`. Prefer `token_file`, which keeps it out of the config.
    pub token: Option<String>,
    /// A file holding the token (surrounding whitespace ignored); instead of `token`.
    pub token_file: Option<PathBuf>,
}

impl Default for Api {
    fn default() -> Self {
        Api {
            listen: Some(DEFAULT_LISTEN.into()),
            unix: None,
            allow_remote: false,
            token: None,
            token_file: None,
        }
    }
}

pub const DEFAULT_LISTEN: &str = "127.0.0.1:7420";

/// The example rig of simulated devices (`crates/cli/examples/rig-sim.toml`), which the demo,
/// the loop tests and `dioptra eval --suite loop` run.
pub const EXAMPLE_SIM_RIG: &str = include_str!("../../cli/examples/rig-sim.toml");

/// The example binocular rig of simulated devices (`crates/cli/examples/rig-sim-binocular.toml`):
/// a lens per eye, the binocular tracker, the panel split side by side.
pub const EXAMPLE_SIM_BINOCULAR_RIG: &str =
    include_str!("../../cli/examples/rig-sim-binocular.toml");

/// Where the API listens, validated.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Listen {
    Tcp(SocketAddr),
    Unix(PathBuf),
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Recording {
    /// Directory for MCAP files (`dioptra-<unix seconds>.mcap`).
    pub dir: PathBuf,
    /// Start recording when the daemon starts.
    #[serde(default)]
    pub start: bool,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigConfig {
    pub mode: Mode,
    pub method: Method,
    pub devices: Devices,
    pub optics: Optics,
    #[serde(default)]
    pub eye: Eye,
    #[serde(default)]
    pub display: Display,
    #[serde(default)]
    pub api: Api,
    pub recording: Option<Recording>,
    /// `method = "auto"`: the render worker asks the planner (dioptra_render::planner) for
    /// each frame's method; `method` then holds the mode's default, which the scheduler's
    /// frame pacing uses.
    #[serde(skip)]
    pub auto_method: bool,
    #[serde(default)]
    pub render: Render,
    #[serde(default)]
    pub content: ContentConfig,
    /// Lab Streaming Layer outlets.
    #[serde(default)]
    pub lsl: crate::lsl::LslConfig,
    /// The folder of the config file, which its relative paths (calibration tables) are read
    /// from; `None` (config text without a file): the working directory.
    #[serde(skip)]
    pub config_dir: Option<PathBuf>,
    /// The calibration tables' text, read once when the config is (keyed by the path as the
    /// config gives it), so a run and its recording use the tables as they were at start.
    #[serde(skip)]
    pub calibration_tables: std::collections::BTreeMap<PathBuf, String>,
}

/// What the rig shows.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ContentSource {
    /// The procedural scene of `display.scene_seed`.
    #[default]
    Scene,
    /// RGB-D files: one frame, or a numbered sequence.
    Files,
    /// Frames pushed by a running application (shared-memory ring or `PUT /frame`).
    Stream,
}

/// In `content.color` and `content.depth`: the eye, `left` or `right` (a stereo rig's left
/// and right sequences, e.g. `"stim/%e/color_%04d.png"`).
pub const EYE_MARK: &str = "%e";

/// In `content.color` and `content.depth` with `content.views`: the view's place in its grid,
/// `<row>_<column>` with two digits each from `00_00` at the top left (the names `dioptra
/// lightfield` and `dioptra sim scene` give a light field's views: `"lf/view_%v.png"`).
pub const VIEW_MARK: &str = "%v";

/// The largest view grid (`content.views`): the light-field panel warps every input view for
/// each of its views, so the cost grows with the square of the grid.
pub const MAX_CONTENT_VIEWS: usize = 9;

/// The square a view grid spans when `content.view_span_mm` is not given (DeepFocus's and
/// the independent light-field set's 10 mm).
pub const DEFAULT_VIEW_SPAN_MM: f64 = 10.0;

/// `[content]`: the rig's RGB-D content.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContentConfig {
    #[serde(default)]
    pub source: ContentSource,
    /// Colour: PNG (8/16-bit sRGB) or EXR/PFM (linear); `%04d` makes it a sequence; `%e`
    /// (a stereo layout) stands for `left` and `right`, each eye's files.
    pub color: Option<String>,
    /// Depth: EXR/PFM metres or 16-bit PNG millimetres; a sequence (and `%e`) like `color`.
    pub depth: Option<String>,
    /// Override the depth files' units: m, mm or D.
    pub depth_units: Option<String>,
    /// A sequence's frame rate, Hz.
    #[serde(default = "default_content_fps")]
    pub fps: f64,
    /// Play a sequence again from its start (otherwise its last frame stays).
    #[serde(default, rename = "loop")]
    pub looped: bool,
    /// A sequence's first number (default 0).
    pub first: Option<usize>,
    /// Light-field content: each frame is a `views` x `views` grid of RGB-D views over a
    /// square of the eye's pupil plane, `%v` in `color` and `depth` naming each view's file
    /// (a stream: each view sent naming its place, `view=ROW_COLUMN`); light-field
    /// mode synthesises the panel's views from all of them, other modes show the grid's
    /// central view (for an even grid, the one right and below the centre).
    pub views: Option<usize>,
    /// The side of the square the view grid spans, millimetres (default 10): views are
    /// `view_span_mm / (views - 1)` apart, row 0 at the top, column 0 at the left.
    pub view_span_mm: Option<f64>,
    /// `source = "scene"`: move some of its objects, as the demo does (default true).
    pub animate: Option<bool>,
    /// `source = "stream"`: the shared-memory ring's file (default: beside `api.unix`, or
    /// `/dev/shm/dioptra-<pid>.frames`); `"none"` for `PUT /frame` only.
    pub ring: Option<PathBuf>,
}

impl ContentConfig {
    /// The stream's shared-memory ring file (`None`: `ring = "none"`, `PUT /frame` only).
    pub fn ring_path(&self, api: &Api) -> Option<PathBuf> {
        match &self.ring {
            Some(p) if p.as_os_str() == "none" => None,
            Some(p) => Some(p.clone()),
            None => Some(match &api.unix {
                Some(sock) => {
                    let mut p = sock.clone().into_os_string();
                    p.push(".frames");
                    PathBuf::from(p)
                }
                None => {
                    let shm = std::path::Path::new("/dev/shm");
                    let dir = if shm.is_dir() {
                        shm.to_path_buf()
                    } else {
                        std::env::temp_dir()
                    };
                    dir.join(format!("dioptra-{}.frames", std::process::id()))
                }
            }),
        }
    }
}

impl Default for ContentConfig {
    fn default() -> Self {
        ContentConfig {
            source: ContentSource::Scene,
            color: None,
            depth: None,
            depth_units: None,
            fps: default_content_fps(),
            looped: false,
            first: None,
            views: None,
            view_span_mm: None,
            animate: None,
            ring: None,
        }
    }
}

fn default_content_fps() -> f64 {
    30.0
}

/// Render settings.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Render {
    /// Directory of the network's weights for `method = "network"`: `c1.safetensors`
    /// (varifocal) and `c4.safetensors` (multifocal). Default: the shipped crates/net/weights.
    pub weights: Option<PathBuf>,
    /// Where gather, light-field defocus and linear blending run: `auto` (the GPU when a
    /// hardware adapter exists), `cpu` or `gpu` (any adapter, a software one included).
    #[serde(default)]
    pub backend: RenderBackend,
    /// `backend = "gpu"`: the adapter whose name contains this (e.g. "nvidia", "llvmpipe").
    pub adapter: Option<String>,
}

/// `[render] backend`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RenderBackend {
    #[default]
    Auto,
    Cpu,
    Gpu,
}

impl Render {
    /// The weights file of network configuration `config` (`c1`, `c4`).
    pub fn weights_file(&self, config: &str) -> PathBuf {
        match &self.weights {
            Some(dir) => dir.join(format!("{config}.safetensors")),
            None => dioptra_net::shipped_weights(config),
        }
    }
}

fn default_settle_ms() -> f64 {
    15.0
}
fn default_lens_poll_ms() -> f64 {
    10.0
}
fn default_sync_settle_ms() -> f64 {
    SyncDevice::DEFAULT_SIM_SETTLE_MS
}
fn default_scenario() -> String {
    "saccades".into()
}
fn default_min_confidence() -> f32 {
    dioptra_gaze::pupil::ids::RECOMMENDED_MIN_CONFIDENCE
}
fn default_gaze_rate() -> f64 {
    250.0
}
fn default_seed() -> u64 {
    1
}
fn default_planes() -> Vec<f32> {
    vec![0.2, 0.8, 1.4, 2.0]
}
fn default_subframe_hz() -> f64 {
    240.0
}
fn default_pupil() -> f32 {
    4.0
}
fn default_fov() -> f32 {
    20.0
}
fn default_ipd() -> f32 {
    63.0
}
fn default_sink() -> SinkKind {
    SinkKind::Headless
}
fn default_size() -> u32 {
    96
}
fn default_frame_hz() -> f64 {
    60.0
}
fn default_scene_seed() -> u64 {
    1_000_001
}

/// `method = "auto"` becomes the mode's default method plus the auto flag; other text is
/// returned as it is (so parse errors keep their line numbers).
fn resolve_auto(text: &str) -> Result<(std::borrow::Cow<'_, str>, bool), ConfigError> {
    let Ok(mut table) = text.parse::<toml::Table>() else {
        // Not valid TOML: the strict parse below reports where.
        return Ok((text.into(), false));
    };
    if table.get("method").and_then(|m| m.as_str()) != Some("auto") {
        return Ok((text.into(), false));
    }
    let mode = table
        .get("mode")
        .and_then(|m| m.as_str())
        .and_then(Mode::parse)
        .unwrap_or(Mode::Varifocal);
    let base = Method(RenderMethod::default_for(mode.sched()));
    table.insert("method".into(), toml::Value::String(base.as_str().into()));
    let text = toml::to_string(&table).map_err(|e| ConfigError::Parse {
        key: "method".into(),
        message: one_line(&e.to_string()),
    })?;
    Ok((text.into(), true))
}

impl RigConfig {
    /// The eye the rig renders for and looks up depth with: `[eye]`'s pupil and field over
    /// the display's width (not validated: [`RigConfig::validate`] checks it).
    pub fn eye_model(&self) -> dioptra_core::EyeModel {
        dioptra_core::EyeModel {
            pupil_diameter: dioptra_core::Millimeters(self.eye.pupil_mm),
            fov_horizontal_deg: self.eye.fov_deg,
            width_px: self.display.width,
            ..Default::default()
        }
    }

    /// The multifocal schedule the sync hardware runs: `optics.planes` at `optics.subframe_hz`,
    /// dark for the first quarter of each sub-frame while the lens settles.
    pub fn plane_schedule(&self) -> Result<dioptra_core::PlaneSchedule, ConfigError> {
        let o = &self.optics;
        dioptra_core::PlaneSchedule::new(
            o.planes
                .iter()
                .copied()
                .map(dioptra_core::Diopters)
                .collect(),
            std::time::Duration::from_secs_f64(1.0 / o.subframe_hz),
            std::time::Duration::from_secs_f64(0.25 / o.subframe_hz),
        )
        .map_err(|e| invalid("optics.planes", e.to_string()))
    }

    /// The sync device's own settings, and whether it can run the configured schedule.
    fn check_photodiode(&self, p: &PhotodiodeDevice) -> Result<(), ConfigError> {
        match (p.driver, &p.port) {
            (PhotodiodeDriver::SerialLine, None) => {
                return Err(invalid(
                    "devices.photodiode.port",
                    "driver = \"serial-line\" needs the microcontroller's port, e.g. \"/dev/ttyACM0\", or \"sim\"",
                ))
            }
            (PhotodiodeDriver::SerialLine, Some(_)) => {
                for (key, v) in [
                    ("devices.photodiode.threshold", p.threshold),
                    ("devices.photodiode.hysteresis", p.hysteresis),
                ] {
                    if v.is_some() {
                        return Err(invalid(
                            key,
                            "a serial-line photodiode's threshold is its comparator's trimmer; this key sets the sync board's (driver = \"sync\")",
                        ));
                    }
                }
            }
            (PhotodiodeDriver::Sync, None) => match &self.devices.sync {
                Some(s) if s.driver == SyncDriver::Sync => {}
                Some(_) => {
                    return Err(invalid(
                        "devices.photodiode.driver",
                        "driver = \"sync\" without a port uses the dioptra sync board of [devices.sync], which is a DLPC350 here: give the photodiode board's port, or use driver = \"serial-line\"",
                    ))
                }
                None => {
                    return Err(invalid(
                        "devices.photodiode.port",
                        "driver = \"sync\" without a port uses the board of [devices.sync], and there is none: give the board's port, or \"sim\"",
                    ))
                }
            },
            (PhotodiodeDriver::Sync, Some(port)) => {
                if self
                    .devices
                    .sync
                    .as_ref()
                    .is_some_and(|s| s.driver == SyncDriver::Sync && &s.port == port && *port != Port::Sim)
                {
                    return Err(invalid(
                        "devices.photodiode.port",
                        format!("{port} is the board of [devices.sync]: remove this port to use its photodiode input (one link per board)"),
                    ));
                }
            }
        }
        if let Some(Port::Net(a) | Port::Usb(Some(a))) = &p.port {
            return Err(invalid(
                "devices.photodiode.port",
                format!("{a}: a photodiode is reached by device path, VID:PID or \"sim\""),
            ));
        }
        if p.port == Some(Port::Usb(None)) {
            return Err(invalid(
                "devices.photodiode.port",
                "usb: a photodiode is reached by device path, VID:PID or \"sim\"",
            ));
        }
        if p.driver == PhotodiodeDriver::Sync {
            dioptra_sync::board::wire_photodiode_config(Some(p.band())).map_err(|e| {
                invalid(
                    "devices.photodiode.threshold",
                    format!("{e} (devices.photodiode.threshold and hysteresis)"),
                )
            })?;
        }
        Ok(())
    }

    fn check_marker_and_panel(&self) -> Result<(), ConfigError> {
        let d = &self.display;
        if let Some(m) = &d.marker_patch {
            let most = d.width.min(d.height).min(512);
            if !(1..=most).contains(&m.size) {
                return Err(invalid(
                    "display.marker_patch.size",
                    format!("{}: expected 1 to {most} pixels (within the display's {}x{} and at most 512)", m.size, d.width, d.height),
                ));
            }
            if m.toggle_on.is_empty() {
                return Err(invalid(
                    "display.marker_patch.toggle_on",
                    "name what toggles the patch: [\"frame\"] (every presented frame), or any of \"lens-command\", \"mode-change\", \"api-marker\"",
                ));
            }
            if m.toggle_on.len() > 1 && m.toggle_on.contains(&MarkerEvent::Frame) {
                return Err(invalid(
                    "display.marker_patch.toggle_on",
                    "\"frame\" toggles the patch on every presented frame; the other events cannot be told apart from it: give \"frame\" alone, or the events alone",
                ));
            }
        }
        if let Some(l) = d.sim_photon_latency_ms {
            if !(l.is_finite() && (0.0..=200.0).contains(&l)) {
                return Err(invalid(
                    "display.sim_photon_latency_ms",
                    format!("expected 0 to 200 ms from a vsync to the panel's light, got {l} (dioptra hil looks 250 ms for the light)"),
                ));
            }
        }
        if let Some(p) = d.sim_persistence_ms {
            let period_ms = 1000.0 / d.frame_hz;
            if !(p.is_finite() && p > 0.0 && p <= period_ms) {
                return Err(invalid(
                    "display.sim_persistence_ms",
                    format!("expected more than 0 and at most one refresh ({period_ms:.2} ms at display.frame_hz = {}); remove it for a panel that holds its light (got {p})", d.frame_hz),
                ));
            }
        }
        if d.sim_dropped_refreshes.len() > 10_000 {
            return Err(invalid(
                "display.sim_dropped_refreshes",
                "at most 10000 refreshes",
            ));
        }
        if self.devices.photodiode.is_some() && d.marker_patch.is_none() {
            return Err(invalid(
                "display.marker_patch",
                "[devices.photodiode] is set but no marker patch is drawn for it to see: add display.marker_patch = { corner = \"top-left\", size = 8 }",
            ));
        }
        Ok(())
    }

    /// Whether a photodiode is simulated: its own port is "sim", or it is the input of a
    /// simulated sync board.
    pub fn photodiode_simulated(&self) -> bool {
        self.devices
            .photodiode
            .as_ref()
            .is_some_and(|p| match &p.port {
                Some(port) => *port == Port::Sim,
                None => self
                    .devices
                    .sync
                    .as_ref()
                    .is_some_and(|s| s.port == Port::Sim),
            })
    }

    fn check_sync(&self, s: &SyncDevice) -> Result<(), ConfigError> {
        if !(s.sim_settle_ms.is_finite() && s.sim_settle_ms > 0.0 && s.sim_settle_ms <= 1000.0) {
            return Err(invalid(
                "devices.sync.sim_settle_ms",
                format!(
                    "expected a settle time above 0 and at most 1000 ms (got {})",
                    s.sim_settle_ms
                ),
            ));
        }
        // The board measures the lens when a sub-frame's dark quarter ends: a simulated lens
        // slower than that would fault on every sub-frame.
        let dark_ms = 250.0 / self.optics.subframe_hz;
        if s.port == Port::Sim && s.sim_settle_ms > dark_ms {
            return Err(invalid(
                "devices.sync.sim_settle_ms",
                format!(
                    "the simulated multifocal lens settles in {} ms, longer than the dark quarter \
                     of a sub-frame ({dark_ms:.2} ms at optics.subframe_hz = {}): every sub-frame \
                     would be lit before the lens arrives; lower one of the two",
                    s.sim_settle_ms, self.optics.subframe_hz
                ),
            ));
        }
        match s.driver {
            SyncDriver::Sync => {
                if s.video_hz.is_some() {
                    return Err(invalid(
                        "devices.sync.video_hz",
                        "only the dlpc350 driver takes a video rate (the sync board follows the display's own vsync)",
                    ));
                }
            }
            SyncDriver::Dlpc350 => {
                let hz = s.video_hz.unwrap_or(SyncDevice::DEFAULT_VIDEO_HZ);
                if !(hz.is_finite() && (1.0..=240.0).contains(&hz)) {
                    return Err(invalid(
                        "devices.sync.video_hz",
                        format!("expected the projector's video rate, 1 to 240 Hz (got {hz})"),
                    ));
                }
                // The driver checks the controller's rules before sending anything; check
                // them here too, so a rig that cannot run says so at start with its keys.
                let schedule = self.plane_schedule()?;
                dioptra_sync::dlpc350::PatternSequence::for_schedule(
                    &schedule,
                    &s.dlpc350_config(),
                )
                .map_err(|e| {
                    invalid(
                        "optics.subframe_hz",
                        format!(
                            "the DLPC350 cannot run {} planes at {} Hz with {hz} Hz video: {e}",
                            self.optics.planes.len(),
                            self.optics.subframe_hz
                        ),
                    )
                })?;
            }
        }
        Ok(())
    }

    /// One lens's section (`key`: `devices.lens`, `devices.lens.left` or `.right`).
    fn check_lens(&self, key: &str, l: &LensDevice) -> Result<(), ConfigError> {
        let r = self.optics.lens_range;
        let k = |field: &str| format!("{key}.{field}");
        let park = l.park_power;
        if !(park.is_finite() && (r.min..=r.max).contains(&park)) {
            return Err(invalid(
                &k("park_power"),
                format!(
                    "{park} D is outside optics.lens_range {}..{} D: the lens must park inside the rig's range",
                    r.min, r.max
                ),
            ));
        }
        if let Some([lo, hi]) = l.temperature_limits_c {
            if l.driver != LensDriver::Optotune {
                return Err(invalid(
                    &k("temperature_limits_c"),
                    "only the Optotune Lens Driver 4 takes temperature limits (driver = \"optotune\")",
                ));
            }
            if !(lo.is_finite() && hi.is_finite() && lo < hi && lo >= -120.0 && hi <= 120.0) {
                return Err(invalid(
                    &k("temperature_limits_c"),
                    format!("[{lo}, {hi}]: expected [lower, upper] in °C, lower below upper, within -120..120"),
                ));
            }
        }
        let settle = l.sim_settle_ms;
        if !(settle.is_finite() && settle > 0.0 && settle <= 1000.0) {
            return Err(invalid(
                &k("sim_settle_ms"),
                format!("expected a settle time above 0 and at most 1000 ms (got {settle})"),
            ));
        }
        if let Some(settle) = l.settle_ms {
            if !(settle.is_finite() && settle > 0.0 && settle <= 1000.0) {
                return Err(invalid(
                    &k("settle_ms"),
                    format!("expected the lens's settle time, more than 0 and at most 1000 ms (got {settle})"),
                ));
            }
        }
        let poll = l.poll_ms;
        if !(poll.is_finite() && (1.0..=1000.0).contains(&poll)) {
            return Err(invalid(
                &k("poll_ms"),
                format!("expected a read-back interval of 1 to 1000 ms (got {poll})"),
            ));
        }
        if let Port::Net(a) = &l.port {
            return Err(invalid(
                &k("port"),
                format!("{a}: lenses are reached by device path, VID:PID or \"sim\", not over the network"),
            ));
        }
        Ok(())
    }

    /// A `port = "usb"` only for a driver that talks over USB bulk endpoints (the drivers'
    /// table says which).
    fn check_usb_ports(&self) -> Result<(), ConfigError> {
        use crate::devices::open::{row, GAZE, LENS, SYNC};
        let d = &self.devices;
        let keys: Vec<String> = (0..d.lens.count())
            .map(|i| format!("{}.port", d.lens.key(i)))
            .collect();
        let usb = d
            .lens
            .each()
            .into_iter()
            .zip(&keys)
            .map(|(l, key)| {
                let found = row(&LENS, l.driver).map(|r| (r.what, r.usb.is_some()));
                (key.as_str(), &l.port, found)
            })
            .chain([(
                "devices.gaze.port",
                &d.gaze.port,
                row(&GAZE, d.gaze.driver).map(|r| (r.what, r.usb.is_some())),
            )])
            .chain(d.sync.as_ref().map(|s| {
                (
                    "devices.sync.port",
                    &s.port,
                    row(&SYNC, s.driver).map(|r| (r.what, r.usb.is_some())),
                )
            }));
        for (key, port, found) in usb {
            if let (Port::Usb(_), Ok((what, false))) = (port, found) {
                return Err(invalid(
                    key,
                    format!(
                        "{port}: the {what} is not reached over USB bulk endpoints; give its device path (e.g. /dev/ttyACM0 or /dev/hidraw0), its USB VID:PID or \"sim\""
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Reads and validates a rig config file; its relative paths are read from its folder.
    pub fn load(path: &Path) -> Result<RigConfig, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        // Absolute, so that the paths it resolves (and recordings of them) do not depend on
        // the working directory.
        let dir = std::path::absolute(path)
            .ok()
            .and_then(|p| p.parent().map(Path::to_path_buf))
            .unwrap_or_else(|| path.parent().unwrap_or(Path::new("")).to_path_buf());
        Self::parse_in(&text, Some(dir))
    }

    /// Parses and validates rig config text (relative paths from the working directory).
    pub fn parse(text: &str) -> Result<RigConfig, ConfigError> {
        Self::parse_in(text, None)
    }

    /// Parses and validates rig config text whose relative paths are in `config_dir`.
    pub fn parse_in(text: &str, config_dir: Option<PathBuf>) -> Result<RigConfig, ConfigError> {
        Self::parse_with(text, config_dir, Default::default())
    }

    /// Parses and validates rig config text with its calibration tables given (a recording's:
    /// `dioptra replay` runs with the tables the run had); a table not given is read from
    /// its file.
    pub fn parse_with_tables(
        text: &str,
        tables: std::collections::BTreeMap<PathBuf, String>,
    ) -> Result<RigConfig, ConfigError> {
        Self::parse_with(text, None, tables)
    }

    fn parse_with(
        text: &str,
        config_dir: Option<PathBuf>,
        tables: std::collections::BTreeMap<PathBuf, String>,
    ) -> Result<RigConfig, ConfigError> {
        let (text, auto_method) = resolve_auto(text)?;
        let text = text.as_ref();
        let de = toml::Deserializer::parse(text).map_err(|e| ConfigError::Parse {
            key: ".".into(),
            message: one_line(&e.to_string()),
        })?;
        let cfg: RigConfig = serde_path_to_error::deserialize(de).map_err(|e| {
            let key = e.path().to_string();
            let inner = e.into_inner();
            let mut message = inner.message().to_string();
            if let Some(span) = inner.span() {
                let line = text[..span.start.min(text.len())].matches('\n').count() + 1;
                message += &format!(" (line {line})");
            }
            ConfigError::Parse { key, message }
        })?;
        let mut cfg = RigConfig {
            auto_method,
            config_dir,
            calibration_tables: tables,
            ..cfg
        };
        cfg.read_calibration_tables()?;
        cfg.resolve_paths();
        cfg.validate()?;
        Ok(cfg)
    }

    /// Reads every calibration table the optics settings name and does not hold yet.
    fn read_calibration_tables(&mut self) -> Result<(), ConfigError> {
        let o = &self.optics;
        let named = [
            ("optics", o.calibration.as_ref()),
            (
                "optics.left",
                o.left.as_ref().and_then(|e| e.calibration.as_ref()),
            ),
            (
                "optics.right",
                o.right.as_ref().and_then(|e| e.calibration.as_ref()),
            ),
        ];
        let mut read = Vec::new();
        for (section, file) in named {
            let Some(file) = file else { continue };
            if self.calibration_tables.contains_key(file) {
                continue;
            }
            let path = self.config_path(file);
            let text = std::fs::read_to_string(&path).map_err(|e| {
                invalid(
                    &format!("{section}.calibration"),
                    format!(
                        "cannot read the calibration table {} ({}): {e}",
                        path.display(),
                        if file.is_relative() {
                            "relative paths are read from the config file's folder"
                        } else {
                            "as given"
                        }
                    ),
                )
            })?;
            read.push((file.clone(), text));
        }
        self.calibration_tables.extend(read);
        Ok(())
    }

    /// Makes the config's relative file paths (content files and ring, recording.dir,
    /// render.weights, api.unix and token_file, display.png_dir) relative to its folder, so
    /// the daemon finds the same files whatever directory it is started from. Recordings hold
    /// the config with these paths. (Calibration tables are read through
    /// [`RigConfig::config_path`].)
    fn resolve_paths(&mut self) {
        let Some(dir) = self.config_dir.clone() else {
            return;
        };
        let at = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = dir.join(&*p);
            }
        };
        let c = &mut self.content;
        for pattern in [&mut c.color, &mut c.depth].into_iter().flatten() {
            let mut p = PathBuf::from(&*pattern);
            at(&mut p);
            *pattern = p.display().to_string();
        }
        if let Some(r) = c.ring.as_mut().filter(|r| r.as_os_str() != "none") {
            at(r);
        }
        if let Some(r) = self.recording.as_mut() {
            at(&mut r.dir);
        }
        for p in [
            &mut self.render.weights,
            &mut self.api.unix,
            &mut self.api.token_file,
            &mut self.display.png_dir,
        ]
        .into_iter()
        .flatten()
        {
            at(p);
        }
    }

    /// A path given in the config, as it is read: relative ones from the config's folder.
    pub fn config_path(&self, p: &Path) -> PathBuf {
        match &self.config_dir {
            Some(dir) if p.is_relative() => dir.join(p),
            _ => p.to_path_buf(),
        }
    }

    /// The optics map of an eye (`None`: the rig's one lens, see
    /// [`Optics::one_lens_eye`]): its layout or calibration table (read now) and the viewer's
    /// prescription, for the lens range. Errors name the key, the file and the points.
    pub fn optics_map(&self, side: Option<Side>) -> Result<OpticsMap, ConfigError> {
        self.optics_map_from(side, true)
    }

    /// The optics a simulated lens sits in: `[optics.layout]` and the viewer's prescription,
    /// without the calibration table (which is what the rig believes, not the physics), so a
    /// simulated rig whose table is wrong shows the focus error it would have.
    pub fn simulated_optics(&self, side: Option<Side>) -> Result<OpticsMap, ConfigError> {
        self.optics_map_from(side, false)
    }

    fn optics_map_from(
        &self,
        side: Option<Side>,
        with_table: bool,
    ) -> Result<OpticsMap, ConfigError> {
        let o = &self.optics;
        let shared = o.shared();
        let side = side.or_else(|| o.one_lens_eye());
        let section = side.map(|s| match s {
            Side::Left => "optics.left",
            Side::Right => "optics.right",
        });
        let eye = side.and_then(|s| o.eye(s)).zip(section);
        let r = resolve(&shared, eye);
        let key = |section: &str, name: &str| format!("{section}.{name}");
        let layout = match r.layout {
            Some((l, section)) => Some(
                ThinLensLayout::new(l.display_distance_m, l.eye_relief_m, l.fixed_power_d)
                    .map_err(|e| optics_error(e, &format!("{section}.layout")))?,
            ),
            None => None,
        };
        let table = match r.calibration.filter(|_| with_table) {
            Some((file, section)) => {
                let text = self.calibration_tables.get(file).ok_or_else(|| {
                    invalid(
                        &key(section, "calibration"),
                        format!("{} was not read with the config", file.display()),
                    )
                })?;
                let name = self.config_path(file).display().to_string();
                Some(
                    CalibrationTable::parse_csv(&name, text)
                        .map_err(|e| optics_error(e, &key(section, "calibration")))?,
                )
            }
            None => None,
        };
        // The prescription's keys may come from different sections: name the sphere's.
        let rx_section = r.sphere.or(r.cylinder).map_or("optics", |v| v.1);
        let prescription = Prescription::new(
            r.sphere.map_or(0.0, |v| v.0),
            r.cylinder.map_or(0.0, |v| v.0),
            r.vertex_mm
                .map_or(dioptra_core::optics_map::DEFAULT_VERTEX_M, |v| v.0 / 1000.0),
        )
        .map_err(|e| optics_error(e, rx_section))?;
        let range = PowerRange::new(Diopters(o.lens_range.min), Diopters(o.lens_range.max))
            .ok_or_else(|| invalid("optics.lens_range", "min must be below max"))?;
        let section = r
            .calibration
            .filter(|_| with_table)
            .map(|c| key(c.1, "calibration"))
            .or(r.layout.map(|l| format!("{}.layout", l.1)))
            .unwrap_or_else(|| "optics".into());
        OpticsMap::new(layout, table, prescription, range).map_err(|e| optics_error(e, &section))
    }

    /// Things worth saying at start that are not errors: keys that no longer do anything,
    /// defaults a real rig should set.
    pub fn notices(&self) -> Vec<String> {
        let mut out = Vec::new();
        if self.optics.display_distance_m.is_some() {
            out.push(
                "optics.display_distance_m is no longer read (it never was used): the display's \
                 distance from the tunable lens is [optics.layout] display_distance_m, with \
                 eye_relief_m and fixed_power_d; without a layout or calibration the lens \
                 command is the focus (the identity map)"
                    .to_string(),
            );
        }
        let lenses = &self.devices.lens;
        for (i, l) in lenses.each().into_iter().enumerate() {
            if l.port != Port::Sim && l.settle_ms.is_none() {
                out.push(format!(
                    "{}.settle_ms is not set: the scheduler models the lens as settling \
                     in {} ms (the EL-10-30's datasheet); measure yours with `dioptra lens set D \
                     --watch-ms 100` and set it",
                    lenses.key(i),
                    LensDevice::DEFAULT_SETTLE_MS
                ));
            }
        }
        out
    }

    /// Range and consistency checks serde cannot express.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let name = &self.lsl.name;
        if name.is_empty()
            || name.len() > 64
            || !name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        {
            return Err(invalid(
                "lsl.name",
                format!("{name:?}: expected 1 to 64 letters, digits, '-' or '_' (it names the LSL streams)"),
            ));
        }
        if self.render.adapter.is_some() && self.render.backend == RenderBackend::Cpu {
            return Err(invalid(
                "render.adapter",
                "an adapter is chosen for the GPU: set render.backend = \"gpu\" or remove it",
            ));
        }
        let c = &self.content;
        match c.source {
            ContentSource::Files => {
                for (key, v) in [("content.color", &c.color), ("content.depth", &c.depth)] {
                    if v.as_deref().is_none_or(str::is_empty) {
                        return Err(invalid(
                            key,
                            "source = \"files\" needs content.color and content.depth (a file, or a pattern such as \"stim/color_%04d.png\")",
                        ));
                    }
                }
                if !(c.fps.is_finite() && c.fps > 0.0 && c.fps <= 1000.0) {
                    return Err(invalid(
                        "content.fps",
                        "expected a frame rate of 0 to 1000 Hz",
                    ));
                }
                self.check_eye_patterns()?;
                self.check_view_grid()?;
                if let Some(u) = &c.depth_units {
                    if !["m", "mm", "D"].contains(&u.as_str()) {
                        return Err(invalid(
                            "content.depth_units",
                            format!("{u:?}: expected m, mm or D"),
                        ));
                    }
                }
            }
            ContentSource::Scene | ContentSource::Stream => {
                if c.color.is_some() || c.depth.is_some() {
                    return Err(invalid(
                        "content.source",
                        "content.color and content.depth are read with source = \"files\"",
                    ));
                }
                if c.source == ContentSource::Stream {
                    self.check_view_grid()?;
                } else if c.views.is_some() || c.view_span_mm.is_some() {
                    return Err(invalid(
                        "content.views",
                        "a view grid comes from files (source = \"files\", %v in content.color \
                         and content.depth) or a stream (source = \"stream\")",
                    ));
                }
            }
        }
        if c.animate.is_some() && c.source != ContentSource::Scene {
            return Err(invalid(
                "content.animate",
                "the procedural scene is animated (source = \"scene\"); files and streams move as their frames do",
            ));
        }
        if c.ring.is_some() && c.source != ContentSource::Stream {
            return Err(invalid(
                "content.ring",
                "the shared-memory ring is made with source = \"stream\"",
            ));
        }
        let o = &self.optics;
        let r = o.lens_range;
        if !(r.min.is_finite() && r.max.is_finite()) {
            return Err(invalid(
                "optics.lens_range",
                "min and max must be finite numbers of diopters",
            ));
        }
        if r.min >= r.max {
            return Err(invalid(
                "optics.lens_range",
                format!(
                    "min must be below max (got min = {}, max = {})",
                    r.min, r.max
                ),
            ));
        }
        if !(-20.0..=20.0).contains(&r.min) || !(-20.0..=20.0).contains(&r.max) {
            return Err(invalid(
                "optics.lens_range",
                "expected powers within -20..20 D",
            ));
        }
        if o.display_distance_m.is_some() && o.layout.is_some() {
            return Err(invalid(
                "optics.display_distance_m",
                "this key moved to [optics.layout] display_distance_m (the display's distance \
                 from the tunable lens): remove it from [optics]",
            ));
        }
        if o.planes.is_empty() || o.planes.len() > dioptra_core::device::MAX_PLANES {
            return Err(invalid(
                "optics.planes",
                format!(
                    "expected 1 to {} plane powers in diopters, e.g. [0.2, 0.8, 1.4, 2.0]",
                    dioptra_core::device::MAX_PLANES
                ),
            ));
        }
        if let Some(p) = o
            .planes
            .iter()
            .find(|p| !(p.is_finite() && (r.min..=r.max).contains(*p)))
        {
            return Err(invalid(
                "optics.planes",
                format!(
                    "plane {p} D is outside optics.lens_range {}..{} D",
                    r.min, r.max
                ),
            ));
        }
        if !(o.subframe_hz.is_finite() && (1.0..=10_000.0).contains(&o.subframe_hz)) {
            return Err(invalid(
                "optics.subframe_hz",
                "expected a sub-frame rate of 1 to 10000 Hz",
            ));
        }
        for (i, l) in self.devices.lens.each().into_iter().enumerate() {
            self.check_lens(&self.devices.lens.key(i), l)?;
        }
        let g = &self.devices.gaze;
        if g.port == Port::Sim && !dioptra_sim::gaze::SCENARIOS.contains(&g.sim_scenario.as_str()) {
            return Err(invalid(
                "devices.gaze.sim_scenario",
                format!(
                    "unknown scenario {:?}; expected one of {}",
                    g.sim_scenario,
                    dioptra_sim::gaze::SCENARIOS.join(", ")
                ),
            ));
        }
        let c = g.min_confidence;
        if !(c.is_finite() && (0.0..=1.0).contains(&c)) {
            return Err(invalid(
                "devices.gaze.min_confidence",
                format!("expected a confidence of 0 to 1 (got {c})"),
            ));
        }
        match (g.driver, &g.port) {
            (GazeDriver::Pupil, Port::Net(_) | Port::Sim) => {}
            (GazeDriver::Pupil, p) => {
                return Err(invalid(
                    "devices.gaze.port",
                    format!("{p}: driver = \"pupil\" reaches Pupil Capture over the network: give Pupil Remote's address, e.g. \"127.0.0.1:50020\", or \"sim\""),
                ))
            }
            (_, Port::Net(a)) => {
                return Err(invalid(
                    "devices.gaze.port",
                    format!("{a}: a network address is for driver = \"pupil\"; this driver needs a device path, a VID:PID or \"sim\""),
                ))
            }
            _ => {}
        }
        self.check_usb_ports()?;
        if let Some(Port::Net(a)) = self.devices.sync.as_ref().map(|s| &s.port) {
            return Err(invalid(
                "devices.sync.port",
                format!("{a}: sync hardware is reached by device path, VID:PID or \"sim\", not over the network"),
            ));
        }
        if !(g.sim_rate_hz.is_finite() && (1.0..=2000.0).contains(&g.sim_rate_hz)) {
            return Err(invalid(
                "devices.gaze.sim_rate_hz",
                "expected a sample rate of 1 to 2000 Hz",
            ));
        }
        if self.mode == Mode::Multifocal && self.devices.sync.is_none() {
            return Err(invalid(
                "devices.sync",
                "multifocal mode needs sync hardware: add [devices.sync] with driver = \"sync\" (the dioptra sync board) or \"dlpc350\", and a port",
            ));
        }
        if let Some(s) = &self.devices.sync {
            self.check_sync(s)?;
        }
        if let Some(p) = &self.devices.photodiode {
            self.check_photodiode(p)?;
        }
        if self.auto_method && self.mode != Mode::Varifocal {
            return Err(invalid(
                "method",
                format!(
                    "auto chooses a method per frame in varifocal mode only (in {} mode the planes or views are fixed by the hardware's program); expected {}",
                    self.mode.as_str(),
                    Method::for_mode(self.mode)
                ),
            ));
        }
        if !self.method.fits(self.mode) {
            return Err(invalid(
                "method",
                format!(
                    "{} does not render for {} mode; expected {}",
                    self.method.as_str(),
                    self.mode.as_str(),
                    Method::for_mode(self.mode)
                ),
            ));
        }
        if let Some(why) = self.method.unavailable(self.mode) {
            return Err(invalid("method", why));
        }
        let e = &self.eye;
        // A human pupil: about 2 mm in bright light to 8 mm dark-adapted.
        if !(e.pupil_mm.is_finite() && (1.0..=10.0).contains(&e.pupil_mm)) {
            return Err(invalid(
                "eye.pupil_mm",
                format!(
                    "expected a pupil diameter of 1 to 10 mm (got {}; DeepFocus's eye: 4)",
                    e.pupil_mm
                ),
            ));
        }
        dioptra_core::EyeModel {
            pupil_diameter: dioptra_core::Millimeters(e.pupil_mm),
            fov_horizontal_deg: e.fov_deg,
            ..Default::default()
        }
        .validated()
        .map_err(|err| invalid("eye", err.to_string()))?;
        if !(e.ipd_mm.is_finite() && (40.0..=90.0).contains(&e.ipd_mm)) {
            return Err(invalid("eye.ipd_mm", "expected 40 to 90 mm"));
        }
        let d = &self.display;
        if !(8..=4096).contains(&d.width) || !(8..=4096).contains(&d.height) {
            return Err(invalid(
                "display",
                "width and height must be 8 to 4096 pixels",
            ));
        }
        if !(d.frame_hz.is_finite() && (1.0..=1000.0).contains(&d.frame_hz)) {
            return Err(invalid("display.frame_hz", "expected 1 to 1000 Hz"));
        }
        if d.monitor.is_some() && d.kind != SinkKind::Window {
            return Err(invalid(
                "display.monitor",
                "a monitor is chosen only for the window: set display.kind = \"window\" or remove it",
            ));
        }
        self.check_layout()?;
        if d.png_every > 0 && d.png_dir.is_none() {
            return Err(invalid(
                "display.png_dir",
                "display.png_every is set: give a directory for the PNGs",
            ));
        }
        let one_lens = matches!(self.devices.lens, Lenses::One(_));
        if one_lens && self.optics.left.is_some() && self.optics.right.is_some() {
            return Err(invalid(
                "optics.right",
                "[optics.left] and [optics.right] are both given, but this rig has one lens \
                 ([devices.lens]): put that lens's optics in [optics] (or in the one eye's \
                 section of a monocular bench); per-eye maps need a lens per eye",
            ));
        }
        if one_lens {
            self.optics_map(None)?;
        } else {
            for side in Side::BOTH {
                self.optics_map(Some(side))?;
            }
        }
        self.check_marker_and_panel()?;
        self.listen()?;
        self.api_token()?;
        Ok(())
    }

    /// `display.layout` with its monitors and offsets.
    fn check_layout(&self) -> Result<(), ConfigError> {
        let d = &self.display;
        let window = d.kind == SinkKind::Window;
        match d.layout {
            DisplayLayout::TwoOutputs => {
                if d.monitor.is_some() {
                    return Err(invalid(
                        "display.monitor",
                        "layout = \"two-outputs\" shows each eye on its own monitor: give \
                         display.monitor_left and display.monitor_right instead",
                    ));
                }
                if window {
                    for (key, m) in [
                        ("display.monitor_left", &d.monitor_left),
                        ("display.monitor_right", &d.monitor_right),
                    ] {
                        if m.is_none() {
                            return Err(invalid(
                                key,
                                "layout = \"two-outputs\" with the window needs each eye's \
                                 monitor (a name such as \"HDMI-1\" or an index)",
                            ));
                        }
                    }
                    if d.monitor_left == d.monitor_right {
                        return Err(invalid(
                            "display.monitor_right",
                            "the same monitor as display.monitor_left: two outputs need two \
                             monitors (one panel for both eyes is layout = \"side-by-side\")",
                        ));
                    }
                }
            }
            _ => {
                for (key, m) in [
                    ("display.monitor_left", &d.monitor_left),
                    ("display.monitor_right", &d.monitor_right),
                ] {
                    if m.is_some() {
                        return Err(invalid(
                            key,
                            format!(
                                "a monitor per eye is for layout = \"two-outputs\" (layout is \
                                 \"{}\"); one panel's monitor is display.monitor",
                                d.layout.as_str()
                            ),
                        ));
                    }
                }
            }
        }
        if (d.monitor_left.is_some() || d.monitor_right.is_some()) && !window {
            return Err(invalid(
                "display.monitor_left",
                "monitors are chosen only for the window: set display.kind = \"window\" or \
                 remove them",
            ));
        }
        if d.layout == DisplayLayout::One && d.eye_offset_px.right != [0, 0] {
            return Err(invalid(
                "display.eye_offset_px.right",
                "layout = \"one\" shows one image (placed by eye_offset_px.left): a right \
                 eye's offset needs layout = \"side-by-side\" or \"two-outputs\"",
            ));
        }
        for side in Side::BOTH {
            let [x, y] = d.eye_offset_px.of(side);
            if x.unsigned_abs() > 4096 || y.unsigned_abs() > 4096 {
                return Err(invalid(
                    match side {
                        Side::Left => "display.eye_offset_px.left",
                        Side::Right => "display.eye_offset_px.right",
                    },
                    "expected -4096 to 4096 pixels",
                ));
            }
        }
        Ok(())
    }

    /// `%e` in `content.color`/`content.depth` (a left and a right sequence): only on a
    /// stereo layout, and in both patterns or neither.
    fn check_eye_patterns(&self) -> Result<(), ConfigError> {
        let c = &self.content;
        let keys = [("content.color", &c.color), ("content.depth", &c.depth)];
        let has = |v: &Option<String>| v.as_deref().is_some_and(|p| p.contains(EYE_MARK));
        for (key, v) in keys {
            if has(v) && !self.stereo() {
                return Err(invalid(
                    key,
                    format!(
                        "{EYE_MARK} names the eye (a left and a right sequence), and \
                         display.layout is \"one\" (one image): set display.layout = \
                         \"side-by-side\" or \"two-outputs\", or name one sequence without \
                         {EYE_MARK}"
                    ),
                ));
            }
        }
        if has(&c.color) != has(&c.depth) {
            let (key, other) = if has(&c.color) {
                ("content.depth", "content.color")
            } else {
                ("content.color", "content.depth")
            };
            return Err(invalid(
                key,
                format!(
                    "{other} names each eye's files with {EYE_MARK}, so this must too: each \
                     eye's colour needs that eye's depth"
                ),
            ));
        }
        Ok(())
    }

    /// `content.views` and `content.view_span_mm`, and (files) `%v` in the patterns.
    fn check_view_grid(&self) -> Result<(), ConfigError> {
        let c = &self.content;
        let has = |v: &Option<String>| v.as_deref().is_some_and(|p| p.contains(VIEW_MARK));
        match c.views {
            None => {
                for (key, v) in [("content.color", &c.color), ("content.depth", &c.depth)] {
                    if has(v) {
                        return Err(invalid(
                            key,
                            format!(
                                "{VIEW_MARK} names the views of a light field's grid: set \
                                 content.views to the grid's side (views per row)"
                            ),
                        ));
                    }
                }
                if c.view_span_mm.is_some() {
                    return Err(invalid(
                        "content.view_span_mm",
                        "it is the span of a view grid: set content.views too, or remove it",
                    ));
                }
            }
            Some(n) => {
                if !(2..=MAX_CONTENT_VIEWS).contains(&n) {
                    return Err(invalid(
                        "content.views",
                        format!(
                            "{n}: expected 2 to {MAX_CONTENT_VIEWS} views per side (every view \
                             is warped for each of the light-field panel's views)"
                        ),
                    ));
                }
                for (key, v) in [("content.color", &c.color), ("content.depth", &c.depth)] {
                    if c.source == ContentSource::Files && !has(v) {
                        return Err(invalid(
                            key,
                            format!(
                                "content.views = {n} needs {VIEW_MARK} in the pattern, where each \
                                 view's <row>_<column> goes (e.g. \"lf/view_{VIEW_MARK}.png\" for \
                                 view_00_00.png ...)"
                            ),
                        ));
                    }
                }
                if let Some(s) = c.view_span_mm {
                    if !(s.is_finite() && s > 0.0 && s <= 100.0) {
                        return Err(invalid(
                            "content.view_span_mm",
                            format!("{s}: expected a span of 0 to 100 mm"),
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    /// Whether each eye gets its own image (`display.layout` is not "one").
    pub fn stereo(&self) -> bool {
        self.display.layout.stereo()
    }

    /// Where the API listens. A non-loopback address needs `api.allow_remote = true`.
    pub fn listen(&self) -> Result<Listen, ConfigError> {
        let a = &self.api;
        match (&a.listen, &a.unix) {
            (Some(_), Some(_)) => Err(invalid(
                "api",
                "give either listen (TCP) or unix (a socket path), not both",
            )),
            (None, Some(p)) => Ok(Listen::Unix(p.clone())),
            (listen, None) => {
                let s = listen.as_deref().unwrap_or(DEFAULT_LISTEN);
                let addr: SocketAddr = s.parse().map_err(|_| {
                    invalid(
                        "api.listen",
                        format!(
                            "{s:?} is not an address: expected IP:PORT, e.g. \"127.0.0.1:7420\""
                        ),
                    )
                })?;
                if !addr.ip().is_loopback() && !a.allow_remote {
                    return Err(invalid(
                        "api.listen",
                        format!(
                            "{addr} is reachable from other machines; use 127.0.0.1, or set \
                             api.allow_remote = true and an api.token_file if you mean it"
                        ),
                    ));
                }
                if !addr.ip().is_loopback() && a.token.is_none() && a.token_file.is_none() {
                    return Err(invalid(
                        "api.token_file",
                        format!(
                            "{addr} is reachable from other machines: the API needs a token \
                             (api.token_file, or api.token) that every request must carry"
                        ),
                    ));
                }
                Ok(Listen::Tcp(addr))
            }
        }
    }

    /// The API's bearer token, read from `api.token_file` or taken from `api.token`.
    pub fn api_token(&self) -> Result<Option<String>, ConfigError> {
        let a = &self.api;
        let token = match (&a.token, &a.token_file) {
            (Some(_), Some(_)) => {
                return Err(invalid(
                    "api.token",
                    "give either token or token_file, not both",
                ))
            }
            (Some(t), None) => t.trim().to_string(),
            (None, Some(p)) => std::fs::read_to_string(p)
                .map_err(|e| {
                    invalid(
                        "api.token_file",
                        format!("cannot read {}: {e}", p.display()),
                    )
                })?
                .trim()
                .to_string(),
            (None, None) => return Ok(None),
        };
        // Short tokens can be guessed; a header value cannot hold control characters.
        if token.len() < 16 || !token.bytes().all(|b| b.is_ascii_graphic()) {
            let key = if a.token.is_some() {
                "api.token"
            } else {
                "api.token_file"
            };
            return Err(invalid(
                key,
                "the token must be at least 16 printable ASCII characters without spaces \
                 (e.g. the output of `openssl rand -hex 16`)",
            ));
        }
        Ok(Some(token))
    }
}

/// An optics error under the config key it is about (`section` is where the setting was).
fn optics_error(e: OpticsError, section: &str) -> ConfigError {
    match e {
        OpticsError::Invalid {
            key: "layout",
            message,
        } => invalid(section, message),
        OpticsError::Invalid { key, message } => invalid(&format!("{section}.{key}"), message),
        e @ OpticsError::Table { .. } => invalid(section, e.to_string()),
    }
}

fn one_line(s: &str) -> String {
    s.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join(" ")
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A complete simulated rig; tests edit it.
    pub const SIM_RIG: &str = EXAMPLE_SIM_RIG;

    fn err(text: &str) -> ConfigError {
        match RigConfig::parse(text) {
            Ok(c) => panic!("config accepted: {c:?}"),
            Err(e) => e,
        }
    }

    #[test]
    fn the_example_config_parses() {
        let c = RigConfig::parse(SIM_RIG).unwrap();
        assert_eq!(c.mode, Mode::Varifocal);
        assert_eq!(c.devices.lens.first().port, Port::Sim);
        assert_eq!(
            c.listen().unwrap(),
            Listen::Tcp("127.0.0.1:7420".parse().unwrap())
        );
    }

    /// The example rig with a photodiode (`photodiode` its section's lines) and `display`
    /// lines added to [display].
    fn with_photodiode(photodiode: &str, display: &str) -> String {
        let t = SIM_RIG.replace("png_every = 0 ", &format!("{display}\npng_every = 0 "));
        assert_ne!(t, SIM_RIG);
        format!("{t}\n[devices.photodiode]\n{photodiode}\n")
    }

    const PATCH: &str = "marker_patch = { corner = \"top-left\", size = 8 }";

    #[test]
    fn a_photodiode_and_its_marker_patch_are_checked_naming_the_key() {
        let ok = RigConfig::parse(&with_photodiode(
            "driver = \"serial-line\"\nport = \"sim\"",
            PATCH,
        ))
        .unwrap();
        let m = ok.display.marker_patch.as_ref().unwrap();
        assert_eq!((m.corner, m.size), (Corner::TopLeft, 8));
        assert_eq!(m.toggle_on, [MarkerEvent::Frame]);
        assert!(ok.photodiode_simulated());
        // The sync board's input: no port of its own, and a band.
        let on_board = RigConfig::parse(&with_photodiode(
            "driver = \"sync\"\nthreshold = 0.3\nhysteresis = 0.02",
            PATCH,
        ))
        .unwrap();
        let p = on_board.devices.photodiode.as_ref().unwrap();
        assert!(p.on_sync_board());
        assert_eq!((p.band().threshold, p.band().hysteresis), (0.3, 0.02));
        assert!(on_board.photodiode_simulated());

        for (photodiode, display, key, says) in [
            (
                "driver = \"serial-line\"",
                PATCH,
                "devices.photodiode.port",
                "needs the microcontroller's port",
            ),
            (
                "driver = \"serial-line\"\nport = \"sim\"\nthreshold = 0.4",
                PATCH,
                "devices.photodiode.threshold",
                "trimmer",
            ),
            (
                "driver = \"sync\"\nthreshold = 0.98",
                PATCH,
                "devices.photodiode.threshold",
                "strictly inside",
            ),
            (
                "driver = \"serial-line\"\nport = \"127.0.0.1:5000\"",
                PATCH,
                "devices.photodiode.port",
                "device path",
            ),
            (
                "driver = \"serial-line\"\nport = \"sim\"",
                "",
                "display.marker_patch",
                "no marker patch",
            ),
            (
                "driver = \"serial-line\"\nport = \"sim\"",
                "marker_patch = { size = 0 }",
                "display.marker_patch.size",
                "1 to 96",
            ),
            (
                "driver = \"serial-line\"\nport = \"sim\"",
                "marker_patch = { size = 8, toggle_on = [] }",
                "display.marker_patch.toggle_on",
                "name what toggles",
            ),
            (
                "driver = \"serial-line\"\nport = \"sim\"",
                "marker_patch = { size = 8, toggle_on = [\"frame\", \"lens-command\"] }",
                "display.marker_patch.toggle_on",
                "alone",
            ),
            (
                "driver = \"serial-line\"\nport = \"sim\"",
                &format!("{PATCH}\nsim_persistence_ms = 20.0"),
                "display.sim_persistence_ms",
                "one refresh",
            ),
            (
                "driver = \"serial-line\"\nport = \"sim\"",
                &format!("{PATCH}\nsim_photon_latency_ms = -1.0"),
                "display.sim_photon_latency_ms",
                "0 to 200",
            ),
        ] {
            let e = err(&with_photodiode(photodiode, display));
            assert_eq!(e.key(), key, "{photodiode} / {display}: {e}");
            assert!(e.to_string().contains(says), "{e}");
        }
        // The board of [devices.sync] is not opened twice, and a DLPC350 has no input.
        let dlp = with_photodiode("driver = \"sync\"", PATCH).replace(
            "driver = \"sync\"             # sync (the dioptra",
            "driver = \"dlpc350\"          # sync (the dioptra",
        );
        assert_eq!(err(&dlp).key(), "devices.photodiode.driver");
        let same = with_photodiode("driver = \"sync\"\nport = \"/dev/ttyACM3\"", PATCH).replace(
            "port = \"sim\"\n# video_hz",
            "port = \"/dev/ttyACM3\"\n# video_hz",
        );
        let e = err(&same);
        assert_eq!(e.key(), "devices.photodiode.port", "{e}");
        assert!(e.to_string().contains("one link per board"), "{e}");
        // Unknown events are refused by name.
        let e = err(&with_photodiode(
            "driver = \"serial-line\"\nport = \"sim\"",
            "marker_patch = { size = 8, toggle_on = [\"vsync\"] }",
        ));
        assert!(e.to_string().contains("vsync"), "{e}");
    }

    #[test]
    fn lens_range_min_must_be_below_max() {
        let e = err(&SIM_RIG.replace(
            "lens_range = { min = -1.0, max = 4.0 }",
            "lens_range = { min = 3.0, max = 1.0 }",
        ));
        assert_eq!(e.key(), "optics.lens_range");
        assert!(e.to_string().contains("min must be below max"), "{e}");
    }

    #[test]
    fn dlpc350_settings_are_checked_against_the_schedule() {
        let dlp = SIM_RIG.replace("driver = \"sync\"", "driver = \"dlpc350\"");
        assert_ne!(dlp, SIM_RIG);
        let cfg = RigConfig::parse(&dlp).unwrap();
        let s = cfg.devices.sync.as_ref().unwrap();
        assert_eq!(s.driver, SyncDriver::Dlpc350);
        assert_eq!(s.dlpc350_config().vsync_hz, SyncDevice::DEFAULT_VIDEO_HZ);
        // 4 planes at 240 Hz fill one 60 Hz video frame, not a 120 Hz one.
        let fast = dlp.replace("# video_hz = 60.0", "video_hz = 120.0");
        assert_ne!(fast, dlp);
        let e = err(&fast);
        assert_eq!(e.key(), "optics.subframe_hz", "{e}");
        assert!(e.to_string().contains("do not fit"), "{e}");
        // 2 planes at 240 Hz fill one 120 Hz video frame.
        let ok = fast.replace("planes = [0.2, 0.8, 1.4, 2.0]", "planes = [0.5, 1.5]");
        assert_ne!(ok, fast);
        assert_eq!(
            RigConfig::parse(&ok)
                .unwrap()
                .devices
                .sync
                .unwrap()
                .video_hz,
            Some(120.0)
        );
        let e = err(&fast.replace("video_hz = 120.0", "video_hz = 0.0"));
        assert_eq!(e.key(), "devices.sync.video_hz", "{e}");
        // The sync board follows the display's vsync: a video rate there is a mistake.
        let e = err(&fast.replace("driver = \"dlpc350\"", "driver = \"sync\""));
        assert_eq!(e.key(), "devices.sync.video_hz", "{e}");
        assert!(e.to_string().contains("only the dlpc350 driver"), "{e}");
    }

    #[test]
    fn content_animate_is_for_the_procedural_scene() {
        let still = SIM_RIG.to_string() + "\n[content]\nanimate = false\n";
        assert_eq!(
            RigConfig::parse(&still).unwrap().content.animate,
            Some(false)
        );
        let e = err(&(SIM_RIG.to_string()
            + "\n[content]\nsource = \"stream\"\nring = \"none\"\nanimate = true\n"));
        assert_eq!(e.key(), "content.animate", "{e}");
        assert!(e.to_string().contains("source = \"scene\""), "{e}");
    }

    #[test]
    fn unknown_keys_are_named() {
        let e = err(&SIM_RIG.replace("[optics]", "[optics]\nfocal_lenght = 3"));
        assert_eq!(e.key(), "optics.focal_lenght", "{e}");
        let s = e.to_string();
        assert!(s.contains("unknown field `focal_lenght`"), "{s}");
        assert!(s.contains("expected one of `lens_range`"), "{s}");
    }

    #[test]
    fn wrong_types_name_the_key_and_form() {
        let e = err(&SIM_RIG.replace("park_power = 0.5", "park_power = \"far\""));
        assert_eq!(e.key(), "devices.lens.park_power", "{e}");
        assert!(e.to_string().contains("expected f32"), "{e}");
        let line = SIM_RIG
            .lines()
            .position(|l| l.starts_with("park_power"))
            .unwrap()
            + 1;
        assert!(e.to_string().contains(&format!("(line {line})")), "{e}");
    }

    #[test]
    fn method_auto_plans_varifocal_frames_only() {
        let cfg =
            RigConfig::parse(&SIM_RIG.replace("method = \"gather\"", "method = \"auto\"")).unwrap();
        assert!(cfg.auto_method);
        // The scheduler paces frames by the mode's default method.
        assert_eq!(cfg.method, Method(RenderMethod::Gather));
        assert!(!RigConfig::parse(SIM_RIG).unwrap().auto_method);
        let e = err(&SIM_RIG
            .replace("method = \"gather\"", "method = \"auto\"")
            .replace("mode = \"varifocal\"", "mode = \"multifocal\""));
        assert_eq!(e.key(), "method", "{e}");
        assert!(e.to_string().contains("varifocal mode only"), "{e}");
        // An unknown method's message offers auto.
        let e = err(&SIM_RIG.replace("method = \"gather\"", "method = \"fast\""));
        assert!(e.to_string().contains("auto"), "{e}");
    }

    #[test]
    fn unknown_mode_lists_the_modes() {
        let e = err(&SIM_RIG.replace("mode = \"varifocal\"", "mode = \"holographic\""));
        assert_eq!(e.key(), "mode");
        let s = e.to_string();
        assert!(s.contains("varifocal") && s.contains("multifocal"), "{s}");
    }

    #[test]
    fn bad_ports_say_the_accepted_forms() {
        let e = err(&SIM_RIG.replace("port = \"sim\"\npark_power", "port = \"COM3\"\npark_power"));
        assert_eq!(e.key(), "devices.lens.port", "{e}");
        assert!(e.to_string().contains("VID:PID"), "{e}");
        let ok = RigConfig::parse(&SIM_RIG.replace(
            "port = \"sim\"\npark_power",
            "port = \"/dev/ttyACM0\"\npark_power",
        ))
        .unwrap();
        assert_eq!(
            ok.devices.lens.first().port,
            Port::Path("/dev/ttyACM0".into())
        );
    }

    /// The lens controller's USB bulk endpoints, which `dioptra lens --device lens:usb`
    /// reaches, can be named in a rig config; a driver without them is refused naming the key.
    #[test]
    fn a_usb_bulk_port_is_for_drivers_that_have_one() {
        let port = |s: &str| Port::try_from(s.to_string());
        assert_eq!(port("usb"), Ok(Port::Usb(None)));
        assert_eq!(port("usb:A1B2"), Ok(Port::Usb(Some("A1B2".into()))));
        assert_eq!(String::from(Port::Usb(Some("A1B2".into()))), "usb:A1B2");
        assert!(port("usb:").unwrap_err().contains("usb:SERIAL"));
        let lens = SIM_RIG
            .replace("driver = \"optotune\"", "driver = \"lens\"")
            .replace(
                "port = \"sim\"\npark_power",
                "port = \"usb:A1B2\"\npark_power",
            );
        let c = RigConfig::parse(&lens).unwrap();
        assert_eq!(c.devices.lens.first().port, Port::Usb(Some("A1B2".into())));
        let optotune = SIM_RIG.replace("port = \"sim\"\npark_power", "port = \"usb\"\npark_power");
        let e = err(&optotune);
        assert_eq!(e.key(), "devices.lens.port", "{e}");
        assert!(
            e.to_string()
                .contains("Lens Driver 4 is not reached over USB bulk"),
            "{e}"
        );
        let gaze = SIM_RIG.replace(
            "port = \"sim\"                # pupil",
            "port = \"usb\"                # pupil",
        );
        assert_ne!(gaze, SIM_RIG);
        assert_eq!(err(&gaze).key(), "devices.gaze.port");
    }

    /// `[devices.lens.left]` and `[devices.lens.right]`: a lens per eye, each a full lens
    /// section checked under its own keys; half a pair, or one lens's keys beside the pair, is
    /// refused naming the key; one `[devices.lens]` is one lens as before.
    #[test]
    fn a_lens_per_eye_is_two_full_sections() {
        let c = RigConfig::parse(EXAMPLE_SIM_BINOCULAR_RIG).unwrap();
        assert_eq!(c.devices.lens.count(), 2);
        assert_eq!(c.devices.lens.side(1), Some(Side::Right));
        assert_eq!(c.devices.lens.name(1), "lens_right");
        assert_eq!(c.devices.lens.key(0), "devices.lens.left");
        // It goes through TOML and back (recordings keep the config).
        let again = RigConfig::parse(&toml::to_string(&c).unwrap()).unwrap();
        assert_eq!(again.devices.lens, c.devices.lens);
        let one = RigConfig::parse(SIM_RIG).unwrap();
        assert!(matches!(one.devices.lens, Lenses::One(_)));
        assert_eq!(one.devices.lens.name(0), "lens");
        let again = RigConfig::parse(&toml::to_string(&one).unwrap()).unwrap();
        assert_eq!(again.devices.lens, one.devices.lens);
        // The right's own keys are checked under its own name.
        let bad = EXAMPLE_SIM_BINOCULAR_RIG.replace(
            "[devices.lens.right]\ndriver = \"optotune\"\nport = \"sim\"\npark_power = 0.5",
            "[devices.lens.right]\ndriver = \"optotune\"\nport = \"sim\"\npark_power = 9.5",
        );
        assert_ne!(bad, EXAMPLE_SIM_BINOCULAR_RIG);
        let e = err(&bad);
        assert_eq!(e.key(), "devices.lens.right.park_power", "{e}");
        let bad = EXAMPLE_SIM_BINOCULAR_RIG.replace(
            "sim_settle_ms = 15.0\n\n[devices.gaze]",
            "sim_settle_ms = 15.0\nbogus = 1\n\n[devices.gaze]",
        );
        assert_ne!(bad, EXAMPLE_SIM_BINOCULAR_RIG);
        let e = err(&bad);
        assert_eq!(e.key(), "devices.lens.right.bogus", "{e}");
        // A right lens without a left one; a left without a right; one lens's keys beside both.
        let right_only =
            EXAMPLE_SIM_BINOCULAR_RIG.replace("[devices.lens.left]", "[devices.lens.unused]");
        let e = err(&right_only);
        assert!(e.to_string().contains("unused"), "{e}");
        let start = EXAMPLE_SIM_BINOCULAR_RIG
            .find("[devices.lens.left]")
            .unwrap();
        let end = EXAMPLE_SIM_BINOCULAR_RIG
            .find("[devices.lens.right]")
            .unwrap();
        let no_left = format!(
            "{}{}",
            &EXAMPLE_SIM_BINOCULAR_RIG[..start],
            &EXAMPLE_SIM_BINOCULAR_RIG[end..]
        );
        let e = err(&no_left);
        assert_eq!(e.key(), "devices.lens", "{e}");
        assert!(
            e.to_string().contains("a right lens without a left one"),
            "{e}"
        );
        let gaze = EXAMPLE_SIM_BINOCULAR_RIG.find("[devices.gaze]").unwrap();
        let no_right = format!(
            "{}{}",
            &EXAMPLE_SIM_BINOCULAR_RIG[..end],
            &EXAMPLE_SIM_BINOCULAR_RIG[gaze..]
        );
        let e = err(&no_right);
        assert!(
            e.to_string().contains("a left lens without a right one"),
            "{e}"
        );
        let mixed = EXAMPLE_SIM_BINOCULAR_RIG.replace(
            "[devices.lens.left]",
            "[devices.lens]\npark_power = 0.5\n\n[devices.lens.left]",
        );
        let e = err(&mixed);
        assert!(
            e.to_string().contains("devices.lens.left.park_power"),
            "{e}"
        );
    }

    #[test]
    fn ports_tell_vid_pids_from_network_addresses() {
        let port = |s: &str| Port::try_from(s.to_string());
        assert_eq!(port("1209:d10a"), Ok(Port::VidPid(0x1209, 0xd10a)));
        // Four digits each side are hex: a VID:PID, never a host.
        assert_eq!(port("1234:5678"), Ok(Port::VidPid(0x1234, 0x5678)));
        for a in [
            "127.0.0.1:50020",
            "localhost:50020",
            "[::1]:50020",
            "capture.lab:50020",
        ] {
            assert_eq!(port(a), Ok(Port::Net(a.into())), "{a}");
            assert_eq!(String::from(Port::Net(a.into())), a);
        }
        for bad in [
            "capture:50020",
            "127.0.0.1:0",
            "127.0.0.1:70000",
            "127.0.0.1:",
            "localhost",
            ".lab:1",
            "::1:50020",
            "1209:d10",
        ] {
            let e = port(bad).unwrap_err();
            assert!(
                e.contains("host:port") && e.contains("VID:PID"),
                "{bad}: {e}"
            );
        }
    }

    #[test]
    fn the_pupil_driver_takes_an_address_and_a_confidence_threshold() {
        let pupil = SIM_RIG.replace("driver = \"dioptra-tracker\"", "driver = \"pupil\"");
        assert_ne!(pupil, SIM_RIG);
        let c = RigConfig::parse(&pupil).unwrap();
        assert_eq!(c.devices.gaze.driver, GazeDriver::Pupil);
        assert_eq!(c.devices.gaze.min_confidence, 0.6);
        let net = pupil.replace(
            "port = \"sim\"                # pupil",
            "port = \"127.0.0.1:50020\"\nmin_confidence = 0.8 # pupil",
        );
        assert_ne!(net, pupil);
        let c = RigConfig::parse(&net).unwrap();
        assert_eq!(c.devices.gaze.port, Port::Net("127.0.0.1:50020".into()));
        assert_eq!(c.devices.gaze.min_confidence, 0.8);
        let e = err(&net.replace("min_confidence = 0.8", "min_confidence = 1.2"));
        assert_eq!(e.key(), "devices.gaze.min_confidence", "{e}");
        // A path is not where Pupil Capture is; an address is not where a HID tracker is.
        let e = err(&pupil.replace(
            "port = \"sim\"                # pupil",
            "port = \"/dev/hidraw0\" # pupil",
        ));
        assert_eq!(e.key(), "devices.gaze.port", "{e}");
        let e = err(&SIM_RIG.replace(
            "port = \"sim\"                # pupil",
            "port = \"127.0.0.1:50020\" # pupil",
        ));
        assert_eq!(e.key(), "devices.gaze.port", "{e}");
        assert!(e.to_string().contains("pupil"), "{e}");
    }

    #[test]
    fn missing_sections_are_named() {
        let start = SIM_RIG.find("[devices.gaze]").unwrap();
        let end = SIM_RIG.find("[optics]").unwrap();
        let text = format!("{}{}", &SIM_RIG[..start], &SIM_RIG[end..]);
        let e = err(&text);
        assert!(e.to_string().contains("missing field `gaze`"), "{e}");
        assert_eq!(e.key(), "devices");
    }

    #[test]
    fn park_power_must_be_inside_the_lens_range() {
        let e = err(&SIM_RIG.replace("park_power = 0.5", "park_power = 9.0"));
        assert_eq!(e.key(), "devices.lens.park_power");
    }

    #[test]
    fn multifocal_needs_a_sync_board_and_a_decomposition() {
        let text = SIM_RIG.replace("mode = \"varifocal\"", "mode = \"multifocal\"");
        let start = text.find("[devices.sync]").unwrap();
        let end = text.find("[optics]").unwrap();
        let no_sync = format!("{}{}", &text[..start], &text[end..]);
        assert_eq!(err(&no_sync).key(), "devices.sync");
        let e = err(&text);
        assert_eq!(e.key(), "method");
        assert!(e.to_string().contains("linear, optimized"), "{e}");
        let ok = RigConfig::parse(&text.replace("method = \"gather\"", "method = \"linear\""));
        assert!(ok.is_ok(), "{ok:?}");
    }

    /// Relative paths are the config file's folder's, from any working directory (issue 39
    /// item 3); absolute ones stay.
    #[test]
    fn relative_paths_are_read_from_the_config_files_folder() {
        let dir = tempfile::tempdir().unwrap();
        let text = SIM_RIG.replace("dir = \"recordings\"", "dir = \"rec\"")
            + "\n[content]\nsource = \"files\"\ncolor = \"stim/c_%04d.png\"\n\
               depth = \"/abs/d.exr\"\n\n[render]\nweights = \"w\"\n";
        let path = dir.path().join("rig.toml");
        std::fs::write(&path, &text).unwrap();
        let cfg = RigConfig::load(&path).unwrap();
        let base = std::path::absolute(dir.path()).unwrap();
        assert_eq!(cfg.recording.as_ref().unwrap().dir, base.join("rec"));
        assert_eq!(
            cfg.content.color.as_deref(),
            Some(base.join("stim/c_%04d.png").to_str().unwrap())
        );
        assert_eq!(cfg.content.depth.as_deref(), Some("/abs/d.exr"));
        assert_eq!(cfg.render.weights, Some(base.join("w")));
        // Text without a file: the working directory's, as before.
        let cfg = RigConfig::parse(&text).unwrap();
        assert_eq!(cfg.recording.unwrap().dir, PathBuf::from("rec"));
    }

    /// `devices.*.required`: true for a real port by default, false for a simulator; the
    /// config can say otherwise.
    #[test]
    fn devices_are_required_by_default_on_a_real_port() {
        let cfg = RigConfig::parse(SIM_RIG).unwrap();
        assert!(cfg.devices.list().iter().all(|d| !d.required));
        let real = SIM_RIG.replacen("port = \"sim\"", "port = \"/dev/ttyACM0\"", 1);
        let cfg = RigConfig::parse(&real).unwrap();
        let list = cfg.devices.list();
        assert_eq!((list[0].name.as_str(), list[0].required), ("lens", true));
        let optional = real.replacen("park_power", "required = false\npark_power", 1);
        assert!(!RigConfig::parse(&optional).unwrap().devices.list()[0].required);
    }

    #[test]
    fn pupil_and_settle_times_are_checked_as_their_messages_say() {
        let e = err(&SIM_RIG.replace("pupil_mm = 4.0", "pupil_mm = 40.0"));
        assert_eq!(e.key(), "eye.pupil_mm", "{e}");
        assert!(e.to_string().contains("1 to 10 mm (got 40"), "{e}");
        assert!(RigConfig::parse(&SIM_RIG.replace("pupil_mm = 4.0", "pupil_mm = 8.0")).is_ok());
        // 0 is refused, and the message says so.
        let e = err(&SIM_RIG.replace("sim_settle_ms = 0.8", "sim_settle_ms = 0.0"));
        assert_eq!(e.key(), "devices.sync.sim_settle_ms", "{e}");
        assert!(
            e.to_string()
                .contains("above 0 and at most 1000 ms (got 0)"),
            "{e}"
        );
        let e = err(&SIM_RIG.replace("sim_settle_ms = 15.0", "sim_settle_ms = 0.0"));
        assert_eq!(e.key(), "devices.lens.sim_settle_ms", "{e}");
        assert!(e.to_string().contains("above 0 and at most 1000 ms"), "{e}");
    }

    #[test]
    fn the_display_layout_and_its_monitors_and_offsets_are_checked() {
        let with = |extra: &str| {
            let (kind, rest) = match extra.strip_prefix("kind = \"window\"\n") {
                Some(rest) => ("window", rest),
                None => ("headless", extra),
            };
            SIM_RIG
                .replacen("kind = \"headless\"", &format!("kind = \"{kind}\""), 1)
                .replacen("[display]", &format!("[display]\n{rest}"), 1)
        };
        let c = RigConfig::parse(&with(
            "layout = \"side-by-side\"\neye_offset_px = { left = [-12, 0], right = [12, 3] }",
        ))
        .unwrap();
        assert_eq!(c.display.layout, DisplayLayout::SideBySide);
        assert!(c.stereo());
        assert_eq!(c.display.eye_offset_px.of(Side::Right), [12, 3]);
        assert_eq!(c.display.scale, Scale::Exact);
        let c = RigConfig::parse(&with("scale = \"fit\"")).unwrap();
        assert_eq!(c.display.scale, Scale::Fit);
        assert!(!c.stereo());
        // Headless two-outputs: an image per eye, no monitors.
        assert!(RigConfig::parse(&with("layout = \"two-outputs\"")).is_ok());
        for (extra, key) in [
            ("layout = \"sideways\"", "display.layout"),
            (
                "layout = \"two-outputs\"\nmonitor_left = 0",
                "display.monitor_left",
            ),
            (
                "kind = \"window\"\nlayout = \"two-outputs\"\nmonitor_left = 0",
                "display.monitor_right",
            ),
            (
                "kind = \"window\"\nlayout = \"two-outputs\"\nmonitor_left = 1\nmonitor_right = 1",
                "display.monitor_right",
            ),
            (
                "kind = \"window\"\nlayout = \"two-outputs\"\nmonitor = 0",
                "display.monitor",
            ),
            (
                "kind = \"window\"\nlayout = \"side-by-side\"\nmonitor_right = 1",
                "display.monitor_right",
            ),
            (
                "eye_offset_px = { right = [4, 0] }",
                "display.eye_offset_px.right",
            ),
            (
                "layout = \"side-by-side\"\neye_offset_px = { left = [9000, 0] }",
                "display.eye_offset_px.left",
            ),
        ] {
            let e = err(&with(extra));
            assert_eq!(e.key(), key, "{extra}: {e}");
        }
        let two = RigConfig::parse(&with(
            "kind = \"window\"\nlayout = \"two-outputs\"\nmonitor_left = \"DP-1\"\nmonitor_right = \"DP-2\"",
        ))
        .unwrap();
        assert_eq!(
            two.display.monitor_right,
            Some(MonitorChoice::Name("DP-2".into()))
        );
    }

    #[test]
    fn a_simulated_multifocal_lens_slower_than_the_dark_allowance_is_refused() {
        let slow = SIM_RIG.replace("sim_settle_ms = 0.8", "sim_settle_ms = 1.2");
        let e = err(&slow);
        assert_eq!(e.key(), "devices.sync.sim_settle_ms", "{e}");
        assert!(e.to_string().contains("optics.subframe_hz"), "{e}");
        // At 120 Hz sub-frames the dark quarter is 2.08 ms: 1.2 ms fits.
        assert!(
            RigConfig::parse(&slow.replace("subframe_hz = 240.0", "subframe_hz = 120.0")).is_ok()
        );
    }

    #[test]
    fn optotune_temperature_limits_are_checked() {
        let with = |v: &str| {
            SIM_RIG.replace(
                "park_power = 0.5",
                &format!("park_power = 0.5\ntemperature_limits_c = {v}"),
            )
        };
        let ok = RigConfig::parse(&with("[15.0, 45.0]")).unwrap();
        assert_eq!(
            ok.devices.lens.first().temperature_limits_c,
            Some([15.0, 45.0])
        );
        for bad in ["[45.0, 15.0]", "[-200.0, 40.0]", "[20.0, nan]"] {
            let e = err(&with(bad));
            assert_eq!(e.key(), "devices.lens.temperature_limits_c", "{bad}: {e}");
        }
        let other = with("[15.0, 45.0]").replace("driver = \"optotune\"", "driver = \"lens\"");
        assert_eq!(err(&other).key(), "devices.lens.temperature_limits_c");
    }

    #[test]
    fn a_remote_listen_address_needs_allow_remote() {
        let text = SIM_RIG.replace("127.0.0.1:7420", "0.0.0.0:7420");
        let e = err(&text);
        assert_eq!(e.key(), "api.listen");
        assert!(e.to_string().contains("allow_remote"), "{e}");
        // Reachable from other machines: only with a token.
        let remote = text.replace("[api]", "[api]\nallow_remote = true");
        assert_eq!(err(&remote).key(), "api.token_file");
        let with_token = remote.replace("[api]", "[api]\ntoken = \"0123456789abcdef0123\"");
        let ok = RigConfig::parse(&with_token).unwrap();
        assert!(matches!(ok.listen().unwrap(), Listen::Tcp(a) if !a.ip().is_loopback()));
        assert_eq!(
            ok.api_token().unwrap().as_deref(),
            Some("0123456789abcdef0123")
        );
        let e = err(&remote.replace("[api]", "[api]\ntoken = \"short\""));
        assert_eq!(e.key(), "api.token");
        let e = err(&SIM_RIG.replace("127.0.0.1:7420", "localhost"));
        assert!(e.to_string().contains("IP:PORT"), "{e}");
    }

    #[test]
    fn toml_syntax_errors_say_where() {
        let e = err("mode = varifocal");
        assert!(e.to_string().contains("line 1"), "{e}");
    }

    #[test]
    fn the_display_kind_and_monitor_parse() {
        let win = |extra: &str| {
            RigConfig::parse(&SIM_RIG.replace(
                "kind = \"headless\"",
                &format!("kind = \"window\"\n{extra}"),
            ))
        };
        let c = win("monitor = \"HDMI-1\"").unwrap();
        assert_eq!(c.display.kind, SinkKind::Window);
        assert_eq!(
            c.display.monitor,
            Some(MonitorChoice::Name("HDMI-1".into()))
        );
        let c = win("monitor = 1").unwrap();
        assert_eq!(c.display.monitor, Some(MonitorChoice::Index(1)));
        assert_eq!(win("").unwrap().display.monitor, None);
        let e = win("monitor = 1.5").unwrap_err();
        assert_eq!(e.key(), "display.monitor", "{e}");
        assert!(e.to_string().contains("a monitor name such as"), "{e}");
        let e = err(&SIM_RIG.replace("kind = \"headless\"", "kind = \"screen\""));
        assert_eq!(e.key(), "display.kind", "{e}");
        assert!(
            e.to_string().contains("expected `headless` or `window`"),
            "{e}"
        );
        // A monitor without the window is a mistake worth naming.
        let e = err(&SIM_RIG.replace("kind = \"headless\"", "kind = \"headless\"\nmonitor = 0"));
        assert_eq!(e.key(), "display.monitor", "{e}");
        // The older key name still reads.
        let c =
            RigConfig::parse(&SIM_RIG.replace("kind = \"headless\"", "sink = \"window\"")).unwrap();
        assert_eq!(c.display.kind, SinkKind::Window);
    }

    /// `text` with `extra` added to the end of its `[optics]` section.
    fn with_optics(text: &str, extra: &str) -> String {
        text.replace(
            "subframe_hz = 240.0\n",
            &format!("subframe_hz = 240.0\n{extra}\n"),
        )
    }

    #[test]
    fn old_configs_with_display_distance_still_load_and_say_where_it_moved() {
        assert!(!SIM_RIG.contains("\ndisplay_distance_m"));
        let old = SIM_RIG.replace("[optics]\n", "[optics]\ndisplay_distance_m = 1.0\n");
        assert_ne!(old, SIM_RIG);
        let c = RigConfig::parse(&old).unwrap();
        assert!(c.optics_map(None).unwrap().is_identity());
        let notes = c.notices().join("\n");
        assert!(
            notes.contains("optics.display_distance_m is no longer read")
                && notes.contains("[optics.layout] display_distance_m"),
            "{notes}"
        );
        assert!(RigConfig::parse(SIM_RIG).unwrap().notices().is_empty());
        // Beside a layout it is a mistake.
        let e = err(&with_optics(
            &old,
            "[optics.layout]\ndisplay_distance_m = 0.05\neye_relief_m = 0.0",
        ));
        assert_eq!(e.key(), "optics.display_distance_m", "{e}");
        assert!(e.to_string().contains("moved to [optics.layout]"), "{e}");
    }

    #[test]
    fn nothing_configured_is_the_identity_map() {
        let c = RigConfig::parse(SIM_RIG).unwrap();
        for side in [None, Some(Side::Left), Some(Side::Right)] {
            let m = c.optics_map(side).unwrap();
            assert!(m.is_identity());
            assert_eq!(m.command_for(Diopters(1.5)), Diopters(1.5));
        }
    }

    #[test]
    fn optics_layouts_tables_and_prescriptions_resolve_per_eye() {
        let dir = tempfile::tempdir().unwrap();
        // A table measured on the left eye: demand 2 - command, every 0.5 D over the range.
        let rows: String = (0..=10)
            .map(|k| {
                let c = -1.0 + 0.5 * f64::from(k);
                format!("{c},{}\n", 2.0 - c)
            })
            .collect();
        std::fs::create_dir(dir.path().join("cal")).unwrap();
        std::fs::write(
            dir.path().join("cal/left.csv"),
            format!("# test\ncommand_d,demand_d\n{rows}"),
        )
        .unwrap();
        let text = with_optics(
            SIM_RIG,
            "prescription_sphere_d = -1.0\nprescription_vertex_mm = 0.0\n\
             [optics.layout]\ndisplay_distance_m = 0.05\neye_relief_m = 0.02\nfixed_power_d = 18.0\n\
             [optics.left]\ncalibration = \"cal/left.csv\"\nprescription_sphere_d = 0.5",
        );
        let path = dir.path().join("rig.toml");
        std::fs::write(&path, &text).unwrap();
        // Loaded from another working directory: the table is found beside the config.
        let c = RigConfig::load(&path).unwrap();
        let left = c.optics_map(Some(Side::Left)).unwrap();
        assert_eq!(left.source_name(), "calibration");
        // Focus 1 D, Rx +0.5 at 0 mm: presented 0.5 D; the table gives command 1.5 D.
        assert!((left.command_for(Diopters(1.0)).0 - 1.5).abs() < 1e-5);
        // The layout still gives the magnification.
        assert!(left.magnification(Diopters(0.0)).is_some());
        // The right eye has the shared layout and prescription: focus 1 D with Rx -1 at 0 mm
        // is presented at 2 D; X = 2 / (1 - 0.04), command = 20 - 18 - X = -0.083333.
        let right = c.optics_map(Some(Side::Right)).unwrap();
        assert_eq!(right.source_name(), "layout");
        assert!((right.command_for(Diopters(1.0)).0 + 0.083333).abs() < 1e-5);
        // The one lens of this rig is the left eye's (the one per-eye section).
        assert_eq!(c.optics_map(None).unwrap(), left);
        // Parsed without a file, the relative path is read from the working directory.
        let e = err(&text);
        assert_eq!(e.key(), "optics.left.calibration", "{e}");
        assert!(
            e.to_string()
                .contains("relative paths are read from the config file's folder"),
            "{e}"
        );
    }

    #[test]
    fn bad_optics_settings_name_the_key_the_file_and_the_points() {
        let dir = tempfile::tempdir().unwrap();
        let load = |extra: &str| {
            let path = dir.path().join("rig.toml");
            std::fs::write(&path, with_optics(SIM_RIG, extra)).unwrap();
            RigConfig::load(&path)
        };
        let e =
            load("[optics.layout]\ndisplay_distance_m = 0.05\neye_relief_m = -0.01").unwrap_err();
        assert_eq!(e.key(), "optics.layout.eye_relief_m", "{e}");
        let e = load("[optics.layout]\ndisplay_distance_m = 0.05").unwrap_err();
        assert_eq!(e.key(), "optics.layout", "{e}");
        assert!(
            e.to_string().contains("missing field `eye_relief_m`"),
            "{e}"
        );
        // The image would reach the eye inside the lens range.
        let e = load(
            "[optics.layout]\ndisplay_distance_m = 0.05\neye_relief_m = 0.05\nfixed_power_d = 38.0",
        )
        .unwrap_err();
        assert_eq!(e.key(), "optics.layout", "{e}");
        let e =
            load("[optics.right]\nprescription_sphere_d = -2.0\nprescription_cylinder_d = -0.5")
                .unwrap_err();
        assert_eq!(e.key(), "optics.right.prescription_cylinder_d", "{e}");
        assert!(e.to_string().contains("spherical equivalent"), "{e}");
        let e = load("calibration = \"nope.csv\"").unwrap_err();
        assert_eq!(e.key(), "optics.calibration", "{e}");
        assert!(
            e.to_string()
                .contains(&dir.path().join("nope.csv").display().to_string()),
            "{e}"
        );
        std::fs::write(
            dir.path().join("bent.csv"),
            "command_d,demand_d\n-1,3\n0,2\n1,2.2\n2,0\n3,-1\n4,-2\n",
        )
        .unwrap();
        let e = load("calibration = \"bent.csv\"").unwrap_err();
        assert_eq!(e.key(), "optics.calibration", "{e}");
        let s = e.to_string();
        assert!(s.contains("bent.csv") && s.contains("not monotonic"), "{s}");
        assert!(
            s.contains(
                "(command 0 D, demand 2 D) (line 3) -> (command 1 D, demand 2.2 D) (line 4)"
            ),
            "{s}"
        );
        std::fs::write(
            dir.path().join("short.csv"),
            "command_d,demand_d\n-1,3\n0,2\n1,1\n2,0\n",
        )
        .unwrap();
        let e = load("calibration = \"short.csv\"").unwrap_err();
        assert!(
            e.to_string().contains("span -1..2 D") && e.to_string().contains("-1..4 D"),
            "{e}"
        );
        let e = load("[optics.left]\nprescription_sphere_d = -1.0\n[optics.right]\nprescription_sphere_d = -2.0").unwrap_err();
        assert_eq!(e.key(), "optics.right", "{e}");
        assert!(e.to_string().contains("one lens"), "{e}");
        let e = load("[optics.left]\nfocal_power = 1").unwrap_err();
        assert_eq!(e.key(), "optics.left.focal_power", "{e}");
    }

    #[test]
    fn the_lens_model_settles_as_the_lens_does() {
        let c = RigConfig::parse(SIM_RIG).unwrap();
        assert_eq!(c.devices.lens.first().model_settle_ms(), 15.0);
        let slow =
            RigConfig::parse(&SIM_RIG.replace("sim_settle_ms = 15.0", "sim_settle_ms = 40.0"))
                .unwrap();
        assert_eq!(slow.devices.lens.first().model_settle_ms(), 40.0);
        // A real lens: its own settle_ms, not the simulator's.
        let real = SIM_RIG.replace(
            "port = \"sim\"\npark_power",
            "port = \"/dev/ttyACM0\"\npark_power",
        );
        assert_ne!(real, SIM_RIG);
        let c = RigConfig::parse(&real.replace("sim_settle_ms = 15.0", "sim_settle_ms = 40.0"))
            .unwrap();
        assert_eq!(
            c.devices.lens.first().model_settle_ms(),
            LensDevice::DEFAULT_SETTLE_MS
        );
        assert!(c
            .notices()
            .join(" ")
            .contains("devices.lens.settle_ms is not set"));
        let c = RigConfig::parse(
            &real.replace("park_power = 0.5", "park_power = 0.5\nsettle_ms = 8.0"),
        )
        .unwrap();
        assert_eq!(c.devices.lens.first().model_settle_ms(), 8.0);
        assert!(c.notices().is_empty());
        let e = err(&real.replace("park_power = 0.5", "park_power = 0.5\nsettle_ms = 0.0"));
        assert_eq!(e.key(), "devices.lens.settle_ms", "{e}");
    }

    #[test]
    fn planes_outside_the_lens_range_are_refused() {
        let e = err(&SIM_RIG.replace("planes = [0.2, 0.8, 1.4, 2.0]", "planes = [0.2, 8.0]"));
        assert_eq!(e.key(), "optics.planes");
    }

    /// `%e` in the files' patterns: each eye's sequence on a stereo layout; refused on a mono
    /// one and in one pattern without the other, naming the key.
    #[test]
    fn eye_patterns_need_a_stereo_layout_and_both_keys() {
        let files = |layout: &str, color: &str, depth: &str| {
            SIM_RIG.replacen("[display]", &format!("[display]\nlayout = \"{layout}\""), 1)
                + &format!(
                    "\n[content]\nsource = \"files\"\ncolor = {color:?}\ndepth = {depth:?}\n"
                )
        };
        let ok = RigConfig::parse(&files("side-by-side", "s/%e/c_%04d.png", "s/%e/d_%04d.exr"));
        assert!(ok.is_ok(), "{ok:?}");
        // Without %e a stereo rig shows one view (each eye's synthesised).
        assert!(RigConfig::parse(&files("two-outputs", "c.png", "d.exr")).is_ok());
        let e = err(&files("one", "s/%e/c.png", "s/%e/d.exr"));
        assert_eq!(e.key(), "content.color", "{e}");
        assert!(e.to_string().contains("display.layout"), "{e}");
        let e = err(&files("one", "c.png", "d_%e.exr"));
        assert_eq!(e.key(), "content.depth", "{e}");
        let e = err(&files("side-by-side", "c_%e.png", "d.exr"));
        assert_eq!(e.key(), "content.depth", "{e}");
        assert!(e.to_string().contains("content.color names"), "{e}");
        let e = err(&files("side-by-side", "c.png", "d_%e.exr"));
        assert_eq!(e.key(), "content.color", "{e}");
    }

    /// `content.views`: a grid of 2 to 9 views a side with `%v` in both patterns and a span
    /// of 0 to 100 mm; `%v` without it, or a grid with another source, names the key.
    #[test]
    fn a_view_grid_needs_its_mark_its_size_and_files() {
        let files = |extra: &str, color: &str, depth: &str| {
            format!(
                "{SIM_RIG}\n[content]\nsource = \"files\"\ncolor = {color:?}\ndepth = {depth:?}\n{extra}\n"
            )
        };
        let ok = RigConfig::parse(&files("views = 3", "lf/v_%v.png", "lf/v_%v.exr"));
        assert_eq!(ok.map(|c| c.content.views).ok(), Some(Some(3)));
        let ok = RigConfig::parse(&files(
            "views = 2\nview_span_mm = 4.5",
            "lf/%04d/v_%v.png",
            "lf/%04d/v_%v.exr",
        ));
        assert!(ok.is_ok(), "{ok:?}");
        for (extra, color, depth, key, says) in [
            ("", "v_%v.png", "v_%v.exr", "content.color", "content.views"),
            ("views = 3", "v.png", "v_%v.exr", "content.color", "%v"),
            ("views = 3", "v_%v.png", "v.exr", "content.depth", "%v"),
            (
                "views = 1",
                "v_%v.png",
                "v_%v.exr",
                "content.views",
                "2 to 9",
            ),
            (
                "views = 12",
                "v_%v.png",
                "v_%v.exr",
                "content.views",
                "2 to 9",
            ),
            (
                "view_span_mm = 4",
                "v.png",
                "v.exr",
                "content.view_span_mm",
                "views",
            ),
            (
                "views = 3\nview_span_mm = -1",
                "v_%v.png",
                "v_%v.exr",
                "content.view_span_mm",
                "0 to 100",
            ),
            (
                "views = 3\nview_span_mm = nan",
                "v_%v.png",
                "v_%v.exr",
                "content.view_span_mm",
                "0 to 100",
            ),
        ] {
            let e = err(&files(extra, color, depth));
            assert_eq!(e.key(), key, "{extra} {color} {depth}: {e}");
            assert!(e.to_string().contains(says), "{e}");
        }
        let e = err(&format!(
            "{SIM_RIG}\n[content]\nsource = \"scene\"\nviews = 3\n"
        ));
        assert_eq!(e.key(), "content.views", "{e}");
        // A stream takes a grid without patterns.
        let stream = |extra: &str| format!("{SIM_RIG}\n[content]\nsource = \"stream\"\n{extra}\n");
        assert!(RigConfig::parse(&stream("views = 3\nview_span_mm = 4")).is_ok());
        assert_eq!(err(&stream("views = 10")).key(), "content.views");
        assert_eq!(
            err(&stream("view_span_mm = 4")).key(),
            "content.view_span_mm"
        );
    }
}
