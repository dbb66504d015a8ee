//! `dioptra optics --config RIG.toml [--eye left|right] (--focus D | --command D) [--json]`:
//! an eye's optics map both ways, so a lab can check its numbers before a session.
//!
//! `dioptra optics --distortion FILE --panel WxH --distortion-grid OUT.png`: the pre-warped
//! grid a lab puts in front of its eyepiece (straight and fringe-free through it when the
//! model is right); `--points project|unproject|warp` maps points read on stdin through the
//! model (the OpenCV check, scripts/check_distortion_opencv.py, drives it).

use std::io::BufRead;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use dioptra_core::distortion::EyepieceModel;
use dioptra_core::{Diopters, OpticsMap, Plane, RgbImage, Side};
use dioptra_render::warp::{warp_cpu, WarpDraw, WarpMesh, DEFAULT_STEP_PX};
use dioptra_rig::config::RigConfig;
use serde_json::json;

#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("what").required(true).args(["focus", "command", "distortion_grid", "points"])))]
pub struct Args {
    /// The rig config (TOML); needed for --focus and --command.
    #[arg(long, required_unless_present = "distortion")]
    config: Option<PathBuf>,
    /// The eye whose map to use: left or right (default: the rig's one lens; `[optics]`, or
    /// the one per-eye section a monocular bench gives).
    #[arg(long, value_parser = parse_side)]
    eye: Option<Side>,
    /// A focus (the accommodation demand the content asks of the eye, diopters): prints the
    /// lens command that gives it.
    #[arg(long, allow_hyphen_values = true)]
    focus: Option<f32>,
    /// A lens command (the tunable lens's power, diopters): prints the focus it gives.
    #[arg(long, allow_hyphen_values = true)]
    command: Option<f32>,
    /// One JSON object instead of text: `lens_command_d` for a focus, `focus_d` for a
    /// command, and `magnification` (null where no layout gives it).
    #[arg(long)]
    json: bool,
    /// The eyepiece's distortion model: a TOML file with the keys of rig.toml's
    /// `[optics.distortion]` (fx, fy, cx, cy, k1..k6, p1, p2, and [red], [green], [blue]
    /// overriding any of them), either at its top level or under `[optics.distortion]` /
    /// `[optics.left.distortion]` as in a rig config. See docs/optics-image.md.
    #[arg(long)]
    distortion: Option<PathBuf>,
    /// Draw the pre-warped grid for the eyepiece into this PNG (the panel's size): white
    /// lines every --grid-step-px of the ideal image and a cross at the optical centre. The
    /// eyepiece from --distortion FILE, or from --config's `[optics.distortion]` (or
    /// `[optics.<eye>.distortion]`, `distortion_file`) with the panel the config's display
    /// (one eye's image) and its code values encoded for the eye's `display.transfer`.
    #[arg(long)]
    distortion_grid: Option<PathBuf>,
    /// Read points on stdin, two numbers a line, and print where the model takes them, per
    /// channel (red, green, blue: six numbers a line, `nan` where there is none): `project`
    /// takes eye directions (x, y tangents) to panel pixels; `unproject` panel pixels to
    /// directions; `warp` panel pixels to the source pixels the pre-warp mesh reads there.
    #[arg(long, requires = "distortion", value_parser = ["project", "unproject", "warp"])]
    points: Option<String>,
    /// The panel, WIDTHxHEIGHT pixels (for the grid and `--points warp`).
    #[arg(long, value_parser = parse_size)]
    panel: Option<[usize; 2]>,
    /// The rendered (source) image, WIDTHxHEIGHT (default: the panel's size).
    #[arg(long, value_parser = parse_size)]
    source: Option<[usize; 2]>,
    /// The grid's spacing, pixels of the ideal image.
    #[arg(long, default_value_t = 60)]
    grid_step_px: usize,
    /// The pre-warp mesh's vertex spacing, panel pixels.
    #[arg(long, default_value_t = DEFAULT_STEP_PX)]
    mesh_step_px: usize,
}

fn parse_size(s: &str) -> Result<[usize; 2], String> {
    let bad = || format!("{s:?}: expected WIDTHxHEIGHT in pixels, e.g. 1920x1080");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let (w, h) = (
        w.trim().parse::<usize>().map_err(|_| bad())?,
        h.trim().parse::<usize>().map_err(|_| bad())?,
    );
    if w == 0 || h == 0 || w > 16384 || h > 16384 {
        return Err(format!("{s:?}: each side must be 1 to 16384 pixels"));
    }
    Ok([w, h])
}

fn parse_side(s: &str) -> Result<Side, String> {
    Side::parse(s).ok_or_else(|| format!("{s:?}: expected left or right"))
}

pub fn run(args: Args) -> Result<()> {
    if let Some(path) = &args.distortion {
        let model = load_distortion(path, args.eye)?;
        if let Some(out) = &args.distortion_grid {
            return draw_grid(&args, &model, out, None);
        }
        if let Some(mode) = &args.points {
            return map_points(&args, &model, mode);
        }
    }
    let Some(config) = &args.config else {
        bail!("--focus and --command need --config RIG.toml");
    };
    let cfg = RigConfig::load(config)
        .with_context(|| format!("in the rig config {}", config.display()))?;
    for note in cfg.notices() {
        eprintln!("note: {note}");
    }
    if let Some(out) = &args.distortion_grid {
        return grid_from_config(&args, &cfg, config, out);
    }
    if args.points.is_some() {
        bail!("--points needs --distortion FILE");
    }
    let map = cfg.optics_map(args.eye)?;
    let range = map.range();
    let (command, focus, clamped) = match (args.focus, args.command) {
        (Some(f), None) => {
            if !f.is_finite() {
                bail!("--focus must be a number of diopters");
            }
            let c = map.command_for(Diopters(f));
            // A focus the lens cannot reach comes back as a range end.
            let reached = map.focus_of(c);
            (c, Diopters(f), (reached.0 - f).abs() > 1e-3)
        }
        (None, Some(c)) => {
            if !(c.is_finite() && range.contains(Diopters(c))) {
                bail!(
                    "--command {c} D is outside optics.lens_range {}..{} D",
                    range.min.0,
                    range.max.0
                );
            }
            (Diopters(c), map.focus_of(Diopters(c)), false)
        }
        _ => bail!("give --focus or --command"),
    };
    let magnification = map.magnification(command);
    let (near, far) = focus_span(&map);
    let eye = args.eye.map(Side::as_str);
    if args.json {
        let mut v = json!({
            "eye": eye,
            "source": map.source_name(),
            "map": map.describe(),
            "magnification": magnification.map(round6),
            "focus_range_d": [round6(far), round6(near)],
            "lens_range_d": [round6(range.min.0), round6(range.max.0)],
        });
        if args.focus.is_some() {
            v["focus_d"] = json!(round6(focus.0));
            v["lens_command_d"] = json!(round6(command.0));
            v["clamped"] = json!(clamped);
        } else {
            v["lens_command_d"] = json!(round6(command.0));
            v["focus_d"] = json!(round6(focus.0));
        }
        println!("{v}");
        return Ok(());
    }
    println!("eye            {}", eye.unwrap_or("the rig's one lens"));
    println!("map            {}", map.describe());
    if args.focus.is_some() {
        println!(
            "focus          {:.4} D  ->  lens command {:.4} D{}",
            focus.0,
            command.0,
            if clamped {
                format!(
                    " (the nearest the lens range gives: it reaches focus {far:.3}..{near:.3} D)"
                )
            } else {
                String::new()
            }
        );
    } else {
        println!(
            "lens command   {:.4} D  ->  focus {:.4} D",
            command.0, focus.0
        );
    }
    match magnification {
        Some(m) => {
            println!("magnification  {m:.4} (the image's angular size against the bare display's)")
        }
        None => println!("magnification  not known (no [optics.layout])"),
    }
    println!(
        "lens range     {}..{} D gives focus {far:.3}..{near:.3} D",
        range.min.0, range.max.0
    );
    Ok(())
}

/// A value to 1e-6 (the maps are exact to f32's ~1e-7 relative; more digits are noise).
fn round6(v: f32) -> f64 {
    (f64::from(v) * 1e6).round() / 1e6
}

/// The nearest and farthest focus the lens range gives (as (near, far), diopters).
fn focus_span(map: &OpticsMap) -> (f32, f32) {
    let r = map.range();
    let (a, b) = (map.focus_of(r.min).0, map.focus_of(r.max).0);
    (a.max(b), a.min(b))
}

/// The model from a `--distortion` file: `[optics.<eye>.distortion]`, `[optics.distortion]`,
/// or the section's keys at the top level, in that order.
fn load_distortion(path: &Path, eye: Option<Side>) -> Result<EyepieceModel> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read --distortion {}", path.display()))?;
    let name = path.display().to_string();
    let (section_keys, section) =
        dioptra_rig::optics::config::parse_distortion_file(&name, &text, eye)
            .map_err(anyhow::Error::msg)?;
    section_keys
        .model(&section)
        .with_context(|| format!("in {}", path.display()))
}

/// `--config X --distortion-grid OUT.png`: the eye's eyepiece as the daemon reads it, on its
/// panel (one eye's image, `display.width` x `height`), encoded for its panel.
fn grid_from_config(args: &Args, cfg: &RigConfig, path: &Path, out: &Path) -> Result<()> {
    if cfg.display.stereo() && args.eye.is_none() {
        bail!(
            "{}: display.layout = \"{}\" has an image per eye: give --eye left or --eye right",
            path.display(),
            cfg.display.layout.as_str()
        );
    }
    let eye = if cfg.display.stereo() { args.eye } else { None };
    let images = cfg.eye_images()?;
    let image = images
        .iter()
        .find(|i| i.eye == eye)
        .context("no image for that eye on this display layout")?;
    let Some(eyepiece) = &image.eyepiece else {
        bail!(
            "{}: no eyepiece distortion for {} ([optics.distortion], \
             [optics.<eye>.distortion] or distortion_file; see docs/optics-image.md)",
            path.display(),
            eye.map_or("the one image".to_string(), |e| format!(
                "the {} eye",
                e.as_str()
            ))
        );
    };
    let panel = [cfg.display.width as usize, cfg.display.height as usize];
    let args = Args {
        panel: Some(args.panel.unwrap_or(panel)),
        source: args.source,
        ..args.clone_for_grid()
    };
    println!("eyepiece: {}", eyepiece.from);
    draw_grid(&args, &eyepiece.model, out, Some(&image.transfer))
}

impl Args {
    /// The grid's settings (the rest left empty).
    fn clone_for_grid(&self) -> Args {
        Args {
            config: None,
            eye: self.eye,
            focus: None,
            command: None,
            json: false,
            distortion: None,
            distortion_grid: self.distortion_grid.clone(),
            points: None,
            panel: self.panel,
            source: self.source,
            grid_step_px: self.grid_step_px,
            mesh_step_px: self.mesh_step_px,
        }
    }
}

fn panel_of(args: &Args) -> Result<[usize; 2]> {
    args.panel
        .context("give the panel's size, --panel WIDTHxHEIGHT (e.g. 1920x1080)")
}

/// The ideal image of the grid: lines `step` pixels apart through the optical centre, 2 px
/// wide (each pixel lit by the fraction of it the line covers), the centre's lines 4 px.
fn grid_image(size: [usize; 2], centre: [f64; 2], step: f64) -> RgbImage {
    // Coverage of pixel [p - 0.5, p + 0.5] by lines of half-width `half` at c + k step.
    let cover = |p: f64, c: f64| -> f32 {
        let k = ((p - c) / step).round();
        let d = (p - (c + k * step)).abs();
        let half = if k == 0.0 { 2.0 } else { 1.0 };
        (half + 0.5 - d).clamp(0.0, 1.0) as f32
    };
    let [w, h] = size;
    let cols: Vec<f32> = (0..w).map(|x| cover(x as f64, centre[0])).collect();
    let rows: Vec<f32> = (0..h).map(|y| cover(y as f64, centre[1])).collect();
    let data: Vec<f32> = (0..w * h).map(|i| cols[i % w].max(rows[i / w])).collect();
    let p = Plane::from_vec(w, h, data).expect("size");
    RgbImage::from_planes(p.clone(), p.clone(), p).expect("size")
}

/// Draws the grid; with `transfer` its code values are encoded for that panel (written as
/// they are), otherwise sRGB.
fn draw_grid(
    args: &Args,
    model: &EyepieceModel,
    out: &Path,
    transfer: Option<&dioptra_core::transfer::Transfer>,
) -> Result<()> {
    let panel = panel_of(args)?;
    let source = args.source.unwrap_or(panel);
    if args.grid_step_px < 4 {
        bail!("--grid-step-px must be at least 4");
    }
    let mesh = WarpMesh::new(model, panel, source, args.mesh_step_px)?;
    // The render intrinsics in source pixels.
    let (sx, sy) = (
        source[0] as f64 / panel[0] as f64,
        source[1] as f64 / panel[1] as f64,
    );
    let centre = [
        (model.render.cx + 0.5) * sx - 0.5,
        (model.render.cy + 0.5) * sy - 0.5,
    ];
    let ideal = grid_image(source, centre, args.grid_step_px as f64 * sx);
    let lut = transfer.map(dioptra_render::transfer::EncodeLut::new);
    let warped = warp_cpu(
        &ideal,
        &mesh,
        &WarpDraw {
            scale: 1.0,
            encode: lut.as_ref(),
        },
    )?;
    match &lut {
        Some(lut) => {
            dioptra_render::io::write_code_values(out, &warped)?;
            println!("encoded for the panel: {}", lut.describe());
        }
        None => dioptra_render::io::write_color(out, &warped)?,
    }
    println!(
        "wrote {} ({}x{} panel, grid every {} px of the ideal image)",
        out.display(),
        panel[0],
        panel[1],
        args.grid_step_px
    );
    println!(
        "mesh: vertices every {} px, within {:.4} px of the exact model{}",
        args.mesh_step_px,
        mesh.interpolation_error(model),
        match mesh.unreachable() {
            0 => String::new(),
            n => format!(
                "; {n} vertices beyond the model's fold (drawn black: the eye does not see there)"
            ),
        }
    );
    // Where the eye sees the panel's edges (green), degrees from the optical axis.
    let g = &model.channels[1];
    let deg = |t: f64| t.atan().to_degrees();
    let (w, h) = (panel[0] as f64 - 0.5, panel[1] as f64 - 0.5);
    let at = |u: f64, v: f64| g.unproject(u, v);
    match (
        at(-0.5, g.camera.cy),
        at(w, g.camera.cy),
        at(g.camera.cx, -0.5),
        at(g.camera.cx, h),
    ) {
        (Some(l), Some(r), Some(t), Some(b)) => println!(
            "field (green): {:.1} to {:.1} degrees across, {:.1} to {:.1} down",
            deg(l.0),
            deg(r.0),
            deg(t.1),
            deg(b.1)
        ),
        _ => println!("field (green): an edge of the panel is beyond the model's fold"),
    }
    Ok(())
}

fn map_points(args: &Args, model: &EyepieceModel, mode: &str) -> Result<()> {
    let mesh = if mode == "warp" {
        let panel = panel_of(args)?;
        Some(WarpMesh::new(
            model,
            panel,
            args.source.unwrap_or(panel),
            args.mesh_step_px,
        )?)
    } else {
        None
    };
    let stdin = std::io::stdin();
    let mut out = String::new();
    for (n, line) in stdin.lock().lines().enumerate() {
        let line = line.context("reading stdin")?;
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v: Vec<f64> = line
            .split([' ', ',', '\t'])
            .filter(|c| !c.is_empty())
            .map(|c| c.parse::<f64>())
            .collect::<Result<_, _>>()
            .ok()
            .filter(|v: &Vec<f64>| v.len() == 2 && v.iter().all(|x| x.is_finite()))
            .with_context(|| format!("stdin line {}: {line:?} is not two numbers", n + 1))?;
        let mut cells = Vec::with_capacity(6);
        for (c, ch) in model.channels.iter().enumerate() {
            let p = match mode {
                "project" => Some(ch.project(v[0], v[1])),
                "unproject" => ch.unproject(v[0], v[1]),
                _ => mesh
                    .as_ref()
                    .and_then(|m| m.source_at(v[0] as f32, v[1] as f32, c))
                    .map(|s| (f64::from(s[0]), f64::from(s[1]))),
            };
            match p {
                Some((a, b)) => {
                    cells.push(format!("{a:.12e}"));
                    cells.push(format!("{b:.12e}"));
                }
                None => cells.extend(["nan".to_string(), "nan".to_string()]),
            }
        }
        out += &cells.join(" ");
        out.push('\n');
    }
    print!("{out}");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse() {
        assert_eq!(parse_size("1920x1080"), Ok([1920, 1080]));
        for bad in ["1920", "0x10", "ax3", "20000x10"] {
            assert!(parse_size(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_grid_s_lines_are_where_the_step_puts_them() {
        let g = grid_image([41, 21], [20.0, 10.0], 10.0);
        let at = |x, y| g.channels[1].get(x, y).unwrap();
        // The centre's lines are 4 px wide, the others 2 (a pixel half covered, half lit).
        assert_eq!(
            (at(20, 3), at(19, 3), at(18, 3), at(23, 3)),
            (1.0, 1.0, 0.5, 0.0)
        );
        assert_eq!((at(30, 3), at(31, 3), at(32, 3)), (1.0, 0.5, 0.0));
        assert_eq!(at(5, 0), 1.0);
        assert_eq!(at(5, 5), 0.0);
    }
}
