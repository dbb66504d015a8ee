//! Latency measured in photons: the edges of a photodiode taped over the display's marker
//! patch, matched to the presents that toggled the patch.
//!
//! [`PhotonRecorder`] is a loop hook that keeps what the match needs: every whole-frame present
//! with its patch colour, the light, the lens commands a gaze sample caused and the render
//! requests. [`analyse`] then:
//!
//! 1. anchors: the patch was held black before `from` (`MarkerControl::hold_black`), so the
//!    first rising edge after the first white present is that present's light. Without the
//!    anchor a patch toggled every frame is ambiguous by a multiple of two frames.
//! 2. follows: each present that changes the patch expects an edge of its direction within
//!    half a refresh of its vsync plus the latency so far (the median of the last 16 matches):
//!    `vsync to photons` and `frame presented to photons`. A low-persistence panel pulses every
//!    white refresh and its dark transitions have no edge of their own; rising edges match as
//!    on any panel.
//! 3. checks every refresh: the light in the middle of its lit time (a quarter refresh, or half
//!    the median pulse on a pulsed panel, after vsync plus latency) must be its frame's patch.
//!    One that is not showed another frame (the previous one again: a dropped or late frame).
//!    Refreshes around edges the photodiode reported lost are not judged.
//! 4. gaze sample to photons: for each lens command a gaze sample caused, the first frame
//!    requested after it (the first rendered for the new focus), its first present, and that
//!    present's light: from the gaze task receiving the sample to the photons.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::{lock, LightEvent, Timestamp};
use dioptra_sched::{Command, FocusReason};

use crate::devices::DeviceInput;
use crate::display::DisplaySink;
use crate::engine::Engine;
use crate::executor::{LoopHook, Presented};

/// One whole-frame present.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PresentRec {
    /// When the loop handed it to the display.
    pub at: Timestamp,
    /// The vsync it is shown from (what the sink returned).
    pub vsync: Timestamp,
    pub frame: u64,
    pub white: bool,
    pub repeat: bool,
}

/// A lens command a gaze sample caused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GazeCommand {
    pub id: u64,
    /// When the loop gave the command.
    pub at: Timestamp,
    /// When the gaze task received the sample (host clock).
    pub gaze_received: Timestamp,
}

/// What [`PhotonRecorder`] keeps.
#[derive(Debug, Clone, Default)]
pub struct PhotonLog {
    pub presents: Vec<PresentRec>,
    pub light: Vec<LightEvent>,
    pub gaze_commands: Vec<GazeCommand>,
    /// (frame, when the loop asked for it).
    pub renders: Vec<(u64, Timestamp)>,
    /// Whether the hook records (a harness turns it on after its hold).
    pub recording: bool,
}

/// Records into a shared [`PhotonLog`] while `recording` is set.
pub struct PhotonRecorder {
    pub log: Arc<Mutex<PhotonLog>>,
    /// The gaze sample the loop is handling this turn.
    turn_gaze: Option<Timestamp>,
}

impl PhotonRecorder {
    pub fn new(log: Arc<Mutex<PhotonLog>>) -> PhotonRecorder {
        PhotonRecorder {
            log,
            turn_gaze: None,
        }
    }
}

impl LoopHook for PhotonRecorder {
    fn input(&mut self, _now: Timestamp, input: &DeviceInput, _engine: &Engine) {
        match input {
            DeviceInput::Gaze(s, _) => self.turn_gaze = Some(s.host_receive_time),
            DeviceInput::Light(e) => {
                let mut log = lock(&self.log);
                if log.recording {
                    log.light.push(*e);
                }
            }
            _ => {}
        }
    }
    fn command(&mut self, now: Timestamp, cmd: &Command) {
        let mut log = lock(&self.log);
        if !log.recording {
            return;
        }
        match cmd {
            Command::SetLensPower { id, reason, .. } => {
                let by_gaze = matches!(
                    reason,
                    FocusReason::FixationOnset
                        | FocusReason::Fixation
                        | FocusReason::SaccadeLanding
                );
                if let (true, Some(g)) = (by_gaze, self.turn_gaze) {
                    log.gaze_commands.push(GazeCommand {
                        id: id.0,
                        at: now,
                        gaze_received: g,
                    });
                }
            }
            Command::RenderFrame(req) => log.renders.push((req.frame.0, now)),
            _ => {}
        }
    }
    fn presented(&mut self, now: Timestamp, shown: &Presented, _sink: &dyn DisplaySink) {
        let (None, Some(white)) = (shown.layer, shown.marker_white) else {
            return;
        };
        let mut log = lock(&self.log);
        if log.recording {
            log.presents.push(PresentRec {
                at: now,
                vsync: shown.shown,
                frame: shown.frame,
                white,
                repeat: shown.repeat,
            });
        }
    }
    fn stepped(&mut self, _now: Timestamp, _engine: &Engine) {
        self.turn_gaze = None;
    }
}

/// The parts of one gaze sample's way to the photons.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GazeToPhotons {
    pub command: u64,
    /// When the gaze task received the sample.
    pub gaze_received: Timestamp,
    /// The frame first rendered for the new focus, shown from `vsync`.
    pub frame: u64,
    pub total: Duration,
    /// Gaze sample received to the lens command (the loop and scheduler).
    pub gaze_to_command: Duration,
    /// Lens command to the vsync the frame rendered for it is shown from (waiting for the
    /// next frame request, the render, waiting for the vsync).
    pub command_to_vsync: Duration,
    pub vsync_to_photons: Duration,
}

/// What [`analyse`] found.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PhotonReport {
    /// The median interval between presents.
    pub refresh_period: Duration,
    /// The lit time per refresh: the median from a matched rising edge to the next falling
    /// edge (a refresh or more on a panel that holds its light).
    pub pulse_width: Duration,
    /// Presents that changed the patch, and those whose edge was found.
    pub transitions: u64,
    pub matched: u64,
    pub vsync_to_photons: Vec<Duration>,
    pub presented_to_photons: Vec<Duration>,
    pub gaze_to_photons: Vec<GazeToPhotons>,
    /// Refreshes judged, and those that showed another frame's patch: (vsync, frame).
    pub refreshes_checked: u64,
    pub refreshes_wrong: Vec<(Timestamp, u64)>,
    /// Refreshes not judged: around edges the photodiode lost.
    pub refreshes_unknown: u64,
    /// Frames presented (and judged), and those never seen on any of their refreshes.
    pub frames_checked: u64,
    pub frames_never_seen: Vec<u64>,
    pub edges: u64,
    pub edges_lost: u64,
}

fn median(v: &mut [u64]) -> Option<u64> {
    if v.is_empty() {
        return None;
    }
    v.sort_unstable();
    Some(v[v.len() / 2])
}

/// Matches `log`'s presents and light, judging refreshes up to `until` (when the light stops
/// being watched). `max_latency` bounds the anchor's search.
pub fn analyse(
    log: &PhotonLog,
    until: Timestamp,
    max_latency: Duration,
) -> Result<PhotonReport, String> {
    let presents: Vec<&PresentRec> = log.presents.iter().collect();
    if presents.len() < 3 {
        return Err(format!(
            "{} frames presented while the light was watched: too few to match",
            presents.len()
        ));
    }
    let mut gaps: Vec<u64> = presents
        .windows(2)
        .map(|w| w[1].vsync.0.saturating_sub(w[0].vsync.0))
        .filter(|g| *g > 0)
        .collect();
    let period = median(&mut gaps).ok_or("every present had the same vsync")?;
    let half = period / 2;
    let mut edges: Vec<(u64, bool)> = Vec::new();
    // Where edges went missing: the edge before each loss, and the loss's report.
    let mut losses: Vec<(u64, u64)> = Vec::new();
    let mut edges_lost = 0;
    for e in &log.light {
        match e {
            LightEvent::Edge(e) => edges.push((e.host_time.0, e.rising)),
            LightEvent::Lost { count, host_time } => {
                edges_lost += count;
                losses.push((edges.last().map_or(0, |e| e.0), host_time.0));
            }
        }
    }
    edges.sort_by_key(|e| e.0);
    // The light is unknown from the edge before a loss to the first edge after its report.
    let lost_spans: Vec<(u64, u64)> = losses
        .iter()
        .map(|&(before, report)| {
            let after = edges
                .iter()
                .find(|e| e.0 >= report)
                .map_or(u64::MAX, |e| e.0);
            (before, after)
        })
        .collect();

    // 1. The anchor.
    let first_white = presents
        .iter()
        .position(|p| p.white)
        .ok_or("the marker patch was never white while the light was watched")?;
    let v0 = presents[first_white].vsync.0;
    let limit = v0 + u64::try_from(max_latency.as_nanos()).unwrap_or(u64::MAX);
    let Some(&(t0, _)) = edges.iter().find(|e| e.1 && e.0 >= v0 && e.0 <= limit) else {
        return Err(format!(
            "no light came on within {} ms of the first white marker patch: is the photodiode over \
             the patch (display.marker_patch.corner) and its threshold between the patch's black \
             and white? ({} edges seen)",
            max_latency.as_millis(),
            edges.len()
        ));
    };

    // 2. Follow the transitions.
    let mut report = PhotonReport {
        refresh_period: Duration::from_nanos(period),
        edges: edges.len() as u64,
        edges_lost,
        ..Default::default()
    };
    let mut latency = t0 - v0;
    let mut recent: Vec<u64> = Vec::new();
    let mut used = vec![false; edges.len()];
    // Per present: the latency in effect, and its edge when matched.
    let mut at_present: Vec<(u64, Option<u64>)> = vec![(latency, None); presents.len()];
    let mut prev_white = false;
    let mut cursor = 0;
    for (i, p) in presents.iter().enumerate().skip(first_white) {
        at_present[i].0 = latency;
        let changed = p.white != prev_white;
        prev_white = p.white;
        if !changed {
            continue;
        }
        report.transitions += 1;
        let expected = p.vsync.0 + latency;
        let (lo, hi) = (expected.saturating_sub(half), expected + half);
        while cursor < edges.len() && edges[cursor].0 < lo {
            cursor += 1;
        }
        let found = (cursor..edges.len())
            .take_while(|&k| edges[k].0 < hi)
            .find(|&k| !used[k] && edges[k].1 == p.white);
        let Some(k) = found else {
            continue;
        };
        used[k] = true;
        let t = edges[k].0;
        report.matched += 1;
        let l = t.saturating_sub(p.vsync.0);
        report.vsync_to_photons.push(Duration::from_nanos(l));
        report
            .presented_to_photons
            .push(Duration::from_nanos(t.saturating_sub(p.at.0)));
        at_present[i].1 = Some(t);
        recent.push(l);
        if recent.len() > 16 {
            recent.remove(0);
        }
        latency = median(&mut recent.clone()).unwrap_or(latency);
    }

    // The lit time of a refresh: rising edge to the next falling one.
    let mut widths: Vec<u64> = edges
        .iter()
        .enumerate()
        .filter(|(_, e)| e.1)
        .filter_map(|(k, e)| edges[k + 1..].iter().find(|f| !f.1).map(|f| f.0 - e.0))
        .collect();
    let width = median(&mut widths).unwrap_or(period);
    report.pulse_width = Duration::from_nanos(width);
    let into = (period / 4).min(width / 2);

    // 3. Judge every refresh by the light in the middle of its lit time.
    let mut seen: std::collections::BTreeMap<u64, bool> = Default::default();
    for (i, p) in presents.iter().enumerate().skip(first_white) {
        let sample = p.vsync.0 + at_present[i].0 + into;
        if sample >= until.0 {
            break;
        }
        if lost_spans.iter().any(|(a, b)| (*a..*b).contains(&sample)) {
            report.refreshes_unknown += 1;
            continue;
        }
        let on = edges
            .iter()
            .rev()
            .find(|e| e.0 <= sample)
            .is_some_and(|e| e.1);
        report.refreshes_checked += 1;
        let ok = on == p.white;
        if !ok {
            report.refreshes_wrong.push((p.vsync, p.frame));
        }
        *seen.entry(p.frame).or_default() |= ok;
    }
    report.frames_checked = seen.len() as u64;
    report.frames_never_seen = seen
        .into_iter()
        .filter(|(_, ok)| !ok)
        .map(|(f, _)| f)
        .collect();

    // 4. Gaze sample to photons.
    let start = presents[first_white].at;
    for c in log.gaze_commands.iter().filter(|c| c.at >= start) {
        let Some(&(frame, _)) = log.renders.iter().find(|(_, t)| *t >= c.at) else {
            continue;
        };
        let Some(i) = presents.iter().position(|p| p.frame == frame && !p.repeat) else {
            continue;
        };
        let (Some(t), p) = (at_present[i].1, presents[i]) else {
            continue;
        };
        let ns = |a: Timestamp, b: u64| Duration::from_nanos(b.saturating_sub(a.0));
        report.gaze_to_photons.push(GazeToPhotons {
            command: c.id,
            gaze_received: c.gaze_received,
            frame,
            total: ns(c.gaze_received, t),
            gaze_to_command: ns(c.gaze_received, c.at.0),
            command_to_vsync: ns(c.at, p.vsync.0),
            vsync_to_photons: ns(p.vsync, t),
        });
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_core::LightEdge;

    const T: u64 = 11_111_111;

    fn edge(t: u64, rising: bool) -> LightEvent {
        LightEvent::Edge(LightEdge {
            device_time: Timestamp(t),
            host_receive_time: Timestamp(t),
            host_time: Timestamp(t),
            rising,
            level: None,
        })
    }

    /// Presents toggling every frame from vsync 0 on; a panel with `latency` (ns), holding
    /// its light, or pulsing `pulse` ns; refresh `drop` shows the previous image again.
    fn run(n: u64, latency: u64, pulse: Option<u64>, drop: Option<u64>) -> PhotonLog {
        let mut log = PhotonLog::default();
        let mut shown = false;
        for k in 0..n {
            let v = 1_000_000_000 + k * T;
            let white = k % 2 == 0;
            log.presents.push(PresentRec {
                at: Timestamp(v - 2_000_000),
                vsync: Timestamp(v),
                frame: k,
                white,
                repeat: false,
            });
            let showing = if drop == Some(k) { shown } else { white };
            match pulse {
                None if showing != shown => log.light.push(edge(v + latency, showing)),
                None => {}
                Some(w) if showing => {
                    log.light.push(edge(v + latency, true));
                    log.light.push(edge(v + latency + w, false));
                }
                Some(_) => {}
            }
            shown = showing;
        }
        log
    }

    #[test]
    fn latency_is_recovered_on_held_and_pulsed_panels_even_past_a_refresh() {
        for (latency, pulse) in [
            (4_000_000, None),
            (4_000_000, Some(2_000_000)),
            // Longer than a refresh: the anchor tells it from a shorter one.
            (27_500_000, None),
            (27_500_000, Some(1_500_000)),
        ] {
            let log = run(100, latency, pulse, None);
            let r = analyse(&log, Timestamp(u64::MAX), Duration::from_millis(250)).unwrap();
            assert!(!r.vsync_to_photons.is_empty());
            assert!(
                r.vsync_to_photons
                    .iter()
                    .all(|d| d.as_nanos() as u64 == latency),
                "{latency} {pulse:?}: {:?}",
                &r.vsync_to_photons[..3]
            );
            assert!(r
                .presented_to_photons
                .iter()
                .all(|d| d.as_nanos() as u64 == latency + 2_000_000));
            assert_eq!(r.refreshes_checked, 100, "{latency} {pulse:?}");
            assert!(
                r.refreshes_wrong.is_empty(),
                "{latency} {pulse:?}: {:?}",
                r.refreshes_wrong
            );
            assert_eq!(r.frames_never_seen, Vec::<u64>::new());
        }
    }

    #[test]
    fn a_dropped_refresh_is_one_refresh_and_one_frame_not_seen() {
        for pulse in [None, Some(2_000_000)] {
            for drop in [40, 41] {
                let log = run(100, 4_000_000, pulse, Some(drop));
                let r = analyse(&log, Timestamp(u64::MAX), Duration::from_millis(250)).unwrap();
                let wrong: Vec<u64> = r.refreshes_wrong.iter().map(|w| w.1).collect();
                assert_eq!(wrong, [drop], "{pulse:?} {drop}");
                assert_eq!(r.frames_never_seen, [drop]);
            }
        }
    }

    #[test]
    fn no_light_is_a_clear_error_and_losses_are_not_judged() {
        let mut log = run(20, 4_000_000, None, None);
        log.light.clear();
        let e = analyse(&log, Timestamp(u64::MAX), Duration::from_millis(250)).unwrap_err();
        assert!(e.contains("marker_patch.corner"), "{e}");

        // Edges 10 and 11 lost: the refreshes whose light fell among them are not judged.
        let mut log = run(40, 4_000_000, None, None);
        let lost_at = match log.light[11] {
            LightEvent::Edge(e) => e.host_time,
            _ => unreachable!(),
        };
        log.light.drain(10..12);
        log.light.insert(
            10,
            LightEvent::Lost {
                count: 2,
                host_time: lost_at,
            },
        );
        let r = analyse(&log, Timestamp(u64::MAX), Duration::from_millis(250)).unwrap();
        assert!(r.refreshes_wrong.is_empty(), "{:?}", r.refreshes_wrong);
        assert!(r.refreshes_unknown >= 2);
        assert_eq!(r.edges_lost, 2);
    }

    #[test]
    fn gaze_to_photons_follows_the_first_frame_requested_after_the_command() {
        let mut log = run(30, 4_000_000, None, None);
        // Frame k is requested one refresh before its vsync.
        for k in 0..30 {
            log.renders.push((k, Timestamp(1_000_000_000 + k * T - T)));
        }
        // A command 3 ms after frame 10's request: frame 11 is the first rendered for it.
        let at = Timestamp(1_000_000_000 + 9 * T + 3_000_000);
        log.gaze_commands.push(GazeCommand {
            id: 7,
            at,
            gaze_received: Timestamp(at.0 - 500_000),
        });
        let r = analyse(&log, Timestamp(u64::MAX), Duration::from_millis(250)).unwrap();
        let g = r.gaze_to_photons[0];
        assert_eq!((g.command, g.frame), (7, 11));
        assert_eq!(g.gaze_to_command, Duration::from_micros(500));
        assert_eq!(
            g.command_to_vsync.as_nanos() as u64,
            1_000_000_000 + 11 * T - at.0
        );
        assert_eq!(g.vsync_to_photons, Duration::from_millis(4));
        assert_eq!(
            g.total,
            g.gaze_to_command + g.command_to_vsync + g.vsync_to_photons
        );
    }
}
