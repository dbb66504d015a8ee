//! Log lines for things that repeat (a bad frame in a looping sequence, an application
//! sending the wrong size at 30 Hz): the first of each kind in full, then at most one
//! summary a minute of what repeated since, so a log stays readable however long it runs.
//!
//! Time is passed in (host time, [`Timestamp`]): the summaries are deterministic under a
//! simulated clock.

use std::collections::BTreeMap;
use std::time::Duration;

use dioptra_core::Timestamp;

/// At most one summary per this long.
pub const SUMMARY_EVERY: Duration = Duration::from_secs(60);

/// What to log for one occurrence ([`Repeats::note`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Note {
    /// The first of its kind: log it in full.
    First,
    /// Repeats since the last summary, due now: log this line (it lists each kind that
    /// repeated, how often, and its latest message).
    Summary(String),
    /// A repeat, counted for the next summary.
    Counted,
}

#[derive(Debug, Default)]
struct Kind {
    total: u64,
    since_summary: u64,
    latest: String,
}

/// The occurrences of one log's kinds (a sequence's frames, a stream's refusal reasons).
#[derive(Debug)]
pub struct Repeats {
    /// What repeats, for the summary: "frames skipped", "frames refused".
    what: &'static str,
    kinds: BTreeMap<String, Kind>,
    last_summary: Option<Timestamp>,
}

impl Repeats {
    pub fn new(what: &'static str) -> Repeats {
        Repeats {
            what,
            kinds: BTreeMap::new(),
            last_summary: None,
        }
    }

    /// One occurrence of `kind` at `now`, its message `message`: whether to log it in full,
    /// log a summary, or only count it.
    pub fn note(&mut self, kind: &str, message: &str, now: Timestamp) -> Note {
        let first = !self.kinds.contains_key(kind);
        let k = self.kinds.entry(kind.to_string()).or_default();
        k.total += 1;
        k.latest = message.to_string();
        if first {
            // The first of a kind starts its own minute: a summary right after it would only
            // repeat it.
            self.last_summary.get_or_insert(now);
            return Note::First;
        }
        k.since_summary += 1;
        let due = self
            .last_summary
            .is_none_or(|t| now.saturating_since(t) >= SUMMARY_EVERY);
        if !due {
            return Note::Counted;
        }
        let since = self.last_summary.map(|t| now.saturating_since(t));
        self.last_summary = Some(now);
        let repeated: Vec<String> = self
            .kinds
            .iter_mut()
            .filter(|(_, k)| k.since_summary > 0)
            .map(|(name, k)| {
                let line = format!(
                    "{name}: {} {} ({} in all; the latest: {})",
                    k.since_summary,
                    if k.since_summary == 1 {
                        "time"
                    } else {
                        "times"
                    },
                    k.total,
                    k.latest
                );
                k.since_summary = 0;
                line
            })
            .collect();
        let n: u64 = repeated.len() as u64;
        Note::Summary(format!(
            "{} again in the last {:.0} s ({n} {}): {}",
            self.what,
            since.unwrap_or_default().as_secs_f64(),
            if n == 1 { "kind" } else { "kinds" },
            repeated.join("; ")
        ))
    }

    /// Occurrences of `kind` so far.
    pub fn total(&self, kind: &str) -> u64 {
        self.kinds.get(kind).map_or(0, |k| k.total)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(s: u64) -> Timestamp {
        Timestamp(s * 1_000_000_000)
    }

    /// A line logged where nothing listens.
    fn a_line_two_threads_log() {
        tracing::info!("the line two threads log");
    }

    /// The lost-lens test's flake, made certain: with one capture alive, tracing asked only the
    /// registering thread's subscriber for a callsite's interest, so a callsite first reached on
    /// a thread without one was cached "never" and the capture missed it.
    #[test]
    fn a_capture_sees_a_callsite_another_thread_reached_first() {
        let (logs, _capture) = capture::logs(tracing::Level::INFO);
        std::thread::spawn(a_line_two_threads_log).join().unwrap();
        a_line_two_threads_log();
        assert_eq!(
            logs.with("the line two threads log").len(),
            1,
            "{:?}",
            logs.lines()
        );
    }

    #[test]
    fn the_first_of_each_kind_is_logged_then_one_summary_a_minute() {
        let mut r = Repeats::new("frames skipped");
        assert_eq!(r.note("frame 17", "a", at(0)), Note::First);
        assert_eq!(r.note("frame 33", "b", at(1)), Note::First);
        // Every 300 ms for 10 minutes: frame 17 and 33 again and again.
        let mut summaries = Vec::new();
        let mut t = 1_300_000_000u64;
        while t < 600_000_000_000 {
            for (kind, msg) in [("frame 17", "a2"), ("frame 33", "b2")] {
                match r.note(kind, msg, Timestamp(t)) {
                    Note::First => panic!("{kind} at {t} ns logged in full again"),
                    Note::Summary(s) => summaries.push((t, s)),
                    Note::Counted => {}
                }
            }
            t += 300_000_000;
        }
        // At most one a minute: 9 in 599 s, each at least 60 s after the one before.
        assert_eq!(summaries.len(), 9, "{summaries:?}");
        for w in summaries.windows(2) {
            assert!(w[1].0 - w[0].0 >= 60_000_000_000, "{w:?}");
        }
        // Each lists both frames with how often each came since the one before.
        let counted = |s: &str, kind: &str| -> u64 {
            let at = s.find(&format!("{kind}: ")).unwrap() + kind.len() + 2;
            s[at..].split(' ').next().unwrap().parse().unwrap()
        };
        for (_, s) in &summaries {
            assert!(s.starts_with("frames skipped again in the last 6"), "{s}");
            assert!(
                s.contains("(2 kinds)") && s.contains("the latest: b2"),
                "{s}"
            );
        }
        // The first at 60.1 s (1.3 s + 196 x 0.3 s), on frame 17's 197th repeat; frame 33's
        // 196th came before it.
        let (t, s) = &summaries[0];
        assert_eq!(*t, 60_100_000_000);
        assert!(
            s.contains("frame 17: 197 times (198 in all; the latest: a2); frame 33: 196 times"),
            "{s}"
        );
        let summed: u64 = summaries
            .iter()
            .map(|(_, s)| counted(s, "frame 17") + counted(s, "frame 33"))
            .sum();
        // Every repeat is in a summary but those since the last one.
        assert!(
            summed <= 2 * 1996 && 2 * 1996 - summed < 2 * 200,
            "{summed}"
        );
        assert_eq!(r.total("frame 17") + r.total("frame 33"), 2 + 2 * 1996);
    }
}

/// Tests' view of what a piece of code logged: the lines a `fmt` subscriber writes, caught on
/// this thread.
#[cfg(test)]
pub(crate) mod capture {
    use std::sync::{Arc, Mutex};

    #[derive(Clone, Default)]
    pub(crate) struct Lines(Arc<Mutex<Vec<u8>>>);

    impl std::io::Write for Lines {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            dioptra_core::lock(&self.0).extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl<'a> tracing_subscriber::fmt::MakeWriter<'a> for Lines {
        type Writer = Lines;
        fn make_writer(&'a self) -> Lines {
            self.clone()
        }
    }

    impl Lines {
        /// The lines logged so far.
        pub(crate) fn lines(&self) -> Vec<String> {
            String::from_utf8_lossy(&dioptra_core::lock(&self.0))
                .lines()
                .map(str::to_string)
                .collect()
        }
        /// The lines logged so far that contain `text`.
        pub(crate) fn with(&self, text: &str) -> Vec<String> {
            self.lines()
                .into_iter()
                .filter(|l| l.contains(text))
                .collect()
        }
    }

    /// The process's global subscriber in tests: it takes no event, but it keeps every
    /// callsite's cached interest at "sometimes". Without it a callsite first reached on a
    /// thread with no subscriber, while a capture starts on another, could cache "never" and
    /// the capture lose its event; with it each event asks the thread's own subscriber.
    struct KeepsInterest;

    impl tracing::Subscriber for KeepsInterest {
        fn register_callsite(
            &self,
            _: &'static tracing::Metadata<'static>,
        ) -> tracing::subscriber::Interest {
            tracing::subscriber::Interest::sometimes()
        }
        fn max_level_hint(&self) -> Option<tracing::level_filters::LevelFilter> {
            Some(tracing::level_filters::LevelFilter::TRACE)
        }
        fn enabled(&self, _: &tracing::Metadata<'_>) -> bool {
            false
        }
        fn new_span(&self, _: &tracing::span::Attributes<'_>) -> tracing::span::Id {
            tracing::span::Id::from_u64(1)
        }
        fn record(&self, _: &tracing::span::Id, _: &tracing::span::Record<'_>) {}
        fn record_follows_from(&self, _: &tracing::span::Id, _: &tracing::span::Id) {}
        fn event(&self, _: &tracing::Event<'_>) {}
        fn enter(&self, _: &tracing::span::Id) {}
        fn exit(&self, _: &tracing::span::Id) {}
    }

    /// What keeps a capture going: the thread's subscriber.
    pub(crate) struct Capture {
        _default: tracing::subscriber::DefaultGuard,
    }

    /// Catches this thread's events from `level` up until the guard is dropped.
    pub(crate) fn logs(level: tracing::Level) -> (Lines, Capture) {
        static GLOBAL: std::sync::Once = std::sync::Once::new();
        GLOBAL.call_once(|| {
            // Fails only if a global subscriber is set already; then that one decides.
            let _ = tracing::subscriber::set_global_default(KeepsInterest);
        });
        let lines = Lines::default();
        let subscriber = tracing_subscriber::fmt()
            .with_max_level(level)
            .with_writer(lines.clone())
            .without_time()
            .finish();
        let default = tracing::subscriber::set_default(subscriber);
        tracing::callsite::rebuild_interest_cache();
        (lines, Capture { _default: default })
    }
}
