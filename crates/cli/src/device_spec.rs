//! `--device DRIVER:PORT` for the device commands: DRIVER is a driver's name in the rig
//! config (`dioptra_rig::devices::open`'s table) and PORT a rig config port (a device path,
//! a USB VID:PID, `usb[:SERIAL]`, a network address), so every device a command reaches a
//! rig config can name, and the link is opened by the same code.

use anyhow::{bail, Context, Result};
use dioptra_core::{DeviceError, LinkError};
use dioptra_lens::Opener;
use dioptra_rig::config::Port;
use dioptra_rig::devices::open::{device_link, names, row_named, Link, Row};
use dioptra_transport::AnyByteLink;

/// The row and port of `spec` ("DRIVER:PORT") among `rows`; `kind` names what DRIVER is in
/// messages ("lens driver").
pub fn parse<K, D>(
    spec: &str,
    rows: &'static [Row<K, D>],
    kind: &str,
) -> Result<(&'static Row<K, D>, Port)> {
    let example = rows
        .first()
        .map_or_else(String::new, |r| format!(", e.g. {}:/dev/ttyACM0", r.name));
    let (driver, port) = spec
        .split_once(':')
        .with_context(|| format!("--device must be DRIVER:PATH (DRIVER:PORT){example}"))?;
    let Some(row) = row_named(rows, driver) else {
        bail!(
            "unknown {kind} {driver:?}: use one of {} (the rig config's driver names)",
            names(rows)
        );
    };
    let port = Port::try_from(port.to_string()).map_err(anyhow::Error::msg)?;
    if port == Port::Sim {
        bail!(
            "{driver}:sim: the device commands talk to a device; run its simulator with `dioptra sim ... --pty` and give the path it prints"
        );
    }
    Ok((row, port))
}

/// The link to `row`'s device at `port`, opened off the runtime's threads (a USB or serial
/// open blocks).
pub async fn link<K: Sync, D>(row: &'static Row<K, D>, port: &Port) -> Result<Link, DeviceError> {
    let port = port.clone();
    tokio::task::spawn_blocking(move || device_link(row, &port))
        .await
        .map_err(|e| DeviceError::Link(LinkError::Io(e.to_string())))?
}

/// Opens (and after an unplug, reopens) `row`'s byte link at `port`.
pub fn byte_opener<K: Sync, D>(row: &'static Row<K, D>, port: Port) -> Opener<AnyByteLink> {
    Opener::new(move || {
        let port = port.clone();
        async move {
            link(row, &port)
                .await
                .and_then(|l| l.byte(row.what))
                .map_err(|e| match e {
                    DeviceError::Link(l) => l,
                    other => LinkError::Unavailable(other.to_string()),
                })
        }
    })
}
