//! `dioptra sync --device DRIVER:PATH status|program|start|stop|events`: talk to multifocal
//! sync hardware (the dioptra sync board, or a TI DLPC350 / LightCrafter 4500).

use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Subcommand;
use dioptra_core::{
    Clock, Diopters, PlaneSchedule, PlaneSequencer, SequencerEvent, SequencerFault, SystemClock,
};
use dioptra_rig::config::{Port, SyncDriver};
use dioptra_rig::devices::open;
use dioptra_sync::board::SyncBoard;
use dioptra_sync::dlpc350::{Dlpc350, Dlpc350Config};
use dioptra_sync::ids::{DLPC350_PID, TI_VID};
use dioptra_transport::{AnyByteLink, HidLink};

use crate::device_spec;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// DRIVER:PORT, the rig config's driver and port: sync:/dev/ttyACM0 (the sync board, or a
    /// `dioptra sim sync --pty` path), dlpc350:0451:6401 (the first; also dlpc350:hid) or
    /// dlpc350:/dev/hidrawN; dlpc350:sim runs an in-process simulator.
    #[arg(long)]
    device: String,
    /// DLPC350: VSYNC rate of the video the projector receives, Hz.
    #[arg(long, default_value_t = 60.0)]
    video_hz: f64,
    #[command(subcommand)]
    action: Action,
}

#[derive(clap::Args, Debug, Clone)]
struct ScheduleArgs {
    /// Plane powers in display order, diopters.
    #[arg(long, default_value = "0.2,0.8,1.4,2.0", allow_hyphen_values = true)]
    planes: String,
    /// Sub-frame rate, Hz: one plane per sub-frame.
    #[arg(long, default_value_t = 240.0)]
    rate: f64,
    /// Dark time the lens gets to settle at each sub-frame's start, µs.
    #[arg(long, default_value_t = 1000)]
    settle_us: u64,
    /// Sync board: frames start on the falling vsync edge.
    #[arg(long)]
    falling: bool,
}

#[derive(Subcommand, Debug)]
enum Action {
    /// Identity and state.
    Status,
    /// Load a plane schedule, left stopped (dlpc350:sim also prints the commands it saw).
    Program(ScheduleArgs),
    /// Start the loaded schedule.
    Start,
    /// Stop the schedule.
    Stop,
    /// Program and start a schedule, then print sub-frame events and faults.
    Events {
        #[command(flatten)]
        schedule: ScheduleArgs,
        /// Stop after this many events (0: until interrupted).
        #[arg(long, default_value_t = 0)]
        count: u64,
    },
}

impl ScheduleArgs {
    fn schedule(&self) -> Result<PlaneSchedule> {
        let planes = self
            .planes
            .split(',')
            .map(|p| p.trim().parse::<f32>().map(Diopters))
            .collect::<Result<Vec<_>, _>>()
            .context("--planes must be diopters separated by commas, e.g. 0.2,0.8,1.4,2.0")?;
        if !(self.rate.is_finite() && self.rate > 0.0) {
            bail!("--rate must be a positive number of sub-frames per second");
        }
        let period = Duration::from_secs_f64(1.0 / self.rate);
        Ok(PlaneSchedule::new(
            planes,
            period,
            Duration::from_micros(self.settle_us),
        )?)
    }
}

pub fn run(args: Args) -> Result<()> {
    crate::block_on(run_async(args))
}

async fn run_async(args: Args) -> Result<()> {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let dlpc350 = || -> Result<Dlpc350Config> {
        if !(args.video_hz.is_finite() && args.video_hz >= 1.0) {
            bail!("--video-hz must be at least 1");
        }
        Ok(Dlpc350Config {
            vsync_hz: args.video_hz,
            ..Default::default()
        })
    };
    // The in-process simulator, and the first DLPC350 by its VID:PID.
    let spec = match args.device.as_str() {
        "dlpc350:sim" => {
            let cfg = dlpc350()?;
            let (link, sim) = dioptra_sim::dlpc350::new(dioptra_sim::dlpc350::Dlpc350SimConfig {
                vsync_hz: args.video_hz,
                ..Default::default()
            });
            let mut d = Dlpc350::new(link, clock.clone(), cfg);
            let show_log = matches!(args.action, Action::Program(_));
            // What the simulated projector does, beside what the driver predicts.
            let mut patterns = sim.subscribe();
            let printer = tokio::spawn(async move {
                use tokio::sync::broadcast::error::RecvError;
                loop {
                    match patterns.recv().await {
                        Ok(p) => println!(
                            "    projector: pattern {} (LUT {}, {}-bit, {} us){}{}",
                            p.pattern,
                            p.lut_index,
                            p.bit_depth,
                            p.exposure_us,
                            if p.trig_out1 { "  TRIG_OUT_1" } else { "" },
                            if p.trig_out2 {
                                "  TRIG_OUT_2 (sweep start)"
                            } else {
                                ""
                            },
                        ),
                        Err(RecvError::Lagged(_)) => continue,
                        Err(RecvError::Closed) => break,
                    }
                }
            });
            let result = dlpc350_action(&mut d, args.action, clock.as_ref()).await;
            printer.abort();
            result?;
            if show_log {
                println!("commands the simulated DLPC350 received:");
                for l in sim.log() {
                    println!("  {l}");
                }
            }
            return Ok(());
        }
        "dlpc350:hid" => format!("dlpc350:{TI_VID:04x}:{DLPC350_PID:04x}"),
        other => other.to_string(),
    };
    let (row, port) = device_spec::parse(&spec, &open::SYNC, "sync driver")?;
    match row.driver {
        SyncDriver::Sync => {
            let falling = match &args.action {
                Action::Program(s) | Action::Events { schedule: s, .. } => s.falling,
                _ => false,
            };
            let mut board = SyncBoard::connect(open_board(row, &port).await?, clock.clone())
                .await?
                .with_trigger_rising(!falling);
            if let Action::Status = args.action {
                let s = board.status();
                if let Some(info) = s.info {
                    let v = info.firmware_version;
                    println!(
                        "dioptra sync board, serial {}, firmware {}.{}.{}, protocol v{}",
                        info.serial, v.major, v.minor, v.patch, info.protocol_version
                    );
                }
                let synced = board.device_to_host(0).is_some();
                println!(
                    "clocks {}; schedule loaded by this session: {}",
                    if synced {
                        "synchronised"
                    } else {
                        "not synchronised"
                    },
                    s.schedule.is_some()
                );
                return Ok(());
            }
            sequencer_action(&mut board, args.action, clock.as_ref(), move |b| {
                let port = port.clone();
                Box::pin(async move {
                    // Unplugged: wait for the port to come back and restore the session.
                    loop {
                        tokio::time::sleep(Duration::from_millis(500)).await;
                        if let Ok(link) = open_board(row, &port).await {
                            match b.reconnect(link).await {
                                Ok(()) => return Ok(()),
                                Err(e) if e.needs_reconnect() => continue,
                                Err(e) => return Err(e.into()),
                            }
                        }
                    }
                })
            })
            .await
        }
        SyncDriver::Dlpc350 => {
            let cfg = dlpc350()?;
            let link = device_spec::link(row, &port).await?.hid(row.what)?;
            dlpc350_action(
                &mut Dlpc350::new(link, clock.clone(), cfg),
                args.action,
                clock.as_ref(),
            )
            .await
        }
    }
}

/// The sync board's serial link, through the drivers' table.
async fn open_board(
    row: &'static open::Row<SyncDriver, dioptra_rig::devices::BoxSequencer>,
    port: &Port,
) -> Result<AnyByteLink> {
    let link = device_spec::link(row, port)
        .await
        .and_then(|l| l.byte(row.what));
    link.with_context(|| format!("cannot open the sync board at {port}"))
}

async fn dlpc350_action<H: HidLink>(
    d: &mut Dlpc350<H>,
    action: Action,
    clock: &dyn Clock,
) -> Result<()> {
    if let Action::Status = action {
        let v = d.version().await?;
        let s = d.status().await?;
        println!(
            "DLPC350 application {} API {} software config {} sequence config {}",
            v.application, v.api, v.software_config, v.sequence_config
        );
        println!(
            "hardware init {}, sequencer {}, DMD {}{}",
            if s.hardware.init_ok() { "ok" } else { "FAILED" },
            if s.main.sequencer_running() {
                "running"
            } else {
                "stopped"
            },
            if s.main.dmd_parked() {
                "parked"
            } else {
                "active"
            },
            if s.hardware.sequence_abort() || s.hardware.sequence_error() {
                ", sequence error/abort flagged"
            } else {
                ""
            }
        );
        return Ok(());
    }
    sequencer_action(d, action, clock, |_| {
        Box::pin(async {
            bail!("the DLPC350 was unplugged; run the command again once it is back")
        })
    })
    .await
}

type Reconnect<'a> = std::pin::Pin<Box<dyn std::future::Future<Output = Result<()>> + 'a>>;

/// Program, start, stop or print events on any sequencer. `reconnect` restores the device
/// after an unplug while printing events.
async fn sequencer_action<S: PlaneSequencer>(
    s: &mut S,
    action: Action,
    clock: &dyn Clock,
    reconnect: impl for<'a> Fn(&'a mut S) -> Reconnect<'a>,
) -> Result<()> {
    match action {
        Action::Status => Ok(()),
        Action::Program(a) => {
            let schedule = a.schedule()?;
            s.program(&schedule).await?;
            println!(
                "programmed {} planes at {:.1} Hz sub-frames ({} us settle)",
                schedule.planes().len(),
                a.rate,
                a.settle_us
            );
            Ok(())
        }
        Action::Start => Ok(s.start().await?),
        Action::Stop => Ok(s.stop().await?),
        Action::Events { schedule, count } => {
            s.program(&schedule.schedule()?).await?;
            s.start().await?;
            let mut shown = 0u64;
            // Ctrl-C stops the sequence before exiting, so the lens is not left stepping.
            let ctrl_c = tokio::signal::ctrl_c();
            tokio::pin!(ctrl_c);
            while count == 0 || shown < count {
                let next = tokio::select! {
                    ev = s.next_event() => ev,
                    _ = &mut ctrl_c => {
                        eprintln!("interrupted: stopping the sequence");
                        break;
                    }
                };
                match next {
                    Ok(ev) => print_event(&ev, clock),
                    Err(e) if e.needs_reconnect() => {
                        eprintln!("device lost ({e}); waiting for it to come back");
                        reconnect(s).await?;
                        eprintln!("reconnected; schedule restored");
                        continue;
                    }
                    Err(e) => return Err(e.into()),
                }
                shown += 1;
            }
            s.stop().await?;
            Ok(())
        }
    }
}

fn print_event(ev: &SequencerEvent, clock: &dyn Clock) {
    let now = clock.now();
    match ev {
        SequencerEvent::SubframeStart {
            frame,
            plane_index,
            device_time,
            host_time,
            lens_power,
        } => {
            let lens = lens_power.map_or("-".to_string(), |p| format!("{:.3} D", p.0));
            println!(
                "frame {frame:>6} plane {plane_index:>2}  device {:>12.6} s  host {:>10.6} s  (read +{:>5} us)  lens {lens}",
                device_time.as_secs_f64(),
                host_time.as_secs_f64(),
                now.saturating_since(*host_time).as_micros()
            );
        }
        SequencerEvent::Fault {
            fault,
            frame,
            plane_index,
            host_time,
        } => {
            let what = match fault {
                SequencerFault::MissedVsync => "missed vsync".to_string(),
                SequencerFault::LateSettle => "late settle".to_string(),
                SequencerFault::Other(code) => format!("fault {code:#06x}"),
            };
            println!(
                "frame {frame:>6} plane {plane_index:>2}  FAULT {what}  host {:>10.6} s",
                host_time.as_secs_f64()
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(planes: &str, rate: f64, settle_us: u64) -> ScheduleArgs {
        ScheduleArgs {
            planes: planes.into(),
            rate,
            settle_us,
            falling: false,
        }
    }

    #[test]
    fn schedule_arguments() {
        let s = args("0.2, 0.8,1.4,2.0", 240.0, 1000).schedule().unwrap();
        assert_eq!(s.planes().len(), 4);
        assert_eq!(s.subframe_period().as_micros(), 4166);
        assert!(args("0.2,x", 240.0, 1000).schedule().is_err());
        assert!(args("0.2", 0.0, 0).schedule().is_err());
        assert!(args("0.2", f64::NAN, 0).schedule().is_err());
        // Settle allowance longer than the sub-frame: refused by the schedule's own rules.
        assert!(args("0.2", 240.0, 5000).schedule().is_err());
    }
}
