//! A frame's time budget and its predicted cost at the rig's size, method and backend, for
//! `dioptra serve` to say at start whether frames will fit, and which keys would make them
//! fit ([`predict`]). The prediction is dioptra-render's cost model
//! ([`dioptra_render::planner::predict_frame_cost`]); a method or backend it has no model for
//! is measured instead (the caller times a render and hands it to [`Prediction::measured`]).

use dioptra_render::defocus::DefocusMethod;
use dioptra_render::planner::{predict_frame_cost, FoveationSettings, FrameSpec};
use dioptra_sched::RenderMethod;

use crate::config::RigConfig;
use crate::display::config::DisplayLayout;
use crate::mode::Mode;

/// The time a frame may take: the period frames are paced at (the display's refresh in
/// varifocal and light-field mode, the content's frame period in multifocal mode) less a
/// margin for the rest of the frame's work (compose, present).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameBudget {
    pub period_ms: f64,
    pub budget_ms: f64,
    /// Which key sets the period.
    pub period_key: &'static str,
}

impl FrameBudget {
    pub fn of(cfg: &RigConfig, mode: Mode) -> FrameBudget {
        let (hz, period_key) = match mode {
            Mode::Multifocal => (cfg.content.fps, "content.fps"),
            Mode::Varifocal | Mode::Lightfield => (cfg.display.frame_hz, "display.frame_hz"),
        };
        let period_ms = 1e3 / hz.max(1e-3);
        FrameBudget {
            period_ms,
            budget_ms: (period_ms - margin_ms(period_ms)).max(0.0),
            period_key,
        }
    }
}

/// What the rest of a frame's work is allowed: a tenth of the period, at least 1 ms.
pub fn margin_ms(period_ms: f64) -> f64 {
    (0.1 * period_ms).max(1.0).min(period_ms)
}

/// Eyes rendered per frame.
pub fn eyes(cfg: &RigConfig) -> usize {
    match cfg.display.layout {
        DisplayLayout::One => 1,
        DisplayLayout::SideBySide | DisplayLayout::TwoOutputs => 2,
    }
}

/// What the start-up check found.
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// Predicted (or measured) wall time of a frame, all eyes, ms.
    pub frame_ms: f64,
    pub budget: FrameBudget,
    /// How it was obtained, in words.
    pub summary: String,
    /// Settings predicted to fit, each with its key and predicted cost (empty when the
    /// configured one fits, or when nothing is predicted to).
    pub to_fit: Vec<String>,
}

impl Prediction {
    pub fn fits(&self) -> bool {
        self.frame_ms <= self.budget.budget_ms
    }

    /// A frame measured at `frame_ms` (a warm-up render of the rig's renderer).
    pub fn measured(cfg: &RigConfig, frame_ms: f64, what: &str) -> Prediction {
        Prediction {
            frame_ms,
            budget: FrameBudget::of(cfg, cfg.mode),
            summary: format!("measured warm-up render: {what}: {frame_ms:.1} ms a frame"),
            to_fit: Vec::new(),
        }
    }

    /// One line for the log.
    pub fn line(&self) -> String {
        let b = &self.budget;
        let verdict = if self.fits() {
            "fits".to_string()
        } else {
            format!(
                "does NOT fit: expect about {:.1} distinct frames/s, each shown {:.0} times",
                1e3 / self.frame_ms.max(b.period_ms),
                (self.frame_ms / b.period_ms).ceil().max(1.0)
            )
        };
        let mut line = format!(
            "{}; budget {:.1} ms ({} period {:.1} ms less {:.1} ms margin): {verdict}",
            self.summary,
            b.budget_ms,
            b.period_key,
            b.period_ms,
            b.period_ms - b.budget_ms
        );
        if !self.fits() {
            line += &format!(". To fit: {}", self.advice());
        }
        line
    }

    /// What would make frames fit: the settings predicted to, or the keys to turn.
    pub fn advice(&self) -> String {
        if self.to_fit.is_empty() {
            generic_advice(self.budget.period_key)
        } else {
            self.to_fit.join("; ")
        }
    }
}

/// The keys that change a frame's cost, for messages when nothing better is known.
pub fn generic_advice(period_key: &str) -> String {
    format!(
        "a method of bounded cost per pixel (method = \"pyramid\", or \"auto\" to let the \
         planner choose per frame), gaze-contingent resolution (render.foveation = \
         {{ radius_deg = 5.0 }}), a smaller panel (display.width, display.height), \
         render.backend = \"gpu\", or a longer period ({period_key})"
    )
}

/// The cost model's defocus method for `method`, where it has one.
fn modelled(method: RenderMethod) -> Option<DefocusMethod> {
    match method {
        RenderMethod::Gather => Some(DefocusMethod::Gather),
        RenderMethod::Pyramid => Some(DefocusMethod::Pyramid(Default::default())),
        RenderMethod::LightFieldDefocus => Some(DefocusMethod::LightField(Default::default())),
        _ => None,
    }
}

/// The predicted cost of a frame of `cfg` on `backend` (`cpu` or `gpu`, the renderer's), or
/// why there is no prediction (no model for that method or backend: measure instead).
pub fn predict(cfg: &RigConfig, backend: &str) -> Result<Prediction, String> {
    let mode = cfg.mode;
    let budget = FrameBudget::of(cfg, mode);
    // `auto` is predicted as the planner's bounded-cost setting (what it falls to under a
    // short budget).
    let configured = if cfg.auto_method {
        RenderMethod::Pyramid
    } else {
        cfg.method.0
    };
    let method = modelled(configured).ok_or_else(|| {
        format!(
            "no cost model for method {} in {} mode",
            cfg.method.as_str(),
            mode.as_str()
        )
    })?;
    let foveation = cfg.render.foveation.settings();
    let spec = |width: u32, height: u32, method: DefocusMethod, foveation| {
        let mut s = FrameSpec::new(width as usize, height as usize, cfg.eye_model());
        s.eyes = eyes(cfg);
        s.method = method;
        s.foveation = foveation;
        s.backend = backend.to_string();
        s
    };
    let d = &cfg.display;
    let cost = predict_frame_cost(&spec(d.width, d.height, method, foveation))
        .map_err(|e| e.to_string())?;
    let mut p = Prediction {
        frame_ms: cost.wall_ms,
        budget,
        summary: cost.summary,
        to_fit: Vec::new(),
    };
    if !p.fits() {
        // What the model says of the cheaper settings: each alone, then a smaller panel.
        let pyramid = DefocusMethod::Pyramid(Default::default());
        let fovea = FoveationSettings {
            radius_deg: dioptra_render::foveated::DEFAULT_RADIUS_DEG,
            mar_slope: dioptra_render::foveated::DEFAULT_MAR_SLOPE,
        };
        let mut tries: Vec<(String, u32, u32, DefocusMethod, Option<FoveationSettings>)> =
            Vec::new();
        if !matches!(method, DefocusMethod::Pyramid(_)) {
            tries.push((
                "method = \"pyramid\"".into(),
                d.width,
                d.height,
                pyramid,
                None,
            ));
        }
        if foveation.is_none() {
            tries.push((
                "method = \"pyramid\" with render.foveation = { radius_deg = 5.0 }".into(),
                d.width,
                d.height,
                pyramid,
                Some(fovea),
            ));
        }
        for div in [2u32, 3, 4] {
            let (w, h) = (d.width / div, d.height / div);
            if w > 0 && h > 0 {
                tries.push((
                    format!("display.width = {w}, display.height = {h} (scale = \"fit\" fills the panel)"),
                    w,
                    h,
                    method,
                    foveation,
                ));
            }
        }
        for (what, w, h, m, f) in tries {
            if let Ok(c) = predict_frame_cost(&spec(w, h, m, f)) {
                if c.wall_ms <= budget.budget_ms {
                    p.to_fit
                        .push(format!("{what}: predicted {:.1} ms", c.wall_ms));
                }
            }
        }
        let hz_fits = 1e3 / (p.frame_ms + margin_ms(p.frame_ms));
        p.to_fit
            .push(format!("{} = {hz_fits:.1} or less", budget.period_key));
    }
    Ok(p)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rig(extra: &str) -> RigConfig {
        let text = crate::config::EXAMPLE_SIM_RIG.to_string() + extra;
        RigConfig::parse(&text).unwrap()
    }

    #[test]
    fn the_budget_is_the_period_less_a_margin() {
        let c = rig("");
        let b = FrameBudget::of(&c, Mode::Varifocal);
        assert!((b.period_ms - 1e3 / c.display.frame_hz).abs() < 1e-9);
        assert!((b.period_ms - b.budget_ms - margin_ms(b.period_ms)).abs() < 1e-9);
        assert_eq!(b.period_key, "display.frame_hz");
        let m = FrameBudget::of(&c, Mode::Multifocal);
        assert!((m.period_ms - 1e3 / c.content.fps).abs() < 1e-9);
        assert_eq!(m.period_key, "content.fps");
    }

    #[test]
    fn a_panel_too_large_for_its_period_is_said_not_to_fit_naming_the_keys() {
        let small = predict(&rig(""), "cpu").unwrap();
        let mut c = rig("");
        c.display.width = 2160;
        c.display.height = 2160;
        c.display.frame_hz = 90.0;
        let big = predict(&c, "cpu").unwrap();
        assert!(
            big.frame_ms > small.frame_ms * 10.0,
            "{} {}",
            big.frame_ms,
            small.frame_ms
        );
        assert!(!big.fits(), "{}", big.line());
        let line = big.line();
        assert!(
            line.contains("does NOT fit") && line.contains("To fit:"),
            "{line}"
        );
        assert!(line.contains("display.frame_hz = "), "{line}");
        // The GPU has no model: the caller measures instead.
        assert!(predict(&c, "gpu").is_err());
        // Nor has the network.
        c.method = crate::mode::Method(RenderMethod::Network);
        assert!(predict(&c, "cpu")
            .unwrap_err()
            .contains("no cost model for method network"));
    }
}
