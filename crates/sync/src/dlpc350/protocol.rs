//! The DLPC350's USB HID command protocol: packet layout, multi-report payloads, and one typed
//! request with its typed reply per command. Pure: no I/O, no clock.
//!
//! Sources: TI's DLPC350 programmer's guide (DLPU010) and TI's `dlpc350_api.cpp`, checked
//! against pycrafter4500. A packet is
//!
//! ```text
//! byte 0   flags: bit 7 read, bit 6 reply wanted, bit 5 nack (replies), bits 0-2 destination (0)
//! byte 1   sequence (the reply echoes it)
//! 2-3      length, little-endian: bytes after the header (request: 2 + payload; reply: data)
//! 4-5      request only: command word, low byte (CMD3) first
//! then     payload / reply data
//! ```
//!
//! A packet longer than one 64-byte report continues in further reports that carry only data,
//! with no header (TI's `DLPC350_SendMsg` and pycrafter4500 agree; the NIRscan guide's
//! "sequence numbers the packets" does not apply to the DLPC350 API).
//! Reports here are the 64 bytes after the HID report id (which is always 0).
//!
//! A reply echoes the request's flags (plus the nack bit) and sequence. TI's API checks only
//! the nack bit of a write's reply, and fails a read whose reply has the nack bit or length 0;
//! the driver does the same (the simulator acks writes with no data).

use thiserror::Error;

/// Bytes in one HID report, after the report id.
pub const REPORT_LEN: usize = 64;
/// Flags, sequence and length.
pub const HEADER_LEN: usize = 4;
/// The controller's command buffer (TI `HID_MESSAGE_MAX_SIZE`): the longest packet body.
pub const MAX_BODY_LEN: usize = 512;
/// Pattern LUT capacity (TI `MAX_PAT_LUT_ENTRIES`).
pub const MAX_LUT_ENTRIES: usize = 128;
/// The shortest dark gap between exposure and the end of a pattern period.
pub const MIN_DARK_US: u32 = 230;

pub const FLAG_READ: u8 = 0x80;
pub const FLAG_REPLY: u8 = 0x40;
pub const FLAG_NACK: u8 = 0x20;

/// Why bytes do not form a valid DLPC350 packet or command.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum ProtocolError {
    #[error("report of {0} bytes is too short for a packet header")]
    ShortReport(usize),
    #[error("packet of {0} bytes exceeds the controller's {MAX_BODY_LEN}-byte buffer")]
    TooLong(usize),
    #[error("request of {0} bytes has no command word")]
    NoCommand(usize),
    #[error("{name} ({code:#06x}): {got} payload bytes, expected {expected}")]
    PayloadLength {
        code: u16,
        name: &'static str,
        expected: usize,
        got: usize,
    },
    #[error("{name}: {what}")]
    Field { name: &'static str, what: String },
}

/// One command or reply, reassembled from its reports.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Packet {
    pub flags: u8,
    pub seq: u8,
    /// The command word; requests only.
    pub command: Option<u16>,
    pub data: Vec<u8>,
}

impl Packet {
    /// A request that always asks for a reply, so a refusal comes back as a nack.
    pub fn request(read: bool, seq: u8, command: u16, data: Vec<u8>) -> Packet {
        let flags = FLAG_REPLY | if read { FLAG_READ } else { 0 };
        Packet {
            flags,
            seq,
            command: Some(command),
            data,
        }
    }

    /// The reply to `request`: its flags (plus nack) and sequence.
    pub fn reply_to(request: &Packet, nack: bool, data: Vec<u8>) -> Packet {
        let flags = (request.flags & !FLAG_NACK) | if nack { FLAG_NACK } else { 0 };
        Packet {
            flags,
            seq: request.seq,
            command: None,
            data,
        }
    }

    pub fn is_read(&self) -> bool {
        self.flags & FLAG_READ != 0
    }
    pub fn wants_reply(&self) -> bool {
        self.flags & FLAG_REPLY != 0
    }
    pub fn is_nack(&self) -> bool {
        self.flags & FLAG_NACK != 0
    }

    /// The bytes after the header: command word (requests) and data.
    fn body(&self) -> Vec<u8> {
        let mut body = Vec::with_capacity(self.data.len() + 2);
        if let Some(c) = self.command {
            body.extend_from_slice(&c.to_le_bytes());
        }
        body.extend_from_slice(&self.data);
        body
    }

    /// Splits the packet into 64-byte reports, zero-padded.
    pub fn to_reports(&self) -> Result<Vec<[u8; REPORT_LEN]>, ProtocolError> {
        let body = self.body();
        if body.len() > MAX_BODY_LEN {
            return Err(ProtocolError::TooLong(body.len()));
        }
        let len = body.len() as u16;
        let mut first = [0u8; REPORT_LEN];
        first[0] = self.flags;
        first[1] = self.seq;
        first[2..4].copy_from_slice(&len.to_le_bytes());
        let head = body.len().min(REPORT_LEN - HEADER_LEN);
        first[HEADER_LEN..HEADER_LEN + head].copy_from_slice(&body[..head]);
        let mut reports = vec![first];
        for chunk in body[head..].chunks(REPORT_LEN) {
            let mut r = [0u8; REPORT_LEN];
            r[..chunk.len()].copy_from_slice(chunk);
            reports.push(r);
        }
        Ok(reports)
    }
}

/// Which way the packets being reassembled go: requests carry a command word.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    Request,
    Reply,
}

/// Reassembles packets from reports, one packet at a time.
#[derive(Debug, Clone)]
pub struct Assembler {
    direction: Direction,
    pending: Option<(u8, u8, usize, Vec<u8>)>,
}

impl Assembler {
    pub fn new(direction: Direction) -> Self {
        Assembler {
            direction,
            pending: None,
        }
    }

    /// True while a multi-report packet is incomplete.
    pub fn in_progress(&self) -> bool {
        self.pending.is_some()
    }

    pub fn reset(&mut self) {
        self.pending = None;
    }

    /// Takes one report; returns a packet once its last report arrived. A bad header drops
    /// the report.
    pub fn push(&mut self, report: &[u8]) -> Result<Option<Packet>, ProtocolError> {
        let report = &report[..report.len().min(REPORT_LEN)];
        let (flags, seq, len, body) = match self.pending.take() {
            Some((flags, seq, len, mut body)) => {
                let take = (len - body.len()).min(report.len());
                body.extend_from_slice(&report[..take]);
                (flags, seq, len, body)
            }
            None => {
                if report.len() < HEADER_LEN {
                    return Err(ProtocolError::ShortReport(report.len()));
                }
                let len = usize::from(u16::from_le_bytes([report[2], report[3]]));
                if len > MAX_BODY_LEN {
                    return Err(ProtocolError::TooLong(len));
                }
                if self.direction == Direction::Request && len < 2 {
                    return Err(ProtocolError::NoCommand(len));
                }
                let take = len.min(report.len() - HEADER_LEN);
                let body = report[HEADER_LEN..HEADER_LEN + take].to_vec();
                (report[0], report[1], len, body)
            }
        };
        if body.len() < len {
            self.pending = Some((flags, seq, len, body));
            return Ok(None);
        }
        let (command, data) = match self.direction {
            Direction::Request => (
                Some(u16::from_le_bytes([body[0], body[1]])),
                body[2..].to_vec(),
            ),
            Direction::Reply => (None, body),
        };
        Ok(Some(Packet {
            flags,
            seq,
            command,
            data,
        }))
    }
}

/// One DLPC350 command: its code, direction, payload layout and reply layout. Both the driver
/// and the simulator use these, so the two sides cannot disagree on a byte.
pub trait Command: Sized {
    /// CMD2 << 8 | CMD3.
    const CODE: u16;
    const NAME: &'static str;
    /// Read commands set flag bit 7 and get data back; writes get an empty ack.
    const READ: bool;
    type Reply;
    fn encode(&self) -> Vec<u8>;
    fn decode(payload: &[u8]) -> Result<Self, ProtocolError>;
    fn encode_reply(reply: &Self::Reply) -> Vec<u8>;
    fn decode_reply(data: &[u8]) -> Result<Self::Reply, ProtocolError>;
}

fn exact<const N: usize>(
    code: u16,
    name: &'static str,
    payload: &[u8],
) -> Result<[u8; N], ProtocolError> {
    payload
        .try_into()
        .map_err(|_| ProtocolError::PayloadLength {
            code,
            name,
            expected: N,
            got: payload.len(),
        })
}

fn field(name: &'static str, what: impl Into<String>) -> ProtocolError {
    ProtocolError::Field {
        name,
        what: what.into(),
    }
}

fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]])
}

/// A write command whose payload is one enumerated byte.
macro_rules! byte_enum_command {
    ($(#[$m:meta])* $cmd:ident, $code:literal, $name:literal, $ty:ident { $($(#[$vm:meta])* $variant:ident = $value:literal),+ $(,)? }) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        pub enum $ty {
            $($(#[$vm])* $variant = $value),+
        }
        impl $ty {
            pub fn from_byte(b: u8) -> Option<Self> {
                match b {
                    $($value => Some($ty::$variant),)+
                    _ => None,
                }
            }
        }
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        pub struct $cmd(pub $ty);
        impl Command for $cmd {
            const CODE: u16 = $code;
            const NAME: &'static str = $name;
            const READ: bool = false;
            type Reply = ();
            fn encode(&self) -> Vec<u8> {
                vec![self.0 as u8]
            }
            fn decode(payload: &[u8]) -> Result<Self, ProtocolError> {
                let [b] = exact::<1>($code, $name, payload)?;
                $ty::from_byte(b)
                    .map($cmd)
                    .ok_or_else(|| field($name, format!("value {b} is not defined")))
            }
            fn encode_reply(_: &()) -> Vec<u8> {
                Vec::new()
            }
            fn decode_reply(_: &[u8]) -> Result<(), ProtocolError> {
                Ok(())
            }
        }
    };
}

/// A read command without payload whose reply is one status byte.
macro_rules! status_read {
    ($(#[$m:meta])* $cmd:ident, $code:literal, $name:literal, $reply:ident) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        pub struct $cmd;
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        pub struct $reply(pub u8);
        impl Command for $cmd {
            const CODE: u16 = $code;
            const NAME: &'static str = $name;
            const READ: bool = true;
            type Reply = $reply;
            fn encode(&self) -> Vec<u8> {
                Vec::new()
            }
            fn decode(payload: &[u8]) -> Result<Self, ProtocolError> {
                exact::<0>($code, $name, payload).map(|_| $cmd)
            }
            fn encode_reply(r: &$reply) -> Vec<u8> {
                vec![r.0]
            }
            fn decode_reply(data: &[u8]) -> Result<$reply, ProtocolError> {
                // Some firmware pads replies; the status is the first byte.
                data.first()
                    .map(|b| $reply(*b))
                    .ok_or_else(|| field($name, "empty reply"))
            }
        }
    };
}

byte_enum_command!(
    /// 0x1A1B: video mode (image processing on) or pattern mode (bypassed).
    SetDisplayMode, 0x1A1B, "display mode", DisplayMode { Video = 0, Pattern = 1 }
);
byte_enum_command!(
    /// 0x1A22: where pattern data comes from.
    SetPatternSource, 0x1A22, "pattern input source", PatternSource {
        /// Streamed over the parallel RGB / FPD-link port (24 bits per video frame).
        VideoPort = 0,
        /// Images stored in the controller's flash.
        Flash = 3,
    }
);
byte_enum_command!(
    /// 0x1A23: what advances the pattern sequence.
    SetTriggerMode, 0x1A23, "pattern trigger mode", TriggerMode {
        /// Mode 0: the video port's VSYNC starts each frame's patterns.
        Vsync = 0,
        /// Mode 1: internal timer or TRIG_IN_1/2.
        InternalOrExternal = 1,
        /// Mode 2: TRIG_IN_1 alternates two patterns, TRIG_IN_2 advances the pair.
        TrigInPairs = 2,
        /// Mode 3: internal or external trigger, variable exposure.
        VariableExposure = 3,
        /// Mode 4: VSYNC, variable exposure.
        VsyncVariableExposure = 4,
    }
);
byte_enum_command!(
    /// 0x1A24: start, pause or stop the pattern sequence.
    PatternDisplay, 0x1A24, "pattern start/stop", SequenceAction {
        /// The next start begins from the first pattern.
        Stop = 0,
        /// The next start re-shows the current pattern.
        Pause = 1,
        Start = 2,
    }
);
byte_enum_command!(
    /// 0x1A33: opens one mailbox (or closes them all) for 0x1A32 / 0x1A34.
    MailboxControl, 0x1A33, "mailbox control", Mailbox {
        Closed = 0,
        ImageIndex = 1,
        PatternLut = 2,
        VariableExposure = 3,
    }
);

status_read!(
    /// 0x1A0A: hardware status.
    GetHardwareStatus, 0x1A0A, "hardware status", HardwareStatus
);
status_read!(
    /// 0x1A0B: system status (internal memory test).
    GetSystemStatus, 0x1A0B, "system status", SystemStatus
);
status_read!(
    /// 0x1A0C: main status.
    GetMainStatus, 0x1A0C, "main status", MainStatus
);
status_read!(
    /// 0x1A1A read: result of the last LUT validation.
    GetValidation, 0x1A1A, "LUT validation status", ValidationStatus
);

/// A read command without payload whose reply's first byte is one of an enum's values.
macro_rules! enum_read {
    ($(#[$m:meta])* $cmd:ident, $code:literal, $name:literal, $ty:ident) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        pub struct $cmd;
        impl Command for $cmd {
            const CODE: u16 = $code;
            const NAME: &'static str = $name;
            const READ: bool = true;
            type Reply = $ty;
            fn encode(&self) -> Vec<u8> {
                Vec::new()
            }
            fn decode(payload: &[u8]) -> Result<Self, ProtocolError> {
                exact::<0>($code, $name, payload).map(|_| $cmd)
            }
            fn encode_reply(r: &$ty) -> Vec<u8> {
                vec![*r as u8]
            }
            fn decode_reply(data: &[u8]) -> Result<$ty, ProtocolError> {
                let b = *data.first().ok_or_else(|| field($name, "empty reply"))?;
                $ty::from_byte(b).ok_or_else(|| field($name, format!("value {b} is not defined")))
            }
        }
    };
}

enum_read!(
    /// 0x1A1B read: the display mode. TI's `DLPC350_GetMode` reads any non-zero byte as
    /// pattern mode; this reads 0 and 1 and refuses the rest.
    GetDisplayMode, 0x1A1B, "display mode read", DisplayMode
);
enum_read!(
    /// 0x1A24 read: whether the pattern sequence is stopped, paused or running (TI's
    /// `DLPC350_GetPatternDisplay`).
    GetPatternDisplay, 0x1A24, "pattern display read", SequenceAction
);

impl HardwareStatus {
    /// Bit 1: incompatible controller or DMD (hardware.md; DLPC900 clients name the same bit so,
    /// and two DLPC350 C++ wrappers leave it "reserved", so a set bit is never normal).
    pub const INCOMPATIBLE: u8 = 0x02;
    /// Bit 0 set means initialisation succeeded.
    pub fn init_ok(self) -> bool {
        self.0 & 0x01 != 0
    }
    pub fn incompatible(self) -> bool {
        self.0 & Self::INCOMPATIBLE != 0
    }
    /// What stops the controller from being programmed at all, in words.
    pub fn fatal_problems(self) -> Vec<&'static str> {
        let mut v = Vec::new();
        if !self.init_ok() {
            v.push("internal initialisation failed");
        }
        if self.incompatible() {
            v.push("incompatible controller or DMD (or wrong firmware)");
        }
        v
    }
    pub fn drc_error(self) -> bool {
        self.0 & 0x04 != 0
    }
    pub fn forced_swap_error(self) -> bool {
        self.0 & 0x08 != 0
    }
    pub fn sequence_abort(self) -> bool {
        self.0 & 0x40 != 0
    }
    pub fn sequence_error(self) -> bool {
        self.0 & 0x80 != 0
    }
}

impl SystemStatus {
    pub fn memory_test_ok(self) -> bool {
        self.0 & 0x01 != 0
    }
}

impl MainStatus {
    pub const DMD_PARKED: u8 = 0x01;
    pub const SEQUENCER_RUNNING: u8 = 0x02;
    pub const BUFFER_FROZEN: u8 = 0x04;
    pub const GAMMA_ENABLED: u8 = 0x08;
    pub fn dmd_parked(self) -> bool {
        self.0 & Self::DMD_PARKED != 0
    }
    pub fn sequencer_running(self) -> bool {
        self.0 & Self::SEQUENCER_RUNNING != 0
    }
    pub fn buffer_frozen(self) -> bool {
        self.0 & Self::BUFFER_FROZEN != 0
    }
}

impl ValidationStatus {
    pub const EXPOSURE_OR_PERIOD_INVALID: u8 = 0x01;
    pub const PATTERN_NUMBER_INVALID: u8 = 0x02;
    pub const TRIG_OUT1_WARNING: u8 = 0x04;
    /// Bit 3. TI's SDK (lcr4500.cpp): "black vector missing when exposure less than frame
    /// period"; TI's API (dlpc350_api.cpp): "post vector was not inserted prior to external
    /// triggered vector". Both hold: its fill rule (insert black in both cases) is what
    /// [`super::sequence`] follows.
    pub const BLACK_VECTOR_MISSING: u8 = 0x08;
    pub const DARK_GAP_TOO_SHORT: u8 = 0x10;
    pub const BUSY: u8 = 0x80;
    /// Still validating: poll again.
    pub fn busy(self) -> bool {
        self.0 & Self::BUSY != 0
    }
    pub fn ok(self) -> bool {
        self.0 & 0x1f == 0
    }
    /// The failed checks, in words.
    pub fn problems(self) -> Vec<&'static str> {
        [
            (
                Self::EXPOSURE_OR_PERIOD_INVALID,
                "exposure or frame period invalid",
            ),
            (
                Self::PATTERN_NUMBER_INVALID,
                "pattern numbers in the LUT invalid",
            ),
            (
                Self::TRIG_OUT1_WARNING,
                "TRIG_OUT1 continuous or overlapping black sectors",
            ),
            (
                Self::BLACK_VECTOR_MISSING,
                "black vector missing when exposure is less than the period, or before an \
                 externally triggered pattern",
            ),
            (
                Self::DARK_GAP_TOO_SHORT,
                "exposure differs from the period by less than 230 us",
            ),
        ]
        .iter()
        .filter(|(bit, _)| self.0 & bit != 0)
        .map(|(_, text)| *text)
        .collect()
    }
}

/// 0x1A1A write: starts validating the pattern configuration; poll [`GetValidation`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StartValidation;

impl Command for StartValidation {
    const CODE: u16 = 0x1A1A;
    const NAME: &'static str = "LUT validate";
    const READ: bool = false;
    type Reply = ();
    fn encode(&self) -> Vec<u8> {
        // TI's API declares one payload byte and pycrafter4500 sends 0.
        vec![0]
    }
    fn decode(payload: &[u8]) -> Result<Self, ProtocolError> {
        exact::<1>(Self::CODE, Self::NAME, payload).map(|_| StartValidation)
    }
    fn encode_reply(_: &()) -> Vec<u8> {
        Vec::new()
    }
    fn decode_reply(_: &[u8]) -> Result<(), ProtocolError> {
        Ok(())
    }
}

/// 0x0200: standby (true) or normal operation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SetPowerMode {
    pub standby: bool,
}

/// 0x1A32: offset in the open mailbox, 0..=127.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SetMailboxAddress(pub u8);

/// 0x1A36: TRIG_IN_2 edge that advances patterns in trigger mode 2.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SetTrigIn2 {
    pub falling: bool,
}

/// Writes with a fixed-size payload and an empty ack.
macro_rules! fixed_write {
    ($cmd:ident, $code:literal, $name:literal, $n:literal, |$s:ident| $enc:expr, |$b:ident| $dec:expr) => {
        impl Command for $cmd {
            const CODE: u16 = $code;
            const NAME: &'static str = $name;
            const READ: bool = false;
            type Reply = ();
            fn encode(&self) -> Vec<u8> {
                let $s = self;
                $enc
            }
            fn decode(payload: &[u8]) -> Result<Self, ProtocolError> {
                let $b = exact::<$n>($code, $name, payload)?;
                $dec
            }
            fn encode_reply(_: &()) -> Vec<u8> {
                Vec::new()
            }
            fn decode_reply(_: &[u8]) -> Result<(), ProtocolError> {
                Ok(())
            }
        }
    };
}

fn flag_byte(name: &'static str, b: u8) -> Result<bool, ProtocolError> {
    match b {
        0 => Ok(false),
        1 => Ok(true),
        _ => Err(field(name, format!("flag byte {b} is neither 0 nor 1"))),
    }
}

fixed_write!(
    SetPowerMode,
    0x0200,
    "power control",
    1,
    |s| vec![u8::from(s.standby)],
    |b| Ok(SetPowerMode {
        standby: flag_byte("power control", b[0])?
    })
);
fixed_write!(
    SetMailboxAddress,
    0x1A32,
    "mailbox address",
    1,
    |s| vec![s.0],
    |b| if b[0] <= 127 {
        Ok(SetMailboxAddress(b[0]))
    } else {
        Err(field("mailbox address", format!("{} is over 127", b[0])))
    }
);
fixed_write!(
    SetTrigIn2,
    0x1A36,
    "TRIG_IN_2 control",
    1,
    |s| vec![u8::from(s.falling)],
    |b| Ok(SetTrigIn2 {
        falling: flag_byte("TRIG_IN_2 control", b[0])?
    })
);

/// 0x1A29: pattern exposure and pattern period, microseconds. The exposure equals the period
/// or is at least [`MIN_DARK_US`] shorter (see [`exposure_fits_period`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SetExposure {
    pub exposure_us: u32,
    pub period_us: u32,
}

// Exposure first, then period: TI's API and pycrafter4500 agree.
fixed_write!(
    SetExposure,
    0x1A29,
    "exposure and frame period",
    8,
    |s| {
        let mut v = s.exposure_us.to_le_bytes().to_vec();
        v.extend_from_slice(&s.period_us.to_le_bytes());
        v
    },
    |b| Ok(SetExposure {
        exposure_us: u32_at(&b, 0),
        period_us: u32_at(&b, 4)
    })
);

/// 0x1A31: how the pattern LUT runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SetPatternConfig {
    /// Entries used, 1..=128.
    pub lut_entries: u8,
    /// Repeat the sequence (true) or run it once.
    pub repeat: bool,
    /// TRIG_OUT_2 fires once every this many patterns, 1..=256: the start of a lens sweep.
    pub trig_out2_every: u16,
    /// Image-index LUT entries, 1..=64 (flash source only).
    pub images: u8,
}

// Counts go on the wire minus one. TI's API subtracts one from the image count too;
// pycrafter4500 sends it unchanged. We follow TI (it only matters for the flash source).
// Byte 1 is 1 to repeat (TI); pycrafter4500's docstring says the opposite, its code agrees
// with TI.
fixed_write!(
    SetPatternConfig,
    0x1A31,
    "pattern config",
    4,
    |s| vec![
        s.lut_entries.saturating_sub(1) & 0x7f,
        u8::from(s.repeat),
        u8::try_from(s.trig_out2_every.saturating_sub(1)).unwrap_or(u8::MAX),
        s.images.saturating_sub(1) & 0x3f,
    ],
    |b| Ok(SetPatternConfig {
        lut_entries: (b[0] & 0x7f) + 1,
        repeat: flag_byte("pattern config", b[1])?,
        trig_out2_every: u16::from(b[2]) + 1,
        images: (b[3] & 0x3f) + 1,
    })
);

/// 0x1A1D: TRIG_OUT_1 polarity and edge delays (each step 107.2 ns; 0xBB is no delay).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SetTrigOut1 {
    pub invert: bool,
    pub rising_delay: u8,
    pub falling_delay: u8,
}

/// 0x1A1E: TRIG_OUT_2 polarity and rising-edge delay.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SetTrigOut2 {
    pub invert: bool,
    pub rising_delay: u8,
}

/// The trigger-out delay code for no delay.
pub const TRIG_DELAY_ZERO: u8 = 0xBB;

fixed_write!(
    SetTrigOut1,
    0x1A1D,
    "TRIG_OUT_1 control",
    3,
    |s| vec![u8::from(s.invert), s.rising_delay, s.falling_delay],
    |b| Ok(SetTrigOut1 {
        invert: flag_byte("TRIG_OUT_1 control", b[0])?,
        rising_delay: b[1],
        falling_delay: b[2]
    })
);
fixed_write!(
    SetTrigOut2,
    0x1A1E,
    "TRIG_OUT_2 control",
    2,
    |s| vec![u8::from(s.invert), s.rising_delay],
    |b| Ok(SetTrigOut2 {
        invert: flag_byte("TRIG_OUT_2 control", b[0])?,
        rising_delay: b[1]
    })
);

/// 0x1A35: TRIG_IN_1 delay in 107.2 ns steps; 19 bits are used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SetTrigIn1Delay(pub u32);

fixed_write!(
    SetTrigIn1Delay,
    0x1A35,
    "TRIG_IN_1 delay",
    4,
    |s| (s.0 & 0x7_ffff).to_le_bytes().to_vec(),
    |b| Ok(SetTrigIn1Delay(u32_at(&b, 0) & 0x7_ffff))
);

/// What starts a LUT entry's pattern.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TriggerType {
    Internal = 0,
    ExternalPositive = 1,
    ExternalNegative = 2,
    /// No trigger: continue from the previous pattern.
    Continue = 3,
}

/// One pattern LUT entry (3 bytes on the wire).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LutEntry {
    pub trigger: TriggerType,
    /// Pattern number within the 24-bit image, 0..=63 on the wire (see [`patterns_per_image`]).
    pub pattern: u8,
    /// 1..=8 bits; 0 and 9..=15 are reserved and fail validation.
    pub bit_depth: u8,
    /// LED enables: bit 0 red, 1 green, 2 blue.
    pub leds: u8,
    pub invert: bool,
    pub insert_black: bool,
    pub buffer_swap: bool,
    /// TRIG_OUT_1 stays high from the previous pattern.
    pub trig_out_prev: bool,
}

impl LutEntry {
    pub fn to_bytes(self) -> [u8; 3] {
        [
            (self.trigger as u8) | (self.pattern & 0x3f) << 2,
            (self.bit_depth & 0x0f) | (self.leds & 0x0f) << 4,
            u8::from(self.invert)
                | u8::from(self.insert_black) << 1
                | u8::from(self.buffer_swap) << 2
                | u8::from(self.trig_out_prev) << 3,
        ]
    }
    pub fn from_bytes(b: [u8; 3]) -> LutEntry {
        LutEntry {
            trigger: match b[0] & 0x03 {
                0 => TriggerType::Internal,
                1 => TriggerType::ExternalPositive,
                2 => TriggerType::ExternalNegative,
                _ => TriggerType::Continue,
            },
            pattern: b[0] >> 2,
            bit_depth: b[1] & 0x0f,
            leds: b[1] >> 4,
            invert: b[2] & 0x01 != 0,
            insert_black: b[2] & 0x02 != 0,
            buffer_swap: b[2] & 0x04 != 0,
            trig_out_prev: b[2] & 0x08 != 0,
        }
    }
}

fn lut_from_bytes(name: &'static str, data: &[u8]) -> Result<Vec<LutEntry>, ProtocolError> {
    if data.len() % 3 != 0 || data.len() / 3 > MAX_LUT_ENTRIES {
        return Err(field(
            name,
            format!(
                "{} bytes is not 1 to {MAX_LUT_ENTRIES} 3-byte LUT entries",
                data.len()
            ),
        ));
    }
    Ok(data
        .chunks_exact(3)
        .map(|c| LutEntry::from_bytes([c[0], c[1], c[2]]))
        .collect())
}

fn lut_to_bytes(entries: &[LutEntry]) -> Vec<u8> {
    entries.iter().flat_map(|e| e.to_bytes()).collect()
}

/// 0x1A34 write: LUT entries into the open mailbox from the mailbox address on. 20 or more
/// entries span several reports.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WriteMailbox(pub Vec<LutEntry>);

impl Command for WriteMailbox {
    const CODE: u16 = 0x1A34;
    const NAME: &'static str = "mailbox data";
    const READ: bool = false;
    type Reply = ();
    fn encode(&self) -> Vec<u8> {
        lut_to_bytes(&self.0)
    }
    fn decode(payload: &[u8]) -> Result<Self, ProtocolError> {
        if payload.is_empty() {
            return Err(field(Self::NAME, "no entries"));
        }
        lut_from_bytes(Self::NAME, payload).map(WriteMailbox)
    }
    fn encode_reply(_: &()) -> Vec<u8> {
        Vec::new()
    }
    fn decode_reply(_: &[u8]) -> Result<(), ProtocolError> {
        Ok(())
    }
}

/// 0x1A34 read: the open mailbox's entries from the mailbox address to the configured count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadMailbox;

impl Command for ReadMailbox {
    const CODE: u16 = 0x1A34;
    const NAME: &'static str = "mailbox data read";
    const READ: bool = true;
    type Reply = Vec<LutEntry>;
    fn encode(&self) -> Vec<u8> {
        Vec::new()
    }
    fn decode(payload: &[u8]) -> Result<Self, ProtocolError> {
        exact::<0>(Self::CODE, Self::NAME, payload).map(|_| ReadMailbox)
    }
    fn encode_reply(r: &Vec<LutEntry>) -> Vec<u8> {
        lut_to_bytes(r)
    }
    /// Every whole entry the controller sends, up to [`MAX_LUT_ENTRIES`]: the reply may run
    /// past the entries in use (TI's `DLPC350_GetPatLut` reads the first `numEntries * 3`
    /// bytes and ignores the rest), so the caller compares the prefix it wrote.
    fn decode_reply(data: &[u8]) -> Result<Vec<LutEntry>, ProtocolError> {
        let whole = data.len() / 3 * 3;
        let entries = &data[..whole.min(3 * MAX_LUT_ENTRIES)];
        lut_from_bytes(Self::NAME, entries)
    }
}

/// A firmware component's version.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ComponentVersion {
    pub major: u8,
    pub minor: u8,
    pub patch: u16,
}

impl ComponentVersion {
    fn from_word(w: u32) -> Self {
        ComponentVersion {
            major: (w >> 24) as u8,
            minor: (w >> 16) as u8,
            patch: w as u16,
        }
    }
    fn to_word(self) -> u32 {
        u32::from(self.major) << 24 | u32::from(self.minor) << 16 | u32::from(self.patch)
    }
}

impl std::fmt::Display for ComponentVersion {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}.{}.{}", self.major, self.minor, self.patch)
    }
}

/// Reply to [`GetVersion`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Version {
    pub application: ComponentVersion,
    pub api: ComponentVersion,
    pub software_config: ComponentVersion,
    pub sequence_config: ComponentVersion,
}

/// 0x0205 read: firmware component versions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GetVersion;

impl Command for GetVersion {
    const CODE: u16 = 0x0205;
    const NAME: &'static str = "version";
    const READ: bool = true;
    type Reply = Version;
    fn encode(&self) -> Vec<u8> {
        Vec::new()
    }
    fn decode(payload: &[u8]) -> Result<Self, ProtocolError> {
        exact::<0>(Self::CODE, Self::NAME, payload).map(|_| GetVersion)
    }
    fn encode_reply(v: &Version) -> Vec<u8> {
        [v.application, v.api, v.software_config, v.sequence_config]
            .iter()
            .flat_map(|c| c.to_word().to_le_bytes())
            .collect()
    }
    fn decode_reply(data: &[u8]) -> Result<Version, ProtocolError> {
        if data.len() < 16 {
            return Err(field(
                Self::NAME,
                format!("{} bytes, expected 16", data.len()),
            ));
        }
        let c = |i| ComponentVersion::from_word(u32_at(data, i));
        Ok(Version {
            application: c(0),
            api: c(4),
            software_config: c(8),
            sequence_config: c(12),
        })
    }
}

/// Patterns of `bit_depth` bits in one 24-bit image (programmer's guide, pattern-number table):
/// 24 one-bit, 12 two-bit, 8 three-bit, 6 four-bit, 4 five- or six-bit, 3 seven- or eight-bit.
/// 0 for a reserved depth.
pub fn patterns_per_image(bit_depth: u8) -> u8 {
    match bit_depth {
        1..=8 => 24 / bit_depth,
        _ => 0,
    }
}

/// Shortest exposure per bit depth 1..=8, µs, from the programmer's guide's pattern-exposure
/// table as we read it (no second source found: the simulator enforces it, so a rig that
/// disagrees shows up as a validation error there, not on hardware).
const MIN_EXPOSURE_US: [u32; 8] = [235, 700, 1570, 1700, 2000, 2500, 4500, 8333];

/// Shortest exposure for `bit_depth`; `None` for a reserved depth.
pub fn min_exposure_us(bit_depth: u8) -> Option<u32> {
    MIN_EXPOSURE_US
        .get(usize::from(bit_depth).checked_sub(1)?)
        .copied()
}

/// The controller's exposure rule: equal to the period, or at least [`MIN_DARK_US`] shorter.
pub fn exposure_fits_period(exposure_us: u32, period_us: u32) -> bool {
    exposure_us > 0
        && (exposure_us == period_us || exposure_us.saturating_add(MIN_DARK_US) <= period_us)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip<C: Command + PartialEq + std::fmt::Debug>(c: C) {
        let bytes = c.encode();
        assert_eq!(C::decode(&bytes).unwrap(), c);
    }

    #[test]
    fn request_layout_matches_the_programmers_guide() {
        // Exposure 4166 us, period 4166 us, sequence 7: flags 0x40, length 10, CMD3 0x29 first.
        let cmd = SetExposure {
            exposure_us: 4166,
            period_us: 4166,
        };
        let p = Packet::request(false, 7, SetExposure::CODE, cmd.encode());
        let reports = p.to_reports().unwrap();
        assert_eq!(reports.len(), 1);
        assert_eq!(
            &reports[0][..14],
            &[0x40, 7, 10, 0, 0x29, 0x1a, 0x46, 0x10, 0, 0, 0x46, 0x10, 0, 0]
        );
        assert!(reports[0][14..].iter().all(|b| *b == 0));
        // A read: flags 0xC0, length 2.
        let r = Packet::request(true, 1, GetMainStatus::CODE, vec![]);
        assert_eq!(
            &r.to_reports().unwrap()[0][..6],
            &[0xc0, 1, 2, 0, 0x0c, 0x1a]
        );
    }

    #[test]
    fn lut_entry_bits() {
        let e = LutEntry {
            trigger: TriggerType::ExternalPositive,
            pattern: 3,
            bit_depth: 6,
            leds: 0b111,
            invert: false,
            insert_black: true,
            buffer_swap: true,
            trig_out_prev: false,
        };
        assert_eq!(e.to_bytes(), [0x0d, 0x76, 0x06]);
        assert_eq!(LutEntry::from_bytes(e.to_bytes()), e);
    }

    #[test]
    fn pattern_config_counts_are_sent_minus_one() {
        let c = SetPatternConfig {
            lut_entries: 4,
            repeat: true,
            trig_out2_every: 4,
            images: 1,
        };
        assert_eq!(c.encode(), vec![3, 1, 3, 0]);
        round_trip(c);
        round_trip(SetPatternConfig {
            lut_entries: 128,
            repeat: false,
            trig_out2_every: 256,
            images: 64,
        });
    }

    #[test]
    fn multi_report_payloads_split_and_reassemble() {
        // 40 entries = 120 payload bytes + 2 command bytes: reports of 60 + 62.
        let entries: Vec<LutEntry> = (0..40)
            .map(|i| LutEntry::from_bytes([i as u8 * 4, 0x71, 0]))
            .collect();
        let p = Packet::request(
            false,
            3,
            WriteMailbox::CODE,
            WriteMailbox(entries.clone()).encode(),
        );
        let reports = p.to_reports().unwrap();
        assert_eq!(reports.len(), 2);
        assert_eq!(u16::from_le_bytes([reports[0][2], reports[0][3]]), 122);
        // The continuation carries data only, no header: entry 19 straddles the two reports.
        assert_eq!(&reports[0][62..], &[0, 19 * 4]);
        assert_eq!(&reports[1][..3], &[0x71, 0, 20 * 4]);
        let mut asm = Assembler::new(Direction::Request);
        assert_eq!(asm.push(&reports[0]).unwrap(), None);
        assert!(asm.in_progress());
        let got = asm.push(&reports[1]).unwrap().unwrap();
        assert_eq!(got.command, Some(0x1A34));
        assert_eq!(WriteMailbox::decode(&got.data).unwrap().0, entries);
        // Replies carry no command word and may span reports too.
        let reply = Packet::reply_to(&got, false, lut_to_bytes(&entries));
        let mut asm = Assembler::new(Direction::Reply);
        let mut out = None;
        for r in reply.to_reports().unwrap() {
            out = asm.push(&r).unwrap();
        }
        let out = out.unwrap();
        assert_eq!(out.seq, 3);
        assert_eq!(ReadMailbox::decode_reply(&out.data).unwrap(), entries);
    }

    #[test]
    fn bad_packets_are_errors_not_panics() {
        let mut asm = Assembler::new(Direction::Request);
        assert_eq!(asm.push(&[0x40, 0]), Err(ProtocolError::ShortReport(2)));
        assert_eq!(asm.push(&[0x40, 0, 1, 0]), Err(ProtocolError::NoCommand(1)));
        assert_eq!(
            asm.push(&[0x40, 0, 0xff, 0xff]),
            Err(ProtocolError::TooLong(65535))
        );
        assert!(SetExposure::decode(&[1, 2, 3]).is_err());
        assert!(SetDisplayMode::decode(&[7]).is_err());
        assert!(SetMailboxAddress::decode(&[200]).is_err());
        assert!(WriteMailbox::decode(&[1, 2]).is_err());
        assert!(GetVersion::decode_reply(&[0; 5]).is_err());
        let too_long = Packet::request(false, 0, 0x1A34, vec![0; 600]);
        assert_eq!(too_long.to_reports(), Err(ProtocolError::TooLong(602)));
    }

    #[test]
    fn exposure_rule_and_depth_tables() {
        assert!(exposure_fits_period(4166, 4166));
        assert!(exposure_fits_period(3936, 4166));
        assert!(!exposure_fits_period(4000, 4166));
        assert!(!exposure_fits_period(5000, 4166));
        assert!(!exposure_fits_period(0, 0));
        assert_eq!(
            (1..=8).map(patterns_per_image).collect::<Vec<_>>(),
            vec![24, 12, 8, 6, 4, 4, 3, 3]
        );
        assert_eq!(patterns_per_image(0), 0);
        assert_eq!(min_exposure_us(6), Some(2500));
        assert_eq!(min_exposure_us(0), None);
        assert_eq!(min_exposure_us(9), None);
    }

    #[test]
    fn version_words() {
        let v = Version {
            application: ComponentVersion {
                major: 3,
                minor: 0,
                patch: 0,
            },
            api: ComponentVersion {
                major: 2,
                minor: 1,
                patch: 7,
            },
            ..Default::default()
        };
        let bytes = GetVersion::encode_reply(&v);
        assert_eq!(&bytes[..4], &[0, 0, 0, 3]);
        assert_eq!(GetVersion::decode_reply(&bytes).unwrap(), v);
        assert_eq!(v.api.to_string(), "2.1.7");
    }

    proptest::proptest! {
        /// Any packet up to the buffer size survives splitting into reports and reassembly.
        #[test]
        fn packets_round_trip(
            read: bool,
            seq: u8,
            command: u16,
            data in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..=510),
        ) {
            let p = Packet::request(read, seq, command, data);
            let mut asm = Assembler::new(Direction::Request);
            let mut out = None;
            for r in p.to_reports().unwrap() {
                proptest::prop_assert!(out.is_none());
                out = asm.push(&r).unwrap();
            }
            proptest::prop_assert_eq!(out, Some(p));
        }

        /// Arbitrary reports never panic either side, and every decoder takes any payload.
        #[test]
        fn garbage_never_panics(reports in proptest::collection::vec(
            proptest::collection::vec(proptest::prelude::any::<u8>(), 0..70), 0..8)) {
            let mut req = Assembler::new(Direction::Request);
            let mut rep = Assembler::new(Direction::Reply);
            for r in &reports {
                let _ = req.push(r);
                let _ = rep.push(r);
                let _ = SetExposure::decode(r);
                let _ = SetPatternConfig::decode(r);
                let _ = WriteMailbox::decode(r);
                let _ = ReadMailbox::decode_reply(r);
                let _ = GetVersion::decode_reply(r);
                let _ = GetValidation::decode_reply(r);
            }
        }
    }
}
