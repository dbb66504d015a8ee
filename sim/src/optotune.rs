//! Simulated Optotune Lens Driver 4: the device side of its serial protocol, over the shared
//! [`LensModel`]. It stands in for the device, not for dioptra's driver, so it is written
//! from the protocol description (Optotune's manual and its "Lens Driver V4 Communication
//! Protocol" sheet, hardware.md, the open clients) and not from the driver's code, and it
//! accepts what other clients send: `V` with or without a trailing zero byte, `PrTA` with or
//! without its four zero bytes.
//!
//! As the device: it powers up without temperature limits and refuses focal-power mode until
//! it has them (status bit 2); the `Start` handshake resets the output current; replies echo
//! the command without its r/w letter (`MSA` for `MwSA`, `CMA` for `CrMA`); `E` codes are the
//! sheet's; status bits are the sheet's (bit 5, temperature outside the product
//! specification, is not modelled: the specification is not in the sources).
//!
//! [`OptotuneSim`] is sans-IO (bytes in, bytes out, time passed in); [`serve`] runs it on a
//! [`ByteLink`] (a pty master, an in-memory link).

use std::time::Duration;

use dioptra_core::{Diopters, Timestamp};

use crate::lens_model::{DriveMode, LensModel, LensModelConfig};
use crate::serve::ByteDevice;

/// CRC-16/ARC (reflected 0xA001, init 0, no final XOR), as the Lens Driver 4 computes it.
const CRC: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_ARC);

/// `E` reply codes, per Optotune's protocol sheet ("02-Error Commands").
pub mod error_code {
    /// CRC failed. A command with a bad CRC gets `N\r\n` instead (the sheet); unused here.
    pub const CRC_FAILED: u8 = 1;
    /// Not available in this firmware type (here: focal-power commands without
    /// [`super::OptotuneSimConfig::focal_power_control`]).
    pub const NOT_AVAILABLE_IN_FIRMWARE_TYPE: u8 = 2;
    pub const NOT_RECOGNISED: u8 = 3;
    /// The lens is not compatible with the firmware (focal-power commands).
    pub const LENS_INCOMPATIBLE: u8 = 4;
}

/// Status bits of the `Sr` word (byte #1 is the low byte; `PwTA`, `PrTA` and `MwCA` replies
/// carry byte #1), per Optotune's protocol sheet.
pub mod status_bit {
    pub const NOT_ALL_HARDWARE: u32 = 1 << 0;
    pub const NO_EEPROM: u32 = 1 << 1;
    pub const NO_TEMPERATURE_LIMITS: u32 = 1 << 2;
    pub const CANNOT_REACH_FOCAL_POWER: u32 = 1 << 3;
    pub const FOCAL_POWER_INVERSION: u32 = 1 << 4;
    pub const TEMPERATURE_OUTSIDE_SPEC: u32 = 1 << 5;
    pub const FOCAL_POWER_OUTSIDE_GUARANTEED_RANGE: u32 = 1 << 6;
    pub const TEMPERATURE_OUTSIDE_LIMITS: u32 = 1 << 7;
    pub const LENS_INCOMPATIBLE: u32 = 1 << 8;
}

/// The simulated unit.
#[derive(Debug, Clone, PartialEq)]
pub struct OptotuneSimConfig {
    pub lens: LensModelConfig,
    /// Firmware type letter; `A` encodes focal power with a +5 D offset.
    pub firmware_type: u8,
    pub firmware_branch: u8,
    /// major, minor, build, revision
    pub firmware_version: (u8, u8, u16, u16),
    pub part_number: [u8; 3],
    pub serial_number: [u8; 8],
    pub device_id: [u8; 8],
    /// Temperature limits at power-up, (lower, upper) °C. The device has none until a
    /// client sends `PwTA`.
    pub temperature_limits_c: Option<(f32, f32)>,
    /// Quiet time after which an incomplete command is dropped and answered `N`.
    pub idle_gap: Duration,
    /// The firmware type has focal-power control (otherwise its commands answer `E2`).
    pub focal_power_control: bool,
    /// Faults: not all hardware present (bit 0), no or faulty lens EEPROM (bit 1), a lens
    /// the firmware does not support (byte #2 bit 0; focal-power commands answer `E4`).
    pub hardware_complete: bool,
    pub eeprom_ok: bool,
    pub lens_compatible: bool,
}

impl Default for OptotuneSimConfig {
    fn default() -> Self {
        OptotuneSimConfig {
            lens: LensModelConfig::default(),
            firmware_type: b'A',
            firmware_branch: 1,
            firmware_version: (1, 6, 0, 2),
            part_number: *b"LD4",
            serial_number: *b"SIM00001",
            device_id: *b"EL103000",
            temperature_limits_c: None,
            idle_gap: Duration::from_millis(20),
            focal_power_control: true,
            hardware_complete: true,
            eeprom_ok: true,
            lens_compatible: true,
        }
    }
}

/// Mode numbers of `MMA`.
const MODE_CURRENT: u8 = 1;
const MODE_SINUSOIDAL: u8 = 2;
const MODE_TRIANGULAR: u8 = 3;
const MODE_RECTANGULAR: u8 = 4;
const MODE_FOCAL_POWER: u8 = 5;
const MODE_ANALOG: u8 = 6;

/// Command letters and the argument lengths accepted after them (CRC not counted).
const COMMANDS: &[(&[u8], &[usize])] = &[
    (b"H", &[0]),
    (b"F", &[0]),
    (b"J", &[0]),
    (b"V", &[0, 1]),
    (b"X", &[0]),
    (b"IR", &[8]),
    (b"CrMA", &[2]),
    (b"CwMA", &[2]),
    (b"CrUA", &[2]),
    (b"CwUA", &[2]),
    (b"CrLA", &[2]),
    (b"CwLA", &[2]),
    (b"Aw", &[2]),
    (b"Ar", &[2]),
    (b"TCA", &[0]),
    (b"PwTA", &[4]),
    (b"PrTA", &[0, 4]),
    (b"MwDA", &[0]),
    (b"MwCA", &[0]),
    (b"MwSA", &[0]),
    (b"MwTA", &[0]),
    (b"MwQA", &[0]),
    (b"MwAA", &[0]),
    (b"MMA", &[0]),
    (b"PwDA", &[4]),
    (b"PrDA", &[4]),
    (b"Sr", &[0]),
];
const HANDSHAKE: &[u8] = b"Start";

/// A simulated Lens Driver 4 with its lens.
#[derive(Debug, Clone)]
pub struct OptotuneSim {
    cfg: OptotuneSimConfig,
    lens: LensModel,
    rx: Vec<u8>,
    mode: u8,
    /// Maximum output current in 0.01 mA (`CrMA`/`CwMA`).
    max_current_centi_ma: i16,
    /// Software current limits, raw (× 4095 / max).
    upper_raw: i16,
    lower_raw: i16,
    temperature_limits_c: Option<(f32, f32)>,
    /// The focal power last set with `PwDA`, kept in any mode (the sheet: outside focal-power
    /// mode "it will be changed internally however this value will not be used").
    focal_power_target: Option<f32>,
    /// The last focal-power target could not be reached (status bit 3).
    unreachable: bool,
    /// Model time.
    now: Timestamp,
    handshakes: u64,
}

impl OptotuneSim {
    pub fn new(cfg: OptotuneSimConfig) -> Self {
        let max = (cfg.lens.max_current_ma * 100.0)
            .round()
            .clamp(0.0, f32::from(i16::MAX)) as i16;
        OptotuneSim {
            lens: LensModel::new(cfg.lens),
            temperature_limits_c: cfg.temperature_limits_c,
            cfg,
            rx: Vec::new(),
            mode: MODE_CURRENT,
            max_current_centi_ma: max,
            upper_raw: 4095,
            lower_raw: 0,
            focal_power_target: None,
            unreachable: false,
            now: Timestamp::ZERO,
            handshakes: 0,
        }
    }

    pub fn lens(&self) -> &LensModel {
        &self.lens
    }
    pub fn config(&self) -> &OptotuneSimConfig {
        &self.cfg
    }
    /// `Start` handshakes answered so far.
    pub fn handshakes(&self) -> u64 {
        self.handshakes
    }
    /// True while part of a command is waiting for the rest.
    pub fn has_partial_command(&self) -> bool {
        !self.rx.is_empty()
    }

    /// Moves the lens model to time `now` (never backwards).
    pub fn advance_to(&mut self, now: Timestamp) {
        let dt = now.saturating_since(self.now);
        if !dt.is_zero() {
            self.lens.advance(dt);
            self.now = now;
        }
    }

    /// Takes bytes from the host; appends the replies to `out`.
    pub fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        self.rx.extend_from_slice(bytes);
        while !self.rx.is_empty() {
            match self.parse_one(out) {
                Some(used) => {
                    self.rx.drain(..used.min(self.rx.len()));
                }
                None => break,
            }
        }
    }

    /// The host went quiet with a command incomplete: drop it and answer `N`, as a bad CRC.
    pub fn idle_timeout(&mut self, out: &mut Vec<u8>) {
        if !self.rx.is_empty() {
            self.rx.clear();
            out.extend_from_slice(b"N\r\n");
        }
    }

    /// Handles the command at the front of `rx`; returns the bytes it used, or `None` to wait
    /// for more.
    fn parse_one(&mut self, out: &mut Vec<u8>) -> Option<usize> {
        let rx = &self.rx;
        if rx.starts_with(HANDSHAKE) {
            self.handshakes += 1;
            // The handshake "will reset the current to zero" (pyopto, after the manual):
            // modelled as a reset of the drive, the focal-power target included.
            self.mode = MODE_CURRENT;
            self.lens.set_current_ma(0.0);
            self.focal_power_target = None;
            self.unreachable = false;
            out.extend_from_slice(b"Ready\r\n");
            return Some(HANDSHAKE.len());
        }
        let maybe_start = HANDSHAKE.starts_with(rx);
        let spec = COMMANDS.iter().find(|(letters, _)| rx.starts_with(letters));
        let Some(&(letters, arg_lens)) = spec else {
            let partial = maybe_start || COMMANDS.iter().any(|(l, _)| l.starts_with(rx));
            if partial {
                return None;
            }
            // Unknown: answer once and skip to a byte that can start a command.
            reply(out, &[b'E', error_code::NOT_RECOGNISED]);
            let skip = 1 + rx[1..].iter().take_while(|b| !can_start(**b)).count();
            return Some(skip);
        };
        let mut longest = 0;
        for &n in arg_lens {
            let total = letters.len() + n + 2;
            longest = longest.max(total);
            if rx.len() < total {
                continue;
            }
            let body = &rx[..total - 2];
            if CRC.checksum(body) == u16::from_le_bytes([rx[total - 2], rx[total - 1]]) {
                let (letters, args) = body.split_at(letters.len());
                let (letters, args) = (letters.to_vec(), args.to_vec());
                self.execute(&letters, &args, out);
                return Some(total);
            }
        }
        if rx.len() < longest {
            return None;
        }
        out.extend_from_slice(b"N\r\n");
        Some(longest)
    }

    fn scale_power(&self, d: f32) -> i16 {
        let offset = if self.cfg.firmware_type == b'A' {
            5.0
        } else {
            0.0
        };
        ((d + offset) * 200.0)
            .round()
            .clamp(f32::from(i16::MIN), f32::from(i16::MAX)) as i16
    }
    fn unscale_power(&self, raw: i16) -> f32 {
        let offset = if self.cfg.firmware_type == b'A' {
            5.0
        } else {
            0.0
        };
        f32::from(raw) / 200.0 - offset
    }
    fn max_current_ma(&self) -> f32 {
        f32::from(self.max_current_centi_ma) / 100.0
    }
    fn raw_to_ma(&self, raw: i16) -> f32 {
        f32::from(raw) * self.max_current_ma() / 4095.0
    }
    fn ma_to_raw(&self, ma: f32) -> i16 {
        let max = self.max_current_ma();
        if max <= 0.0 {
            return 0;
        }
        (ma * 4095.0 / max)
            .round()
            .clamp(f32::from(i16::MIN), f32::from(i16::MAX)) as i16
    }

    /// Currents the software limits allow (the lens model drives 0..=max only).
    fn current_window_ma(&self) -> (f32, f32) {
        let hw = self
            .max_current_ma()
            .min(self.lens.config().max_current_ma)
            .max(0.0);
        let hi = self.raw_to_ma(self.upper_raw).clamp(0.0, hw);
        let lo = self.raw_to_ma(self.lower_raw).clamp(0.0, hi);
        (lo, hi)
    }

    /// Focal powers that can be held at every temperature within the limits and within the
    /// current window: static power falls with temperature, so the top comes from the upper
    /// temperature limit and the bottom from the lower one. `None` without limits; an
    /// inverted range (min above max) when the limits are too wide for the current window.
    pub fn holdable_range(&self) -> Option<(f32, f32)> {
        let (t_lo, t_hi) = self.temperature_limits_c?;
        let now = self.lens.power_range();
        let cfg = self.lens.config();
        let span_ma = cfg.max_current_ma.max(1e-3);
        let (lo_ma, hi_ma) = self.current_window_ma();
        let at = |ma: f32| now.min.0 + (now.max.0 - now.min.0) * ma / span_ma;
        let t = self.lens.temperature_c();
        let max = at(hi_ma) - cfg.drift_d_per_c * (t_hi - t);
        let min = at(lo_ma) - cfg.drift_d_per_c * (t_lo - t);
        Some((min, max))
    }

    /// Status word (byte #1 low, byte #2 above it) for the present state.
    pub fn status_word(&self) -> u32 {
        use status_bit::*;
        let mut s = 0;
        if !self.cfg.hardware_complete {
            s |= NOT_ALL_HARDWARE;
        }
        if !self.cfg.eeprom_ok {
            s |= NO_EEPROM;
        }
        if !self.cfg.lens_compatible {
            s |= LENS_INCOMPATIBLE;
        }
        let t = self.lens.temperature_c();
        match (self.temperature_limits_c, self.holdable_range()) {
            (Some((lo, hi)), Some((min, max))) => {
                if min > max {
                    s |= FOCAL_POWER_INVERSION;
                }
                if t < lo || t > hi {
                    s |= TEMPERATURE_OUTSIDE_LIMITS;
                }
                // Bit 6 is about the focal power a client asked for (`PwDA`): outside what the
                // limits guarantee, it may drift as the lens warms or cools. Entering focal-
                // power mode without one (the session's first `MwCA`, after the handshake
                // reset the current) raises nothing: an independent client tested on a Lens
                // Driver 4 (elhananby/optotune-lens) refuses any non-zero status byte in the
                // `PwTA` and `MwCA` replies of its connect, which does exactly that.
                if let (MODE_FOCAL_POWER, Some(d)) = (self.mode, self.focal_power_target) {
                    if d < min || d > max {
                        s |= FOCAL_POWER_OUTSIDE_GUARANTEED_RANGE;
                    }
                }
            }
            _ => s |= NO_TEMPERATURE_LIMITS,
        }
        if self.mode == MODE_FOCAL_POWER && self.unreachable {
            s |= CANNOT_REACH_FOCAL_POWER;
        }
        s
    }

    /// `echo` + status byte #1 + max + min focal power (zeros without a range).
    fn range_reply(&self, echo: &[u8], out: &mut Vec<u8>) {
        let (min, max) = self.holdable_range().map_or((0, 0), |(min, max)| {
            (self.scale_power(min), self.scale_power(max))
        });
        let mut p = echo.to_vec();
        p.push(self.status_word() as u8);
        p.extend_from_slice(&max.to_be_bytes());
        p.extend_from_slice(&min.to_be_bytes());
        reply(out, &p);
    }

    /// Focal-power target within the reachable power range and current window.
    fn apply_focal_power(&mut self, d: f32) {
        let now = self.lens.power_range();
        let span_ma = self.lens.config().max_current_ma.max(1e-3);
        let (lo_ma, hi_ma) = self.current_window_ma();
        let at = |ma: f32| now.min.0 + (now.max.0 - now.min.0) * ma / span_ma;
        let target = d.clamp(at(lo_ma), at(hi_ma));
        self.unreachable = target != d;
        self.lens.set_focal_power(Diopters(target));
    }

    /// Why focal-power commands are refused outright, if they are: `E2` or `E4`.
    fn focal_power_refusal(&self) -> Option<u8> {
        if !self.cfg.focal_power_control {
            Some(error_code::NOT_AVAILABLE_IN_FIRMWARE_TYPE)
        } else if !self.cfg.lens_compatible {
            Some(error_code::LENS_INCOMPATIBLE)
        } else {
            None
        }
    }

    fn execute(&mut self, letters: &[u8], args: &[u8], out: &mut Vec<u8>) {
        let arg16 = |i: usize| i16::from_be_bytes([args[i], args[i + 1]]);
        let focal_power_command =
            matches!(letters, b"PwTA" | b"PrTA" | b"MwCA" | b"PwDA" | b"PrDA");
        if focal_power_command {
            if let Some(code) = self.focal_power_refusal() {
                return reply(out, &[b'E', code]);
            }
        }
        match letters {
            b"H" => reply(out, &[b'H', self.cfg.firmware_type]),
            b"F" => reply(out, &[b'F', self.cfg.firmware_branch]),
            b"J" => reply(out, &[&b"J"[..], &self.cfg.part_number].concat()),
            b"V" => {
                let (a, b, c, d) = self.cfg.firmware_version;
                let mut p = vec![b'V', a, b];
                p.extend_from_slice(&c.to_be_bytes());
                p.extend_from_slice(&d.to_be_bytes());
                reply(out, &p);
            }
            b"X" => reply(out, &[&b"X"[..], &self.cfg.serial_number].concat()),
            b"IR" => reply(out, &[&b"IR"[..], &self.cfg.device_id].concat()),
            // Echoes drop the r/w letter: CMA, CUA, CLA (the sheet).
            b"CrMA" => reply(
                out,
                &[&b"CMA"[..], &self.max_current_centi_ma.to_be_bytes()].concat(),
            ),
            b"CwMA" => {
                // The sheet gives no refusal; the driver cannot source more than its hardware.
                let hw = (self.lens.config().max_current_ma * 100.0).round() as i16;
                let v = arg16(0).clamp(1, hw.max(1));
                self.max_current_centi_ma = v;
                reply(out, &[&b"CMA"[..], &v.to_be_bytes()].concat());
            }
            b"CrUA" => reply(out, &[&b"CUA"[..], &self.upper_raw.to_be_bytes()].concat()),
            b"CrLA" => reply(out, &[&b"CLA"[..], &self.lower_raw.to_be_bytes()].concat()),
            b"CwUA" | b"CwLA" => {
                // "Encoded values can only be within the range -4095 to 4095."
                let v = arg16(0).clamp(-4095, 4095);
                if letters[2] == b'U' {
                    self.upper_raw = v;
                } else {
                    self.lower_raw = v;
                }
                self.reapply();
                reply(
                    out,
                    &[&[b'C', letters[2], b'A'][..], &v.to_be_bytes()].concat(),
                );
            }
            b"Aw" => {
                // In focal-power mode the control loop owns the current; the sheet documents
                // no refusal, so the command is taken and has no lasting effect.
                if self.mode == MODE_FOCAL_POWER {
                    return;
                }
                let raw = arg16(0)
                    .clamp(-4095, 4095)
                    .clamp(self.lower_raw, self.upper_raw.max(self.lower_raw));
                let ma = self.raw_to_ma(raw);
                self.lens.set_current_ma(ma);
            }
            b"Ar" => {
                let raw = self.ma_to_raw(self.lens.current_ma());
                reply(out, &[&b"A"[..], &raw.to_be_bytes()].concat());
            }
            b"TCA" => {
                let raw = (self.lens.temperature_c() * 16.0).round() as i16;
                reply(out, &[&b"TCA"[..], &raw.to_be_bytes()].concat());
            }
            b"PwTA" => {
                let hi = f32::from(arg16(0)) / 16.0;
                let lo = f32::from(arg16(2)) / 16.0;
                // The sheet: "The temperature must be between 120 and -120 degrees celsius."
                // An impossible pair is not taken: the old limits (or none) stay.
                if lo < hi && lo >= -120.0 && hi <= 120.0 {
                    self.temperature_limits_c = Some((lo, hi));
                    self.reapply();
                }
                self.range_reply(b"PT", out);
            }
            // The sheet gives PrTA the PwTA reply: PT + status + max + min focal power. (pyopto
            // and uedatatsu read the two temperatures there instead; see the driver.)
            b"PrTA" => self.range_reply(b"PT", out),
            b"MwDA" => {
                if self.mode != MODE_CURRENT {
                    // Keep the present current: switching modes does not move the lens.
                    let ma = self.lens.current_ma();
                    self.lens.set_current_ma(ma);
                    self.mode = MODE_CURRENT;
                }
                reply(out, b"MDA");
            }
            b"MwCA" => {
                // "This command requires temperature limits to be set" and "can only be
                // entered if there is a valid EEPROM": otherwise the status byte says why and
                // the mode stays.
                let refused = self.temperature_limits_c.is_none() || !self.cfg.eeprom_ok;
                if !refused && self.mode != MODE_FOCAL_POWER {
                    let p = self
                        .focal_power_target
                        .unwrap_or(self.lens.target_power().0);
                    self.mode = MODE_FOCAL_POWER;
                    self.apply_focal_power(p);
                }
                self.range_reply(b"MCA", out);
            }
            b"MwSA" | b"MwTA" | b"MwQA" | b"MwAA" => {
                // Signal-generator and analog modes: the mode and its echo, no waveform (the
                // lens holds its current).
                let ma = self.lens.current_ma();
                self.lens.set_current_ma(ma);
                self.mode = match letters[2] {
                    b'S' => MODE_SINUSOIDAL,
                    b'T' => MODE_TRIANGULAR,
                    b'Q' => MODE_RECTANGULAR,
                    _ => MODE_ANALOG,
                };
                reply(out, &[b'M', letters[2], b'A']);
            }
            b"MMA" => reply(out, &[b'M', b'M', b'A', self.mode]),
            b"PwDA" => {
                let d = self.unscale_power(arg16(0));
                self.focal_power_target = Some(d);
                if self.mode == MODE_FOCAL_POWER {
                    self.apply_focal_power(d);
                }
            }
            b"PrDA" => {
                let raw = self.scale_power(self.lens.power().0);
                reply(out, &[&b"PD"[..], &raw.to_be_bytes()].concat());
            }
            b"Sr" => reply(
                out,
                &[&b"S"[..], &self.status_word().to_be_bytes()].concat(),
            ),
            // COMMANDS and this match list the same letters.
            _ => reply(out, &[b'E', error_code::NOT_RECOGNISED]),
        }
    }

    /// Re-applies the drive after a limit changed.
    fn reapply(&mut self) {
        match self.lens.mode() {
            DriveMode::FocalPower(d) if self.mode == MODE_FOCAL_POWER => self.apply_focal_power(d),
            DriveMode::Current(ma) => {
                let (lo, hi) = self.current_window_ma();
                self.lens.set_current_ma(ma.clamp(lo, hi));
            }
            DriveMode::FocalPower(_) => {}
        }
    }
}

/// Could `b` begin a command or the handshake?
fn can_start(b: u8) -> bool {
    b == HANDSHAKE[0] || COMMANDS.iter().any(|(l, _)| l[0] == b)
}

/// Appends payload, CRC (low byte first) and `\r\n`.
fn reply(out: &mut Vec<u8>, payload: &[u8]) {
    out.extend_from_slice(payload);
    out.extend_from_slice(&CRC.checksum(payload).to_le_bytes());
    out.extend_from_slice(b"\r\n");
}

pub use crate::serve::serve;

impl ByteDevice for OptotuneSim {
    fn wait(&self, _now: Timestamp) -> Duration {
        self.cfg.idle_gap
    }
    fn advance_to(&mut self, now: Timestamp, _out: &mut Vec<u8>) {
        OptotuneSim::advance_to(self, now)
    }
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        OptotuneSim::receive(self, bytes, out)
    }
    fn idle(&mut self, out: &mut Vec<u8>) {
        self.idle_timeout(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cmd(body: &[u8]) -> Vec<u8> {
        let mut v = body.to_vec();
        v.extend_from_slice(&CRC.checksum(body).to_le_bytes());
        v
    }

    fn ask(sim: &mut OptotuneSim, bytes: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        sim.receive(bytes, &mut out);
        out
    }

    /// Splits a reply into payload after checking CRC and CRLF.
    fn payload(r: &[u8]) -> &[u8] {
        let (p, t) = r.split_at(r.len() - 4);
        assert_eq!(&t[2..], b"\r\n");
        assert_eq!(u16::from_le_bytes([t[0], t[1]]), CRC.checksum(p), "{r:?}");
        p
    }

    #[test]
    fn handshake_and_identity() {
        let mut sim = OptotuneSim::new(OptotuneSimConfig::default());
        assert_eq!(ask(&mut sim, b"Start"), b"Ready\r\n");
        assert_eq!(payload(&ask(&mut sim, &cmd(b"H"))), b"HA");
        // `V` alone and `V\0` (the opto client's form) both answer 7 payload bytes.
        assert_eq!(
            payload(&ask(&mut sim, &cmd(b"V"))),
            &[b'V', 1, 6, 0, 0, 0, 2]
        );
        assert_eq!(payload(&ask(&mut sim, &cmd(b"V\0"))).len(), 7);
        assert_eq!(payload(&ask(&mut sim, &cmd(b"X"))), b"XSIM00001");
        // The sheet's echo for CrMA is CMA.
        assert_eq!(
            payload(&ask(&mut sim, &cmd(b"CrMA\0\0"))),
            &[b'C', b'M', b'A', 0x72, 0x64]
        );
    }

    #[test]
    fn echoes_drop_the_read_write_letter_as_the_sheet_gives_them() {
        let mut sim = OptotuneSim::new(OptotuneSimConfig::default());
        let echo = |sim: &mut OptotuneSim, body: &[u8], n: usize| {
            payload(&ask(sim, &cmd(body)))[..n].to_vec()
        };
        assert_eq!(echo(&mut sim, b"CwUA\x0f\xff", 3), b"CUA");
        assert_eq!(echo(&mut sim, b"CrLA\0\0", 3), b"CLA");
        assert_eq!(echo(&mut sim, b"MwSA", 3), b"MSA");
        assert_eq!(payload(&ask(&mut sim, &cmd(b"MMA"))), b"MMA\x02");
        assert_eq!(echo(&mut sim, b"MwTA", 3), b"MTA");
        assert_eq!(echo(&mut sim, b"MwQA", 3), b"MQA");
        assert_eq!(echo(&mut sim, b"MwAA", 3), b"MAA");
        assert_eq!(echo(&mut sim, b"MwDA", 3), b"MDA");
        assert_eq!(echo(&mut sim, b"PwTA\x02\x80\x01\x40", 2), b"PT");
        assert_eq!(echo(&mut sim, b"MwCA", 3), b"MCA");
        assert_eq!(echo(&mut sim, b"PrDA\0\0\0\0", 2), b"PD");
        assert_eq!(echo(&mut sim, b"TCA", 3), b"TCA");
        assert_eq!(echo(&mut sim, b"Ar\0\0", 1), b"A");
    }

    #[test]
    fn focal_power_mode_needs_temperature_limits_first() {
        let mut sim = OptotuneSim::new(OptotuneSimConfig::default());
        // Power-up: no limits. MwCA answers with status bit 2 and zero range, and the mode
        // stays current mode.
        let r = payload(&ask(&mut sim, &cmd(b"MwCA"))).to_vec();
        assert_eq!(&r, &[b'M', b'C', b'A', 0x04, 0, 0, 0, 0]);
        assert_eq!(payload(&ask(&mut sim, &cmd(b"MMA"))), b"MMA\x01");
        assert_eq!(
            payload(&ask(&mut sim, &cmd(b"Sr"))),
            &[b'S', 0, 0, 0, status_bit::NO_TEMPERATURE_LIMITS as u8]
        );
        // Limits 20..40 °C, then focal-power mode works.
        let r = payload(&ask(&mut sim, &cmd(b"PwTA\x02\x80\x01\x40"))).to_vec();
        assert_eq!(r[2], 0, "{r:?}");
        let r = payload(&ask(&mut sim, &cmd(b"MwCA"))).to_vec();
        // Entering focal-power mode raises nothing: no focal power was asked for yet (the
        // lens holds its zero-current -2 D, below the -1.9 D that 20 °C guarantees).
        assert_eq!(r[3], 0, "{r:?}");
        assert_eq!(payload(&ask(&mut sim, &cmd(b"MMA"))), b"MMA\x05");
        assert_eq!(payload(&ask(&mut sim, &cmd(b"Sr"))), b"S\0\0\0\0");
        // Limits too wide for the current window (upper current limit raw 512 = 36.6 mA): the
        // holdable range inverts (bit 4).
        ask(&mut sim, &cmd(b"CwUA\x02\x00"));
        let r = payload(&ask(&mut sim, &cmd(b"PwTA\x07\x80\xfe\x20"))).to_vec(); // 120, -30 °C
        assert_eq!(
            r[2] & status_bit::FOCAL_POWER_INVERSION as u8,
            0x10,
            "{r:?}"
        );
    }

    #[test]
    fn the_guaranteed_range_bit_follows_the_power_asked_for_not_the_connect() {
        let mut sim = OptotuneSim::new(OptotuneSimConfig::default());
        // What a client does at connect: handshake, limits 20..40 °C, focal-power mode.
        let connect = |sim: &mut OptotuneSim| {
            assert_eq!(ask(sim, b"Start"), b"Ready\r\n");
            let pt = payload(&ask(sim, &cmd(b"PwTA\x02\x80\x01\x40"))).to_vec();
            let mca = payload(&ask(sim, &cmd(b"MwCA"))).to_vec();
            let sr = payload(&ask(sim, &cmd(b"Sr"))).to_vec();
            (pt[2], mca[3], sr[4])
        };
        let sr = |sim: &mut OptotuneSim| payload(&ask(sim, &cmd(b"Sr")))[4];
        // Firmware type A: raw = (D + 5) x 200.
        let set = |sim: &mut OptotuneSim, d: f32| {
            let raw = ((d + 5.0) * 200.0).round() as i16;
            let mut body = b"PwDA".to_vec();
            body.extend_from_slice(&raw.to_be_bytes());
            body.extend_from_slice(&[0, 0]);
            assert!(ask(sim, &cmd(&body)).is_empty());
        };
        let bit6 = status_bit::FOCAL_POWER_OUTSIDE_GUARANTEED_RANGE as u8;
        // The guaranteed range at 25 °C for 20..40 °C: -2 + 0.02 x 5 = -1.9 D up to
        // -2 + 0.03 x 292.84 - 0.02 x 15 = 6.49 D (the lens model's defaults).
        let (min, max) = sim_range(&mut sim);
        assert!(
            (min + 1.9).abs() < 1e-3 && (max - 6.485).abs() < 1e-2,
            "{min} {max}"
        );
        for d in [0.0, 0.5, 1.0] {
            assert_eq!(connect(&mut sim), (0, 0, 0), "connect before {d} D");
            set(&mut sim, d);
            assert_eq!(sr(&mut sim), 0, "{d} D is within the guaranteed range");
        }
        // Asked for outside the range, either side: bit 6, until a power inside it.
        for d in [6.6, -1.95] {
            set(&mut sim, d);
            assert_eq!(sr(&mut sim), bit6, "{d} D");
        }
        set(&mut sim, 1.0);
        assert_eq!(sr(&mut sim), 0);
        // A new session's handshake clears the request with the current.
        set(&mut sim, 6.6);
        assert_eq!(connect(&mut sim), (0, 0, 0));
    }

    /// The range the simulated unit reports for its temperature limits, D.
    fn sim_range(sim: &mut OptotuneSim) -> (f32, f32) {
        sim.temperature_limits_c = Some((20.0, 40.0));
        let r = sim.holdable_range().unwrap();
        sim.temperature_limits_c = None;
        r
    }

    #[test]
    fn faults_show_in_the_status_word_and_refuse_as_the_sheet_says() {
        let mut sim = OptotuneSim::new(OptotuneSimConfig {
            lens_compatible: false,
            eeprom_ok: false,
            temperature_limits_c: Some((20.0, 40.0)),
            ..OptotuneSimConfig::default()
        });
        let s = payload(&ask(&mut sim, &cmd(b"Sr"))).to_vec();
        assert_eq!(s, vec![b'S', 0, 0, 0x01, 0x02]);
        assert_eq!(
            payload(&ask(&mut sim, &cmd(b"MwCA"))),
            &[b'E', error_code::LENS_INCOMPATIBLE]
        );
        let mut sim = OptotuneSim::new(OptotuneSimConfig {
            focal_power_control: false,
            ..OptotuneSimConfig::default()
        });
        assert_eq!(
            payload(&ask(&mut sim, &cmd(b"PwDA\x05\x14\0\0"))),
            &[b'E', error_code::NOT_AVAILABLE_IN_FIRMWARE_TYPE]
        );
    }

    #[test]
    fn bad_crc_unknown_commands_and_incomplete_ones() {
        let mut sim = OptotuneSim::new(OptotuneSimConfig::default());
        let mut bad = cmd(b"MMA");
        bad[3] ^= 1;
        assert_eq!(ask(&mut sim, &bad), b"N\r\n");
        assert_eq!(
            payload(&ask(&mut sim, b"zzz")),
            &[b'E', error_code::NOT_RECOGNISED]
        );
        // PwDA in current mode is kept, not refused, and does not move the lens.
        assert!(ask(&mut sim, &cmd(b"PwDA\x05\x14\0\0")).is_empty());
        assert_eq!(sim.lens().mode(), DriveMode::Current(0.0));
        // Incomplete command: nothing until the idle gap, then N.
        assert!(ask(&mut sim, b"MM").is_empty());
        let mut out = Vec::new();
        sim.idle_timeout(&mut out);
        assert_eq!(out, b"N\r\n");
        assert!(!sim.has_partial_command());
    }

    #[test]
    fn focal_power_mode_moves_the_lens_and_start_resets_the_current() {
        let mut sim = OptotuneSim::new(OptotuneSimConfig::default());
        ask(&mut sim, &cmd(b"PwTA\x02\x80\x01\x40"));
        let r = ask(&mut sim, &cmd(b"MwCA"));
        assert_eq!(payload(&r).len(), 8);
        assert!(ask(&mut sim, &cmd(b"PwDA\x05\x14\0\0")).is_empty()); // 1.5 D, type A
        sim.advance_to(Timestamp::from_millis(100));
        let power = |sim: &mut OptotuneSim| {
            let p = payload(&ask(sim, &cmd(b"PrDA\0\0\0\0"))).to_vec();
            f32::from(i16::from_be_bytes([p[2], p[3]])) / 200.0 - 5.0
        };
        assert!((power(&mut sim) - 1.5).abs() < 0.01);
        assert_eq!(payload(&ask(&mut sim, &cmd(b"MMA"))), b"MMA\x05");
        // A new session's handshake: zero current, current mode; the lens relaxes.
        assert_eq!(ask(&mut sim, b"Start"), b"Ready\r\n");
        assert_eq!(payload(&ask(&mut sim, &cmd(b"MMA"))), b"MMA\x01");
        sim.advance_to(Timestamp::from_millis(200));
        assert!((power(&mut sim) + 2.0).abs() < 0.01);
    }

    #[test]
    fn any_bytes_never_panic() {
        let mut sim = OptotuneSim::new(OptotuneSimConfig::default());
        let mut x = 0x1234_5678u32;
        let mut out = Vec::new();
        for _ in 0..20_000 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            let b = [x as u8, (x >> 8) as u8, b"PwDACrMA"[(x >> 16) as usize % 8]];
            sim.receive(&b[..1 + (x >> 24) as usize % 3], &mut out);
            if x.is_multiple_of(7) {
                sim.idle_timeout(&mut out);
            }
        }
    }
}
