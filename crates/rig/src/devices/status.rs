//! What the devices part publishes ([`DevicesHandle`]): each device's link in the
//! [`Registry`], the device tasks' settings, the simulated devices of `port = "sim"` and when
//! the lenses are parked; `/status`'s `devices`, `device_tasks` and `sim_lens`, and the
//! devices that are down now.

use std::sync::{Arc, OnceLock};

use serde_json::{json, Map, Value};
use tokio_util::sync::CancellationToken;

use super::config::{Devices, SyncDriver};
use super::link::DeviceSettings;
use super::registry::{Registry, State};
use super::simulators::{SimDevices, SimSlot};
use crate::problem::Problem;

/// The devices part's handle.
pub struct DevicesHandle {
    /// `[devices]`.
    config: Devices,
    registry: Arc<Registry>,
    settings: DeviceSettings,
    sims: OnceLock<SimDevices>,
    lens_parked: CancellationToken,
}

impl DevicesHandle {
    pub fn new(config: Devices, registry: Arc<Registry>, settings: DeviceSettings) -> Self {
        DevicesHandle {
            config,
            registry,
            settings,
            sims: OnceLock::new(),
            lens_parked: CancellationToken::new(),
        }
    }

    /// Every device's link: its state, last error and counts.
    pub fn registry(&self) -> &Arc<Registry> {
        &self.registry
    }

    /// The device tasks' settings.
    pub fn settings(&self) -> DeviceSettings {
        self.settings
    }

    /// The simulated devices (none on a hardware rig, or before the devices start).
    pub fn sims(&self) -> Option<&SimDevices> {
        self.sims.get()
    }

    pub(crate) fn set_sims(&self, sims: SimDevices) {
        let _ = self.sims.set(sims);
    }

    /// Fires when every lens task has parked its lens (or given up) and ended: after this,
    /// exiting the process leaves the lenses safe.
    pub fn lens_parked(&self) -> &CancellationToken {
        &self.lens_parked
    }

    /// Lens `index`'s link now (`None`: not registered yet).
    pub fn lens_link(&self, index: usize) -> Option<State> {
        let name = self.config.lens.name(index);
        self.registry.snapshot().get(&name).map(|d| d.state)
    }

    /// `/status`'s `devices`, `device_tasks` and `sim_lens`.
    pub fn status(&self, out: &mut Map<String, Value>) {
        out.insert("devices".into(), json!(self.registry.snapshot()));
        out.insert("device_tasks".into(), json!(self.settings));
        out.insert("sim_lens".into(), self.sim_lens_json());
    }

    /// Where each simulated lens really is: the one lens's, or each eye's under `left` and
    /// `right`.
    fn sim_lens_json(&self) -> Value {
        let Some(sims) = self.sims.get() else {
            return Value::Null;
        };
        let one = |slot: Option<&SimSlot>| -> Value {
            let Some(slot) = slot else {
                return Value::Null;
            };
            let Some(lens) = slot.lens.as_ref() else {
                return Value::Null;
            };
            let m = lens.model();
            json!({
                "power_d": m.power().0,
                "target_d": m.target_power().0,
                "settled": m.settled(),
                "plugged": slot.plug.is_plugged(),
            })
        };
        let lenses = &self.config.lens;
        if lenses.count() == 1 {
            return one(sims.lenses.first().and_then(Option::as_ref));
        }
        let mut out = json!({});
        for i in 0..lenses.count() {
            if let Some(side) = lenses.side(i) {
                out[side.as_str()] = one(sims.lenses.get(i).and_then(Option::as_ref));
            }
        }
        out
    }

    /// What measures the multifocal lens at each sub-frame (`/status`'s `subframes`): the
    /// dioptra sync board reads it back; a DLPC350 only sequences, so nothing confirms the
    /// planes were reached and `measured` stays 0.
    pub fn subframe_measurement(&self) -> Option<&'static str> {
        let sync = self.config.sync.as_ref()?;
        Some(match sync.driver {
            SyncDriver::Sync => "the sync board's lens read-back at each sub-frame",
            SyncDriver::Dlpc350 => {
                "nothing: the DLPC350 sequences the planes but reports no lens power, so \
                 measured stays 0; a photodiode or the lens's own read-back is needed to \
                 confirm the planes were reached"
            }
        })
    }

    /// Each configured device whose link is not up now, under its port's key.
    pub fn problems(&self) -> Vec<Problem> {
        let snap = self.registry.snapshot();
        // The devices of the config, and a photodiode with a port of its own.
        let photodiode = snap
            .contains_key("photodiode")
            .then(|| ("photodiode".to_string(), "devices.photodiode".to_string()));
        self.config
            .list()
            .into_iter()
            .map(|d| (d.name, d.section))
            .chain(photodiode)
            .filter_map(|(name, section)| {
                let s = snap.get(&name)?;
                let state = match s.state {
                    State::Ok => return None,
                    State::Connecting => "connecting",
                    State::Lost => "lost",
                };
                let why = s.last_error.as_deref().unwrap_or("no answer yet");
                Some(Problem::new(
                    "devices",
                    format!("{section}.port"),
                    format!(
                        "the {name} device ({} driver at {}) is {state}: {why}",
                        s.driver, s.port
                    ),
                ))
            })
            .collect()
    }
}
