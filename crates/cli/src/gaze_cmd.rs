//! `dioptra gaze --device SPEC info|stream`: run an eye-tracker driver, on hardware or
//! in-process against a simulated tracker, and print its samples with the processor's
//! reading of them (phase, fused vergence). `dioptra gaze inspect --descriptor FILE |
//! --device SPEC`: what the usage page 0x12 driver finds in a report descriptor, and whether
//! it can drive the device (exit 0) or what it lacks (exit 1).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{anyhow, bail, Context as _, Result};
use clap::Subcommand;
use dioptra_core::{Clock, DeviceError, GazeSample, GazeSource, SystemClock};
use dioptra_protocol::{BinocularSample, EyeSample};
use dioptra_rig::config::Port;
use dioptra_rig::devices::open::{self, Context, GazeSetup, Transport};
use dioptra_rig::devices::simulators::SimSpec;
use dioptra_sched::processing::{Angles, GazeProcessor, ProcessorConfig};
use dioptra_sim::gaze::csv;
use dioptra_sim::gaze::{GazeGenerator, GeneratorConfig, Scene, SCENARIOS};
use dioptra_transport::HidLink;

use crate::common::device_spec::{self, Target};

/// What `--device` takes, for messages.
const USAGE: &str = "sim:SCENARIO, sim-hid:SCENARIO, hid:VID:PID or pupil:HOST:PORT";

#[derive(clap::Args, Debug)]
pub struct Args {
    /// sim:SCENARIO or sim:TRACE.csv (simulated dioptra tracker, in-process),
    /// sim-hid:SCENARIO (simulated usage page 0x12 tracker), or the rig config's driver and
    /// port: hid:VID:PID or hid:/dev/hidrawN, dioptra-tracker:VID:PID (or its hidraw path),
    /// pupil:HOST:PORT (Pupil Capture's Pupil Remote, e.g. pupil:127.0.0.1:50020).
    /// Scenarios: saccades, fixation, pursuit, vergence, blinks.
    #[arg(long)]
    device: Option<String>,
    /// Sample rate of a simulated tracker, Hz.
    #[arg(long, default_value_t = 500.0)]
    rate: f64,
    /// Tracker noise of a simulated tracker, degrees per eye and axis.
    #[arg(long, default_value_t = 0.03)]
    noise_deg: f64,
    /// Seed of a simulated tracker.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    #[command(subcommand)]
    action: Action,
}

#[derive(Subcommand, Debug)]
enum Action {
    /// What the tracker reports about itself.
    Info,
    /// The report ids and fields the usage page 0x12 driver finds in a report descriptor
    /// (usage, offset, size, unit, scale) and whether it can drive the device. Exit 1, with
    /// what is missing, when it cannot. Reads no reports, so the device can stay in use.
    Inspect {
        /// Raw descriptor bytes, e.g. a copy of
        /// /sys/class/hidraw/hidrawN/device/report_descriptor.
        #[arg(long, conflicts_with = "device")]
        descriptor: Option<PathBuf>,
        /// hid:/dev/hidrawN (read from sysfs), hid:VID:PID, or sim-hid (the simulator's).
        #[arg(long)]
        device: Option<String>,
    },
    /// Print samples as they arrive (real time), one line each, after a header line.
    Stream {
        /// Stop after this many samples.
        #[arg(long)]
        count: Option<u64>,
        /// Stop after this many seconds.
        #[arg(long)]
        seconds: Option<f64>,
        /// Print every Nth sample (all are processed).
        #[arg(long, default_value_t = 1)]
        every: u64,
        /// Also record every sample to this CSV trace (replay it with `--device sim:FILE.csv`).
        #[arg(long)]
        csv: Option<PathBuf>,
    },
}

pub fn run(args: Args) -> Result<()> {
    crate::common::block_on(run_async(args))
}

/// The simulators' setup for `sim[:WHAT]`: WHAT a scenario or a recorded CSV trace (the
/// fixation scenario without one), at the command's rate, noise and seed.
fn sim_spec(what: Option<&str>, args: &Args) -> Result<SimSpec> {
    let mut spec = SimSpec::standalone();
    spec.gaze = GeneratorConfig {
        rate_hz: args.rate,
        noise_deg: args.noise_deg,
        seed: args.seed,
        ..GeneratorConfig::default()
    };
    match what {
        Some(what) if what.ends_with(".csv") => {
            let text =
                std::fs::read_to_string(what).with_context(|| format!("cannot read {what}"))?;
            spec.gaze_trace = Some(Arc::new(csv::parse(&text)?));
        }
        Some(what) => {
            let Some(scene) = Scene::named(what) else {
                bail!("unknown scenario {what:?}; known: {}", SCENARIOS.join(", "));
            };
            spec.gaze_scene = scene;
        }
        None => {}
    }
    if spec.gaze_trace.is_none() {
        // Checked here, so that a bad rate or noise is a usage error, not a lost link.
        GazeGenerator::new(spec.gaze_scene.clone(), spec.gaze).map_err(anyhow::Error::msg)?;
    }
    Ok(spec)
}

async fn run_async(args: Args) -> Result<()> {
    if let Action::Inspect { descriptor, device } = &args.action {
        let (bytes, what) = match (descriptor, device.as_ref().or(args.device.as_ref())) {
            (Some(path), _) => (
                std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?,
                path.display().to_string(),
            ),
            (None, Some(spec)) => (descriptor_of(spec, &args).await?, spec.clone()),
            (None, None) => bail!("inspect needs --descriptor FILE or --device hid:/dev/hidrawN"),
        };
        return inspect(&bytes, &what);
    }
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let device = args
        .device
        .as_deref()
        .with_context(|| format!("--device SPEC is required ({USAGE})"))?;
    let (row, target) = device_spec::parse(device, &open::GAZE, "device kind", USAGE)?;
    let setup = GazeSetup {
        rate_hz: matches!(target, Target::Sim(_)).then_some(args.rate as f32),
        ..GazeSetup::default()
    };
    let ctx = Context::new(clock, setup);
    let (link, _sim, place, noise_deg) = match &target {
        Target::Sim(what) => {
            let spec = sim_spec(what.as_deref(), &args)?;
            let (link, sim) = open::simulated(row, &spec, &ctx)?;
            let place = format!("simulated: {}", what.as_deref().unwrap_or("fixation"));
            (link, Some(sim), place, args.noise_deg)
        }
        Target::Port(port) => {
            let link = device_spec::link(row, port).await?;
            (link, None, port.to_string(), HARDWARE_NOISE_DEG)
        }
    };
    let mut g = (row.connect)(link, ctx).await.map_err(|e| {
        anyhow!(
            "cannot start a session with the {} ({place}): {e}",
            row.what
        )
    })?;
    let mut facts = vec![("driver", format!("{} ({}, {place})", row.name, row.what))];
    facts.extend(g.about().await?);
    act(g, &args.action, facts, noise_deg).await
}

/// Angular noise assumed for real trackers (a conservative HMD tracker figure), degrees.
const HARDWARE_NOISE_DEG: f64 = 0.5;

/// `noise_deg`: the tracker's angular noise, for the vergence uncertainty.
async fn act<G: GazeSource>(
    mut g: G,
    action: &Action,
    mut facts: Vec<(&'static str, String)>,
    noise_deg: f64,
) -> Result<()> {
    match *action {
        Action::Info => {
            facts.push(("rate", format!("{} Hz", g.rate_hz())));
            device_spec::print_facts(&facts);
            let s = g.next_sample().await?;
            println!("first sample: {}", line(&s, None));
            Ok(())
        }
        Action::Inspect { .. } => bail!("inspect reads a descriptor, not samples"),
        Action::Stream {
            count,
            seconds,
            every,
            ref csv,
        } => {
            let opts = StreamOpts {
                count,
                seconds,
                every: every.max(1),
                csv: csv.clone(),
            };
            stream(&mut g, noise_deg, opts).await
        }
    }
}

/// The report descriptor of `spec`: sysfs for a hidraw node (no permission on the node
/// needed), the device itself for VID:PID, the simulator's for `sim-hid` (any HID driver's
/// simulator).
async fn descriptor_of(spec: &str, args: &Args) -> Result<Vec<u8>> {
    let (row, target) = device_spec::parse(spec, &open::GAZE, "device kind", USAGE)?;
    if row.transport != Transport::Hid {
        bail!(
            "inspect reads hid:/dev/hidrawN, hid:VID:PID or sim-hid; the {} is not a HID device",
            row.what
        );
    }
    let mut simulator = None;
    let mut link = match &target {
        Target::Port(Port::Path(path)) => {
            let node = path
                .file_name()
                .and_then(|n| n.to_str())
                .filter(|n| n.starts_with("hidraw"))
                .with_context(|| format!("{:?} is not a /dev/hidrawN path", path.display()))?;
            let sys = format!("/sys/class/hidraw/{node}/device/report_descriptor");
            return std::fs::read(&sys).with_context(|| format!("cannot read {sys}"));
        }
        Target::Port(port) => device_spec::link(row, port).await?.hid(row.what)?,
        Target::Sim(what) => {
            let ctx = Context::new(Arc::new(SystemClock::new()), GazeSetup::default());
            let (link, sim) = open::simulated(row, &sim_spec(what.as_deref(), args)?, &ctx)?;
            simulator = Some(sim);
            link.hid(row.what)?
        }
    };
    let descriptor = link.report_descriptor().await?;
    drop(simulator);
    Ok(descriptor)
}

/// Prints what the page 0x12 driver finds in `bytes`; an error (exit 1) names what it lacks.
fn inspect(bytes: &[u8], what: &str) -> Result<()> {
    use dioptra_gaze::eye_hid::protocol::{usage_name, TrackerLayout};
    use dioptra_gaze::hid_descriptor::{self, ReportKind};
    println!("descriptor {what}: {} bytes", bytes.len());
    let d = hid_descriptor::parse(bytes).context("the report descriptor does not parse")?;
    let pages: Vec<String> = d.applications.iter().map(|u| u.to_string()).collect();
    println!("application collections: {}", pages.join(", "));
    println!("reports (id, kind, bytes with the id byte):");
    for &(kind, id, bits) in &d.report_bits {
        let kind = match kind {
            ReportKind::Input => "input",
            ReportKind::Output => "output",
            ReportKind::Feature => "feature",
        };
        println!("  {id:#04x} {kind:7} {}", 1 + bits.div_ceil(8));
    }
    match TrackerLayout::locate_all(&d) {
        Ok(layout) => {
            println!(
                "fields the driver reads (offset and size in bits, after the report id):\n  {:<28} {:<11} {:>6} {:>6} {:>5} {:>7} {:>4}  {:<16} flags",
                "name", "usage", "report", "offset", "bits", "unit", "exp", "scale"
            );
            for l in layout.fields() {
                let f = &l.field;
                let usage = format!("{:#06x}", f.usage.id());
                println!(
                    "  {:<28} {:<11} {:>#6x} {:>6} {:>5} {:>#7x} {:>4}  {:<16} {}",
                    l.name,
                    usage,
                    f.report_id,
                    f.bit_offset,
                    f.total_bits(),
                    f.unit,
                    f.unit_exponent,
                    format!("{} {}", l.scale, l.page_unit).trim_end(),
                    if f.constant { "constant" } else { "data" }
                );
            }
            for note in &layout.notes {
                println!("note: {note}");
            }
            let t = &layout.tracking;
            let optional = [
                ("Left Eye Position", t.left_eye.is_some()),
                ("Right Eye Position", t.right_eye.is_some()),
                ("Head Position", t.head_position.is_some()),
                ("Head Direction", t.head_direction.is_some()),
                ("Configuration report", layout.configuration.is_some()),
            ];
            let absent: Vec<&str> = optional.iter().filter(|o| !o.1).map(|o| o.0).collect();
            if !absent.is_empty() {
                println!("optional, not used: {}", absent.join(", "));
            }
            println!("dioptra can drive this device (driver hid, usage page 0x12)");
            Ok(())
        }
        Err(errors) => {
            println!("dioptra cannot drive this device; it lacks:");
            for e in &errors {
                println!("  - {e}");
            }
            let names: Vec<&str> = d
                .fields
                .iter()
                .map(|f| usage_name(f.usage))
                .filter(|n| !n.is_empty())
                .collect();
            if !names.is_empty() {
                println!("page 0x12 usages it has: {}", names.join(", "));
            }
            bail!(
                "{what} cannot be driven as a usage page 0x12 eye tracker: {}",
                errors[0]
            )
        }
    }
}

fn eye(e: &dioptra_core::EyeRay) -> String {
    let d = e.direction.map(f64::from);
    let a = Angles::from_direction(d);
    if e.valid {
        format!("1 {:7.2} {:7.2}", a.yaw_deg, a.pitch_deg)
    } else {
        format!("0 {:>7} {:>7}", "-", "-")
    }
}

pub const HEADER: &str =
    "host_time_s device_time_us host_receive_s  L_ok  L_yaw   L_pitch R_ok  R_yaw   R_pitch phase    vergence_D";

fn line(s: &GazeSample, p: Option<&GazeProcessor>) -> String {
    let (phase, verg) = match p {
        Some(p) => (
            p.state().phase.as_str(),
            p.state().vergence.map_or("-".into(), |v| {
                format!("{:.2}±{:.3}", v.diopters, v.sigma_d)
            }),
        ),
        None => ("-", "-".into()),
    };
    format!(
        "{:11.6} {:14} {:14.6}  {}  {}  {:8} {}",
        s.host_time.as_secs_f64(),
        s.device_time.as_micros(),
        s.host_receive_time.as_secs_f64(),
        eye(&s.left),
        eye(&s.right),
        phase,
        verg
    )
}

struct StreamOpts {
    count: Option<u64>,
    seconds: Option<f64>,
    every: u64,
    csv: Option<PathBuf>,
}

/// A driver's sample as the trace records it (the tracker's side of the wire).
fn to_recorded(s: &GazeSample) -> BinocularSample {
    let eye = |e: &dioptra_core::EyeRay| EyeSample {
        origin_mm: e.origin_mm,
        direction: e.direction,
        pupil_mm: e.pupil_mm,
        valid: e.valid,
    };
    BinocularSample {
        device_time_us: s.device_time.as_micros(),
        left: eye(&s.left),
        right: eye(&s.right),
    }
}

async fn stream<G: GazeSource>(g: &mut G, noise_deg: f64, opts: StreamOpts) -> Result<()> {
    let StreamOpts {
        count,
        seconds,
        every,
        csv: csv_path,
    } = opts;
    let mut recorded = Vec::new();
    let mut p = GazeProcessor::new(ProcessorConfig {
        tracker_noise_deg: noise_deg,
        ..ProcessorConfig::default()
    });
    let until = seconds
        .and_then(|s| Duration::try_from_secs_f64(s).ok())
        .and_then(|d| tokio::time::Instant::now().checked_add(d));
    if seconds.is_some() && until.is_none() {
        bail!("--seconds must be a non-negative, finite number of seconds");
    }
    println!("{HEADER}");
    let (mut n, mut bad) = (0u64, 0u64);
    while count.is_none_or(|c| n < c) && until.is_none_or(|u| tokio::time::Instant::now() < u) {
        let s = match g.next_sample().await {
            Ok(s) => s,
            // One bad report is worth a line, not the end of the stream.
            Err(e @ DeviceError::Protocol(_)) => {
                bad += 1;
                eprintln!("skipped: {e}");
                continue;
            }
            Err(e) => {
                write_trace(csv_path.as_deref(), &recorded)?;
                return Err(e.into());
            }
        };
        if csv_path.is_some() {
            recorded.push(to_recorded(&s));
        }
        p.push(&s);
        if n % every == 0 {
            println!("{}", line(&s, Some(&p)));
        }
        n += 1;
    }
    let st = p.state();
    eprintln!(
        "{n} samples, {bad} malformed; {} saccades, {} blinks",
        st.saccades, st.blinks
    );
    write_trace(csv_path.as_deref(), &recorded)
}

fn write_trace(path: Option<&std::path::Path>, samples: &[BinocularSample]) -> Result<()> {
    let Some(path) = path else { return Ok(()) };
    std::fs::write(path, csv::write(samples))
        .with_context(|| format!("cannot write the trace to {}", path.display()))?;
    eprintln!("recorded {} samples to {}", samples.len(), path.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(device: &str, action: Action) -> Args {
        Args {
            device: Some(device.into()),
            rate: 1000.0,
            noise_deg: 0.03,
            seed: 1,
            action,
        }
    }

    fn stream_n(n: u64) -> Action {
        Action::Stream {
            count: Some(n),
            seconds: None,
            every: 1,
            csv: None,
        }
    }

    #[test]
    fn streams_and_describes_simulated_trackers() {
        run(args("sim:saccades", stream_n(3))).unwrap();
        run(args("sim-hid:pursuit", stream_n(3))).unwrap();
        run(args("sim:vergence", Action::Info)).unwrap();
        run(args("sim-hid:fixation", Action::Info)).unwrap();
    }

    /// `pupil:HOST:PORT` against a simulated Capture served by another runtime (as another
    /// process would); a port with no Capture is an error, not a hang.
    #[test]
    fn streams_from_pupil_capture_by_address() {
        use dioptra_sim::gaze::pupil_capture::{PupilCaptureConfig, PupilCaptureSim};
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let gen = GazeGenerator::new(Scene::named("saccades").unwrap(), Default::default());
        let sim = rt
            .block_on(async {
                PupilCaptureSim::spawn(PupilCaptureConfig::default(), Box::new(gen.unwrap()))
            })
            .unwrap();
        let addr = sim.remote_addr();
        run(args(&format!("pupil:{addr}"), stream_n(3))).unwrap();
        run(args(&format!("pupil:{addr}"), Action::Info)).unwrap();
        drop(sim);
        let free = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = free.local_addr().unwrap().port();
        drop(free);
        let e = run(args(&format!("pupil:127.0.0.1:{port}"), stream_n(1))).unwrap_err();
        assert!(e.to_string().contains("Pupil Remote"), "{e:#}");
    }

    #[test]
    fn a_recorded_trace_replays_the_same_samples() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("trace.csv");
        let record = Action::Stream {
            count: Some(20),
            seconds: None,
            every: 10,
            csv: Some(path.clone()),
        };
        run(args("sim:pursuit", record)).unwrap();
        let first = csv::parse(&std::fs::read_to_string(&path).unwrap()).unwrap();
        assert_eq!(first.len(), 20);
        // Replay it through the simulated tracker and record again: the same samples.
        let again = dir.path().join("again.csv");
        let replay = Action::Stream {
            count: Some(20),
            seconds: None,
            every: 1,
            csv: Some(again.clone()),
        };
        run(args(
            path.to_str().map(|p| format!("sim:{p}")).unwrap().as_str(),
            replay,
        ))
        .unwrap();
        let second = csv::parse(&std::fs::read_to_string(&again).unwrap()).unwrap();
        assert_eq!(first, second);
    }

    #[test]
    fn bad_specs_say_what_is_accepted() {
        let e = run(args("sim:nope", Action::Info)).unwrap_err().to_string();
        assert!(e.contains("saccades, fixation"), "{e}");
        let e = run(args("nothing", Action::Info)).unwrap_err().to_string();
        assert!(e.contains("sim:SCENARIO"), "{e}");
        let e = run(args("usb:1:2", Action::Info)).unwrap_err().to_string();
        assert!(e.contains("unknown device kind"), "{e}");
        let port = |spec| device_spec::parse(spec, &open::GAZE, "device kind", USAGE).unwrap();
        // The dioptra tracker by its VID:PID is the dioptra-tracker driver's, whatever its name.
        assert_eq!(port("hid:1209:d109").0.name, "dioptra-tracker");
        assert_eq!(
            port("hid:1209:d109").1,
            Target::Port(Port::VidPid(0x1209, 0xd109))
        );
        assert_eq!(
            port("hid:/dev/hidraw0").1,
            Target::Port(Port::Path("/dev/hidraw0".into()))
        );
        let e = run(args(
            "sim:fixation",
            Action::Stream {
                count: None,
                seconds: Some(-1.0),
                every: 1,
                csv: None,
            },
        ))
        .unwrap_err();
        assert!(e.to_string().contains("--seconds"));
    }

    #[test]
    fn lines_carry_validity_and_all_three_times() {
        let mut s = GazeSample::default();
        s.left.valid = true;
        s.left.direction = [0.0, 0.0, 1.0];
        s.device_time = dioptra_core::Timestamp::from_micros(1_234_567);
        let l = line(&s, None);
        assert!(l.contains("1234567"), "{l}");
        assert!(l.contains("1    0.00    0.00  0       -       -"), "{l}");
        assert_eq!(HEADER.split_whitespace().count(), 11);
    }
}
