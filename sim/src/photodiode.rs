//! Simulated serial-line photodiode: the microcontroller side of the line protocol in
//! firmware-protocol/photodiode/README.md (what the Arduino sketch there does), written from
//! that text, not from the driver's parser.
//!
//! The board sends its hello line when it boots (the first step of its loop), answers `v` with
//! it again and `s` with `s,<t_us>` (its clock when the `s` arrived), and writes one
//! `<t_us>,<level>` line per edge of its [`Comparator`] (a fixed band: the comparator module's
//! potentiometer), stamped with the edge's own time. At most [`SerialPhotodiodeSimConfig::queue`]
//! edges go out per step of its loop; the rest are counted and reported as `!overflow,<n>` at
//! the next step, before any later edge, as the sketch does when its ring buffer fills.
//! Anything else the host sends is
//! ignored, with a `#` comment. Its clock is a 64-bit microsecond counter with an offset and
//! a drift; [`SerialPhotodiodeSim::restart`] reboots it (clock from zero, hello again).

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::Timestamp;

use crate::light::{Comparator, LightSource};
use crate::serve::ByteDevice;

#[derive(Debug, Clone, PartialEq)]
pub struct SerialPhotodiodeSimConfig {
    /// The hello line's version field.
    pub protocol_version: u32,
    /// The hello line's free text.
    pub about: String,
    /// Device clock at host time zero, µs.
    pub clock_offset_us: u64,
    /// Device clock rate error, parts per million.
    pub drift_ppm: f64,
    /// The comparator's band, fractions of the sensor's scale.
    pub threshold: f32,
    pub hysteresis: f32,
    /// The photodiode's response (sensor and amplifier delay), µs.
    pub response_us: u64,
    /// Edges the board writes per step of its loop; more are dropped and counted.
    pub queue: usize,
}

impl Default for SerialPhotodiodeSimConfig {
    fn default() -> Self {
        SerialPhotodiodeSimConfig {
            protocol_version: 1,
            about: "dioptra-sim serial photodiode".into(),
            clock_offset_us: 3_000_000,
            drift_ppm: 35.0,
            threshold: 0.5,
            hysteresis: 0.05,
            response_us: 5,
            queue: 32,
        }
    }
}

/// A simulated serial-line photodiode.
pub struct SerialPhotodiodeSim {
    cfg: SerialPhotodiodeSimConfig,
    light: Option<Arc<dyn LightSource>>,
    comparator: Comparator,
    /// Host time the board's clock started counting, and its count then.
    booted_at: Timestamp,
    clock_at_boot_us: u64,
    now: Timestamp,
    sent_hello: bool,
    command: Vec<u8>,
    lost: u64,
    edges_sent: u64,
}

impl std::fmt::Debug for SerialPhotodiodeSim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SerialPhotodiodeSim")
            .field("cfg", &self.cfg)
            .field("now", &self.now)
            .field("edges_sent", &self.edges_sent)
            .finish_non_exhaustive()
    }
}

/// Longest command line the board buffers; a longer one is dropped.
const MAX_COMMAND: usize = 32;

impl SerialPhotodiodeSim {
    pub fn new(cfg: SerialPhotodiodeSimConfig) -> Self {
        let comparator = Comparator::new(
            cfg.threshold,
            cfg.hysteresis,
            Duration::from_micros(cfg.response_us),
        );
        SerialPhotodiodeSim {
            cfg: cfg.clone(),
            light: None,
            comparator,
            booted_at: Timestamp::ZERO,
            clock_at_boot_us: cfg.clock_offset_us,
            now: Timestamp::ZERO,
            sent_hello: false,
            command: Vec::new(),
            lost: 0,
            edges_sent: 0,
        }
    }

    /// Connects `light` to the photodiode.
    pub fn with_light(mut self, light: Arc<dyn LightSource>) -> Self {
        self.light = Some(light);
        self
    }

    /// The board's clock at host time `t`, µs.
    pub fn device_time_us(&self, t: Timestamp) -> u64 {
        let since_boot = t.saturating_since(self.booted_at).as_nanos() as f64 / 1000.0;
        self.clock_at_boot_us + (since_boot * (1.0 + self.cfg.drift_ppm * 1e-6)) as u64
    }

    /// Reboots the board now: its clock starts from zero and it says hello again.
    pub fn restart(&mut self) {
        self.booted_at = self.now;
        self.clock_at_boot_us = 0;
        self.sent_hello = false;
        self.command.clear();
    }

    pub fn edges_sent(&self) -> u64 {
        self.edges_sent
    }

    fn hello(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(
            format!(
                "dioptra-photodiode,{},{}\n",
                self.cfg.protocol_version, self.cfg.about
            )
            .as_bytes(),
        );
    }

    fn run_command(&mut self, command: &[u8], out: &mut Vec<u8>) {
        let command = command.strip_suffix(b"\r").unwrap_or(command);
        match command {
            b"" => {}
            b"v" => self.hello(out),
            b"s" => {
                let t = self.device_time_us(self.now);
                out.extend_from_slice(format!("s,{t}\n").as_bytes());
            }
            _ => out.extend_from_slice(b"#unknown command\n"),
        }
    }
}

impl ByteDevice for SerialPhotodiodeSim {
    fn wait(&self, now: Timestamp) -> Duration {
        if !self.sent_hello {
            return Duration::ZERO;
        }
        self.light
            .as_deref()
            .and_then(|l| self.comparator.next_due(l))
            .map_or(Duration::from_millis(5), |due| {
                due.saturating_since(now)
                    .clamp(Duration::from_micros(50), Duration::from_millis(5))
            })
    }

    fn advance_to(&mut self, now: Timestamp, out: &mut Vec<u8>) {
        self.now = self.now.max(now);
        if !self.sent_hello {
            self.sent_hello = true;
            self.hello(out);
        }
        let Some(light) = self.light.clone() else {
            return;
        };
        // Edges dropped in the last step are reported as soon as there is room again.
        if self.lost > 0 {
            out.extend_from_slice(format!("!overflow,{}\n", self.lost).as_bytes());
            self.lost = 0;
        }
        let crossings = self.comparator.sense(light.as_ref(), self.now);
        for (i, c) in crossings.iter().enumerate() {
            if i >= self.cfg.queue {
                self.lost += 1;
                continue;
            }
            let t = self.device_time_us(c.at);
            out.extend_from_slice(format!("{t},{}\n", if c.rising { 1 } else { 0 }).as_bytes());
            self.edges_sent += 1;
        }
    }

    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        for &b in bytes {
            if b == b'\n' {
                let command = std::mem::take(&mut self.command);
                self.run_command(&command, out);
            } else if self.command.len() < MAX_COMMAND {
                self.command.push(b);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::light::ScriptedLight;

    fn text(out: &[u8]) -> String {
        String::from_utf8(out.to_vec()).unwrap()
    }

    #[test]
    fn hello_sync_edges_and_overflow_as_the_line_protocol_says() {
        let light = ScriptedLight::new();
        let starts = [2_000, 3_000, 4_000, 8_000].map(Timestamp::from_micros);
        light.pulses(starts, Duration::from_micros(400), 0.9, 0.0);
        let cfg = SerialPhotodiodeSimConfig {
            clock_offset_us: 1_000,
            drift_ppm: 0.0,
            response_us: 5,
            queue: 4,
            ..Default::default()
        };
        let mut sim = SerialPhotodiodeSim::new(cfg).with_light(Arc::new(light));
        let mut out = Vec::new();
        sim.advance_to(Timestamp::from_millis(1), &mut out);
        assert_eq!(
            text(&out),
            "dioptra-photodiode,1,dioptra-sim serial photodiode\n"
        );
        out.clear();
        sim.receive(b"s\nv\nxyz\n", &mut out);
        assert_eq!(
            text(&out),
            "s,2000\ndioptra-photodiode,1,dioptra-sim serial photodiode\n#unknown command\n"
        );
        // Six edges in one step of the loop: four go out, the overflow at the next step.
        out.clear();
        sim.advance_to(Timestamp::from_millis(5), &mut out);
        assert_eq!(text(&out), "3005,1\n3405,0\n4005,1\n4405,0\n");
        out.clear();
        sim.advance_to(Timestamp::from_millis(9), &mut out);
        assert_eq!(text(&out), "!overflow,2\n9005,1\n9405,0\n");
        assert_eq!(sim.edges_sent(), 6);
        // A reboot: the clock starts from zero and the hello comes again.
        out.clear();
        sim.restart();
        sim.advance_to(Timestamp::from_millis(10), &mut out);
        assert_eq!(
            text(&out),
            "dioptra-photodiode,1,dioptra-sim serial photodiode\n"
        );
        assert_eq!(sim.device_time_us(Timestamp::from_millis(11)), 2_000);
    }
}
