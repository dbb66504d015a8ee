//! TI DLPC350 (DLP LightCrafter 4500) over USB HID, as a [`PlaneSequencer`].
//!
//! The controller shows one pattern per focal plane and its trigger outputs step the lens
//! (see [`sequence`]). It reports nothing while running, so [`PlaneSequencer::next_event`]
//! yields the sub-frame starts the programmed timing predicts (without lens power), checks
//! the sequencer is still running once per frame, and reports a fault when it stopped.
//!
//! State changes are confirmed as TI's own code confirms them: after Stop the pattern
//! display state is read back (and Stop re-sent) until it says stopped (TI's LightCrafter
//! GUI and the clients derived from it); before programming the power mode is set to normal
//! and the hardware status checked (TI's SDK, `LCr4500::CreateSendStartSequenceLut`); after
//! SetDisplayMode the driver waits 100 ms and reads the mode back, up to 5 more times 100 ms
//! apart (TI's GUI, `SetDLPC350InPatternMode`); after Start it reads the main status and
//! starts once more if the sequencer is not running (pycrafter4500: "idk why you need a
//! second start coming out of video mode").

pub mod protocol;
pub mod sequence;

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{
    Clock, DeviceError, LinkError, PlaneSchedule, PlaneSequencer, SequencerEvent, SequencerFault,
    Timestamp,
};
use dioptra_transport::HidLink;
use tokio::time::Instant;

use protocol::{
    Assembler, Command, Direction, DisplayMode, GetDisplayMode, GetHardwareStatus, GetMainStatus,
    GetPatternDisplay, GetSystemStatus, GetValidation, GetVersion, HardwareStatus, LutEntry,
    Mailbox, MailboxControl, MainStatus, Packet, PatternDisplay, PatternSource, ReadMailbox,
    SequenceAction, SetDisplayMode, SetMailboxAddress, SetPatternSource, SetPowerMode,
    SetTriggerMode, StartValidation, SystemStatus, TriggerMode, ValidationStatus, Version,
    WriteMailbox, REPORT_LEN,
};
pub use sequence::{Dlpc350Config, PatternSequence};

/// Wait for each reply (TI's API waits 2 s; the controller answers in a few ms).
pub const DEFAULT_TIMEOUT: Duration = Duration::from_millis(500);
/// Validation polls and their spacing: validation takes milliseconds.
const VALIDATION_POLLS: u32 = 100;
const VALIDATION_POLL_INTERVAL: Duration = Duration::from_millis(5);
/// [`SequencerFault::Other`] code: the pattern sequencer stopped on its own.
pub const FAULT_SEQUENCER_STOPPED: u16 = 0x1A0C;
/// Wait before reading a state change back, and between further reads (TI's GUI: 100 ms).
pub const STATE_POLL_INTERVAL: Duration = Duration::from_millis(100);
/// Further reads after the first (TI's GUI: `MAX_NUM_RETRIES` 5).
const STATE_RETRIES: u32 = 5;
/// After Start, before the main status is read (TI's SDK: 10 ms).
const START_SETTLE: Duration = Duration::from_millis(10);

/// The three status bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Status {
    pub hardware: HardwareStatus,
    pub system: SystemStatus,
    pub main: MainStatus,
}

struct Run {
    host_start: Timestamp,
    start: Instant,
    next: u64,
    planes: u64,
    period: Duration,
    /// VSYNC period: each frame's patterns start at a VSYNC.
    frame: Duration,
}

/// A DLPC350 on any [`HidLink`].
pub struct Dlpc350<H: HidLink> {
    link: H,
    clock: Arc<dyn Clock>,
    cfg: Dlpc350Config,
    seq: u8,
    timeout: Duration,
    programmed: Option<(PlaneSchedule, PatternSequence)>,
    run: Option<Run>,
}

fn protocol_error(what: &str, e: impl std::fmt::Display) -> DeviceError {
    DeviceError::Protocol(format!("DLPC350 {what}: {e}"))
}

impl<H: HidLink> Dlpc350<H> {
    pub fn new(link: H, clock: Arc<dyn Clock>, cfg: Dlpc350Config) -> Self {
        Dlpc350 {
            link,
            clock,
            cfg,
            seq: 0,
            timeout: DEFAULT_TIMEOUT,
            programmed: None,
            run: None,
        }
    }

    pub fn with_timeout(mut self, timeout: Duration) -> Self {
        self.timeout = timeout;
        self
    }

    /// The link, e.g. to inject raw reports in tests.
    pub fn link_mut(&mut self) -> &mut H {
        &mut self.link
    }

    pub fn config(&self) -> &Dlpc350Config {
        &self.cfg
    }

    /// Sends one command and returns its typed reply. Every command asks for a reply, so a
    /// refusal is [`DeviceError::Refused`] with the command code.
    pub async fn execute<C: Command>(&mut self, cmd: &C) -> Result<C::Reply, DeviceError> {
        let seq = self.seq;
        self.seq = self.seq.wrapping_add(1);
        let packet = Packet::request(C::READ, seq, C::CODE, cmd.encode());
        let reports = packet
            .to_reports()
            .map_err(|e| DeviceError::Invalid(format!("DLPC350 {}: {e}", C::NAME)))?;
        for r in &reports {
            let mut out = [0u8; REPORT_LEN + 1];
            out[1..].copy_from_slice(r);
            self.link.write_output_report(&out).await?;
        }
        let reply = self.read_reply(seq, C::NAME).await?;
        if reply.is_nack() {
            return Err(DeviceError::Refused {
                code: C::CODE,
                detail: format!("DLPC350 refused {} ({:#06x})", C::NAME, C::CODE),
            });
        }
        if C::READ && reply.data.is_empty() {
            return Err(DeviceError::Refused {
                code: C::CODE,
                detail: format!(
                    "DLPC350 sent an empty reply to {} ({:#06x})",
                    C::NAME,
                    C::CODE
                ),
            });
        }
        C::decode_reply(&reply.data).map_err(|e| protocol_error("reply", e))
    }

    /// The reply with sequence `seq`; replies to earlier, timed-out requests are skipped.
    async fn read_reply(&mut self, seq: u8, name: &str) -> Result<Packet, DeviceError> {
        let deadline = Instant::now() + self.timeout;
        let mut asm = Assembler::new(Direction::Reply);
        let mut garbage = None;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let mut buf = [0u8; REPORT_LEN + 1];
            let n = match self.link.read_input_report(&mut buf, left).await {
                Ok(n) => n,
                Err(LinkError::Timeout { .. }) if garbage.is_some() => {
                    return Err(protocol_error(
                        &format!("no valid reply to {name}"),
                        garbage.unwrap_or_default(),
                    ))
                }
                Err(e) => return Err(e.into()),
            };
            match asm.push(buf.get(1..n).unwrap_or_default()) {
                Ok(None) => {}
                Ok(Some(p)) if p.seq == seq => return Ok(p),
                Ok(Some(p)) => tracing::debug!(seq = p.seq, want = seq, "stale DLPC350 reply"),
                Err(e) => garbage = Some(e.to_string()),
            }
        }
    }

    pub async fn version(&mut self) -> Result<Version, DeviceError> {
        self.execute(&GetVersion).await
    }

    pub async fn status(&mut self) -> Result<Status, DeviceError> {
        Ok(Status {
            hardware: self.execute(&GetHardwareStatus).await?,
            system: self.execute(&GetSystemStatus).await?,
            main: self.execute(&GetMainStatus).await?,
        })
    }

    /// Runs the controller's LUT validation; a failed check is a refusal naming it.
    pub async fn validate(&mut self) -> Result<ValidationStatus, DeviceError> {
        self.execute(&StartValidation).await?;
        for _ in 0..VALIDATION_POLLS {
            let v = self.execute(&GetValidation).await?;
            if v.busy() {
                tokio::time::sleep(VALIDATION_POLL_INTERVAL).await;
                continue;
            }
            if !v.ok() {
                return Err(DeviceError::Refused {
                    code: StartValidation::CODE,
                    detail: format!("DLPC350 validation failed: {}", v.problems().join("; ")),
                });
            }
            return Ok(v);
        }
        Err(DeviceError::Protocol(
            "DLPC350 validation did not finish; power-cycle the projector".into(),
        ))
    }

    /// The pattern LUT as the controller holds it.
    pub async fn read_lut(&mut self) -> Result<Vec<LutEntry>, DeviceError> {
        self.execute(&MailboxControl(Mailbox::PatternLut)).await?;
        self.execute(&SetMailboxAddress(0)).await?;
        let read = self.execute(&ReadMailbox).await;
        let close = self.execute(&MailboxControl(Mailbox::Closed)).await;
        let entries = read?;
        close?;
        Ok(entries)
    }

    /// Stops the sequence and reads the state back until the controller says stopped,
    /// re-sending Stop each time it does not.
    async fn stop_confirmed(&mut self) -> Result<(), DeviceError> {
        self.execute(&PatternDisplay(SequenceAction::Stop)).await?;
        for retry in 0..=STATE_RETRIES {
            if self.execute(&GetPatternDisplay).await? == SequenceAction::Stop {
                return Ok(());
            }
            if retry < STATE_RETRIES {
                tokio::time::sleep(STATE_POLL_INTERVAL).await;
                self.execute(&PatternDisplay(SequenceAction::Stop)).await?;
            }
        }
        Err(DeviceError::Refused {
            code: PatternDisplay::CODE,
            detail: "the DLPC350 still shows its pattern sequence after Stop".into(),
        })
    }

    /// Pattern display mode, confirmed by reading it back after TI's wait.
    async fn pattern_mode_confirmed(&mut self) -> Result<(), DeviceError> {
        if self.execute(&GetDisplayMode).await? == DisplayMode::Pattern {
            return Ok(());
        }
        self.execute(&SetDisplayMode(DisplayMode::Pattern)).await?;
        for _ in 0..=STATE_RETRIES {
            tokio::time::sleep(STATE_POLL_INTERVAL).await;
            if self.execute(&GetDisplayMode).await? == DisplayMode::Pattern {
                return Ok(());
            }
        }
        Err(DeviceError::Refused {
            code: SetDisplayMode::CODE,
            detail: "the DLPC350 did not switch to pattern display mode".into(),
        })
    }

    /// Programs `seq` in the order TI documents (stop, power, mode, source, config, trigger,
    /// period, trigger outputs, LUT through the mailbox, validate), reads the LUT back, and
    /// leaves the sequence stopped. Checks the sequence first: an impossible one sends nothing.
    pub async fn program_sequence(&mut self, seq: &PatternSequence) -> Result<(), DeviceError> {
        seq.check()?;
        self.run = None;
        self.stop_confirmed().await?;
        // "Standby mode must be disabled prior to sending any new data."
        self.execute(&SetPowerMode { standby: false }).await?;
        let hw = self.execute(&GetHardwareStatus).await?;
        let fatal = hw.fatal_problems();
        if !fatal.is_empty() {
            return Err(DeviceError::Refused {
                code: GetHardwareStatus::CODE,
                detail: format!(
                    "DLPC350 hardware status {:#04x}: {}",
                    hw.0,
                    fatal.join("; ")
                ),
            });
        }
        self.pattern_mode_confirmed().await?;
        self.execute(&SetPatternSource(PatternSource::VideoPort))
            .await?;
        self.execute(&seq.config).await?;
        self.execute(&SetTriggerMode(TriggerMode::Vsync)).await?;
        self.execute(&seq.exposure).await?;
        self.execute(&seq.trig_out1).await?;
        self.execute(&seq.trig_out2).await?;
        self.execute(&MailboxControl(Mailbox::PatternLut)).await?;
        self.execute(&SetMailboxAddress(0)).await?;
        self.execute(&WriteMailbox(seq.entries.clone())).await?;
        self.execute(&MailboxControl(Mailbox::Closed)).await?;
        let back = self.read_lut().await?;
        // The controller may return more than was written; what was written comes first.
        if back.get(..seq.entries.len()) != Some(&seq.entries[..]) {
            return Err(DeviceError::Protocol(format!(
                "DLPC350 LUT read back differs from what was written: {back:?}"
            )));
        }
        self.validate().await?;
        Ok(())
    }

    /// After an unplug: takes the reopened link and restores the programmed schedule (and
    /// restarts it if it was running).
    pub async fn reconnect(&mut self, link: H) -> Result<(), DeviceError> {
        self.link = link;
        let was_running = self.run.take().is_some();
        if let Some((_, seq)) = self.programmed.clone() {
            self.program_sequence(&seq).await?;
            if was_running {
                self.start().await?;
            }
        }
        Ok(())
    }
}

impl<H: HidLink> PlaneSequencer for Dlpc350<H> {
    async fn program(&mut self, schedule: &PlaneSchedule) -> Result<(), DeviceError> {
        let seq = PatternSequence::for_schedule(schedule, &self.cfg)?;
        self.programmed = None;
        self.program_sequence(&seq).await?;
        self.programmed = Some((schedule.clone(), seq));
        Ok(())
    }

    async fn start(&mut self) -> Result<(), DeviceError> {
        let Some((schedule, seq)) = &self.programmed else {
            return Err(DeviceError::Invalid(
                "no schedule programmed: program one before start".into(),
            ));
        };
        let planes = schedule.planes().len() as u64;
        let period = schedule.subframe_period();
        let frame = seq.frame_period;
        for _ in 0..2 {
            let (host_start, start) = (self.clock.now(), Instant::now());
            self.execute(&PatternDisplay(SequenceAction::Start)).await?;
            tokio::time::sleep(START_SETTLE).await;
            if self.execute(&GetMainStatus).await?.sequencer_running() {
                self.run = Some(Run {
                    host_start,
                    start,
                    next: 0,
                    planes,
                    period,
                    frame,
                });
                return Ok(());
            }
        }
        Err(DeviceError::Refused {
            code: PatternDisplay::CODE,
            detail: "the DLPC350 acknowledged Start twice but its sequencer is not running".into(),
        })
    }

    async fn stop(&mut self) -> Result<(), DeviceError> {
        self.run = None;
        self.stop_confirmed().await
    }

    async fn next_event(&mut self) -> Result<SequencerEvent, DeviceError> {
        let Some(run) = &self.run else {
            return Err(DeviceError::Invalid("the sequence is not running".into()));
        };
        let k = run.next;
        let (frame, plane_index) = (k / run.planes, k % run.planes);
        let offset = run
            .frame
            .saturating_mul(u32::try_from(frame).unwrap_or(u32::MAX))
            .saturating_add(run.period.saturating_mul(plane_index as u32));
        let host_time = run.host_start.saturating_add(offset);
        tokio::time::sleep_until(run.start + offset).await;
        // The wire frame counter wraps, like the sync board's.
        let (frame, plane_index) = (frame as u32, plane_index as u8);
        if k > 0 && plane_index == 0 && !self.execute(&GetMainStatus).await?.sequencer_running() {
            self.run = None;
            return Ok(SequencerEvent::Fault {
                fault: SequencerFault::Other(FAULT_SEQUENCER_STOPPED),
                frame,
                plane_index,
                host_time,
            });
        }
        if let Some(run) = &mut self.run {
            run.next += 1;
        }
        Ok(SequencerEvent::SubframeStart {
            frame,
            plane_index,
            // The controller has no clock to read: its time is the predicted time since start.
            device_time: Timestamp::ZERO.saturating_add(offset),
            host_time,
            lens_power: None,
        })
    }
}
