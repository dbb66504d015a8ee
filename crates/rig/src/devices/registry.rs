//! What each device task reports: its state (connecting, ok, lost), its last error and its
//! counts, in the [`Registry`] that `/status` shows; and the wait for the required devices at
//! start.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::{lock, DeviceError};
use serde::Serialize;

use super::config::{ConfiguredDevice, Port};

/// A device's connection state, as the API shows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum State {
    Connecting,
    Ok,
    Lost,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DeviceStatus {
    pub driver: String,
    pub port: String,
    pub state: State,
    /// The last error, kept after the device comes back.
    pub last_error: Option<String>,
    /// Successful connects so far (more than one: it was lost and came back).
    pub connects: u64,
    /// Failed connects and losses so far.
    pub failures: u64,
}

/// Every device's status, shared between the device tasks and the API.
#[derive(Debug, Default)]
pub struct Registry(Mutex<BTreeMap<String, DeviceStatus>>);

impl Registry {
    pub fn snapshot(&self) -> BTreeMap<String, DeviceStatus> {
        lock(&self.0).clone()
    }
    pub(crate) fn add(self: &Arc<Self>, name: &str, driver: &str, port: &Port) -> DeviceHandle {
        lock(&self.0).insert(
            name.to_string(),
            DeviceStatus {
                driver: driver.to_string(),
                port: port.to_string(),
                state: State::Connecting,
                last_error: None,
                connects: 0,
                failures: 0,
            },
        );
        DeviceHandle {
            registry: self.clone(),
            name: name.to_string(),
        }
    }
}

/// Waits up to `timeout` for every required device of `devices` to connect. The error names
/// each one that did not: its config key, port, and why (a device path that does not exist
/// fails at once).
pub async fn wait_for_required(
    registry: &Registry,
    devices: &[ConfiguredDevice],
    timeout: Duration,
) -> Result<(), String> {
    let required: Vec<_> = devices.iter().filter(|d| d.required).collect();
    let why_required = |d: &ConfiguredDevice| {
        format!(
            "the rig requires it ({0}.required, true by default for a real port; set it to \
             false to start without it, or port = \"sim\")",
            d.section
        )
    };
    let absent: Vec<String> = required
        .iter()
        .filter_map(|d| match &d.port {
            Port::Path(p) if !p.exists() => Some(format!(
                "{}.port = \"{}\": the {} device is not present (no such file); {}",
                d.section,
                p.display(),
                d.name,
                why_required(d)
            )),
            _ => None,
        })
        .collect();
    if !absent.is_empty() {
        return Err(absent.join("\n"));
    }
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        let snap = registry.snapshot();
        let missing: Vec<_> = required
            .iter()
            .filter(|d| snap.get(&d.name).is_none_or(|s| s.state != State::Ok))
            .collect();
        if missing.is_empty() {
            return Ok(());
        }
        if tokio::time::Instant::now() >= deadline {
            return Err(missing
                .iter()
                .map(|d| {
                    let s = snap.get(&d.name);
                    format!(
                        "{}.port = \"{}\": the {} device ({} driver) did not connect within {} s: \
                         {}; {}",
                        d.section,
                        d.port,
                        d.name,
                        s.map_or("?", |s| s.driver.as_str()),
                        timeout.as_secs_f64(),
                        s.and_then(|s| s.last_error.as_deref())
                            .unwrap_or("no answer"),
                        why_required(d)
                    )
                })
                .collect::<Vec<_>>()
                .join("\n"));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// One device's entry in the [`Registry`].
#[derive(Debug, Clone)]
pub struct DeviceHandle {
    registry: Arc<Registry>,
    name: String,
}

impl DeviceHandle {
    fn update(&self, f: impl FnOnce(&mut DeviceStatus)) {
        if let Some(s) = lock(&self.registry.0).get_mut(&self.name) {
            f(s);
        }
    }
    pub(crate) fn connecting(&self) {
        self.update(|s| s.state = State::Connecting);
    }
    pub(crate) fn ok(&self) {
        self.update(|s| {
            s.state = State::Ok;
            s.connects += 1;
        });
        tracing::info!(device = %self.name, "connected");
    }
    pub(crate) fn lost(&self, e: &DeviceError) {
        self.update(|s| {
            s.state = State::Lost;
            s.failures += 1;
            s.last_error = Some(e.to_string());
        });
        tracing::warn!(device = %self.name, error = %e, "lost; retrying");
    }
    /// An error that did not cost the connection (a refusal, a single timeout).
    pub(crate) fn error(&self, e: &DeviceError) {
        self.update(|s| s.last_error = Some(e.to_string()));
        tracing::warn!(device = %self.name, error = %e, "device error");
    }
}
