//! The demo's charts, drawn with plotters' bitmap backend and the bundled font
//! ([`crate::common::charts`]), so they need no system library.

use std::path::Path;

use anyhow::{anyhow, Result};
#[cfg(feature = "simulated")]
use dioptra_rig::simulated_rig::Run;
use dioptra_sched::{Mode, Stage};
use plotters::prelude::*;

use crate::common::charts::font;

fn err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("drawing a chart failed: {e:?}")
}

/// Histogram of the loop's main latency: gaze-to-focus (varifocal) or gaze-to-display.
#[cfg(feature = "simulated")]
pub fn latency(path: &Path, r: &Run) -> Result<()> {
    font();
    let l = &r.latency;
    let (stage, what) = if l.stage(Stage::GazeToSettled).is_empty() {
        (Stage::GazeToDisplay, "gaze sample to display")
    } else {
        (Stage::GazeToSettled, "gaze sample to lens settled")
    };
    let h = l.stage(stage);
    // 0.5 ms bins up to the 99.9th percentile.
    let bin_us = 500u64;
    let top = h.value_at_quantile(0.999).max(bin_us) + bin_us;
    let nbins = (top / bin_us) as usize;
    let mut bins = vec![0u64; nbins.max(1)];
    for v in h.iter_recorded() {
        let b = ((v.value_iterated_to() / bin_us) as usize).min(bins.len() - 1);
        bins[b] += v.count_at_value();
    }
    let ymax = bins.iter().copied().max().unwrap_or(1).max(1) as f64 * 1.1;
    let root = BitMapBackend::new(path, (900, 500)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let caption = format!(
        "{what}: p50 {:.1} ms, p99 {:.1} ms, n = {}",
        h.value_at_quantile(0.5) as f64 / 1000.0,
        h.value_at_quantile(0.99) as f64 / 1000.0,
        h.len()
    );
    let mut chart = ChartBuilder::on(&root)
        .caption(caption, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(56)
        .build_cartesian_2d(0f64..top as f64 / 1000.0, 0f64..ymax)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("latency (ms)")
        .y_desc("count")
        .draw()
        .map_err(err)?;
    chart
        .draw_series(bins.iter().enumerate().map(|(i, &c)| {
            let x0 = (i as u64 * bin_us) as f64 / 1000.0;
            let x1 = x0 + bin_us as f64 / 1000.0;
            Rectangle::new([(x0, 0.0), (x1, c as f64)], BLUE.mix(0.7).filled())
        }))
        .map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}

/// Focus over time: the depth looked at and the eyes' vergence (ground truth), and in
/// varifocal mode the commanded and actual lens power.
#[cfg(feature = "simulated")]
pub fn focus(path: &Path, r: &Run, mode: Mode) -> Result<()> {
    font();
    let p = &r.log.probes;
    let secs = |t: dioptra_core::Timestamp| t.as_secs_f64();
    let xmax = p.last().map_or(1.0, |q| secs(q.t)).max(0.1);
    let ymax = p
        .iter()
        .flat_map(|q| {
            [
                q.gaze_target_d.map(|v| v as f32),
                q.eye_focus.map(|v| v.0),
                q.commanded_focus.map(|v| v.0),
            ]
        })
        .flatten()
        .fold(1.0f32, f32::max) as f64
        * 1.15;
    let root = BitMapBackend::new(path, (1200, 500)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("focus over time ({} mode)", mode.as_str()),
            ("sans-serif", 22),
        )
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(56)
        .build_cartesian_2d(0f64..xmax, 0f64..ymax)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("simulated time (s)")
        .y_desc("diopters")
        .draw()
        .map_err(err)?;
    type Pick = fn(&dioptra_rig::simulated_rig::Probe) -> Option<f64>;
    let series: [(&str, RGBColor, Pick); 4] = [
        ("depth looked at (truth)", RGBColor(120, 120, 120), |q| {
            q.gaze_target_d
        }),
        ("vergence (truth)", GREEN, |q| q.vergence_d),
        // Lens powers as the focus each gives: the command through the rig's optics map,
        // the simulated lens through the simulated optics (what the eye sees).
        ("lens commanded (focus it aims at)", BLUE, |q| {
            q.commanded_focus.map(|v| f64::from(v.0))
        }),
        ("lens actual (focus it gives, simulated)", RED, |q| {
            q.eye_focus.map(|v| f64::from(v.0))
        }),
    ];
    for (name, colour, pick) in series {
        let pts: Vec<(f64, f64)> = p
            .iter()
            .filter_map(|q| pick(q).map(|v| (secs(q.t), v)))
            .collect();
        if pts.is_empty() {
            continue;
        }
        chart
            .draw_series(LineSeries::new(pts, colour.stroke_width(2)))
            .map_err(err)?
            .label(name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}
