//! The host side of dioptra-protocol over any [`ByteLink`]: requests matched to replies by
//! request id, device `Error` replies kept apart from broken links, unsolicited events
//! queued, version negotiation and clock synchronisation.
//!
//! Used by every driver for dioptra's own firmware (lens controller, sync board).

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{Clock, ClockMapper, DeviceError, LinkError, Timestamp};
use dioptra_protocol::{
    encode_frame, next_request_id, DecodeError, DeviceInfo, ErrorCode, Frame, FrameDecoder,
    Message, EVENT_REQUEST_ID, MAX_FRAME_LEN, PROTOCOL_VERSION,
};
use tokio::time::Instant;

use crate::ByteLink;

/// Default wait for a reply (PROTOCOL.md: devices answer within 5 ms; USB and OS scheduling
/// add the rest).
pub const DEFAULT_REPLY_TIMEOUT: Duration = Duration::from_millis(100);

/// A message from the device with the host time it was read.
#[derive(Debug, Clone, PartialEq)]
pub struct Received {
    pub request_id: u16,
    pub message: Message,
    pub host_time: Timestamp,
}

/// Session state of one link to a dioptra device.
pub struct ProtocolClient<L: ByteLink> {
    link: L,
    clock: Arc<dyn Clock>,
    decoder: FrameDecoder,
    inbox: VecDeque<Result<Frame, DecodeError>>,
    inbox_time: Timestamp,
    events: VecDeque<Received>,
    next_id: u16,
    /// Requests sent with [`ProtocolClient::send`] whose replies nobody awaits.
    unawaited: VecDeque<u16>,
    unawaited_errors: VecDeque<DeviceError>,
    mapper: ClockMapper,
    device_info: Option<DeviceInfo>,
    reply_timeout: Duration,
    garbled: u64,
}

/// Most fire-and-forget requests remembered; older ones' replies are then dropped as stale.
const MAX_UNAWAITED: usize = 64;
/// Most queued events kept when nobody reads them; the oldest are dropped.
const MAX_EVENTS: usize = 4096;

impl<L: ByteLink> ProtocolClient<L> {
    pub fn new(link: L, clock: Arc<dyn Clock>) -> Self {
        ProtocolClient {
            link,
            clock,
            decoder: FrameDecoder::new(),
            inbox: VecDeque::new(),
            inbox_time: Timestamp::ZERO,
            events: VecDeque::new(),
            next_id: 0,
            unawaited: VecDeque::new(),
            unawaited_errors: VecDeque::new(),
            mapper: ClockMapper::new(),
            device_info: None,
            reply_timeout: DEFAULT_REPLY_TIMEOUT,
            garbled: 0,
        }
    }

    pub fn with_reply_timeout(mut self, timeout: Duration) -> Self {
        self.reply_timeout = timeout;
        self
    }

    pub fn link(&self) -> &L {
        &self.link
    }
    pub fn link_mut(&mut self) -> &mut L {
        &mut self.link
    }
    pub fn into_link(self) -> L {
        self.link
    }
    pub fn clock_mapper(&self) -> &ClockMapper {
        &self.mapper
    }
    /// What the device said about itself in the last [`ProtocolClient::hello`].
    pub fn device_info(&self) -> Option<&DeviceInfo> {
        self.device_info.as_ref()
    }
    /// Frames that failed to decode so far (bad CRC, bad COBS, unknown message...).
    pub fn garbled_frames(&self) -> u64 {
        self.garbled
    }
    /// Device time mapped to host time, once clocks are synchronised.
    pub fn device_to_host(&self, device_time_us: u64) -> Option<Timestamp> {
        self.mapper.to_host(device_time_us)
    }

    /// Sends `message` as a new request; returns its id and the host time at which the frame
    /// was handed to the link. Its reply is not awaited: a refusal surfaces from
    /// [`ProtocolClient::take_unawaited_error`] or the next call that reads.
    pub async fn send(&mut self, message: &Message) -> Result<(u16, Timestamp), DeviceError> {
        // Read what has arrived first: replies nobody awaits would otherwise fill the link
        // until the device blocks on writing them.
        self.poll().await?;
        let (id, t) = self.write_request(message).await?;
        self.unawaited.push_back(id);
        if self.unawaited.len() > MAX_UNAWAITED {
            self.unawaited.pop_front();
        }
        Ok((id, t))
    }

    /// Sends `message` and waits for the reply with its id. An `Error` reply is
    /// [`DeviceError::Refused`]; silence is a link timeout.
    pub async fn request(&mut self, message: &Message) -> Result<Received, DeviceError> {
        let (id, _) = self.write_request(message).await?;
        let deadline = Instant::now() + self.reply_timeout;
        loop {
            let r = match self.read_one(deadline).await {
                Ok(r) => r,
                Err(e) => {
                    if matches!(e, DeviceError::Link(LinkError::Timeout { .. })) {
                        // A frame whose delimiter was lost would swallow the next good reply.
                        self.decoder.reset();
                    }
                    return Err(self.explain_timeout(e));
                }
            };
            if r.request_id == id {
                return match r.message {
                    Message::Error { code, detail } => Err(refused(code, &detail)),
                    _ => Ok(r),
                };
            }
            if r.request_id == EVENT_REQUEST_ID {
                // The device could not trust a frame it received: most likely this request.
                if let Message::Error { code, detail } = &r.message {
                    if matches!(code, ErrorCode::BadCrc | ErrorCode::FrameTooLong) {
                        return Err(DeviceError::Protocol(format!(
                            "the device received a corrupted frame ({code:?}: {detail}); check the cable"
                        )));
                    }
                }
                self.queue_event(r);
            } else {
                self.settle_unawaited(r);
            }
        }
    }

    /// Waits up to `timeout` for the next unsolicited message (request id 0).
    pub async fn next_event(&mut self, timeout: Duration) -> Result<Received, DeviceError> {
        if let Some(e) = self.events.pop_front() {
            return Ok(e);
        }
        let deadline = Instant::now() + timeout;
        loop {
            let r = self.read_one(deadline).await?;
            if r.request_id == EVENT_REQUEST_ID {
                return Ok(r);
            }
            self.settle_unawaited(r);
        }
    }

    /// Reads what has already arrived without waiting: late replies settle, events queue.
    pub async fn poll(&mut self) -> Result<(), DeviceError> {
        loop {
            match self.read_one(Instant::now()).await {
                Ok(r) if r.request_id == EVENT_REQUEST_ID => self.queue_event(r),
                Ok(r) => self.settle_unawaited(r),
                Err(DeviceError::Link(LinkError::Timeout { .. })) => return Ok(()),
                Err(e) => return Err(e),
            }
        }
    }

    /// A refusal of an earlier [`ProtocolClient::send`], oldest first.
    pub fn take_unawaited_error(&mut self) -> Option<DeviceError> {
        self.unawaited_errors.pop_front()
    }

    /// Opens the session: sends Hello and checks the device's protocol version.
    pub async fn hello(&mut self) -> Result<DeviceInfo, DeviceError> {
        let r = self
            .request(&Message::Hello {
                protocol_version: u16::from(PROTOCOL_VERSION),
            })
            .await?;
        match r.message {
            Message::DeviceInfo(info) if info.protocol_version == u16::from(PROTOCOL_VERSION) => {
                self.device_info = Some(info.clone());
                Ok(info)
            }
            Message::DeviceInfo(info) => Err(DeviceError::Invalid(format!(
                "device speaks protocol version {}, this host speaks {PROTOCOL_VERSION}: update the firmware or dioptra",
                info.protocol_version
            ))),
            other => Err(unexpected("DeviceInfo", &other)),
        }
    }

    /// Runs `rounds` ping/pong exchanges and feeds them to the clock mapper.
    pub async fn sync_time(&mut self, rounds: usize) -> Result<(), DeviceError> {
        for _ in 0..rounds {
            let sent = self.clock.now();
            let r = self
                .request(&Message::TimeSyncPing {
                    host_time_us: sent.as_micros(),
                })
                .await?;
            match r.message {
                Message::TimeSyncPong { device_time_us, .. } => {
                    self.mapper.add_exchange(sent, device_time_us, r.host_time)
                }
                other => return Err(unexpected("TimeSyncPong", &other)),
            }
        }
        Ok(())
    }

    /// Forgets per-connection state after the link was reopened.
    pub fn reset_session(&mut self, link: L) {
        self.link = link;
        self.decoder.reset();
        self.inbox.clear();
        self.events.clear();
        self.unawaited.clear();
        self.mapper.reset();
        self.device_info = None;
    }

    async fn write_request(&mut self, message: &Message) -> Result<(u16, Timestamp), DeviceError> {
        self.next_id = next_request_id(self.next_id);
        let mut buf = [0u8; MAX_FRAME_LEN];
        let n = encode_frame(self.next_id, message, &mut buf)
            .map_err(|e| DeviceError::Invalid(format!("cannot encode {message:?}: {e}")))?;
        self.link.write_all(&buf[..n]).await?;
        Ok((self.next_id, self.clock.now()))
    }

    /// The next decoded frame, reading from the link until `deadline`. Garbled frames are
    /// counted and skipped: the stream decoder has already resynchronised.
    async fn read_one(&mut self, deadline: Instant) -> Result<Received, DeviceError> {
        loop {
            while let Some(item) = self.inbox.pop_front() {
                match item {
                    Ok(frame) => {
                        return Ok(Received {
                            request_id: frame.request_id,
                            message: frame.message,
                            host_time: self.inbox_time,
                        })
                    }
                    Err(DecodeError::UnsupportedVersion { version, .. }) => {
                        return Err(DeviceError::Invalid(format!(
                            "device speaks protocol version {version}, this host speaks {PROTOCOL_VERSION}: update the firmware or dioptra"
                        )))
                    }
                    Err(_) => self.garbled += 1,
                }
            }
            let mut buf = [0u8; 512];
            let left = deadline.saturating_duration_since(Instant::now());
            let n = self.link.read(&mut buf, left).await?;
            self.inbox_time = self.clock.now();
            self.inbox.extend(self.decoder.push(&buf[..n]));
        }
    }

    fn settle_unawaited(&mut self, r: Received) {
        let Some(pos) = self.unawaited.iter().position(|&id| id == r.request_id) else {
            return; // a stale reply to a request that timed out
        };
        self.unawaited.remove(pos);
        if let Message::Error { code, detail } = &r.message {
            self.unawaited_errors.push_back(refused(*code, detail));
        }
    }

    fn queue_event(&mut self, r: Received) {
        self.events.push_back(r);
        if self.events.len() > MAX_EVENTS {
            self.events.pop_front();
        }
    }

    fn explain_timeout(&self, e: DeviceError) -> DeviceError {
        match e {
            DeviceError::Link(LinkError::Timeout { .. }) if self.garbled > 0 => {
                DeviceError::Protocol(format!(
                    "no valid reply within {:?}; {} garbled frame(s) received so far on {}",
                    self.reply_timeout,
                    self.garbled,
                    self.link.describe()
                ))
            }
            other => other,
        }
    }
}

fn refused(code: ErrorCode, detail: &str) -> DeviceError {
    DeviceError::Refused {
        code: u16::from(code),
        detail: format!("{code:?}: {detail}"),
    }
}

fn unexpected(wanted: &str, got: &Message) -> DeviceError {
    DeviceError::Protocol(format!("expected {wanted}, device sent {got:?}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::memory::{self, MemoryLink};
    use dioptra_core::SimClock;
    use dioptra_protocol::{decode_frame, Capabilities, DeviceKind, FirmwareVersion};

    /// A minimal device: answers Hello, TimeSyncPing (device clock = host µs + 1 s) and
    /// refuses everything else; sends one event before each reply.
    async fn fake_device(mut link: MemoryLink) {
        let mut decoder = FrameDecoder::new();
        let mut buf = [0u8; 256];
        loop {
            let Ok(n) = link.read(&mut buf, Duration::from_secs(10)).await else {
                return;
            };
            let frames: Vec<_> = decoder.push(&buf[..n]).collect();
            for f in frames.into_iter().flatten() {
                let reply = match f.message {
                    Message::Hello { .. } => Message::DeviceInfo(DeviceInfo {
                        kind: DeviceKind::Lens,
                        protocol_version: u16::from(PROTOCOL_VERSION),
                        firmware_version: FirmwareVersion {
                            major: 1,
                            minor: 0,
                            patch: 0,
                        },
                        serial: dioptra_protocol::truncated("T1"),
                        capabilities: Capabilities(0),
                    }),
                    Message::TimeSyncPing { host_time_us } => Message::TimeSyncPong {
                        host_time_us,
                        device_time_us: host_time_us + 1_000_000,
                    },
                    _ => Message::error(ErrorCode::NotSupported, "fake"),
                };
                let mut out = [0u8; MAX_FRAME_LEN];
                let n = encode_frame(0, &Message::Start, &mut out).unwrap();
                let _ = link.write_all(&out[..n]).await;
                let n = encode_frame(f.request_id, &reply, &mut out).unwrap();
                let _ = link.write_all(&out[..n]).await;
            }
        }
    }

    fn client() -> ProtocolClient<MemoryLink> {
        let (host, dev) = memory::pair(4096);
        tokio::spawn(fake_device(dev));
        ProtocolClient::new(host, Arc::new(SimClock::new(Timestamp::from_millis(5))))
    }

    #[tokio::test]
    async fn hello_sync_refusal_and_events() {
        let mut c = client();
        let info = c.hello().await.unwrap();
        assert_eq!(info.kind, DeviceKind::Lens);
        c.sync_time(3).await.unwrap();
        // host 5 ms -> device 5 ms + 1 s
        assert_eq!(c.device_to_host(1_005_000), Some(Timestamp::from_millis(5)));
        let e = c.request(&Message::GetLimits).await.unwrap_err();
        assert!(
            matches!(e, DeviceError::Refused { code, .. } if code == u16::from(ErrorCode::NotSupported))
        );
        // Every exchange was preceded by an event; they were queued, not lost.
        for _ in 0..5 {
            let ev = c.next_event(Duration::from_millis(50)).await.unwrap();
            assert_eq!(ev.message, Message::Start);
        }
    }

    #[tokio::test]
    async fn unawaited_refusal_surfaces_later() {
        let mut c = client();
        let (id, _) = c.send(&Message::GetLimits).await.unwrap();
        assert!(id != 0);
        // The reply is read while waiting for something else.
        c.hello().await.unwrap();
        assert!(matches!(
            c.take_unawaited_error(),
            Some(DeviceError::Refused { .. })
        ));
        assert!(c.take_unawaited_error().is_none());
    }

    #[tokio::test(start_paused = true)]
    async fn garbage_then_silence_is_reported_as_protocol_error() {
        let (host, mut dev) = memory::pair(4096);
        let mut c = ProtocolClient::new(host, Arc::new(SimClock::default()));
        dev.write_all(&[1, 2, 3, 0, 9, 9, 0]).await.unwrap();
        let e = c.request(&Message::GetLimits).await.unwrap_err();
        assert!(
            matches!(&e, DeviceError::Protocol(m) if m.contains("garbled")),
            "{e}"
        );
        // The request did reach the device intact.
        let mut buf = [0u8; 64];
        let n = dev.read(&mut buf, Duration::from_millis(1)).await.unwrap();
        assert_eq!(decode_frame(&buf[..n]).unwrap().message, Message::GetLimits);
    }

    #[tokio::test(start_paused = true)]
    async fn lost_delimiter_costs_one_request_not_two() {
        let (host, mut dev) = memory::pair(4096);
        // Answers every request with Ack, but drops the first reply's 0x00 delimiter.
        tokio::spawn(async move {
            let mut decoder = FrameDecoder::new();
            let mut buf = [0u8; 256];
            let mut first = true;
            while let Ok(n) = dev.read(&mut buf, Duration::from_secs(10)).await {
                let frames: Vec<_> = decoder.push(&buf[..n]).collect();
                for f in frames.into_iter().flatten() {
                    let mut out = [0u8; MAX_FRAME_LEN];
                    let n = encode_frame(f.request_id, &Message::Ack, &mut out).unwrap();
                    let n = if first { n - 1 } else { n };
                    first = false;
                    let _ = dev.write_all(&out[..n]).await;
                }
            }
        });
        let mut c = ProtocolClient::new(host, Arc::new(SimClock::default()));
        assert!(c.request(&Message::Start).await.is_err());
        // The half frame was dropped at the timeout, so it cannot swallow the next reply.
        assert_eq!(
            c.request(&Message::Stop).await.unwrap().message,
            Message::Ack
        );
    }

    #[tokio::test]
    async fn unplug_is_a_link_error() {
        let (host, dev) = memory::pair(64);
        drop(dev);
        let mut c = ProtocolClient::new(host, Arc::new(SimClock::default()));
        let e = c.hello().await.unwrap_err();
        assert!(e.needs_reconnect(), "{e:?}");
    }
}
