//! `dioptra devices`: what is plugged in that dioptra knows, with the driver for each (the
//! drivers' match tables, joined in the drivers' table: `dioptra_rig::devices::open`).

use dioptra_rig::devices::open::known_devices;
use dioptra_transport::discovery;

#[derive(clap::Args)]
pub struct Args {
    /// Also list devices that no dioptra driver handles.
    #[arg(long)]
    all: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let found = discovery::discover(&known_devices());
    print!("{}", found.report(args.all));
    Ok(())
}
