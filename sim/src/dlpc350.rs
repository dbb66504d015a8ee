//! A simulated TI DLPC350 (LightCrafter 4500) on the in-memory HID link: the controller's
//! side of the 64-byte USB HID reports, its validation rules and nacks, and a pattern
//! sequencer that emits pattern and trigger-out events on tokio's clock.
//!
//! Its decoding is its own, written from TI's documentation and code (the DLPC350
//! programmer's guide as TI's `dlpc350_api.cpp` implements it: command codes and payload
//! lengths from its `CmdList`, the packet header from `hidMessageStruct`; TI's SDK
//! `lcr4500.cpp` and pycrafter4500 for the LUT entry and exposure layouts), not from the
//! driver, so a layout slip in the driver fails a test here instead of being mirrored.
//!
//! Rules enforced (a nack, as the controller sends for an invalid command): configuration
//! commands while the sequence runs or the controller is in standby ("Standby mode must be
//! disabled prior to sending any new data"), unknown commands, malformed payloads, mailbox
//! data with no pattern mailbox open or past entry 127, and start without a successful
//! validation since the last configuration change or outside pattern display mode.
//! Validation reports bits 0-4 as TI's SDK names them. As the device does, it takes time:
//! a display-mode change shows after [`Dlpc350SimConfig::mode_switch`], Stop takes effect
//! at the end of the pattern being shown, and the first Start after leaving video mode is
//! lost (pycrafter4500 sends Start twice for this). It answers the reads real clients send:
//! the three status bytes, version, firmware tag, LED currents, gamma, display mode,
//! pattern display state, power mode, validation and the pattern mailbox.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use dioptra_transport::hid::memory::{
    self, HidBehaviour, HidDeviceHandle, HidRefusal, MemoryHidLink,
};
use tokio::sync::broadcast;
use tokio::task::JoinHandle;
use tokio::time::Instant;

/// Bytes in one HID report after the report id (0).
pub const REPORT_BYTES: usize = 64;
/// Flags, sequence, length (little-endian).
const HEADER_BYTES: usize = 4;
/// The controller's command buffer (TI `HID_MESSAGE_MAX_SIZE`).
const BUFFER_BYTES: usize = 512;
const FLAG_READ: u8 = 0x80;
const FLAG_REPLY: u8 = 0x40;
const FLAG_NACK: u8 = 0x20;
/// Pattern LUT entries (TI `MAX_PAT_LUT_ENTRIES`).
pub const LUT_SIZE: usize = 128;
/// The shortest black gap between an exposure and the next pattern.
const MIN_GAP_US: u32 = 230;

/// Command words, CMD2 << 8 | CMD3, as TI's `CmdList` gives them.
pub mod cmd {
    pub const POWER_CONTROL: u16 = 0x0200;
    pub const GET_VERSION: u16 = 0x0205;
    pub const LED_CURRENT: u16 = 0x0B01;
    pub const STATUS_HW: u16 = 0x1A0A;
    pub const STATUS_SYS: u16 = 0x1A0B;
    pub const STATUS_MAIN: u16 = 0x1A0C;
    /// Not in `CmdList`; pycrafter4500's `set_gamma_correction` (one byte, bit 7 enable).
    pub const GAMMA: u16 = 0x1A0E;
    pub const LUT_VALID: u16 = 0x1A1A;
    pub const DISP_MODE: u16 = 0x1A1B;
    pub const TRIG_OUT1_CTL: u16 = 0x1A1D;
    pub const TRIG_OUT2_CTL: u16 = 0x1A1E;
    pub const PAT_DISP_MODE: u16 = 0x1A22;
    pub const PAT_TRIG_MODE: u16 = 0x1A23;
    pub const PAT_START_STOP: u16 = 0x1A24;
    pub const PAT_EXPO_PRD: u16 = 0x1A29;
    pub const PAT_CONFIG: u16 = 0x1A31;
    pub const MBOX_ADDRESS: u16 = 0x1A32;
    pub const MBOX_CONTROL: u16 = 0x1A33;
    pub const MBOX_DATA: u16 = 0x1A34;
    pub const TRIG_IN1_DELAY: u16 = 0x1A35;
    pub const TRIG_IN2_CONTROL: u16 = 0x1A36;
    pub const GET_FIRMWARE_TAG: u16 = 0x1AFF;
}

/// Validation status bits (TI's SDK, `LCr4500::CreateSendStartSequenceLut`).
pub mod validation {
    /// Exposure or frame period out of range.
    pub const EXPOSURE_OR_PERIOD: u8 = 0x01;
    /// Pattern number in the LUT invalid.
    pub const PATTERN_NUMBER: u8 = 0x02;
    /// Continued output trigger overlaps a black vector.
    pub const OVERLAP_BLACK: u8 = 0x04;
    /// Black vector missing when exposure less than frame period (TI's API: post vector not
    /// inserted before an externally triggered vector). Both are checked.
    pub const BLACK_MISSING: u8 = 0x08;
    /// Exposure and frame period differ by less than 230 µs.
    pub const GAP_TOO_SHORT: u8 = 0x10;
    pub const BUSY: u8 = 0x80;
}

/// Shortest exposure per bit depth 1..=8, µs: the programmer's guide's pattern-exposure table.
const MIN_EXPOSURE_US: [u32; 8] = [235, 700, 1570, 1700, 2000, 2500, 4500, 8333];

/// What starts a pattern (LUT entry byte 0, bits 0-1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Trigger {
    Internal,
    ExternalPositive,
    ExternalNegative,
    /// No trigger: continue from the previous pattern.
    Continue,
}

/// One pattern LUT entry as the controller reads the 3 wire bytes: byte 0 trigger (bits
/// 0-1) and pattern number (2-7); byte 1 bit depth (0-3) and LED select (4-7); byte 2
/// invert (0), insert black (1), buffer swap (2), TRIG_OUT_1 from the previous pattern (3).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PatternEntry {
    pub trigger: Trigger,
    pub pattern: u8,
    pub bit_depth: u8,
    pub leds: u8,
    pub invert: bool,
    pub insert_black: bool,
    pub buffer_swap: bool,
    pub trig_out_prev: bool,
}

impl PatternEntry {
    fn from_wire(b: [u8; 3]) -> PatternEntry {
        PatternEntry {
            trigger: match b[0] & 0x03 {
                0 => Trigger::Internal,
                1 => Trigger::ExternalPositive,
                2 => Trigger::ExternalNegative,
                _ => Trigger::Continue,
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
    fn to_wire(self) -> [u8; 3] {
        let trigger = match self.trigger {
            Trigger::Internal => 0,
            Trigger::ExternalPositive => 1,
            Trigger::ExternalNegative => 2,
            Trigger::Continue => 3,
        };
        [
            trigger | (self.pattern & 0x3f) << 2,
            (self.bit_depth & 0x0f) | (self.leds & 0x0f) << 4,
            u8::from(self.invert)
                | u8::from(self.insert_black) << 1
                | u8::from(self.buffer_swap) << 2
                | u8::from(self.trig_out_prev) << 3,
        ]
    }
    fn external(self) -> bool {
        matches!(
            self.trigger,
            Trigger::ExternalPositive | Trigger::ExternalNegative
        )
    }
}

/// Firmware component versions the simulated controller reports, (major, minor, patch).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SimVersion {
    pub application: (u8, u8, u16),
    pub api: (u8, u8, u16),
    pub software_config: (u8, u8, u16),
    pub sequence_config: (u8, u8, u16),
}

/// What the simulated projector is attached to, and how it behaves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dlpc350SimConfig {
    /// Video-port frame rate (VSYNC), Hz.
    pub vsync_hz: f64,
    pub version: SimVersion,
    /// Up to 32 bytes (TI's `DLPC350_GetFirmwareTagInfo` reads at most 32).
    pub firmware_tag: &'static str,
    /// How long a display-mode change takes to show (TI's GUI waits 100 ms, then polls).
    pub mode_switch: Duration,
    /// The first Start after leaving video mode is acknowledged and lost.
    pub first_start_lost: bool,
    /// In standby at power-up.
    pub standby: bool,
    /// The hardware status byte when nothing went wrong: bit 0 initialisation done; set bit
    /// 1 for an incompatible controller or DMD.
    pub hardware_status: u8,
}

impl Default for Dlpc350SimConfig {
    fn default() -> Self {
        Dlpc350SimConfig {
            vsync_hz: 60.0,
            version: SimVersion {
                application: (3, 0, 0),
                api: (2, 1, 0),
                software_config: (1, 0, 0),
                sequence_config: (1, 0, 0),
            },
            firmware_tag: "dioptra simulated DLPC350",
            mode_switch: Duration::from_millis(50),
            first_start_lost: true,
            standby: false,
            hardware_status: 0x01,
        }
    }
}

/// One pattern shown, with the trigger outputs at its start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PatternEvent {
    /// Video frame since start.
    pub frame: u64,
    pub lut_index: u8,
    pub pattern: u8,
    pub bit_depth: u8,
    /// Microseconds since the simulator was made.
    pub device_time_us: u64,
    pub exposure_us: u32,
    /// TRIG_OUT_1 rose (every pattern).
    pub trig_out1: bool,
    /// TRIG_OUT_2 rose (every `trig_out2_every` patterns: a lens sweep starts).
    pub trig_out2: bool,
}

/// One command as the simulator saw it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Logged {
    pub read: bool,
    pub code: u16,
    pub payload: Vec<u8>,
    pub nack: bool,
}

impl std::fmt::Display for Logged {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let hex: Vec<String> = self.payload.iter().map(|b| format!("{b:02x}")).collect();
        write!(
            f,
            "{} {:04X} [{}]{}",
            if self.read { "read " } else { "write" },
            self.code,
            hex.join(" "),
            if self.nack { " -> NACK" } else { "" }
        )
    }
}

/// A command reassembled from its reports.
struct Request {
    flags: u8,
    seq: u8,
    code: u16,
    data: Vec<u8>,
}

/// Reassembles requests: the first report carries the header, the command word (CMD3 first)
/// and the start of the data; continuation reports carry data only.
#[derive(Default)]
struct Reassembly {
    pending: Option<(u8, u8, usize, Vec<u8>)>,
}

impl Reassembly {
    /// `Err` for a report that cannot start a request (it is dropped).
    fn push(&mut self, report: &[u8]) -> Result<Option<Request>, ()> {
        let report = &report[..report.len().min(REPORT_BYTES)];
        let (flags, seq, len, mut body) = match self.pending.take() {
            Some(p) => p,
            None => {
                let [flags, seq, lo, hi, ..] = *report else {
                    return Err(());
                };
                let len = usize::from(u16::from_le_bytes([lo, hi]));
                if !(2..=BUFFER_BYTES).contains(&len) {
                    return Err(());
                }
                let first = &report[HEADER_BYTES..];
                let take = len.min(first.len());
                return self.finish(flags, seq, len, first[..take].to_vec());
            }
        };
        let take = (len - body.len()).min(report.len());
        body.extend_from_slice(&report[..take]);
        self.finish(flags, seq, len, body)
    }

    fn finish(
        &mut self,
        flags: u8,
        seq: u8,
        len: usize,
        body: Vec<u8>,
    ) -> Result<Option<Request>, ()> {
        if body.len() < len {
            self.pending = Some((flags, seq, len, body));
            return Ok(None);
        }
        Ok(Some(Request {
            flags,
            seq,
            code: u16::from_le_bytes([body[0], body[1]]),
            data: body[2..].to_vec(),
        }))
    }
}

/// A reply's reports (report id 0 first): the request's flags with the nack bit, its
/// sequence, the data length and the data.
fn reply_reports(req: &Request, nack: bool, data: &[u8]) -> Vec<[u8; REPORT_BYTES + 1]> {
    let flags = (req.flags & !FLAG_NACK) | if nack { FLAG_NACK } else { 0 };
    let len = data.len().min(BUFFER_BYTES) as u16;
    let mut stream = vec![flags, req.seq];
    stream.extend_from_slice(&len.to_le_bytes());
    stream.extend_from_slice(&data[..usize::from(len)]);
    let mut out = Vec::new();
    let mut first = true;
    let mut rest = &stream[..];
    while first || !rest.is_empty() {
        first = false;
        let mut r = [0u8; REPORT_BYTES + 1];
        let n = rest.len().min(REPORT_BYTES);
        r[1..=n].copy_from_slice(&rest[..n]);
        rest = &rest[n..];
        out.push(r);
    }
    out
}

/// Where the running sequence is.
#[derive(Clone, Copy)]
struct Running {
    start: Instant,
    period: Duration,
    frame: Duration,
    patterns: u32,
    vsync: bool,
}

impl Running {
    /// The end of the pattern being shown at `now`: the next pattern start after it.
    fn pattern_end(&self, now: Instant) -> Instant {
        let since = now.saturating_duration_since(self.start);
        let cycle = if self.vsync {
            self.frame
        } else {
            self.period.saturating_mul(self.patterns)
        };
        if cycle.is_zero() || self.period.is_zero() {
            return now;
        }
        let cycles = (since.as_nanos() / cycle.as_nanos()) as u32;
        let cycle_start = self.start + cycle.saturating_mul(cycles);
        let into = now.saturating_duration_since(cycle_start);
        let k = (into.as_nanos() / self.period.as_nanos()) as u32 + 1;
        if k < self.patterns {
            cycle_start + self.period.saturating_mul(k)
        } else {
            cycle_start + cycle
        }
    }
}

struct State {
    cfg: Dlpc350SimConfig,
    origin: Instant,
    /// 0 video, 1 pattern, as the controller shows it now.
    display_mode: u8,
    /// A display-mode change not yet showing: (mode, when).
    mode_change: Option<(u8, Instant)>,
    lose_next_start: bool,
    source: u8,
    trigger_mode: u8,
    exposure_us: u32,
    period_us: u32,
    lut_entries: usize,
    repeat: bool,
    trig_out2_every: u32,
    trig_out1: [u8; 3],
    trig_out2: [u8; 2],
    trig_in1_delay: u32,
    trig_in2: u8,
    led_current: [u8; 3],
    gamma: u8,
    mailbox: u8,
    address: usize,
    lut: Vec<Option<PatternEntry>>,
    validation: u8,
    /// Polls left before the validation result shows (it reports busy meanwhile).
    validation_busy_polls: u8,
    validated: bool,
    standby: bool,
    hardware: u8,
    paused: bool,
    asm: Reassembly,
    log: Vec<Logged>,
    garbage: u64,
    /// Commands are executed but not answered (a hung USB stack).
    muted: bool,
    runner: Option<(JoinHandle<()>, Running)>,
    /// When a requested Stop takes effect; the sequencer task reads it too.
    stop_at: Arc<Mutex<Option<Instant>>>,
}

/// The simulator's handle: events, the command log, and fault injection.
pub struct Dlpc350Sim {
    state: Arc<Mutex<State>>,
    handle: Arc<Mutex<Option<HidDeviceHandle>>>,
    events: broadcast::Sender<PatternEvent>,
}

struct Behaviour {
    state: Arc<Mutex<State>>,
    handle: Arc<Mutex<Option<HidDeviceHandle>>>,
    events: broadcast::Sender<PatternEvent>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // No invariant spans a panic point.
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// A HID report descriptor like the LightCrafter's: vendor page, 64-byte input and output
/// reports without report ids.
const DESCRIPTOR: [u8; 25] = [
    0x06, 0x00, 0xff, // usage page (vendor 0xFF00)
    0x09, 0x01, // usage 1
    0xa1, 0x01, // collection (application)
    0x15, 0x00, 0x26, 0xff, 0x00, // logical 0..255
    0x75, 0x08, 0x95, 0x40, // 64 bytes
    0x09, 0x01, 0x81, 0x02, // input
    0x09, 0x01, 0x91, 0x02, // output
    0xc0, // end collection
];

/// Makes a simulated DLPC350: the host's link and the simulator's handle. Call inside a tokio
/// runtime (the sequencer runs as a task on it).
pub fn new(cfg: Dlpc350SimConfig) -> (MemoryHidLink, Dlpc350Sim) {
    let state = Arc::new(Mutex::new(State {
        origin: Instant::now(),
        display_mode: 0,
        mode_change: None,
        lose_next_start: false,
        source: 0,
        trigger_mode: 0,
        exposure_us: 16_666,
        period_us: 16_666,
        lut_entries: 1,
        repeat: true,
        trig_out2_every: 1,
        trig_out1: [0, 0xbb, 0xbb],
        trig_out2: [0, 0xbb],
        trig_in1_delay: 0,
        trig_in2: 0,
        led_current: [0x97, 0x78, 0x7d],
        gamma: 0,
        mailbox: 0,
        address: 0,
        lut: vec![None; LUT_SIZE],
        validation: 0,
        validation_busy_polls: 0,
        validated: false,
        standby: cfg.standby,
        hardware: cfg.hardware_status,
        paused: false,
        asm: Reassembly::default(),
        log: Vec::new(),
        garbage: 0,
        muted: false,
        runner: None,
        stop_at: Arc::new(Mutex::new(None)),
        cfg,
    }));
    let handle = Arc::new(Mutex::new(None));
    let (events, _) = broadcast::channel(4096);
    let behaviour = Behaviour {
        state: state.clone(),
        handle: handle.clone(),
        events: events.clone(),
    };
    let (link, device) = memory::device(DESCRIPTOR.to_vec(), behaviour, 64);
    *lock(&handle) = Some(device);
    (
        link.named("simulated DLPC350"),
        Dlpc350Sim {
            state,
            handle,
            events,
        },
    )
}

impl Dlpc350Sim {
    /// Pattern and trigger events from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<PatternEvent> {
        self.events.subscribe()
    }

    /// Every command received so far, in order.
    pub fn log(&self) -> Vec<Logged> {
        lock(&self.state).log.clone()
    }

    /// Reports that did not form a packet.
    pub fn garbage_reports(&self) -> u64 {
        lock(&self.state).garbage
    }

    /// The pattern LUT entries in use.
    pub fn lut(&self) -> Vec<Option<PatternEntry>> {
        let s = lock(&self.state);
        s.lut[..s.lut_entries].to_vec()
    }

    pub fn running(&self) -> bool {
        let mut s = lock(&self.state);
        s.catch_up(Instant::now());
        s.running()
    }

    /// The display mode showing now: 0 video, 1 pattern.
    pub fn display_mode(&self) -> u8 {
        let mut s = lock(&self.state);
        s.catch_up(Instant::now());
        s.display_mode
    }

    /// Puts the controller in (or out of) standby, as its power button or another client.
    pub fn set_standby(&self, standby: bool) {
        let mut s = lock(&self.state);
        if standby {
            s.stop_now();
        }
        s.standby = standby;
    }

    /// The sequencer aborts (as on a lost video signal): it stops and hardware status shows
    /// a sequence abort.
    pub fn abort_sequence(&self) {
        let mut s = lock(&self.state);
        s.hardware |= 0x40;
        s.stop_now();
    }

    /// Puts a raw input report (report id first) in front of the host, as a confused
    /// controller or a noisy cable would.
    pub fn inject_input(&self, report: &[u8]) {
        if let Some(h) = lock(&self.handle).as_ref() {
            let _ = h.send_input(report);
        }
    }

    /// Stops answering (true) or answers again (false).
    pub fn mute(&self, muted: bool) {
        lock(&self.state).muted = muted;
    }

    /// Unplugs the USB cable.
    pub fn unplug(&self, reason: &str) {
        if let Some(h) = lock(&self.handle).as_ref() {
            h.disconnect(reason);
        }
        lock(&self.state).stop_now();
    }
}

impl Drop for Dlpc350Sim {
    fn drop(&mut self) {
        lock(&self.state).stop_now();
        // The last device handle goes: the host sees the device disappear.
        lock(&self.handle).take();
    }
}

impl HidBehaviour for Behaviour {
    fn write_output(&mut self, report: &[u8]) -> Result<(), HidRefusal> {
        let Some((&0, body)) = report.split_first() else {
            return Err(HidRefusal::new("the DLPC350 uses report id 0"));
        };
        let replies = {
            let mut s = lock(&self.state);
            match s.asm.push(body) {
                Ok(None) => return Ok(()),
                Ok(Some(req)) => s.handle(&req, &self.events),
                Err(()) => {
                    s.garbage += 1;
                    return Ok(());
                }
            }
        };
        let guard = lock(&self.handle);
        let Some(device) = guard.as_ref() else {
            return Ok(());
        };
        for r in replies {
            if device.send_input(&r).is_err() {
                break;
            }
        }
        Ok(())
    }
}

/// A command's outcome: nack, or the reply data.
type Outcome = Result<Vec<u8>, ()>;

fn ack() -> Outcome {
    Ok(Vec::new())
}

/// The payload if it has exactly `N` bytes.
fn exact<const N: usize>(data: &[u8]) -> Result<[u8; N], ()> {
    data.try_into().map_err(|_| ())
}

fn flag(b: u8) -> Result<bool, ()> {
    match b {
        0 => Ok(false),
        1 => Ok(true),
        _ => Err(()),
    }
}

fn le32(b: &[u8]) -> u32 {
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

fn version_word((major, minor, patch): (u8, u8, u16)) -> [u8; 4] {
    (u32::from(major) << 24 | u32::from(minor) << 16 | u32::from(patch)).to_le_bytes()
}

impl State {
    fn handle(
        &mut self,
        req: &Request,
        events: &broadcast::Sender<PatternEvent>,
    ) -> Vec<[u8; REPORT_BYTES + 1]> {
        let now = Instant::now();
        self.catch_up(now);
        let read = req.flags & FLAG_READ != 0;
        let outcome = if read {
            self.read(req.code, &req.data)
        } else {
            self.write(req.code, &req.data, now, events)
        };
        self.log.push(Logged {
            read,
            code: req.code,
            payload: req.data.clone(),
            nack: outcome.is_err(),
        });
        if req.flags & FLAG_REPLY == 0 || self.muted {
            return Vec::new();
        }
        match outcome {
            Ok(data) => reply_reports(req, false, &data),
            Err(()) => reply_reports(req, true, &[]),
        }
    }

    /// Applies what became due by `now`: a display-mode change, a requested stop.
    fn catch_up(&mut self, now: Instant) {
        if let Some((mode, at)) = self.mode_change {
            if now >= at {
                if self.display_mode == 0 && mode == 1 && self.cfg.first_start_lost {
                    self.lose_next_start = true;
                }
                self.display_mode = mode;
                self.mode_change = None;
            }
        }
        let due = matches!(*lock(&self.stop_at), Some(t) if now >= t);
        if due {
            self.stop_now();
        }
    }

    fn running(&self) -> bool {
        self.runner.is_some()
    }

    fn stop_now(&mut self) {
        if let Some((task, _)) = self.runner.take() {
            task.abort();
        }
        *lock(&self.stop_at) = None;
    }

    /// Configuration is refused while the sequence runs or in standby, and undoes the last
    /// validation.
    fn configure(&mut self) -> Result<(), ()> {
        if self.running() || self.standby {
            return Err(());
        }
        self.validated = false;
        Ok(())
    }

    fn read(&mut self, code: u16, data: &[u8]) -> Outcome {
        if !data.is_empty() {
            return Err(());
        }
        let running = u8::from(self.running());
        match code {
            cmd::GET_VERSION => {
                let v = self.cfg.version;
                let words = [v.application, v.api, v.software_config, v.sequence_config];
                Ok(words.into_iter().flat_map(version_word).collect())
            }
            cmd::STATUS_HW => Ok(vec![self.hardware]),
            cmd::STATUS_SYS => Ok(vec![0x01]), // internal memory test passed
            // Bit 0 DMD parked, 1 sequencer running, 2 buffer frozen, 3 gamma enabled.
            cmd::STATUS_MAIN => Ok(vec![running << 1 | (self.gamma >> 7) << 3]),
            cmd::GET_FIRMWARE_TAG => {
                let mut tag = self.cfg.firmware_tag.as_bytes().to_vec();
                tag.resize(32, 0);
                tag.truncate(32);
                Ok(tag)
            }
            cmd::LED_CURRENT => Ok(self.led_current.to_vec()),
            cmd::GAMMA => Ok(vec![self.gamma]),
            cmd::POWER_CONTROL => Ok(vec![u8::from(self.standby)]),
            cmd::DISP_MODE => Ok(vec![self.display_mode]),
            cmd::PAT_DISP_MODE => Ok(vec![self.source]),
            cmd::PAT_TRIG_MODE => Ok(vec![self.trigger_mode]),
            cmd::PAT_START_STOP => Ok(vec![if self.running() {
                2
            } else {
                u8::from(self.paused)
            }]),
            cmd::PAT_EXPO_PRD => {
                let mut v = self.exposure_us.to_le_bytes().to_vec();
                v.extend_from_slice(&self.period_us.to_le_bytes());
                Ok(v)
            }
            cmd::PAT_CONFIG => Ok(vec![
                (self.lut_entries - 1) as u8,
                u8::from(self.repeat),
                (self.trig_out2_every - 1) as u8,
                0,
            ]),
            cmd::TRIG_OUT1_CTL => Ok(self.trig_out1.to_vec()),
            cmd::TRIG_OUT2_CTL => Ok(self.trig_out2.to_vec()),
            cmd::TRIG_IN1_DELAY => Ok(self.trig_in1_delay.to_le_bytes().to_vec()),
            cmd::TRIG_IN2_CONTROL => Ok(vec![self.trig_in2]),
            cmd::MBOX_CONTROL => Ok(vec![self.mailbox]),
            cmd::LUT_VALID => {
                if self.validation_busy_polls > 0 {
                    self.validation_busy_polls -= 1;
                    return Ok(vec![validation::BUSY]);
                }
                Ok(vec![self.validation])
            }
            cmd::MBOX_DATA => {
                if self.mailbox != 2 {
                    return Err(());
                }
                // The whole table from the mailbox address (unused slots read as zeros): more
                // than was written, as TI's `DLPC350_GetPatLut` allows for by reading only
                // the prefix it needs.
                Ok(self.lut[self.address..]
                    .iter()
                    .flat_map(|e| e.map_or([0; 3], |e| e.to_wire()))
                    .collect())
            }
            _ => Err(()),
        }
    }

    fn write(
        &mut self,
        code: u16,
        data: &[u8],
        now: Instant,
        events: &broadcast::Sender<PatternEvent>,
    ) -> Outcome {
        match code {
            cmd::POWER_CONTROL => {
                let [b] = exact(data)?;
                let standby = flag(b)?;
                if standby {
                    self.stop_now();
                }
                self.standby = standby;
                ack()
            }
            cmd::LED_CURRENT => {
                self.led_current = exact(data)?;
                ack()
            }
            cmd::GAMMA => {
                let [b] = exact(data)?;
                self.gamma = b & 0x83;
                ack()
            }
            cmd::DISP_MODE => {
                let [b] = exact(data)?;
                let mode = u8::from(flag(b)?);
                self.configure()?;
                let shown = self.mode_change.map_or(self.display_mode, |(m, _)| m);
                if mode != shown {
                    self.mode_change = Some((mode, now + self.cfg.mode_switch));
                }
                ack()
            }
            cmd::PAT_DISP_MODE => {
                let [b] = exact(data)?;
                // 0 video port, 3 flash; 1 and 2 are reserved.
                if b != 0 && b != 3 {
                    return Err(());
                }
                self.configure()?;
                self.source = b;
                ack()
            }
            cmd::PAT_TRIG_MODE => {
                let [b] = exact(data)?;
                if b > 4 {
                    return Err(());
                }
                self.configure()?;
                self.trigger_mode = b;
                ack()
            }
            cmd::PAT_EXPO_PRD => {
                let b: [u8; 8] = exact(data)?;
                self.configure()?;
                // Exposure first, then period (TI's API, pycrafter4500).
                self.exposure_us = le32(&b[..4]);
                self.period_us = le32(&b[4..]);
                ack()
            }
            cmd::PAT_CONFIG => {
                let b: [u8; 4] = exact(data)?;
                let repeat = flag(b[1])?;
                self.configure()?;
                // Counts are sent minus one.
                self.lut_entries = usize::from(b[0] & 0x7f) + 1;
                self.repeat = repeat;
                self.trig_out2_every = u32::from(b[2]) + 1;
                ack()
            }
            cmd::TRIG_OUT1_CTL => {
                let b: [u8; 3] = exact(data)?;
                flag(b[0])?;
                self.configure()?;
                self.trig_out1 = b;
                ack()
            }
            cmd::TRIG_OUT2_CTL => {
                let b: [u8; 2] = exact(data)?;
                flag(b[0])?;
                self.configure()?;
                self.trig_out2 = b;
                ack()
            }
            cmd::TRIG_IN1_DELAY => {
                let b: [u8; 4] = exact(data)?;
                self.configure()?;
                self.trig_in1_delay = le32(&b);
                ack()
            }
            cmd::TRIG_IN2_CONTROL => {
                let [b] = exact(data)?;
                flag(b)?;
                self.configure()?;
                self.trig_in2 = b;
                ack()
            }
            cmd::MBOX_CONTROL => {
                let [b] = exact(data)?;
                if b > 3 {
                    return Err(());
                }
                self.mailbox = b;
                ack()
            }
            cmd::MBOX_ADDRESS => {
                let [b] = exact(data)?;
                if usize::from(b) >= LUT_SIZE {
                    return Err(());
                }
                self.address = usize::from(b);
                ack()
            }
            cmd::MBOX_DATA => {
                if data.is_empty() || !data.len().is_multiple_of(3) {
                    return Err(());
                }
                let n = data.len() / 3;
                if self.mailbox != 2 || self.address + n > LUT_SIZE {
                    return Err(());
                }
                self.configure()?;
                for (slot, b) in self.lut[self.address..]
                    .iter_mut()
                    .zip(data.chunks_exact(3))
                {
                    *slot = Some(PatternEntry::from_wire([b[0], b[1], b[2]]));
                }
                self.address = (self.address + n).min(LUT_SIZE - 1);
                ack()
            }
            cmd::LUT_VALID => {
                exact::<1>(data)?;
                if self.running() {
                    return Err(());
                }
                self.validation = self.validate();
                self.validated = self.validation & 0x1f == 0;
                self.validation_busy_polls = 1;
                ack()
            }
            cmd::PAT_START_STOP => {
                let [b] = exact(data)?;
                match b {
                    0 | 1 => {
                        // The pattern on show finishes first.
                        if let Some((_, run)) = &self.runner {
                            *lock(&self.stop_at) = Some(run.pattern_end(now));
                        }
                        self.paused = b == 1;
                        ack()
                    }
                    2 => self.start(events),
                    _ => Err(()),
                }
            }
            _ => Err(()),
        }
    }

    fn start(&mut self, events: &broadcast::Sender<PatternEvent>) -> Outcome {
        if self.running() {
            // A Start while a Stop is pending cancels it.
            *lock(&self.stop_at) = None;
            return ack();
        }
        if !self.validated || self.standby || self.display_mode != 1 {
            return Err(());
        }
        if std::mem::take(&mut self.lose_next_start) {
            return ack();
        }
        self.hardware &= !0x40;
        self.paused = false;
        let running = Running {
            start: Instant::now(),
            period: Duration::from_micros(u64::from(self.period_us)),
            frame: self.frame(),
            patterns: self.lut_entries as u32,
            vsync: self.trigger_mode == 0,
        };
        let task = self.spawn_sequencer(running, events.clone());
        self.runner = Some((task, running));
        ack()
    }

    fn frame(&self) -> Duration {
        // An unusable rate fails validation, so no sequence starts with it.
        Duration::try_from_secs_f64(1.0 / self.cfg.vsync_hz).unwrap_or(Duration::MAX)
    }

    fn entries(&self) -> &[Option<PatternEntry>] {
        &self.lut[..self.lut_entries]
    }

    /// The validation bits for the present configuration.
    fn validate(&self) -> u8 {
        use validation::*;
        let (exposure, period) = (self.exposure_us, self.period_us);
        let entries = self.entries();
        let mut bits = 0;
        let min_exposure = |depth: u8| {
            MIN_EXPOSURE_US
                .get(usize::from(depth).wrapping_sub(1))
                .copied()
        };
        let too_short = entries
            .iter()
            .flatten()
            .any(|e| min_exposure(e.bit_depth).is_none_or(|min| exposure < min));
        let frame_us = 1e6 / self.cfg.vsync_hz;
        let frame_overrun = self.trigger_mode == 0
            && !(frame_us.is_finite()
                && frame_us > 0.0
                && f64::from(period) * entries.len() as f64 <= frame_us);
        if exposure == 0 || exposure > period || too_short || frame_overrun {
            bits |= EXPOSURE_OR_PERIOD;
        } else if exposure != period && exposure + MIN_GAP_US > period {
            bits |= GAP_TOO_SHORT;
        }
        let bad_pattern = |e: &Option<PatternEntry>| match e {
            None => true,
            Some(e) => {
                !(1..=8).contains(&e.bit_depth)
                    || u32::from(e.pattern) >= 24 / u32::from(e.bit_depth)
            }
        };
        if entries.iter().any(bad_pattern) {
            bits |= PATTERN_NUMBER;
        }
        if entries
            .iter()
            .flatten()
            .any(|e| e.trig_out_prev && e.insert_black)
        {
            bits |= OVERLAP_BLACK;
        }
        let dark_without_black = exposure < period
            && entries
                .iter()
                .flatten()
                .any(|e| !e.insert_black && !e.trig_out_prev);
        let no_post_vector = entries.windows(2).any(|w| match (w[0], w[1]) {
            (Some(prev), Some(next)) => next.external() && !prev.insert_black,
            _ => false,
        });
        if dark_without_black || no_post_vector {
            bits |= BLACK_MISSING;
        }
        bits
    }

    /// Shows the LUT: in VSYNC mode each video frame starts the sequence again.
    fn spawn_sequencer(
        &self,
        run: Running,
        events: broadcast::Sender<PatternEvent>,
    ) -> JoinHandle<()> {
        let entries: Vec<PatternEntry> = self.entries().iter().flatten().copied().collect();
        let exposure_us = self.exposure_us;
        let every = u64::from(self.trig_out2_every.max(1));
        let repeat = self.repeat;
        let origin = self.origin;
        let stop_at = self.stop_at.clone();
        tokio::spawn(async move {
            if entries.is_empty() || run.period.is_zero() {
                return; // validation never passes then; never spin
            }
            let mut shown: u64 = 0;
            for f in 0u64.. {
                let frame_start = if run.vsync {
                    run.start
                        + run
                            .frame
                            .saturating_mul(u32::try_from(f).unwrap_or(u32::MAX))
                } else {
                    run.start
                        + run
                            .period
                            .saturating_mul(u32::try_from(shown).unwrap_or(u32::MAX))
                };
                for (i, e) in entries.iter().enumerate() {
                    let at = frame_start + run.period.saturating_mul(i as u32);
                    tokio::time::sleep_until(at).await;
                    if matches!(*lock(&stop_at), Some(t) if at >= t) {
                        return;
                    }
                    let ev = PatternEvent {
                        frame: f,
                        lut_index: i as u8,
                        pattern: e.pattern,
                        bit_depth: e.bit_depth,
                        device_time_us: at.duration_since(origin).as_micros() as u64,
                        exposure_us,
                        trig_out1: true,
                        trig_out2: shown.is_multiple_of(every),
                    };
                    shown += 1;
                    // No subscriber is fine: the projector runs whether or not anyone watches.
                    let _ = events.send(ev);
                }
                if !repeat {
                    return;
                }
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Hand-assembled request reports (report id 0 first), as the programmer's guide lays
    /// them out: flags, sequence, length (LE, command word included), CMD3, CMD2, data.
    fn request(flags: u8, seq: u8, code: u16, data: &[u8]) -> Vec<[u8; REPORT_BYTES + 1]> {
        let len = (data.len() + 2) as u16;
        let mut stream = vec![flags, seq];
        stream.extend_from_slice(&len.to_le_bytes());
        stream.extend_from_slice(&code.to_le_bytes());
        stream.extend_from_slice(data);
        stream
            .chunks(REPORT_BYTES)
            .map(|c| {
                let mut r = [0u8; REPORT_BYTES + 1];
                r[1..=c.len()].copy_from_slice(c);
                r
            })
            .collect()
    }

    #[test]
    fn reassembles_continuation_reports_without_headers() {
        // 40 LUT entries: 120 data bytes + the command word = 122, over two reports.
        let data: Vec<u8> = (0..120).map(|i| i as u8).collect();
        let reports = request(0x40, 9, cmd::MBOX_DATA, &data);
        assert_eq!(reports.len(), 2);
        let mut asm = Reassembly::default();
        assert!(asm.push(&reports[0][1..]).unwrap().is_none());
        let req = asm.push(&reports[1][1..]).unwrap().unwrap();
        assert_eq!((req.seq, req.code), (9, 0x1A34));
        assert_eq!(req.data, data);
        // A header with length 1 has no command word; 513 is past the buffer.
        assert!(asm.push(&[0x40, 0, 1, 0]).is_err());
        assert!(asm.push(&[0x40, 0, 0x01, 0x02]).is_err());
    }

    #[test]
    fn replies_echo_flags_and_sequence_with_the_data_length() {
        let req = Request {
            flags: 0xc0,
            seq: 7,
            code: cmd::STATUS_MAIN,
            data: vec![],
        };
        let r = reply_reports(&req, false, &[0x02]);
        assert_eq!(r.len(), 1);
        assert_eq!(&r[0][..6], &[0, 0xc0, 7, 1, 0, 0x02]);
        let r = reply_reports(&req, true, &[]);
        assert_eq!(&r[0][..5], &[0, 0xe0, 7, 0, 0]);
        // 384 bytes of LUT: 388 with the header, 7 reports.
        assert_eq!(reply_reports(&req, false, &[0; 384]).len(), 7);
    }

    #[test]
    fn lut_entries_decode_as_ti_lays_them_out() {
        // pycrafter4500's send_pattern_lut(trig_type=1, pat_num=3, bit_depth=6,
        // led_select=7, do_insert_black=True, do_buf_swap=True): bytes 0d 76 06.
        let e = PatternEntry::from_wire([0x0d, 0x76, 0x06]);
        assert_eq!(
            e,
            PatternEntry {
                trigger: Trigger::ExternalPositive,
                pattern: 3,
                bit_depth: 6,
                leds: 7,
                invert: false,
                insert_black: true,
                buffer_swap: true,
                trig_out_prev: false,
            }
        );
        assert_eq!(e.to_wire(), [0x0d, 0x76, 0x06]);
    }

    #[test]
    fn stop_waits_for_the_end_of_the_pattern_on_show() {
        let start = Instant::now();
        let run = Running {
            start,
            period: Duration::from_micros(4000),
            frame: Duration::from_micros(16_666),
            patterns: 4,
            vsync: true,
        };
        let at = |us| start + Duration::from_micros(us);
        assert_eq!(run.pattern_end(at(100)), at(4000));
        assert_eq!(run.pattern_end(at(12_100)), at(16_666));
        assert_eq!(run.pattern_end(at(16_700)), at(16_666 + 4000));
    }
}
