//! `dioptra serve` as a systemd service (`Type=notify`, `WatchdogSec=`; the unit is
//! `packaging/systemd/dioptra.service`), through the notify protocol (`sd-notify`):
//! `READY=1` once the rig is up (required devices connected) and the API listens;
//! `WATCHDOG=1` while the rig's loop turns, so that a hung loop stops the pings and systemd
//! restarts the daemon; `STOPPING=1` when the shutdown begins, whatever began it. Outside
//! systemd (no `NOTIFY_SOCKET`) nothing is sent, and without `WATCHDOG_USEC` no ping.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use dioptra_core::Timestamp;
use dioptra_rig::engine::Engine;
use dioptra_rig::executor::LoopHook;
use dioptra_rig::RigSetup;
use sd_notify::NotifyState;
use tokio_util::sync::CancellationToken;

use super::Listening;

/// The daemon's side of the notify protocol.
pub struct Service {
    /// `WatchdogSec=`'s period (systemd sets `WATCHDOG_USEC`, and `WATCHDOG_PID` when given
    /// is this process), and the loop's turns the watchdog watches.
    watchdog: Option<(Duration, Arc<AtomicU64>)>,
}

impl Service {
    /// Reads what systemd asks for; with a watchdog, adds to `setup` the loop hook that
    /// counts the loop's turns.
    pub fn from_env(setup: &mut RigSetup) -> Service {
        let watchdog = sd_notify::watchdog_enabled()
            .filter(|d| !d.is_zero())
            .map(|period| (period, Arc::new(AtomicU64::new(0))));
        if let Some((period, turns)) = &watchdog {
            setup.hooks.push(Box::new(LoopTurns {
                turns: turns.clone(),
                every: *period / 4,
                next: None,
            }));
        }
        Service { watchdog }
    }

    /// The rig runs and the API listens `at`: sends `READY=1`, then `WATCHDOG=1` every half
    /// period in which the loop turned, and `STOPPING=1` once `cancel` fires (a signal,
    /// `POST /shutdown`, the window closed), after which the pings stop.
    pub fn ready(self, at: &Listening, cancel: CancellationToken) {
        let status = match at {
            Listening::Tcp(a) => format!("API on http://{a}"),
            Listening::Unix(p) => format!("API on unix:{}", p.display()),
        };
        send(&[NotifyState::Ready, NotifyState::Status(&status)]);
        if let Some((period, turns)) = self.watchdog {
            tokio::spawn(ping_while_turning(turns, period / 2, cancel.clone()));
        }
        tokio::spawn(async move {
            cancel.cancelled().await;
            send(&[
                NotifyState::Stopping,
                NotifyState::Status("stopping: parking the lens, finishing files"),
            ]);
        });
    }
}

fn send(states: &[NotifyState]) {
    if let Err(e) = sd_notify::notify(states) {
        // A service manager that cannot be told is worth a line, not a failed rig.
        tracing::warn!("cannot notify systemd (NOTIFY_SOCKET): {e}");
    }
}

/// The watchdog's loop hook: counts the loop's turns, and wakes the loop when it has nothing
/// else to do (at least twice per check), so that an idle rig still turns. A loop that stops
/// turning (blocked, or waiting on something that never comes) stops the pings, and systemd
/// restarts the daemon one `WatchdogSec` later.
struct LoopTurns {
    turns: Arc<AtomicU64>,
    /// Wake the loop at least this often.
    every: Duration,
    next: Option<Timestamp>,
}

impl LoopTurns {
    fn turned(&mut self, now: Timestamp) {
        self.turns.fetch_add(1, Ordering::Relaxed);
        self.next = Some(now + self.every);
    }
}

impl LoopHook for LoopTurns {
    fn started(
        &mut self,
        now: Timestamp,
        _engine: &Engine,
        _sink: &dyn dioptra_rig::display::DisplaySink,
    ) {
        self.turned(now);
    }
    fn stepped(&mut self, now: Timestamp, _engine: &Engine) {
        self.turned(now);
    }
    fn next_wakeup(&self) -> Option<Timestamp> {
        self.next
    }
    fn wake(&mut self, now: Timestamp, _engine: &Engine) {
        self.turned(now);
    }
}

async fn ping_while_turning(turns: Arc<AtomicU64>, every: Duration, cancel: CancellationToken) {
    let mut pings = Pings::default();
    loop {
        tokio::select! {
            _ = cancel.cancelled() => return,
            _ = tokio::time::sleep(every) => {}
        }
        match pings.check(turns.load(Ordering::Relaxed)) {
            Verdict::Ping => send(&[NotifyState::Watchdog]),
            Verdict::Stalled => tracing::error!(
                "the rig's loop has not turned for {every:?}: no watchdog ping; systemd \
                 restarts the daemon if it stays stuck"
            ),
            Verdict::StillStalled => {}
        }
    }
}

/// Whether a watchdog period deserves a ping: only if the loop turned in it.
#[derive(Debug, Default)]
struct Pings {
    last: Option<u64>,
    stalled: bool,
}

#[derive(Debug, PartialEq, Eq)]
enum Verdict {
    Ping,
    /// The loop did not turn this period (said once per stall).
    Stalled,
    StillStalled,
}

impl Pings {
    fn check(&mut self, turns: u64) -> Verdict {
        let turned = self.last != Some(turns);
        self.last = Some(turns);
        if turned {
            self.stalled = false;
            Verdict::Ping
        } else if !self.stalled {
            self.stalled = true;
            Verdict::Stalled
        } else {
            Verdict::StillStalled
        }
    }
}

/// Whether stderr goes to the journal: systemd sets `JOURNAL_STREAM` to the device and inode
/// of the stream it connects to stdout and stderr, which a shell under the service (or a
/// redirect) no longer matches.
pub fn stderr_is_the_journal() -> bool {
    use std::os::fd::AsFd;
    use std::os::unix::fs::MetadataExt;
    let Some(stream) = std::env::var_os("JOURNAL_STREAM") else {
        return false;
    };
    let Some((dev, ino)) = stream.to_str().and_then(|s| s.split_once(':')) else {
        return false;
    };
    let (Ok(dev), Ok(ino)) = (dev.parse::<u64>(), ino.parse::<u64>()) else {
        return false;
    };
    std::io::stderr()
        .as_fd()
        .try_clone_to_owned()
        .map(std::fs::File::from)
        .and_then(|f| f.metadata())
        .is_ok_and(|m| m.dev() == dev && m.ino() == ino)
}

/// A log line for the journal: no timestamp of its own (the journal stamps each line), and
/// the level as a syslog priority prefix (`<4>` for WARN), which the journal takes off and
/// keeps as the line's priority (`journalctl -p warning`).
pub struct JournalLine<F>(pub F);

impl<S, N, F> tracing_subscriber::fmt::FormatEvent<S, N> for JournalLine<F>
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
    N: for<'a> tracing_subscriber::fmt::FormatFields<'a> + 'static,
    F: tracing_subscriber::fmt::FormatEvent<S, N>,
{
    fn format_event(
        &self,
        ctx: &tracing_subscriber::fmt::FmtContext<'_, S, N>,
        mut writer: tracing_subscriber::fmt::format::Writer<'_>,
        event: &tracing::Event<'_>,
    ) -> std::fmt::Result {
        write!(writer, "<{}>", syslog_priority(*event.metadata().level()))?;
        self.0.format_event(ctx, writer, event)
    }
}

/// sd-daemon(3)'s priorities: err, warning, info, debug.
fn syslog_priority(level: tracing::Level) -> u8 {
    match level {
        tracing::Level::ERROR => 3,
        tracing::Level::WARN => 4,
        tracing::Level::INFO => 6,
        _ => 7,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_period_without_a_loop_turn_gets_no_ping() {
        let mut p = Pings::default();
        assert_eq!(p.check(5), Verdict::Ping);
        assert_eq!(p.check(9), Verdict::Ping);
        assert_eq!(p.check(9), Verdict::Stalled);
        assert_eq!(p.check(9), Verdict::StillStalled);
        assert_eq!(p.check(10), Verdict::Ping);
        assert_eq!(p.check(10), Verdict::Stalled);
    }

    #[test]
    fn the_hook_counts_turns_and_wakes_an_idle_loop_within_its_interval() {
        let turns = Arc::new(AtomicU64::new(0));
        let mut hook = LoopTurns {
            turns: turns.clone(),
            every: Duration::from_millis(2500),
            next: None,
        };
        assert_eq!(hook.next_wakeup(), None);
        hook.turned(Timestamp::from_millis(1));
        hook.turned(Timestamp::from_millis(2));
        assert_eq!(
            hook.next_wakeup(),
            Some(Timestamp::from_millis(2) + Duration::from_millis(2500))
        );
        assert_eq!(turns.load(Ordering::Relaxed), 2);
    }
}
