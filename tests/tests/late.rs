//! A rig that cannot keep up says so: on simulated devices and tokio's paused clock, renders
//! that take longer than the display period give one log line at the first miss, then a
//! summary at most every few seconds, and `/status.display` the distinct frame rate.

use std::io::Write;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::{DepthMap, Plane};
use dioptra_rig::config::{RigConfig, EXAMPLE_SIM_RIG};
use dioptra_rig::simulated_rig::{ScriptedRenderer, SimRun};

/// The log, as text.
#[derive(Clone, Default)]
struct Captured(Arc<Mutex<Vec<u8>>>);

impl Write for Captured {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl<'a> tracing_subscriber::fmt::MakeWriter<'a> for Captured {
    type Writer = Captured;
    fn make_writer(&'a self) -> Captured {
        self.clone()
    }
}

/// Runs the example rig (60 Hz) for `seconds` with every render taking `render`: the log's
/// lines and `/status`.
async fn run(render: Duration, seconds: u64) -> (Vec<String>, serde_json::Value) {
    let log = Captured::default();
    let subscriber = tracing_subscriber::fmt()
        .with_writer(log.clone())
        .with_ansi(false)
        .with_max_level(tracing::Level::INFO)
        .finish();
    let _guard = tracing::subscriber::set_default(subscriber);
    let cfg = RigConfig::parse(EXAMPLE_SIM_RIG).unwrap();
    assert_eq!(cfg.display.frame_hz, 60.0);
    let opts = SimRun::new(cfg, Duration::from_secs(seconds)).unwrap();
    let depth = Arc::new(DepthMap::from_diopters(Plane::new(64, 64, 1.0)).unwrap());
    let renderer = ScriptedRenderer::new(opts.cfg.optics.planes.len(), move |_| render);
    let r = opts
        .run(
            Some(ScriptedRenderer::still(&depth)),
            Arc::new(renderer),
            None,
        )
        .await
        .unwrap();
    let status = r.state.status_json();
    let text = String::from_utf8(log.0.lock().unwrap().clone()).unwrap();
    (text.lines().map(str::to_string).collect(), status)
}

#[tokio::test(start_paused = true)]
async fn renders_longer_than_the_period_log_the_first_miss_then_summaries() {
    // 40 ms renders against a 16.7 ms refresh: a new frame every third refresh at best.
    let (lines, status) = run(Duration::from_millis(40), 12).await;
    let first: Vec<_> = lines
        .iter()
        .filter(|l| l.contains("frames are late"))
        .collect();
    let summaries: Vec<_> = lines
        .iter()
        .filter(|l| l.contains("frames late in the last"))
        .collect();
    assert_eq!(first.len(), 1, "{lines:#?}");
    assert!(first[0].contains("WARN"), "{}", first[0]);
    assert!(
        first[0].contains("the newest render took 40.0 ms against a refresh period of 16.7 ms"),
        "{}",
        first[0]
    );
    // One every 5 s after the first miss: at about 5 and 10 s of the 12.
    assert_eq!(summaries.len(), 2, "{lines:#?}");
    let d = &status["display"];
    let repeats = d["repeated_refreshes"].as_u64().unwrap();
    let distinct = d["distinct_frames"].as_u64().unwrap();
    // Hundreds of misses, three lines.
    assert!(repeats > 300, "{d}");
    assert_eq!(d["refreshes"].as_u64().unwrap(), repeats + distinct);
    let fps = d["distinct_fps"].as_f64().unwrap();
    let hz = d["refresh_hz"].as_f64().unwrap();
    assert!((15.0..=25.0).contains(&fps), "{d}");
    assert!((hz - 60.0).abs() < 1.5, "{d}");
    assert_eq!(d["late"], true);
    let problems = status["problems"].as_array().unwrap();
    assert!(
        problems.iter().any(|p| p["part"] == "display"
            && p["problem"]
                .as_str()
                .unwrap()
                .starts_with("frames are late")),
        "{problems:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn renders_within_the_period_log_nothing_and_show_every_refresh_new() {
    let (lines, status) = run(Duration::from_millis(4), 6).await;
    assert!(!lines.iter().any(|l| l.contains("late")), "{lines:#?}");
    let d = &status["display"];
    assert_eq!(d["repeated_refreshes"], 0, "{d}");
    assert_eq!(d["late"], false);
    let fps = d["distinct_fps"].as_f64().unwrap();
    assert!((fps - 60.0).abs() < 1.5, "{d}");
}
