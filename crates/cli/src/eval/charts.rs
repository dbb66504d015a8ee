//! `dioptra eval`'s charts, each written as PNG (bitmap backend, bundled font) and SVG.

use std::path::Path;

use anyhow::{anyhow, Result};
use plotters::coord::Shift;
use plotters::prelude::*;

fn err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("drawing a chart failed: {e:?}")
}

/// Distinct colours for up to a dozen series, then repeating.
pub fn colour(i: usize) -> RGBColor {
    const C: [RGBColor; 12] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(127, 127, 127),
        RGBColor(188, 189, 34),
        RGBColor(23, 190, 207),
        RGBColor(0, 0, 0),
        RGBColor(255, 187, 120),
    ];
    C[i % C.len()]
}

/// A chart to draw.
pub enum Chart<'a> {
    SpeedAccuracy {
        title: &'a str,
        series: &'a [Series],
    },
    PsnrByFocus {
        title: &'a str,
        series: &'a [Series],
    },
    Dots {
        title: &'a str,
        x_desc: &'a str,
        categories: &'a [String],
        series: &'a [Series],
    },
    Panels {
        y_desc: &'a str,
        panels: &'a [(String, Vec<Series>)],
    },
}

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, chart: &Chart) -> Result<()> {
    root.fill(&WHITE).map_err(err)?;
    match chart {
        Chart::SpeedAccuracy { title, series } => speed_accuracy(root, title, series)?,
        Chart::PsnrByFocus { title, series } => psnr_by_focus(root, title, series)?,
        Chart::Dots {
            title,
            x_desc,
            categories,
            series,
        } => dots_by_category(root, title, x_desc, categories, series)?,
        Chart::Panels { y_desc, panels } => panels_over_time(root, y_desc, panels)?,
    }
    root.present().map_err(err)?;
    Ok(())
}

/// Draws `chart` into `BASE.png` and `BASE.svg`.
pub fn write(base: &Path, size: (u32, u32), chart: &Chart) -> Result<()> {
    crate::demo::plots::font();
    let png = base.with_extension("png");
    let svg = base.with_extension("svg");
    draw(&BitMapBackend::new(&png, size).into_drawing_area(), chart)?;
    draw(&SVGBackend::new(&svg, size).into_drawing_area(), chart)?;
    Ok(())
}

/// One named series of points.
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    /// Short text beside each point (a setting), or empty.
    pub tags: Vec<String>,
}

/// The lower-left Pareto frontier of `points` (time, accuracy): the points no other point is
/// both faster than and more accurate than, in order of time.
pub fn pareto(points: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut p: Vec<(f64, f64)> = points
        .iter()
        .copied()
        .filter(|(t, a)| t.is_finite() && a.is_finite() && *t > 0.0)
        .collect();
    p.sort_by(|a, b| a.0.total_cmp(&b.0).then(b.1.total_cmp(&a.1)));
    let mut out: Vec<(f64, f64)> = Vec::new();
    for q in p {
        if out.last().is_none_or(|l| q.1 > l.1) {
            out.push(q);
        }
    }
    out
}

fn range(vals: impl Iterator<Item = f64>, pad: f64) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in vals.filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo < 1e-9 {
        return (lo - 1.0, hi + 1.0);
    }
    let p = (hi - lo) * pad;
    (lo - p, hi + p)
}

/// Time per frame (log x) against PSNR, one marker series per method, the Pareto frontier of
/// all points drawn as a dashed step line.
fn speed_accuracy<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    series: &[Series],
) -> Result<()> {
    let all: Vec<(f64, f64)> = series.iter().flat_map(|s| s.points.clone()).collect();
    let (tlo, thi) = range(all.iter().map(|p| p.0.max(1e-3).log10()), 0.08);
    let (ylo, yhi) = range(all.iter().map(|p| p.1), 0.08);
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 22))
        .margin(14)
        .x_label_area_size(44)
        .y_label_area_size(60)
        .build_cartesian_2d((10f64.powf(tlo)..10f64.powf(thi)).log_scale(), ylo..yhi)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("time per frame (ms, log scale)")
        .y_desc("PSNR (dB)")
        .x_label_formatter(&|v| {
            if *v >= 10.0 {
                format!("{v:.0}")
            } else {
                format!("{v:.2}")
            }
        })
        .draw()
        .map_err(err)?;
    let front = pareto(&all);
    if front.len() > 1 {
        // A step line: each frontier point holds until the next, faster-and-better one.
        let mut steps = Vec::new();
        for w in front.windows(2) {
            steps.push(w[0]);
            steps.push((w[1].0, w[0].1));
        }
        steps.push(*front.last().unwrap_or(&front[0]));
        chart
            .draw_series(DashedLineSeries::new(steps, 6, 4, BLACK.stroke_width(1)))
            .map_err(err)?
            .label("Pareto frontier")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
    }
    for (i, s) in series.iter().enumerate() {
        let c = colour(i);
        chart
            .draw_series(s.points.iter().map(move |&p| Circle::new(p, 5, c.filled())))
            .map_err(err)?
            .label(s.name.clone())
            .legend(move |(x, y)| Circle::new((x + 10, y), 5, c.filled()));
        chart
            .draw_series(s.points.iter().zip(&s.tags).map(|(&p, tag)| {
                EmptyElement::at(p) + Text::new(tag.clone(), (7, -16), ("sans-serif", 13))
            }))
            .map_err(err)?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(err)?;
    Ok(())
}

/// PSNR against focus distance, one line per method.
fn psnr_by_focus<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    series: &[Series],
) -> Result<()> {
    let all: Vec<(f64, f64)> = series.iter().flat_map(|s| s.points.clone()).collect();
    let (xlo, xhi) = range(all.iter().map(|p| p.0), 0.03);
    let (ylo, yhi) = range(all.iter().map(|p| p.1), 0.08);
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 22))
        .margin(14)
        .x_label_area_size(44)
        .y_label_area_size(60)
        .build_cartesian_2d(xlo..xhi, ylo..yhi)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("focus distance (diopters)")
        .y_desc("PSNR (dB)")
        .draw()
        .map_err(err)?;
    for (i, s) in series.iter().enumerate() {
        let c = colour(i);
        let mut pts = s.points.clone();
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        chart
            .draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))
            .map_err(err)?
            .label(s.name.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
        chart
            .draw_series(pts.into_iter().map(move |p| Circle::new(p, 3, c.filled())))
            .map_err(err)?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(err)?;
    Ok(())
}

/// A dot plot: one row per category (named on the y axis), one marker series per method.
fn dots_by_category<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    x_desc: &str,
    categories: &[String],
    series: &[Series],
) -> Result<()> {
    let (xlo, xhi) = range(
        series.iter().flat_map(|s| s.points.iter().map(|p| p.0)),
        0.06,
    );
    let n = categories.len().max(1) as f64;
    let cats = categories.to_vec();
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 22))
        .margin(14)
        .x_label_area_size(44)
        .y_label_area_size(230)
        .build_cartesian_2d(xlo..xhi, -0.5..n - 0.5)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_labels(categories.len().max(1))
        .y_label_formatter(&move |v| {
            let i = v.round();
            if (v - i).abs() < 0.01 && i >= 0.0 {
                cats.get(i as usize).cloned().unwrap_or_default()
            } else {
                String::new()
            }
        })
        .draw()
        .map_err(err)?;
    let k = series.len().max(1) as f64;
    for (i, s) in series.iter().enumerate() {
        let c = colour(i);
        // Spread series vertically inside each row so markers do not hide each other.
        let off = (i as f64 - (k - 1.0) * 0.5) * (0.6 / k);
        chart
            .draw_series(
                s.points
                    .iter()
                    .map(move |&(x, row)| Circle::new((x, row + off), 5, c.filled())),
            )
            .map_err(err)?
            .label(s.name.clone())
            .legend(move |(x, y)| Circle::new((x + 10, y), 5, c.filled()));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(err)?;
    Ok(())
}

/// Stacked panels of lines over time: one panel per name, each with its own series.
fn panels_over_time<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    y_desc: &str,
    panels: &[(String, Vec<Series>)],
) -> Result<()> {
    let areas = root.split_evenly((panels.len().max(1), 1));
    let xmax = panels
        .iter()
        .flat_map(|p| p.1.iter().flat_map(|s| s.points.iter().map(|q| q.0)))
        .fold(0.1f64, f64::max);
    for ((name, series), area) in panels.iter().zip(areas.iter()) {
        let ymax = series
            .iter()
            .flat_map(|s| s.points.iter().map(|q| q.1))
            .filter(|v| v.is_finite())
            .fold(0.5f64, f64::max)
            * 1.1;
        let mut chart = ChartBuilder::on(area)
            .caption(name, ("sans-serif", 16))
            .margin(6)
            .x_label_area_size(26)
            .y_label_area_size(50)
            .build_cartesian_2d(0f64..xmax, 0f64..ymax)
            .map_err(err)?;
        chart
            .configure_mesh()
            .y_desc(y_desc)
            .y_labels(4)
            .draw()
            .map_err(err)?;
        for (i, s) in series.iter().enumerate() {
            let c = colour(i);
            chart
                .draw_series(LineSeries::new(s.points.clone(), c.stroke_width(1)))
                .map_err(err)?
                .label(s.name.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c));
        }
        if series.len() > 1 {
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .draw()
                .map_err(err)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_keeps_only_undominated_points() {
        let p = [
            (1.0, 30.0),
            (2.0, 29.0),
            (3.0, 35.0),
            (10.0, 34.0),
            (20.0, 40.0),
        ];
        assert_eq!(pareto(&p), vec![(1.0, 30.0), (3.0, 35.0), (20.0, 40.0)]);
        assert!(pareto(&[(f64::NAN, 1.0)]).is_empty());
    }
}
