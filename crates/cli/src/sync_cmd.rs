//! `dioptra sync --device DRIVER:PATH status|program|start|stop|events`: talk to multifocal
//! sync hardware (the dioptra sync board, or a TI DLPC350 / LightCrafter 4500).

use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context as _, Result};
use clap::Subcommand;
use dioptra_core::{
    Clock, Diopters, PlaneSchedule, PlaneSequencer, SequencerEvent, SequencerFault, SystemClock,
};
use dioptra_rig::devices::open::{self, Context, SyncSetup};
use dioptra_rig::devices::simulators::SimSpec;
use dioptra_rig::devices::BoxSequencer;
use dioptra_sync::dlpc350::Dlpc350Config;

use crate::common::device_spec::{self, Target};

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
    crate::common::block_on(run_async(args))
}

async fn run_async(args: Args) -> Result<()> {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    if !(args.video_hz.is_finite() && args.video_hz >= 1.0) {
        bail!("--video-hz must be at least 1");
    }
    let usage = "DRIVER:PORT, e.g. sync:/dev/ttyACM0, dlpc350:hid or dlpc350:sim";
    let (row, target) = device_spec::parse(&args.device, &open::SYNC, "sync driver", usage)?;
    let falling = match &args.action {
        Action::Program(s) | Action::Events { schedule: s, .. } => s.falling,
        _ => false,
    };
    let setup = SyncSetup {
        trigger_rising: !falling,
        dlpc350: Dlpc350Config {
            vsync_hz: args.video_hz,
            ..Default::default()
        },
        light: None,
    };
    let ctx = Context::new(clock.clone(), setup);
    let (link, sim) = match &target {
        Target::Sim(_) => {
            let mut spec = SimSpec::standalone();
            spec.dlpc350.vsync_hz = args.video_hz;
            let (link, sim) = open::simulated(row, &spec, &ctx)?;
            (link, Some(sim))
        }
        Target::Port(port) => {
            let link = device_spec::link(row, port)
                .await
                .with_context(|| format!("cannot open the {} at {port}", row.what))?;
            (link, None)
        }
    };
    let mut s = (row.connect)(link, ctx).await?;
    // What a simulated projector does, beside what the driver predicts.
    let projector = sim.as_ref().and_then(|s| s.projector.clone());
    let show_log = projector.is_some() && matches!(args.action, Action::Program(_));
    let printer = projector.as_ref().map(|p| {
        let mut patterns = p.subscribe();
        tokio::spawn(async move {
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
        })
    });
    let what = row.what;
    let result = match args.action {
        Action::Status => s
            .about()
            .await
            .map(|f| device_spec::print_facts(&f))
            .map_err(Into::into),
        action => {
            sequencer_action(&mut s, action, clock.as_ref(), move |s| {
                let port = match &target {
                    Target::Port(p) => Some(p.clone()),
                    Target::Sim(_) => None,
                };
                Box::pin(async move {
                    let Some(port) = port.filter(|_| s.resumes()) else {
                        bail!("the {what} was unplugged; run the command again once it is back")
                    };
                    // Unplugged: wait for the port to come back and restore the session.
                    loop {
                        tokio::time::sleep(Duration::from_millis(500)).await;
                        if let Ok(link) = device_spec::link(row, &port).await {
                            match s.resume(link).await {
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
    };
    if let Some(p) = printer {
        p.abort();
    }
    result?;
    if let (true, Some(p)) = (show_log, &projector) {
        println!("commands the simulated DLPC350 received:");
        for l in p.log() {
            println!("  {l}");
        }
    }
    Ok(())
}

type Reconnect<'a> = std::pin::Pin<Box<dyn std::future::Future<Output = Result<()>> + 'a>>;

/// Program, start, stop or print events on any sequencer. `reconnect` restores the device
/// after an unplug while printing events.
async fn sequencer_action(
    s: &mut BoxSequencer,
    action: Action,
    clock: &dyn Clock,
    reconnect: impl for<'a> Fn(&'a mut BoxSequencer) -> Reconnect<'a>,
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
