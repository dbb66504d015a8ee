//! What each device task reports: its state (connecting, ok, lost), its last error and its
//! counts, in the [`Registry`] that `/status` shows; and the wait for the required devices at
//! start.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::{lock, DeviceError, Timestamp};
use serde::Serialize;

use super::config::{ConfiguredDevice, Port};
use crate::repeats::{Note, Repeats, SUMMARY_EVERY};

fn tries(n: u64) -> &'static str {
    if n == 1 {
        "try"
    } else {
        "tries"
    }
}

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
    /// The last error: why it is down, or one that did not cost the link (a refusal);
    /// cleared when it (re)connects.
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
            label: label_of(name),
            log: Arc::new(Mutex::new(LinkLog::new())),
        }
    }
}

/// How log lines name a device: `right lens` for `lens_right`, `eye tracker` for `gaze`.
pub fn label_of(name: &str) -> String {
    match name.strip_prefix("lens_") {
        Some(side) => format!("{side} lens"),
        None => match name {
            "gaze" => "eye tracker".into(),
            "sync" => "sync board".into(),
            other => other.into(),
        },
    }
}

/// A device's log lines about its link: a loss (or a failed first connect) once, then a
/// summary at most every [`SUMMARY_EVERY`] while it stays down, then its return; and errors
/// that did not cost the link, each kind in full once, then summarised.
#[derive(Debug)]
struct LinkLog {
    /// Since the link went down (or the start, before it was ever up).
    down: Option<Down>,
    connected_before: bool,
    errors: Repeats,
    /// The origin of the times `errors` is given.
    origin: tokio::time::Instant,
}

#[derive(Debug)]
struct Down {
    since: tokio::time::Instant,
    /// Failed connect attempts since.
    tries: u64,
    /// When the last line about it was logged.
    logged: tokio::time::Instant,
}

impl LinkLog {
    fn new() -> LinkLog {
        LinkLog {
            down: None,
            connected_before: false,
            errors: Repeats::new("device errors"),
            origin: tokio::time::Instant::now(),
        }
    }
}

fn why_required(d: &ConfiguredDevice) -> String {
    format!(
        "the rig requires it ({0}.required, true by default for a real port; set it to false \
         to start without it, or port = \"sim\")",
        d.section
    )
}

/// Every required device of `devices` whose port is a path that does not exist, named with
/// its config key: checked before the device tasks start, so that a start this ends does not
/// first log the device as lost and retrying.
pub fn required_present(devices: &[ConfiguredDevice]) -> Result<(), String> {
    let absent: Vec<String> = devices
        .iter()
        .filter(|d| d.required)
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
    if absent.is_empty() {
        Ok(())
    } else {
        Err(absent.join("\n"))
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
    required_present(devices)?;
    let required: Vec<_> = devices.iter().filter(|d| d.required).collect();
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
    /// Its key in the registry and `/status` (`lens_right`).
    pub(crate) name: String,
    /// How log lines name it (`right lens`).
    pub(crate) label: String,
    log: Arc<Mutex<LinkLog>>,
}

impl DeviceHandle {
    fn update(&self, f: impl FnOnce(&mut DeviceStatus)) {
        if let Some(s) = lock(&self.registry.0).get_mut(&self.name) {
            f(s);
        }
    }
    fn state(&self) -> Option<State> {
        lock(&self.registry.0).get(&self.name).map(|s| s.state)
    }
    pub(crate) fn connecting(&self) {
        self.update(|s| s.state = State::Connecting);
    }
    /// Connected. The error of an earlier loss is cleared (`/status` shows it while the
    /// device is down, not after it came back).
    pub(crate) fn ok(&self) {
        self.update(|s| {
            s.state = State::Ok;
            s.connects += 1;
            s.last_error = None;
        });
        let mut log = lock(&self.log);
        let label = &self.label;
        match log.down.take() {
            Some(d) if log.connected_before => tracing::info!(
                "{label} connected again after {} failed {} ({:.0} s)",
                d.tries,
                tries(d.tries),
                d.since.elapsed().as_secs_f64()
            ),
            Some(d) => tracing::info!(
                "{label} connected after {} failed {} ({:.0} s)",
                d.tries,
                tries(d.tries),
                d.since.elapsed().as_secs_f64()
            ),
            None => tracing::info!("{label} connected"),
        }
        log.connected_before = true;
    }
    /// The link was lost, or a connect attempt failed: the first logged, then a summary at
    /// most every [`SUMMARY_EVERY`] while it stays down (each attempt at debug level).
    pub(crate) fn lost(&self, e: &DeviceError) {
        let was_up = self.state() == Some(State::Ok);
        self.update(|s| {
            s.state = State::Lost;
            s.failures += 1;
            s.last_error = Some(e.to_string());
        });
        let now = tokio::time::Instant::now();
        let mut log = lock(&self.log);
        let label = &self.label;
        let what = if log.connected_before {
            "lost"
        } else {
            "not connected"
        };
        match &mut log.down {
            None => {
                // A loss of a link that was up, or the first failed connect.
                let tries = u64::from(!was_up);
                log.down = Some(Down {
                    since: now,
                    tries,
                    logged: now,
                });
                tracing::warn!(
                    "{label} {what}: {e}; retrying (a summary at most once a minute until it \
                     is back)"
                );
            }
            Some(d) => {
                d.tries += 1;
                tracing::debug!("{label}: connect attempt {} failed: {e}", d.tries);
                if now.duration_since(d.logged) >= SUMMARY_EVERY {
                    d.logged = now;
                    tracing::warn!(
                        "{label} still {what} after {} {} ({:.0} s): {e}",
                        d.tries,
                        tries(d.tries),
                        now.duration_since(d.since).as_secs_f64()
                    );
                }
            }
        }
    }
    /// An error that did not cost the connection (a refusal, a single timeout): each kind
    /// logged in full once, then summarised.
    pub(crate) fn error(&self, e: &DeviceError) {
        self.update(|s| s.last_error = Some(e.to_string()));
        let mut log = lock(&self.log);
        let at = Timestamp(log.origin.elapsed().as_nanos() as u64);
        let message = format!("{}: {e}", self.label);
        // Kinds by their words: numbers in a message do not make another kind.
        let kind: String = message.chars().filter(|c| !c.is_ascii_digit()).collect();
        match log.errors.note(&kind, &message, at) {
            Note::First => tracing::warn!("{message}"),
            Note::Summary(s) => tracing::warn!("{}: {s}", self.label),
            Note::Counted => {}
        }
    }
}
