//! `dioptra recording recover FILE`: a recording cut off mid-write (the daemon killed, the
//! power cut) rewritten into a complete MCAP file that every reader opens.

use std::path::PathBuf;

use anyhow::{Context, Result};

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    pub command: Cmd,
}

#[derive(clap::Subcommand, Debug)]
pub enum Cmd {
    /// Rewrites a cut-off recording into a complete one: every message up to the cut (the
    /// daemon closes a chunk at least every second, so a kill loses at most the last one).
    Recover {
        /// The recording (MCAP) to recover.
        file: PathBuf,
        /// Where to write the complete file (default: FILE with `.recovered.mcap`); never
        /// overwritten.
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

pub fn run(args: Args) -> Result<()> {
    match args.command {
        Cmd::Recover { file, out } => {
            let out = out.unwrap_or_else(|| file.with_extension("recovered.mcap"));
            let r = dioptra_rig::recording::recover(&file, &out)
                .with_context(|| format!("recovering {}", file.display()))?;
            if r.was_cut {
                println!(
                    "{}: cut off ({}); {} messages before the cut written to {}",
                    file.display(),
                    r.cut_at.as_deref().unwrap_or("no more records"),
                    r.messages,
                    out.display()
                );
            } else {
                println!(
                    "{} was complete; its {} messages copied to {}",
                    file.display(),
                    r.messages,
                    out.display()
                );
            }
            Ok(())
        }
    }
}
