//! Mapping a device's clock onto the host timeline, with drift.
//!
//! Two kinds of evidence: ping/pong exchanges (host send, device stamp, host receive), whose
//! midpoint bounds the offset by half the round trip, and one-way samples (device stamp, host
//! receive) from streams that have no ping, whose host time is the device time plus an unknown
//! non-negative latency. Either way the best evidence is the one with the least delay, so the
//! mapper keeps the best point per time bucket and fits `host = a + b * device` through them
//! (b = 1 until the points span long enough to measure drift).

use crate::time::Timestamp;

const BUCKET_US: u64 = 250_000;
const MAX_BUCKETS: usize = 64;
/// Points must span this much device time before drift is fitted.
const MIN_DRIFT_SPAN_US: u64 = 2_000_000;
/// Drift beyond this is taken as a bad fit, not a real oscillator (crystals: ±100 ppm).
const MAX_DRIFT_PPM: f64 = 1_000.0;

#[derive(Debug, Clone, Copy, PartialEq)]
struct Point {
    device_us: u64,
    /// Host-time estimate of the device stamp, ns.
    host_ns: f64,
    /// Delay that bounds this point's error (half round trip, or one-way excess), ns.
    delay_ns: f64,
}

/// Device-to-host clock mapping. Feed it evidence; ask it for host times.
#[derive(Debug, Clone, Default)]
pub struct ClockMapper {
    points: Vec<Point>,
    /// Fitted: host_ns = offset_ns + slope * (device_us - ref_us) * 1000.
    fit: Option<(u64, f64, f64)>,
    /// One-way evidence only ever bounds latency from above: remember which kind we have.
    one_way: bool,
}

impl ClockMapper {
    pub fn new() -> Self {
        Self::default()
    }

    /// A ping sent at `host_send`, stamped `device_time_us` by the device, answered at `host_receive`.
    pub fn add_exchange(
        &mut self,
        host_send: Timestamp,
        device_time_us: u64,
        host_receive: Timestamp,
    ) {
        if host_receive < host_send {
            return;
        }
        let rtt = (host_receive.0 - host_send.0) as f64;
        let mid = host_send.0 as f64 + rtt / 2.0;
        self.insert(Point {
            device_us: device_time_us,
            host_ns: mid,
            delay_ns: rtt / 2.0,
        });
    }

    /// A sample stamped `device_time_us` that reached the host at `host_receive`.
    pub fn add_one_way(&mut self, device_time_us: u64, host_receive: Timestamp) {
        self.one_way = true;
        // The delay is unknown; rank by the apparent offset so the least-delayed sample wins.
        let host = host_receive.0 as f64;
        let offset = host - device_time_us as f64 * 1000.0;
        self.insert(Point {
            device_us: device_time_us,
            host_ns: host,
            delay_ns: offset,
        });
    }

    fn insert(&mut self, p: Point) {
        let bucket = p.device_us / BUCKET_US;
        // A device clock that jumps backwards (reboot) invalidates everything before it.
        if let Some(last) = self.points.last() {
            if p.device_us + BUCKET_US < last.device_us {
                self.points.clear();
            }
        }
        match self
            .points
            .iter_mut()
            .find(|q| q.device_us / BUCKET_US == bucket)
        {
            Some(q) if p.delay_ns < q.delay_ns => *q = p,
            Some(_) => {}
            None => {
                self.points.push(p);
                if self.points.len() > MAX_BUCKETS {
                    self.points.remove(0);
                }
            }
        }
        self.refit();
    }

    fn refit(&mut self) {
        let Some(first) = self.points.first() else {
            self.fit = None;
            return;
        };
        let ref_us = first.device_us;
        let n = self.points.len() as f64;
        let xs = |p: &Point| (p.device_us - ref_us.min(p.device_us)) as f64 * 1000.0;
        // One-way points: the best one per bucket still carries its latency floor; fitting the
        // lower envelope is a least-squares fit through the per-bucket minima.
        let span_us = self
            .points
            .last()
            .map_or(0, |l| l.device_us.saturating_sub(ref_us));
        let mean_x = self.points.iter().map(xs).sum::<f64>() / n;
        let mean_y = self.points.iter().map(|p| p.host_ns).sum::<f64>() / n;
        let mut slope = 1.0;
        if span_us >= MIN_DRIFT_SPAN_US && self.points.len() >= 3 {
            let sxx: f64 = self.points.iter().map(|p| (xs(p) - mean_x).powi(2)).sum();
            let sxy: f64 = self
                .points
                .iter()
                .map(|p| (xs(p) - mean_x) * (p.host_ns - mean_y))
                .sum();
            if sxx > 0.0 {
                let s = sxy / sxx;
                if ((s - 1.0) * 1e6).abs() <= MAX_DRIFT_PPM {
                    slope = s;
                }
            }
        }
        let mut offset = mean_y - slope * mean_x;
        if self.one_way {
            // Lower envelope: no sample can arrive before it was stamped.
            let min_resid = self
                .points
                .iter()
                .map(|p| p.host_ns - (offset + slope * xs(p)))
                .fold(f64::INFINITY, f64::min);
            offset += min_resid;
        }
        self.fit = Some((ref_us, offset, slope));
    }

    /// Host time of a device timestamp; `None` before any evidence.
    pub fn to_host(&self, device_time_us: u64) -> Option<Timestamp> {
        let (ref_us, offset, slope) = self.fit?;
        let x = (device_time_us as f64 - ref_us as f64) * 1000.0;
        let ns = offset + slope * x;
        Some(Timestamp(ns.clamp(0.0, u64::MAX as f64) as u64))
    }

    /// Device clock rate error against the host's, parts per million, once measurable.
    pub fn drift_ppm(&self) -> Option<f64> {
        let (_, _, slope) = self.fit?;
        // host = device / (1 + ppm): a fast device clock has a slope below one.
        (slope != 1.0).then_some((1.0 / slope - 1.0) * 1e6)
    }

    /// Error bound of the best evidence, ns (half the smallest round trip); one-way-only
    /// mappers report `None`, as their latency is unknown.
    pub fn uncertainty_ns(&self) -> Option<f64> {
        if self.one_way {
            return None;
        }
        self.points.iter().map(|p| p.delay_ns).reduce(f64::min)
    }

    pub fn is_synced(&self) -> bool {
        self.fit.is_some()
    }

    /// Forgets everything (after a reconnect the device clock may have restarted).
    pub fn reset(&mut self) {
        *self = Self::default();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A device clock that starts at `start_us` when the host is at `host0_ns` and runs `ppm` fast.
    fn device_at(host_ns: u64, host0_ns: u64, start_us: u64, ppm: f64) -> u64 {
        start_us + ((host_ns - host0_ns) as f64 * (1.0 + ppm * 1e-6) / 1000.0) as u64
    }

    #[test]
    fn exchanges_recover_offset_and_drift() {
        let mut m = ClockMapper::new();
        assert_eq!(m.to_host(5), None);
        let (host0, start, ppm) = (10_000_000_000u64, 1_000u64, 50.0);
        // Pings once per 100 ms for 10 s with round trips between 0.2 and 2 ms.
        for i in 0..100u64 {
            let send = host0 + i * 100_000_000;
            let rtt = 200_000 + (i * 7919 % 10) * 200_000;
            let stamp = device_at(send + rtt / 2, host0, start, ppm);
            m.add_exchange(Timestamp(send), stamp, Timestamp(send + rtt));
        }
        let drift = m.drift_ppm().unwrap();
        assert!((drift - 50.0).abs() < 5.0, "drift {drift}");
        let probe_host = host0 + 9_876_543_210;
        let mapped = m.to_host(device_at(probe_host, host0, start, ppm)).unwrap();
        let err = mapped.signed_diff_ns(Timestamp(probe_host)).abs();
        assert!(err < 50_000, "error {err} ns");
        assert!(m.uncertainty_ns().unwrap() <= 100_000.0);
    }

    #[test]
    fn one_way_samples_find_the_latency_floor() {
        let mut m = ClockMapper::new();
        let host0 = 5_000_000_000u64;
        // 500 Hz for 4 s; latency 1 ms plus up to 3 ms of jitter.
        for i in 0..2000u64 {
            let stamp_host = host0 + i * 2_000_000;
            let latency = 1_000_000 + (i * 104_729 % 3_000_000);
            m.add_one_way(
                device_at(stamp_host, host0, 0, 0.0),
                Timestamp(stamp_host + latency),
            );
        }
        let mapped = m
            .to_host(device_at(host0 + 3_000_000_000, host0, 0, 0.0))
            .unwrap();
        let err = mapped.signed_diff_ns(Timestamp(host0 + 3_000_000_000));
        // Maps to stamp + minimum latency (1 ms), within the jitter of the best samples.
        assert!((900_000..1_300_000).contains(&err), "error {err} ns");
        assert_eq!(m.uncertainty_ns(), None);
    }

    #[test]
    fn device_clock_restart_discards_old_evidence() {
        let mut m = ClockMapper::new();
        m.add_exchange(Timestamp(1_000_000), 50_000_000, Timestamp(1_100_000));
        m.add_exchange(Timestamp(2_000_000), 10, Timestamp(2_100_000));
        let t = m.to_host(10).unwrap();
        assert_eq!(t, Timestamp(2_050_000));
        m.add_exchange(Timestamp(9), 0, Timestamp(3)); // receive before send: ignored
        assert_eq!(m.to_host(10).unwrap(), Timestamp(2_050_000));
    }
}
