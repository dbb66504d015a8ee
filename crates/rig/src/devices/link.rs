//! How a device task treats its link: the one policy for retry waits, connect and park
//! timeouts ([`LinkPolicy`], [`DeviceSettings`]), the backoff between attempts ([`Backoff`]),
//! and the one place that decides whether an error costs the link ([`LinkHealth`]).

use std::future::Future;
use std::time::Duration;

use dioptra_core::{DeviceError, LinkError};
use serde::Serialize;
use tokio_util::sync::CancellationToken;

use super::config::Devices;
use super::registry::DeviceHandle;

/// How the device tasks treat their links: retry waits, connect and park timeouts, and when
/// a run of timeouts counts as a lost link. The same for every device kind and for every
/// command that runs a rig (serve, hil, demo, eval, the loop tests).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LinkPolicy {
    /// First wait after a failed connect or a loss; doubles per failure up to `backoff_max`.
    #[serde(rename = "backoff_min_ms", serialize_with = "as_ms")]
    pub backoff_min: Duration,
    #[serde(rename = "backoff_max_ms", serialize_with = "as_ms")]
    pub backoff_max: Duration,
    /// A connect attempt that takes longer is abandoned and retried.
    #[serde(rename = "connect_timeout_ms", serialize_with = "as_ms")]
    pub connect_timeout: Duration,
    /// This many timeouts in a row mean the device stopped answering: the link is lost.
    pub timeouts_lost: u32,
}

impl Default for LinkPolicy {
    fn default() -> Self {
        LinkPolicy {
            backoff_min: Duration::from_millis(100),
            backoff_max: Duration::from_secs(5),
            connect_timeout: Duration::from_secs(5),
            timeouts_lost: 3,
        }
    }
}

impl LinkPolicy {
    /// The times, counted from a loss, at which the first `n` reconnect attempts start when
    /// each fails at once: the first at once, then after each [`Backoff`] wait.
    pub fn attempts_after_loss(&self, n: usize) -> Vec<Duration> {
        let mut b = Backoff::new(self.backoff_min, self.backoff_max);
        let mut t = Duration::ZERO;
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            out.push(t);
            t += b.next_wait();
        }
        out
    }
}

/// A duration in `/status` and recordings: milliseconds, a plain number (the field's name
/// says the unit), not serde's `{"secs", "nanos"}`.
fn as_ms<S: serde::Serializer>(d: &Duration, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_f64(d.as_secs_f64() * 1e3)
}

/// The device tasks' settings, from the rig config.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DeviceSettings {
    pub link: LinkPolicy,
    /// How often the lens task reads the lens back.
    #[serde(rename = "lens_poll_ms", serialize_with = "as_ms")]
    pub lens_poll: Duration,
    /// How long parking may take at shutdown before the rig stops without it.
    #[serde(rename = "park_timeout_ms", serialize_with = "as_ms")]
    pub park_timeout: Duration,
}

impl DeviceSettings {
    pub fn from_config(devices: &Devices) -> DeviceSettings {
        DeviceSettings {
            link: LinkPolicy::default(),
            lens_poll: Duration::from_secs_f64(devices.lens.first().poll_ms / 1000.0),
            park_timeout: Duration::from_secs(1),
        }
    }
}

/// Exponential backoff between connection attempts.
#[derive(Debug, Clone)]
pub struct Backoff {
    next: Duration,
    min: Duration,
    max: Duration,
}

impl Backoff {
    pub fn new(min: Duration, max: Duration) -> Self {
        Backoff {
            next: min,
            min,
            max,
        }
    }
    /// The wait before the next attempt; doubles each call up to the maximum.
    pub fn next_wait(&mut self) -> Duration {
        let w = self.next;
        self.next = (self.next * 2).min(self.max);
        w
    }
    pub fn reset(&mut self) {
        self.next = self.min;
    }
}

/// What an error means for a link that was up: the one place that decides "lost".
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Reopen the link (back to connecting).
    Lost,
    /// Report it and keep the link.
    Keep,
}

/// Counts the timeouts in a row of one link and judges each error by [`LinkPolicy`].
#[derive(Debug, Clone)]
pub struct LinkHealth {
    timeouts: u32,
    limit: u32,
}

impl LinkHealth {
    pub fn new(policy: &LinkPolicy) -> Self {
        LinkHealth {
            timeouts: 0,
            limit: policy.timeouts_lost.max(1),
        }
    }
    /// An exchange succeeded.
    pub fn ok(&mut self) {
        self.timeouts = 0;
    }
    pub fn judge(&mut self, e: &DeviceError) -> Verdict {
        if e.needs_reconnect() {
            return Verdict::Lost;
        }
        if matches!(e, DeviceError::Link(LinkError::Timeout { .. })) {
            self.timeouts += 1;
            if self.timeouts >= self.limit {
                return Verdict::Lost;
            }
        }
        Verdict::Keep
    }
}

/// Connects, retrying with backoff; `None` when cancelled first.
pub(crate) async fn connect_retrying<D, F, Fut>(
    dev: &DeviceHandle,
    policy: &LinkPolicy,
    cancel: &CancellationToken,
    backoff: &mut Backoff,
    connect: &mut F,
) -> Option<D>
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<D, DeviceError>>,
{
    loop {
        dev.connecting();
        let attempt = tokio::time::timeout(policy.connect_timeout, connect());
        let r = tokio::select! {
            _ = cancel.cancelled() => return None,
            r = attempt => r,
        };
        let r = r.unwrap_or_else(|_| {
            Err(DeviceError::Link(LinkError::Timeout {
                ms: policy.connect_timeout.as_millis() as u64,
            }))
        });
        match r {
            Ok(d) => {
                backoff.reset();
                return Some(d);
            }
            Err(e) => {
                dev.lost(&e);
                let wait = backoff.next_wait();
                tokio::select! {
                    _ = cancel.cancelled() => return None,
                    _ = tokio::time::sleep(wait) => {}
                }
            }
        }
    }
}
