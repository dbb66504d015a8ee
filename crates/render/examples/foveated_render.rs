//! Renders one RGB-D image with the foveated pyramid method (CPU), as `dioptra render --method
//! pyramid` does the full-resolution one, for scripts that score it
//! (`scripts/independent_validation/score_defocus.py --methods foveated`). The eye is the
//! CLI's default (4 mm pupil, 17 mm, 20 degrees); the foveation the default (5 degrees at full
//! resolution, Guenter's slope).
//!
//!   cargo run --release -p dioptra-render --example foveated_render -- \
//!       COLOR DEPTH FOCUS_D GAZE_X GAZE_Y OUT

use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::foveated::{foveated, Foveation};
use dioptra_render::io::{read_color, read_depth, write_color};
use std::path::Path;
use std::process::ExitCode;

fn run(a: &[String]) -> Result<(), String> {
    let [color, depth, focus, gx, gy, out] = a else {
        return Err("usage: foveated_render COLOR DEPTH FOCUS_D GAZE_X GAZE_Y OUT".into());
    };
    let num = |s: &str, what: &str| {
        s.parse::<f32>()
            .map_err(|_| format!("{what} {s:?} is not a number"))
    };
    let color = read_color(Path::new(color)).map_err(|e| format!("{color}: {e}"))?;
    let depth = read_depth(Path::new(depth), None).map_err(|e| format!("{depth}: {e}"))?;
    let input = Rgbd::new(color, depth).map_err(|e| e.to_string())?;
    let fov = Foveation::at([num(gx, "gaze x")?, num(gy, "gaze y")?]);
    let img = foveated(
        &input,
        Diopters(num(focus, "focus")?),
        &EyeModel::default(),
        &fov,
    )
    .map_err(|e| e.to_string())?;
    write_color(Path::new(out), &img.image).map_err(|e| format!("{out}: {e}"))
}

fn main() -> ExitCode {
    let a: Vec<String> = std::env::args().skip(1).collect();
    match run(&a) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("foveated_render: {e}");
            ExitCode::FAILURE
        }
    }
}
