//! `[optics]` and `[eye]`: the lens range, the multifocal planes, each eye's optics (a
//! thin-lens layout or a calibration table, and the viewer's prescription) and the viewer's
//! eye; their defaults and checks, and the optics maps they make.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use dioptra_core::optics_map::{
    CalibrationTable, OpticsError, OpticsMap, Prescription, ThinLensLayout,
};
use dioptra_core::{Diopters, PowerRange, Side};
use serde::{Deserialize, Serialize};

use crate::config::error::{invalid, ConfigError};

/// A range of lens powers, diopters (`optics.lens_range = { min = ..., max = ... }`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Range {
    pub min: f32,
    pub max: f32,
}

/// `[optics]`: the lens range, the multifocal planes, and both eyes' optics (each eye's own
/// section overriding them).
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

/// `[eye]`: the viewer's eye (DeepFocus's by default: a 4 mm pupil, a 20 degree field).
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

impl Eye {
    /// The eye the rig renders for and looks up depth with: its pupil and field over
    /// `width_px` pixels (the display's width; not validated: [`Eye::check`] checks it).
    pub fn model(&self, width_px: u32) -> dioptra_core::EyeModel {
        dioptra_core::EyeModel {
            pupil_diameter: dioptra_core::Millimeters(self.pupil_mm),
            fov_horizontal_deg: self.fov_deg,
            width_px,
            ..Default::default()
        }
    }

    /// `[eye]`'s keys: a human pupil, a field the eye model takes, an interpupillary distance.
    pub fn check(&self) -> Result<(), ConfigError> {
        let e = self;
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
        Ok(())
    }
}

/// The calibration tables a config names, as read with it, and the folder its relative paths
/// are read from (for the tables' names in messages).
#[derive(Debug, Clone, Copy)]
pub struct Tables<'a> {
    pub text: &'a BTreeMap<PathBuf, String>,
    pub dir: Option<&'a Path>,
}

impl Tables<'_> {
    /// A path given in the config, as it is read: relative ones from the config's folder.
    fn path(&self, p: &Path) -> PathBuf {
        match self.dir {
            Some(dir) if p.is_relative() => dir.join(p),
            _ => p.to_path_buf(),
        }
    }
}

impl Optics {
    /// The multifocal schedule the sync hardware runs: `planes` at `subframe_hz`, dark for
    /// the first quarter of each sub-frame while the lens settles.
    pub fn plane_schedule(&self) -> Result<dioptra_core::PlaneSchedule, ConfigError> {
        dioptra_core::PlaneSchedule::new(
            self.planes
                .iter()
                .copied()
                .map(dioptra_core::Diopters)
                .collect(),
            std::time::Duration::from_secs_f64(1.0 / self.subframe_hz),
            std::time::Duration::from_secs_f64(0.25 / self.subframe_hz),
        )
        .map_err(|e| invalid("optics.planes", e.to_string()))
    }

    /// The lens range and the planes in it; the sub-frame rate.
    pub fn check(&self) -> Result<(), ConfigError> {
        let o = self;
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
        Ok(())
    }

    /// The calibration tables the settings name, each with its section.
    pub fn calibration_files(&self) -> [(&'static str, Option<&PathBuf>); 3] {
        [
            ("optics", self.calibration.as_ref()),
            (
                "optics.left",
                self.left.as_ref().and_then(|e| e.calibration.as_ref()),
            ),
            (
                "optics.right",
                self.right.as_ref().and_then(|e| e.calibration.as_ref()),
            ),
        ]
    }

    /// The optics map of an eye (`None`: the rig's one lens, see [`Optics::one_lens_eye`]):
    /// its layout or calibration table and the viewer's prescription, for the lens range.
    /// Without `tables` the calibration table is left out (a simulated lens sits in the
    /// layout: the table is the rig's belief, not the physics). Errors name the key, the file
    /// and the points.
    pub fn map(
        &self,
        side: Option<Side>,
        tables: Option<Tables>,
    ) -> Result<OpticsMap, ConfigError> {
        let o = self;
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
        let with_table = tables.is_some();
        let table = match r.calibration.zip(tables) {
            Some(((file, section), tables)) => {
                let text = tables.text.get(file).ok_or_else(|| {
                    invalid(
                        &key(section, "calibration"),
                        format!("{} was not read with the config", file.display()),
                    )
                })?;
                let name = tables.path(file).display().to_string();
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

    /// Keys that no longer do anything.
    pub fn notices(&self) -> Vec<String> {
        let mut out = Vec::new();
        if self.display_distance_m.is_some() {
            out.push(
                "optics.display_distance_m is no longer read (it never was used): the display's \
                 distance from the tunable lens is [optics.layout] display_distance_m, with \
                 eye_relief_m and fixed_power_d; without a layout or calibration the lens \
                 command is the focus (the identity map)"
                    .to_string(),
            );
        }
        out
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
