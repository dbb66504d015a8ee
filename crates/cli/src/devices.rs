//! `dioptra devices`: what is plugged in that dioptra knows, with the driver for each.

use dioptra_transport::discovery::{self, KnownDevice};

#[derive(clap::Args)]
pub struct Args {
    /// Also list devices that no dioptra driver handles.
    #[arg(long)]
    all: bool,
}

/// Every driver's match table, joined. A new driver crate adds its `ids::KNOWN_DEVICES` here.
pub fn known_devices() -> Vec<KnownDevice> {
    [
        dioptra_lens::ids::KNOWN_DEVICES,
        dioptra_gaze::ids::KNOWN_DEVICES,
        dioptra_sync::ids::KNOWN_DEVICES,
    ]
    .concat()
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let found = discovery::discover(&known_devices());
    print!("{}", found.report(args.all));
    Ok(())
}
