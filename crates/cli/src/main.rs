//! `dioptra`: one binary for the rig. Each command group lives in its own module;
//! add a variant to [`Command`] and a module beside this file.

mod devices;
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
    /// List serial, USB and HID devices, each with the dioptra driver that matches it.
    Devices(devices::Args),
    /// Print udev rules for every device dioptra has a driver for.
    Udev(udev::Args),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Devices(args) => devices::run(args),
        Command::Udev(args) => udev::run(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
