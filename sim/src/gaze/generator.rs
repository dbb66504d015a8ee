//! An eye-movement generator driven by a scene: the eyes fixate targets at known depths
//! (with drift and microsaccades), saccade between them on the main sequence, pursue moving
//! targets, change vergence with the target's depth, and blink; the tracker adds noise and
//! drops eyes. Deterministic for a given seed.

use dioptra_protocol::{BinocularSample, EyeSample};

/// A point of interest in the scene, as seen from between the eyes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Target {
    pub yaw_deg: f64,
    pub pitch_deg: f64,
    /// Depth, diopters (1 / metres).
    pub diopters: f64,
}

/// One step of the viewer's script.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Segment {
    /// Look at a target (saccade there first if needed).
    Fixate { target: usize, ms: u32 },
    /// Follow a target moving in a straight line (angles and depth) from one target to another.
    Pursue { from: usize, to: usize, ms: u32 },
    /// Close the eyes.
    Blink { ms: u32 },
}

/// Where things are and what the viewer does; the script repeats.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    pub name: String,
    pub targets: Vec<Target>,
    pub script: Vec<Segment>,
}

/// Names accepted by [`Scene::named`].
pub const SCENARIOS: &[&str] = &["saccades", "fixation", "pursuit", "vergence", "blinks"];

fn t(yaw_deg: f64, pitch_deg: f64, diopters: f64) -> Target {
    Target {
        yaw_deg,
        pitch_deg,
        diopters,
    }
}

impl Scene {
    /// A built-in scenario (see [`SCENARIOS`]).
    pub fn named(name: &str) -> Option<Scene> {
        use Segment::*;
        let (targets, script) = match name {
            // Four objects at 0.5-3 D, 400 ms on each: saccades of 8-20 degrees with
            // vergence changes.
            "saccades" => (
                vec![
                    t(-10.0, 5.0, 0.5),
                    t(8.0, 4.0, 2.0),
                    t(6.0, -8.0, 1.0),
                    t(-6.0, -6.0, 3.0),
                ],
                (0..4).map(|i| Fixate { target: i, ms: 400 }).collect(),
            ),
            "fixation" => (
                vec![t(2.0, -1.0, 1.5)],
                vec![Fixate {
                    target: 0,
                    ms: 5000,
                }],
            ),
            "pursuit" => (
                vec![t(-12.0, 0.0, 1.0), t(12.0, 0.0, 2.0)],
                vec![
                    Fixate { target: 0, ms: 300 },
                    Pursue {
                        from: 0,
                        to: 1,
                        ms: 1500,
                    },
                    Fixate { target: 1, ms: 300 },
                    Pursue {
                        from: 1,
                        to: 0,
                        ms: 1500,
                    },
                ],
            ),
            // Straight ahead, near and far: vergence only.
            "vergence" => (
                vec![t(0.0, 0.0, 0.5), t(0.0, 0.0, 3.0)],
                vec![
                    Fixate {
                        target: 0,
                        ms: 1000,
                    },
                    Fixate {
                        target: 1,
                        ms: 1000,
                    },
                ],
            ),
            "blinks" => (
                vec![t(-4.0, 0.0, 1.0), t(4.0, 0.0, 1.0)],
                vec![
                    Fixate { target: 0, ms: 700 },
                    Blink { ms: 150 },
                    Fixate { target: 1, ms: 700 },
                    Blink { ms: 150 },
                ],
            ),
            _ => return None,
        };
        Some(Scene {
            name: name.to_string(),
            targets,
            script,
        })
    }

    fn validate(&self) -> Result<(), String> {
        if self.script.is_empty() {
            return Err("the script is empty".into());
        }
        for s in &self.script {
            let (ids, ms) = match *s {
                Segment::Fixate { target, ms } => (vec![target], ms),
                Segment::Pursue { from, to, ms } => (vec![from, to], ms),
                Segment::Blink { ms } => (vec![], ms),
            };
            if ms == 0 {
                return Err(format!("segment {s:?} has zero length"));
            }
            if let Some(i) = ids.iter().find(|i| **i >= self.targets.len()) {
                return Err(format!(
                    "segment {s:?} names target {i}, which does not exist"
                ));
            }
        }
        for t in &self.targets {
            let in_range = t.yaw_deg.abs() < 80.0
                && t.pitch_deg.abs() < 80.0
                && (0.0..=20.0).contains(&t.diopters);
            if !in_range {
                return Err(format!("target {t:?} is outside the field or depth range"));
            }
        }
        Ok(())
    }
}

/// Generator settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeneratorConfig {
    pub rate_hz: f64,
    pub ipd_mm: f64,
    /// Tracker noise per eye and axis, degrees (1 sd).
    pub noise_deg: f64,
    /// Chance per sample that the tracker loses one eye.
    pub dropout_probability: f64,
    /// Spontaneous blinks per second (besides scripted ones), and their length.
    pub blink_rate_hz: f64,
    pub blink_ms: f64,
    /// Microsaccades per second during fixation.
    pub microsaccade_rate_hz: f64,
    /// Fixational drift, degrees per sqrt(second) (random walk).
    pub drift_deg_per_sqrt_s: f64,
    /// Vergence time constant, ms.
    pub vergence_tau_ms: f64,
    pub pupil_mm: f64,
    /// The device clock: value at the first sample, and rate error.
    pub device_start_us: u64,
    pub device_clock_ppm: f64,
    pub seed: u64,
}

impl Default for GeneratorConfig {
    fn default() -> Self {
        GeneratorConfig {
            rate_hz: 500.0,
            ipd_mm: 64.0,
            noise_deg: 0.03,
            dropout_probability: 0.002,
            blink_rate_hz: 0.25,
            blink_ms: 150.0,
            microsaccade_rate_hz: 1.5,
            drift_deg_per_sqrt_s: 0.1,
            vergence_tau_ms: 150.0,
            pupil_mm: 4.0,
            device_start_us: 1_000_000,
            device_clock_ppm: 30.0,
            seed: 1,
        }
    }
}

/// What the eyes are really doing at a sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TruePhase {
    Fixation,
    Saccade,
    Microsaccade,
    Pursuit,
    Blink,
}

/// One generated sample: the ground truth and what the tracker reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthSample {
    /// True time since the first sample, µs (the device clock differs: see `reported`).
    pub time_us: u64,
    pub yaw_deg: f64,
    pub pitch_deg: f64,
    /// Current vergence depth of the eyes.
    pub diopters: f64,
    /// Depth of the target being looked at.
    pub target_diopters: f64,
    pub phase: TruePhase,
    pub reported: BinocularSample,
}

/// Something that yields tracker samples in time order: the generator, or a replay.
pub trait SampleSource: Send {
    /// The next sample with its true time since the start, µs; `None` at the end.
    fn next_sample(&mut self) -> Option<(u64, BinocularSample)>;
    fn rate_hz(&self) -> f64;
}

/// SplitMix64 with Box-Muller: small, deterministic, good enough for noise.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed)
    }
    pub fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
    pub fn normal(&mut self) -> f64 {
        let u = self.uniform().max(1e-300);
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * self.uniform()).cos()
    }
}

/// Saccade duration on the main sequence, ms: 2.2 ms/deg + 21 ms (Carpenter 1988).
pub fn saccade_duration_ms(amplitude_deg: f64) -> f64 {
    2.2 * amplitude_deg.abs() + 21.0
}

/// Minimum-jerk position fraction; its peak speed is 1.875 x amplitude / duration.
fn min_jerk(s: f64) -> f64 {
    let s = s.clamp(0.0, 1.0);
    s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
}

#[derive(Debug, Clone, Copy)]
struct Movement {
    from: (f64, f64),
    to: (f64, f64),
    start_us: f64,
    dur_us: f64,
    micro: bool,
}

/// The generator.
#[derive(Debug, Clone)]
pub struct GazeGenerator {
    scene: Scene,
    cfg: GeneratorConfig,
    rng: Rng,
    index: u64,
    segment: usize,
    segment_start_us: f64,
    gaze: (f64, f64),
    /// Where fixational drift is centred: the target.
    anchor: (f64, f64),
    diopters: f64,
    target_diopters: f64,
    movement: Option<Movement>,
    blink_until_us: f64,
    segment_entered: bool,
}

impl GazeGenerator {
    pub fn new(scene: Scene, cfg: GeneratorConfig) -> Result<Self, String> {
        scene.validate()?;
        if !(cfg.rate_hz > 0.0 && cfg.rate_hz <= 10_000.0) {
            return Err(format!("rate {} Hz is outside 0-10000 Hz", cfg.rate_hz));
        }
        let first = match scene.script[0] {
            Segment::Fixate { target, .. } => scene.targets[target],
            Segment::Pursue { from, .. } => scene.targets[from],
            Segment::Blink { .. } => scene.targets.first().copied().unwrap_or(Target {
                yaw_deg: 0.0,
                pitch_deg: 0.0,
                diopters: 1.0,
            }),
        };
        Ok(GazeGenerator {
            rng: Rng::new(cfg.seed),
            cfg,
            index: 0,
            segment: 0,
            segment_start_us: 0.0,
            gaze: (first.yaw_deg, first.pitch_deg),
            anchor: (first.yaw_deg, first.pitch_deg),
            diopters: first.diopters,
            target_diopters: first.diopters,
            movement: None,
            blink_until_us: -1.0,
            segment_entered: false,
            scene,
        })
    }

    pub fn config(&self) -> &GeneratorConfig {
        &self.cfg
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    fn segment_ms(&self) -> f64 {
        match self.scene.script[self.segment] {
            Segment::Fixate { ms, .. } | Segment::Pursue { ms, .. } | Segment::Blink { ms } => {
                f64::from(ms)
            }
        }
    }

    fn start_saccade(&mut self, now_us: f64, to: (f64, f64), micro: bool) {
        let amp = (to.0 - self.gaze.0).hypot(to.1 - self.gaze.1);
        self.movement = Some(Movement {
            from: self.gaze,
            to,
            start_us: now_us,
            dur_us: saccade_duration_ms(amp) * 1e3,
            micro,
        });
    }

    /// The next sample.
    pub fn next_truth(&mut self) -> TruthSample {
        let period_us = 1e6 / self.cfg.rate_hz;
        let now = self.index as f64 * period_us;
        self.index += 1;
        let dt = period_us * 1e-6;

        while now - self.segment_start_us >= self.segment_ms() * 1e3 {
            self.segment_start_us += self.segment_ms() * 1e3;
            self.segment = (self.segment + 1) % self.scene.script.len();
            self.segment_entered = false;
        }
        let seg = self.scene.script[self.segment];
        let mut phase = TruePhase::Fixation;
        match seg {
            Segment::Fixate { target, .. } => {
                let tg = self.scene.targets[target];
                if !self.segment_entered {
                    self.segment_entered = true;
                    self.anchor = (tg.yaw_deg, tg.pitch_deg);
                    self.target_diopters = tg.diopters;
                    let off = (tg.yaw_deg - self.gaze.0).hypot(tg.pitch_deg - self.gaze.1);
                    if off > 1.0 {
                        self.start_saccade(now, self.anchor, false);
                    }
                }
            }
            Segment::Pursue { from, to, ms } => {
                let (a, b) = (self.scene.targets[from], self.scene.targets[to]);
                let s = ((now - self.segment_start_us) / (f64::from(ms) * 1e3)).clamp(0.0, 1.0);
                let lerp = |x: f64, y: f64| x + (y - x) * s;
                self.anchor = (lerp(a.yaw_deg, b.yaw_deg), lerp(a.pitch_deg, b.pitch_deg));
                self.target_diopters = lerp(a.diopters, b.diopters);
                if self.movement.is_none() {
                    // Follow the target; an offset left by drift closes smoothly (50 ms),
                    // a large one with a catch-up saccade.
                    let off = (self.gaze.0 - self.anchor.0, self.gaze.1 - self.anchor.1);
                    if off.0.hypot(off.1) > 1.0 {
                        self.start_saccade(now, self.anchor, false);
                    } else {
                        let keep = (-period_us / 50_000.0).exp();
                        self.gaze = (self.anchor.0 + off.0 * keep, self.anchor.1 + off.1 * keep);
                        phase = TruePhase::Pursuit;
                    }
                }
            }
            Segment::Blink { .. } => {
                self.blink_until_us = self.blink_until_us.max(now + period_us);
            }
        }
        // Spontaneous blinks.
        if self.rng.uniform() < self.cfg.blink_rate_hz * dt {
            self.blink_until_us = self.blink_until_us.max(now + self.cfg.blink_ms * 1e3);
        }

        if let Some(m) = self.movement {
            let s = (now - m.start_us) / m.dur_us;
            let f = min_jerk(s);
            self.gaze = (
                m.from.0 + (m.to.0 - m.from.0) * f,
                m.from.1 + (m.to.1 - m.from.1) * f,
            );
            phase = if m.micro {
                TruePhase::Microsaccade
            } else {
                TruePhase::Saccade
            };
            if s >= 1.0 {
                self.movement = None;
                phase = TruePhase::Fixation;
            }
        } else if phase == TruePhase::Fixation {
            // Drift as a random walk; microsaccades bring the eye back near the target.
            let k = self.cfg.drift_deg_per_sqrt_s * dt.sqrt();
            self.gaze.0 += k * self.rng.normal();
            self.gaze.1 += k * self.rng.normal();
            if self.rng.uniform() < self.cfg.microsaccade_rate_hz * dt {
                let to = (
                    self.anchor.0 + 0.15 * self.rng.normal(),
                    self.anchor.1 + 0.15 * self.rng.normal(),
                );
                self.start_saccade(now, to, true);
            }
        }
        // Vergence: first-order approach to the target depth.
        let a = 1.0 - (-period_us / (self.cfg.vergence_tau_ms.max(1.0) * 1e3)).exp();
        self.diopters += (self.target_diopters - self.diopters) * a;

        let blinking = now < self.blink_until_us;
        if blinking {
            phase = TruePhase::Blink;
        }
        let reported = self.report(now, blinking);
        TruthSample {
            time_us: now as u64,
            yaw_deg: self.gaze.0,
            pitch_deg: self.gaze.1,
            diopters: self.diopters,
            target_diopters: self.target_diopters,
            phase,
            reported,
        }
    }

    fn report(&mut self, now_us: f64, blinking: bool) -> BinocularSample {
        let (y, p) = (self.gaze.0.to_radians(), self.gaze.1.to_radians());
        let dir = glam::DVec3::new(p.cos() * y.sin(), p.sin(), p.cos() * y.cos());
        let dist = 1000.0 / self.diopters.max(1e-3);
        // The fixated point, and each eye's ray to it (the eyes sit on the x axis).
        let point = dir * dist;
        let half = self.cfg.ipd_mm / 2.0;
        let eye = |x: f64, rng: &mut Rng| {
            let d = point - glam::DVec3::new(x, 0.0, 0.0);
            // Perturb the eye's angles by the tracker noise.
            let yaw = d.x.atan2(d.z) + self.cfg.noise_deg.to_radians() * rng.normal();
            let pitch = d.y.atan2(d.x.hypot(d.z)) + self.cfg.noise_deg.to_radians() * rng.normal();
            let valid = !blinking && rng.uniform() >= self.cfg.dropout_probability;
            EyeSample {
                origin_mm: [x as f32, 0.0, 0.0],
                direction: [
                    (pitch.cos() * yaw.sin()) as f32,
                    pitch.sin() as f32,
                    (pitch.cos() * yaw.cos()) as f32,
                ],
                pupil_mm: (self.cfg.pupil_mm + 0.02 * rng.normal()) as f32,
                valid,
            }
        };
        let left = eye(-half, &mut self.rng);
        let right = eye(half, &mut self.rng);
        let device =
            self.cfg.device_start_us as f64 + now_us * (1.0 + self.cfg.device_clock_ppm * 1e-6);
        BinocularSample {
            device_time_us: device as u64,
            left,
            right,
        }
    }
}

impl SampleSource for GazeGenerator {
    fn next_sample(&mut self) -> Option<(u64, BinocularSample)> {
        let s = self.next_truth();
        Some((s.time_us, s.reported))
    }
    fn rate_hz(&self) -> f64 {
        self.cfg.rate_hz
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quiet() -> GeneratorConfig {
        GeneratorConfig {
            noise_deg: 0.0,
            dropout_probability: 0.0,
            blink_rate_hz: 0.0,
            microsaccade_rate_hz: 0.0,
            drift_deg_per_sqrt_s: 0.0,
            ..GeneratorConfig::default()
        }
    }

    #[test]
    fn saccades_follow_the_main_sequence() {
        let scene = Scene {
            name: "two".into(),
            targets: vec![t(0.0, 0.0, 1.0), t(10.0, 0.0, 1.0), t(30.0, 0.0, 1.0)],
            script: vec![
                Segment::Fixate { target: 0, ms: 200 },
                Segment::Fixate { target: 1, ms: 300 },
                Segment::Fixate { target: 2, ms: 300 },
            ],
        };
        let mut g = GazeGenerator::new(
            scene,
            GeneratorConfig {
                rate_hz: 1000.0,
                ..quiet()
            },
        )
        .unwrap();
        let s: Vec<TruthSample> = (0..800).map(|_| g.next_truth()).collect();
        for (amp, from, to) in [(10.0, 200, 500), (20.0, 500, 800)] {
            let moving: Vec<&TruthSample> = s[from..to]
                .iter()
                .filter(|x| x.phase == TruePhase::Saccade)
                .collect();
            let dur = moving.len() as f64; // ms at 1 kHz
            assert!(
                (dur - saccade_duration_ms(amp)).abs() <= 1.5,
                "{amp}: {dur} ms"
            );
            let peak = s[from..to]
                .windows(2)
                .map(|w| (w[1].yaw_deg - w[0].yaw_deg) * 1000.0)
                .fold(0.0, f64::max);
            let expect = 1.875 * amp / (saccade_duration_ms(amp) * 1e-3);
            assert!(
                (peak - expect).abs() / expect < 0.02,
                "{amp}: peak {peak} vs {expect}"
            );
        }
        assert!((s[799].yaw_deg - 30.0).abs() < 1e-9);
    }

    #[test]
    fn rays_meet_at_the_target_depth_after_vergence_settles() {
        let mut g = GazeGenerator::new(Scene::named("vergence").unwrap(), quiet()).unwrap();
        let s: Vec<TruthSample> = (0..1000).map(|_| g.next_truth()).collect();
        // 2 s at 500 Hz: near target for 1 s, far for 1 s; check the end of each.
        for (i, want) in [(499, 0.5), (999, 3.0)] {
            let r = s[i].reported;
            let (l, rr) = (r.left.direction, r.right.direction);
            // Symmetric convergence straight ahead: x components are opposite.
            let half_angle = f64::from(l[0]).atan2(f64::from(l[2]));
            let depth_mm = 32.0 / half_angle.tan();
            assert!(
                (1000.0 / depth_mm - want).abs() < 0.02,
                "{i}: {}",
                1000.0 / depth_mm
            );
            assert!((f64::from(rr[0]) + f64::from(l[0])).abs() < 1e-6);
        }
    }

    #[test]
    fn blinks_dropouts_and_the_device_clock() {
        let cfg = GeneratorConfig {
            dropout_probability: 0.1,
            blink_rate_hz: 0.0,
            ..GeneratorConfig::default()
        };
        let mut g = GazeGenerator::new(Scene::named("blinks").unwrap(), cfg).unwrap();
        let s: Vec<TruthSample> = (0..1700).map(|_| g.next_truth()).collect();
        // Scripted blink from 700 to 850 ms.
        assert!(s[360..420]
            .iter()
            .all(|x| x.phase == TruePhase::Blink && !x.reported.left.valid));
        let drops = s[..340].iter().filter(|x| !x.reported.left.valid).count();
        assert!((15..60).contains(&drops), "{drops} dropouts of 340");
        // 30 ppm fast device clock from 1 s.
        let last = s[1699].reported.device_time_us;
        let want = 1_000_000.0 + 1699.0 * 2000.0 * (1.0 + 30e-6);
        assert!((last as f64 - want).abs() <= 1.0);
    }

    #[test]
    fn bad_scenes_are_refused_and_every_scenario_runs() {
        let mut bad = Scene::named("saccades").unwrap();
        bad.script.push(Segment::Fixate { target: 9, ms: 10 });
        assert!(GazeGenerator::new(bad, GeneratorConfig::default()).is_err());
        let mut bad = Scene::named("saccades").unwrap();
        bad.targets[0].diopters = f64::NAN;
        assert!(GazeGenerator::new(bad, GeneratorConfig::default()).is_err());
        let mut bad = Scene::named("saccades").unwrap();
        bad.script.clear();
        assert!(GazeGenerator::new(bad, GeneratorConfig::default()).is_err());
        assert!(GazeGenerator::new(
            Scene::named("fixation").unwrap(),
            GeneratorConfig {
                rate_hz: 0.0,
                ..GeneratorConfig::default()
            }
        )
        .is_err());
        assert!(Scene::named("nope").is_none());
        for name in SCENARIOS {
            let mut g = GazeGenerator::new(Scene::named(name).unwrap(), GeneratorConfig::default())
                .unwrap();
            for _ in 0..3000 {
                let s = g.next_truth();
                assert!(s.yaw_deg.is_finite() && s.diopters.is_finite());
            }
        }
    }
}
