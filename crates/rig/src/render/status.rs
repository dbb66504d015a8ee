//! What the render part publishes ([`RenderHandle`]): the renderer, whether the planner
//! chooses each frame's method (`method = "auto"`), and how the renders went ([`RenderStatus`]);
//! `/status`'s `render`, `render_errors`, `last_render_ms` and `planned`, and a failing render.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::lock;
use serde::Serialize;
use serde_json::{json, Map, Value};

use super::job::{Planned, Renderer};
use crate::problem::Problem;

/// The newest render error, as `/status` shows it.
#[derive(Debug, Clone, Serialize)]
pub struct RenderErrorNote {
    pub frame: u64,
    pub method: String,
    pub kind: &'static str,
    pub error: String,
    pub focus_d: f32,
}

/// How the renders went.
#[derive(Debug, Clone, Default)]
pub struct RenderStatus {
    pub render_errors: u64,
    /// Render errors per method (`gather`, `network`, ...).
    pub render_errors_by_method: BTreeMap<String, u64>,
    /// The newest render error.
    pub last_render_error: Option<RenderErrorNote>,
    /// Frames shown unblurred because their render failed.
    pub fallback_frames: u64,
    pub last_render_ms: Option<f64>,
    /// `method = "auto"`: the planner's choice for the newest frame.
    pub planned: Option<Planned>,
    /// The newest render failed (the next one made clears it).
    pub failing: bool,
}

/// The render part's handle.
pub struct RenderHandle {
    renderer: Arc<dyn Renderer>,
    auto: AtomicBool,
    status: Mutex<RenderStatus>,
}

impl RenderHandle {
    /// `auto`: the planner chooses each varifocal frame's method (`method = "auto"`).
    pub fn new(renderer: Arc<dyn Renderer>, auto: bool) -> Self {
        RenderHandle {
            renderer,
            auto: AtomicBool::new(auto),
            status: Mutex::new(RenderStatus::default()),
        }
    }

    /// What renders the frames.
    pub fn renderer(&self) -> &Arc<dyn Renderer> {
        &self.renderer
    }

    /// Whether the planner chooses each varifocal frame's method.
    pub fn auto(&self) -> bool {
        self.auto.load(Ordering::Relaxed)
    }

    /// Turns the planner on or off; off, its last choice no longer describes the frames.
    pub fn set_auto(&self, auto: bool) {
        self.auto.store(auto, Ordering::Relaxed);
        if !auto {
            lock(&self.status).planned = None;
        }
    }

    /// How the renders went.
    pub fn status_now(&self) -> RenderStatus {
        lock(&self.status).clone()
    }

    /// A frame was made in `took` (with the planner's choice, where it chose).
    pub(crate) fn made(&self, took: Duration, planned: Option<&Planned>) {
        let mut st = lock(&self.status);
        st.last_render_ms = Some(took.as_secs_f64() * 1e3);
        if let Some(p) = planned {
            st.planned = Some(p.clone());
        }
        st.failing = false;
    }

    /// A frame failed after `took` (`fallback`: its content was shown unblurred instead).
    pub(crate) fn failed(&self, took: Duration, note: RenderErrorNote, fallback: bool) {
        let mut st = lock(&self.status);
        st.last_render_ms = Some(took.as_secs_f64() * 1e3);
        st.render_errors += 1;
        *st.render_errors_by_method
            .entry(note.method.clone())
            .or_default() += 1;
        st.last_render_error = Some(note);
        if fallback {
            st.fallback_frames += 1;
        }
        st.failing = true;
    }

    /// `/status`'s `render`, `render_errors`, `last_render_ms` and `planned`.
    pub fn status(&self, out: &mut Map<String, Value>) {
        let st = self.status_now();
        out.insert("render".into(), self.renderer.backend_status());
        out.insert(
            "render_errors".into(),
            json!({
                "by_method": st.render_errors_by_method,
                "last": st.last_render_error,
            }),
        );
        out.insert("last_render_ms".into(), json!(st.last_render_ms));
        out.insert(
            "planned".into(),
            json!(st.planned.as_ref().map(|p| json!({
                "method": p.choice,
                "predicted_fovea_psnr_db": p.predicted_psnr_db,
                "predicted_ms": p.predicted_ms,
                "budget_ms": p.budget_ms,
                "why": p.why,
            }))),
        );
    }

    /// The newest render failed: its method (or the GPU backend) is the key to look at.
    pub fn problems(&self) -> Vec<Problem> {
        let st = lock(&self.status);
        let Some(e) = st.last_render_error.as_ref().filter(|_| st.failing) else {
            return Vec::new();
        };
        let key = match e.kind {
            "gpu" => "render.backend",
            _ => "method",
        };
        vec![Problem::new(
            "render",
            key,
            format!(
                "frame {} ({}) did not render: {}",
                e.frame, e.method, e.error
            ),
        )]
    }
}
