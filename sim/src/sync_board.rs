//! Simulated dioptra multifocal sync board: the firmware's side of dioptra-protocol
//! (PROTOCOL.md) with a display model and the shared [`LensModel`].
//!
//! The display sends a vsync pulse every sub-frame (its refresh, with jitter; a pulse can be
//! dropped); the schedule's trigger polarity picks its rising or falling edge. At each edge while a schedule runs the board starts sub-frame `s`, plane
//! `s % planes`, and commands the lens to that plane's power. When the settle allowance runs
//! out (the first lit instant of the sub-frame) it measures the lens and sends a
//! `SubframeEvent` stamped with the edge's device time; a lens still off target by more than
//! [`SETTLED_TOLERANCE_D`] is a `LateSettle` fault. PROTOCOL.md says the power is measured "at
//! the subframe's start"; a lens commanded at the edge has not moved yet then, so this board
//! measures where the question "did it settle in time" is answered. An edge that does not come
//! within 1.5 sub-frame periods is a `MissedVsync` fault, and that sub-frame is skipped.
//!
//! Its photodiode input ([`SyncBoardSim::with_light`]: the light of a simulated panel's
//! marker patch, or a script) runs through a [`Comparator`] with the band the host configures
//! (`PhotodiodeConfig`); while enabled, each crossing is a `PhotodiodeEdge` stamped with the
//! crossing's device time. Without a light attached the input sees darkness. At most
//! [`SyncBoardSimConfig::photodiode_queue`] edges go out per step of the board's loop; the rest
//! are dropped and counted, as a board whose queue overflows does.
//!
//! Sans-IO like the other simulators: bytes in, bytes out, host time passed in; [`serve`]
//! runs it on a link with a clock (wall time on a pty, tokio's paused clock in tests).

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{Diopters, Timestamp};
use dioptra_protocol::{
    truncated, Capabilities, DeviceInfo, DeviceKind, ErrorCode, Fault, FaultKind, FirmwareVersion,
    Message, PhotodiodeEdge, PlaneSchedule, SubframeEvent, PROTOCOL_VERSION,
};

use crate::lens_model::{LensModel, LensModelConfig, SETTLED_TOLERANCE_D};
use crate::light::{Comparator, LightSource};
use crate::protocol_device::ProtocolDevice;
use crate::serve::ByteDevice;

#[derive(Debug, Clone, PartialEq)]
pub struct SyncBoardSimConfig {
    pub lens: LensModelConfig,
    /// Display refresh, Hz; `None` follows the loaded schedule's sub-frame rate.
    pub display_hz: Option<f64>,
    /// Each vsync edge lands uniformly within ± this of its nominal time, µs.
    pub jitter_us: f64,
    /// Width of the vsync pulse, µs: a schedule triggered on the falling edge starts its
    /// sub-frames this much after one triggered on the rising edge.
    pub vsync_pulse_us: f64,
    /// Chance that the display drops a vsync edge.
    pub missed_vsync_probability: f64,
    /// Seed of the jitter and dropped-edge generator.
    pub seed: u64,
    pub serial: String,
    /// Device clock at host time zero, µs.
    pub clock_offset_us: u64,
    /// Device clock rate error, parts per million.
    pub drift_ppm: f64,
    /// The photodiode's response (sensor and amplifier delay), µs.
    pub photodiode_response_us: u64,
    /// Photodiode edges the board sends per step of its loop; more are dropped (and counted).
    pub photodiode_queue: usize,
}

impl Default for SyncBoardSimConfig {
    fn default() -> Self {
        SyncBoardSimConfig {
            lens: LensModelConfig::default(),
            display_hz: None,
            jitter_us: 20.0,
            vsync_pulse_us: 20.0,
            missed_vsync_probability: 0.0,
            seed: 1,
            serial: "DSB-SIM-0001".into(),
            clock_offset_us: 7_000_000,
            drift_ppm: -20.0,
            photodiode_response_us: 5,
            photodiode_queue: 64,
        }
    }
}

/// The board while a schedule runs; times are host nanoseconds.
#[derive(Debug, Clone)]
struct Run {
    /// Sub-frames started (or missed) so far.
    subframe: u64,
    next_edge_ns: u64,
    /// The sub-frame whose lens power is still to be measured: (measure at, edge, sub-frame, target).
    pending: Option<(u64, u64, u64, f32)>,
}

/// A simulated sync board.
pub struct SyncBoardSim {
    cfg: SyncBoardSimConfig,
    lens: LensModel,
    dev: ProtocolDevice,
    /// Host time the lens model has reached.
    now: Timestamp,
    schedule: Option<PlaneSchedule>,
    run: Option<Run>,
    rng: u64,
    light: Option<Arc<dyn LightSource>>,
    comparator: Comparator,
    /// The edge counter while the photodiode input is enabled.
    photodiode: Option<u32>,
    edges_dropped: u64,
}

impl std::fmt::Debug for SyncBoardSim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SyncBoardSim")
            .field("cfg", &self.cfg)
            .field("now", &self.now)
            .field("running", &self.run.is_some())
            .field("photodiode", &self.photodiode)
            .finish_non_exhaustive()
    }
}

impl SyncBoardSim {
    pub fn new(cfg: SyncBoardSimConfig) -> Self {
        let lens = LensModel::new(cfg.lens);
        let rng = cfg.seed | 1;
        let comparator =
            Comparator::new(0.5, 0.0, Duration::from_micros(cfg.photodiode_response_us));
        SyncBoardSim {
            cfg,
            lens,
            dev: ProtocolDevice::new(),
            now: Timestamp::ZERO,
            schedule: None,
            run: None,
            rng,
            light: None,
            comparator,
            photodiode: None,
            edges_dropped: 0,
        }
    }

    /// Connects `light` to the photodiode input.
    pub fn with_light(mut self, light: Arc<dyn LightSource>) -> Self {
        self.light = Some(light);
        self
    }

    /// Photodiode edges the board could not send (its queue overflowed).
    pub fn photodiode_edges_dropped(&self) -> u64 {
        self.edges_dropped
    }

    pub fn lens(&self) -> &LensModel {
        &self.lens
    }

    pub fn running(&self) -> bool {
        self.run.is_some()
    }

    pub fn schedule(&self) -> Option<&PlaneSchedule> {
        self.schedule.as_ref()
    }

    /// The device clock at host time `t`.
    pub fn device_time_us(&self, t: Timestamp) -> u64 {
        let us = t.as_nanos() as f64 / 1000.0 * (1.0 + self.cfg.drift_ppm * 1e-6);
        self.cfg.clock_offset_us.saturating_add(us.max(0.0) as u64)
    }

    /// Host time of the running schedule's next sub-frame work.
    fn run_due(&self) -> Option<Timestamp> {
        let run = self.run.as_ref()?;
        let edge = run.next_edge_ns;
        Some(Timestamp(run.pending.map_or(edge, |(m, ..)| m.min(edge))))
    }

    /// Host time of the next thing the board will do by itself: sub-frame work while
    /// running, a change of the light on its photodiode.
    pub fn next_due(&self) -> Option<Timestamp> {
        let light = self
            .light
            .as_deref()
            .and_then(|l| self.comparator.next_due(l));
        match (self.run_due(), light) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Takes the host's bytes received at host time `now` (after [`Self::advance_to`]).
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
                Message::DeviceInfo(DeviceInfo {
                    kind: DeviceKind::SyncBoard,
                    protocol_version: u16::from(PROTOCOL_VERSION),
                    firmware_version: FirmwareVersion {
                        major: 0,
                        minor: 1,
                        patch: 0,
                    },
                    serial: truncated(&self.cfg.serial),
                    capabilities: Capabilities::PLANE_SCHEDULE
                        .with(Capabilities::TIME_SYNC)
                        .with(Capabilities::PHOTODIODE),
                })
            }
            Message::Hello { .. } => Message::error(
                ErrorCode::UnsupportedVersion,
                &format!("device speaks v{PROTOCOL_VERSION}"),
            ),
            Message::TimeSyncPing { host_time_us } => Message::TimeSyncPong {
                host_time_us,
                device_time_us: now_us,
            },
            Message::PlaneSchedule(s) => {
                if self.run.is_some() {
                    return Message::error(ErrorCode::Busy, "stop first");
                }
                if let Err(e) = s.validate() {
                    return Message::error(ErrorCode::InvalidSchedule, &e.to_string());
                }
                let range = self.lens.power_range();
                if let Some(p) = s
                    .plane_powers_d
                    .iter()
                    .find(|p| !range.contains(Diopters(**p)))
                {
                    return Message::error(
                        ErrorCode::OutOfRange,
                        &format!("{p} D outside {:.2}..{:.2}", range.min.0, range.max.0),
                    );
                }
                self.schedule = Some(s);
                Message::Ack
            }
            Message::Start => match &self.schedule {
                None => Message::error(ErrorCode::NotConfigured, "no schedule loaded"),
                Some(_) if self.run.is_some() => Message::Ack,
                Some(s) => {
                    // From the next vsync edge: one display period from now, plus the pulse
                    // width when the schedule triggers on the falling edge.
                    let pulse_ns = if s.trigger_rising {
                        0
                    } else {
                        (self.cfg.vsync_pulse_us.max(0.0) * 1000.0) as u64
                    };
                    let first = self.now.as_nanos() + self.edge_interval_ns() + pulse_ns;
                    let first_plane = s.plane_powers_d.first().copied();
                    self.run = Some(Run {
                        subframe: 0,
                        next_edge_ns: first,
                        pending: None,
                    });
                    // The lens goes to the first plane at once (PROTOCOL.md, Start), so the
                    // first subframe does not find it wherever the last run left it.
                    if let Some(p) = first_plane {
                        let now = self.now.as_nanos();
                        self.move_lens_to(now);
                        self.lens.set_focal_power(Diopters(p));
                    }
                    Message::Ack
                }
            },
            Message::Stop => {
                self.run = None;
                Message::Ack
            }
            Message::PhotodiodeConfig(c) => {
                if let Err(e) = c.validate() {
                    return Message::error(ErrorCode::OutOfRange, &e.to_string());
                }
                // Levels the host has not seen yet belong to the old config: take them now.
                self.sense_light(self.now, &mut Vec::new());
                let scale = f32::from(u16::MAX);
                self.comparator.set_band(
                    f32::from(c.threshold) / scale,
                    f32::from(c.hysteresis) / scale,
                );
                self.photodiode = c.enabled.then_some(0);
                Message::Ack
            }
            _ => Message::error(ErrorCode::NotSupported, "not a sync board request"),
        }
    }

    /// Nominal time between display vsync edges, ns.
    fn edge_interval_ns(&self) -> u64 {
        let period_us = self
            .schedule
            .as_ref()
            .map_or(4_166.0, |s| f64::from(s.subframe_period_us));
        let ns = match self.cfg.display_hz {
            Some(hz) if hz.is_finite() && hz > 0.0 => 1e9 / hz,
            _ => period_us * 1000.0,
        };
        ns.max(1000.0) as u64
    }

    /// Uniform in [0, 1), xorshift64*: deterministic for a seed.
    fn random(&mut self) -> f64 {
        self.rng ^= self.rng >> 12;
        self.rng ^= self.rng << 25;
        self.rng ^= self.rng >> 27;
        (self.rng.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// The next edge after one at `edge_ns`, with jitter.
    fn next_edge_after(&mut self, edge_ns: u64) -> u64 {
        let jitter = (self.random() * 2.0 - 1.0) * self.cfg.jitter_us * 1000.0;
        let next = edge_ns as f64 + self.edge_interval_ns() as f64 + jitter;
        (next.max(edge_ns as f64 + 1.0)) as u64
    }

    fn move_lens_to(&mut self, t_ns: u64) {
        if t_ns > self.now.as_nanos() {
            self.lens
                .advance(Duration::from_nanos(t_ns - self.now.as_nanos()));
            self.now = Timestamp(t_ns);
        }
    }

    /// Runs the photodiode's comparator up to host time `now`; while the input is enabled,
    /// its crossings go to `out` as edges (up to the queue's size).
    fn sense_light(&mut self, now: Timestamp, out: &mut Vec<u8>) {
        let Some(light) = self.light.clone() else {
            return;
        };
        let crossings = self.comparator.sense(light.as_ref(), now);
        let Some(mut counter) = self.photodiode else {
            return;
        };
        for (i, c) in crossings.iter().enumerate() {
            let edge = counter;
            counter = counter.wrapping_add(1);
            if i >= self.cfg.photodiode_queue {
                self.edges_dropped += 1;
                continue;
            }
            let device_time_us = self.device_time_us(c.at);
            ProtocolDevice::event(
                out,
                &Message::PhotodiodeEdge(PhotodiodeEdge {
                    edge,
                    device_time_us,
                    rising: c.rising,
                    level: (c.level.clamp(0.0, 1.0) * f32::from(u16::MAX)).round() as u16,
                }),
            );
        }
        self.photodiode = Some(counter);
    }

    /// Runs the display and the lens up to host time `now`, appending events to `out`.
    pub fn advance_to(&mut self, now: Timestamp, out: &mut Vec<u8>) {
        self.sense_light(now, out);
        while let (Some(due), Some(schedule)) = (self.run_due(), self.schedule.clone()) {
            if due > now {
                break;
            }
            let Some(mut run) = self.run.take() else {
                break;
            };
            let n = schedule.plane_powers_d.len().max(1) as u64;
            match run.pending {
                Some((measure_ns, edge_ns, s, target)) if measure_ns <= run.next_edge_ns => {
                    self.move_lens_to(measure_ns);
                    let power = self.lens.power().0;
                    let (frame, plane_index) = ((s / n) as u32, (s % n) as u8);
                    let device_time_us = self.device_time_us(Timestamp(edge_ns));
                    ProtocolDevice::event(
                        out,
                        &Message::SubframeEvent(SubframeEvent {
                            frame,
                            plane_index,
                            device_time_us,
                            lens_power_d: power,
                        }),
                    );
                    if (power - target).abs() > SETTLED_TOLERANCE_D {
                        ProtocolDevice::event(
                            out,
                            &Message::Fault(Fault {
                                kind: FaultKind::LateSettle,
                                frame,
                                plane_index,
                                device_time_us: self.device_time_us(Timestamp(measure_ns)),
                            }),
                        );
                    }
                    run.pending = None;
                }
                _ => {
                    let edge = run.next_edge_ns;
                    let s = run.subframe;
                    run.subframe += 1;
                    run.next_edge_ns = self.next_edge_after(edge);
                    let (frame, plane_index) = ((s / n) as u32, (s % n) as u8);
                    if self.random() < self.cfg.missed_vsync_probability {
                        // Seen once the edge is half a period overdue.
                        let seen = edge + self.edge_interval_ns() / 2;
                        self.move_lens_to(seen);
                        ProtocolDevice::event(
                            out,
                            &Message::Fault(Fault {
                                kind: FaultKind::MissedVsync,
                                frame,
                                plane_index,
                                device_time_us: self.device_time_us(Timestamp(seen)),
                            }),
                        );
                    } else {
                        self.move_lens_to(edge);
                        let target = schedule.plane_powers_d[(s % n) as usize];
                        self.lens.set_focal_power(Diopters(target));
                        let measure = edge + u64::from(schedule.settle_allowance_us) * 1000;
                        run.pending = Some((measure, edge, s, target));
                    }
                }
            }
            self.run = Some(run);
        }
        self.move_lens_to(now.as_nanos());
    }
}

pub use crate::serve::serve;

impl ByteDevice for SyncBoardSim {
    /// Wake for the board's next sub-frame work, or every few ms to let the lens move.
    fn wait(&self, now: Timestamp) -> Duration {
        self.next_due().map_or(Duration::from_millis(5), |due| {
            due.saturating_since(now)
                .clamp(Duration::from_micros(50), Duration::from_millis(5))
        })
    }
    fn advance_to(&mut self, now: Timestamp, out: &mut Vec<u8>) {
        SyncBoardSim::advance_to(self, now, out)
    }
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        SyncBoardSim::receive(self, bytes, out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_protocol::{encode_frame, FrameDecoder, MAX_FRAME_LEN};

    fn send(sim: &mut SyncBoardSim, id: u16, m: &Message) -> Vec<(u16, Message)> {
        let mut wire = [0u8; MAX_FRAME_LEN];
        let n = encode_frame(id, m, &mut wire).unwrap();
        let mut out = Vec::new();
        sim.receive(&wire[..n], &mut out);
        frames(&out)
    }

    fn frames(bytes: &[u8]) -> Vec<(u16, Message)> {
        FrameDecoder::new()
            .push(bytes)
            .map(|f| f.map(|f| (f.request_id, f.message)).unwrap())
            .collect()
    }

    fn schedule(period_us: u32, settle_us: u32) -> Message {
        Message::PlaneSchedule(
            PlaneSchedule::new(&[0.2, 0.8, 1.4, 2.0], period_us, settle_us, true).unwrap(),
        )
    }

    fn quiet(lens: LensModelConfig) -> SyncBoardSimConfig {
        SyncBoardSimConfig {
            lens,
            jitter_us: 0.0,
            drift_ppm: 0.0,
            clock_offset_us: 0,
            ..Default::default()
        }
    }

    /// Runs the board for `ms` in 100 µs steps; returns its events.
    fn run_for(sim: &mut SyncBoardSim, from: Timestamp, ms: u64) -> Vec<Message> {
        let mut out = Vec::new();
        for i in 1..=ms * 10 {
            sim.advance_to(from + Duration::from_micros(i * 100), &mut out);
        }
        frames(&out)
            .into_iter()
            .map(|(id, m)| {
                assert_eq!(id, 0);
                m
            })
            .collect()
    }

    #[test]
    fn requests_and_refusals() {
        let mut sim = SyncBoardSim::new(SyncBoardSimConfig::default());
        let r = send(&mut sim, 1, &Message::Start);
        assert!(matches!(
            r[..],
            [(
                1,
                Message::Error {
                    code: ErrorCode::NotConfigured,
                    ..
                }
            )]
        ));
        let mut bad = PlaneSchedule::new(&[1.0], 100, 50, true).unwrap();
        bad.settle_allowance_us = 100;
        let bad = Message::PlaneSchedule(bad);
        assert!(matches!(
            send(&mut sim, 2, &bad)[..],
            [(
                2,
                Message::Error {
                    code: ErrorCode::InvalidSchedule,
                    ..
                }
            )]
        ));
        let far = Message::PlaneSchedule(PlaneSchedule::new(&[40.0], 4000, 1000, true).unwrap());
        assert!(matches!(
            send(&mut sim, 3, &far)[..],
            [(
                3,
                Message::Error {
                    code: ErrorCode::OutOfRange,
                    ..
                }
            )]
        ));
        assert_eq!(
            send(&mut sim, 4, &schedule(4166, 1000)),
            vec![(4, Message::Ack)]
        );
        assert_eq!(send(&mut sim, 5, &Message::Start), vec![(5, Message::Ack)]);
        assert!(matches!(
            send(&mut sim, 6, &schedule(4166, 1000))[..],
            [(
                6,
                Message::Error {
                    code: ErrorCode::Busy,
                    ..
                }
            )]
        ));
        assert!(matches!(
            send(&mut sim, 7, &Message::GetLimits)[..],
            [(
                7,
                Message::Error {
                    code: ErrorCode::NotSupported,
                    ..
                }
            )]
        ));
        assert_eq!(send(&mut sim, 8, &Message::Stop), vec![(8, Message::Ack)]);
        assert!(!sim.running());
    }

    #[test]
    fn start_moves_the_lens_to_the_first_plane_so_no_subframe_is_off() {
        // The rig's schedule: 240 Hz, a quarter of it dark; a 0.8 ms lens starting at its
        // zero-current power (-2 D), outside every plane.
        let lens = LensModelConfig {
            settle_time: Duration::from_micros(800),
            ..Default::default()
        };
        let mut sim = SyncBoardSim::new(quiet(lens));
        assert!(sim.lens().power().0 < -1.0);
        send(&mut sim, 1, &schedule(4166, 1041));
        send(&mut sim, 2, &Message::Start);
        // Before the first vsync edge the lens is already at the first plane.
        let early = run_for(&mut sim, Timestamp::ZERO, 4);
        assert!(early.is_empty(), "{early:?}");
        assert!(
            (sim.lens().power().0 - 0.2).abs() < 0.02,
            "{:?}",
            sim.lens().power()
        );
        let events = run_for(&mut sim, Timestamp::ZERO + Duration::from_millis(4), 100);
        let mut n = 0;
        for m in &events {
            match m {
                Message::SubframeEvent(e) => {
                    let want = [0.2, 0.8, 1.4, 2.0][e.plane_index as usize];
                    assert!((e.lens_power_d - want).abs() < 0.02, "{e:?}");
                    n += 1;
                }
                other => panic!("{other:?}"),
            }
        }
        assert!(n >= 20, "{n} subframes");
    }

    #[test]
    fn a_fast_lens_reaches_every_plane_and_a_slow_one_settles_late() {
        let fast = LensModelConfig {
            settle_time: Duration::from_micros(800),
            ..Default::default()
        };
        let mut sim = SyncBoardSim::new(quiet(fast));
        send(&mut sim, 1, &schedule(4166, 1500));
        send(&mut sim, 2, &Message::Start);
        let events = run_for(&mut sim, Timestamp::ZERO, 40);
        let subframes: Vec<SubframeEvent> = events
            .iter()
            .filter_map(|m| match m {
                Message::SubframeEvent(e) => Some(*e),
                _ => None,
            })
            .collect();
        assert!(subframes.len() >= 8, "{events:?}");
        assert!(
            events
                .iter()
                .all(|m| matches!(m, Message::SubframeEvent(_))),
            "{events:?}"
        );
        for (k, e) in subframes.iter().enumerate() {
            assert_eq!((e.frame as usize, e.plane_index as usize), (k / 4, k % 4));
            let want = [0.2, 0.8, 1.4, 2.0][k % 4];
            assert!((e.lens_power_d - want).abs() < 0.02, "{e:?}");
        }
        assert_eq!(
            subframes[1].device_time_us - subframes[0].device_time_us,
            4166
        );

        // The default lens needs ~15 ms: at 240 Hz it never settles in 1.5 ms.
        let mut sim = SyncBoardSim::new(quiet(LensModelConfig::default()));
        send(&mut sim, 1, &schedule(4166, 1500));
        send(&mut sim, 2, &Message::Start);
        let events = run_for(&mut sim, Timestamp::ZERO, 40);
        let late = events
            .iter()
            .filter(|m| {
                matches!(
                    m,
                    Message::Fault(Fault {
                        kind: FaultKind::LateSettle,
                        ..
                    })
                )
            })
            .count();
        assert!(late >= 8, "{events:?}");
    }

    #[test]
    fn dropped_vsyncs_are_faults_and_jitter_moves_edges() {
        let cfg = SyncBoardSimConfig {
            missed_vsync_probability: 0.3,
            jitter_us: 50.0,
            drift_ppm: 0.0,
            clock_offset_us: 0,
            ..Default::default()
        };
        let mut sim = SyncBoardSim::new(cfg);
        send(&mut sim, 1, &schedule(4166, 1000));
        send(&mut sim, 2, &Message::Start);
        let events = run_for(&mut sim, Timestamp::ZERO, 200);
        let missed = events
            .iter()
            .filter(|m| {
                matches!(
                    m,
                    Message::Fault(Fault {
                        kind: FaultKind::MissedVsync,
                        ..
                    })
                )
            })
            .count();
        let times: Vec<u64> = events
            .iter()
            .filter_map(|m| match m {
                Message::SubframeEvent(e) => Some(e.device_time_us),
                _ => None,
            })
            .collect();
        assert!(missed > 5 && missed < 25, "{missed} missed of 48");
        let gaps: Vec<u64> = times.windows(2).map(|w| w[1] - w[0]).collect();
        assert!(gaps.iter().any(|g| *g != 4166), "no jitter: {gaps:?}");
        assert!(gaps.iter().all(|g| *g >= 4166 - 100), "{gaps:?}");
    }

    #[test]
    fn clock_offset_and_drift() {
        let sim = SyncBoardSim::new(SyncBoardSimConfig {
            clock_offset_us: 1_000,
            drift_ppm: 100.0,
            ..Default::default()
        });
        assert_eq!(sim.device_time_us(Timestamp::ZERO), 1_000);
        assert_eq!(
            sim.device_time_us(Timestamp::from_millis(1000)),
            1_000 + 1_000_100
        );
    }

    #[test]
    fn garbage_is_answered_per_protocol_and_the_board_recovers() {
        let mut sim = SyncBoardSim::new(SyncBoardSimConfig::default());
        let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
        let mut out = Vec::new();
        for i in 0..200u64 {
            let chunk: Vec<u8> = (0..50)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    x as u8
                })
                .collect();
            sim.advance_to(Timestamp::from_millis(i * 20), &mut out);
            sim.receive(&chunk, &mut out);
        }
        // Whatever came back decodes as frames (error events, rate-limited).
        let back: Vec<_> = FrameDecoder::new().push(&out).collect();
        assert!(back.iter().all(|f| f.is_ok()));
        // A delimiter ends the garbage; the next request is answered.
        let mut out = Vec::new();
        sim.receive(&[0], &mut out);
        let r = send(
            &mut sim,
            9,
            &Message::Hello {
                protocol_version: PROTOCOL_VERSION.into(),
            },
        );
        assert!(
            matches!(r.last(), Some((9, Message::DeviceInfo(_)))),
            "{r:?}"
        );
    }

    fn photodiode(threshold: u16, hysteresis: u16) -> Message {
        Message::PhotodiodeConfig(dioptra_protocol::PhotodiodeConfig {
            enabled: true,
            threshold,
            hysteresis,
        })
    }

    fn edges(events: &[Message]) -> Vec<PhotodiodeEdge> {
        events
            .iter()
            .filter_map(|m| match m {
                Message::PhotodiodeEdge(e) => Some(*e),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn photodiode_edges_carry_the_crossings_device_time_with_or_without_a_schedule() {
        use crate::light::ScriptedLight;
        let light = ScriptedLight::new();
        // A white patch (0.9) for 2 ms every 11.1 ms, black (0.02) otherwise.
        let starts: Vec<Timestamp> = (0..4)
            .map(|k| Timestamp::from_micros(3_000 + k * 11_100))
            .collect();
        light.pulses(starts.clone(), Duration::from_millis(2), 0.9, 0.02);
        let cfg = SyncBoardSimConfig {
            clock_offset_us: 1_000_000,
            ..quiet(LensModelConfig::default())
        };
        let mut sim = SyncBoardSim::new(cfg).with_light(Arc::new(light));
        let Message::DeviceInfo(info) = send(
            &mut sim,
            1,
            &Message::Hello {
                protocol_version: PROTOCOL_VERSION.into(),
            },
        )[0]
        .1
        .clone() else {
            panic!("no DeviceInfo");
        };
        assert!(info.capabilities.contains(Capabilities::PHOTODIODE));
        // Off until the host enables it: the first pulse goes unreported.
        assert!(edges(&run_for(&mut sim, Timestamp::ZERO, 10)).is_empty());
        assert_eq!(
            send(&mut sim, 2, &photodiode(32_768, 3_000)),
            vec![(2, Message::Ack)]
        );
        // A schedule running meanwhile changes nothing about the edges.
        send(&mut sim, 3, &schedule(4166, 1000));
        send(&mut sim, 4, &Message::Start);
        let events = run_for(&mut sim, Timestamp::from_millis(10), 40);
        let subframes = events
            .iter()
            .filter(|m| matches!(m, Message::SubframeEvent(_)))
            .count();
        assert!(subframes >= 8, "{subframes} sub-frames");
        let got = edges(&events);
        let want: Vec<(u32, u64, bool)> = starts[1..]
            .iter()
            .enumerate()
            .flat_map(|(k, t)| {
                let on = 1_000_000 + t.as_micros() + 5;
                [
                    (2 * k as u32, on, true),
                    (2 * k as u32 + 1, on + 2_000, false),
                ]
            })
            .collect();
        let seen: Vec<(u32, u64, bool)> = got
            .iter()
            .map(|e| (e.edge, e.device_time_us, e.rising))
            .collect();
        assert_eq!(seen, want);
        assert_eq!(got[0].level, (0.9f32 * 65_535.0).round() as u16);
        assert_eq!(got[1].level, (0.02f32 * 65_535.0).round() as u16);
    }

    #[test]
    fn photodiode_config_is_checked_and_a_full_queue_leaves_a_gap() {
        use crate::light::ScriptedLight;
        let light = ScriptedLight::new();
        let starts = (0..5).map(|k| Timestamp::from_micros(1_000 + k * 100));
        light.pulses(starts, Duration::from_micros(50), 1.0, 0.0);
        let cfg = SyncBoardSimConfig {
            photodiode_queue: 4,
            ..quiet(LensModelConfig::default())
        };
        let mut sim = SyncBoardSim::new(cfg).with_light(Arc::new(light));
        for (id, bad) in [(1, photodiode(100, 100)), (2, photodiode(65_000, 600))] {
            assert!(matches!(
                send(&mut sim, id, &bad)[..],
                [(
                    _,
                    Message::Error {
                        code: ErrorCode::OutOfRange,
                        ..
                    }
                )]
            ));
        }
        assert_eq!(
            send(&mut sim, 3, &photodiode(30_000, 1_000)),
            vec![(3, Message::Ack)]
        );
        // Ten edges within one step of the loop: four go out, six are dropped and counted.
        let mut out = Vec::new();
        sim.advance_to(Timestamp::from_millis(3), &mut out);
        let got: Vec<u32> = edges(&frames(&out).into_iter().map(|f| f.1).collect::<Vec<_>>())
            .iter()
            .map(|e| e.edge)
            .collect();
        assert_eq!(got, [0, 1, 2, 3]);
        assert_eq!(sim.photodiode_edges_dropped(), 6);
        // Switching it off stops the edges.
        let off = Message::PhotodiodeConfig(dioptra_protocol::PhotodiodeConfig {
            enabled: false,
            threshold: 30_000,
            hysteresis: 1_000,
        });
        assert_eq!(send(&mut sim, 4, &off), vec![(4, Message::Ack)]);
    }

    #[test]
    fn a_falling_edge_trigger_starts_sub_frames_one_pulse_later() {
        let first_start = |rising: bool| {
            let mut sim = SyncBoardSim::new(quiet(LensModelConfig::default()));
            let m = Message::PlaneSchedule(
                PlaneSchedule::new(&[1.0, 2.0], 4166, 1000, rising).unwrap(),
            );
            send(&mut sim, 1, &m);
            send(&mut sim, 2, &Message::Start);
            run_for(&mut sim, Timestamp::ZERO, 10)
                .into_iter()
                .find_map(|m| match m {
                    Message::SubframeEvent(e) => Some(e.device_time_us),
                    _ => None,
                })
                .unwrap()
        };
        assert_eq!(first_start(false) - first_start(true), 20);
    }
}
