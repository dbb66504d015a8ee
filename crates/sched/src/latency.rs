//! Latency accounting: one HdrHistogram per stage, in microseconds.
//!
//! Per gaze sample: device time (mapped to the host) -> host receive -> lens command on the
//! wire -> lens settled. Per frame: render time, and gaze sample -> display time of the first
//! frame rendered after it. Per content frame (a lab's RGB-D): arrival to ready, and arrival
//! to the display time of the first frame showing it.

use std::time::Duration;

use hdrhistogram::Histogram;

use crate::config::RenderMethod;

/// A stage of the loop whose latency is recorded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stage {
    /// Tracker exposure (device time on the host timeline) to host receive.
    TrackerToHost,
    /// Host receive of the gaze sample that moved focus to its lens command on the wire.
    HostToWire,
    /// Lens command on the wire to the lens reporting itself settled at the commanded power.
    WireToSettled,
    /// Tracker exposure of the gaze sample that moved focus to the lens settled there.
    GazeToSettled,
    /// Tracker exposure of the newest gaze sample a frame was rendered with to that frame's
    /// display time.
    GazeToDisplay,
    /// Render time of every frame, all methods.
    Render,
    /// A content frame's arrival (a stream frame's request, a file frame's due time) to its
    /// being ready to render (copied, checked, converted; decoded), for each frame the display
    /// takes up (a frame a newer one replaces first never reaches the scheduler).
    ContentReceived,
    /// A content frame's arrival to the display time of the first frame showing it.
    ContentToPresented,
}

impl Stage {
    pub const ALL: [Stage; 8] = [
        Stage::TrackerToHost,
        Stage::HostToWire,
        Stage::WireToSettled,
        Stage::GazeToSettled,
        Stage::GazeToDisplay,
        Stage::Render,
        Stage::ContentReceived,
        Stage::ContentToPresented,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            Stage::TrackerToHost => "tracker to host",
            Stage::HostToWire => "host receive to lens command on the wire",
            Stage::WireToSettled => "lens command to lens settled",
            Stage::GazeToSettled => "gaze sample to lens settled",
            Stage::GazeToDisplay => "gaze sample to display",
            Stage::Render => "render",
            Stage::ContentReceived => "content received",
            Stage::ContentToPresented => "content to presented",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// Highest latency recorded exactly, µs (longer ones saturate): a minute.
const MAX_US: u64 = 60_000_000;

fn histogram() -> Result<Histogram<u64>, hdrhistogram::CreationError> {
    Histogram::new_with_bounds(1, MAX_US, 3)
}

/// The histograms, µs.
#[derive(Debug, Clone)]
pub struct Latency {
    stages: Vec<Histogram<u64>>,
    per_method: Vec<(RenderMethod, Histogram<u64>)>,
}

fn micros(d: Duration) -> u64 {
    d.as_micros().min(u128::from(MAX_US)) as u64
}

impl Latency {
    pub fn new() -> Result<Self, hdrhistogram::CreationError> {
        Ok(Latency {
            stages: Stage::ALL
                .iter()
                .map(|_| histogram())
                .collect::<Result<_, _>>()?,
            per_method: Vec::new(),
        })
    }

    pub fn record(&mut self, stage: Stage, d: Duration) {
        if let Some(h) = self.stages.get_mut(stage.index()) {
            h.saturating_record(micros(d));
        }
    }

    pub fn record_render(&mut self, method: RenderMethod, d: Duration) {
        self.record(Stage::Render, d);
        if let Some((_, h)) = self.per_method.iter_mut().find(|(m, _)| *m == method) {
            h.saturating_record(micros(d));
        } else if let Ok(mut h) = histogram() {
            h.saturating_record(micros(d));
            self.per_method.push((method, h));
        }
    }

    /// The histogram of one stage, µs.
    pub fn stage(&self, stage: Stage) -> &Histogram<u64> {
        &self.stages[stage.index()]
    }

    /// Render time per method, µs, in the order methods were first seen.
    pub fn render_by_method(&self) -> &[(RenderMethod, Histogram<u64>)] {
        &self.per_method
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_record_microseconds_and_saturate() {
        let mut l = Latency::new().unwrap();
        l.record(Stage::HostToWire, Duration::from_micros(150));
        l.record(Stage::HostToWire, Duration::from_secs(3600));
        let h = l.stage(Stage::HostToWire);
        assert_eq!(h.len(), 2);
        assert!(h.min() >= 149 && h.min() <= 151, "{}", h.min());
        assert!(h.max() >= MAX_US - MAX_US / 500, "{}", h.max());
        l.record_render(RenderMethod::Gather, Duration::from_millis(4));
        l.record_render(RenderMethod::Linear, Duration::from_millis(2));
        l.record_render(RenderMethod::Gather, Duration::from_millis(6));
        assert_eq!(l.render_by_method().len(), 2);
        assert_eq!(l.render_by_method()[0].1.len(), 2);
        assert_eq!(l.stage(Stage::Render).len(), 3);
    }
}
