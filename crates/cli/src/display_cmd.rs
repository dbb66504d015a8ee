//! `dioptra display calibrate --measure-cmd CMD --out FILE`: the panel's transfer function,
//! measured. It shows grey levels from black to white, runs a measure command at each (as
//! `dioptra lens calibrate` does: a photometer script whose last line of stdout is the
//! luminance in cd/m²), fits a monotone curve (dioptra_core's `TransferFit`), prints the
//! residuals and writes the table rig.toml's `display.transfer = { table = "FILE" }` reads,
//! with its provenance. A noisy or non-monotone result is refused with the reason and
//! nothing is written.
//!
//! Where the levels are shown: for now a headless frame, a PNG of the panel at the level's
//! code value (`DIOPTRA_DISPLAY_FRAME` names it), which `dioptra display sim-photometer`
//! measures; a photometer on a real panel needs the level on the screen, which is the
//! daemon's window (see docs/optics-image.md for what that part needs).
//!
//! `dioptra display sim-photometer`: a simulated spot photometer on a simulated panel (gamma,
//! black, white, noise), for CI and for trying the calibration without hardware.

use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::common;
use crate::common::measure::run_measure_cmd;
use anyhow::{bail, Context, Result};
use dioptra_core::transfer::{TransferFit, TransferFitLimits, MIN_LEVELS};
use dioptra_sim::eye_camera::{PanelResponse, Photometer};

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    command: DisplayCommand,
}

#[derive(clap::Subcommand, Debug)]
enum DisplayCommand {
    /// Measure the panel's transfer function with a photometer and write its table.
    Calibrate(CalibrateArgs),
    /// A simulated photometer on a simulated panel: prints the luminance of the level shown.
    SimPhotometer(SimPhotometerArgs),
}

#[derive(clap::Args, Debug)]
pub struct CalibrateArgs {
    /// A shell command that reads the photometer and prints the luminance in cd/m² (its last
    /// line of stdout), run once per reading with DIOPTRA_DISPLAY_LEVEL (the level shown, 0 to
    /// 1), DIOPTRA_DISPLAY_CODE (its code value at --bits), DIOPTRA_DISPLAY_BITS,
    /// DIOPTRA_DISPLAY_STEP (1 to --levels), DIOPTRA_DISPLAY_READING (1 to --readings) and
    /// DIOPTRA_DISPLAY_FRAME (the frame shown, a PNG) set.
    #[arg(long)]
    measure_cmd: String,
    /// Grey levels from black to white, evenly spaced in code value (at least 6; PsychoPy's
    /// monitor centre takes 8, 17 or more follow a panel's toe).
    #[arg(long, default_value_t = 17)]
    levels: usize,
    /// Readings per level, averaged.
    #[arg(long, default_value_t = 1)]
    readings: usize,
    /// The panel's bits per channel: each level is shown as the nearest code value.
    #[arg(long, default_value_t = 8)]
    bits: u32,
    /// Wait this long after showing a level before reading, ms (the panel's response and the
    /// photometer's integration).
    #[arg(long, default_value_t = 500)]
    settle_ms: u64,
    /// Seconds a measure command may take.
    #[arg(long, default_value_t = 60)]
    measure_timeout_s: u64,
    /// The size of the frame shown, WIDTHxHEIGHT pixels.
    #[arg(long, default_value = "64x64")]
    frame: String,
    /// What was calibrated, for the provenance (e.g. "left microdisplay, Sony ECX335, brightness 80").
    #[arg(long, default_value = "not given (--panel-name)")]
    panel_name: String,
    /// Largest root-mean-square residual of the fit accepted, percent of the luminance range.
    #[arg(long, default_value_t = 100.0 * TransferFitLimits::default().max_rms)]
    max_rms_pct: f64,
    /// Largest single residual accepted, percent of the luminance range.
    #[arg(long, default_value_t = 100.0 * TransferFitLimits::default().max_residual)]
    max_residual_pct: f64,
    /// Where the table goes (CSV; `display.transfer = { table = "FILE" }` reads it).
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing table.
    #[arg(long)]
    force: bool,
}

#[derive(clap::Args, Debug)]
pub struct SimPhotometerArgs {
    /// The simulated panel's exponent.
    #[arg(long, default_value_t = 2.4)]
    gamma: f64,
    /// Its luminance at code 0, cd/m² (light added on top: backlight bleed, flare).
    #[arg(long, default_value_t = 0.3)]
    black_cd_m2: f64,
    /// Its luminance at full scale, cd/m².
    #[arg(long, default_value_t = 120.0)]
    white_cd_m2: f64,
    /// Its bits per channel.
    #[arg(long, default_value_t = 8)]
    bits: u32,
    /// The reading's noise, percent of the reading (standard deviation).
    #[arg(long, default_value_t = 0.0)]
    noise_pct: f64,
    /// Seed of the noise (a reading's draw also depends on DIOPTRA_DISPLAY_STEP and
    /// DIOPTRA_DISPLAY_READING).
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

pub fn run(args: Args) -> Result<()> {
    match args.command {
        DisplayCommand::Calibrate(a) => common::block_on(calibrate(a)),
        DisplayCommand::SimPhotometer(a) => sim_photometer(a),
    }
}

/// One level's record.
struct Level {
    level: f64,
    code: u64,
    readings: Vec<f64>,
}

impl Level {
    fn mean(&self) -> f64 {
        self.readings.iter().sum::<f64>() / self.readings.len() as f64
    }
}

fn full_scale(bits: u32) -> u64 {
    (1u64 << bits) - 1
}

async fn calibrate(args: CalibrateArgs) -> Result<()> {
    if !(MIN_LEVELS..=1024).contains(&args.levels) {
        bail!(
            "--levels {}: a calibration needs {MIN_LEVELS} to 1024 levels",
            args.levels
        );
    }
    if !(1..=16).contains(&args.bits) {
        bail!("--bits {}: expected 1 to 16", args.bits);
    }
    if !(1..=100).contains(&args.readings) {
        bail!("--readings {}: expected 1 to 100", args.readings);
    }
    let full = full_scale(args.bits);
    if (args.levels as u64) > full + 1 {
        bail!(
            "--levels {} is more than the {} code values of a {}-bit panel",
            args.levels,
            full + 1,
            args.bits
        );
    }
    let frame = parse_frame(&args.frame)?;
    if args.out.exists() && !args.force {
        bail!(
            "{} exists; give --force to replace it, or another --out",
            args.out.display()
        );
    }
    let limits = TransferFitLimits {
        max_rms: args.max_rms_pct / 100.0,
        max_residual: args.max_residual_pct / 100.0,
    };
    let shown = std::env::temp_dir().join(format!(
        "dioptra-display-calibrate-{}.png",
        std::process::id()
    ));
    println!(
        "calibrating {} at {} levels ({} bits, {} reading(s) each, {} ms settle), measured by `{}`",
        args.panel_name, args.levels, args.bits, args.readings, args.settle_ms, args.measure_cmd
    );
    let result = measure_levels(&args, full, frame, &shown).await;
    std::fs::remove_file(&shown).ok();
    let levels = result?;
    let points: Vec<(f64, f64)> = levels.iter().map(|l| (l.level, l.mean())).collect();
    let fit = TransferFit::fit(&points, limits)
        .map_err(|e| anyhow::anyhow!("calibration refused, nothing written: {e}"))?;
    println!(
        "fit: polynomial of degree {} in level^{:.3}",
        fit.degree, fit.gamma
    );
    println!("  level     code  measured_cd_m2  fitted_cd_m2  residual_%");
    for ((l, f), r) in levels.iter().zip(&fit.fitted).zip(fit.residuals()) {
        println!(
            "  {:.4}  {:>6}  {:>14.4}  {f:>12.4}  {:>+10.3}",
            l.level,
            l.code,
            l.mean(),
            100.0 * r
        );
    }
    println!(
        "residuals: rms {:.3} %, largest {:+.3} % at level {:.4} (of the luminance range)",
        100.0 * fit.rms,
        100.0 * fit.max_residual,
        fit.max_residual_at
    );
    write_table(&fit, &levels, &args)?;
    println!("wrote {}", args.out.display());
    Ok(())
}

fn parse_frame(s: &str) -> Result<[usize; 2]> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("--frame {s:?}: expected WIDTHxHEIGHT, e.g. 64x64"))?;
    let (w, h) = (
        w.trim().parse::<usize>().ok(),
        h.trim().parse::<usize>().ok(),
    );
    match (w, h) {
        (Some(w), Some(h)) if (1..=8192).contains(&w) && (1..=8192).contains(&h) => Ok([w, h]),
        _ => bail!("--frame {s:?}: expected WIDTHxHEIGHT, 1 to 8192 pixels each"),
    }
}

async fn measure_levels(
    args: &CalibrateArgs,
    full: u64,
    frame: [usize; 2],
    shown: &Path,
) -> Result<Vec<Level>> {
    let n = args.levels;
    let timeout = Duration::from_secs(args.measure_timeout_s);
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let code = ((k as f64 / (n - 1) as f64) * full as f64).round() as u64;
        let level = code as f64 / full as f64;
        show_headless(shown, frame, code, args.bits)?;
        tokio::time::sleep(Duration::from_millis(args.settle_ms)).await;
        let mut readings = Vec::with_capacity(args.readings);
        for r in 0..args.readings {
            let env = [
                ("DIOPTRA_DISPLAY_LEVEL", Some(format!("{level:.6}"))),
                ("DIOPTRA_DISPLAY_CODE", Some(code.to_string())),
                ("DIOPTRA_DISPLAY_BITS", Some(args.bits.to_string())),
                ("DIOPTRA_DISPLAY_STEP", Some((k + 1).to_string())),
                ("DIOPTRA_DISPLAY_READING", Some((r + 1).to_string())),
                ("DIOPTRA_DISPLAY_FRAME", Some(shown.display().to_string())),
            ];
            let at = format!("at level {level:.4} (code {code})");
            readings.push(
                run_measure_cmd(
                    &args.measure_cmd,
                    &env,
                    timeout,
                    &at,
                    "the luminance in cd/m²",
                )
                .await?,
            );
        }
        let l = Level {
            level,
            code,
            readings,
        };
        println!(
            "level {:>4}/{n}  {level:.4} (code {code:>5})  {:.4} cd/m²",
            k + 1,
            l.mean()
        );
        out.push(l);
    }
    Ok(out)
}

/// Shows a level on the headless panel: the whole frame at `code`, written as a PNG (8-bit up
/// to 8 bits, else 16-bit with the code scaled to full range), through a temporary file so a
/// reader never sees half a frame.
fn show_headless(path: &Path, frame: [usize; 2], code: u64, bits: u32) -> Result<()> {
    let [w, h] = frame;
    let (depth, bytes) = if bits <= 8 {
        let v = (code * 255 / full_scale(bits)) as u8;
        (png::BitDepth::Eight, vec![v; w * h])
    } else {
        let v = ((code as f64 / full_scale(bits) as f64) * 65535.0).round() as u16;
        (png::BitDepth::Sixteen, v.to_be_bytes().repeat(w * h))
    };
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".partial");
    let tmp = PathBuf::from(tmp);
    let file = std::fs::File::create(&tmp)
        .with_context(|| format!("cannot write the frame {}", tmp.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w as u32, h as u32);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(depth);
    enc.write_header()
        .and_then(|mut wr| wr.write_image_data(&bytes))
        .with_context(|| format!("cannot write the frame {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

/// Writes the fitted table (every 8-bit code's level) with the provenance and the readings
/// as comments, through a temporary file in the same folder.
fn write_table(fit: &TransferFit, levels: &[Level], args: &CalibrateArgs) -> Result<()> {
    let now = std::time::SystemTime::now();
    let unix = now
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let mut comments = vec![
        "dioptra panel calibration (dioptra display calibrate)".to_string(),
        format!("date: {} (unix {unix})", httpdate::fmt_http_date(now)),
        format!("panel: {}", args.panel_name),
        format!(
            "levels: {} from black to white, {} bits, {} reading(s) each averaged, settle {} ms",
            levels.len(),
            args.bits,
            args.readings,
            args.settle_ms
        ),
        format!("measured by: the command `{}`", args.measure_cmd),
        format!(
            "fit: polynomial of degree {} in level^{:.4}, residual rms {:.3} %, largest {:+.3} % at level {:.4} (of the luminance range)",
            fit.degree,
            fit.gamma,
            100.0 * fit.rms,
            100.0 * fit.max_residual,
            fit.max_residual_at
        ),
        "columns: level the code value as a fraction of full scale (8-bit code 128 is 128/255); \
         luminance_cd_m2 the fitted luminance there"
            .to_string(),
        "readings: level, code, measured_cd_m2 (mean), the readings".to_string(),
    ];
    for l in levels {
        let each: Vec<String> = l.readings.iter().map(|r| format!("{r:.6}")).collect();
        comments.push(format!(
            "  {:.6}, {}, {:.6}, {}",
            l.level,
            l.code,
            l.mean(),
            each.join(" ")
        ));
    }
    let name = args.out.display().to_string();
    let table = fit
        .table(&name, 255)
        .map_err(|e| anyhow::anyhow!("calibration refused, nothing written: {e}"))?;
    let text = table.to_csv(&comments, &[], &[]);
    let mut tmp = args.out.clone().into_os_string();
    tmp.push(".partial");
    let tmp = PathBuf::from(tmp);
    std::fs::write(&tmp, text).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, &args.out)
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    Ok(())
}

/// The level a frame shows: the mean code value of its central tenth (a spot photometer's
/// field), as a fraction of full scale.
fn frame_level(path: &Path) -> Result<f64> {
    let file = std::fs::File::open(path)
        .with_context(|| format!("cannot read the frame {}", path.display()))?;
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .with_context(|| format!("{} is not a PNG", path.display()))?;
    let (w, h) = (reader.info().width as usize, reader.info().height as usize);
    if w * h > 64 << 20 {
        bail!(
            "{}: a {w}x{h} frame is larger than any panel",
            path.display()
        );
    }
    let (color, depth) = (reader.info().color_type, reader.info().bit_depth);
    if color != png::ColorType::Grayscale
        || !matches!(depth, png::BitDepth::Eight | png::BitDepth::Sixteen)
    {
        bail!(
            "{}: expected a grey 8- or 16-bit frame, found {color:?} {depth:?}",
            path.display()
        );
    }
    let mut buf = vec![0u8; reader.output_buffer_size().context("frame too large")?];
    reader
        .next_frame(&mut buf)
        .with_context(|| format!("cannot decode {}", path.display()))?;
    let value = |x: usize, y: usize| -> f64 {
        let i = y * w + x;
        match depth {
            png::BitDepth::Eight => f64::from(buf[i]) / 255.0,
            _ => f64::from(u16::from_be_bytes([buf[2 * i], buf[2 * i + 1]])) / 65535.0,
        }
    };
    let (x0, x1) = (w * 9 / 20, (w * 11 / 20).max(w * 9 / 20 + 1).min(w));
    let (y0, y1) = (h * 9 / 20, (h * 11 / 20).max(h * 9 / 20 + 1).min(h));
    let mut sum = 0.0;
    for y in y0..y1 {
        for x in x0..x1 {
            sum += value(x, y);
        }
    }
    Ok(sum / ((x1 - x0) * (y1 - y0)) as f64)
}

fn sim_photometer(args: SimPhotometerArgs) -> Result<()> {
    let sane = args.gamma.is_finite()
        && args.gamma > 0.0
        && args.black_cd_m2.is_finite()
        && args.black_cd_m2 >= 0.0
        && args.white_cd_m2.is_finite()
        && args.white_cd_m2 > args.black_cd_m2
        && (1..=16).contains(&args.bits)
        && args.noise_pct.is_finite()
        && args.noise_pct >= 0.0;
    if !sane {
        bail!("the simulated panel needs --gamma above 0, 0 <= --black-cd-m2 < --white-cd-m2, --bits 1 to 16 and --noise-pct at least 0");
    }
    let var = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
    // The frame shown when there is one (the photometer looks at the panel); else the level
    // the calibration says it shows.
    let level = match (var("DIOPTRA_DISPLAY_FRAME"), var("DIOPTRA_DISPLAY_LEVEL")) {
        (Some(frame), _) => frame_level(Path::new(&frame))?,
        (None, Some(l)) => l
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .with_context(|| format!("DIOPTRA_DISPLAY_LEVEL={l:?} is not a number"))?,
        (None, None) => bail!(
            "nothing shown: run me as `dioptra display calibrate`'s --measure-cmd (it sets \
             DIOPTRA_DISPLAY_FRAME and DIOPTRA_DISPLAY_LEVEL)"
        ),
    };
    let index = |k: &str| var(k).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
    let meter = Photometer {
        panel: PanelResponse {
            gamma: args.gamma,
            black_cd_m2: args.black_cd_m2,
            white_cd_m2: args.white_cd_m2,
            bits: args.bits,
        },
        noise: args.noise_pct / 100.0,
        seed: args.seed,
    };
    let reading = meter.read(
        level,
        1000 * index("DIOPTRA_DISPLAY_STEP") + index("DIOPTRA_DISPLAY_READING"),
    );
    println!("{reading:.6}");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_shown_is_the_level_read() {
        let dir = std::env::temp_dir().join(format!("dioptra-frame-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (bits, code) in [(8, 128u64), (10, 700), (1, 1)] {
            let path = dir.join(format!("f{bits}.png"));
            show_headless(&path, [20, 10], code, bits).unwrap();
            let want = code as f64 / full_scale(bits) as f64;
            let got = frame_level(&path).unwrap();
            assert!((got - want).abs() < 1e-4, "{bits} bits: {got} vs {want}");
        }
        std::fs::remove_dir_all(&dir).ok();
        assert!(parse_frame("64x64").is_ok());
        assert!(parse_frame("64").is_err() && parse_frame("0x5").is_err());
    }
}
