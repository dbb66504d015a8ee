// Without the `simulated` feature the demo and the loop suite are left out, and with them
// some helpers they share with other commands.
#![cfg_attr(not(feature = "simulated"), allow(dead_code, unused_imports))]

//! `dioptra`: one binary for the rig. Each command group lives in its own module;
//! add a variant to [`Command`] and a module beside this file. What commands share is in
//! [`common`]; a command imports that, never another command (`crates/cli/LAYERS`).

mod common;
mod demo;
mod devices;
mod display_cmd;
mod eval;
mod gaze_cmd;
mod hil;
mod lens_cmd;
mod lsl_cmd;
mod optics_cmd;
mod recording_cmd;
mod render_cmd;
mod replay;
mod serve;
mod sim_cmd;
mod sync_cmd;
mod train;
mod udev;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "dioptra",
    version,
    about = "Drive and simulate accommodation-supporting HMD rigs"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The whole loop on simulated devices and a procedural scene: summary, frames, charts.
    Demo(demo::Args),
    /// List serial, USB and HID devices, each with the dioptra driver that matches it.
    Devices(devices::Args),
    /// Print udev rules for every device dioptra has a driver for.
    Udev(udev::Args),
    /// Talk to one varifocal lens: info, get, set, sweep, temp, calibrate.
    Lens(lens_cmd::Args),
    /// An eye's optics map both ways: the lens command for a focus, the focus of a command.
    Optics(optics_cmd::Args),
    /// Talk to one eye tracker: info, stream (`--device sim:saccades` runs a simulated one).
    Gaze(gaze_cmd::Args),
    /// Simulators: devices on a pty (`optotune`, `lens`, `sync`) and procedural scenes (`scene`).
    Sim(sim_cmd::Args),
    /// Talk to multifocal sync hardware: status, program, start, stop, events.
    Sync(sync_cmd::Args),
    /// Depth of field from RGB-D at one focus (gather or lightfield).
    Render(render_cmd::RenderArgs),
    /// A focal stack from RGB-D (default 40 slices over 0.1-4.0 D).
    Focalstack(render_cmd::FocalStackArgs),
    /// Multifocal layers from RGB-D (linear or optimized blending).
    Decompose(render_cmd::DecomposeArgs),
    /// What the eye sees focusing at q through a varifocal, multifocal or light-field display.
    Retina(render_cmd::RetinaArgs),
    /// PSNR and SSIM of two images (sRGB-encoded), optionally inside a mask.
    Metrics(render_cmd::MetricsArgs),
    /// A dense light field synthesised from 5 or 9 sparse RGB-D views.
    Lightfield(render_cmd::LightFieldArgs),
    /// Log-polar foveated sampling and inverse-distance interpolation of an image.
    Foveate(render_cmd::FoveateArgs),
    /// The display-control daemon: devices, scheduler, display, control API, recording.
    Serve(serve::Args),
    /// Drive a scheduler from a `serve` recording (MCAP) and compare its commands.
    Replay(replay::Args),
    /// Recordings: `recover` rewrites a cut-off one (the daemon killed) into a complete file.
    Recording(recording_cmd::Args),
    /// Train a DeepFocus-family network on simulated scenes (c1, c3, c4).
    Train(train::Args),
    /// Speed against accuracy of every render method, and the failure-case suite: CSV, charts, report.
    Eval(eval::Args),
    /// Hardware-in-the-loop latency harness: gaze to lens command, command to settled,
    /// sub-frame timing, on the devices a rig config names (simulated ones say so).
    Hil(hil::Args),
    /// Lab Streaming Layer: the outlets a rig config makes (`--list`).
    Lsl(lsl_cmd::Args),
    /// The panel's light: `calibrate` its transfer function with a photometer; `sim-photometer`.
    Display(display_cmd::Args),
}

/// The crates' `tracing` events (devices lost and reconnected, display misfits, failed
/// renders, lens status warnings) on stderr: from `level` up, or as `RUST_LOG` says
/// (`RUST_LOG=debug`, `RUST_LOG=dioptra_lens=trace`). Without a subscriber they went nowhere.
fn log_to_stderr(level: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    // Fails only if a subscriber is already set, which nothing else does.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

/// A closed pipe on stdout (`dioptra replay --json | head`) ends the command quietly, as it
/// does other Unix tools, instead of a panic in `println!`. Not for commands that drive a rig
/// (serve, hil): they must park the lens whatever happens to their output.
fn quiet_broken_pipes() {
    // SAFETY: setting a signal's disposition to its default, before any thread is started.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// On a machine with no Wayland session (`XDG_RUNTIME_DIR` unset: a headless rig PC, CI, an
/// ssh login), Mesa's Vulkan device-selection layer still asks libwayland for a display while
/// wgpu lists adapters, and libwayland prints `error: XDG_RUNTIME_DIR is invalid or not set in
/// the environment.` on every instance, which reads as a failure of ours. The layer only
/// orders GPUs by the session's display, and there is none; it is left on when the user picks
/// a GPU through it (`MESA_VK_DEVICE_SELECT`, `DRI_PRIME`) or says either way
/// (`NODEVICE_SELECT`).
fn device_select_layer_is_moot(var: impl Fn(&str) -> Option<std::ffi::OsString>) -> bool {
    let set = |k: &str| var(k).is_some_and(|v| !v.is_empty());
    !set("XDG_RUNTIME_DIR")
        && !set("WAYLAND_DISPLAY")
        && !set("MESA_VK_DEVICE_SELECT")
        && !set("DRI_PRIME")
        && var("NODEVICE_SELECT").is_none()
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    if device_select_layer_is_moot(|k| std::env::var_os(k)) {
        // Before any thread is started (the render worker reads the environment later).
        std::env::set_var("NODEVICE_SELECT", "1");
    }
    dioptra_render::alloc::keep_freed_memory();
    let drives_a_rig = matches!(cli.command, Command::Serve(_) | Command::Hil(_));
    log_to_stderr(if drives_a_rig { "info" } else { "warn" });
    if !drives_a_rig {
        quiet_broken_pipes();
    }
    let result = match cli.command {
        Command::Demo(args) => demo::run_demo(args),
        Command::Devices(args) => devices::run(args),
        Command::Udev(args) => udev::run(args),
        Command::Lens(args) => lens_cmd::run(args),
        Command::Optics(args) => optics_cmd::run(args),
        Command::Gaze(args) => gaze_cmd::run(args),
        Command::Sim(args) => sim_cmd::run(args),
        Command::Sync(args) => sync_cmd::run(args),
        Command::Render(args) => render_cmd::render(args),
        Command::Focalstack(args) => render_cmd::focalstack(args),
        Command::Decompose(args) => render_cmd::decompose(args),
        Command::Retina(args) => render_cmd::retina(args),
        Command::Metrics(args) => render_cmd::metrics(args),
        Command::Lightfield(args) => render_cmd::lightfield(args),
        Command::Foveate(args) => render_cmd::foveate(args),
        Command::Serve(args) => serve::run(args),
        Command::Replay(args) => replay::run(args),
        Command::Recording(args) => recording_cmd::run(args),
        Command::Train(args) => train::run(args),
        Command::Eval(args) => eval::run(args),
        Command::Hil(args) => hil::run(args),
        Command::Lsl(args) => lsl_cmd::run(args),
        Command::Display(args) => display_cmd::run(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            match e.downcast_ref::<common::Exit>() {
                Some(exit) => std::process::ExitCode::from(exit.code),
                None => std::process::ExitCode::FAILURE,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::device_select_layer_is_moot;
    use std::ffi::OsString;

    fn env<'a>(vars: &'a [(&str, &str)]) -> impl Fn(&str) -> Option<OsString> + 'a {
        move |k| {
            vars.iter()
                .find(|(name, _)| *name == k)
                .map(|(_, v)| OsString::from(v))
        }
    }

    #[test]
    fn the_device_select_layer_is_off_only_without_a_session() {
        assert!(device_select_layer_is_moot(env(&[])));
        assert!(device_select_layer_is_moot(env(&[("XDG_RUNTIME_DIR", "")])));
        assert!(!device_select_layer_is_moot(env(&[(
            "XDG_RUNTIME_DIR",
            "/run/user/1000"
        )])));
        assert!(!device_select_layer_is_moot(env(&[("DRI_PRIME", "1")])));
        assert!(!device_select_layer_is_moot(env(&[(
            "MESA_VK_DEVICE_SELECT",
            "10de:2684"
        )])));
        // The user's own choice stands, either way.
        assert!(!device_select_layer_is_moot(env(&[(
            "NODEVICE_SELECT",
            "0"
        )])));
    }
}
