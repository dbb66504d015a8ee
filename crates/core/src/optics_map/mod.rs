//! The optics map of one eye: accommodation demand (the focus the content asks the eye for,
//! diopters) <-> lens command (the tunable lens's power, diopters), through the rig's optics
//! and the viewer's prescription.
//!
//! focus --prescription--> demand presented at the eye --layout or table--> lens command
//!
//! - [`ThinLensLayout`]: display, tunable lens (+ fixed lens), eye; the thin-lens formula.
//! - [`CalibrationTable`]: measured (command, demand) points, read monotonically.
//! - [`Prescription`]: the viewer's spectacle sphere; the rig shows the uncorrected eye what
//!   spectacles would have shown it.
//! - Neither a layout nor a table: the identity (the lens's power is the demand), as a
//!   simulated rig or an ideal Badal system with the lens calibrated in demand units.
//!
//! A table gives the demand when there is one; a layout given beside it still gives the
//! image's angular magnification.

mod fit;
mod layout;
mod magnification;
mod prescription;
mod table;

pub use fit::{CalibrationFit, FitError, FitLimits, MIN_FIT_POINTS};
pub use layout::ThinLensLayout;
pub use prescription::{Prescription, DEFAULT_VERTEX_M};
pub use table::{CalibrationTable, MAX_GAP_D, MIN_POINTS};
// Shared with the panel's transfer function (crate::transfer).
pub(crate) use fit::{least_squares, poly};
pub(crate) use table::pchip_slopes;

use crate::units::{Diopters, PowerRange};

/// The largest demand (either sign) the maps work with, diopters: a point 3.3 cm from the
/// eye. Inputs beyond are clamped, which keeps every formula away from its pole.
pub const MAX_FOCUS_D: f64 = 30.0;

/// A setting or table the map cannot use. `key` is the setting's name as rig.toml spells it
/// (under `[optics]`, `[optics.layout]` or a per-eye section).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OpticsError {
    #[error("{key}: {message}")]
    Invalid { key: &'static str, message: String },
    #[error("calibration table {file}: {message}")]
    Table { file: String, message: String },
}

impl OpticsError {
    pub(crate) fn invalid(key: &'static str, message: impl Into<String>) -> Self {
        OpticsError::Invalid {
            key,
            message: message.into(),
        }
    }
}

/// Where a map's demand comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum Relation {
    /// The lens command is the demand.
    Identity,
    Layout(ThinLensLayout),
    Table(CalibrationTable),
}

/// One eye's map between focus and lens command, for one lens's range.
#[derive(Debug, Clone, PartialEq)]
pub struct OpticsMap {
    relation: Relation,
    /// For the magnification (also when a table gives the demand).
    layout: Option<ThinLensLayout>,
    prescription: Prescription,
    range: PowerRange,
}

impl OpticsMap {
    /// The identity map: the lens command is the focus (nothing configured).
    pub fn identity(range: PowerRange) -> Self {
        OpticsMap {
            relation: Relation::Identity,
            layout: None,
            prescription: Prescription::default(),
            range,
        }
    }

    /// A map from its sources for a lens driven within `range`. A table, if given, gives the
    /// demand, and must cover `range` densely; otherwise a layout, if given, must keep the
    /// display's image in front of the eye over `range`.
    pub fn new(
        layout: Option<ThinLensLayout>,
        table: Option<CalibrationTable>,
        prescription: Prescription,
        range: PowerRange,
    ) -> Result<Self, OpticsError> {
        let (lo, hi) = (f64::from(range.min.0), f64::from(range.max.0));
        if let Some(l) = &layout {
            l.check_range(lo, hi)?;
        }
        if let Some(t) = &table {
            t.check_covers(lo, hi)?;
        }
        let relation = match (table, layout) {
            (Some(t), _) => Relation::Table(t),
            (None, Some(l)) => Relation::Layout(l),
            (None, None) => Relation::Identity,
        };
        Ok(OpticsMap {
            relation,
            layout,
            prescription,
            range,
        })
    }

    /// Where the demand comes from.
    pub fn relation(&self) -> &Relation {
        &self.relation
    }
    pub fn layout(&self) -> Option<&ThinLensLayout> {
        self.layout.as_ref()
    }
    pub fn prescription(&self) -> &Prescription {
        &self.prescription
    }
    /// The lens range the map was made for (commands are clamped to it).
    pub fn range(&self) -> PowerRange {
        self.range
    }

    /// True when focus and command are the same number (no optics and no prescription).
    pub fn is_identity(&self) -> bool {
        self.relation == Relation::Identity && self.prescription.is_none()
    }

    /// The demand presented at the eye for a lens command (before the prescription).
    fn presented_at(&self, command: f64) -> f64 {
        match &self.relation {
            Relation::Identity => command,
            // A readback or prediction a little past the range is still in front of the
            // eye; where one is not, the range's end stands in (the range was checked).
            Relation::Layout(l) if l.image_in_front(command) => l.demand_at(command),
            Relation::Layout(l) => {
                l.demand_at(command.clamp(f64::from(self.range.min.0), f64::from(self.range.max.0)))
            }
            Relation::Table(t) => t.demand_at(command),
        }
    }

    /// The lens command for a presented demand, unclamped (`None`: out of the layout's reach).
    fn command_for_presented(&self, demand: f64) -> Option<f64> {
        match &self.relation {
            Relation::Identity => Some(demand),
            Relation::Layout(l) => l.power_for(demand),
            Relation::Table(t) => Some(t.command_for(demand)),
        }
    }

    /// The lens command that puts the display's image at `focus` (for the corrected eye),
    /// within the lens range (NaN only for a NaN focus, so callers can drop it).
    pub fn command_for(&self, focus: Diopters) -> Diopters {
        if focus.0.is_nan() {
            return focus;
        }
        let presented = self.prescription.presented(f64::from(focus.0));
        let (lo, hi) = (f64::from(self.range.min.0), f64::from(self.range.max.0));
        let command = match self.command_for_presented(presented) {
            Some(c) if c.is_finite() => c,
            // Nearer than the layout can place the image: as near as the lens can.
            _ => {
                if self.presented_at(lo) > self.presented_at(hi) {
                    lo
                } else {
                    hi
                }
            }
        };
        Diopters(command.clamp(lo, hi) as f32)
    }

    /// The focus (for the corrected eye) at which a lens command puts the display's image.
    pub fn focus_of(&self, command: Diopters) -> Diopters {
        let presented = self.presented_at(f64::from(command.0));
        Diopters(self.prescription.focus_of(presented) as f32)
    }

    /// The image's angular magnification at a lens command (against the bare display at the
    /// same place); `None` without a layout, where it is not known.
    pub fn magnification(&self, command: Diopters) -> Option<f32> {
        self.layout
            .as_ref()
            .map(|l| l.magnification_at(f64::from(command.0)) as f32)
    }

    /// One line for people: where the demand comes from, and the prescription.
    pub fn describe(&self) -> String {
        let mut s = match &self.relation {
            Relation::Identity => {
                "identity (no [optics.layout] or calibration: the lens command is the focus)"
                    .to_string()
            }
            Relation::Layout(l) => format!(
                "thin-lens layout: display {} m from the lens, eye relief {} m, fixed lens {} D",
                l.display_distance_m, l.eye_relief_m, l.fixed_power_d
            ),
            Relation::Table(t) => {
                let (a, b) = t.command_span();
                format!(
                    "calibration table {} ({} points, commands {a}..{b} D){}",
                    t.name(),
                    t.len(),
                    if self.layout.is_some() {
                        "; magnification from [optics.layout]"
                    } else {
                        ""
                    }
                )
            }
        };
        if !self.prescription.is_none() {
            s += &format!(
                "; prescription {:+.2} D sphere at {} mm",
                self.prescription.sphere_d,
                self.prescription.vertex_m * 1000.0
            );
        }
        s
    }

    /// A short name of where the demand comes from: `identity`, `layout` or `calibration`.
    pub fn source_name(&self) -> &'static str {
        match self.relation {
            Relation::Identity => "identity",
            Relation::Layout(_) => "layout",
            Relation::Table(_) => "calibration",
        }
    }
}

#[cfg(test)]
mod tests;
