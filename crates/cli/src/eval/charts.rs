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
    /// One panel per group of methods (varifocal, multifocal): each its own colours.
    PsnrByFocus {
        title: &'a str,
        panels: &'a [(String, Vec<Series>)],
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
        Chart::PsnrByFocus { title, panels } => psnr_by_focus(root, title, panels)?,
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
    crate::common::charts::font();
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
    /// Drawn with hollow markers: on the speed chart, the GPU backend's points of the method
    /// `name`, which shares its colour with the CPU's filled ones.
    pub hollow: bool,
}

impl Series {
    pub fn new(name: impl Into<String>) -> Series {
        Series {
            name: name.into(),
            points: Vec::new(),
            tags: Vec::new(),
            hollow: false,
        }
    }
}

/// Each series' colour: one per distinct name in order of first appearance, so a method's
/// filled (CPU) and hollow (GPU) series share it and distinct methods differ while there are
/// no more than the palette's dozen.
pub fn colours_by_name(series: &[Series]) -> Vec<RGBColor> {
    let mut names: Vec<&str> = Vec::new();
    series
        .iter()
        .map(|s| {
            let i = match names.iter().position(|n| *n == s.name) {
                Some(i) => i,
                None => {
                    names.push(&s.name);
                    names.len() - 1
                }
            };
            colour(i)
        })
        .collect()
}

/// `root` below its title (the area a chart with its legend beside it splits).
fn titled<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
) -> Result<DrawingArea<DB, Shift>> {
    root.margin(6, 0, 0, 0)
        .titled(title, ("sans-serif", 22))
        .map_err(err)
}

/// What a legend row shows before its text.
enum Key {
    Dot(RGBColor, bool),
    Line(RGBColor),
    Dashed,
}

/// A legend drawn in its own area beside a plot, so it hides no data.
fn legend_beside<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    top: i32,
    rows: &[(String, Key)],
) -> Result<()> {
    let font = ("sans-serif", 13).into_font();
    for (i, (text, key)) in rows.iter().enumerate() {
        let y = top + 18 * i as i32;
        match *key {
            Key::Dot(c, hollow) => area.draw(&dot((14, y), 5, c, hollow)).map_err(err)?,
            Key::Line(c) => area
                .draw(&PathElement::new(vec![(4, y), (24, y)], c.stroke_width(2)))
                .map_err(err)?,
            Key::Dashed => {
                for x in [4, 14] {
                    area.draw(&PathElement::new(vec![(x, y), (x + 6, y)], BLACK))
                        .map_err(err)?;
                }
            }
        }
        area.draw(&Text::new(text.clone(), (32, y - 7), font.clone()))
            .map_err(err)?;
    }
    Ok(())
}

/// A round marker, filled or (hollow) a ring.
fn dot<C>(at: C, r: i32, c: RGBColor, hollow: bool) -> Circle<C, i32> {
    Circle::new(
        at,
        r,
        if hollow {
            c.stroke_width(2)
        } else {
            c.filled()
        },
    )
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

/// Time per frame (log x) against PSNR: a colour per method, filled markers for the CPU and
/// hollow for the GPU, the Pareto frontier of all points drawn as a dashed step line, the
/// legend beside the plot.
fn speed_accuracy<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    series: &[Series],
) -> Result<()> {
    let root = titled(root, title)?;
    let (plot, side) = root.split_horizontally(root.dim_in_pixel().0.saturating_sub(190));
    let all: Vec<(f64, f64)> = series.iter().flat_map(|s| s.points.clone()).collect();
    let (tlo, thi) = range(all.iter().map(|p| p.0.max(1e-3).log10()), 0.08);
    let (ylo, yhi) = range(all.iter().map(|p| p.1), 0.08);
    let mut chart = ChartBuilder::on(&plot)
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
    let mut legend: Vec<(String, Key)> = Vec::new();
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
            .map_err(err)?;
        legend.push(("Pareto frontier".into(), Key::Dashed));
    }
    let colours = colours_by_name(series);
    for (s, &c) in series.iter().zip(&colours) {
        let hollow = s.hollow;
        chart
            .draw_series(s.points.iter().map(move |&p| dot(p, 5, c, hollow)))
            .map_err(err)?;
        chart
            .draw_series(s.points.iter().zip(&s.tags).map(|(&p, tag)| {
                EmptyElement::at(p) + Text::new(tag.clone(), (7, -16), ("sans-serif", 13))
            }))
            .map_err(err)?;
        if !legend.iter().any(|(n, _)| *n == s.name) {
            legend.push((s.name.clone(), Key::Dot(c, false)));
        }
    }
    if series.iter().any(|s| s.hollow) {
        legend.push(("filled: CPU".into(), Key::Dot(BLACK, false)));
        legend.push(("hollow: GPU".into(), Key::Dot(BLACK, true)));
    }
    legend_beside(&side, 30, &legend)
}

/// PSNR against focus distance, one line per method, a panel per group of methods side by
/// side, each with its legend below the plot.
fn psnr_by_focus<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    panels: &[(String, Vec<Series>)],
) -> Result<()> {
    let areas = titled(root, title)?.split_evenly((1, panels.len().max(1)));
    for ((name, series), area) in panels.iter().zip(areas.iter()) {
        let rows = series.len() as u32;
        let (plot, side) = area.split_vertically(
            area.dim_in_pixel()
                .1
                .saturating_sub(18 * rows.div_ceil(2) + 12),
        );
        let all: Vec<(f64, f64)> = series.iter().flat_map(|s| s.points.clone()).collect();
        let (xlo, xhi) = range(all.iter().map(|p| p.0), 0.03);
        let (ylo, yhi) = range(all.iter().map(|p| p.1), 0.08);
        let mut chart = ChartBuilder::on(&plot)
            .caption(name, ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(56)
            .build_cartesian_2d(xlo..xhi, ylo..yhi)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("focus distance (diopters)")
            .y_desc("PSNR (dB)")
            .draw()
            .map_err(err)?;
        let mut legend = Vec::new();
        for (i, s) in series.iter().enumerate() {
            let c = colour(i);
            let mut pts = s.points.clone();
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
            chart
                .draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))
                .map_err(err)?;
            chart
                .draw_series(pts.into_iter().map(move |p| Circle::new(p, 3, c.filled())))
                .map_err(err)?;
            legend.push((s.name.clone(), Key::Line(c)));
        }
        // Two columns of legend rows under the plot.
        let half = legend.len().div_ceil(2);
        let cols = side.split_evenly((1, 2));
        let right = legend.split_off(half);
        legend_beside(&cols[0].margin(0, 0, 60, 0), 6, &legend)?;
        legend_beside(&cols[1], 6, &right)?;
    }
    Ok(())
}

/// A dot plot: one row per category (named on the y axis), one marker series per method, the
/// legend beside the plot.
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
    let root = titled(root, title)?;
    let (plot, side) = root.split_horizontally(root.dim_in_pixel().0.saturating_sub(190));
    let mut chart = ChartBuilder::on(&plot)
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
    let mut legend = Vec::new();
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
            .map_err(err)?;
        legend.push((s.name.clone(), Key::Dot(c, false)));
    }
    legend_beside(&side, 30, &legend)
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

    #[test]
    fn a_method_keeps_one_colour_across_backends_and_methods_differ() {
        let mut gpu = Series::new("gather");
        gpu.hollow = true;
        let s = [
            Series::new("gather"),
            Series::new("lightfield"),
            gpu,
            Series::new("linear"),
        ];
        let c = colours_by_name(&s);
        assert_eq!(c[0], c[2], "gather on the CPU and the GPU");
        assert_ne!(c[0], c[1]);
        assert_ne!(c[1], c[3]);
        assert_ne!(c[0], c[3]);
    }
}
