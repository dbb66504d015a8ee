//! Pupil Remote: a REQ socket to Capture, one string command and one string reply at a time,
//! and the clock-offset estimate Pupil Labs document (several `t` requests, each against the
//! host time before and after it; the offset is the mean over the midpoints).

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{Clock, DeviceError, LinkError};
use zeromq::{ReqSocket, Socket, SocketRecv, SocketSend, ZmqMessage};

use super::ids::command;
use super::protocol::{parse_port, parse_time};

/// Pupil time minus host time, seconds, from `samples` measurements.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClockOffset {
    /// Mean of the measurements: add to host seconds to get Pupil seconds.
    pub mean_s: f64,
    /// Their sample standard deviation.
    pub std_s: f64,
    /// The smallest round trip seen: how well any one measurement can be trusted.
    pub min_round_trip_s: f64,
    pub samples: usize,
}

impl ClockOffset {
    /// Host seconds of Pupil time `pupil_s`.
    pub fn to_host_s(&self, pupil_s: f64) -> f64 {
        pupil_s - self.mean_s
    }
}

/// A Pupil Remote connection. A REQ socket that timed out waiting for a reply is in the
/// middle of its send/receive cycle and cannot send again, so it is dropped: every later
/// request fails as a lost link until a new [`PupilRemote::connect`].
pub struct PupilRemote {
    socket: Option<ReqSocket>,
    address: String,
    timeout: Duration,
}

impl std::fmt::Debug for PupilRemote {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PupilRemote")
            .field("address", &self.address)
            .field("usable", &self.socket.is_some())
            .finish_non_exhaustive()
    }
}

fn lost(what: String) -> DeviceError {
    DeviceError::Link(LinkError::Disconnected(what))
}

impl PupilRemote {
    /// Connects to Pupil Remote at `address` ("host:port"). `timeout` bounds the connect and
    /// every request's round trip.
    pub async fn connect(address: &str, timeout: Duration) -> Result<Self, DeviceError> {
        let mut socket = ReqSocket::new();
        let endpoint = format!("tcp://{address}");
        match tokio::time::timeout(timeout, socket.connect(&endpoint)).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                return Err(DeviceError::Link(LinkError::Unavailable(format!(
                    "Pupil Remote at {address}: {e}"
                ))))
            }
            // zmq retries a refused connect until it succeeds: no answer in time is absence.
            Err(_) => {
                return Err(DeviceError::Link(LinkError::Unavailable(format!(
                    "Pupil Remote at {address} did not accept a connection within {} ms: is Pupil Capture running with Pupil Remote on this port?",
                    timeout.as_millis()
                ))))
            }
        }
        Ok(PupilRemote {
            socket: Some(socket),
            address: address.to_string(),
            timeout,
        })
    }

    pub fn address(&self) -> &str {
        &self.address
    }

    /// Sends `cmd` and returns the reply string.
    pub async fn request(&mut self, cmd: &str) -> Result<String, DeviceError> {
        self.exchange(ZmqMessage::from(cmd), cmd).await
    }

    /// Sends a multipart message (e.g. a notification: topic, msgpack payload) and returns
    /// the reply string.
    pub async fn request_multipart(
        &mut self,
        frames: Vec<Vec<u8>>,
        what: &str,
    ) -> Result<String, DeviceError> {
        let mut frames = frames.into_iter();
        let first = frames
            .next()
            .ok_or_else(|| DeviceError::Invalid("a message needs at least one frame".into()))?;
        let mut msg = ZmqMessage::from(first);
        for f in frames {
            msg.push_back(f.into());
        }
        self.exchange(msg, what).await
    }

    async fn exchange(&mut self, msg: ZmqMessage, what: &str) -> Result<String, DeviceError> {
        let address = self.address.clone();
        let Some(socket) = self.socket.as_mut() else {
            return Err(lost(format!(
                "Pupil Remote at {address}: the connection was dropped after an earlier request failed"
            )));
        };
        let round_trip = async {
            socket.send(msg).await?;
            socket.recv().await
        };
        let reply = match tokio::time::timeout(self.timeout, round_trip).await {
            Ok(Ok(reply)) => reply,
            Ok(Err(e)) => {
                self.socket = None;
                return Err(lost(format!("Pupil Remote at {address}, {what:?}: {e}")));
            }
            Err(_) => {
                self.socket = None;
                return Err(DeviceError::Link(LinkError::Timeout {
                    ms: self.timeout.as_millis() as u64,
                }));
            }
        };
        let frames = reply.into_vec();
        match frames.as_slice() {
            [one] => String::from_utf8(one.to_vec()).map_err(|_| {
                DeviceError::Protocol(format!(
                    "Pupil Remote at {address} answered {what:?} with bytes that are not UTF-8"
                ))
            }),
            _ => Err(DeviceError::Protocol(format!(
                "Pupil Remote at {address} answered {what:?} with {} frames, expected one",
                frames.len()
            ))),
        }
    }

    /// The port of Capture's IPC publisher (where gaze is subscribed to).
    pub async fn sub_port(&mut self) -> Result<u16, DeviceError> {
        self.port(command::SUB_PORT).await
    }

    /// The port of Capture's IPC subscriber (where messages are published into Capture).
    pub async fn pub_port(&mut self) -> Result<u16, DeviceError> {
        self.port(command::PUB_PORT).await
    }

    async fn port(&mut self, cmd: &str) -> Result<u16, DeviceError> {
        let reply = self.request(cmd).await?;
        parse_port(&reply).map_err(|e| {
            DeviceError::Protocol(format!("Pupil Remote at {}, {cmd:?}: {e}", self.address))
        })
    }

    /// Capture's version string.
    pub async fn version(&mut self) -> Result<String, DeviceError> {
        self.request(command::VERSION).await
    }

    /// Current Pupil time, seconds.
    pub async fn pupil_time(&mut self) -> Result<f64, DeviceError> {
        let reply = self.request(command::TIME).await?;
        parse_time(&reply).map_err(|e| {
            DeviceError::Protocol(format!("Pupil Remote at {}, \"t\": {e}", self.address))
        })
    }

    /// Measures Pupil time minus `clock`'s time `samples` times (at least 2).
    pub async fn estimate_offset(
        &mut self,
        clock: &Arc<dyn Clock>,
        samples: usize,
    ) -> Result<ClockOffset, DeviceError> {
        let samples = samples.max(2);
        let mut offsets = Vec::with_capacity(samples);
        let mut min_rtt = f64::INFINITY;
        for _ in 0..samples {
            let before = clock.now().as_secs_f64();
            let pupil = self.pupil_time().await?;
            let after = clock.now().as_secs_f64();
            min_rtt = min_rtt.min(after - before);
            offsets.push(pupil - (before + after) / 2.0);
        }
        let n = offsets.len() as f64;
        let mean = offsets.iter().sum::<f64>() / n;
        let var = offsets.iter().map(|o| (o - mean).powi(2)).sum::<f64>() / (n - 1.0);
        Ok(ClockOffset {
            mean_s: mean,
            std_s: var.sqrt(),
            min_round_trip_s: min_rtt,
            samples,
        })
    }
}
