//! `[devices]`: the lens (one, or one per eye), the eye tracker, the sync hardware and the
//! photodiode; each device's driver and port, their defaults and checks. Whether a driver's
//! device has USB bulk endpoints comes from its driver crate's match table (`ids`).

use std::path::PathBuf;

use dioptra_core::Side;
use dioptra_transport::discovery::{Interface, KnownDevice};
use serde::de::{self, DeserializeSeed, IntoDeserializer, MapAccess, Visitor};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::config::error::{invalid, one_line, ConfigError};
use crate::mode::Mode;
use crate::optics::config::Optics;

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

/// `[devices.lens]`: one lens (a monocular bench, or one lens both eyes look through), or a
/// lens per eye in `[devices.lens.left]` and `[devices.lens.right]`, each a full lens section.
#[derive(Debug, Clone, PartialEq)]
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

/// `[devices.lens]` is read as one lens's keys ([`LensDevice`]), with `left` and `right`
/// taken aside as they come: each is a whole [`LensDevice`] of its own. Errors keep their keys
/// (`devices.lens.park_power`, `devices.lens.right.bogus`), since every key and value is read
/// through the map the config's reader hands in.
impl<'de> Deserialize<'de> for Lenses {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Lenses, D::Error> {
        d.deserialize_map(LensesVisitor)
    }
}

impl Serialize for Lenses {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        match self {
            Lenses::One(l) => l.serialize(s),
            Lenses::PerEye { left, right } => {
                let mut m = s.serialize_map(Some(2))?;
                m.serialize_entry("left", left)?;
                m.serialize_entry("right", right)?;
                m.end()
            }
        }
    }
}

/// What `[devices.lens]` held besides one lens's keys.
#[derive(Default)]
struct EyeTables {
    left: Option<LensDevice>,
    right: Option<LensDevice>,
    /// One lens's keys given, in order.
    one_keys: Vec<String>,
    /// The table was read to its end.
    ended: bool,
}

struct LensesVisitor;

impl<'de> Visitor<'de> for LensesVisitor {
    type Value = Lenses;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("one lens's keys, or the tables [devices.lens.left] and [devices.lens.right]")
    }

    fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<Lenses, A::Error> {
        let mut eyes = EyeTables::default();
        let one = LensDevice::deserialize(de::value::MapAccessDeserializer::new(SplitEyes {
            map,
            eyes: &mut eyes,
        }));
        // An error before the table's end is in a key or a value: it says which.
        let one = match one {
            Err(e) if !eyes.ended => return Err(e),
            one => one,
        };
        match (eyes.left, eyes.right) {
            (Some(left), Some(right)) => match eyes.one_keys.first() {
                Some(k) => Err(de::Error::custom(format!(
                    "{k}: with [devices.lens.left] and [devices.lens.right], each lens's keys go in its own table (devices.lens.left.{k}, devices.lens.right.{k})"
                ))),
                None => Ok(Lenses::PerEye { left, right }),
            },
            (None, Some(_)) => Err(de::Error::custom(
                "right: a right lens without a left one: add [devices.lens.left], or give one lens in [devices.lens] (a monocular bench, or one lens both eyes look through)",
            )),
            (Some(_), None) => Err(de::Error::custom(
                "left: a left lens without a right one: add [devices.lens.right], or give one lens in [devices.lens] (a monocular bench, or one lens both eyes look through)",
            )),
            // After the table's end only a missing key is left to refuse.
            (None, None) => one.map(Lenses::One).map_err(|e| {
                de::Error::custom(format!(
                    "{} (one lens: driver, port and park_power; a lens per eye: [devices.lens.left] and [devices.lens.right])",
                    one_line(&e.to_string())
                ))
            }),
        }
    }
}

/// `[devices.lens]`'s entries as one lens's, with `left` and `right` read into `eyes`.
struct SplitEyes<'a, A> {
    map: A,
    eyes: &'a mut EyeTables,
}

/// A key of `[devices.lens]`: one lens's, or an eye's table.
enum LensKey<K> {
    One(K),
    Eye(Side),
}

impl<'de, A: MapAccess<'de>> MapAccess<'de> for SplitEyes<'_, A> {
    type Error = A::Error;

    fn next_key_seed<K: DeserializeSeed<'de>>(
        &mut self,
        seed: K,
    ) -> Result<Option<K::Value>, A::Error> {
        let mut seed = Some(seed);
        loop {
            let key = self.map.next_key_seed(OneLensKey {
                seed: &mut seed,
                one_keys: &mut self.eyes.one_keys,
            })?;
            match key {
                None => {
                    self.eyes.ended = true;
                    return Ok(None);
                }
                Some(LensKey::One(k)) => return Ok(Some(k)),
                Some(LensKey::Eye(Side::Left)) => self.eyes.left = Some(self.map.next_value()?),
                Some(LensKey::Eye(Side::Right)) => self.eyes.right = Some(self.map.next_value()?),
            }
        }
    }

    fn next_value_seed<V: DeserializeSeed<'de>>(&mut self, seed: V) -> Result<V::Value, A::Error> {
        self.map.next_value_seed(seed)
    }
}

/// Reads a key: `left` and `right` are the eyes' tables, any other goes to one lens's keys.
struct OneLensKey<'a, K> {
    seed: &'a mut Option<K>,
    one_keys: &'a mut Vec<String>,
}

impl<'de, K: DeserializeSeed<'de>> DeserializeSeed<'de> for OneLensKey<'_, K> {
    type Value = LensKey<K::Value>;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        let name = String::deserialize(d)?;
        match name.as_str() {
            "left" => return Ok(LensKey::Eye(Side::Left)),
            "right" => return Ok(LensKey::Eye(Side::Right)),
            _ => {}
        }
        // Taken once: the key seed is asked again only after its value is read.
        let Some(seed) = self.seed.take() else {
            return Err(de::Error::custom(format!("{name}: read twice")));
        };
        let key = seed
            .deserialize(name.as_str().into_deserializer())
            .map_err(|e: D::Error| {
                de::Error::custom(format!(
                    "{}, or the tables `left` and `right` (a lens per eye)",
                    one_line(&e.to_string())
                ))
            })?;
        self.one_keys.push(name);
        Ok(LensKey::One(key))
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

impl LensDriver {
    /// Its name in the rig config and the driver crate's match table.
    pub fn name(self) -> &'static str {
        match self {
            LensDriver::Optotune => "optotune",
            LensDriver::Lens => "lens",
        }
    }
}

impl GazeDriver {
    /// Its name in the rig config and the driver crate's match table.
    pub fn name(self) -> &'static str {
        match self {
            GazeDriver::DioptraTracker => "dioptra-tracker",
            GazeDriver::Hid => "hid",
            GazeDriver::Pupil => dioptra_gaze::pupil::ids::DRIVER,
        }
    }
}

impl SyncDriver {
    /// Its name in the rig config and the driver crate's match table.
    pub fn name(self) -> &'static str {
        match self {
            SyncDriver::Sync => "sync",
            SyncDriver::Dlpc350 => "dlpc350",
        }
    }
}

/// Whether driver `name`'s device is reached over USB bulk endpoints, as its driver crate's
/// match table (`known`) says, and what the table calls the device.
fn usb_bulk(known: &[KnownDevice], name: &str) -> (bool, Option<&'static str>) {
    let rows = || known.iter().filter(|k| k.driver == name);
    (
        rows().any(|k| k.interface == Interface::UsbBulk),
        rows().next().map(|k| k.name),
    )
}

impl Devices {
    /// Every device's section, and what spans them (a photodiode on the sync board). The lens
    /// parks inside `optics.lens_range`; the sync hardware must run `optics`' planes;
    /// multifocal `mode` needs sync hardware.
    pub fn check(&self, optics: &Optics, mode: Mode) -> Result<(), ConfigError> {
        for (i, l) in self.lens.each().into_iter().enumerate() {
            check_lens(&self.lens.key(i), l, optics)?;
        }
        let g = &self.gaze;
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
        if let Some(Port::Net(a)) = self.sync.as_ref().map(|s| &s.port) {
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
        if mode == Mode::Multifocal && self.sync.is_none() {
            return Err(invalid(
                "devices.sync",
                "multifocal mode needs sync hardware: add [devices.sync] with driver = \"sync\" (the dioptra sync board) or \"dlpc350\", and a port",
            ));
        }
        if let Some(s) = &self.sync {
            check_sync(s, optics)?;
        }
        if let Some(p) = &self.photodiode {
            self.check_photodiode(p)?;
        }
        Ok(())
    }

    /// A `port = "usb"` only for a driver that talks over USB bulk endpoints (the driver
    /// crates' match tables say which).
    fn check_usb_ports(&self) -> Result<(), ConfigError> {
        let keys: Vec<String> = (0..self.lens.count())
            .map(|i| format!("{}.port", self.lens.key(i)))
            .collect();
        let ports = self
            .lens
            .each()
            .into_iter()
            .zip(&keys)
            .map(|(l, key)| {
                let name = l.driver.name();
                (
                    key.as_str(),
                    &l.port,
                    name,
                    usb_bulk(dioptra_lens::ids::KNOWN_DEVICES, name),
                )
            })
            .chain([(
                "devices.gaze.port",
                &self.gaze.port,
                self.gaze.driver.name(),
                usb_bulk(dioptra_gaze::ids::KNOWN_DEVICES, self.gaze.driver.name()),
            )])
            .chain(self.sync.as_ref().map(|s| {
                (
                    "devices.sync.port",
                    &s.port,
                    s.driver.name(),
                    usb_bulk(dioptra_sync::ids::KNOWN_DEVICES, s.driver.name()),
                )
            }));
        for (key, port, name, (usb, what)) in ports {
            if let (Port::Usb(_), false) = (port, usb) {
                let what = what.map_or_else(|| format!("{name} driver's device"), str::to_string);
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

    /// The photodiode: its port for its driver, and a sync board's comparator band.
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
            (PhotodiodeDriver::Sync, None) => match &self.sync {
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

    /// Whether a photodiode is simulated: its own port is "sim", or it is the input of a
    /// simulated sync board.
    pub fn photodiode_simulated(&self) -> bool {
        self.photodiode.as_ref().is_some_and(|p| match &p.port {
            Some(port) => *port == Port::Sim,
            None => self.sync.as_ref().is_some_and(|s| s.port == Port::Sim),
        })
    }

    /// Defaults a real rig should set: a real lens's settle time.
    pub fn notices(&self) -> Vec<String> {
        let mut out = Vec::new();
        for (i, l) in self.lens.each().into_iter().enumerate() {
            if l.port != Port::Sim && l.settle_ms.is_none() {
                out.push(format!(
                    "{}.settle_ms is not set: the scheduler models the lens as settling \
                     in {} ms (the EL-10-30's datasheet); measure yours with `dioptra lens set D \
                     --watch-ms 100` and set it",
                    self.lens.key(i),
                    LensDevice::DEFAULT_SETTLE_MS
                ));
            }
        }
        out
    }
}

/// The sync device's own settings, and whether it can run the configured schedule.
fn check_sync(s: &SyncDevice, optics: &Optics) -> Result<(), ConfigError> {
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
    let dark_ms = 250.0 / optics.subframe_hz;
    if s.port == Port::Sim && s.sim_settle_ms > dark_ms {
        return Err(invalid(
            "devices.sync.sim_settle_ms",
            format!(
                "the simulated multifocal lens settles in {} ms, longer than the dark quarter \
                 of a sub-frame ({dark_ms:.2} ms at optics.subframe_hz = {}): every sub-frame \
                 would be lit before the lens arrives; lower one of the two",
                s.sim_settle_ms, optics.subframe_hz
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
            let schedule = optics.plane_schedule()?;
            dioptra_sync::dlpc350::PatternSequence::for_schedule(&schedule, &s.dlpc350_config())
                .map_err(|e| {
                    invalid(
                        "optics.subframe_hz",
                        format!(
                            "the DLPC350 cannot run {} planes at {} Hz with {hz} Hz video: {e}",
                            optics.planes.len(),
                            optics.subframe_hz
                        ),
                    )
                })?;
        }
    }
    Ok(())
}

/// One lens's section (`key`: `devices.lens`, `devices.lens.left` or `.right`).
fn check_lens(key: &str, l: &LensDevice, optics: &Optics) -> Result<(), ConfigError> {
    let r = optics.lens_range;
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
            format!(
                "{a}: lenses are reached by device path, VID:PID or \"sim\", not over the network"
            ),
        ));
    }
    Ok(())
}
