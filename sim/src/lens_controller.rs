//! Simulated dioptra lens controller: the firmware's side of dioptra-protocol (PROTOCOL.md)
//! for a lens, over the shared [`LensModel`] in focal-power mode. Its clock runs from its own
//! power-up with a configurable offset and drift, so host-side time synchronisation has
//! something to find.

use std::time::Duration;

use dioptra_core::{Diopters, Timestamp};
use dioptra_protocol::{
    truncated, Capabilities, DeviceInfo, DeviceKind, ErrorCode, Fault, FaultKind, FirmwareVersion,
    LensState, Limits, Message, MAX_APPLY_AHEAD_US, PROTOCOL_VERSION,
};

use crate::lens_model::{LensModel, LensModelConfig};
use crate::protocol_device::ProtocolDevice;
use crate::serve::ByteDevice;

#[derive(Debug, Clone, PartialEq)]
pub struct LensControllerSimConfig {
    pub lens: LensModelConfig,
    pub serial: String,
    pub firmware: (u16, u16, u16),
    /// Device clock at host time zero, µs (devices count from their own power-up).
    pub clock_offset_us: u64,
    /// Device clock rate error, parts per million (positive: device clock runs fast).
    pub drift_ppm: f64,
    /// Margin kept inside the lens's reachable range in the reported `Limits`, diopters, so
    /// the limits still hold as the lens warms and its range moves.
    pub limit_margin_d: f32,
}

impl Default for LensControllerSimConfig {
    fn default() -> Self {
        LensControllerSimConfig {
            lens: LensModelConfig::default(),
            serial: "DLC-SIM-0001".into(),
            firmware: (0, 1, 0),
            clock_offset_us: 5_000_000,
            drift_ppm: 30.0,
            limit_margin_d: 0.3,
        }
    }
}

/// Wakes the serve loop at least this often to move the lens and apply scheduled powers.
const TICK: Duration = Duration::from_millis(1);

/// A simulated lens controller.
#[derive(Debug)]
pub struct LensControllerSim {
    cfg: LensControllerSimConfig,
    lens: LensModel,
    dev: ProtocolDevice,
    /// Host-side model time.
    now: Timestamp,
    /// A scheduled power: (device time, diopters).
    pending: Option<(u64, f32)>,
    limits: Limits,
}

impl LensControllerSim {
    pub fn new(cfg: LensControllerSimConfig) -> Self {
        let mut lens = LensModel::new(cfg.lens);
        let r = lens.power_range();
        let limits = Limits {
            min_power_d: r.min.0 + cfg.limit_margin_d,
            max_power_d: r.max.0 - cfg.limit_margin_d,
            max_current_ma: cfg.lens.max_current_ma,
        };
        lens.set_focal_power(Diopters(
            limits.min_power_d.max(0.0).min(limits.max_power_d),
        ));
        LensControllerSim {
            cfg,
            lens,
            dev: ProtocolDevice::new(),
            now: Timestamp::ZERO,
            pending: None,
            limits,
        }
    }

    pub fn lens(&self) -> &LensModel {
        &self.lens
    }
    pub fn limits(&self) -> Limits {
        self.limits
    }

    pub fn capabilities() -> Capabilities {
        Capabilities::FOCAL_POWER
            .with(Capabilities::SCHEDULED_APPLY)
            .with(Capabilities::TEMPERATURE)
            .with(Capabilities::TIME_SYNC)
    }

    /// Device clock at host model time `t`.
    pub fn device_time_us(&self, t: Timestamp) -> u64 {
        let us = t.as_nanos() as f64 / 1000.0 * (1.0 + self.cfg.drift_ppm * 1e-6);
        self.cfg.clock_offset_us.saturating_add(us.max(0.0) as u64)
    }

    /// Moves the model to `now`, applying a scheduled power at its exact time.
    pub fn advance_to(&mut self, now: Timestamp) {
        if now <= self.now {
            return;
        }
        if let Some((at_us, d)) = self.pending {
            if self.device_time_us(now) >= at_us {
                // Host time of the device instant `at_us`.
                let dev_now = self.device_time_us(self.now);
                let ns = (at_us.saturating_sub(dev_now) as f64 * 1000.0
                    / (1.0 + self.cfg.drift_ppm * 1e-6)) as u64;
                let at = Timestamp(self.now.0.saturating_add(ns)).min(now);
                self.lens.advance(at.saturating_since(self.now));
                self.now = at;
                self.lens.set_focal_power(Diopters(d));
                self.pending = None;
            }
        }
        self.lens.advance(now.saturating_since(self.now));
        self.now = now;
    }

    /// Takes bytes from the host; appends replies and events to `out`.
    pub fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        let now_us = self.device_time_us(self.now);
        for (id, msg) in self.dev.receive(bytes, now_us, out) {
            let reply = self.handle(msg, now_us);
            ProtocolDevice::reply(out, id, &reply);
        }
    }

    fn handle(&mut self, msg: Message, now_us: u64) -> Message {
        match msg {
            Message::Hello { protocol_version }
                if protocol_version == u16::from(PROTOCOL_VERSION) =>
            {
                let (major, minor, patch) = self.cfg.firmware;
                Message::DeviceInfo(DeviceInfo {
                    kind: DeviceKind::Lens,
                    protocol_version: u16::from(PROTOCOL_VERSION),
                    firmware_version: FirmwareVersion {
                        major,
                        minor,
                        patch,
                    },
                    serial: truncated(&self.cfg.serial),
                    capabilities: Self::capabilities(),
                })
            }
            Message::Hello { protocol_version } => Message::error(
                ErrorCode::UnsupportedVersion,
                &format!("device speaks v{PROTOCOL_VERSION}, not v{protocol_version}"),
            ),
            Message::TimeSyncPing { host_time_us } => Message::TimeSyncPong {
                host_time_us,
                device_time_us: now_us,
            },
            Message::SetFocalPower {
                diopters,
                apply_at_us,
            } => self.set_focal_power(diopters, apply_at_us, now_us),
            Message::GetLensState => Message::LensState(LensState {
                power_d: self.lens.power().0,
                current_ma: self.lens.current_ma(),
                temperature_c: self.lens.temperature_c(),
                settled: self.lens.settled(),
                device_time_us: now_us,
            }),
            Message::GetLimits => Message::Limits(self.limits),
            _ => Message::error(ErrorCode::NotSupported, "not a lens request"),
        }
    }

    fn set_focal_power(&mut self, d: f32, apply_at_us: u64, now_us: u64) -> Message {
        if !d.is_finite() || d < self.limits.min_power_d || d > self.limits.max_power_d {
            return Message::error(ErrorCode::OutOfRange, "power outside limits");
        }
        match apply_at_us {
            0 => {
                self.pending = None;
                self.lens.set_focal_power(Diopters(d));
                Message::Ack
            }
            t if t > now_us.saturating_add(MAX_APPLY_AHEAD_US) => {
                Message::error(ErrorCode::OutOfRange, "apply_at_us more than 1 s ahead")
            }
            t if t > now_us => {
                self.pending = Some((t, d));
                Message::Ack
            }
            _ => {
                self.pending = None;
                self.lens.set_focal_power(Diopters(d));
                Message::Fault(Fault {
                    kind: FaultKind::LateApply,
                    frame: 0,
                    plane_index: 0,
                    device_time_us: now_us,
                })
            }
        }
    }
}

pub use crate::serve::serve;

impl ByteDevice for LensControllerSim {
    fn wait(&self, _now: Timestamp) -> Duration {
        TICK
    }
    fn advance_to(&mut self, now: Timestamp, _out: &mut Vec<u8>) {
        LensControllerSim::advance_to(self, now)
    }
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        LensControllerSim::receive(self, bytes, out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_protocol::{encode_frame, FrameDecoder, MAX_FRAME_LEN};

    fn ask(sim: &mut LensControllerSim, id: u16, m: &Message) -> Message {
        let mut wire = [0u8; MAX_FRAME_LEN];
        let n = encode_frame(id, m, &mut wire).unwrap();
        let mut out = Vec::new();
        sim.receive(&wire[..n], &mut out);
        let mut d = FrameDecoder::new();
        let frames: Vec<_> = d.push(&out).map(|f| f.unwrap()).collect();
        assert_eq!(frames.len(), 1);
        assert_eq!(frames[0].request_id, id);
        frames[0].message.clone()
    }

    #[test]
    fn scheduled_apply_happens_at_its_device_time() {
        let mut sim = LensControllerSim::new(LensControllerSimConfig {
            drift_ppm: 0.0,
            ..Default::default()
        });
        let now_us = sim.device_time_us(Timestamp::ZERO);
        let at = now_us + 10_000;
        assert_eq!(
            ask(
                &mut sim,
                1,
                &Message::SetFocalPower {
                    diopters: 2.0,
                    apply_at_us: at
                }
            ),
            Message::Ack
        );
        sim.advance_to(Timestamp::from_millis(9));
        assert!(sim.lens().target_power().0 < 1.0);
        sim.advance_to(Timestamp::from_millis(11));
        assert!((sim.lens().target_power().0 - 2.0).abs() < 1e-4);
        // Late and too-far-ahead requests.
        let late = ask(
            &mut sim,
            2,
            &Message::SetFocalPower {
                diopters: 1.0,
                apply_at_us: 1,
            },
        );
        assert!(matches!(
            late,
            Message::Fault(Fault {
                kind: FaultKind::LateApply,
                ..
            })
        ));
        let far = ask(
            &mut sim,
            3,
            &Message::SetFocalPower {
                diopters: 1.0,
                apply_at_us: u64::MAX,
            },
        );
        assert!(matches!(
            far,
            Message::Error {
                code: ErrorCode::OutOfRange,
                ..
            }
        ));
        let nan = ask(
            &mut sim,
            4,
            &Message::SetFocalPower {
                diopters: f32::NAN,
                apply_at_us: 0,
            },
        );
        assert!(matches!(
            nan,
            Message::Error {
                code: ErrorCode::OutOfRange,
                ..
            }
        ));
    }

    #[test]
    fn state_limits_and_refusals() {
        let mut sim = LensControllerSim::new(LensControllerSimConfig::default());
        let Message::Limits(l) = ask(&mut sim, 1, &Message::GetLimits) else {
            panic!()
        };
        assert!(l.min_power_d < 0.0 && l.max_power_d > 5.0);
        ask(
            &mut sim,
            2,
            &Message::SetFocalPower {
                diopters: 1.5,
                apply_at_us: 0,
            },
        );
        sim.advance_to(Timestamp::from_millis(100));
        let Message::LensState(s) = ask(&mut sim, 3, &Message::GetLensState) else {
            panic!()
        };
        assert!((s.power_d - 1.5).abs() < 0.02 && s.settled);
        assert!(matches!(
            ask(&mut sim, 4, &Message::Start),
            Message::Error {
                code: ErrorCode::NotSupported,
                ..
            }
        ));
        assert!(matches!(
            ask(
                &mut sim,
                5,
                &Message::Hello {
                    protocol_version: 9
                }
            ),
            Message::Error {
                code: ErrorCode::UnsupportedVersion,
                ..
            }
        ));
    }
}
