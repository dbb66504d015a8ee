//! The rig config (`rig.toml`): the composition of its sections, each owned by the part it
//! configures (its type, defaults and checks in that part's `config` module: [`devices`],
//! [`optics`], [`display`], [`content`], [`render`], [`recording`], [`lsl`], [`api`]; `mode`
//! and `method` in [`crate::mode`]). Here the sections are put together, deserialised,
//! their relative paths resolved from the config file's folder and what spans sections
//! checked. Parsing is strict (`deny_unknown_fields`) and every error names the key and the
//! form it expects, e.g. `optics.lens_range: min must be below max`.
//!
//! [`devices`]: crate::devices::config
//! [`optics`]: crate::optics::config
//! [`display`]: crate::display::config
//! [`content`]: crate::content::config
//! [`render`]: crate::render::config
//! [`recording`]: crate::recording::config
//! [`lsl`]: crate::lsl::config
//! [`api`]: crate::api

pub mod error;
#[cfg(test)]
pub(crate) mod tests;

use std::path::{Path, PathBuf};

use dioptra_core::optics_map::OpticsMap;
use dioptra_core::Side;
use dioptra_sched::RenderMethod;
use serde::{Deserialize, Serialize};

pub use crate::api::{Api, Listen, DEFAULT_LISTEN};
pub use crate::content::config::{
    ContentConfig, ContentSource, DEFAULT_VIEW_SPAN_MM, EYE_MARK, MAX_CONTENT_VIEWS, VIEW_MARK,
};
pub use crate::devices::config::{
    ConfiguredDevice, Devices, GazeDevice, GazeDriver, LensDevice, LensDriver, Lenses,
    PhotodiodeDevice, PhotodiodeDriver, Port, SyncDevice, SyncDriver,
};
pub use crate::display::config::{
    Corner, Display, DisplayLayout, EyeOffsets, MarkerEvent, MarkerPatch, MonitorChoice, Scale,
    SinkKind,
};
pub use crate::lsl::config::LslConfig;
pub use crate::mode::{methods, Method, Mode, RENDERED};
pub use crate::optics::config::{Eye, EyeOptics, Eyepiece, Layout, Optics, Range, Tables};
pub use crate::recording::config::Recording;
pub use crate::render::config::{Render, RenderBackend};
pub use error::ConfigError;
use error::{invalid, one_line};

/// A rig config: its sections, each owned by the part it configures, and what was read with
/// it (the folder it came from, its calibration tables).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
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
    pub lsl: LslConfig,
    /// The folder of the config file, which its relative paths (calibration tables) are read
    /// from; `None` (config text without a file): the working directory.
    #[serde(skip)]
    pub config_dir: Option<PathBuf>,
    /// The calibration tables' text, read once when the config is (keyed by the path as the
    /// config gives it), so a run and its recording use the tables as they were at start.
    #[serde(skip)]
    pub calibration_tables: std::collections::BTreeMap<PathBuf, String>,
}

/// How one eye's image goes to its panel: the magnification compensation, the eyepiece's
/// pre-warp and the panel's transfer function ([`RigConfig::eye_images`]).
#[derive(Debug, Clone)]
pub struct EyeImage {
    /// The eye (`None`: the one image of layout `one`).
    pub eye: Option<Side>,
    /// The lens in front of it (the scheduler's lens index).
    pub lens: usize,
    /// With the magnification compensated: the lens power whose magnification the image
    /// keeps ([`OpticsMap::magnification_reference`]); `None`: not compensated.
    pub reference: Option<dioptra_core::Diopters>,
    /// The eyepiece's distortion, pre-warped; `None`: drawn 1:1.
    pub eyepiece: Option<Eyepiece>,
    pub transfer: dioptra_core::transfer::Transfer,
    /// The key it was given under.
    pub transfer_key: &'static str,
}

/// The example rig of simulated devices (`crates/cli/examples/rig-sim.toml`), which the demo,
/// the loop tests and `dioptra eval --suite loop` run.
pub const EXAMPLE_SIM_RIG: &str = include_str!("../../cli/examples/rig-sim.toml");

/// The example binocular rig of simulated devices (`crates/cli/examples/rig-sim-binocular.toml`):
/// a lens per eye, the binocular tracker, the panel split side by side.
pub const EXAMPLE_SIM_BINOCULAR_RIG: &str =
    include_str!("../../cli/examples/rig-sim-binocular.toml");

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
        self.eye.model(self.display.width)
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

    /// Reads every file the config's optics and display settings name (calibration tables,
    /// distortion files, transfer tables) and does not hold yet.
    fn read_calibration_tables(&mut self) -> Result<(), ConfigError> {
        let mut read = Vec::new();
        let mut files: Vec<(String, &PathBuf, &str)> = Vec::new();
        for (section, file) in self.optics.calibration_files() {
            if let Some(file) = file {
                files.push((format!("{section}.calibration"), file, "calibration table"));
            }
        }
        for (section, file) in self.optics.distortion_files() {
            if let Some(file) = file {
                files.push((
                    format!("{section}.distortion_file"),
                    file,
                    "distortion file",
                ));
            }
        }
        for (key, file) in self.display.transfer_files() {
            files.push((format!("{key}.table"), file, "transfer table"));
        }
        for (key, file, what) in files {
            if self.calibration_tables.contains_key(file) {
                continue;
            }
            let path = self.config_path(file);
            let text = std::fs::read_to_string(&path).map_err(|e| {
                invalid(
                    &key,
                    format!(
                        "cannot read the {what} {} ({}): {e}",
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

    /// The calibration tables read with the config, and where its relative paths are.
    pub fn tables(&self) -> Tables<'_> {
        Tables {
            text: &self.calibration_tables,
            dir: self.config_dir.as_deref(),
        }
    }

    /// The optics map of an eye (`None`: the rig's one lens, see
    /// [`Optics::one_lens_eye`]): its layout or calibration table and the viewer's
    /// prescription, for the lens range. Errors name the key, the file and the points.
    pub fn optics_map(&self, side: Option<Side>) -> Result<OpticsMap, ConfigError> {
        self.optics.map(side, Some(self.tables()))
    }

    /// The optics a simulated lens sits in: `[optics.layout]` and the viewer's prescription,
    /// without the calibration table (which is what the rig believes, not the physics), so a
    /// simulated rig whose table is wrong shows the focus error it would have.
    pub fn simulated_optics(&self, side: Option<Side>) -> Result<OpticsMap, ConfigError> {
        self.optics.map(side, None)
    }

    /// Things worth saying at start that are not errors: keys that no longer do anything,
    /// defaults a real rig should set.
    pub fn notices(&self) -> Vec<String> {
        let mut out = self.optics.notices();
        out.extend(self.devices.notices());
        out
    }

    /// Each section's checks, and those that span sections, in that order: the first error
    /// found is the one reported.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.lsl.check()?;
        self.render.check()?;
        self.content.check(self.display.stereo())?;
        self.optics.check()?;
        self.devices.check(&self.optics, self.mode)?;
        crate::mode::check(self.mode, self.method, self.auto_method)?;
        self.eye.check()?;
        self.check_foveation()?;
        self.render.hybrid.check(self.eye.fov_deg)?;
        self.render.spectral.check()?;
        self.display.check()?;
        self.check_optics_per_lens()?;
        self.check_eye_images()?;
        self.display.check_marker_and_panel()?;
        if self.devices.photodiode.is_some() && self.display.marker_patch.is_none() {
            return Err(invalid(
                "display.marker_patch",
                "[devices.photodiode] is set but no marker patch is drawn for it to see: add display.marker_patch = { corner = \"top-left\", size = 8 }",
            ));
        }
        self.api.check()
    }

    /// The eyes the display shows an image for: the one image (`None`), or the left's and
    /// the right's.
    pub fn image_eyes(&self) -> Vec<Option<Side>> {
        if self.display.stereo() {
            Side::BOTH.into_iter().map(Some).collect()
        } else {
            vec![None]
        }
    }

    /// The lens in front of an eye's image: the one lens, or that eye's.
    pub fn lens_of_image(&self, side: Option<Side>) -> usize {
        match (&self.devices.lens, side) {
            (Lenses::PerEye { .. }, Some(Side::Right)) => 1,
            _ => 0,
        }
    }

    /// How each eye's image goes to its panel ([`EyeImage`]), in [`RigConfig::image_eyes`]'
    /// order. Errors name the key.
    pub fn eye_images(&self) -> Result<Vec<EyeImage>, ConfigError> {
        let per_eye = matches!(self.devices.lens, Lenses::PerEye { .. });
        self.image_eyes()
            .into_iter()
            .map(|eye| {
                let map = self.optics_map(if per_eye { eye } else { None })?;
                let compensate = self.optics.compensates(eye, &map)?;
                let eyepiece = self.optics.eyepiece(eye, self.tables())?;
                let (transfer, transfer_key) = self.display.transfer_of(
                    eye.filter(|_| self.display.layout == DisplayLayout::TwoOutputs),
                    self.tables(),
                )?;
                Ok(EyeImage {
                    eye,
                    lens: self.lens_of_image(eye),
                    reference: if compensate {
                        map.magnification_reference()
                    } else {
                        None
                    },
                    eyepiece,
                    transfer,
                    transfer_key,
                })
            })
            .collect()
    }

    /// `render.foveation` fits the eye's field and applies to what the rig renders: the
    /// varifocal pyramid method, fixed or chosen by `auto`.
    fn check_foveation(&self) -> Result<(), ConfigError> {
        self.render.foveation.check(self.eye.fov_deg)?;
        if self.render.foveation.settings().is_none() {
            return Ok(());
        }
        let renders_pyramid = self.auto_method || self.method.0 == RenderMethod::Pyramid;
        if self.mode != Mode::Varifocal || !renders_pyramid {
            return Err(invalid(
                "render.foveation",
                format!(
                    "foveation applies to the varifocal render's pyramid method (method = \"pyramid\" or \"auto\"), not {} in {} mode: set one of those or foveation = \"off\"",
                    self.method.as_str(),
                    self.mode.as_str()
                ),
            ));
        }
        Ok(())
    }

    /// Each eye's image settings can be used: the eyepiece's optical centre is on the panel
    /// (an eye's image is `display.width` x `height`).
    fn check_eye_images(&self) -> Result<(), ConfigError> {
        let (w, h) = (
            f64::from(self.display.width),
            f64::from(self.display.height),
        );
        for image in self.eye_images()? {
            if let Some(e) = &image.eyepiece {
                let r = &e.model.render;
                if !((-0.5..w - 0.5).contains(&r.cx) && (-0.5..h - 0.5).contains(&r.cy)) {
                    return Err(invalid(
                        &format!("{}.cx", e.from),
                        format!(
                            "the optical centre ({}, {}) is off the eye's {}x{} image \
                             (display.width x display.height): the model's pixels are the \
                             panel's, centre at (width - 1) / 2 for a centred eyepiece",
                            r.cx, r.cy, self.display.width, self.display.height
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// `[optics]`' eye sections fit the lenses of `[devices.lens]`, and each lens's optics map
    /// can be made.
    fn check_optics_per_lens(&self) -> Result<(), ConfigError> {
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
        Ok(())
    }
}
