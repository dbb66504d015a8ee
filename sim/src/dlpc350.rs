//! A simulated TI DLPC350 (LightCrafter 4500) on the in-memory HID link: the controller's
//! side of the same 64-byte reports, its validation rules and nacks, and a pattern sequencer
//! that emits pattern and trigger-out events on tokio's clock.
//!
//! Rules enforced (a nack, as the controller sends for an invalid command):
//! configuration commands while the sequence runs, unknown commands, malformed payloads,
//! mailbox data with no pattern mailbox open or past entry 127, and start without a
//! successful validation since the last configuration change (the real controller would run
//! garbage; refusing makes the mistake visible). Validation reports bits 0, 1, 2 and 4 of the
//! programmer's guide; bit 3 (post vector) is not modelled.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use dioptra_sync::dlpc350::protocol::{
    exposure_fits_period, min_exposure_us, patterns_per_image, Assembler, Command,
    ComponentVersion, Direction, DisplayMode, GetHardwareStatus, GetMainStatus, GetSystemStatus,
    GetValidation, GetVersion, HardwareStatus, LutEntry, Mailbox, MailboxControl, MainStatus,
    Packet, PatternDisplay, PatternSource, ProtocolError, ReadMailbox, SequenceAction,
    SetDisplayMode, SetExposure, SetMailboxAddress, SetPatternConfig, SetPatternSource,
    SetPowerMode, SetTrigIn1Delay, SetTrigIn2, SetTrigOut1, SetTrigOut2, SetTriggerMode,
    StartValidation, SystemStatus, TriggerMode, ValidationStatus, Version, WriteMailbox,
    MAX_LUT_ENTRIES, REPORT_LEN,
};
use dioptra_transport::hid::memory::{
    self, HidBehaviour, HidDeviceHandle, HidRefusal, MemoryHidLink,
};
use tokio::sync::broadcast;
use tokio::task::JoinHandle;
use tokio::time::Instant;

/// What the simulated projector is attached to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dlpc350SimConfig {
    /// Video-port frame rate (VSYNC), Hz.
    pub vsync_hz: f64,
    pub version: Version,
}

impl Default for Dlpc350SimConfig {
    fn default() -> Self {
        let v = |major, minor, patch| ComponentVersion {
            major,
            minor,
            patch,
        };
        Dlpc350SimConfig {
            vsync_hz: 60.0,
            version: Version {
                application: v(3, 0, 0),
                api: v(2, 1, 0),
                software_config: v(1, 0, 0),
                sequence_config: v(1, 0, 0),
            },
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

struct State {
    cfg: Dlpc350SimConfig,
    origin: Instant,
    display_mode: DisplayMode,
    source: PatternSource,
    trigger_mode: TriggerMode,
    exposure: SetExposure,
    pattern_config: SetPatternConfig,
    trig_out1: SetTrigOut1,
    trig_out2: SetTrigOut2,
    mailbox: Mailbox,
    address: u8,
    lut: Vec<Option<LutEntry>>,
    validation: ValidationStatus,
    /// Polls left before the validation result shows (it reports busy meanwhile).
    validation_busy_polls: u8,
    validated: bool,
    standby: bool,
    hardware: u8,
    asm: Assembler,
    log: Vec<Logged>,
    garbage: u64,
    /// Commands are executed but not answered (a hung USB stack).
    muted: bool,
    runner: Option<JoinHandle<()>>,
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
        cfg,
        origin: Instant::now(),
        display_mode: DisplayMode::Video,
        source: PatternSource::VideoPort,
        trigger_mode: TriggerMode::Vsync,
        exposure: SetExposure {
            exposure_us: 16_666,
            period_us: 16_666,
        },
        pattern_config: SetPatternConfig {
            lut_entries: 1,
            repeat: true,
            trig_out2_every: 1,
            images: 1,
        },
        trig_out1: SetTrigOut1 {
            invert: false,
            rising_delay: 0xbb,
            falling_delay: 0xbb,
        },
        trig_out2: SetTrigOut2 {
            invert: false,
            rising_delay: 0xbb,
        },
        mailbox: Mailbox::Closed,
        address: 0,
        lut: vec![None; MAX_LUT_ENTRIES],
        validation: ValidationStatus(0),
        validation_busy_polls: 0,
        validated: false,
        standby: false,
        hardware: 0x01,
        asm: Assembler::new(Direction::Request),
        log: Vec::new(),
        garbage: 0,
        muted: false,
        runner: None,
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
    pub fn lut(&self) -> Vec<Option<LutEntry>> {
        let s = lock(&self.state);
        s.lut[..usize::from(s.pattern_config.lut_entries)].to_vec()
    }

    pub fn running(&self) -> bool {
        lock(&self.state).runner.is_some()
    }

    /// The sequencer aborts (as on a lost video signal): it stops and hardware status shows
    /// a sequence abort.
    pub fn abort_sequence(&self) {
        let mut s = lock(&self.state);
        s.hardware |= 0x40;
        if let Some(r) = s.runner.take() {
            r.abort();
        }
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
        if let Some(r) = lock(&self.state).runner.take() {
            r.abort();
        }
    }
}

impl Drop for Dlpc350Sim {
    fn drop(&mut self) {
        if let Some(r) = lock(&self.state).runner.take() {
            r.abort();
        }
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
                Ok(Some(packet)) => s.handle(&packet, &self.events),
                Err(_) => {
                    s.garbage += 1;
                    return Ok(());
                }
            }
        };
        if let Some(reply) = replies {
            let guard = lock(&self.handle);
            let Some(device) = guard.as_ref() else {
                return Ok(());
            };
            // A packet too long for the buffer cannot come from handle(); nothing to send then.
            for r in reply.to_reports().unwrap_or_default() {
                let mut out = [0u8; REPORT_LEN + 1];
                out[1..].copy_from_slice(&r);
                if device.send_input(&out).is_err() {
                    break;
                }
            }
        }
        Ok(())
    }
}

/// A command's outcome: nack, or the reply data.
type Outcome = Result<Vec<u8>, ()>;

fn decode<C: Command>(data: &[u8]) -> Result<C, ()> {
    C::decode(data).map_err(|_: ProtocolError| ())
}

fn ack() -> Outcome {
    Ok(Vec::new())
}

impl State {
    fn handle(&mut self, p: &Packet, events: &broadcast::Sender<PatternEvent>) -> Option<Packet> {
        let code = p.command.unwrap_or_default();
        let outcome = self.execute(p.is_read(), code, &p.data, events);
        self.log.push(Logged {
            read: p.is_read(),
            code,
            payload: p.data.clone(),
            nack: outcome.is_err(),
        });
        (p.wants_reply() && !self.muted).then(|| match outcome {
            Ok(data) => Packet::reply_to(p, false, data),
            Err(()) => Packet::reply_to(p, true, Vec::new()),
        })
    }

    fn running(&self) -> bool {
        self.runner.is_some()
    }

    /// Configuration is refused while the sequence runs, and undoes the last validation.
    fn configure(&mut self) -> Result<(), ()> {
        if self.running() {
            return Err(());
        }
        self.validated = false;
        Ok(())
    }

    fn execute(
        &mut self,
        read: bool,
        code: u16,
        data: &[u8],
        events: &broadcast::Sender<PatternEvent>,
    ) -> Outcome {
        match (read, code) {
            (true, GetVersion::CODE) => {
                decode::<GetVersion>(data)?;
                Ok(GetVersion::encode_reply(&self.cfg.version))
            }
            (true, GetHardwareStatus::CODE) => {
                decode::<GetHardwareStatus>(data)?;
                Ok(GetHardwareStatus::encode_reply(&HardwareStatus(
                    self.hardware,
                )))
            }
            (true, GetSystemStatus::CODE) => {
                decode::<GetSystemStatus>(data)?;
                Ok(GetSystemStatus::encode_reply(&SystemStatus(0x01)))
            }
            (true, GetMainStatus::CODE) => {
                decode::<GetMainStatus>(data)?;
                let running = if self.running() {
                    MainStatus::SEQUENCER_RUNNING
                } else {
                    0
                };
                Ok(GetMainStatus::encode_reply(&MainStatus(running)))
            }
            (true, GetValidation::CODE) => {
                decode::<GetValidation>(data)?;
                if self.validation_busy_polls > 0 {
                    self.validation_busy_polls -= 1;
                    return Ok(vec![ValidationStatus::BUSY]);
                }
                Ok(GetValidation::encode_reply(&self.validation))
            }
            (true, ReadMailbox::CODE) => {
                decode::<ReadMailbox>(data)?;
                if self.mailbox != Mailbox::PatternLut {
                    return Err(());
                }
                let from = usize::from(self.address);
                let to = usize::from(self.pattern_config.lut_entries).max(from);
                let entries: Option<Vec<LutEntry>> = self.lut[from..to].iter().copied().collect();
                Ok(ReadMailbox::encode_reply(&entries.ok_or(())?))
            }
            (false, SetPowerMode::CODE) => {
                let c = decode::<SetPowerMode>(data)?;
                if c.standby {
                    self.stop();
                }
                self.standby = c.standby;
                ack()
            }
            (false, SetDisplayMode::CODE) => {
                let c = decode::<SetDisplayMode>(data)?;
                self.configure()?;
                self.display_mode = c.0;
                ack()
            }
            (false, SetPatternSource::CODE) => {
                let c = decode::<SetPatternSource>(data)?;
                self.configure()?;
                self.source = c.0;
                ack()
            }
            (false, SetTriggerMode::CODE) => {
                let c = decode::<SetTriggerMode>(data)?;
                self.configure()?;
                self.trigger_mode = c.0;
                ack()
            }
            (false, SetExposure::CODE) => {
                let c = decode::<SetExposure>(data)?;
                self.configure()?;
                self.exposure = c;
                ack()
            }
            (false, SetPatternConfig::CODE) => {
                let c = decode::<SetPatternConfig>(data)?;
                self.configure()?;
                self.pattern_config = c;
                ack()
            }
            (false, SetTrigOut1::CODE) => {
                let c = decode::<SetTrigOut1>(data)?;
                self.configure()?;
                self.trig_out1 = c;
                ack()
            }
            (false, SetTrigOut2::CODE) => {
                let c = decode::<SetTrigOut2>(data)?;
                self.configure()?;
                self.trig_out2 = c;
                ack()
            }
            (false, SetTrigIn1Delay::CODE) => {
                decode::<SetTrigIn1Delay>(data)?;
                self.configure().map(|()| Vec::new())
            }
            (false, SetTrigIn2::CODE) => {
                decode::<SetTrigIn2>(data)?;
                self.configure().map(|()| Vec::new())
            }
            (false, MailboxControl::CODE) => {
                let c = decode::<MailboxControl>(data)?;
                self.mailbox = c.0;
                ack()
            }
            (false, SetMailboxAddress::CODE) => {
                let c = decode::<SetMailboxAddress>(data)?;
                self.address = c.0;
                ack()
            }
            (false, WriteMailbox::CODE) => {
                let c = decode::<WriteMailbox>(data)?;
                let from = usize::from(self.address);
                if self.mailbox != Mailbox::PatternLut || from + c.0.len() > MAX_LUT_ENTRIES {
                    return Err(());
                }
                self.configure()?;
                for (slot, e) in self.lut[from..].iter_mut().zip(&c.0) {
                    *slot = Some(*e);
                }
                self.address = (from + c.0.len()).min(MAX_LUT_ENTRIES - 1) as u8;
                ack()
            }
            (false, StartValidation::CODE) => {
                decode::<StartValidation>(data)?;
                if self.running() {
                    return Err(());
                }
                self.validation = self.validate();
                self.validated = self.validation.ok();
                self.validation_busy_polls = 1;
                ack()
            }
            (false, PatternDisplay::CODE) => match decode::<PatternDisplay>(data)?.0 {
                SequenceAction::Stop | SequenceAction::Pause => {
                    self.stop();
                    ack()
                }
                SequenceAction::Start => {
                    if self.running() {
                        return ack();
                    }
                    if !self.validated || self.standby || self.display_mode != DisplayMode::Pattern
                    {
                        return Err(());
                    }
                    self.hardware &= !0x40;
                    self.runner = Some(self.spawn_sequencer(events.clone()));
                    ack()
                }
            },
            _ => Err(()),
        }
    }

    fn stop(&mut self) {
        if let Some(r) = self.runner.take() {
            r.abort();
        }
    }

    fn entries(&self) -> Vec<Option<LutEntry>> {
        self.lut[..usize::from(self.pattern_config.lut_entries)].to_vec()
    }

    fn frame_period_us(&self) -> u64 {
        let us = 1e6 / self.cfg.vsync_hz;
        if us.is_finite() && us > 0.0 {
            us as u64
        } else {
            0
        }
    }

    /// The programmer's guide's validation bits for the present configuration.
    fn validate(&self) -> ValidationStatus {
        let SetExposure {
            exposure_us,
            period_us,
        } = self.exposure;
        let entries = self.entries();
        let mut bits = 0;
        let too_short = entries
            .iter()
            .flatten()
            .any(|e| min_exposure_us(e.bit_depth).is_some_and(|min| exposure_us < min));
        let frame_overrun = self.trigger_mode == TriggerMode::Vsync
            && u64::from(period_us) * entries.len() as u64 > self.frame_period_us();
        if exposure_us == 0 || exposure_us > period_us || too_short || frame_overrun {
            bits |= ValidationStatus::EXPOSURE_OR_PERIOD_INVALID;
        } else if !exposure_fits_period(exposure_us, period_us) {
            bits |= ValidationStatus::DARK_GAP_TOO_SHORT;
        }
        let bad_pattern = |e: &Option<LutEntry>| match e {
            None => true,
            Some(e) => e.pattern >= patterns_per_image(e.bit_depth),
        };
        if entries.iter().any(bad_pattern) {
            bits |= ValidationStatus::PATTERN_NUMBER_INVALID;
        }
        if entries
            .iter()
            .flatten()
            .any(|e| e.trig_out_prev && e.insert_black)
        {
            bits |= ValidationStatus::TRIG_OUT1_WARNING;
        }
        ValidationStatus(bits)
    }

    /// Shows the LUT: in VSYNC mode each video frame starts the sequence again.
    fn spawn_sequencer(&self, events: broadcast::Sender<PatternEvent>) -> JoinHandle<()> {
        let entries: Vec<LutEntry> = self.entries().into_iter().flatten().collect();
        let period = Duration::from_micros(u64::from(self.exposure.period_us));
        let exposure_us = self.exposure.exposure_us;
        // An unusable rate fails validation, so no sequence starts with it.
        let frame = Duration::try_from_secs_f64(1.0 / self.cfg.vsync_hz).unwrap_or(Duration::MAX);
        let every = u64::from(self.pattern_config.trig_out2_every.max(1));
        let vsync = self.trigger_mode == TriggerMode::Vsync;
        let origin = self.origin;
        tokio::spawn(async move {
            if entries.is_empty() {
                return; // validation never passes without entries; never spin
            }
            let start = Instant::now();
            let mut shown: u64 = 0;
            for f in 0u64.. {
                let frame_start = if vsync {
                    start + frame.saturating_mul(u32::try_from(f).unwrap_or(u32::MAX))
                } else {
                    start + period.saturating_mul(u32::try_from(shown).unwrap_or(u32::MAX))
                };
                for (i, e) in entries.iter().enumerate() {
                    let at = frame_start + period.saturating_mul(i as u32);
                    tokio::time::sleep_until(at).await;
                    let ev = PatternEvent {
                        frame: f,
                        lut_index: i as u8,
                        pattern: e.pattern,
                        bit_depth: e.bit_depth,
                        device_time_us: at.duration_since(origin).as_micros() as u64,
                        exposure_us,
                        trig_out1: true,
                        trig_out2: shown % every == 0,
                    };
                    shown += 1;
                    // No subscriber is fine: the projector runs whether or not anyone watches.
                    let _ = events.send(ev);
                }
            }
        })
    }
}
