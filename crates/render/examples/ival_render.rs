//! Renders one RGB-D image on the CPU with gather, the pyramid method or the pyramid foveated
//! around a gaze (the functions `dioptra render --backend cpu --method gather|pyramid` calls;
//! the CLI has no gaze option), for `scripts/independent_validation/score_defocus.py
//! --library`. The eye is the CLI's default (4 mm pupil, 17 mm, 20 degrees); the foveation the
//! default (5 degrees at full resolution, Guenter's slope). The gaze is ignored but by
//! `foveated`.
//!
//!   cargo run --release -p dioptra-render --example ival_render -- \
//!       gather|pyramid|foveated COLOR DEPTH FOCUS_D GAZE_X GAZE_Y OUT

use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::foveated::{foveated, Foveation};
use dioptra_render::gather::gather;
use dioptra_render::io::{read_color, read_depth, write_color};
use dioptra_render::pyramid::pyramid;
use std::path::Path;
use std::process::ExitCode;

fn run(a: &[String]) -> Result<(), String> {
    let [method, color, depth, focus, gx, gy, out] = a else {
        return Err(
            "usage: ival_render gather|pyramid|foveated COLOR DEPTH FOCUS_D GAZE_X GAZE_Y OUT"
                .into(),
        );
    };
    let num = |s: &str, what: &str| {
        s.parse::<f32>()
            .map_err(|_| format!("{what} {s:?} is not a number"))
    };
    let color = read_color(Path::new(color)).map_err(|e| format!("{color}: {e}"))?;
    let depth = read_depth(Path::new(depth), None).map_err(|e| format!("{depth}: {e}"))?;
    let input = Rgbd::new(color, depth).map_err(|e| e.to_string())?;
    let (q, eye) = (Diopters(num(focus, "focus")?), EyeModel::default());
    let img = match method.as_str() {
        "gather" => gather(&input, q, &eye),
        "pyramid" => pyramid(&input, q, &eye),
        "foveated" => {
            let fov = Foveation::at([num(gx, "gaze x")?, num(gy, "gaze y")?]);
            foveated(&input, q, &eye, &fov).map(|f| f.image)
        }
        _ => {
            return Err(format!(
                "unknown method {method:?}: gather, pyramid or foveated"
            ))
        }
    }
    .map_err(|e| e.to_string())?;
    write_color(Path::new(out), &img).map_err(|e| format!("{out}: {e}"))
}

fn main() -> ExitCode {
    let a: Vec<String> = std::env::args().skip(1).collect();
    match run(&a) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("ival_render: {e}");
            ExitCode::FAILURE
        }
    }
}
