//! `dioptra lens --device DRIVER:PORT info|get|set|sweep|temp|calibrate`: talk to one
//! varifocal lens, opened through the rig's drivers' table (`crate::common::device_spec`);
//! `calibrate` is in [`calibrate`].

use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context as _, Result};
use clap::Subcommand;
use dioptra_core::{Clock, Diopters, LensState, PowerRange, SystemClock, Timestamp, VarifocalLens};
use dioptra_lens::{LensLimits, OutOfRange};
use dioptra_rig::devices::open::{self, Context, LensSetup};

use crate::common::device_spec;

mod calibrate;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// DRIVER:PORT, the rig config's driver and port: optotune:/dev/ttyACM0, lens:/dev/ttyACM1
    /// (CDC-ACM), lens:usb[:SERIAL] (USB bulk endpoints), or a USB serial device by VID:PID
    /// (lens:1209:d10b).
    #[arg(long)]
    device: String,
    /// Lowest power the rig allows, diopters (narrowed further to what the lens reaches).
    #[arg(long, default_value_t = -10.0, allow_hyphen_values = true)]
    min_d: f32,
    /// Highest power the rig allows, diopters.
    #[arg(long, default_value_t = 10.0, allow_hyphen_values = true)]
    max_d: f32,
    /// Refuse an out-of-range power instead of clamping it.
    #[arg(long)]
    refuse: bool,
    #[command(subcommand)]
    action: Action,
}

#[derive(Subcommand, Debug)]
enum Action {
    /// Identity, limits and mode of the device.
    Info,
    /// Power, current and temperature now.
    Get,
    /// Command a power, diopters.
    Set {
        #[arg(allow_hyphen_values = true)]
        diopters: f32,
        /// Then print the lens state every 5 ms for this long.
        #[arg(long, default_value_t = 0)]
        watch_ms: u64,
    },
    /// Step through powers FROM:TO (diopters), reading the state after each dwell.
    Sweep {
        #[arg(allow_hyphen_values = true)]
        range: String,
        #[arg(long, default_value_t = 0.5)]
        step: f32,
        #[arg(long, default_value_t = 50)]
        dwell_ms: u64,
    },
    /// Lens temperature (and, on an Optotune, the status bits).
    Temp,
    /// Measure the accommodation demand at each of a range of commands and write the rig's
    /// calibration table (`optics.calibration`).
    Calibrate(calibrate::CalibrateArgs),
}

pub fn run(args: Args) -> Result<()> {
    crate::common::block_on(run_async(args))
}

async fn run_async(args: Args) -> Result<()> {
    let (row, port) = device_spec::parse_device(&args.device, &open::LENS, "lens driver")?;
    let power = PowerRange::new(Diopters(args.min_d), Diopters(args.max_d))
        .context("--min-d must not exceed --max-d, and both must be finite")?;
    let policy = if args.refuse {
        OutOfRange::Refuse
    } else {
        OutOfRange::Clamp
    };
    let limits = LensLimits::new(power).with_policy(policy);
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    // The driver keeps every command within `limits`, and reopens the port after an unplug.
    let ctx = Context::new(clock.clone(), LensSetup::new(limits));
    let ctx = device_spec::reopening(ctx, row, port.clone());
    let session = || format!("cannot start a session with the {} at {port}", row.what);
    let link = device_spec::link(row, &port).await.with_context(session)?;
    let mut d = (row.connect)(link, ctx).await.with_context(session)?;
    match &args.action {
        Action::Info => device_spec::print_facts(&d.about().await?),
        Action::Temp => device_spec::print_facts(&d.condition().await?),
        Action::Calibrate(c) => {
            let who = calibrate::LensIdentity {
                description: d.identity(),
                device: args.device.clone(),
            };
            return calibrate::run(&mut d, c, &who).await;
        }
        action => return common(&mut d, action, &limits, &*clock).await,
    }
    Ok(())
}

/// get, set and sweep: the same for every driver. `limits` are the driver's, so what is
/// printed as sent is what the driver sent.
async fn common<V: VarifocalLens>(
    d: &mut V,
    action: &Action,
    limits: &LensLimits,
    clock: &dyn Clock,
) -> Result<()> {
    let start = clock.now();
    match action {
        Action::Get => println!("{}", line(&d.state().await?)),
        Action::Set { diopters, watch_ms } => {
            let sent = d.set_power(Diopters(*diopters)).await?;
            println!(
                "{} (on the wire {:.3} ms after start)",
                what_went_out(*diopters, limits, d.power_range()),
                ms(sent, start)
            );
            let mut next = tokio::time::Instant::now();
            let until = next + Duration::from_millis(*watch_ms);
            while next < until {
                next += Duration::from_millis(5);
                tokio::time::sleep_until(next).await;
                let s = d.state().await?;
                println!("+{:7.2} ms  {}", ms(s.host_time, sent), line(&s));
            }
        }
        Action::Sweep {
            range,
            step,
            dwell_ms,
        } => {
            let (from, to) = parse_range(range)?;
            if step.is_nan() || *step <= 0.0 || !step.is_finite() {
                bail!("--step must be a positive number of diopters");
            }
            let n = ((to - from).abs() / step + 1e-4).floor() as usize;
            for k in 0..=n {
                let p = from + (to - from).signum() * *step * k as f32;
                let sent = d.set_power(Diopters(p)).await?;
                let out = sent_power(p, limits, d.power_range());
                tokio::time::sleep(Duration::from_millis(*dwell_ms)).await;
                let s = d.state().await?;
                let clamped = if out == p { "" } else { " (clamped)" };
                println!(
                    "{:8.1} ms  set {out:7.3} D{clamped}  ->  {}",
                    ms(sent, start),
                    line(&s)
                );
            }
        }
        Action::Info | Action::Temp | Action::Calibrate(_) => {
            bail!("{action:?} is not a power command")
        }
    }
    Ok(())
}

/// The power the driver sent for a request of `asked` (it clamps with the same limits and
/// range; a refused request never gets here).
fn sent_power(asked: f32, limits: &LensLimits, range: PowerRange) -> f32 {
    limits
        .check_power(Diopters(asked), range)
        .map_or(asked, |p| p.0)
}

/// `set`'s line: the power that went out, and the request when it was clamped.
fn what_went_out(asked: f32, limits: &LensLimits, range: PowerRange) -> String {
    let out = sent_power(asked, limits, range);
    if out == asked {
        format!("set {out:.3} D")
    } else {
        format!(
            "set {out:.3} D (asked {asked:.3} D, clamped to the driving range {:.3} .. {:.3} D)",
            range.min.0, range.max.0
        )
    }
}

fn parse_range(s: &str) -> Result<(f32, f32)> {
    let (a, b) = s
        .split_once(':')
        .context("a sweep range is FROM:TO, e.g. 0:3")?;
    let a: f32 = a.trim().parse().context("FROM is not a number")?;
    let b: f32 = b.trim().parse().context("TO is not a number")?;
    if !a.is_finite() || !b.is_finite() {
        bail!("sweep bounds must be finite");
    }
    Ok((a, b))
}

fn ms(t: Timestamp, since: Timestamp) -> f64 {
    t.signed_diff_ns(since) as f64 / 1e6
}

fn line(s: &LensState) -> String {
    let opt =
        |v: Option<f32>, unit: &str| v.map_or("n/a".to_string(), |v| format!("{v:.2} {unit}"));
    let settled = match s.settled {
        Some(true) => "settled",
        Some(false) => "moving",
        None => "settling not reported",
    };
    format!(
        "power {:.3} D  current {}  temperature {}  {settled}",
        s.power.0,
        opt(s.current_ma, "mA"),
        opt(s.temperature_c, "°C")
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn set_says_what_went_out() {
        let range = PowerRange::new(Diopters(-1.9000001), Diopters(6.4849997)).unwrap();
        let limits = LensLimits::new(range);
        assert_eq!(what_went_out(2.5, &limits, range), "set 2.500 D");
        assert_eq!(
            what_went_out(9.0, &limits, range),
            "set 6.485 D (asked 9.000 D, clamped to the driving range -1.900 .. 6.485 D)"
        );
        assert_eq!(sent_power(-3.0, &limits, range), -1.9000001);
    }

    #[test]
    fn sweep_ranges_parse() {
        assert_eq!(parse_range("0:3").unwrap(), (0.0, 3.0));
        assert_eq!(parse_range("-1.5: 2").unwrap(), (-1.5, 2.0));
        assert!(parse_range("3").is_err());
        assert!(parse_range("a:1").is_err());
        assert!(parse_range("0:inf").is_err());
    }
}
