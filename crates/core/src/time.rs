//! Time is passed in: one [`Timestamp`] type and a [`Clock`] trait, so the scheduler
//! and the simulators never read the wall clock themselves.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Nanoseconds on one host-side monotonic timeline.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct Timestamp(pub u64);

impl Timestamp {
    pub const ZERO: Timestamp = Timestamp(0);

    pub const fn from_nanos(ns: u64) -> Self {
        Timestamp(ns)
    }
    pub const fn from_micros(us: u64) -> Self {
        Timestamp(us.saturating_mul(1_000))
    }
    pub const fn from_millis(ms: u64) -> Self {
        Timestamp(ms.saturating_mul(1_000_000))
    }
    pub const fn as_nanos(self) -> u64 {
        self.0
    }
    pub const fn as_micros(self) -> u64 {
        self.0 / 1_000
    }
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 * 1e-9
    }
    /// `self - earlier`, or zero when `earlier` is later.
    pub fn saturating_since(self, earlier: Timestamp) -> Duration {
        Duration::from_nanos(self.0.saturating_sub(earlier.0))
    }
    /// Signed difference `self - other` in nanoseconds.
    pub fn signed_diff_ns(self, other: Timestamp) -> i64 {
        (self.0 as i128 - other.0 as i128).clamp(i64::MIN as i128, i64::MAX as i128) as i64
    }
    pub fn saturating_add(self, d: Duration) -> Timestamp {
        Timestamp(
            self.0
                .saturating_add(d.as_nanos().min(u64::MAX as u128) as u64),
        )
    }
    pub fn saturating_sub(self, d: Duration) -> Timestamp {
        Timestamp(
            self.0
                .saturating_sub(d.as_nanos().min(u64::MAX as u128) as u64),
        )
    }
}

impl std::ops::Add<Duration> for Timestamp {
    type Output = Timestamp;
    fn add(self, d: Duration) -> Timestamp {
        self.saturating_add(d)
    }
}

impl std::fmt::Display for Timestamp {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.6} s", self.as_secs_f64())
    }
}

/// A source of host time.
pub trait Clock: Send + Sync {
    fn now(&self) -> Timestamp;
}

/// The host's monotonic clock, counted from when this value was made.
#[derive(Debug, Clone)]
pub struct SystemClock {
    origin: Instant,
}

impl SystemClock {
    pub fn new() -> Self {
        SystemClock {
            origin: Instant::now(),
        }
    }
}

impl Default for SystemClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for SystemClock {
    fn now(&self) -> Timestamp {
        Timestamp(self.origin.elapsed().as_nanos().min(u64::MAX as u128) as u64)
    }
}

/// A clock that only moves when a test moves it. Clones share one time.
#[derive(Debug, Clone, Default)]
pub struct SimClock {
    now_ns: Arc<AtomicU64>,
}

impl SimClock {
    pub fn new(start: Timestamp) -> Self {
        SimClock {
            now_ns: Arc::new(AtomicU64::new(start.0)),
        }
    }
    pub fn advance(&self, d: Duration) -> Timestamp {
        let add = d.as_nanos().min(u64::MAX as u128) as u64;
        let prev = self
            .now_ns
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |t| {
                Some(t.saturating_add(add))
            })
            .unwrap_or_else(|t| t);
        Timestamp(prev.saturating_add(add))
    }
    /// Moves the clock to `t`; never backwards.
    pub fn set(&self, t: Timestamp) {
        self.now_ns.fetch_max(t.0, Ordering::AcqRel);
    }
}

impl Clock for SimClock {
    fn now(&self) -> Timestamp {
        Timestamp(self.now_ns.load(Ordering::Acquire))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sim_clock_moves_only_when_told_and_clones_share_time() {
        let c = SimClock::new(Timestamp::from_millis(5));
        let c2 = c.clone();
        assert_eq!(c.now(), Timestamp::from_millis(5));
        c.advance(Duration::from_micros(1500));
        assert_eq!(c2.now(), Timestamp(6_500_000));
        c.set(Timestamp::from_millis(1)); // backwards: ignored
        assert_eq!(c.now(), Timestamp(6_500_000));
    }

    #[test]
    fn timestamp_arithmetic_saturates() {
        let t = Timestamp(10);
        assert_eq!(t.saturating_since(Timestamp(20)), Duration::ZERO);
        assert_eq!(t.signed_diff_ns(Timestamp(25)), -15);
        assert_eq!(
            Timestamp(u64::MAX) + Duration::from_secs(1),
            Timestamp(u64::MAX)
        );
    }

    #[test]
    fn system_clock_is_monotonic() {
        let c = SystemClock::new();
        let a = c.now();
        let b = c.now();
        assert!(b >= a);
    }
}
