//! `--suite panel`: a prototype's panel sizes per eye, at a narrow and a wide field. Two parts:
//! - each per-frame stage timed alone on each backend: the procedural scene's ray cast (one
//!   eye), an eye's view synthesised from one RGB-D, the varifocal render per method, and the
//!   two eyes packed into the side-by-side panel's 8-bit sRGB (what the window uploads);
//! - the rig itself (`dioptra serve`'s, on the system clock, the binocular example rig of
//!   simulated devices with only the panel, field and method changed) run for some seconds
//!   per size: distinct frames per second, repeated refreshes and gaze sample to display
//!   p50/p99, as its `/status` reports them.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::defocus::PyramidParams;
use dioptra_render::foveated::Foveation;
use dioptra_render::views::{synthesize_rgbd_view, RgbdView};
use dioptra_render::{Backend, DefocusMethod, LightFieldParams};
use dioptra_rig::config::{Method, RigConfig, EXAMPLE_SIM_BINOCULAR_RIG};
use dioptra_rig::render::config::{FoveationSetting, GazeFoveation, RenderBackend};
use dioptra_sched::RenderMethod;
use dioptra_sim::scene::{render_pinhole, Camera, Scene};

use super::report::{num, Table};

/// The scene the stages are timed on.
const SEED: u64 = 1_000_000;
/// Rays per pixel of the rig's procedural scene (its ray cast's setting).
const SCENE_SAMPLES: usize = 2;
/// The rig's default interpupillary distance, metres.
const IPD_M: f32 = 0.063;

/// What the panel suite runs.
pub struct PanelPlan {
    /// Each eye's panel, width x height.
    pub sizes: Vec<[usize; 2]>,
    /// Horizontal fields of one eye, degrees.
    pub fields_deg: Vec<f32>,
    /// A stage whose one run took longer than this (ms) is not timed at the larger sizes.
    pub budget_ms: f64,
    /// Fields the rig runs at (each size, each method).
    pub rig_fields_deg: Vec<f32>,
    /// Seconds each rig run is measured for (after a second to start).
    pub rig_seconds: f64,
}

/// A varifocal render the stages and the rig runs compare.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PanelMethod {
    Gather,
    Pyramid,
    /// The pyramid method, full resolution within 5 degrees of the gaze.
    PyramidFoveated,
    /// The light-field method with the daemon's 16 views (stages only).
    LightField16,
    /// `method = "auto"` with the 5-degree foveation (rig runs only).
    Auto,
}

impl PanelMethod {
    pub fn label(self) -> &'static str {
        match self {
            PanelMethod::Gather => "gather",
            PanelMethod::Pyramid => "pyramid",
            PanelMethod::PyramidFoveated => "pyramid-foveated",
            PanelMethod::LightField16 => "lightfield-16",
            PanelMethod::Auto => "auto-foveated",
        }
    }

    /// The methods the stages time.
    pub const STAGES: [PanelMethod; 4] = [
        PanelMethod::Gather,
        PanelMethod::Pyramid,
        PanelMethod::PyramidFoveated,
        PanelMethod::LightField16,
    ];
    /// The methods the rig runs with.
    pub const RIG: [PanelMethod; 4] = [
        PanelMethod::Gather,
        PanelMethod::Pyramid,
        PanelMethod::PyramidFoveated,
        PanelMethod::Auto,
    ];

    fn defocus(self, gaze: [f32; 2]) -> Option<DefocusMethod> {
        match self {
            PanelMethod::Gather => Some(DefocusMethod::Gather),
            PanelMethod::Pyramid => Some(DefocusMethod::Pyramid(PyramidParams::default())),
            PanelMethod::PyramidFoveated => Some(DefocusMethod::Pyramid(PyramidParams {
                foveation: Some(Foveation::at(gaze)),
            })),
            PanelMethod::LightField16 => Some(DefocusMethod::LightField(LightFieldParams {
                views: 16,
                mip: true,
            })),
            PanelMethod::Auto => None,
        }
    }
}

/// One stage at one size and field on one backend.
pub struct StageRow {
    pub size: [usize; 2],
    pub field_deg: f32,
    pub backend: &'static str,
    pub stage: &'static str,
    /// The render's method; empty for the other stages.
    pub method: String,
    pub time_ms: Option<f64>,
    pub note: String,
}

/// One rig run.
pub struct RigRow {
    pub size: [usize; 2],
    pub field_deg: f32,
    pub method: &'static str,
    pub seconds: f64,
    pub distinct_frames: u64,
    pub refreshes: u64,
    pub repeated: u64,
    pub gaze_to_display_ms: (Option<f64>, Option<f64>),
    /// The size the procedural scene was cast at (smaller than the panel when it could not
    /// keep up).
    pub cast_size: String,
    /// `/status.problems` at the end, one line.
    pub problems: String,
}

impl RigRow {
    pub fn distinct_fps(&self) -> f64 {
        self.distinct_frames as f64 / self.seconds.max(1e-9)
    }
}

impl PanelPlan {
    /// Progress units: stages per size, field and backend, and the rig runs.
    pub fn units(&self, backends: usize) -> u64 {
        let n = self.sizes.len() * self.fields_deg.len();
        let rigs = self.sizes.len() * self.rig_fields_deg.len() * PanelMethod::RIG.len();
        (n * backends * (2 + PanelMethod::STAGES.len()) + rigs) as u64
    }
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Times every stage on each backend, smallest size first; a stage over the budget is not
/// run at the larger sizes of its field and backend (its rows say so).
pub fn stages(
    plan: &PanelPlan,
    backends: &[&dyn Backend],
    tick: &dyn Fn(&str),
) -> Result<Vec<StageRow>> {
    let mut rows = Vec::new();
    for &field in &plan.fields_deg {
        for b in backends {
            // What overran the budget, and how long it took.
            let mut over: Vec<(String, f64)> = Vec::new();
            for &[w, h] in &plan.sizes {
                let eye = EyeModel {
                    fov_horizontal_deg: field,
                    ..EyeModel::default()
                }
                .with_width(w as u32);
                let mut row = |stage: &'static str, method: &str, time_ms, note: String| {
                    rows.push(StageRow {
                        size: [w, h],
                        field_deg: field,
                        backend: b.name(),
                        stage,
                        method: method.to_string(),
                        time_ms,
                        note,
                    })
                };
                let t = Instant::now();
                let scene = Scene::generate(SEED);
                let (color, depth) =
                    render_pinhole(&scene, &Camera::new(eye, w, h), [0.0, 0.0], SCENE_SAMPLES)?;
                let input = Rgbd::new(color, depth)?;
                // The scene is cast on the CPU whatever the backend.
                row("scene ray cast (one eye)", "", Some(ms(t)), "CPU".into());
                let t = Instant::now();
                let view = synthesize_rgbd_view(
                    &[RgbdView {
                        position: [0.0, 0.0],
                        rgbd: input.clone(),
                    }],
                    [0.5 * IPD_M, 0.0],
                    &eye,
                )?;
                row("eye view from one RGB-D", "", Some(ms(t)), "CPU".into());
                tick("stages");
                let gaze = [0.5 * w as f32, 0.5 * h as f32];
                let focus = input.depth.at(w / 2, h / 2).unwrap_or(Diopters(1.0));
                let mut images = Vec::new();
                for m in PanelMethod::STAGES {
                    tick(m.label());
                    if let Some((_, took)) = over.iter().find(|(l, _)| l == m.label()) {
                        row(
                            "render",
                            m.label(),
                            None,
                            format!(
                                "skipped: {took:.0} ms at a smaller size, over the {:.0} ms budget",
                                plan.budget_ms
                            ),
                        );
                        continue;
                    }
                    let Some(method) = m.defocus(gaze) else {
                        continue;
                    };
                    if b.name() == "gpu" {
                        // Pipelines and buffers for this size, untimed.
                        b.defocus(&input, &[focus], &eye, method, &|_| {})?;
                    }
                    let t = Instant::now();
                    let out = b.defocus(&input, &[focus], &eye, method, &|_| {})?;
                    let took = ms(t);
                    row(
                        "render",
                        m.label(),
                        Some(took),
                        format!("focus {:.2} D, one run", focus.0),
                    );
                    if took > plan.budget_ms {
                        over.push((m.label().to_string(), took));
                    }
                    images.extend(out);
                }
                if let Some(left) = images.first() {
                    let t = Instant::now();
                    let mut panel = Vec::new();
                    let mut eye_bytes = Vec::new();
                    // The left eye's image twice: both eyes' are the same size.
                    for image in [left, left] {
                        dioptra_rig::display::blit::pack_rgba8_srgb(image, &mut eye_bytes);
                        panel.extend_from_slice(&eye_bytes);
                    }
                    row(
                        "pack both eyes (8-bit sRGB)",
                        "",
                        Some(ms(t)),
                        format!("{} bytes", panel.len()),
                    );
                }
                drop(view);
                tick("packed");
            }
        }
    }
    Ok(rows)
}

/// The binocular example rig at `size` per eye over `field` degrees, rendering with `method`
/// on the CPU.
pub fn rig_config(size: [usize; 2], field: f32, method: PanelMethod) -> Result<RigConfig> {
    let mut cfg = RigConfig::parse(EXAMPLE_SIM_BINOCULAR_RIG)?;
    cfg.display.width = size[0] as u32;
    cfg.display.height = size[1] as u32;
    cfg.eye.fov_deg = field;
    cfg.recording = None;
    cfg.render.backend = RenderBackend::Cpu;
    let fovea = FoveationSetting::Around(GazeFoveation {
        radius_deg: dioptra_render::foveated::DEFAULT_RADIUS_DEG,
        falloff_arcmin_per_deg: dioptra_render::foveated::DEFAULT_MAR_SLOPE * 60.0,
    });
    match method {
        PanelMethod::Gather => cfg.method = Method(RenderMethod::Gather),
        PanelMethod::Pyramid => cfg.method = Method(RenderMethod::Pyramid),
        PanelMethod::PyramidFoveated => {
            cfg.method = Method(RenderMethod::Pyramid);
            cfg.render.foveation = fovea;
        }
        PanelMethod::Auto => {
            cfg.auto_method = true;
            cfg.render.foveation = fovea;
        }
        PanelMethod::LightField16 => cfg.method = Method(RenderMethod::LightFieldDefocus),
    }
    cfg.validate()
        .with_context(|| format!("the panel rig {}x{} {field} deg", size[0], size[1]))?;
    Ok(cfg)
}

/// Every rig run of `plan`, smallest size first.
pub fn rigs(plan: &PanelPlan, tick: &dyn Fn(&str)) -> Result<Vec<RigRow>> {
    let mut rows = Vec::new();
    for &field in &plan.rig_fields_deg {
        for &size in &plan.sizes {
            for m in PanelMethod::RIG {
                tick(&format!(
                    "rig {}x{} {field} deg {}",
                    size[0],
                    size[1],
                    m.label()
                ));
                rows.push(run_rig(
                    rig_config(size, field, m)?,
                    m.label(),
                    plan.rig_seconds,
                )?);
            }
        }
    }
    Ok(rows)
}

/// Runs the rig of `cfg` on the system clock for a second to start and then `seconds`, and
/// reads what its `/status` says.
pub fn run_rig(cfg: RigConfig, method: &'static str, seconds: f64) -> Result<RigRow> {
    let (size, field) = (
        [cfg.display.width as usize, cfg.display.height as usize],
        cfg.eye.fov_deg,
    );
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    rt.block_on(async move {
        let rig = dioptra_rig::Rig::start(dioptra_rig::RigSetup::new(cfg))
            .await
            .map_err(|e| anyhow::anyhow!("the panel rig did not start: {e}"))?;
        let state = Arc::clone(rig.state());
        let counts = |v: &serde_json::Value| {
            let d = &v["display"];
            [
                d["distinct_frames"].as_u64().unwrap_or(0),
                d["refreshes"].as_u64().unwrap_or(0),
                d["repeated_refreshes"].as_u64().unwrap_or(0),
            ]
        };
        tokio::time::sleep(Duration::from_secs(1)).await;
        let before = counts(&state.status_json());
        let t = Instant::now();
        tokio::time::sleep(Duration::from_secs_f64(seconds)).await;
        let status = state.status_json();
        let secs = t.elapsed().as_secs_f64();
        state.cancel().cancel();
        rig.wait().await;
        let after = counts(&status);
        let lat = &status["scheduler"]["latency_us"]["gaze sample to display"];
        let ms_of = |k: &str| lat[k].as_f64().map(|us| us / 1e3);
        let cast = &status["content"]["cast_size"];
        let problems: Vec<String> = status["problems"]
            .as_array()
            .map(|a| {
                a.iter()
                    .map(|p| {
                        let text = |k: &str| p[k].as_str().unwrap_or("").to_string();
                        format!("{} ({}): {}", text("part"), text("key"), text("problem"))
                    })
                    .collect()
            })
            .unwrap_or_default();
        Ok(RigRow {
            size,
            field_deg: field,
            method,
            seconds: secs,
            distinct_frames: after[0].saturating_sub(before[0]),
            refreshes: after[1].saturating_sub(before[1]),
            repeated: after[2].saturating_sub(before[2]),
            gaze_to_display_ms: (ms_of("p50_us"), ms_of("p99_us")),
            cast_size: format!("{}x{}", cast[0], cast[1]),
            problems: problems.join("; "),
        })
    })
}

pub const STAGE_HEADER: [&str; 8] = [
    "width",
    "height",
    "field_deg",
    "backend",
    "stage",
    "method",
    "time_ms",
    "note",
];

pub fn stage_table(rows: &[StageRow]) -> Table {
    let mut t = Table::new(&STAGE_HEADER);
    for r in rows {
        t.push(vec![
            r.size[0].to_string(),
            r.size[1].to_string(),
            format!("{}", r.field_deg),
            r.backend.to_string(),
            r.stage.to_string(),
            r.method.clone(),
            num(r.time_ms, 1),
            r.note.clone(),
        ]);
    }
    t
}

pub const RIG_HEADER: [&str; 12] = [
    "width",
    "height",
    "field_deg",
    "method",
    "seconds",
    "distinct_fps",
    "refresh_hz",
    "repeated_refreshes",
    "gaze_to_display_p50_ms",
    "gaze_to_display_p99_ms",
    "scene_cast_size",
    "problems",
];

pub fn rig_cells(r: &RigRow) -> Vec<String> {
    vec![
        r.size[0].to_string(),
        r.size[1].to_string(),
        format!("{}", r.field_deg),
        r.method.to_string(),
        format!("{:.1}", r.seconds),
        format!("{:.1}", r.distinct_fps()),
        format!("{:.1}", r.refreshes as f64 / r.seconds.max(1e-9)),
        r.repeated.to_string(),
        num(r.gaze_to_display_ms.0, 1),
        num(r.gaze_to_display_ms.1, 1),
        r.cast_size.clone(),
        r.problems.clone(),
    ]
}

pub fn rig_table(rows: &[RigRow]) -> Table {
    let mut t = Table::new(&RIG_HEADER);
    for r in rows {
        t.push(rig_cells(r));
    }
    t
}

/// Writes `panel_stages.csv`, `panel_rig.csv`, the chart `panel_fps` (distinct frames per
/// second against the panel size, a series per method and field) and the report's section.
pub fn write(
    out: &std::path::Path,
    md: &mut String,
    plan: &PanelPlan,
    stage_rows: &[StageRow],
    rig_rows: &[RigRow],
    gpu_note: &str,
) -> Result<()> {
    use super::charts::{self, Chart, Series};
    use super::report::markdown_table;
    use std::fmt::Write as _;
    stage_table(stage_rows).write(&out.join("panel_stages.csv"))?;
    rig_table(rig_rows).write(&out.join("panel_rig.csv"))?;
    let label = |s: [usize; 2]| format!("{} x {}", s[0], s[1]);
    let categories: Vec<String> = plan.sizes.iter().map(|&s| label(s)).collect();
    let mut series: Vec<Series> = Vec::new();
    for r in rig_rows {
        let name = format!("{}, {} deg", r.method, r.field_deg);
        let row = plan.sizes.iter().position(|&s| s == r.size).unwrap_or(0) as f64;
        match series.iter_mut().find(|s| s.name == name) {
            Some(s) => s.points.push((r.distinct_fps(), row)),
            None => series.push(Series {
                points: vec![(r.distinct_fps(), row)],
                ..Series::new(name)
            }),
        }
    }
    charts::write(
        &out.join("panel_fps"),
        (1100, 600),
        &Chart::Dots {
            title: "the binocular rig on the CPU: distinct frames per second by panel size per eye",
            x_desc: "distinct frames per second (60 Hz display)",
            categories: &categories,
            series: &series,
        },
    )?;
    let _ = writeln!(md, "## Panel sizes\n");
    let _ = writeln!(
        md,
        "Each eye's panel {} at {:?} degrees of horizontal field. Per-frame stages timed alone \
         (`panel_stages.csv`; one run each, a stage over {:.0} ms is not run at the larger \
         sizes). {gpu_note}\n",
        categories.join(", "),
        plan.fields_deg,
        plan.budget_ms
    );
    let stage_cells: Vec<Vec<String>> = stage_rows
        .iter()
        .map(|r| {
            vec![
                label(r.size),
                format!("{}", r.field_deg),
                r.backend.to_string(),
                if r.method.is_empty() {
                    r.stage.to_string()
                } else {
                    format!("{} ({})", r.stage, r.method)
                },
                num(r.time_ms, 1),
                r.note.clone(),
            ]
        })
        .collect();
    let _ = writeln!(
        md,
        "{}",
        markdown_table(
            &[
                "panel per eye",
                "field (deg)",
                "backend",
                "stage",
                "ms",
                "note"
            ],
            &stage_cells
        )
    );
    let _ = writeln!(
        md,
        "\nThe rig (`dioptra serve`'s, system clock): the binocular example rig of simulated \
         devices at 60 Hz, side by side, CPU backend, with only the panel, the field and the \
         method changed, measured for {:.0} s after a second to start (`panel_rig.csv`, chart \
         `panel_fps.png`). `pyramid-foveated` and `auto-foveated` set `render.foveation = {{ \
         radius_deg = 5.0 }}`.\n",
        plan.rig_seconds
    );
    let rig_cells: Vec<Vec<String>> = rig_rows.iter().map(rig_cells).collect();
    let _ = writeln!(md, "{}", markdown_table(&RIG_HEADER, &rig_cells));
    Ok(())
}
