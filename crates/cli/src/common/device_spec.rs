//! `--device DRIVER:PORT` for the device commands: DRIVER is a driver's name in the rig
//! config (`dioptra_rig::devices::open`'s table, with the aliases the table lists) and PORT a
//! rig config port (a device path, a USB VID:PID, `usb[:SERIAL]`, a network address; `hid`
//! for the driver's own HID VID:PID), or `sim[:ARG]` for the driver's simulator in this
//! process where the command takes one. Every device a command reaches a rig config can name,
//! and the link is opened and the driver connected by the same code.

use anyhow::{bail, Context as _, Result};
use dioptra_core::{DeviceError, LinkError};
use dioptra_rig::config::Port;
use dioptra_rig::devices::open::{
    alias_names, claimed_by, device_link, names, port_for, row_named, unalias, Context, Link, Row,
};

/// Where `--device` points.
#[derive(Debug, Clone, PartialEq)]
pub enum Target {
    /// The device at a port.
    Port(Port),
    /// The driver's simulator in this process, with the argument after `sim:` (a scenario).
    Sim(Option<String>),
}

/// The row and port of `spec` ("DRIVER:PORT") among `rows`, for a command that talks to a
/// device only; `kind` names what DRIVER is in messages ("lens driver").
pub fn parse_device<K, D, S>(
    spec: &str,
    rows: &'static [Row<K, D, S>],
    kind: &str,
) -> Result<(&'static Row<K, D, S>, Port)> {
    let example = rows
        .first()
        .map_or_else(String::new, |r| format!(", e.g. {}:/dev/ttyACM0", r.name));
    let usage = format!("DRIVER:PATH (DRIVER:PORT){example}");
    match parse(spec, rows, kind, &usage)? {
        (row, Target::Port(port)) => Ok((row, port)),
        (row, Target::Sim(_)) => bail!(
            "{}:sim: the device commands talk to a device; run its simulator with `dioptra sim ... --pty` and give the path it prints",
            row.name
        ),
    }
}

/// The row and target of `spec` among `rows`: `DRIVER:PORT`, `DRIVER:sim[:ARG]`, or an alias
/// the table lists. `usage` says what `--device` takes when `spec` is none of these.
pub fn parse<K, D, S>(
    spec: &str,
    rows: &'static [Row<K, D, S>],
    kind: &str,
    usage: &str,
) -> Result<(&'static Row<K, D, S>, Target)> {
    let spec = unalias(rows, spec).unwrap_or_else(|| spec.to_string());
    let (driver, port) = spec
        .split_once(':')
        .with_context(|| format!("--device must be {usage}"))?;
    let Some(row) = row_named(rows, driver) else {
        let aliases = alias_names(rows);
        let aliases = if aliases.is_empty() {
            String::new()
        } else {
            format!(", or {aliases}")
        };
        bail!(
            "unknown {kind} {driver:?}: use one of {} (the rig config's driver names){aliases}",
            names(rows)
        );
    };
    if port == "sim" {
        return Ok((row, Target::Sim(None)));
    }
    if let Some(arg) = port.strip_prefix("sim:") {
        return Ok((row, Target::Sim(Some(arg.to_string()))));
    }
    let port = port_for(row, port).map_err(anyhow::Error::msg)?;
    // A device is driven by the driver whose match table claims its VID:PID.
    let row = claimed_by(rows, &port).unwrap_or(row);
    Ok((row, Target::Port(port)))
}

/// The link to `row`'s device at `port`, opened off the runtime's threads (a USB or serial
/// open blocks).
pub async fn link<K: Sync, D, S>(
    row: &'static Row<K, D, S>,
    port: &Port,
) -> Result<Link, DeviceError> {
    let port = port.clone();
    tokio::task::spawn_blocking(move || device_link(row, &port))
        .await
        .map_err(|e| DeviceError::Link(LinkError::Io(e.to_string())))?
}

/// `ctx` for a driver that reopens its own link: after an unplug it opens `row`'s device at
/// `port` again.
pub fn reopening<K: Sync, D, S>(
    ctx: Context<S>,
    row: &'static Row<K, D, S>,
    port: Port,
) -> Context<S> {
    ctx.reopening(move || {
        let port = port.clone();
        async move { link(row, &port).await }
    })
}

/// Prints a device's facts, one a line, their labels in a column.
pub fn print_facts(facts: &[(&str, String)]) {
    let width = facts
        .iter()
        .map(|(label, _)| label.len())
        .max()
        .unwrap_or(0);
    for (label, value) in facts {
        println!("{label:<width$} {value}");
    }
}
