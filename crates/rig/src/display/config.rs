//! `[display]`: where frames go (headless or a window, on which monitors, in which layout),
//! the display's size and rate, the marker patch a photodiode watches and the simulated
//! panel; their defaults and checks.

use std::path::PathBuf;

use dioptra_core::transfer::{Transfer, TransferName, TransferSetting, TransferTable};
use dioptra_core::Side;
use serde::{Deserialize, Serialize};

use crate::config::error::{invalid, ConfigError};
use crate::optics::config::Tables;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum SinkKind {
    /// Frame timing (and optionally PNGs) recorded, nothing shown: tests, CI.
    Headless,
    /// A borderless fullscreen window on `display.monitor`, vsync (rigs).
    Window,
}

/// Where the eyes' images go (`display.layout`).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, schemars::JsonSchema,
)]
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
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, schemars::JsonSchema,
)]
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
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(deny_unknown_fields)]
pub struct EyeOffsets {
    /// The left eye's (or the one image's) offset, [right, down] pixels.
    #[serde(default)]
    pub left: [i32; 2],
    /// The right eye's offset, [right, down] pixels.
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
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
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

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Display {
    /// `headless` or `window` (`sink` is the older name of this key).
    #[serde(default = "default_sink", alias = "sink")]
    pub kind: SinkKind,
    /// The window's monitor: a name such as "HDMI-1" or an index; default the primary.
    pub monitor: Option<MonitorChoice>,
    /// `layout = "two-outputs"` with the window: the left eye's monitor, a name such as
    /// "DP-1" or an index (as `display.monitor`). Each eye gets a borderless fullscreen window
    /// on its monitor, drawn 1:1 as the one window is; a monitor not there stops the start
    /// with the list of monitors.
    pub monitor_left: Option<MonitorChoice>,
    /// `layout = "two-outputs"` with the window: the right eye's monitor (not the left's).
    /// Both windows are drawn and presented in the same pass, each at its own monitor's
    /// vsync (not locked together: up to one refresh apart); monitors at different rates go
    /// at the slower one's, with a warning at start.
    pub monitor_right: Option<MonitorChoice>,
    /// One eye's image (per eye on a stereo layout), pixels.
    #[serde(default = "default_size")]
    pub width: u32,
    /// One eye's image height, pixels.
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
    /// The panel's transfer function, which the renderer's linear light is encoded through:
    /// `"srgb"` (default), `"linear"`, `{ gamma = G, black = B }` (BT.1886) or
    /// `{ table = "FILE" }` (`dioptra display calibrate` writes it; relative to the config
    /// file). Every panel's (each projector's in multifocal), unless `transfer_left` /
    /// `transfer_right` give an output's own (`layout = "two-outputs"`).
    pub transfer: Option<TransferSetting>,
    pub transfer_left: Option<TransferSetting>,
    pub transfer_right: Option<TransferSetting>,
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
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "kebab-case")]
pub enum Corner {
    #[default]
    TopLeft,
    TopRight,
    BottomLeft,
    BottomRight,
}

/// What toggles the marker patch between white and black.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
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
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
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
            transfer: None,
            transfer_left: None,
            transfer_right: None,
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

impl Display {
    /// Whether each eye gets its own image (`layout` is not "one").
    pub fn stereo(&self) -> bool {
        self.layout.stereo()
    }

    /// The transfer tables the settings name, each with its key.
    pub fn transfer_files(&self) -> Vec<(&'static str, &PathBuf)> {
        [
            ("display.transfer", &self.transfer),
            ("display.transfer_left", &self.transfer_left),
            ("display.transfer_right", &self.transfer_right),
        ]
        .into_iter()
        .filter_map(|(key, t)| match t {
            Some(TransferSetting::Table { table }) => Some((key, table)),
            _ => None,
        })
        .collect()
    }

    /// The transfer function of an eye's panel (`None`: the one panel), with its key
    /// (`display.transfer`, or the output's own); sRGB when none is given.
    pub fn transfer_of(
        &self,
        side: Option<Side>,
        tables: Tables,
    ) -> Result<(Transfer, &'static str), ConfigError> {
        let own = match side {
            Some(Side::Left) => self
                .transfer_left
                .as_ref()
                .map(|t| (t, "display.transfer_left")),
            Some(Side::Right) => self
                .transfer_right
                .as_ref()
                .map(|t| (t, "display.transfer_right")),
            None => None,
        };
        let Some((setting, key)) = own.or(self.transfer.as_ref().map(|t| (t, "display.transfer")))
        else {
            return Ok((Transfer::Srgb, "display.transfer"));
        };
        let transfer = match setting {
            TransferSetting::Named(TransferName::Srgb) => Transfer::Srgb,
            TransferSetting::Named(TransferName::Linear) => Transfer::linear(),
            TransferSetting::Gamma { gamma, black } => {
                Transfer::gamma(*gamma, *black).map_err(|e| match e {
                    dioptra_core::transfer::TransferError::Invalid { key: k, message } => {
                        let leaf = k.rsplit('.').next().unwrap_or(k);
                        invalid(&format!("{key}.{leaf}"), message)
                    }
                    e => invalid(key, e.to_string()),
                })?
            }
            TransferSetting::Table { table } => {
                let text = tables.text.get(table).ok_or_else(|| {
                    invalid(
                        key,
                        format!("{} was not read with the config", table.display()),
                    )
                })?;
                let name = tables.path(table).display().to_string();
                Transfer::Table(
                    TransferTable::parse_csv(&name, text)
                        .map_err(|e| invalid(key, e.to_string()))?,
                )
            }
        };
        Ok((transfer, key))
    }

    /// The display's size and rate, its monitors and layout, its PNGs.
    pub fn check(&self) -> Result<(), ConfigError> {
        let d = self;
        if d.layout != DisplayLayout::TwoOutputs {
            for (key, t) in [
                ("display.transfer_left", &d.transfer_left),
                ("display.transfer_right", &d.transfer_right),
            ] {
                if t.is_some() {
                    return Err(invalid(
                        key,
                        "an output's own transfer function is for layout = \"two-outputs\"; \
                         one panel's is display.transfer",
                    ));
                }
            }
        }
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
        Ok(())
    }

    /// `display.layout` with its monitors and offsets.
    fn check_layout(&self) -> Result<(), ConfigError> {
        let d = self;
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

    /// The marker patch a photodiode watches, and the simulated panel it sees.
    pub fn check_marker_and_panel(&self) -> Result<(), ConfigError> {
        let d = self;
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
        Ok(())
    }
}
