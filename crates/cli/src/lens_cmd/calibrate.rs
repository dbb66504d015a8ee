//! `dioptra lens --device SPEC calibrate --powers=LO:HI:STEP [--settle-ms N]
//! (--measure-cmd CMD | --prompt | --from-csv FILE) --out FILE`: steps the lens through its
//! range, waits for it to settle, records its readback and temperature, takes the measured
//! accommodation demand at each step, fits a monotone curve (dioptra_core's
//! `CalibrationFit`), prints the residuals and writes the table the rig config's
//! `optics.calibration` reads, with its provenance. A noisy or non-monotonic result is
//! refused with the reason and nothing is written.

use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use dioptra_core::optics_map::{CalibrationFit, FitLimits, MAX_GAP_D, MIN_FIT_POINTS};
use dioptra_core::{Diopters, VarifocalLens};

use crate::common::measure::run_measure_cmd;

#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("measure").required(true).args(["measure_cmd", "prompt", "from_csv"])))]
pub struct CalibrateArgs {
    /// The commands to measure at, LO:HI:STEP diopters (e.g. -1:4:0.25; HI is always included;
    /// STEP at most 1 D). Cover the rig's optics.lens_range.
    #[arg(long, allow_hyphen_values = true)]
    powers: String,
    /// Wait this long after each command before reading the lens and measuring, ms.
    #[arg(long, default_value_t = 100)]
    settle_ms: u64,
    /// A shell command that measures the demand and prints it in diopters (its last line of
    /// stdout), run once per step with DIOPTRA_LENS_POWER_D (the command), DIOPTRA_LENS_READBACK_D
    /// and DIOPTRA_LENS_TEMPERATURE_C (when the lens reports them) set: a camera focus sweep, a
    /// focimeter or autorefractor script.
    #[arg(long)]
    measure_cmd: Option<String>,
    /// Ask the operator for each measurement (type the diopters, `skip` or `quit`).
    #[arg(long)]
    prompt: bool,
    /// Take the measurements from a CSV with columns command_d and measured_d (or demand_d),
    /// one row per power; the lens is still stepped, read and recorded.
    #[arg(long)]
    from_csv: Option<PathBuf>,
    /// Seconds a measure command may take.
    #[arg(long, default_value_t = 120)]
    measure_timeout_s: u64,
    /// Largest root-mean-square residual of the fit accepted, diopters.
    #[arg(long, default_value_t = FitLimits::default().max_rms_d)]
    max_rms_d: f64,
    /// Largest single residual accepted, diopters.
    #[arg(long, default_value_t = FitLimits::default().max_residual_d)]
    max_residual_d: f64,
    /// Where the table goes (CSV; `optics.calibration` in the rig config reads it).
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing table.
    #[arg(long)]
    force: bool,
}

/// Who was calibrated, for the provenance.
pub struct LensIdentity {
    /// e.g. "Optotune Lens Driver 4, serial ABC, firmware type A version 1.2.3".
    pub description: String,
    /// The --device argument.
    pub device: String,
}

/// One step's record.
struct Step {
    command: f64,
    readback: f64,
    temperature: Option<f32>,
    measured: Option<f64>,
}

/// Where the measurements come from.
enum Source {
    Command(String, Duration),
    Prompt,
    Table(Vec<(f64, f64)>, PathBuf),
}

impl Source {
    fn describe(&self) -> String {
        match self {
            Source::Command(c, _) => format!("the command `{c}`"),
            Source::Prompt => "the operator, at a prompt".into(),
            Source::Table(_, p) => format!("the file {}", p.display()),
        }
    }

    /// The measured demand at a step; `None`: skipped (prompt only).
    async fn measure(&self, step: &Step, k: usize, n: usize) -> Result<Option<f64>> {
        match self {
            Source::Command(cmd, timeout) => measure_step(cmd, step, *timeout).await.map(Some),
            Source::Prompt => prompt(step, k, n),
            Source::Table(rows, path) => rows
                .iter()
                .find(|(c, _)| (c - step.command).abs() < 5e-4)
                .map(|r| Some(r.1))
                .with_context(|| {
                    format!(
                        "{} has no row for command {} D",
                        path.display(),
                        step.command
                    )
                }),
        }
    }
}

pub async fn run<V: VarifocalLens>(
    lens: &mut V,
    args: &CalibrateArgs,
    who: &LensIdentity,
) -> Result<()> {
    let powers = parse_powers(&args.powers)?;
    let range = lens.power_range();
    if let Some(p) = powers
        .iter()
        .find(|p| !range.contains(Diopters(**p as f32)))
    {
        bail!(
            "--powers reaches {p} D, outside the range this lens is driven within, {}..{} D \
             (--min-d/--max-d, narrowed to what the lens reports it reaches)",
            range.min.0,
            range.max.0
        );
    }
    if args.out.exists() && !args.force {
        bail!(
            "{} exists; give --force to replace it, or another --out",
            args.out.display()
        );
    }
    let source = if let Some(cmd) = &args.measure_cmd {
        Source::Command(cmd.clone(), Duration::from_secs(args.measure_timeout_s))
    } else if let Some(path) = &args.from_csv {
        let rows = read_measurements(path)?;
        // Every power must have its row before the lens moves.
        if let Some(p) = powers
            .iter()
            .find(|p| !rows.iter().any(|(c, _)| (c - **p).abs() < 5e-4))
        {
            bail!(
                "{} has no row for command {p} D (one row per --powers step)",
                path.display()
            );
        }
        Source::Table(rows, path.clone())
    } else {
        Source::Prompt
    };
    let limits = FitLimits {
        max_rms_d: args.max_rms_d,
        max_residual_d: args.max_residual_d,
    };
    let settle = Duration::from_millis(args.settle_ms);
    let n = powers.len();
    println!(
        "calibrating {} over {} commands ({}), {} ms settle, measured by {}",
        who.description,
        n,
        args.powers,
        args.settle_ms,
        source.describe()
    );
    let mut steps = Vec::with_capacity(n);
    for (k, &p) in powers.iter().enumerate() {
        lens.set_power(Diopters(p as f32))
            .await
            .with_context(|| format!("cannot command {p} D"))?;
        tokio::time::sleep(settle).await;
        let state = lens
            .state()
            .await
            .with_context(|| format!("cannot read the lens back at {p} D"))?;
        let mut step = Step {
            command: p,
            readback: f64::from(state.power.0),
            temperature: state.temperature_c,
            measured: None,
        };
        step.measured = source.measure(&step, k, n).await?;
        println!(
            "step {:>3}/{n}  command {p:7.3} D  readback {:7.3} D  {}  measured {}",
            k + 1,
            step.readback,
            step.temperature
                .map_or("temperature n/a".to_string(), |t| format!("{t:6.2} °C")),
            step.measured
                .map_or("skipped".to_string(), |m| format!("{m:.4} D"))
        );
        steps.push(step);
    }
    let points: Vec<(f64, f64)> = steps
        .iter()
        .filter_map(|s| s.measured.map(|m| (s.command, m)))
        .collect();
    let fit = CalibrationFit::fit(&points, limits)
        .map_err(|e| anyhow::anyhow!("calibration refused, nothing written: {e}"))?;
    println!("fit: polynomial of degree {}", fit.degree);
    println!("  command_d  measured_d  fitted_d  residual_d");
    for ((m, f), r) in fit.measured.iter().zip(&fit.fitted).zip(fit.residuals()) {
        println!("  {:9.3}  {:10.4}  {f:8.4}  {r:+10.4}", m.0, m.1);
    }
    println!(
        "residuals: rms {:.4} D, largest {:+.4} D at command {:.3} D",
        fit.rms_d, fit.max_residual_d, fit.max_residual_at_d
    );
    write_table(&fit, &steps, args, who, &source)?;
    println!("wrote {}", args.out.display());
    Ok(())
}

/// LO:HI:STEP -> the commands, HI included.
fn parse_powers(s: &str) -> Result<Vec<f64>> {
    let parts: Vec<&str> = s.split(':').map(str::trim).collect();
    let [lo, hi, step] = parts[..] else {
        bail!("--powers is LO:HI:STEP in diopters, e.g. -1:4:0.25 (got {s:?})");
    };
    let num = |v: &str, what: &str| -> Result<f64> {
        v.parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .with_context(|| format!("--powers: {what} {v:?} is not a number of diopters"))
    };
    let (lo, hi, step) = (num(lo, "LO")?, num(hi, "HI")?, num(step, "STEP")?);
    if lo >= hi {
        bail!("--powers: LO must be below HI (got {lo}:{hi})");
    }
    if !(step > 0.0 && step <= MAX_GAP_D) {
        bail!("--powers: STEP must be more than 0 and at most {MAX_GAP_D} D (got {step}): the table needs a point at least every {MAX_GAP_D} D");
    }
    let count = ((hi - lo) / step + 1e-9).floor() as usize;
    if count > 2000 {
        bail!(
            "--powers: {} steps is too many; use a larger STEP",
            count + 1
        );
    }
    let mut out: Vec<f64> = (0..=count)
        .map(|k| ((lo + step * k as f64) * 1e6).round() / 1e6)
        .collect();
    if out.last().is_some_and(|&l| hi - l > 1e-6) {
        out.push(hi);
    }
    if out.len() < MIN_FIT_POINTS {
        bail!(
            "--powers {s} gives {} commands; a calibration needs at least {MIN_FIT_POINTS}: use a smaller STEP",
            out.len()
        );
    }
    Ok(out)
}

/// Runs the measure command for one step; its last non-empty line of stdout is the demand.
async fn measure_step(cmd: &str, step: &Step, timeout: Duration) -> Result<f64> {
    let env = [
        ("DIOPTRA_LENS_POWER_D", Some(format!("{}", step.command))),
        (
            "DIOPTRA_LENS_READBACK_D",
            Some(format!("{:.4}", step.readback)),
        ),
        (
            "DIOPTRA_LENS_TEMPERATURE_C",
            step.temperature.map(|t| format!("{t:.2}")),
        ),
    ];
    let at = format!("at command {} D", step.command);
    let measured = "the measured demand in diopters";
    run_measure_cmd(cmd, &env, timeout, &at, measured).await
}

/// Asks the operator; `None` for `skip`.
fn prompt(step: &Step, k: usize, n: usize) -> Result<Option<f64>> {
    let stdin = std::io::stdin();
    loop {
        eprint!(
            "step {}/{n}: lens at {:.3} D (reads {:.3} D{}); measured demand in D, `skip` or `quit`: ",
            k + 1,
            step.command,
            step.readback,
            step.temperature
                .map_or(String::new(), |t| format!(", {t:.2} °C"))
        );
        std::io::stderr().flush().ok();
        let mut line = String::new();
        if stdin.lock().read_line(&mut line)? == 0 {
            bail!("input ended at step {} of {n}; nothing written", k + 1);
        }
        match line.trim() {
            "skip" => return Ok(None),
            "quit" | "q" => bail!(
                "stopped by the operator at step {} of {n}; nothing written",
                k + 1
            ),
            v => match v.parse::<f64>() {
                Ok(d) if d.is_finite() => return Ok(Some(d)),
                _ => eprintln!("{v:?} is not a number of diopters"),
            },
        }
    }
}

/// A measurements CSV: `#` comments, a header naming command_d and measured_d (or demand_d).
fn read_measurements(path: &Path) -> Result<Vec<(f64, f64)>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read --from-csv {}", path.display()))?;
    let mut rows = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
    let (_, header) = rows
        .next()
        .with_context(|| format!("{}: no header line (command_d,measured_d)", path.display()))?;
    let names: Vec<&str> = header.split(',').map(str::trim).collect();
    let col = |want: &[&str]| names.iter().position(|n| want.contains(n));
    let (Some(ci), Some(mi)) = (col(&["command_d"]), col(&["measured_d", "demand_d"])) else {
        bail!(
            "{}: the header {header:?} needs columns command_d and measured_d (or demand_d)",
            path.display()
        );
    };
    rows.map(|(line, row)| {
        let cells: Vec<&str> = row.split(',').map(str::trim).collect();
        let num = |i: usize| {
            cells
                .get(i)
                .and_then(|c| c.parse::<f64>().ok())
                .filter(|v| v.is_finite())
        };
        match (num(ci), num(mi)) {
            (Some(c), Some(m)) => Ok((c, m)),
            _ => bail!("{} line {line}: {row:?} is not two numbers", path.display()),
        }
    })
    .collect()
}

/// Writes the fitted table with its provenance, through a temporary file in the same folder.
fn write_table(
    fit: &CalibrationFit,
    steps: &[Step],
    args: &CalibrateArgs,
    who: &LensIdentity,
    source: &Source,
) -> Result<()> {
    let now = std::time::SystemTime::now();
    let unix = now
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let temps: Vec<f32> = steps.iter().filter_map(|s| s.temperature).collect();
    let temperature = if temps.is_empty() {
        "not reported by this lens".to_string()
    } else {
        let lo = temps.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = temps.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let mean = temps.iter().sum::<f32>() / temps.len() as f32;
        format!("{lo:.2} to {hi:.2} °C (mean {mean:.2})")
    };
    let comments = vec![
        "dioptra lens calibration (dioptra lens calibrate)".to_string(),
        format!("date: {} (unix {unix})", httpdate::fmt_http_date(now)),
        format!("lens: {}", who.description),
        format!("device: {}", who.device),
        format!(
            "powers: {}, settle {} ms, {} measured of {} steps",
            args.powers,
            args.settle_ms,
            fit.measured.len(),
            steps.len()
        ),
        format!("measured by: {}", source.describe()),
        format!("lens temperature: {temperature}"),
        format!(
            "fit: polynomial of degree {}, residual rms {:.4} D, largest {:+.4} D at command {:.3} D",
            fit.degree, fit.rms_d, fit.max_residual_d, fit.max_residual_at_d
        ),
        "columns: command_d the lens command; demand_d the fitted accommodation demand at the eye \
         (what the rig reads); measured_d the measurement; readback_d and temperature_c the lens's own"
            .to_string(),
    ];
    let extra: Vec<Vec<String>> = fit
        .measured
        .iter()
        .map(|(c, m)| {
            let s = steps.iter().find(|s| s.command == *c);
            vec![
                format!("{m:.4}"),
                s.map_or(String::new(), |s| format!("{:.4}", s.readback)),
                s.and_then(|s| s.temperature)
                    .map_or(String::new(), |t| format!("{t:.2}")),
            ]
        })
        .collect();
    let name = args.out.display().to_string();
    let table = fit
        .table(&name)
        .map_err(|e| anyhow::anyhow!("calibration refused, nothing written: {e}"))?;
    let text = table.to_csv(
        &comments,
        &["measured_d", "readback_d", "temperature_c"],
        &extra,
    );
    // Beside the target, then renamed over it: a table is whole or absent.
    let mut tmp = args.out.clone().into_os_string();
    tmp.push(".partial");
    let tmp = PathBuf::from(tmp);
    std::fs::write(&tmp, text).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, &args.out)
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn powers_parse_with_the_end_included() {
        assert_eq!(
            parse_powers("-1:1:0.5").unwrap(),
            vec![-1.0, -0.5, 0.0, 0.5, 1.0]
        );
        assert_eq!(
            parse_powers("0:1.1:0.25").unwrap(),
            vec![0.0, 0.25, 0.5, 0.75, 1.0, 1.1]
        );
        for bad in ["0:1", "1:0:0.1", "0:4:1.5", "0:4:0", "a:1:0.1", "0:1:0.5"] {
            assert!(parse_powers(bad).is_err(), "{bad}");
        }
        let e = parse_powers("0:1:0.5").unwrap_err().to_string();
        assert!(e.contains("at least 5"), "{e}");
    }
}
