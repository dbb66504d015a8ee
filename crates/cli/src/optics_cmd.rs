//! `dioptra optics --config RIG.toml [--eye left|right] (--focus D | --command D) [--json]`:
//! an eye's optics map both ways, so a lab can check its numbers before a session.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use dioptra_core::{Diopters, OpticsMap, Side};
use dioptra_rig::config::RigConfig;
use serde_json::json;

#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("what").required(true).args(["focus", "command"])))]
pub struct Args {
    /// The rig config (TOML).
    #[arg(long)]
    config: PathBuf,
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
}

fn parse_side(s: &str) -> Result<Side, String> {
    Side::parse(s).ok_or_else(|| format!("{s:?}: expected left or right"))
}

pub fn run(args: Args) -> Result<()> {
    let cfg = RigConfig::load(&args.config)
        .with_context(|| format!("in the rig config {}", args.config.display()))?;
    for note in cfg.notices() {
        eprintln!("note: {note}");
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
