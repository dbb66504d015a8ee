//! What the optics part publishes ([`OpticsHandle`]): each lens's optics map (the scheduler's:
//! focus <-> lens command) and the focus the lenses were commanded and reported;
//! `/status`'s `focus` and `optics`.

use std::sync::Mutex;

use dioptra_core::{lock, Diopters, OpticsMap};
use serde_json::{json, Map, Value};

use super::config::Range;
use crate::devices::config::Lenses;
use crate::devices::input::LensId;
use crate::devices::registry::State;
use crate::problem::Problem;

/// Each lens's newest commanded and reported power, as the loop saw them.
#[derive(Debug, Clone, Default)]
pub struct FocusStatus {
    /// The newest lens power the scheduler commanded (the one lens, or the left eye's).
    pub commanded_power_d: Option<f32>,
    /// The newest lens power the lens reported (the one lens, or the left eye's).
    pub lens_power_d: Option<f32>,
    /// Each lens's newest commanded and reported power, by lens id (a lens per eye: left,
    /// right).
    pub commanded_by_lens: [Option<f32>; 2],
    pub reported_by_lens: [Option<f32>; 2],
    /// Whether that read-back had the lens settled at the power commanded.
    pub lens_settled: Option<bool>,
}

/// The optics part's handle.
pub struct OpticsHandle {
    /// The one lens's map, or the left's then the right's.
    maps: Vec<OpticsMap>,
    /// `optics.lens_range`.
    lens_range: Range,
    /// `[devices.lens]`: which lens is in front of which eye.
    lenses: Lenses,
    focus: Mutex<FocusStatus>,
}

impl OpticsHandle {
    /// `maps`: the one lens's, or the left's then the right's (the scheduler's).
    pub fn new(maps: Vec<OpticsMap>, lens_range: Range, lenses: Lenses) -> Self {
        OpticsHandle {
            maps,
            lens_range,
            lenses,
            focus: Mutex::new(FocusStatus::default()),
        }
    }

    /// The optics map of `lens` (the one lens, or an eye's).
    pub fn of(&self, lens: LensId) -> &OpticsMap {
        self.maps
            .get(lens.index())
            .or(self.maps.first())
            .expect("a rig has a lens")
    }

    /// The focus range each lens's range gives its eye through its optics map, nearest last:
    /// the one lens's, or the left's then the right's.
    pub fn focus_ranges_d(&self) -> Vec<[f32; 2]> {
        self.maps
            .iter()
            .map(|o| {
                let r = o.range();
                let (a, b) = (o.focus_of(r.min).0, o.focus_of(r.max).0);
                [a.min(b), a.max(b)]
            })
            .collect()
    }

    /// The focus range the lens range gives through the optics map, nearest last; with a lens
    /// per eye, the range both eyes' lenses reach (`None`: they reach no focus in common, as
    /// with prescriptions further apart than the lens range).
    pub fn focus_range_d(&self) -> Option<[f32; 2]> {
        let r = self
            .focus_ranges_d()
            .into_iter()
            .fold([f32::MIN, f32::MAX], |acc, r| {
                [acc[0].max(r[0]), acc[1].min(r[1])]
            });
        (r[0] <= r[1]).then_some(r)
    }

    /// The lenses' powers as the loop saw them.
    pub fn focus(&self) -> FocusStatus {
        lock(&self.focus).clone()
    }

    /// The scheduler commanded `lens` to `power`.
    pub(crate) fn commanded(&self, lens: LensId, power: Diopters) {
        let mut f = lock(&self.focus);
        if lens == LensId::FIRST {
            f.commanded_power_d = Some(power.0);
        }
        if let Some(p) = f.commanded_by_lens.get_mut(lens.index()) {
            *p = Some(power.0);
        }
    }

    /// `lens` reported `power`, settled at its target or not (`None`: no target yet).
    pub(crate) fn reported(&self, lens: LensId, power: Diopters, settled: Option<bool>) {
        let mut f = lock(&self.focus);
        if lens == LensId::FIRST {
            f.lens_power_d = Some(power.0);
            f.lens_settled = settled;
        }
        if let Some(p) = f.reported_by_lens.get_mut(lens.index()) {
            *p = Some(power.0);
        }
    }

    /// `/status`'s `focus` (with the manual focus the loop holds, `manual_d`, and each lens's
    /// link, `link`) and `optics`.
    pub fn status(
        &self,
        out: &mut Map<String, Value>,
        manual_d: Option<f32>,
        link: impl Fn(usize) -> Option<State>,
    ) {
        let focus = self.focus();
        out.insert("focus".into(), self.focus_json(&focus, manual_d, link));
        out.insert("optics".into(), self.optics_json(&focus));
    }

    /// The one lens's, or the left eye's; with a lens per eye, each eye's under `left` and
    /// `right` (commanded and reported power, the focus each gives through that eye's optics
    /// map, and the lens's link).
    fn focus_json(
        &self,
        status: &FocusStatus,
        manual_d: Option<f32>,
        link: impl Fn(usize) -> Option<State>,
    ) -> Value {
        let focus_of =
            |lens: LensId, p: Option<f32>| p.map(|p| self.of(lens).focus_of(Diopters(p)).0);
        let mut focus = json!({
            "manual_d": manual_d,
            "commanded_d": status.commanded_power_d,
            "commanded_focus_d": focus_of(LensId::FIRST, status.commanded_power_d),
            "lens_d": status.lens_power_d,
            "lens_focus_d": focus_of(LensId::FIRST, status.lens_power_d),
            "lens_settled": status.lens_settled,
            "lens_range_d": [self.lens_range.min, self.lens_range.max],
            "focus_range_d": self.focus_range_d(),
        });
        let lenses = &self.lenses;
        if lenses.count() > 1 {
            for i in 0..lenses.count() {
                let Some(side) = lenses.side(i) else { continue };
                let lens = LensId(i as u8);
                focus[side.as_str()] = json!({
                    "commanded_d": status.commanded_by_lens[i],
                    "commanded_focus_d": focus_of(lens, status.commanded_by_lens[i]),
                    "lens_d": status.reported_by_lens[i],
                    "lens_focus_d": focus_of(lens, status.reported_by_lens[i]),
                    "link": link(i),
                });
            }
        }
        focus
    }

    /// The map of the one lens, or each eye's.
    fn optics_json(&self, status: &FocusStatus) -> Value {
        let one = |lens: LensId, power: Option<f32>| {
            let o = self.of(lens);
            json!({
                "source": o.source_name(),
                "map": o.describe(),
                "magnification": power.and_then(|p| o.magnification(Diopters(p))),
            })
        };
        let lenses = &self.lenses;
        if lenses.count() == 1 {
            let mut v = one(LensId::FIRST, status.lens_power_d);
            v["eyes"] = json!("one map: this rig has one lens ([devices.lens])");
            return v;
        }
        let mut v = json!({ "eyes": "a map per eye: this rig has a lens per eye" });
        for i in 0..lenses.count() {
            if let Some(side) = lenses.side(i) {
                v[side.as_str()] = one(LensId(i as u8), status.reported_by_lens[i]);
            }
        }
        v
    }

    /// With a lens per eye, eyes whose lenses reach no focus in common.
    pub fn problems(&self) -> Vec<Problem> {
        if self.focus_range_d().is_some() {
            return Vec::new();
        }
        let ranges: Vec<String> = self
            .focus_ranges_d()
            .iter()
            .map(|[a, b]| format!("{a:.2}..{b:.2} D"))
            .collect();
        vec![Problem::new(
            "optics",
            "optics.lens_range",
            format!(
                "the eyes' lenses reach no focus in common (each eye's focus range: {}); the \
                 prescriptions are further apart than the lens range",
                ranges.join(", ")
            ),
        )]
    }
}
