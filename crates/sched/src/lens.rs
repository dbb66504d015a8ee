//! The lens as the scheduler models it: a second-order step response (natural frequency from
//! the 2 % settle time and the damping ratio, as `dioptra_sim::lens_model` simulates it),
//! propagated in closed form so a prediction costs a few exponentials, not an integration.

use std::time::Duration;

use dioptra_core::{Diopters, Timestamp};

/// How the lens responds to a command.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LensDynamics {
    /// Time for a step to settle within 2 % of its size.
    pub settle_time: Duration,
    /// Damping ratio of the step response (1 = critically damped).
    pub damping: f32,
    /// From the scheduler's command to the lens starting to move (USB, driver), when the
    /// command is applied on receipt.
    pub command_latency: Duration,
}

impl Default for LensDynamics {
    fn default() -> Self {
        // An Optotune EL-10-30 class lens behind a USB serial driver.
        LensDynamics {
            settle_time: Duration::from_millis(15),
            damping: 0.7,
            command_latency: Duration::from_micros(500),
        }
    }
}

impl LensDynamics {
    /// Natural frequency, rad/s: 2 % settling of a second-order system is t_s ≈ 4 / (ζ ω).
    pub fn omega(&self) -> f64 {
        let ts = self.settle_time.as_secs_f64().max(1e-4);
        4.0 / (f64::from(self.damping).max(0.05) * ts)
    }
}

/// Position and velocity relative to a target.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
struct Motion {
    t: Timestamp,
    power: f64,
    velocity: f64,
    target: f64,
}

/// Most commands waiting for their apply time that the model keeps (older ones are folded in).
const MAX_PENDING: usize = 8;

/// Predicts lens power at future times from the commands sent so far.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct LensPredictor {
    dynamics: LensDynamics,
    omega: f64,
    zeta: f64,
    state: Option<Motion>,
    /// Commands not yet applied at `state.t`: (apply time, power), in time order.
    pending: Vec<(Timestamp, f64)>,
}

impl LensPredictor {
    pub fn new(dynamics: LensDynamics) -> Self {
        LensPredictor {
            omega: dynamics.omega(),
            zeta: f64::from(dynamics.damping).max(0.05),
            dynamics,
            state: None,
            pending: Vec::with_capacity(MAX_PENDING),
        }
    }

    pub fn dynamics(&self) -> &LensDynamics {
        &self.dynamics
    }

    /// True once the model knows where the lens is (a command or a readback).
    pub fn is_known(&self) -> bool {
        self.state.is_some()
    }

    /// Forgets the lens's position (e.g. after the link was lost).
    pub fn forget(&mut self) {
        self.state = None;
        self.pending.clear();
    }

    /// A command that takes effect at `apply_at`.
    pub fn command(&mut self, apply_at: Timestamp, power: Diopters) {
        let p = f64::from(power.0);
        if !p.is_finite() {
            return;
        }
        let Some(s) = self.state else {
            // Nothing known: assume the lens already sits at its first target.
            self.state = Some(Motion {
                t: apply_at,
                power: p,
                velocity: 0.0,
                target: p,
            });
            return;
        };
        if apply_at <= s.t {
            let mut m = s;
            m.target = p;
            self.state = Some(m);
            self.pending.retain(|c| c.0 > s.t);
            return;
        }
        // A later command replaces any pending one at or after its time.
        self.pending.retain(|c| c.0 < apply_at);
        if self.pending.len() == MAX_PENDING {
            let first = self.pending.remove(0);
            let m = self.motion_at(first.0);
            self.state = Some(Motion {
                target: first.1,
                ..m
            });
        }
        self.pending.push((apply_at, p));
    }

    /// A measured power at `t`: re-anchors the model when it disagrees by more than `tol`.
    pub fn observe(&mut self, t: Timestamp, power: Diopters, tol: f32) {
        let p = f64::from(power.0);
        if !p.is_finite() {
            return;
        }
        match self.state {
            None => {
                self.state = Some(Motion {
                    t,
                    power: p,
                    velocity: 0.0,
                    target: p,
                })
            }
            Some(s) if t >= s.t => {
                let m = self.motion_at(t);
                if (m.power - p).abs() > f64::from(tol) {
                    self.pending.retain(|c| c.0 > t);
                    self.state = Some(Motion {
                        t,
                        power: p,
                        velocity: 0.0,
                        target: m.target,
                    });
                }
            }
            Some(_) => {}
        }
    }

    /// Predicted power at `t`; `None` when nothing is known.
    pub fn power_at(&self, t: Timestamp) -> Option<Diopters> {
        self.state?;
        Some(Diopters(self.motion_at(t).power as f32))
    }

    /// The power the lens is heading to once every pending command applied.
    pub fn final_target(&self) -> Option<Diopters> {
        let s = self.state?;
        let p = self.pending.last().map_or(s.target, |c| c.1);
        Some(Diopters(p as f32))
    }

    /// Predicted first time at or after `from` from which the lens stays within `tol` of its
    /// final target, searched in 0.25 ms steps up to 20 settle times.
    pub fn settled_by(&self, from: Timestamp, tol: f32) -> Option<Timestamp> {
        let target = f64::from(self.final_target()?.0);
        let last_apply = self.pending.last().map_or(from, |c| c.0.max(from));
        let step = Duration::from_micros(250);
        let horizon = self.dynamics.settle_time.saturating_mul(20);
        let mut t = last_apply;
        let mut since = None;
        while t <= last_apply + horizon {
            let m = self.motion_at(t);
            if (m.power - target).abs() <= f64::from(tol) {
                since.get_or_insert(t);
            } else {
                since = None;
            }
            // Within tolerance for one settle time without leaving it: settled.
            if since.is_some_and(|s: Timestamp| t.saturating_since(s) >= self.dynamics.settle_time)
            {
                return since;
            }
            t = t + step;
        }
        since
    }

    fn motion_at(&self, t: Timestamp) -> Motion {
        let Some(mut m) = self.state else {
            return Motion {
                t,
                power: 0.0,
                velocity: 0.0,
                target: 0.0,
            };
        };
        for &(at, p) in &self.pending {
            if at > t {
                break;
            }
            m = self.propagate(m, at);
            m.target = p;
        }
        self.propagate(m, t)
    }

    /// Exact solution of x'' + 2ζω x' + ω² x = 0 for x = power - target.
    fn propagate(&self, m: Motion, t: Timestamp) -> Motion {
        if t <= m.t {
            return m;
        }
        let dt = t.saturating_since(m.t).as_secs_f64();
        let (w, z) = (self.omega, self.zeta);
        let x0 = m.power - m.target;
        let v0 = m.velocity;
        let (x, v) = if (z - 1.0).abs() < 1e-6 {
            let (a, b) = (x0, v0 + w * x0);
            let e = (-w * dt).exp();
            ((a + b * dt) * e, (b - w * (a + b * dt)) * e)
        } else if z < 1.0 {
            let wd = w * (1.0 - z * z).sqrt();
            let (a, b) = (x0, (v0 + z * w * x0) / wd);
            let e = (-z * w * dt).exp();
            let (c, s) = ((wd * dt).cos(), (wd * dt).sin());
            let x = e * (a * c + b * s);
            let v = e * (-z * w * (a * c + b * s) + wd * (-a * s + b * c));
            (x, v)
        } else {
            let s = w * (z * z - 1.0).sqrt();
            let (r1, r2) = (-z * w + s, -z * w - s);
            let c1 = (v0 - r2 * x0) / (r1 - r2);
            let c2 = x0 - c1;
            let (e1, e2) = ((r1 * dt).exp(), (r2 * dt).exp());
            (c1 * e1 + c2 * e2, r1 * c1 * e1 + r2 * c2 * e2)
        };
        Motion {
            t,
            power: m.target + x,
            velocity: v,
            target: m.target,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(v: u64) -> Timestamp {
        Timestamp::from_millis(v)
    }

    /// The same second-order system integrated in small steps, as the simulator does.
    fn integrate(dyn_: &LensDynamics, from: f64, to: f64, t: f64) -> f64 {
        let w = dyn_.omega();
        let z = f64::from(dyn_.damping);
        let (mut p, mut v) = (from, 0.0);
        let h = 1e-6;
        let mut left = t;
        while left > 0.0 {
            let a = w * w * (to - p) - 2.0 * z * w * v;
            v += a * h;
            p += v * h;
            left -= h;
        }
        p
    }

    #[test]
    fn closed_form_matches_integration_for_all_dampings() {
        for damping in [0.4f32, 0.7, 1.0, 1.5] {
            let d = LensDynamics {
                damping,
                ..LensDynamics::default()
            };
            let mut p = LensPredictor::new(d);
            p.command(ms(0), Diopters(0.0));
            p.command(ms(10), Diopters(2.0));
            for t_ms in [11u64, 13, 17, 25, 40] {
                let want = integrate(&d, 0.0, 2.0, (t_ms - 10) as f64 * 1e-3);
                let got = f64::from(p.power_at(ms(t_ms)).unwrap().0);
                assert!(
                    (got - want).abs() < 2e-3,
                    "ζ={damping} t={t_ms}: {got} vs {want}"
                );
            }
        }
    }

    #[test]
    fn settles_within_its_settle_time_and_commands_chain() {
        let mut p = LensPredictor::new(LensDynamics::default());
        p.command(ms(0), Diopters(0.5));
        p.command(ms(100), Diopters(2.0));
        // Before the apply time nothing moves.
        assert_eq!(p.power_at(ms(99)), Some(Diopters(0.5)));
        let settled = p.settled_by(ms(100), 0.03).unwrap();
        let after = settled.saturating_since(ms(100));
        assert!(
            after >= Duration::from_millis(8) && after <= Duration::from_millis(16),
            "{after:?}"
        );
        // A second command mid-move takes over from the moving state.
        p.command(ms(105), Diopters(1.0));
        let mid = p.power_at(ms(105)).unwrap().0;
        assert!(mid > 0.6 && mid < 2.0, "{mid}");
        assert!((p.power_at(ms(200)).unwrap().0 - 1.0).abs() < 1e-3);
        assert_eq!(p.final_target(), Some(Diopters(1.0)));
    }

    #[test]
    fn readbacks_reanchor_a_wrong_model_and_bad_numbers_are_ignored() {
        let mut p = LensPredictor::new(LensDynamics::default());
        assert!(p.power_at(ms(0)).is_none());
        p.command(ms(0), Diopters(1.0));
        p.observe(ms(50), Diopters(3.0), 0.05);
        assert!((p.power_at(ms(50)).unwrap().0 - 3.0).abs() < 1e-4);
        // It still heads for the commanded target.
        assert!((p.power_at(ms(200)).unwrap().0 - 1.0).abs() < 1e-3);
        p.command(ms(300), Diopters(f32::NAN));
        p.observe(ms(300), Diopters(f32::INFINITY), 0.05);
        assert!(p.power_at(ms(400)).unwrap().0.is_finite());
    }
}
