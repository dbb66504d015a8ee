// Without the `simulated` feature the demo and the loop suite are left out, and with them
// some helpers they share with other commands.
#![cfg_attr(not(feature = "simulated"), allow(dead_code, unused_imports))]

//! `dioptra`: one binary for the rig. Each command group lives in its own module;
//! add a variant to [`Command`] and a module beside this file. What commands share is in
//! [`common`]; a command imports that, never another command (`crates/cli/LAYERS`).

mod common;
mod config_cmd;
mod demo;
mod devices;
mod display_cmd;
mod doctor;
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

use crate::common::Exit;

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
    /// Whether this machine can run a rig: GPU and Vulkan driver, udev rules, device access,
    /// the configured devices, the API's address. Each failed check prints its fix.
    Doctor(doctor::Args),
    /// Rig configs: `check FILE` (as `serve` reads it, errors naming the key), `schema` (JSON
    /// Schema for editors), `reference` (every key, Markdown).
    Config(config_cmd::Args),
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
    /// Depth of field from RGB-D at one focus (gather, lightfield, network or refine).
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
    ///
    /// The control API listens on api.listen in the rig config (127.0.0.1:7420 by default; a
    /// path for a Unix socket): GET /status, POST /focus, PUT /frame, GET /stream and the rest.
    ///
    /// Logs go to stderr: info and up, or as RUST_LOG says (RUST_LOG=debug adds the loop's and
    /// the scheduler's events; RUST_LOG=dioptra_rig::scheduler=debug only the scheduler's; an
    /// invalid RUST_LOG is an error).
    ///
    /// SIGTERM, SIGINT (Ctrl-C) and SIGHUP stop it as POST /shutdown does: the lens is parked,
    /// the sync sequence stopped and the recording finished; a second signal during the
    /// shutdown exits as soon as the lens is parked.
    Serve(serve::Args),
    /// Drive a scheduler from a `serve` recording (MCAP) and compare its commands.
    Replay(replay::Args),
    /// Recordings: `recover` rewrites a cut-off one (the daemon killed) into a complete file.
    Recording(recording_cmd::Args),
    /// Train a DeepFocus-family network on simulated scenes (c1, c3, c4, c5, fv, c1r, c4r, c5r).
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
/// A `RUST_LOG` that does not parse is an error, not a silent fall back to the default.
fn log_to_stderr(level: &str) -> Result<(), Exit> {
    let rust_log = std::env::var("RUST_LOG").ok();
    let filter = log_filter(rust_log.as_deref(), level).map_err(|e| Exit::new(2, e))?;
    let log = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    // Fails only if a subscriber is already set, which nothing else does. Under systemd the
    // journal stamps each line: no second timestamp, and the level as its priority.
    let _ = if serve::systemd::stderr_is_the_journal() {
        let line = tracing_subscriber::fmt::format().without_time();
        log.event_format(serve::systemd::JournalLine(line))
            .try_init()
    } else {
        log.try_init()
    };
    Ok(())
}

/// The log filter `RUST_LOG` gives (`level` where it is unset or empty), or why it does not
/// parse.
fn log_filter(
    rust_log: Option<&str>,
    level: &str,
) -> Result<tracing_subscriber::EnvFilter, String> {
    let Some(text) = rust_log.filter(|t| !t.trim().is_empty()) else {
        return Ok(tracing_subscriber::EnvFilter::new(level));
    };
    tracing_subscriber::EnvFilter::builder()
        .parse(text)
        .map_err(|e| {
            format!(
                "RUST_LOG={text:?}: {e}: give a level (error, warn, info, debug, trace), or \
                 targets with levels (dioptra_rig=debug,dioptra_lens=trace), or unset it"
            )
        })
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
    if let Err(e) = log_to_stderr(if drives_a_rig { "info" } else { "warn" }) {
        eprintln!("error: {e}");
        return std::process::ExitCode::from(e.code);
    }
    if !drives_a_rig {
        quiet_broken_pipes();
    }
    let result = match cli.command {
        Command::Demo(args) => demo::run_demo(args),
        Command::Devices(args) => devices::run(args),
        Command::Udev(args) => udev::run(args),
        Command::Doctor(args) => doctor::run(args),
        Command::Config(args) => config_cmd::run(args),
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

    /// The lab's report: `render --help` said "gather or lightfield", `train --help` listed
    /// c1, c3, c4 only, `serve --help` said nothing of the API address, RUST_LOG or signals.
    #[test]
    fn help_names_every_method_config_and_the_daemons_address_logs_and_signals() {
        use clap::CommandFactory;
        let cli = super::Cli::command();
        let about = |name: &str| {
            let c = cli.find_subcommand(name).unwrap();
            format!(
                "{} {}",
                c.get_about().map(|s| s.to_string()).unwrap_or_default(),
                c.get_long_about()
                    .map(|s| s.to_string())
                    .unwrap_or_default()
            )
        };
        let render = about("render");
        for m in ["gather", "lightfield", "network", "refine"] {
            assert!(render.contains(m), "{render}");
        }
        // Each a method `render --method` takes: the classical ones parse as such.
        assert!("gather".parse::<dioptra_render::DefocusMethod>().is_ok());
        assert!("lightfield"
            .parse::<dioptra_render::DefocusMethod>()
            .is_ok());
        let train = about("train");
        for c in dioptra_net::arch::CONFIGS {
            assert!(dioptra_net::Arch::preset(c).is_ok(), "{c}");
            assert!(
                train.contains(&format!("{c},")) || train.contains(&format!("{c})")),
                "{c}: {train}"
            );
        }
        let serve = about("serve");
        for words in [
            dioptra_rig::config::DEFAULT_LISTEN,
            "api.listen",
            "RUST_LOG",
            "SIGTERM",
            "SIGINT",
            "SIGHUP",
        ] {
            assert!(serve.contains(words), "{words}: {serve}");
        }
    }

    #[test]
    fn an_invalid_rust_log_is_an_error_naming_it() {
        use super::log_filter;
        for bad in ["dioptra_rig=verbose", "debug,[{", "=info"] {
            let e = log_filter(Some(bad), "info").unwrap_err();
            assert!(e.starts_with(&format!("RUST_LOG={bad:?}: ")), "{e}");
        }
        for good in ["debug", "dioptra_rig::scheduler=debug,info", "warn", ""] {
            assert!(log_filter(Some(good), "info").is_ok(), "{good}");
        }
        assert!(log_filter(None, "info").is_ok());
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
