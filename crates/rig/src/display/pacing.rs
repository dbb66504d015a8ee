//! Whether the display gets a new frame at each refresh, and what the log says when it does
//! not ([`Pacing`]). A refresh that shows the previous frame again (the next one was not
//! rendered in time) is a miss: the first is logged at once, then a summary at most every
//! [`SUMMARY_EVERY`] while misses go on (never a line per frame), and a line when frames are
//! on time again. A rig that has shown no frame at all says so too. `/status.display` shows
//! the distinct frames per second beside the refreshes per second ([`PacingStatus`]).
//!
//! Pure bookkeeping on the rig's clock: the loop's observer feeds it the presents and wakes
//! it when [`Pacing::next_check`] falls due, and logs what it returns.

use std::collections::VecDeque;
use std::time::Duration;

use dioptra_core::Timestamp;
use serde::Serialize;

/// Misses after the first are summarised at most this often.
pub const SUMMARY_EVERY: Duration = Duration::from_secs(5);
/// The frame rates `/status` shows are over this much of the newest presents.
pub const RATE_WINDOW: Duration = Duration::from_secs(2);
/// A rig that has shown no frame this long after its start says so.
pub const FIRST_FRAME_WAIT: Duration = Duration::from_secs(2);

/// What `/status.display` shows of the pacing.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PacingStatus {
    /// Refreshes that showed a frame (multifocal: plane cycles), repeats included.
    pub refreshes: u64,
    /// Refreshes that showed a new frame.
    pub distinct_frames: u64,
    /// Refreshes that showed the previous frame again (a missed deadline).
    pub repeated_refreshes: u64,
    /// Over the newest [`RATE_WINDOW`]: new frames per second, and refreshes per second.
    pub distinct_fps: Option<f64>,
    pub refresh_hz: Option<f64>,
    /// Misses in the newest [`RATE_WINDOW`]: the rig is not keeping up now.
    pub late: bool,
    /// No frame shown [`FIRST_FRAME_WAIT`] or more after the start: what the log said (for
    /// `/status.problems`; the log has it, `/status.display` its counts).
    #[serde(skip)]
    pub no_frame: Option<String>,
}

/// A line for the log.
#[derive(Debug, Clone, PartialEq)]
pub enum Notice {
    /// The first miss (or the first after frames were on time again).
    FirstMiss(String),
    /// Misses since the last notice.
    Summary(String),
    /// No miss in the last summary period after misses.
    OnTime(String),
    /// No frame shown yet.
    NoFrame(String),
}

impl Notice {
    pub fn text(&self) -> &str {
        match self {
            Notice::FirstMiss(s) | Notice::Summary(s) | Notice::OnTime(s) | Notice::NoFrame(s) => s,
        }
    }
}

/// Counts refreshes and misses and decides what to log.
#[derive(Debug)]
pub struct Pacing {
    /// The display's refresh period (multifocal: the plane cycle), for the messages.
    period: Duration,
    /// What would make frames fit, for the messages (config keys).
    advice: String,
    start: Timestamp,
    status: PacingStatus,
    /// The newest presents: (when, a repeat).
    recent: VecDeque<(Timestamp, bool)>,
    /// Since the last notice: refreshes and repeats.
    since: (u64, u64),
    /// When the last notice was given; `None`: frames are on time (no miss since the last
    /// on-time notice, or ever).
    late_since: Option<Timestamp>,
    /// The newest render's time.
    last_render: Option<Duration>,
    /// A no-frame notice was given at this time.
    no_frame_at: Option<Timestamp>,
}

impl Pacing {
    /// `period`: the refresh period frames are paced at; `advice`: what the messages suggest
    /// when frames are late (config keys to turn).
    pub fn new(start: Timestamp, period: Duration, advice: String) -> Pacing {
        Pacing {
            period,
            advice,
            start,
            status: PacingStatus::default(),
            recent: VecDeque::new(),
            since: (0, 0),
            late_since: None,
            last_render: None,
            no_frame_at: None,
        }
    }

    pub fn status(&self) -> &PacingStatus {
        &self.status
    }

    /// A render finished in `took`.
    pub fn rendered(&mut self, took: Duration) {
        self.last_render = Some(took);
    }

    fn ms(d: Duration) -> f64 {
        d.as_secs_f64() * 1e3
    }

    fn render_note(&self) -> String {
        match self.last_render {
            Some(r) => format!(
                "the newest render took {:.1} ms against a refresh period of {:.1} ms",
                Self::ms(r),
                Self::ms(self.period)
            ),
            None => format!("refresh period {:.1} ms", Self::ms(self.period)),
        }
    }

    /// A refresh showed a frame (`repeat`: the previous one again).
    pub fn presented(&mut self, now: Timestamp, frame: u64, repeat: bool) -> Option<Notice> {
        let st = &mut self.status;
        st.refreshes += 1;
        if repeat {
            st.repeated_refreshes += 1;
        } else {
            st.distinct_frames += 1;
        }
        self.since.0 += 1;
        self.since.1 += u64::from(repeat);
        self.recent.push_back((now, repeat));
        while self
            .recent
            .front()
            .is_some_and(|(t, _)| now.saturating_since(*t) > RATE_WINDOW)
        {
            self.recent.pop_front();
        }
        self.rates(now);
        self.no_frame_at = None;
        self.status.no_frame = None;
        if repeat && self.late_since.is_none() {
            self.late_since = Some(now);
            self.since = (0, 0);
            return Some(Notice::FirstMiss(format!(
                "frames are late: refresh at {:.3} s showed frame {frame} again, the next not \
                 rendered in time ({}); a summary follows at most every {} s while frames are \
                 late. To fit: {}",
                now.saturating_since(self.start).as_secs_f64(),
                self.render_note(),
                SUMMARY_EVERY.as_secs(),
                self.advice
            )));
        }
        self.check(now)
    }

    fn rates(&mut self, now: Timestamp) {
        let st = &mut self.status;
        let span = match self.recent.front() {
            Some((first, _)) if self.recent.len() > 1 => now.saturating_since(*first),
            _ => Duration::ZERO,
        };
        if span.is_zero() {
            st.distinct_fps = None;
            st.refresh_hz = None;
            st.late = self.recent.iter().any(|r| r.1);
            return;
        }
        // Intervals between the presents kept: n - 1 of them over the span.
        let n = self.recent.len() as f64 - 1.0;
        let new = self.recent.iter().skip(1).filter(|r| !r.1).count() as f64;
        st.refresh_hz = Some(n / span.as_secs_f64());
        st.distinct_fps = Some(new / span.as_secs_f64());
        st.late = self.recent.iter().any(|r| r.1);
    }

    /// When [`Pacing::check`] should run next (`None`: nothing to watch).
    pub fn next_check(&self) -> Option<Timestamp> {
        if self.status.refreshes == 0 {
            let first = self.start.saturating_add(FIRST_FRAME_WAIT);
            return Some(match self.no_frame_at {
                Some(t) => t.saturating_add(SUMMARY_EVERY),
                None => first,
            });
        }
        self.late_since.map(|t| t.saturating_add(SUMMARY_EVERY))
    }

    /// A summary, an on-time note or a no-frame note when one is due at `now`.
    pub fn check(&mut self, now: Timestamp) -> Option<Notice> {
        let due = self.next_check().is_some_and(|t| t <= now);
        if !due {
            return None;
        }
        if self.status.refreshes == 0 {
            self.no_frame_at = Some(now);
            let line = format!(
                "no frame shown {:.1} s after start: the first render has not finished ({}). \
                 To fit: {}",
                now.saturating_since(self.start).as_secs_f64(),
                self.render_note(),
                self.advice
            );
            self.status.no_frame = Some(line.clone());
            return Some(Notice::NoFrame(line));
        }
        let since = self.late_since?;
        let span = now.saturating_since(since).as_secs_f64();
        let (refreshes, repeats) = std::mem::take(&mut self.since);
        if repeats == 0 {
            self.late_since = None;
            return Some(Notice::OnTime(format!(
                "frames on time again: no refresh repeated a frame in the last {span:.1} s"
            )));
        }
        self.late_since = Some(now);
        let distinct = refreshes - repeats;
        Some(Notice::Summary(format!(
            "frames late in the last {span:.1} s: {repeats} of {refreshes} refreshes repeated a \
             frame; {distinct} distinct frames ({:.1}/s against {:.1} refreshes/s); {}",
            distinct as f64 / span,
            refreshes as f64 / span,
            self.render_note()
        )))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(ms: u64) -> Timestamp {
        Timestamp(ms * 1_000_000)
    }

    /// Every refresh of 60 Hz for `secs`, a new frame every `every` refreshes: the notices.
    fn run(p: &mut Pacing, from_ms: u64, secs: u64, every: u64) -> Vec<Notice> {
        let mut out = Vec::new();
        let n = secs * 60;
        for i in 0..n {
            let t = at(from_ms + i * 1000 / 60);
            if let Some(c) = p.check(t) {
                out.push(c);
            }
            if let Some(c) = p.presented(t, i / every, i % every != 0) {
                out.push(c);
            }
        }
        out
    }

    #[test]
    fn a_late_rig_logs_its_first_miss_then_a_summary_every_few_seconds() {
        let mut p = Pacing::new(at(0), Duration::from_micros(16_667), "method".into());
        p.rendered(Duration::from_millis(40));
        // 20 s, a new frame every third refresh: 20 distinct frames a second of 60.
        let notes = run(&mut p, 0, 20, 3);
        assert!(matches!(notes[0], Notice::FirstMiss(_)), "{notes:?}");
        assert!(notes[0]
            .text()
            .contains("40.0 ms against a refresh period of 16.7 ms"));
        assert!(notes[0].text().contains("To fit: method"));
        let summaries = notes[1..]
            .iter()
            .filter(|n| matches!(n, Notice::Summary(_)))
            .count();
        // One per 5 s after the first miss: at 5, 10 and 15 s (20 s is past the run).
        assert_eq!(summaries, 3, "{notes:?}");
        assert_eq!(notes.len(), 4, "nothing else: {notes:?}");
        // From the first miss (16 ms) to 5.016 s: 299 refreshes, every third new.
        assert!(
            notes[1]
                .text()
                .contains("199 of 299 refreshes repeated a frame; 100 distinct frames (20.0/s"),
            "{}",
            notes[1].text()
        );
        let st = p.status();
        assert_eq!(st.refreshes, 1200);
        assert_eq!(st.distinct_frames, 400);
        assert_eq!(st.repeated_refreshes, 800);
        let fps = st.distinct_fps.unwrap();
        assert!((fps - 20.0).abs() < 0.6, "{fps}");
        assert!((st.refresh_hz.unwrap() - 60.0).abs() < 0.6);
        assert!(st.late);

        // On time from 20 s: the summary of the late seconds before, one on-time note, then
        // nothing.
        let notes = run(&mut p, 20_000, 12, 1);
        assert_eq!(notes.len(), 2, "{notes:?}");
        assert!(matches!(notes[0], Notice::Summary(_)));
        assert!(matches!(notes[1], Notice::OnTime(_)));
        assert!(!p.status().late);
        assert!((p.status().distinct_fps.unwrap() - 60.0).abs() < 0.6);
        // Late again: a first miss again.
        let notes = run(&mut p, 32_000, 1, 2);
        assert!(matches!(notes[0], Notice::FirstMiss(_)), "{notes:?}");
    }

    #[test]
    fn a_rig_on_time_logs_nothing() {
        let mut p = Pacing::new(at(0), Duration::from_micros(16_667), String::new());
        assert!(run(&mut p, 0, 30, 1).is_empty());
        assert_eq!(p.status().repeated_refreshes, 0);
        assert_eq!(p.next_check(), None);
    }

    #[test]
    fn a_rig_that_shows_nothing_says_so_every_few_seconds() {
        let mut p = Pacing::new(at(0), Duration::from_micros(16_667), "display.width".into());
        assert_eq!(p.next_check(), Some(at(2000)));
        assert_eq!(p.check(at(1999)), None);
        assert_eq!(p.status().no_frame, None, "within the grace period");
        let n = p.check(at(2000)).unwrap();
        assert!(matches!(n, Notice::NoFrame(_)));
        assert_eq!(p.status().no_frame.as_deref(), Some(n.text()));
        assert!(
            n.text().contains("no frame shown 2.0 s after start"),
            "{}",
            n.text()
        );
        assert!(n.text().contains("display.width"));
        assert_eq!(p.check(at(6999)), None);
        assert!(matches!(p.check(at(7000)), Some(Notice::NoFrame(_))));
        // The first frame: nothing to say (it is new).
        assert_eq!(p.presented(at(7500), 0, false), None);
        assert_eq!(p.next_check(), None);
        assert_eq!(p.status().no_frame, None);
    }
}
