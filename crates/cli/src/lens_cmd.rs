//! `dioptra lens --device DRIVER:PORT info|get|set|sweep|temp|calibrate`: talk to one
//! varifocal lens, opened through the rig's drivers' table (`crate::device_spec`);
//! `calibrate` is in [`crate::lens_calibrate`].

use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Subcommand;
use dioptra_core::{Clock, Diopters, LensState, PowerRange, SystemClock, Timestamp, VarifocalLens};
use dioptra_lens::optotune::protocol::Status;
use dioptra_lens::{
    ControllerConfig, LensController, LensLimits, Opener, Optotune, OptotuneConfig, OutOfRange,
};
use dioptra_rig::config::LensDriver;
use dioptra_rig::devices::open;
use dioptra_transport::ByteLink;

use crate::device_spec;

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
    Calibrate(crate::lens_calibrate::CalibrateArgs),
}

pub fn run(args: Args) -> Result<()> {
    crate::block_on(run_async(args))
}

async fn run_async(args: Args) -> Result<()> {
    let (row, port) = device_spec::parse(&args.device, &open::LENS, "lens driver")?;
    let power = PowerRange::new(Diopters(args.min_d), Diopters(args.max_d))
        .context("--min-d must not exceed --max-d, and both must be finite")?;
    let policy = if args.refuse {
        OutOfRange::Refuse
    } else {
        OutOfRange::Clamp
    };
    let limits = LensLimits::new(power).with_policy(policy);
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let opener = device_spec::byte_opener(row, port.clone());
    match row.driver {
        LensDriver::Optotune => {
            let mut d = Optotune::connect_with(opener, OptotuneConfig::new(limits), clock.clone())
                .await
                .with_context(|| {
                    format!("cannot start an Optotune Lens Driver 4 session on {port}")
                })?;
            match &args.action {
                Action::Info => optotune_info(&mut d).await,
                Action::Calibrate(c) => {
                    let who = d.info().map_or("Optotune Lens Driver 4".into(), |i| {
                        format!(
                            "Optotune Lens Driver 4, serial {}, firmware type {} version {}",
                            i.serial_number,
                            char::from(i.firmware_type),
                            i.firmware_version
                        )
                    });
                    let who = crate::lens_calibrate::LensIdentity {
                        description: who,
                        device: args.device.clone(),
                    };
                    crate::lens_calibrate::run(&mut d, c, &who).await
                }
                Action::Temp => {
                    let t = d.temperature_c().await?;
                    let s = d.status().await?;
                    println!("temperature {t:.2} °C");
                    println!("status {:#010x}{}", s.0, describe_status(s));
                    Ok(())
                }
                action => common(&mut d, action, &limits, &*clock).await,
            }
        }
        LensDriver::Lens => controller(opener, ControllerConfig::new(limits), &args, clock).await,
    }
}

async fn controller<L: ByteLink + 'static>(
    opener: Opener<L>,
    cfg: ControllerConfig,
    args: &Args,
    clock: Arc<dyn Clock>,
) -> Result<()> {
    let limits = cfg.limits;
    let mut d = LensController::connect_with(opener, cfg, clock.clone())
        .await
        .context("cannot start a dioptra lens controller session")?;
    match &args.action {
        Action::Info => {
            if let Some(i) = d.info() {
                let v = i.firmware_version;
                println!("device        dioptra lens controller ({:?})", i.kind);
                println!("serial        {}", i.serial);
                println!(
                    "firmware      {}.{}.{} (protocol {})",
                    v.major, v.minor, v.patch, i.protocol_version
                );
                println!("capabilities  {:#x}", i.capabilities.0);
            }
            if let Some(l) = d.device_limits() {
                println!(
                    "device limits {:.3} .. {:.3} D, max current {:.2} mA",
                    l.min_power_d, l.max_power_d, l.max_current_ma
                );
            }
            let r = d.power_range();
            println!("driving range {:.3} .. {:.3} D", r.min.0, r.max.0);
            Ok(())
        }
        Action::Calibrate(c) => {
            let who = crate::lens_calibrate::LensIdentity {
                description: d.info().map_or("dioptra lens controller".into(), |i| {
                    let v = i.firmware_version;
                    format!(
                        "dioptra lens controller ({:?}), serial {}, firmware {}.{}.{}",
                        i.kind, i.serial, v.major, v.minor, v.patch
                    )
                }),
                device: args.device.clone(),
            };
            crate::lens_calibrate::run(&mut d, c, &who).await
        }
        Action::Temp => {
            let s = d.state().await?;
            match s.temperature_c {
                Some(t) => println!("temperature {t:.2} °C"),
                None => println!("temperature not measured by this controller"),
            }
            Ok(())
        }
        action => common(&mut d, action, &limits, &*clock).await,
    }
}

async fn optotune_info<L: ByteLink>(d: &mut Optotune<L>) -> Result<()> {
    let temp = d.temperature_c().await?;
    let Some(i) = d.info() else {
        bail!("not connected")
    };
    println!("device        Optotune Lens Driver 4");
    println!(
        "firmware      type {} version {}",
        char::from(i.firmware_type),
        i.firmware_version
    );
    println!("serial        {}", i.serial_number);
    println!("device id     {}", i.device_id);
    println!("max current   {:.2} mA", i.max_current_ma);
    println!(
        "device range  {:.3} .. {:.3} D (focal-power mode, over its temperature limits)",
        i.device_range.min.0, i.device_range.max.0
    );
    let r = d.power_range();
    println!("driving range {:.3} .. {:.3} D", r.min.0, r.max.0);
    println!("mode          {:?}", d.mode());
    println!("temperature   {temp:.2} °C");
    Ok(())
}

/// The status word's set bits in the device's words, errors marked (they stop focal-power
/// control).
fn describe_status(s: Status) -> String {
    let mut names: Vec<String> = s
        .errors()
        .names()
        .into_iter()
        .map(|n| format!("error: {n}"))
        .collect();
    names.extend(s.warnings().names());
    if names.is_empty() {
        String::new()
    } else {
        format!(" ({})", names.join(", "))
    }
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
            bail!("{action:?} is handled by each driver")
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
    fn status_words_are_described_in_the_devices_words() {
        assert_eq!(describe_status(Status(0)), "");
        let s = Status(Status::NO_TEMPERATURE_LIMITS | Status::TEMPERATURE_OUTSIDE_LIMITS);
        assert_eq!(
            describe_status(s),
            " (error: no temperature limits received, temperature outside the user's limits)"
        );
    }

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
