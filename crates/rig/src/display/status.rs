//! What the display part publishes ([`DisplayHandle`]): the sink's status as of the newest
//! present, the frames shown, a frame the sink refused, and the marker patch's requests from
//! outside the loop; `/status`'s `display`.

use std::sync::Mutex;

use dioptra_core::lock;
use serde_json::{Map, Value};

use super::marker::MarkerControl;
use super::pacing::PacingStatus;
use crate::problem::Problem;

/// The display part's handle.
#[derive(Default)]
pub struct DisplayHandle {
    marker: MarkerControl,
    status: Mutex<DisplayStatus>,
}

#[derive(Default)]
struct DisplayStatus {
    /// The sink's own status (`DisplaySink::status`) as of the newest present.
    sink: Value,
    /// Frames the sink has shown.
    shown: u64,
    /// The newest frame was not shown, and why (the sink's newest misfit).
    not_shown: Option<String>,
    /// Distinct frames against refreshes ([`super::pacing`]).
    pacing: PacingStatus,
    /// What would make frames fit (config keys), for the problem a late rig shows.
    advice: String,
}

impl DisplayHandle {
    /// `sink`: the sink's status before its first present.
    pub fn new(sink: Value) -> Self {
        DisplayHandle {
            marker: MarkerControl::default(),
            status: Mutex::new(DisplayStatus {
                sink,
                ..DisplayStatus::default()
            }),
        }
    }

    /// The marker patch's requests from outside the loop (an API marker; `dioptra hil`'s
    /// hold).
    pub fn marker(&self) -> &MarkerControl {
        &self.marker
    }

    /// Frames the sink has shown.
    pub fn shown(&self) -> u64 {
        lock(&self.status).shown
    }

    /// The sink's status now, as the loop starts.
    pub(crate) fn sink_status(&self, sink: Value) {
        lock(&self.status).sink = sink;
    }

    /// A frame was shown.
    pub(crate) fn presented(&self, sink: Value, shown: u64) {
        let mut st = lock(&self.status);
        st.sink = sink;
        st.shown = shown;
        st.not_shown = None;
    }

    /// Distinct frames against refreshes, as of the newest present; `advice`: what would
    /// make frames fit.
    pub(crate) fn pacing(&self, pacing: &PacingStatus, advice: &str) {
        let mut st = lock(&self.status);
        st.pacing = pacing.clone();
        if st.advice != advice {
            st.advice = advice.to_string();
        }
    }

    /// Distinct frames against refreshes.
    pub fn pacing_now(&self) -> PacingStatus {
        lock(&self.status).pacing.clone()
    }

    /// The sink refused a frame (it does not fit its place): its status says why.
    pub(crate) fn not_shown(&self, sink: Value) {
        let mut st = lock(&self.status);
        st.not_shown = Some(
            sink["misfit"]["newest"]
                .as_str()
                .unwrap_or("it does not fit its place")
                .to_string(),
        );
        st.sink = sink;
    }

    /// `/status`'s `display`: the sink's status, and the distinct frames against the
    /// refreshes.
    pub fn status(&self, out: &mut Map<String, Value>) {
        let st = lock(&self.status);
        let mut display = st.sink.clone();
        if let (Some(d), Ok(Value::Object(p))) =
            (display.as_object_mut(), serde_json::to_value(&st.pacing))
        {
            d.extend(p);
        }
        out.insert("display".into(), display);
    }

    /// The newest frame was not shown; frames are late.
    pub fn problems(&self) -> Vec<Problem> {
        let st = lock(&self.status);
        let mut out: Vec<Problem> = st
            .not_shown
            .iter()
            .map(|why| {
                Problem::new(
                    "display",
                    "display.scale",
                    format!("the newest frame is not shown: {why}"),
                )
            })
            .collect();
        let p = &st.pacing;
        if let Some(line) = &p.no_frame {
            out.push(Problem::new("display", "method", line.clone()));
        }
        if p.late {
            out.push(Problem::new(
                "display",
                "method",
                format!(
                    "frames are late: {:.1} distinct frames/s against {:.1} refreshes/s; to fit: {}",
                    p.distinct_fps.unwrap_or(0.0),
                    p.refresh_hz.unwrap_or(0.0),
                    st.advice
                ),
            ));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::display::pacing::Pacing;
    use dioptra_core::Timestamp;
    use std::time::Duration;

    #[test]
    fn no_frame_after_the_grace_period_is_a_problem_naming_what_to_change() {
        let h = DisplayHandle::new(Value::Null);
        let advice = "a smaller panel (display.width, display.height)";
        let mut p = Pacing::new(Timestamp(0), Duration::from_micros(16_667), advice.into());
        let second = |s: u64| Timestamp(s * 1_000_000_000);
        assert_eq!(p.check(second(1)), None);
        h.pacing(p.status(), advice);
        assert!(h.problems().is_empty(), "{:?}", h.problems());
        assert!(p.check(second(3)).is_some());
        h.pacing(p.status(), advice);
        let problems = h.problems();
        assert_eq!(problems.len(), 1, "{problems:?}");
        let json = serde_json::to_value(&problems[0]).unwrap();
        assert_eq!(json["part"], "display");
        assert_eq!(json["key"], "method");
        let text = json["problem"].as_str().unwrap();
        assert!(
            text.contains("no frame shown") && text.contains("display.width"),
            "{text}"
        );
        // The first frame clears it.
        p.presented(second(4), 0, false);
        h.pacing(p.status(), advice);
        assert!(h.problems().is_empty());
    }
}
