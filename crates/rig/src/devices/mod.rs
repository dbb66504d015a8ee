//! One task per device. Each task connects (retrying with [`Backoff`] while the rest of the
//! rig runs), then serves its device until the link is lost (back to connecting) or the rig
//! stops (the lens is parked first). Every task reports its state to the [`Registry`] the API
//! shows: connecting, ok or lost, with the last error.
//!
//! Whether an error costs the link is decided in one place, [`LinkHealth`]; how long to wait
//! between attempts in another, [`LinkPolicy`]. Devices are opened through the drivers'
//! table ([`open`]): the rig config's driver and port become a link (a simulator's in-memory
//! link for `port = "sim"`, a serial port or HID device otherwise) and a connected driver.

mod about;
mod boxed;
pub mod config;
mod forward;
pub mod input;
mod lens;
pub mod link;
pub mod open;
pub mod registry;
pub mod simulators;
pub mod status;
mod sync;

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{Clock, DeviceError, Diopters};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

pub use boxed::{About, BoxGaze, BoxLens, BoxPhotodiode, BoxSequencer, Facts, Resume};
pub use input::{DeviceInput, LensId, LensOrder};
pub use lens::ParkReport;
pub use link::{Backoff, DeviceSettings, LinkHealth, LinkPolicy, Verdict};
pub use registry::{wait_for_required, DeviceHandle, DeviceStatus, Registry, State};
pub use status::DevicesHandle;

use crate::config::RigConfig;
use simulators::{SimDevices, SimSpec};

/// Channels from the loop to the device tasks.
pub struct DeviceLinks {
    /// Each lens's newest command (by [`LensId`]); a newer one replaces one not yet sent.
    pub lens_commands: Vec<watch::Sender<Option<LensOrder>>>,
    pub multifocal: watch::Sender<bool>,
}

/// Spawned device tasks: each lens task's park report comes back through `lenses`.
pub struct DeviceTasks {
    pub lenses: Vec<tokio::task::JoinHandle<ParkReport>>,
    pub others: Vec<tokio::task::JoinHandle<()>>,
}

/// Starts every device task of `cfg`: each device opened through the drivers' table
/// ([`open`]), simulators made from `spec` for `port = "sim"`. Device tasks stop on `stop`
/// (the lens is parked first). Returns the simulator handles, the channels and the tasks.
pub fn spawn_devices(
    cfg: &Arc<RigConfig>,
    spec: &SimSpec,
    settings: DeviceSettings,
    registry: &Arc<Registry>,
    clock: Arc<dyn Clock>,
    out: mpsc::Sender<DeviceInput>,
    stop: &CancellationToken,
) -> Result<(SimDevices, DeviceLinks, DeviceTasks), DeviceError> {
    let mut sims = SimDevices::default();
    let (mf_tx, mf_rx) = watch::channel(cfg.mode == crate::mode::Mode::Multifocal);
    let lens_setup = |i| open::LensSetup::from_rig(cfg, i);

    // A task per lens, each with its own link, backoff and read-backs.
    let mut lens_commands = Vec::new();
    let mut lenses = Vec::new();
    for (i, l) in cfg.devices.lens.each().into_iter().enumerate() {
        let id = LensId(i as u8);
        let (tx, rx) = watch::channel(None);
        let row = open::row(&open::LENS, l.driver)?;
        let dev = registry.add(&cfg.devices.lens.name(i), row.name, &l.port);
        let mut lens_spec = spec.clone();
        lens_spec.lens = spec.lens_of(i);
        let mut slot = None;
        let connect = open::device_connector(
            row,
            &l.port,
            open::Context::new(clock.clone(), lens_setup(i)?),
            &lens_spec,
            &mut slot,
            &mut sims.gaze_truth,
        );
        sims.lenses.push(slot);
        // Each lens is read back at its own interval.
        let lens_settings = DeviceSettings {
            lens_poll: Duration::from_secs_f64(l.poll_ms / 1000.0),
            ..settings
        };
        lenses.push(tokio::spawn(lens::lens_task(
            connect,
            id,
            dev,
            lens_settings,
            rx,
            out.clone(),
            Diopters(l.park_power),
            stop.clone(),
        )));
        lens_commands.push(tx);
    }

    let mut others = Vec::new();
    let g = &cfg.devices.gaze;
    let row = open::row(&open::GAZE, g.driver)?;
    let dev = registry.add("gaze", row.name, &g.port);
    let connect = open::device_connector(
        row,
        &g.port,
        open::Context::new(clock.clone(), open::GazeSetup::from_rig(cfg)),
        spec,
        &mut sims.gaze,
        &mut sims.gaze_truth,
    );
    others.push(tokio::spawn(forward::forward_task(
        connect,
        dev,
        settings,
        out.clone(),
        stop.clone(),
    )));

    if let Some(s) = &cfg.devices.sync {
        let row = open::row(&open::SYNC, s.driver)?;
        let dev = registry.add("sync", row.name, &s.port);
        let schedule = cfg
            .optics
            .plane_schedule()
            .map_err(|e| DeviceError::Invalid(e.to_string()))?;
        let connect = open::device_connector(
            row,
            &s.port,
            open::Context::new(clock.clone(), open::SyncSetup::from_rig(cfg, out.clone())),
            spec,
            &mut sims.sync,
            &mut sims.gaze_truth,
        );
        // A photodiode on this board: its light is read whatever the mode.
        let light = cfg
            .devices
            .photodiode
            .as_ref()
            .is_some_and(|p| p.on_sync_board());
        others.push(tokio::spawn(sync::sync_task(
            connect,
            dev,
            settings,
            sync::SyncWork {
                schedule,
                multifocal: mf_rx,
                light,
            },
            out.clone(),
            stop.clone(),
        )));
    }
    if let Some(p) = cfg.devices.photodiode.as_ref() {
        if let Some(port) = &p.port {
            let row = open::row(&open::PHOTODIODE, p.driver)?;
            let dev = registry.add("photodiode", row.name, port);
            let connect = open::device_connector(
                row,
                port,
                open::Context::new(clock.clone(), open::PhotodiodeSetup::from_rig(cfg)),
                spec,
                &mut sims.photodiode,
                &mut sims.gaze_truth,
            );
            others.push(tokio::spawn(forward::forward_task(
                connect,
                dev,
                settings,
                out.clone(),
                stop.clone(),
            )));
        }
    }
    sims.panel = spec.panel.clone();
    Ok((
        sims,
        DeviceLinks {
            lens_commands,
            multifocal: mf_tx,
        },
        DeviceTasks { lenses, others },
    ))
}

#[cfg(test)]
mod tests;
