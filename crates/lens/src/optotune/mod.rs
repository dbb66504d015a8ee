//! Optotune Lens Driver 4 (EL-10-30, EL-16-40 lenses) over any [`ByteLink`]: a USB CDC-ACM
//! port, a pty to `dioptra sim optotune`, or an in-memory link to the simulator.
//!
//! On connect the driver handshakes, reads the firmware type (which sets the focal-power
//! encoding) and maximum current, programs the rig's current limits and the temperature
//! limits (`PwTA`; the device refuses focal-power mode without them), puts the lens in
//! focal-power mode so that the device's own temperature compensation works, and checks the
//! status word. Status error bits (see [`Status::ERRORS`]) stop focal-power control with the
//! device's own words. After a link error the next call reopens the link through the
//! [`Opener`], if one was given, does all of that again and re-sends the last commanded
//! power: the `Start` handshake resets the output current (pyopto's handshake docstring,
//! after the manual; LidkeLab's "run handshake to reset device").

pub mod protocol;

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{
    Clock, DeviceError, DeviceWarning, Diopters, LensState, LinkError, PowerRange, Timestamp,
    VarifocalLens,
};
use dioptra_transport::ByteLink;
use tokio::time::Instant;

use crate::limits::LensLimits;
use crate::reconnect::Opener;
use protocol::{Command, FirmwareVersion, Mode, ProtocolError, Scaling, Status};

/// The Lens Driver 4's line settings: 115200 8N1, no flow control.
pub const BAUD: u32 = 115_200;
/// Default wait for a reply. The device answers within a few ms; 200 ms covers USB scheduling.
pub const DEFAULT_REPLY_TIMEOUT: Duration = Duration::from_millis(200);

/// Temperature limits sent at connect unless configured: kishorerathinavel's varifocal display
/// uses 20-40 °C; LidkeLab 15-30 °C, the Spesyvtsev client 20-45 °C. A wider span covers a
/// warmer lens but narrows the focal-power range the device can hold.
pub const DEFAULT_TEMPERATURE_LIMITS_C: (f32, f32) = (20.0, 40.0);

/// How the driver runs one lens.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OptotuneConfig {
    pub limits: LensLimits,
    pub reply_timeout: Duration,
    /// (lower, upper) °C sent with `PwTA` at every (re)connect: the span focal-power mode
    /// compensates over. Within -120..120 °C, lower below upper.
    pub temperature_limits_c: (f32, f32),
}

impl OptotuneConfig {
    pub fn new(limits: LensLimits) -> Self {
        OptotuneConfig {
            limits,
            reply_timeout: DEFAULT_REPLY_TIMEOUT,
            temperature_limits_c: DEFAULT_TEMPERATURE_LIMITS_C,
        }
    }
    /// The rig's `(lower, upper)` temperature limits, °C.
    pub fn with_temperature_limits_c(mut self, lower: f32, upper: f32) -> Self {
        self.temperature_limits_c = (lower, upper);
        self
    }
}

/// What the device said about itself at the last (re)connect.
#[derive(Debug, Clone, PartialEq)]
pub struct OptotuneInfo {
    /// ASCII firmware type letter (`A` uses the +5 D focal-power offset).
    pub firmware_type: u8,
    pub firmware_version: FirmwareVersion,
    pub serial_number: String,
    pub device_id: String,
    pub max_current_ma: f32,
    /// Focal-power range the device reported for its temperature limits.
    pub device_range: PowerRange,
}

/// A connected Lens Driver 4.
pub struct Optotune<L: ByteLink> {
    link: Option<L>,
    opener: Option<Opener<L>>,
    clock: Arc<dyn Clock>,
    cfg: OptotuneConfig,
    info: Option<OptotuneInfo>,
    scaling: Scaling,
    /// The rig's limits narrowed to the device's range.
    range: PowerRange,
    mode: Mode,
    /// The last focal power sent, re-sent after a reconnect.
    last_power: Option<Diopters>,
    /// Status error bits last seen; focal-power control stays stopped while set.
    fault: Option<Status>,
    /// Warning bits reported since the last (re)connect: each is reported once per session.
    warned: Status,
    /// Warnings not yet taken by the caller ([`VarifocalLens::take_warnings`]).
    warnings: Vec<DeviceWarning>,
    /// The reply being read, kept here rather than on the exchange's stack: an exchange
    /// dropped mid-reply (a state read cut short by a new command) leaves what it read, and
    /// the next exchange reads the rest of that frame before its own.
    reply: Option<Reply>,
    buf: Vec<u8>,
    stray_crc_errors: u64,
    reconnects: u64,
}

impl<L: ByteLink> std::fmt::Debug for Optotune<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Optotune")
            .field("link", &self.link.as_ref().map(|l| l.describe()))
            .field("info", &self.info)
            .field("range", &self.range)
            .finish_non_exhaustive()
    }
}

impl<L: ByteLink> Optotune<L> {
    /// Opens a session on `link`. Without an [`Opener`] a lost link stays lost.
    pub async fn connect(
        link: L,
        cfg: OptotuneConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, DeviceError> {
        let mut d = Self::unconnected(None, cfg, clock);
        d.link = Some(link);
        d.open_session().await?;
        Ok(d)
    }

    /// Opens the link with `opener` and keeps it to reopen the link after an unplug.
    pub async fn connect_with(
        mut opener: Opener<L>,
        cfg: OptotuneConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, DeviceError> {
        let link = opener.open().await?;
        let mut d = Self::unconnected(Some(opener), cfg, clock);
        d.link = Some(link);
        d.open_session().await?;
        Ok(d)
    }

    fn unconnected(opener: Option<Opener<L>>, cfg: OptotuneConfig, clock: Arc<dyn Clock>) -> Self {
        Optotune {
            link: None,
            opener,
            clock,
            range: cfg.limits.power,
            cfg,
            info: None,
            scaling: Scaling::default(),
            mode: Mode::Other(0),
            last_power: None,
            fault: None,
            warned: Status(0),
            warnings: Vec::new(),
            reply: None,
            buf: Vec::with_capacity(protocol::MAX_COMMAND_LEN),
            stray_crc_errors: 0,
            reconnects: 0,
        }
    }

    /// The device's identity, as read at the last (re)connect.
    pub fn info(&self) -> Option<&OptotuneInfo> {
        self.info.as_ref()
    }
    /// The active mode as this driver last set or read it.
    pub fn mode(&self) -> Mode {
        self.mode
    }
    /// `N` replies the device sent to commands that have no reply of their own (`Aw`,
    /// `PwDA`): each means one such command arrived corrupted and was not applied.
    pub fn stray_crc_errors(&self) -> u64 {
        self.stray_crc_errors
    }
    /// How often the link was reopened.
    pub fn reconnects(&self) -> u64 {
        self.reconnects
    }
    pub fn is_connected(&self) -> bool {
        self.link.is_some()
    }

    /// Sends any typed command and returns its typed reply. Limits are not checked here:
    /// prefer [`VarifocalLens::set_power`] and [`Optotune::set_current_ma`].
    pub async fn request<C: Command>(&mut self, cmd: &C) -> Result<C::Response, DeviceError> {
        self.ensure_link().await?;
        let r = self.exchange(cmd).await;
        self.note(r).map(|(r, _)| r)
    }

    /// Lens temperature, °C.
    pub async fn temperature_c(&mut self) -> Result<f32, DeviceError> {
        self.request(&protocol::GetTemperature).await
    }

    /// Firmware status bits. Error bits stop focal-power control until a status read or a
    /// reconnect without them; warnings are logged.
    pub async fn status(&mut self) -> Result<Status, DeviceError> {
        let s = self.request(&protocol::GetStatus).await?;
        self.note_status(s, true);
        Ok(s)
    }

    /// The status error bits that stopped focal-power control, if any.
    pub fn fault(&self) -> Option<Status> {
        self.fault
    }

    /// The warning bits the device raised since the last (re)connect.
    pub fn warned(&self) -> Status {
        self.warned
    }

    /// Records `s`'s error bits (or their absence) and queues its warning bits not yet
    /// reported this session for the caller, who knows which lens this is. A status byte from
    /// a `PwTA`/`MwCA` reply (`full_word` false) says nothing about the bits above byte #1.
    fn note_status(&mut self, s: Status, full_word: bool) {
        let kept = if full_word {
            0
        } else {
            self.fault.map_or(0, |f| f.0 & !0xff)
        };
        self.fault = Some(Status(s.errors().0 | kept)).filter(|e| e.0 != 0);
        let new = s.warnings().0 & !self.warned.0;
        if new == 0 {
            return;
        }
        self.warned = Status(self.warned.0 | new);
        tracing::debug!(status = new, "Lens Driver 4 status warning");
        for bit in (0..9).map(|b| 1u32 << b).filter(|b| new & b != 0) {
            self.warnings.push(DeviceWarning {
                condition: format!(
                    "the Lens Driver 4 reports {}",
                    Status(bit).names().join(", ")
                ),
                meaning: warning_meaning(bit, self.cfg.temperature_limits_c),
            });
        }
    }

    /// Sends the configured temperature limits again and narrows the driving range to the
    /// focal-power range the device reports for them (its `PwTA` reply).
    pub async fn refresh_range(&mut self) -> Result<PowerRange, DeviceError> {
        self.ensure_link().await?;
        let r = self.send_temperature_limits().await;
        let r = self.note(r)?;
        self.adopt_range(r)?;
        Ok(self.range)
    }

    /// Switches to current mode (open loop: the power drifts as the lens warms). Lasts until
    /// the next reconnect, which restores focal-power mode.
    pub async fn use_current_mode(&mut self) -> Result<(), DeviceError> {
        self.request(&protocol::SetCurrentMode).await?;
        self.mode = Mode::Current;
        Ok(())
    }

    /// Switches to focal-power mode and returns the reachable range the device reports.
    pub async fn use_focal_power_mode(&mut self) -> Result<PowerRange, DeviceError> {
        self.ensure_link().await?;
        let r = self.enter_focal_power_mode().await;
        let r = self.note(r)?;
        self.adopt_range(r)
    }

    /// Sets the drive current (current mode only), within the rig's current limits; returns
    /// the host time the command was on the wire.
    pub async fn set_current_ma(&mut self, ma: f32) -> Result<Timestamp, DeviceError> {
        if self.mode != Mode::Current {
            return Err(DeviceError::Invalid(
                "set_current_ma needs current mode; call use_current_mode first".into(),
            ));
        }
        let ma = self
            .cfg
            .limits
            .check_current(ma, self.scaling.max_current_ma)?;
        self.ensure_link().await?;
        let r = self.exchange(&protocol::SetCurrent { ma }).await;
        self.note(r).map(|(_, t)| t)
    }

    /// Handshake and the setup every session needs.
    async fn open_session(&mut self) -> Result<(), DeviceError> {
        let r = self.session_setup().await;
        self.note(r)
    }

    async fn session_setup(&mut self) -> Result<(), DeviceError> {
        // A new session reports its warnings again, once.
        self.warned = Status(0);
        self.handshake().await?;
        let firmware_type = self.exchange(&protocol::GetFirmwareType).await?.0;
        let firmware_version = self.exchange(&protocol::GetFirmwareVersion).await?.0;
        let serial_number = self.exchange(&protocol::GetSerialNumber).await?.0;
        let device_id = self.exchange(&protocol::GetDeviceId).await?.0;
        let max_current_ma = self.exchange(&protocol::GetMaxCurrent).await?.0;
        if max_current_ma.is_nan() || max_current_ma <= 0.0 {
            return Err(DeviceError::Protocol(format!(
                "device reports a maximum current of {max_current_ma} mA"
            )));
        }
        self.scaling = Scaling {
            firmware_type,
            max_current_ma,
        };
        if let Some((lo, hi)) = self.cfg.limits.current_ma {
            // The device holds these too, so they bind in focal-power mode, where it picks the current.
            let hi = hi.clamp(-max_current_ma, max_current_ma);
            let lo = lo.clamp(-max_current_ma, hi);
            self.exchange(&protocol::SetCurrentLimit {
                which: protocol::CurrentLimit::Upper,
                ma: hi,
            })
            .await?;
            self.exchange(&protocol::SetCurrentLimit {
                which: protocol::CurrentLimit::Lower,
                ma: lo,
            })
            .await?;
        }
        // Every open client sends the limits before focal-power mode (LidkeLab: they "need to
        // be set in order to be able to switch to focal power controlled mode"); their reply
        // carries the range, which spares the disputed `PrTA`.
        let mut range = self.send_temperature_limits().await?;
        if self.exchange(&protocol::GetMode).await?.0 != Mode::FocalPower {
            range = self.enter_focal_power_mode().await?;
        }
        self.mode = Mode::FocalPower;
        // The full word: byte #2 holds the lens-incompatible bit, which no range reply carries.
        let status = self.exchange(&protocol::GetStatus).await?.0;
        self.note_status(status, true);
        check_status(status, "at connect")?;
        let device_range = self.adopt_range(range)?;
        self.info = Some(OptotuneInfo {
            firmware_type,
            firmware_version,
            serial_number,
            device_id,
            max_current_ma,
            device_range,
        });
        Ok(())
    }

    /// `PwTA` with the configured limits; a status byte with error bits is a refusal.
    async fn send_temperature_limits(&mut self) -> Result<protocol::FocalPowerRange, DeviceError> {
        let (lower_c, upper_c) = self.cfg.temperature_limits_c;
        let (r, _) = self
            .exchange(&protocol::SetTemperatureLimits { upper_c, lower_c })
            .await?;
        self.note_status(r.status, false);
        check_status(r.status, "after setting the temperature limits (PwTA)")?;
        Ok(r)
    }

    /// `MwCA`, its status byte checked, then `MMA` to confirm the device switched.
    async fn enter_focal_power_mode(&mut self) -> Result<protocol::FocalPowerRange, DeviceError> {
        let (r, _) = self.exchange(&protocol::SetFocalPowerMode).await?;
        self.note_status(r.status, false);
        check_status(r.status, "when entering focal-power mode (MwCA)")?;
        let mode = self.exchange(&protocol::GetMode).await?.0;
        if mode != Mode::FocalPower {
            return Err(DeviceError::Refused {
                code: u16::from(mode.number()),
                detail: format!(
                    "the Lens Driver 4 stayed in mode {} after MwCA instead of focal-power \
                     mode (5)",
                    mode.number()
                ),
            });
        }
        self.mode = Mode::FocalPower;
        Ok(r)
    }

    /// Narrows the rig's range to what the device reports; returns the device's range.
    fn adopt_range(&mut self, r: protocol::FocalPowerRange) -> Result<PowerRange, DeviceError> {
        let device = PowerRange::new(Diopters(r.min_d), Diopters(r.max_d)).ok_or_else(|| {
            DeviceError::Protocol(format!(
                "device reports an empty focal-power range {}..{} D",
                r.min_d, r.max_d
            ))
        })?;
        self.range = self.cfg.limits.narrowed_to(device)?;
        if let Some(info) = &mut self.info {
            info.device_range = device;
        }
        Ok(device)
    }

    async fn handshake(&mut self) -> Result<(), DeviceError> {
        let timeout = self.cfg.reply_timeout;
        let link = self.link.as_mut().ok_or_else(not_connected)?;
        link.discard_input().await?;
        link.write_all(protocol::HANDSHAKE).await?;
        // Stale bytes (a reply to a previous client still in flight, an `N` for its half-sent
        // command) may come first: look for `Ready\r\n` at the end of what arrives.
        let deadline = Instant::now() + timeout;
        let mut got = Vec::with_capacity(32);
        let mut byte = [0u8; 1];
        while !got.ends_with(protocol::READY) {
            if got.len() >= 64 {
                return Err(DeviceError::Protocol(format!(
                    "handshake answered {:?} instead of \"Ready\\r\\n\"",
                    String::from_utf8_lossy(&got)
                )));
            }
            let left = deadline.saturating_duration_since(Instant::now());
            match link.read_exact(&mut byte, left).await {
                Ok(()) => got.push(byte[0]),
                Err(LinkError::Timeout { .. }) => {
                    return Err(DeviceError::Protocol(format!(
                        "no \"Ready\\r\\n\" reply to the handshake from {} within {timeout:?} (got {:?}): \
                         is this an Optotune Lens Driver 4?",
                        link.describe(),
                        String::from_utf8_lossy(&got)
                    )))
                }
                Err(e) => return Err(e.into()),
            }
        }
        Ok(())
    }

    /// Reopens a lost link (if there is an opener) and redoes the session setup.
    async fn ensure_link(&mut self) -> Result<(), DeviceError> {
        if self.link.is_some() {
            return Ok(());
        }
        let Some(opener) = self.opener.as_mut() else {
            return Err(not_connected());
        };
        let link = opener.open().await?;
        tracing::info!(link = %link.describe(), "Lens Driver 4 reconnected");
        self.link = Some(link);
        self.reconnects += 1;
        self.open_session().await?;
        // The handshake reset the output current: put the lens back where it was commanded
        // before anyone reads it as ok.
        if let Some(p) = self.last_power {
            let r = self
                .exchange(&protocol::SetFocalPower { diopters: p.0 })
                .await;
            self.note(r)?;
        }
        Ok(())
    }

    /// Drops the link after an error that needs a reconnect.
    fn note<T>(&mut self, r: Result<T, DeviceError>) -> Result<T, DeviceError> {
        if let Err(e) = &r {
            if e.needs_reconnect() {
                self.link = None;
            }
        }
        r
    }

    /// One command and its reply, with stray input drained first. Returns the reply and the
    /// host time at which the command was handed to the link.
    async fn exchange<C: Command>(
        &mut self,
        cmd: &C,
    ) -> Result<(C::Response, Timestamp), DeviceError> {
        let timeout = self.cfg.reply_timeout;
        let scaling = self.scaling;
        let link = self.link.as_mut().ok_or_else(not_connected)?;
        // A caller dropped the last exchange after its command went out: the rest of its
        // reply may still be on the way. Read that frame to its end and drop it, or it would
        // be read as this command's reply.
        if self.reply.is_some() {
            match finish_reply(link, &mut self.reply, timeout).await {
                Err(e) if e.needs_reconnect() => return Err(e),
                // A reply that never came (timeout, or garbage): drain resynchronises.
                _ => self.reply = None,
            }
        }
        self.stray_crc_errors += drain(link).await?;
        protocol::encode(cmd, &scaling, &mut self.buf)
            .map_err(|e| DeviceError::Invalid(e.to_string()))?;
        link.write_all(&self.buf).await?;
        let sent = self.clock.now();
        if C::REPLY_LEN == 0 {
            return Ok((C::parse(&[], &scaling).map_err(protocol_error)?, sent));
        }
        self.reply = Some(Reply::new(C::REPLY_LEN));
        let read = finish_reply(link, &mut self.reply, timeout).await;
        let frame = self.reply.take();
        let len = read?;
        let frame = frame.ok_or_else(|| DeviceError::Protocol("reply state lost".into()))?;
        let r = protocol::decode::<C>(&frame.frame[..len], &scaling).map_err(protocol_error)?;
        Ok((r, self.clock.now()))
    }
}

/// Longest reply frame: IR's 10-byte payload + CRC + CRLF.
const MAX_FRAME_LEN: usize = 16;

/// A reply frame read so far.
#[derive(Debug, Clone)]
struct Reply {
    /// Payload length of the command's normal reply (`N\r\n` and `E` frames have their own).
    reply_len: usize,
    frame: [u8; MAX_FRAME_LEN],
    got: usize,
}

impl Reply {
    fn new(reply_len: usize) -> Reply {
        Reply {
            reply_len,
            frame: [0; MAX_FRAME_LEN],
            got: 0,
        }
    }

    /// The whole frame's length, known from its first byte.
    fn len(&self) -> usize {
        if self.got == 0 {
            return 1;
        }
        match self.frame[0] {
            b'N' => protocol::CRC_ERROR_REPLY.len(),
            b'E' => protocol::ERROR_PAYLOAD_LEN + protocol::TRAILER_LEN,
            _ => self.reply_len + protocol::TRAILER_LEN,
        }
        .min(MAX_FRAME_LEN)
    }
}

/// Reads the rest of the frame in `reply` within `timeout`; returns its length. Cancel-safe:
/// every byte read is stored in `reply` before the next await, so a dropped call loses
/// nothing and a later call goes on where it stopped.
async fn finish_reply<L: ByteLink>(
    link: &mut L,
    reply: &mut Option<Reply>,
    timeout: Duration,
) -> Result<usize, DeviceError> {
    let deadline = Instant::now() + timeout;
    let timed_out = |e: LinkError| match e {
        LinkError::Timeout { .. } => LinkError::Timeout {
            ms: u64::try_from(timeout.as_millis()).unwrap_or(u64::MAX),
        }
        .into(),
        other => DeviceError::from(other),
    };
    loop {
        let r = reply
            .as_mut()
            .ok_or_else(|| DeviceError::Protocol("no reply is being read".into()))?;
        let len = r.len();
        if r.got >= len && r.got > 0 {
            return Ok(len);
        }
        let left = deadline.saturating_duration_since(Instant::now());
        let n = link
            .read(&mut r.frame[r.got..len], left)
            .await
            .map_err(timed_out)?;
        if n == 0 && left.is_zero() {
            return Err(timed_out(LinkError::Timeout { ms: 0 }));
        }
        r.got += n;
    }
}

/// Reads and drops whatever already arrived; returns how many `N\r\n` it held.
async fn drain<L: ByteLink>(link: &mut L) -> Result<u64, DeviceError> {
    let mut stray = [0u8; 64];
    let mut crc_errors = 0;
    loop {
        match link.read(&mut stray, Duration::ZERO).await {
            Ok(n) => {
                crc_errors += stray[..n]
                    .windows(3)
                    .filter(|w| *w == protocol::CRC_ERROR_REPLY)
                    .count() as u64;
                if n < stray.len() {
                    return Ok(crc_errors);
                }
            }
            Err(LinkError::Timeout { .. }) => return Ok(crc_errors),
            Err(e) => return Err(e.into()),
        }
    }
}

fn not_connected() -> DeviceError {
    DeviceError::Link(LinkError::Disconnected(
        "the Lens Driver 4 link was lost and this driver has no way to reopen it".into(),
    ))
}

/// Status error bits as a refusal naming them.
fn check_status(s: Status, when: &str) -> Result<(), DeviceError> {
    let e = s.errors();
    if e.0 == 0 {
        return Ok(());
    }
    Err(DeviceError::Refused {
        code: u16::try_from(e.0).unwrap_or(u16::MAX),
        detail: format!(
            "the Lens Driver 4 reports {} {when}; focal-power control stopped{}",
            e.names().join(", "),
            if e.contains(Status::NO_TEMPERATURE_LIMITS) {
                " (check devices.lens.temperature_limits_c)"
            } else {
                ""
            }
        ),
    })
}

/// What a status warning bit means for the person running the rig, and what to do.
fn warning_meaning(bit: u32, (lower_c, upper_c): (f32, f32)) -> String {
    match bit {
        Status::CANNOT_REACH_FOCAL_POWER => "the lens cannot reach the focal power it was \
            commanded to within its current limits: it holds the nearest power it can, so the \
            focus is not the one asked for"
            .into(),
        Status::TEMPERATURE_OUTSIDE_SPEC => "the lens is outside its product's temperature \
            specification: its focal power is not calibrated there; let it return to room \
            temperature before trusting its focus"
            .into(),
        Status::FOCAL_POWER_OUTSIDE_GUARANTEED_RANGE => format!(
            "the commanded focal power is outside the range the driver can hold at every \
             temperature between {lower_c} and {upper_c} °C (devices.lens.temperature_limits_c): \
             it may drift as the lens warms or cools; narrower limits widen that range"
        ),
        Status::TEMPERATURE_OUTSIDE_LIMITS => format!(
            "the lens temperature is outside the limits {lower_c}..{upper_c} °C \
             (devices.lens.temperature_limits_c): its temperature compensation no longer \
             guarantees the focal power; widen the limits or let the lens settle"
        ),
        _ => "a condition Optotune's protocol sheet does not describe further".into(),
    }
}

fn protocol_error(e: ProtocolError) -> DeviceError {
    match e {
        ProtocolError::CommandError { code } => DeviceError::Refused {
            code: u16::from(code),
            detail: format!(
                "the Lens Driver 4 answered E{code}: {}",
                protocol::error_code::meaning(code)
            ),
        },
        ProtocolError::DeviceSawBadCrc => DeviceError::Protocol(
            "the Lens Driver 4 received a corrupted command (it answered N); check the cable"
                .into(),
        ),
        ProtocolError::Unencodable { .. } => DeviceError::Invalid(e.to_string()),
        other => DeviceError::Protocol(other.to_string()),
    }
}

impl<L: ByteLink> VarifocalLens for Optotune<L> {
    fn power_range(&self) -> PowerRange {
        self.range
    }

    async fn set_power(&mut self, power: Diopters) -> Result<Timestamp, DeviceError> {
        self.ensure_link().await?;
        let power = self.cfg.limits.check_power(power, self.range)?;
        if let Some(f) = self.fault {
            check_status(f, "in its last status")?;
        }
        if self.mode != Mode::FocalPower {
            return Err(DeviceError::Invalid(
                "set_power needs focal-power mode; call use_focal_power_mode first".into(),
            ));
        }
        let r = self
            .exchange(&protocol::SetFocalPower { diopters: power.0 })
            .await;
        let t = self.note(r).map(|(_, t)| t)?;
        self.last_power = Some(power);
        Ok(t)
    }

    async fn state(&mut self) -> Result<LensState, DeviceError> {
        self.ensure_link().await?;
        let r = async {
            let (power, _) = self.exchange(&protocol::GetFocalPower).await?;
            let (current, _) = self.exchange(&protocol::GetCurrent).await?;
            let (temperature, host_time) = self.exchange(&protocol::GetTemperature).await?;
            Ok(LensState {
                power: Diopters(power),
                current_ma: Some(current),
                temperature_c: Some(temperature),
                // The Lens Driver 4 does not say whether the lens has settled.
                settled: None,
                host_time,
            })
        }
        .await;
        self.note(r)
    }

    fn take_warnings(&mut self) -> Vec<DeviceWarning> {
        std::mem::take(&mut self.warnings)
    }
}
