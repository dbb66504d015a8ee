//! The messages exchanged between the host and dioptra's device firmware.
//!
//! Every type here serialises with postcard; PROTOCOL.md gives the byte-level layout. The order
//! of `Message`'s variants and of every field is the wire format: append new variants at the
//! end and bump [`crate::PROTOCOL_VERSION`] for any other change.

use heapless::{String, Vec};
use serde::{Deserialize, Serialize};

/// Most focal planes a [`PlaneSchedule`] can hold.
pub const MAX_PLANES: usize = 16;
/// Capacity in bytes (UTF-8) of [`DeviceInfo::serial`].
pub const SERIAL_LEN: usize = 16;
/// Capacity in bytes (UTF-8) of the detail text in [`Message::Error`].
pub const ERROR_DETAIL_LEN: usize = 32;
/// How far ahead of the device clock `apply_at_us` may lie. A device refuses anything later with
/// [`ErrorCode::OutOfRange`]: such a value is almost always a host timestamp sent by mistake.
pub const MAX_APPLY_AHEAD_US: u64 = 1_000_000;

/// A device's serial number.
pub type Serial = String<SERIAL_LEN>;
/// Human-readable detail of a [`Message::Error`].
pub type ErrorDetail = String<ERROR_DETAIL_LEN>;

/// One protocol message. Discriminants (postcard variant indices) are listed in PROTOCOL.md.
///
/// Requests go host -> device with a non-zero request id; the device's reply carries the same id.
/// Events go device -> host unsolicited with request id 0.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Message {
    /// 0, request: opens a session. Reply: [`Message::DeviceInfo`].
    Hello {
        /// The protocol version the host speaks.
        protocol_version: u16,
    },
    /// 1, reply to [`Message::Hello`].
    DeviceInfo(DeviceInfo),
    /// 2, reply: the request was accepted (for a scheduled action: accepted, not yet done).
    Ack,
    /// 3, reply: the request was refused; or an event (id 0) about a frame the device could not
    /// trust enough to answer.
    Error {
        /// What went wrong.
        code: ErrorCode,
        /// Free text for logs; never parsed.
        detail: ErrorDetail,
    },
    /// 4, request: clock synchronisation. Reply: [`Message::TimeSyncPong`].
    TimeSyncPing {
        /// Host clock when the ping was sent, in microseconds.
        host_time_us: u64,
    },
    /// 5, reply to [`Message::TimeSyncPing`].
    TimeSyncPong {
        /// The ping's `host_time_us`, echoed.
        host_time_us: u64,
        /// Device clock when the ping was received, in microseconds.
        device_time_us: u64,
    },
    /// 6, request (lens): set the optical power. Reply: [`Message::Ack`], or
    /// [`Message::Fault`] with [`FaultKind::LateApply`] when `apply_at_us` had already passed.
    SetFocalPower {
        /// Target optical power in diopters.
        diopters: f32,
        /// Device time at which to apply the power; 0 = on receipt.
        apply_at_us: u64,
    },
    /// 7, request (lens). Reply: [`Message::LensState`].
    GetLensState,
    /// 8, reply to [`Message::GetLensState`].
    LensState(LensState),
    /// 9, request (lens). Reply: [`Message::Limits`].
    GetLimits,
    /// 10, reply to [`Message::GetLimits`].
    Limits(Limits),
    /// 11, request (sync board): load a plane schedule. Reply: [`Message::Ack`].
    PlaneSchedule(PlaneSchedule),
    /// 12, request: start the device's activity (sync board: run the schedule; eye tracker:
    /// stream samples). Reply: [`Message::Ack`].
    Start,
    /// 13, request: stop the device's activity; idempotent. Reply: [`Message::Ack`].
    Stop,
    /// 14, event (sync board): a subframe began.
    SubframeEvent(SubframeEvent),
    /// 15, event: something went wrong during operation (or reply, see `SetFocalPower`).
    Fault(Fault),
    /// 16, event (eye tracker): one binocular gaze sample.
    BinocularSample(BinocularSample),
    /// 17, request (sync board, since version 2): switches the photodiode input on or off and
    /// sets its threshold. Reply: [`Message::Ack`].
    PhotodiodeConfig(PhotodiodeConfig),
    /// 18, event (sync board, since version 2): the light on the photodiode crossed the
    /// threshold.
    PhotodiodeEdge(PhotodiodeEdge),
}

/// Number of `Message` variants; a discriminant at or above it is an unknown message.
pub(crate) const MESSAGE_VARIANT_COUNT: u32 = 19;

impl Message {
    /// A [`Message::Error`] with `detail` cut to [`ERROR_DETAIL_LEN`] bytes at a char boundary.
    pub fn error(code: ErrorCode, detail: &str) -> Self {
        Message::Error {
            code,
            detail: truncated(detail),
        }
    }
}

/// `text` cut to the longest prefix of whole chars that fits `N` bytes.
pub fn truncated<const N: usize>(text: &str) -> String<N> {
    let mut out = String::new();
    for c in text.chars() {
        if out.push(c).is_err() {
            break;
        }
    }
    out
}

/// What kind of device is answering.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum DeviceKind {
    /// 0: varifocal lens controller.
    Lens,
    /// 1: multifocal synchronisation board.
    SyncBoard,
    /// 2: binocular eye tracker.
    EyeTracker,
}

/// Firmware version, semantic-versioning style.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FirmwareVersion {
    /// Incompatible changes.
    pub major: u16,
    /// Compatible additions.
    pub minor: u16,
    /// Fixes.
    pub patch: u16,
}

/// Feature bits a device announces in [`DeviceInfo::capabilities`]. Unknown bits are ignored.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Capabilities(pub u32);

impl Capabilities {
    /// Answers `SetFocalPower`, `GetLensState` and `GetLimits`.
    pub const FOCAL_POWER: Self = Self(1 << 0);
    /// Honours a non-zero `apply_at_us` (otherwise applies every power on receipt).
    pub const SCHEDULED_APPLY: Self = Self(1 << 1);
    /// `LensState::temperature_c` is measured (otherwise it is NaN).
    pub const TEMPERATURE: Self = Self(1 << 2);
    /// Runs `PlaneSchedule`s and sends `SubframeEvent`s.
    pub const PLANE_SCHEDULE: Self = Self(1 << 3);
    /// Streams `BinocularSample`s.
    pub const BINOCULAR_GAZE: Self = Self(1 << 4);
    /// `EyeSample::pupil_mm` is measured (otherwise it is NaN).
    pub const PUPIL_SIZE: Self = Self(1 << 5);
    /// Answers `TimeSyncPing`.
    pub const TIME_SYNC: Self = Self(1 << 6);
    /// Has a photodiode input: answers `PhotodiodeConfig`, sends `PhotodiodeEdge`s.
    pub const PHOTODIODE: Self = Self(1 << 7);

    /// Whether every bit of `other` is set in `self`.
    pub const fn contains(self, other: Self) -> bool {
        self.0 & other.0 == other.0
    }

    /// `self` with the bits of `other` added.
    pub const fn with(self, other: Self) -> Self {
        Self(self.0 | other.0)
    }
}

/// Reply to `Hello`: who the device is.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DeviceInfo {
    /// What the device is.
    pub kind: DeviceKind,
    /// The protocol version the device speaks.
    pub protocol_version: u16,
    /// The firmware build.
    pub firmware_version: FirmwareVersion,
    /// Serial number, UTF-8.
    pub serial: Serial,
    /// What the device can do.
    pub capabilities: Capabilities,
}

/// The lens's measured state.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LensState {
    /// Optical power the lens is driven to, in diopters.
    pub power_d: f32,
    /// Drive current in milliamperes.
    pub current_ma: f32,
    /// Lens temperature in degrees Celsius (NaN without [`Capabilities::TEMPERATURE`]).
    pub temperature_c: f32,
    /// Whether the lens has settled at `power_d`.
    pub settled: bool,
    /// Device time of the measurement.
    pub device_time_us: u64,
}

/// The lens's safe operating range.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Limits {
    /// Lowest optical power in diopters.
    pub min_power_d: f32,
    /// Highest optical power in diopters.
    pub max_power_d: f32,
    /// Highest drive current in milliamperes.
    pub max_current_ma: f32,
}

/// A multifocal schedule: each display frame is split into one subframe per plane, and the lens
/// is driven to the plane's power for that subframe.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlaneSchedule {
    /// Optical power of each plane in display order, in diopters (1..=16 planes).
    pub plane_powers_d: Vec<f32, MAX_PLANES>,
    /// Duration of one subframe in microseconds.
    pub subframe_period_us: u32,
    /// Time the lens gets to settle at the start of a subframe, in microseconds; the rest of the
    /// subframe is displayed.
    pub settle_allowance_us: u32,
    /// Whether a frame starts on the rising (true) or falling (false) edge of the vsync trigger.
    pub trigger_rising: bool,
}

/// Why a [`PlaneSchedule`] is unusable. A device replies [`ErrorCode::InvalidSchedule`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ScheduleError {
    /// No planes, or more than [`MAX_PLANES`].
    #[error("a schedule needs 1 to {MAX_PLANES} planes, got {count}")]
    PlaneCount {
        /// Planes given.
        count: usize,
    },
    /// A plane power is NaN or infinite.
    #[error("plane {index} has a non-finite power")]
    NonFinitePower {
        /// Index of the plane.
        index: usize,
    },
    /// `subframe_period_us` is 0.
    #[error("subframe period must be positive")]
    ZeroPeriod,
    /// The settle allowance leaves no display time.
    #[error("settle allowance {settle_allowance_us} us must be shorter than the subframe period {subframe_period_us} us")]
    SettleTooLong {
        /// Allowance given.
        settle_allowance_us: u32,
        /// Period given.
        subframe_period_us: u32,
    },
}

impl PlaneSchedule {
    /// A checked schedule (see [`PlaneSchedule::validate`]).
    pub fn new(
        plane_powers_d: &[f32],
        subframe_period_us: u32,
        settle_allowance_us: u32,
        trigger_rising: bool,
    ) -> Result<Self, ScheduleError> {
        let plane_powers_d =
            Vec::from_slice(plane_powers_d).map_err(|()| ScheduleError::PlaneCount {
                count: plane_powers_d.len(),
            })?;
        let schedule = Self {
            plane_powers_d,
            subframe_period_us,
            settle_allowance_us,
            trigger_rising,
        };
        schedule.validate()?;
        Ok(schedule)
    }

    /// Checks what the wire format cannot: at least one plane, finite powers, a positive period
    /// and a settle allowance shorter than it. Devices call this on every received schedule.
    pub fn validate(&self) -> Result<(), ScheduleError> {
        if self.plane_powers_d.is_empty() {
            return Err(ScheduleError::PlaneCount { count: 0 });
        }
        if let Some(index) = self.plane_powers_d.iter().position(|p| !p.is_finite()) {
            return Err(ScheduleError::NonFinitePower { index });
        }
        if self.subframe_period_us == 0 {
            return Err(ScheduleError::ZeroPeriod);
        }
        if self.settle_allowance_us >= self.subframe_period_us {
            return Err(ScheduleError::SettleTooLong {
                settle_allowance_us: self.settle_allowance_us,
                subframe_period_us: self.subframe_period_us,
            });
        }
        Ok(())
    }
}

/// The sync board started a subframe.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SubframeEvent {
    /// Display frame counter since `Start`, from 0; wraps.
    pub frame: u32,
    /// Index of the plane in the schedule.
    pub plane_index: u8,
    /// Device time of the subframe's start.
    pub device_time_us: u64,
    /// Lens power measured at the subframe's start, in diopters.
    pub lens_power_d: f32,
}

/// What went wrong in a [`Fault`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum FaultKind {
    /// 0: the expected vsync trigger did not come.
    MissedVsync,
    /// 1: the lens had not settled when the settle allowance ran out.
    LateSettle,
    /// 2: the lens or driver is too hot; output reduced or off.
    Overtemperature,
    /// 3: the requested current exceeded the limit and was clamped.
    Overcurrent,
    /// 4: a `SetFocalPower`'s `apply_at_us` had passed; the power was applied on receipt.
    LateApply,
}

/// Something went wrong while the device was running.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Fault {
    /// What went wrong.
    pub kind: FaultKind,
    /// Frame counter at the fault (0 outside a schedule).
    pub frame: u32,
    /// Plane index at the fault (0 outside a schedule).
    pub plane_index: u8,
    /// Device time of the fault (for `LateApply`: when the power was applied).
    pub device_time_us: u64,
}

/// One eye's gaze ray in the head frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EyeSample {
    /// Eye position (x, y, z) in millimetres.
    pub origin_mm: [f32; 3],
    /// Unit gaze direction (x, y, z).
    pub direction: [f32; 3],
    /// Pupil diameter in millimetres (NaN without [`Capabilities::PUPIL_SIZE`]).
    pub pupil_mm: f32,
    /// Whether the tracker saw this eye; the other fields are meaningless when false.
    pub valid: bool,
}

/// Both eyes' gaze at one instant.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BinocularSample {
    /// Device time of the exposure.
    pub device_time_us: u64,
    /// Left eye.
    pub left: EyeSample,
    /// Right eye.
    pub right: EyeSample,
}

/// The photodiode input's comparator: levels are fractions of the sensor's full scale, 0 (dark)
/// to 65535 (full scale). The light counts as on once the level rises above
/// `threshold + hysteresis` and as off once it falls below `threshold - hysteresis`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PhotodiodeConfig {
    /// Whether the board reports edges. Enabling (again) restarts the edge counter at 0.
    pub enabled: bool,
    /// Middle of the comparator's band.
    pub threshold: u16,
    /// Half width of the band; keeps a noisy level near the threshold from chattering.
    pub hysteresis: u16,
}

/// Why a [`PhotodiodeConfig`] is unusable. A device replies [`ErrorCode::OutOfRange`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum PhotodiodeConfigError {
    /// The band reaches 0 or full scale, so one of the edges could never happen.
    #[error("threshold {threshold} +/- hysteresis {hysteresis} must lie strictly inside 0..65535")]
    BandOutsideRange {
        /// Threshold given.
        threshold: u16,
        /// Hysteresis given.
        hysteresis: u16,
    },
}

impl PhotodiodeConfig {
    /// Checks that both edges can happen: `hysteresis < threshold` and
    /// `threshold + hysteresis < 65535`. Devices call this on every received config.
    pub fn validate(&self) -> Result<(), PhotodiodeConfigError> {
        let top = u32::from(self.threshold) + u32::from(self.hysteresis);
        if self.hysteresis >= self.threshold || top >= u32::from(u16::MAX) {
            return Err(PhotodiodeConfigError::BandOutsideRange {
                threshold: self.threshold,
                hysteresis: self.hysteresis,
            });
        }
        Ok(())
    }
}

/// The light on the photodiode crossed the comparator's band.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PhotodiodeEdge {
    /// Index of this edge since the input was enabled (the first is 0); wraps. A gap between
    /// consecutive edges means the board dropped edges it could not send.
    pub edge: u32,
    /// Device time of the crossing.
    pub device_time_us: u64,
    /// The light came on (true) or went off (false).
    pub rising: bool,
    /// Sensor level just after the crossing, 0 to 65535 of full scale (a board that only has a
    /// comparator sends 65535 for a rising edge and 0 for a falling one).
    pub level: u16,
}

/// Why a device refused a request. On the wire the numeric code below, as a varint u16.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
#[serde(into = "u16", try_from = "u16")]
#[repr(u16)]
pub enum ErrorCode {
    /// The message discriminant is unknown to the device.
    #[error("unknown message")]
    UnknownMessage = 1,
    /// The frame passed its CRC but its contents did not parse.
    #[error("malformed message")]
    Malformed = 2,
    /// A frame failed its CRC (or its COBS); sent with request id 0.
    #[error("bad CRC")]
    BadCrc = 3,
    /// A frame exceeded the maximum frame size; sent with request id 0.
    #[error("frame too long")]
    FrameTooLong = 4,
    /// The frame or Hello carried a protocol version the device does not speak.
    #[error("unsupported protocol version")]
    UnsupportedVersion = 5,
    /// A value lies outside the device's limits.
    #[error("value out of range")]
    OutOfRange = 6,
    /// The device cannot do this now (e.g. `SetFocalPower` while a schedule runs).
    #[error("device busy")]
    Busy = 7,
    /// The device does not implement this request.
    #[error("not supported by this device")]
    NotSupported = 8,
    /// A `PlaneSchedule` failed [`PlaneSchedule::validate`] or the device's limits.
    #[error("invalid plane schedule")]
    InvalidSchedule = 9,
    /// `Start` before a schedule was loaded.
    #[error("not configured")]
    NotConfigured = 10,
    /// A firmware bug or hardware failure.
    #[error("internal device error")]
    Internal = 11,
}

impl ErrorCode {
    /// Every code, in numeric order.
    pub const ALL: [ErrorCode; 11] = [
        ErrorCode::UnknownMessage,
        ErrorCode::Malformed,
        ErrorCode::BadCrc,
        ErrorCode::FrameTooLong,
        ErrorCode::UnsupportedVersion,
        ErrorCode::OutOfRange,
        ErrorCode::Busy,
        ErrorCode::NotSupported,
        ErrorCode::InvalidSchedule,
        ErrorCode::NotConfigured,
        ErrorCode::Internal,
    ];
}

impl From<ErrorCode> for u16 {
    fn from(code: ErrorCode) -> u16 {
        code as u16
    }
}

/// A numeric error code this build does not know.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown error code {0}")]
pub struct UnknownErrorCode(pub u16);

impl TryFrom<u16> for ErrorCode {
    type Error = UnknownErrorCode;

    fn try_from(raw: u16) -> Result<Self, Self::Error> {
        ErrorCode::ALL
            .into_iter()
            .find(|code| *code as u16 == raw)
            .ok_or(UnknownErrorCode(raw))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_codes_are_contiguous_from_one_and_round_trip() {
        for (i, code) in ErrorCode::ALL.into_iter().enumerate() {
            assert_eq!(u16::from(code), i as u16 + 1);
            assert_eq!(ErrorCode::try_from(u16::from(code)), Ok(code));
        }
        assert_eq!(ErrorCode::try_from(0), Err(UnknownErrorCode(0)));
        assert_eq!(
            ErrorCode::try_from(ErrorCode::ALL.len() as u16 + 1),
            Err(UnknownErrorCode(12))
        );
    }

    #[test]
    fn error_detail_is_truncated_at_a_char_boundary() {
        // 31 ASCII bytes then a 2-byte char: the char would end at byte 33, so it is dropped.
        let text = "0123456789012345678901234567890é and more";
        let Message::Error { detail, .. } = Message::error(ErrorCode::Busy, text) else {
            panic!("Message::error built another variant");
        };
        assert_eq!(detail.as_str(), "0123456789012345678901234567890");
        let short: ErrorDetail = truncated("ok");
        assert_eq!(short.as_str(), "ok");
    }

    #[test]
    fn plane_schedule_new_checks_every_rule() {
        let ok = PlaneSchedule::new(&[0.2, 0.8, 1.4, 2.0], 4_166, 1_500, true).unwrap();
        assert_eq!(ok.plane_powers_d.len(), 4);
        assert_eq!(
            PlaneSchedule::new(&[], 4_166, 0, true),
            Err(ScheduleError::PlaneCount { count: 0 })
        );
        assert_eq!(
            PlaneSchedule::new(&[1.0; MAX_PLANES + 1], 4_166, 0, true),
            Err(ScheduleError::PlaneCount { count: 17 })
        );
        assert!(PlaneSchedule::new(&[1.0; MAX_PLANES], 4_166, 0, true).is_ok());
        assert_eq!(
            PlaneSchedule::new(&[0.5, f32::NAN], 4_166, 0, true),
            Err(ScheduleError::NonFinitePower { index: 1 })
        );
        assert_eq!(
            PlaneSchedule::new(&[f32::INFINITY], 4_166, 0, true),
            Err(ScheduleError::NonFinitePower { index: 0 })
        );
        assert_eq!(
            PlaneSchedule::new(&[0.5], 0, 0, true),
            Err(ScheduleError::ZeroPeriod)
        );
        assert_eq!(
            PlaneSchedule::new(&[0.5], 1_000, 1_000, false),
            Err(ScheduleError::SettleTooLong {
                settle_allowance_us: 1_000,
                subframe_period_us: 1_000
            })
        );
    }

    #[test]
    fn capabilities_combine_and_test_bits() {
        let caps = Capabilities::FOCAL_POWER.with(Capabilities::TIME_SYNC);
        assert!(caps.contains(Capabilities::FOCAL_POWER));
        assert!(caps.contains(Capabilities::TIME_SYNC));
        assert!(!caps.contains(Capabilities::PLANE_SCHEDULE));
        assert!(!caps.contains(Capabilities::FOCAL_POWER.with(Capabilities::PUPIL_SIZE)));
    }
}
