//! Light on a photodiode, and the sensor that turns it into edges.
//!
//! Whatever models the light (the simulated panel, [`crate::panel`], or a test's script,
//! [`ScriptedLight`]) is a [`LightSource`]: steps of the level reaching the sensor, in host
//! time. A device simulator with a photodiode input takes the steps as its time passes and
//! runs them through a [`Comparator`], as the hardware's comparator does, reporting each
//! crossing of the band. Sources are shared (`Arc`) between the task that drives the display
//! and the task serving the device.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::{lock, Timestamp};

/// Light reaching a sensor: a level from 0 (dark) to 1 (the sensor's full scale) that changes
/// in steps.
pub trait LightSource: Send + Sync {
    /// The steps up to and including host time `now`, oldest first, each returned once:
    /// (when, the level from then on).
    fn take_until(&self, now: Timestamp) -> Vec<(Timestamp, f32)>;
    /// The earliest time the level may change next (a device wakes for it); `None`: not
    /// known, poll.
    fn next_change(&self) -> Option<Timestamp>;
}

/// Light that a test scripts ahead: [`ScriptedLight::set_at`] schedules a step.
#[derive(Debug, Clone, Default)]
pub struct ScriptedLight(Arc<Mutex<VecDeque<(Timestamp, f32)>>>);

impl ScriptedLight {
    pub fn new() -> Self {
        Self::default()
    }

    /// The level becomes `level` at host time `at` (steps are kept in time order).
    pub fn set_at(&self, at: Timestamp, level: f32) {
        let mut steps = lock(&self.0);
        let i = steps.partition_point(|(t, _)| *t <= at);
        steps.insert(i, (at, level));
    }

    /// A square wave: `on` for `high` from each of `starts`, `off` otherwise.
    pub fn pulses(
        &self,
        starts: impl IntoIterator<Item = Timestamp>,
        high: Duration,
        on: f32,
        off: f32,
    ) {
        for t in starts {
            self.set_at(t, on);
            self.set_at(t + high, off);
        }
    }
}

impl LightSource for ScriptedLight {
    fn take_until(&self, now: Timestamp) -> Vec<(Timestamp, f32)> {
        let mut steps = lock(&self.0);
        let n = steps.partition_point(|(t, _)| *t <= now);
        steps.drain(..n).collect()
    }
    fn next_change(&self) -> Option<Timestamp> {
        lock(&self.0).front().map(|(t, _)| *t)
    }
}

/// A crossing of the comparator's band.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Crossing {
    /// Host time the comparator's output changed (the light's step plus the sensor's response).
    pub at: Timestamp,
    /// The light came on.
    pub rising: bool,
    /// The level after the step, 0 to 1.
    pub level: f32,
}

/// A photodiode behind a comparator with hysteresis: on above `threshold + hysteresis`, off
/// below `threshold - hysteresis`; the output follows the light after `response` (the
/// photodiode's and amplifier's delay).
#[derive(Debug, Clone, PartialEq)]
pub struct Comparator {
    threshold: f32,
    hysteresis: f32,
    response: Duration,
    on: bool,
    level: f32,
}

impl Comparator {
    /// Dark at first.
    pub fn new(threshold: f32, hysteresis: f32, response: Duration) -> Self {
        Comparator {
            threshold,
            hysteresis,
            response,
            on: false,
            level: 0.0,
        }
    }

    /// A new band; the output takes the present level's state without a crossing.
    pub fn set_band(&mut self, threshold: f32, hysteresis: f32) {
        self.threshold = threshold;
        self.hysteresis = hysteresis;
        self.on = self.level > threshold;
    }

    pub fn is_on(&self) -> bool {
        self.on
    }

    pub fn response(&self) -> Duration {
        self.response
    }

    /// Takes `source`'s steps until the comparator's output at host time `now` is known, and
    /// returns the crossings among them.
    pub fn sense(&mut self, source: &dyn LightSource, now: Timestamp) -> Vec<Crossing> {
        let until = Timestamp(now.0.saturating_sub(self.response.as_nanos() as u64));
        let mut out = Vec::new();
        for (t, level) in source.take_until(until) {
            self.level = level;
            let rising = !self.on && level > self.threshold + self.hysteresis;
            let falling = self.on && level < self.threshold - self.hysteresis;
            if rising || falling {
                self.on = rising;
                out.push(Crossing {
                    at: t + self.response,
                    rising,
                    level,
                });
            }
        }
        out
    }

    /// When the next crossing may be known: the source's next step plus the response.
    pub fn next_due(&self, source: &dyn LightSource) -> Option<Timestamp> {
        source.next_change().map(|t| t + self.response)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_band_keeps_a_level_near_the_threshold_from_chattering() {
        let light = ScriptedLight::new();
        let ms = Timestamp::from_millis;
        for (i, level) in [0.9, 0.52, 0.47, 0.9, 0.1, 0.5, 0.02]
            .into_iter()
            .enumerate()
        {
            light.set_at(ms(i as u64 + 1), level);
        }
        let mut c = Comparator::new(0.5, 0.05, Duration::from_micros(10));
        let got = c.sense(&light, ms(100));
        let edges: Vec<(u64, bool)> = got.iter().map(|x| (x.at.as_micros(), x.rising)).collect();
        // 0.52 and 0.47 stay inside the band (on), 0.1 turns it off, 0.5 stays off.
        assert_eq!(edges, [(1_010, true), (5_010, false)]);
        assert_eq!(got[0].level, 0.9);
        assert!(!c.is_on());
    }

    #[test]
    fn steps_are_taken_only_once_their_response_has_passed() {
        let light = ScriptedLight::new();
        light.pulses(
            [Timestamp::from_millis(1)],
            Duration::from_millis(2),
            0.9,
            0.0,
        );
        let mut c = Comparator::new(0.5, 0.05, Duration::from_micros(10));
        assert!(c.sense(&light, Timestamp::from_micros(1_005)).is_empty());
        assert_eq!(c.next_due(&light), Some(Timestamp::from_micros(1_010)));
        let got = c.sense(&light, Timestamp::from_micros(1_010));
        assert_eq!(got.len(), 1);
        assert!(got[0].rising);
        let got = c.sense(&light, Timestamp::from_millis(5));
        assert_eq!(got.len(), 1);
        assert!(!got[0].rising);
        assert_eq!(c.next_due(&light), None);
    }

    #[test]
    fn a_new_band_takes_the_present_state_without_an_edge() {
        let light = ScriptedLight::new();
        light.set_at(Timestamp::from_millis(1), 0.3);
        let mut c = Comparator::new(0.5, 0.05, Duration::ZERO);
        assert!(c.sense(&light, Timestamp::from_millis(2)).is_empty());
        c.set_band(0.2, 0.05);
        assert!(c.is_on());
        light.set_at(Timestamp::from_millis(3), 0.1);
        let got = c.sense(&light, Timestamp::from_millis(4));
        assert_eq!(got.len(), 1);
        assert!(!got[0].rising);
    }
}
