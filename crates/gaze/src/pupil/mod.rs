//! Pupil Core eye trackers through Pupil Capture's network API: Pupil Remote (a REQ socket
//! on the configured port) gives the IPC backbone's publisher port and Pupil time; a SUB
//! socket there receives the `gaze.3d.` datums, multipart [topic, msgpack payload]
//! (layouts in [`protocol`]).
//!
//! Each datum becomes one [`GazeSample`]: `device_time` is its Pupil timestamp, `host_time`
//! that timestamp moved onto the host clock by the offset measured at connect, and
//! `host_receive_time` when it arrived. Eye 0 is the right eye, eye 1 the left; Pupil's y axis
//! points down and is flipped. A datum below `min_confidence`, or with an eye's fields
//! missing, mistyped or not finite, gives that eye (or both) `valid: false`: a dropout the
//! scheduler rides through. A payload that does not decode at all is skipped and counted.
//!
//! When Capture restarts, its IPC ports change and the old subscription goes quiet: no
//! datum within `stall_timeout` is reported as a lost link, and a new [`PupilCapture::connect`]
//! asks for the new port and measures the offset again.

pub mod ids;
pub mod protocol;
pub mod remote;

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{Clock, DeviceError, GazeSample, GazeSource, LinkError, Timestamp};
use zeromq::{Socket, SocketRecv, SubSocket};

use crate::timing::deadline;
pub use remote::{ClockOffset, PupilRemote};

/// How to reach Capture and what to trust.
#[derive(Debug, Clone, PartialEq)]
pub struct PupilConfig {
    /// Pupil Remote's address, "host:port" (Capture's default port is 50020).
    pub address: String,
    /// Datums below this confidence (0..=1) are dropouts.
    pub min_confidence: f32,
    /// Gaze rate the rig expects, Hz (Capture does not report it; Pupil Core's eye cameras
    /// run at 120 or 200 Hz).
    pub rate_hz: f32,
    /// Bound on connecting and on each Pupil Remote round trip.
    pub request_timeout: Duration,
    /// No gaze datum for this long: the link is lost (Capture quit or restarted).
    pub stall_timeout: Duration,
    /// `t` requests per clock-offset estimate.
    pub offset_samples: usize,
}

impl PupilConfig {
    pub fn new(address: impl Into<String>) -> Self {
        PupilConfig {
            address: address.into(),
            min_confidence: ids::RECOMMENDED_MIN_CONFIDENCE,
            rate_hz: 200.0,
            request_timeout: Duration::from_secs(2),
            stall_timeout: Duration::from_secs(1),
            offset_samples: 10,
        }
    }
}

/// A connected Pupil Capture, subscribed to 3D gaze.
pub struct PupilCapture {
    cfg: PupilConfig,
    remote: PupilRemote,
    sub: SubSocket,
    sub_port: u16,
    version: String,
    offset: ClockOffset,
    clock: Arc<dyn Clock>,
    skipped: u64,
    last_skip: Option<String>,
}

impl std::fmt::Debug for PupilCapture {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PupilCapture")
            .field("address", &self.cfg.address)
            .field("sub_port", &self.sub_port)
            .field("version", &self.version)
            .field("offset", &self.offset)
            .finish_non_exhaustive()
    }
}

impl PupilCapture {
    /// Asks Pupil Remote for the IPC publisher's port, measures the clock offset and
    /// subscribes to `gaze.3d.`.
    pub async fn connect(cfg: PupilConfig, clock: Arc<dyn Clock>) -> Result<Self, DeviceError> {
        if !(cfg.min_confidence.is_finite() && (0.0..=1.0).contains(&cfg.min_confidence)) {
            return Err(DeviceError::OutOfRange {
                what: "Pupil minimum confidence",
                requested: f64::from(cfg.min_confidence),
                min: 0.0,
                max: 1.0,
            });
        }
        let host = host_of(&cfg.address).ok_or_else(|| {
            DeviceError::Invalid(format!(
                "{:?} is not a host:port address for Pupil Remote",
                cfg.address
            ))
        })?;
        let mut remote = PupilRemote::connect(&cfg.address, cfg.request_timeout).await?;
        let version = remote.version().await?;
        let sub_port = remote.sub_port().await?;
        let offset = remote.estimate_offset(&clock, cfg.offset_samples).await?;
        let mut sub = SubSocket::new();
        let endpoint = format!("tcp://{host}:{sub_port}");
        let connected = async {
            sub.connect(&endpoint).await?;
            sub.subscribe(ids::GAZE_3D_TOPIC).await
        };
        match tokio::time::timeout(cfg.request_timeout, connected).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                return Err(DeviceError::Link(LinkError::Unavailable(format!(
                    "Pupil Capture's IPC publisher at {endpoint}: {e}"
                ))))
            }
            Err(_) => {
                return Err(DeviceError::Link(LinkError::Unavailable(format!(
                    "Pupil Capture's IPC publisher at {endpoint} did not accept a connection within {} ms",
                    cfg.request_timeout.as_millis()
                ))))
            }
        }
        tracing::info!(
            address = %cfg.address, %version, sub_port,
            offset_s = offset.mean_s, offset_std_s = offset.std_s,
            "connected to Pupil Capture"
        );
        Ok(PupilCapture {
            cfg,
            remote,
            sub,
            sub_port,
            version,
            offset,
            clock,
            skipped: 0,
            last_skip: None,
        })
    }

    /// Capture's version string.
    pub fn version(&self) -> &str {
        &self.version
    }

    /// The IPC publisher's port this connection subscribed at.
    pub fn sub_port(&self) -> u16 {
        self.sub_port
    }

    /// Pupil time minus host time, as measured at connect.
    pub fn clock_offset(&self) -> ClockOffset {
        self.offset
    }

    /// Pupil Remote, for commands of the caller's own (recording, calibration, ...).
    pub fn remote(&mut self) -> &mut PupilRemote {
        &mut self.remote
    }

    /// Messages skipped because they did not decode, and why the last one was.
    pub fn skipped(&self) -> (u64, Option<&str>) {
        (self.skipped, self.last_skip.as_deref())
    }

    /// A datum as a sample received at `host_receive`.
    pub fn sample(&self, datum: &protocol::GazeDatum, host_receive: Timestamp) -> GazeSample {
        let trusted = datum
            .confidence
            .is_some_and(|c| c >= f64::from(self.cfg.min_confidence));
        let host_s = self.offset.to_host_s(datum.timestamp_s);
        GazeSample {
            device_time: seconds(datum.timestamp_s).unwrap_or(Timestamp(0)),
            host_receive_time: host_receive,
            // Before host time 0 (or absurd): the receive time is the best there is.
            host_time: seconds(host_s).unwrap_or(host_receive),
            left: protocol::eye_ray(datum.left.as_ref(), trusted),
            right: protocol::eye_ray(datum.right.as_ref(), trusted),
        }
    }
}

/// Non-negative seconds as a timestamp.
fn seconds(s: f64) -> Option<Timestamp> {
    let ns = s * 1e9;
    (ns.is_finite() && ns >= 0.0 && ns < u64::MAX as f64).then(|| Timestamp(ns.round() as u64))
}

/// The host part of "host:port" ("[::1]:50020" keeps its brackets for the zmq endpoint).
fn host_of(address: &str) -> Option<&str> {
    let (host, port) = address.rsplit_once(':')?;
    (!host.is_empty() && port.parse::<u16>().is_ok()).then_some(host)
}

impl GazeSource for PupilCapture {
    fn rate_hz(&self) -> f32 {
        self.cfg.rate_hz
    }

    async fn next_sample(&mut self) -> Result<GazeSample, DeviceError> {
        let stall = self.cfg.stall_timeout;
        let deadline = deadline(stall);
        loop {
            let msg = match tokio::time::timeout_at(deadline, self.sub.recv()).await {
                Ok(Ok(m)) => m,
                Ok(Err(e)) => {
                    return Err(DeviceError::Link(LinkError::Disconnected(format!(
                        "Pupil Capture's IPC publisher (port {}): {e}",
                        self.sub_port
                    ))))
                }
                // The subscription of a Capture that quit or restarted goes quiet, it does
                // not fail: silence is how its loss shows.
                Err(_) => {
                    return Err(DeviceError::Link(LinkError::Disconnected(format!(
                        "no gaze from Pupil Capture at {} for {} ms (Capture stopped, restarted, or its eye processes are not running)",
                        self.cfg.address,
                        stall.as_millis()
                    ))))
                }
            };
            let host_receive = self.clock.now();
            let decoded = match (msg.get(0), msg.get(1)) {
                (Some(topic), Some(payload)) if msg.len() >= 2 => {
                    match std::str::from_utf8(topic) {
                        Ok(topic) => protocol::decode_gaze(topic, payload).map_err(|e| e.0),
                        Err(_) => Err("a topic that is not UTF-8".to_string()),
                    }
                }
                _ => Err(format!("a message of {} frames", msg.len())),
            };
            match decoded {
                Ok(datum) => return Ok(self.sample(&datum, host_receive)),
                Err(why) => {
                    if self.skipped == 0 {
                        tracing::warn!(address = %self.cfg.address, %why, "skipping a Pupil message");
                    }
                    self.skipped += 1;
                    self.last_skip = Some(why);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_split_into_host_and_port() {
        assert_eq!(host_of("127.0.0.1:50020"), Some("127.0.0.1"));
        assert_eq!(host_of("[::1]:50020"), Some("[::1]"));
        assert_eq!(host_of("capture.lab:1"), Some("capture.lab"));
        assert_eq!(host_of("nohost"), None);
        assert_eq!(host_of(":50020"), None);
        assert_eq!(host_of("h:port"), None);
    }

    #[test]
    fn seconds_outside_the_timeline_are_none() {
        assert_eq!(seconds(1.5), Some(Timestamp(1_500_000_000)));
        assert_eq!(seconds(-0.1), None);
        assert_eq!(seconds(f64::NAN), None);
        assert_eq!(seconds(1e30), None);
    }
}
