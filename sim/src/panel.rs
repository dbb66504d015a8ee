//! A simulated display panel that emits light: the marker patch's light reaching a photodiode.
//!
//! The rig's display sink presents one frame per vsync with its marker patch white or black
//! ([`SimPanel::present`]). The panel shows it from that vsync: its light changes
//! `photon_latency` later (scan-out to the patch's rows and the pixels' response, in one
//! figure) and lasts either until a later refresh changes it (sample-and-hold, most LCDs) or
//! `persistence` per refresh (low-persistence OLED and strobed-backlight panels, which pulse
//! every refresh, also when a frame is shown again). A refresh can be dropped
//! ([`SimPanel::drop_refresh`]): the panel keeps the previous image for it and the frame
//! presented for it is never shown, as a display that misses a vsync shows the newest frame
//! at the next one.
//!
//! The light is a [`LightSource`] for the simulated photodiodes. Steps are scheduled ahead as
//! frames are presented; a present cancels the repeat pulses scheduled after its own light
//! starts. A step can never be scheduled before what a sensor has already taken (a present
//! that comes late, on a busy machine in real time): it is moved to then, and the log says so.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::{lock, Timestamp};

use crate::light::LightSource;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PanelConfig {
    /// Time between refreshes.
    pub refresh_period: Duration,
    /// From a refresh's vsync to the patch's light changing.
    pub photon_latency: Duration,
    /// Light per refresh: `None` holds it until a later refresh changes it; `Some(d)` pulses
    /// for `d` every refresh (at most the refresh period).
    pub persistence: Option<Duration>,
    /// The patch's level when white and when black, fractions of the sensor's full scale
    /// (black is not quite dark: backlight bleed).
    pub white_level: f32,
    pub black_level: f32,
}

impl PanelConfig {
    pub fn new(refresh_period: Duration, photon_latency: Duration) -> Self {
        PanelConfig {
            refresh_period,
            photon_latency,
            persistence: None,
            white_level: 0.9,
            black_level: 0.02,
        }
    }
}

/// What the panel did at one refresh: ground truth for tests.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refresh {
    pub vsync: Timestamp,
    /// The frame presented for it and its patch.
    pub frame: u64,
    pub white: bool,
    /// The refresh was dropped: the previous image stayed and this frame was not shown.
    pub dropped: bool,
    /// When the light of this refresh started (vsync + latency, or later if it came late).
    pub light_at: Timestamp,
}

/// How many refreshes the log keeps.
const LOG: usize = 100_000;
/// Repeat pulses of a low-persistence panel are scheduled this far ahead of the last present.
const PULSE_HORIZON: Duration = Duration::from_secs(1);

#[derive(Debug)]
pub struct SimPanel {
    cfg: PanelConfig,
    /// What the patch shows now (after the last refresh): white or black.
    showing: bool,
    steps: VecDeque<(Timestamp, f32)>,
    /// Sensors have taken the light up to here.
    taken_until: Timestamp,
    drops: Vec<u64>,
    presents: u64,
    log: VecDeque<Refresh>,
}

impl SimPanel {
    /// A panel showing a black patch.
    pub fn new(cfg: PanelConfig) -> Self {
        let mut cfg = cfg;
        cfg.persistence = cfg.persistence.map(|p| p.min(cfg.refresh_period));
        SimPanel {
            cfg,
            showing: false,
            steps: VecDeque::new(),
            taken_until: Timestamp::ZERO,
            drops: Vec::new(),
            presents: 0,
            log: VecDeque::new(),
        }
    }

    pub fn config(&self) -> &PanelConfig {
        &self.cfg
    }

    /// Drops refresh `n` (counting presents from 0): it shows the previous image again.
    pub fn drop_refresh(&mut self, n: u64) {
        self.drops.push(n);
    }

    /// Presents taken so far.
    pub fn presents(&self) -> u64 {
        self.presents
    }

    /// The refreshes so far, oldest first (the newest [`LOG`]).
    pub fn refreshes(&self) -> impl Iterator<Item = &Refresh> {
        self.log.iter()
    }

    fn level(&self, white: bool) -> f32 {
        if white {
            self.cfg.white_level
        } else {
            self.cfg.black_level
        }
    }

    /// Frame `frame`, its patch `white`, is shown from the refresh at `vsync`. Returns when its
    /// light starts, or `None` when this refresh is dropped.
    pub fn present(&mut self, vsync: Timestamp, frame: u64, white: bool) -> Option<Timestamp> {
        let n = self.presents;
        self.presents += 1;
        let dropped = self.drops.contains(&n);
        let shown = if dropped { self.showing } else { white };
        let start = (vsync + self.cfg.photon_latency).max(self.taken_until);
        // What was scheduled from here on belonged to the previous image.
        while self.steps.back().is_some_and(|(t, _)| *t >= start) {
            self.steps.pop_back();
        }
        match self.cfg.persistence {
            None => self.steps.push_back((start, self.level(shown))),
            Some(on) => {
                // A pulse every refresh while the image is white (a dropped refresh pulses
                // the previous image again), until a later present replaces them.
                if shown {
                    let mut t = start;
                    while t < start + PULSE_HORIZON {
                        self.steps.push_back((t, self.level(true)));
                        self.steps.push_back((t + on, self.level(false)));
                        t = t + self.cfg.refresh_period;
                    }
                } else {
                    self.steps.push_back((start, self.level(false)));
                }
            }
        }
        self.showing = shown;
        if self.log.len() == LOG {
            self.log.pop_front();
        }
        self.log.push_back(Refresh {
            vsync,
            frame,
            white,
            dropped,
            light_at: start,
        });
        (!dropped).then_some(start)
    }
}

/// A panel shared between the display that presents to it and the sensors that watch it.
#[derive(Debug, Clone)]
pub struct SharedPanel(pub Arc<Mutex<SimPanel>>);

impl SharedPanel {
    pub fn new(cfg: PanelConfig) -> Self {
        SharedPanel(Arc::new(Mutex::new(SimPanel::new(cfg))))
    }
    pub fn lock(&self) -> std::sync::MutexGuard<'_, SimPanel> {
        lock(&self.0)
    }
}

impl LightSource for SharedPanel {
    fn take_until(&self, now: Timestamp) -> Vec<(Timestamp, f32)> {
        let mut p = lock(&self.0);
        p.taken_until = p.taken_until.max(now);
        let n = p.steps.partition_point(|(t, _)| *t <= now);
        p.steps.drain(..n).collect()
    }
    fn next_change(&self) -> Option<Timestamp> {
        lock(&self.0).steps.front().map(|(t, _)| *t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::light::Comparator;

    const T: Duration = Duration::from_micros(11_111);

    fn vsync(k: u64) -> Timestamp {
        Timestamp::from_micros(100_000) + T * k as u32
    }

    /// Presents `n` frames toggling the patch, `drop` dropped; returns the comparator's edges.
    fn run(cfg: PanelConfig, n: u64, drop: Option<u64>) -> (Vec<(Timestamp, bool)>, SharedPanel) {
        let panel = SharedPanel::new(cfg);
        if let Some(d) = drop {
            panel.lock().drop_refresh(d);
        }
        let mut c = Comparator::new(0.5, 0.05, Duration::ZERO);
        let mut edges = Vec::new();
        for k in 0..n {
            // The sensor looks just before each vsync, as a device's loop would.
            edges.extend(c.sense(&panel, Timestamp(vsync(k).0 - 1_000)));
            panel.lock().present(vsync(k), k, k % 2 == 1);
        }
        edges.extend(c.sense(&panel, vsync(n) + Duration::from_millis(20)));
        (edges.into_iter().map(|e| (e.at, e.rising)).collect(), panel)
    }

    #[test]
    fn a_held_patch_changes_at_each_vsync_plus_the_latency() {
        let cfg = PanelConfig::new(T, Duration::from_micros(4_000));
        let (edges, _) = run(cfg, 6, None);
        let want: Vec<(Timestamp, bool)> = (1..6)
            .map(|k| (vsync(k) + Duration::from_micros(4_000), k % 2 == 1))
            .collect();
        assert_eq!(edges, want);
    }

    #[test]
    fn a_low_persistence_patch_pulses_every_white_refresh() {
        let cfg = PanelConfig {
            persistence: Some(Duration::from_millis(2)),
            ..PanelConfig::new(T, Duration::from_micros(4_000))
        };
        let (edges, _) = run(cfg, 4, None);
        let on = |k: u64| vsync(k) + Duration::from_micros(4_000);
        assert_eq!(
            edges,
            [
                (on(1), true),
                (on(1) + Duration::from_millis(2), false),
                (on(3), true),
                (on(3) + Duration::from_millis(2), false),
                // The last white frame stays on screen: it pulses again.
                (on(4), true),
                (on(4) + Duration::from_millis(2), false),
                (on(5), true),
                (on(5) + Duration::from_millis(2), false),
            ]
        );
    }

    #[test]
    fn a_dropped_refresh_keeps_the_previous_image_and_never_shows_its_frame() {
        let cfg = PanelConfig::new(T, Duration::from_micros(4_000));
        // Refresh 3 (white) is dropped: black from refresh 2 to 4, white from 5.
        let (edges, panel) = run(cfg, 7, Some(3));
        let at = |k: u64| vsync(k) + Duration::from_micros(4_000);
        assert_eq!(
            edges,
            [(at(1), true), (at(2), false), (at(5), true), (at(6), false)]
        );
        let log: Vec<(u64, bool)> = panel
            .lock()
            .refreshes()
            .map(|r| (r.frame, r.dropped))
            .collect();
        assert_eq!(log[3], (3, true));
        assert_eq!(log.iter().filter(|r| r.1).count(), 1);
    }

    #[test]
    fn a_late_present_starts_its_light_when_it_comes_not_in_the_past() {
        let panel = SharedPanel::new(PanelConfig::new(T, Duration::from_micros(1_000)));
        let _ = panel.take_until(Timestamp::from_millis(50));
        let at = panel.lock().present(Timestamp::from_millis(40), 0, true);
        assert_eq!(at, Some(Timestamp::from_millis(50)));
        assert_eq!(panel.next_change(), Some(Timestamp::from_millis(50)));
    }
}
