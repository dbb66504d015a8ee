//! `dioptra lsl --list --config rig.toml`: the Lab Streaming Layer outlets a rig config makes
//! (names, types, rates, channels with their units, what each timestamp is), and whether this
//! build can make them.

use std::path::PathBuf;

use anyhow::{Context, Result};
use dioptra_rig::config::RigConfig;
use dioptra_rig::lsl::{stream_specs, BUILT_WITH_LSL, HOW_TO_BUILD};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// List the outlets (the only action; also the default).
    #[arg(long)]
    list: bool,
    /// The rig config (as for `dioptra serve`).
    #[arg(long)]
    config: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> Result<()> {
    let cfg = RigConfig::load(&args.config)
        .with_context(|| format!("rig config {}", args.config.display()))?;
    let specs = stream_specs(&cfg.lsl, &cfg.devices);
    if args.json {
        let v = serde_json::json!({
            "enabled": cfg.lsl.enabled,
            "built_with_lsl": BUILT_WITH_LSL,
            "streams": specs,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let state = match (cfg.lsl.enabled, BUILT_WITH_LSL) {
        (true, true) => "enabled: `dioptra serve` makes these outlets".to_string(),
        (true, false) => format!("enabled, but {HOW_TO_BUILD}"),
        (false, _) => "not enabled: set `[lsl] enabled = true` to make these outlets".to_string(),
    };
    println!("LSL outlets of {} ({state})", args.config.display());
    for s in &specs {
        let rate = if s.rate_hz > 0.0 {
            format!("{} Hz", s.rate_hz)
        } else {
            "irregular".into()
        };
        println!(
            "\n{}  type {}  {}  {:?}  {} channels  source id {}",
            s.name,
            s.kind,
            rate,
            s.format,
            s.channels.len(),
            s.source_id
        );
        println!("  timestamps: {}", s.timestamps);
        for (i, c) in s.channels.iter().enumerate() {
            let eye = if c.eye.is_empty() {
                String::new()
            } else {
                format!("  eye {}", c.eye)
            };
            println!(
                "  {i:>2} {:<24} {:<14} {:<11}{eye}",
                c.label, c.kind, c.unit
            );
        }
    }
    Ok(())
}
