//! `dioptra sim ...`: simulators. `sim scene` writes a procedural scene's ground truth; the
//! device simulators add their subcommands to [`SimCommand`].

use crate::common::progress::bar;
use crate::common::slice_name;
use anyhow::{bail, Context, Result};
use clap::{Args as ClapArgs, Subcommand};
use dioptra_core::{EyeModel, Millimeters};
use dioptra_render::io::{write_color, write_depth};
use dioptra_render::multifocal::linspace;
use dioptra_sim::scene::{
    light_field_positions, render_light_field_view, render_pinhole, render_thin_lens, Camera,
    Scene, SceneOptions, Split,
};
use std::fmt::Write as _;
use std::path::PathBuf;

#[derive(ClapArgs, Debug)]
pub struct Args {
    #[command(subcommand)]
    pub command: SimCommand,
}

#[derive(Subcommand, Debug)]
pub enum SimCommand {
    /// Render a procedural scene: colour, depth, a ground-truth focal stack and a light field.
    Scene(SceneArgs),
    /// Serve a simulated Optotune Lens Driver 4 (`--pty`: on a pseudo-terminal).
    Optotune(OptotuneSimArgs),
    /// Serve a simulated dioptra lens controller (`--pty`: on a pseudo-terminal).
    Lens(LensSimArgs),
    /// Serve a simulated dioptra sync board with a display and a lens (`--pty`).
    Sync(SyncSimArgs),
    /// Serve a simulated Pupil Capture (Pupil Remote and its IPC backbone) on loopback TCP.
    PupilCapture(PupilCaptureArgs),
}

#[derive(ClapArgs, Debug)]
pub struct SceneArgs {
    /// Scene seed; seeds 1000000..2000000 are the test split, all others training.
    #[arg(long)]
    seed: u64,
    /// Image size, pixels: `N` for N x N, or `WIDTHxHEIGHT` (e.g. `960x1080`, one eye of a
    /// 1080p panel split side by side).
    #[arg(long, default_value = "256", value_parser = parse_image_size)]
    size: (usize, usize),
    #[arg(long)]
    out: PathBuf,
    /// Ground-truth focal-stack slices over --range.
    #[arg(long, default_value_t = 40)]
    slices: usize,
    /// Focal-stack range, diopters (lo,hi).
    #[arg(long, default_value = "0.1,4.0")]
    range: String,
    /// Rays per pixel of the thin-lens ground truth (256 keeps its own error near 50 dB).
    #[arg(long, default_value_t = 256)]
    samples: u32,
    /// Light-field grid (views per side; 0 for none).
    #[arg(long, default_value_t = 9)]
    lf_grid: usize,
    /// Side of the square the light-field views span, metres.
    #[arg(long, default_value_t = 0.01)]
    lf_span: f32,
    /// Make some surfaces semi-transparent (a failure case for RGB-D methods).
    #[arg(long)]
    semi_transparent: bool,
    /// Horizontal field of view, degrees.
    #[arg(long, default_value_t = 20.0)]
    fov_deg: f32,
    /// Pupil diameter of the ground truth, millimetres.
    #[arg(long, default_value_t = 4.0)]
    pupil_mm: f32,
}

pub fn run(args: Args) -> Result<()> {
    match args.command {
        SimCommand::Scene(a) => scene(a),
        SimCommand::Optotune(a) => optotune_sim(a),
        SimCommand::Lens(a) => lens_sim(a),
        SimCommand::Sync(a) => sync_sim(a),
        SimCommand::PupilCapture(a) => pupil_capture_sim(a),
    }
}

/// `--size`: `N` or `WIDTHxHEIGHT`, each side 1 to 8192 pixels.
fn parse_image_size(s: &str) -> Result<(usize, usize), String> {
    let side = |v: &str| -> Result<usize, String> {
        match v.trim().parse::<usize>() {
            Ok(n) if (1..=8192).contains(&n) => Ok(n),
            _ => Err(format!(
                "`{v}` is not a side of 1 to 8192 pixels (give N, or WIDTHxHEIGHT such as 960x1080)"
            )),
        }
    };
    match s.split_once(['x', 'X']) {
        Some((w, h)) => Ok((side(w)?, side(h)?)),
        None => side(s).map(|n| (n, n)),
    }
}

fn scene(a: SceneArgs) -> Result<()> {
    let (width, height) = a.size;
    let range: Vec<f32> = a
        .range
        .split(',')
        .map(|v| v.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .context("--range must be lo,hi")?;
    let [lo, hi] = range[..] else {
        bail!("--range must be two numbers, e.g. 0.1,4.0")
    };
    let eye = EyeModel {
        pupil_diameter: Millimeters(a.pupil_mm),
        fov_horizontal_deg: a.fov_deg,
        ..EyeModel::default()
    }
    .validated()?;
    let cam = Camera::new(eye, width, height);
    let opts = SceneOptions {
        semi_transparent: a.semi_transparent,
        ..SceneOptions::default()
    };
    let scene = Scene::generate_with(a.seed, &opts);
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 8)?;
    write_color(&a.out.join("color.png"), &color)?;
    write_color(&a.out.join("color.exr"), &color)?;
    write_depth(&a.out.join("depth.exr"), &depth)?;
    write_depth(&a.out.join("depth.png"), &depth)?;
    let foci = linspace(lo, hi, a.slices);
    let dir = a.out.join("focalstack");
    std::fs::create_dir_all(&dir)?;
    // Said up front: the focal stack is most of the time (minutes at 256 px and 256 rays),
    // and the bars below draw only on a terminal.
    eprintln!(
        "sim scene: {} ground-truth slices at {} rays a pixel and {} light-field views, {}x{} \
         px (fewer --samples or --slices, or --lf-grid 0, for a quicker run)",
        foci.len(),
        a.samples,
        a.lf_grid * a.lf_grid,
        width,
        height
    );
    let pb = bar(foci.len(), "ground truth")?;
    for &q in &foci {
        let img = render_thin_lens(&scene, &cam, q, a.samples)?;
        write_color(&dir.join(slice_name(q, "png")), &img)?;
        write_color(&dir.join(slice_name(q, "exr")), &img)?;
        pb.inc(1);
    }
    pb.finish();
    let mut meta = String::new();
    writeln!(
        meta,
        "seed = {}\nsplit = \"{:?}\"\nwidth = {width}\nheight = {height}\nfov_deg = {}\npupil_mm = {}",
        a.seed,
        Split::of(a.seed),
        a.fov_deg,
        a.pupil_mm
    )?;
    writeln!(
        meta,
        "focal_stack = [{}]\nsamples_per_pixel = {}",
        foci.iter()
            .map(|q| format!("{:.2}", q.0))
            .collect::<Vec<_>>()
            .join(", "),
        a.samples
    )?;
    if a.lf_grid > 0 {
        let dir = a.out.join("lightfield");
        std::fs::create_dir_all(&dir)?;
        let positions = light_field_positions(a.lf_grid, a.lf_span)?;
        let pb = bar(positions.len(), "light field")?;
        for (k, &position) in positions.iter().enumerate() {
            let v = render_light_field_view(&scene, &cam, position, 2)?;
            let (r, c) = (k / a.lf_grid, k % a.lf_grid);
            write_color(&dir.join(format!("view_{r:02}_{c:02}.png")), &v.color)?;
            write_depth(&dir.join(format!("view_{r:02}_{c:02}_depth.exr")), &v.depth)?;
            pb.inc(1);
        }
        pb.finish();
        writeln!(
            meta,
            "light_field = {{ grid = {}, span_m = {} }}",
            a.lf_grid, a.lf_span
        )?;
    }
    std::fs::write(a.out.join("scene.toml"), meta)?;
    println!(
        "wrote scene {} ({:?} split) to {}",
        a.seed,
        Split::of(a.seed),
        a.out.display()
    );
    Ok(())
}

#[derive(ClapArgs, Debug)]
pub struct OptotuneSimArgs {
    /// Serve on a new pseudo-terminal; its path is the first line of stdout.
    #[arg(long)]
    pty: bool,
    /// Time for a focal-power step to settle within 2 %, ms (EL-10-30: about 15).
    #[arg(long, default_value_t = 15)]
    settle_ms: u64,
    /// Firmware type letter the device reports (`A` uses the +5 D focal-power offset).
    #[arg(long, default_value = "A")]
    firmware_type: char,
}

#[derive(ClapArgs, Debug)]
pub struct LensSimArgs {
    /// Serve on a new pseudo-terminal; its path is the first line of stdout.
    #[arg(long)]
    pty: bool,
    /// Time for a focal-power step to settle within 2 %, ms.
    #[arg(long, default_value_t = 15)]
    settle_ms: u64,
}

fn lens_model(settle_ms: u64) -> dioptra_sim::lens_model::LensModelConfig {
    dioptra_sim::lens_model::LensModelConfig {
        settle_time: std::time::Duration::from_millis(settle_ms.max(1)),
        ..Default::default()
    }
}

fn optotune_sim(a: OptotuneSimArgs) -> Result<()> {
    use dioptra_sim::optotune::{serve, OptotuneSim, OptotuneSimConfig};
    if !a.firmware_type.is_ascii_alphabetic() {
        bail!("--firmware-type must be one ASCII letter");
    }
    let cfg = OptotuneSimConfig {
        lens: lens_model(a.settle_ms),
        firmware_type: a.firmware_type as u8,
        ..Default::default()
    };
    serve_on_pty(a.pty, "sim optotune", move |mut master, clock| async move {
        serve(&mut master, &mut OptotuneSim::new(cfg), &clock).await
    })
}

fn lens_sim(a: LensSimArgs) -> Result<()> {
    use dioptra_sim::lens_controller::{serve, LensControllerSim, LensControllerSimConfig};
    let cfg = LensControllerSimConfig {
        lens: lens_model(a.settle_ms),
        ..Default::default()
    };
    serve_on_pty(a.pty, "sim lens", move |mut master, clock| async move {
        serve(&mut master, &mut LensControllerSim::new(cfg), &clock).await
    })
}

#[derive(ClapArgs, Debug)]
pub struct SyncSimArgs {
    /// Serve on a new pseudo-terminal; its path is the first line of stdout.
    #[arg(long)]
    pty: bool,
    /// Time for the multifocal lens to settle within 2 %, ms: the rig's default
    /// (`devices.sync.sim_settle_ms`), within a 240 Hz sub-frame's 1.04 ms dark quarter. A
    /// varifocal lens such as the EL-10-30 (about 15 ms) settles late on every sub-frame.
    #[arg(long, default_value_t = dioptra_rig::config::SyncDevice::DEFAULT_SIM_SETTLE_MS)]
    settle_ms: f64,
    /// Display refresh, Hz (default: the loaded schedule's sub-frame rate).
    #[arg(long)]
    display_hz: Option<f64>,
    /// Vsync jitter, ± µs.
    #[arg(long, default_value_t = 20.0)]
    jitter_us: f64,
    /// Chance that the display drops a vsync edge.
    #[arg(long, default_value_t = 0.0)]
    missed_vsync: f64,
}

fn sync_sim(a: SyncSimArgs) -> Result<()> {
    use dioptra_sim::sync_board::{serve, SyncBoardSim, SyncBoardSimConfig};
    if !(a.settle_ms.is_finite() && a.settle_ms > 0.0) {
        bail!("--settle-ms must be positive");
    }
    if !(0.0..=1.0).contains(&a.missed_vsync) {
        bail!("--missed-vsync is a probability, 0 to 1");
    }
    let cfg = SyncBoardSimConfig {
        lens: dioptra_sim::lens_model::LensModelConfig {
            settle_time: std::time::Duration::from_secs_f64(a.settle_ms / 1000.0),
            ..Default::default()
        },
        display_hz: a.display_hz,
        jitter_us: a.jitter_us.max(0.0),
        missed_vsync_probability: a.missed_vsync,
        ..Default::default()
    };
    serve_on_pty(a.pty, "sim sync", move |mut master, clock| async move {
        serve(&mut master, &mut SyncBoardSim::new(cfg), &clock).await
    })
}

/// Opens a pty, prints its path as the first line of stdout, and serves until stopped. The
/// lens model runs on wall time: the client is another process.
fn serve_on_pty<F, Fut>(pty: bool, what: &str, serve: F) -> Result<()>
where
    F: FnOnce(dioptra_transport::pty::PtyMaster, dioptra_sim::tokio_clock::TokioClock) -> Fut,
    Fut: std::future::Future<Output = Result<(), dioptra_transport::LinkError>>,
{
    use std::io::Write as _;
    if !pty {
        bail!("`dioptra {what}` serves other processes on a pseudo-terminal: add --pty");
    }
    crate::common::block_on(async {
        let pair = dioptra_transport::pty::PtyPair::open()?;
        println!("{}", pair.slave_path.display());
        std::io::stdout().flush()?;
        eprintln!(
            "{what}: serving on {} until stopped (Ctrl-C)",
            pair.slave_path.display()
        );
        serve(pair.master, dioptra_sim::tokio_clock::TokioClock::new()).await?;
        Ok(())
    })
}

#[derive(ClapArgs, Debug)]
pub struct PupilCaptureArgs {
    /// Pupil Remote's port on 127.0.0.1 (0: any free port).
    #[arg(long, default_value_t = dioptra_gaze::pupil::ids::DEFAULT_REMOTE_PORT)]
    port: u16,
    /// Eye movements: saccades, fixation, pursuit, vergence, blinks.
    #[arg(long, default_value = "saccades")]
    scenario: String,
    /// Gaze rate, Hz.
    #[arg(long, default_value_t = 200.0)]
    rate_hz: f64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Pupil time at start, s (Capture's clock has its own base).
    #[arg(long, default_value_t = 3000.0)]
    time_base: f64,
}

/// Serves a simulated Pupil Capture until SIGTERM or Ctrl-C; the first line of stdout gives
/// its ports.
fn pupil_capture_sim(a: PupilCaptureArgs) -> Result<()> {
    use dioptra_sim::gaze::pupil_capture::{PupilCaptureConfig, PupilCaptureSim};
    use dioptra_sim::gaze::{GazeGenerator, GeneratorConfig, Scene, SCENARIOS};
    use std::io::Write as _;
    let scene = Scene::named(&a.scenario).with_context(|| {
        format!(
            "unknown --scenario {:?}; expected one of {}",
            a.scenario,
            SCENARIOS.join(", ")
        )
    })?;
    if !(a.rate_hz.is_finite() && (1.0..=2000.0).contains(&a.rate_hz)) {
        bail!("--rate-hz must be 1 to 2000");
    }
    if !a.time_base.is_finite() {
        bail!("--time-base must be a number of seconds");
    }
    let gen = GazeGenerator::new(
        scene,
        GeneratorConfig {
            rate_hz: a.rate_hz,
            seed: a.seed,
            ..Default::default()
        },
    )
    .map_err(anyhow::Error::msg)?;
    crate::common::block_on(async move {
        let cfg = PupilCaptureConfig {
            remote_port: a.port,
            pupil_time_at_start_s: a.time_base,
            ..Default::default()
        };
        let sim = PupilCaptureSim::spawn(cfg, Box::new(gen))
            .with_context(|| format!("cannot bind Pupil Remote on 127.0.0.1:{}", a.port))?;
        println!(
            "pupil remote {} sub_port {} pub_port {}",
            sim.remote_addr(),
            sim.sub_port(),
            sim.pub_port()
        );
        std::io::stdout().flush()?;
        eprintln!(
            "sim pupil-capture: Pupil Remote on tcp://{} ({} scenario at {} Hz) until stopped (Ctrl-C)",
            sim.remote_addr(),
            a.scenario,
            a.rate_hz
        );
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = term.recv() => {}
        }
        sim.shutdown().await;
        Ok(())
    })
}
