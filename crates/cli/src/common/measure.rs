//! The measure command of the calibrating commands (`lens calibrate`, `display calibrate`): a
//! shell command the lab supplies that reads its instrument and prints the measurement as its
//! last line of output.

use std::time::Duration;

use anyhow::{bail, Context, Result};

/// Runs `cmd` under `sh -c` with `env` set (a `None` value removes the variable), and gives
/// its last non-empty line of stdout as a number. `at` says which step, and `measured` what
/// the number is, for messages; a command that fails, hangs past `timeout` or prints no
/// number stops the calibration with a message saying that nothing was written.
pub async fn run_measure_cmd(
    cmd: &str,
    env: &[(&str, Option<String>)],
    timeout: Duration,
    at: &str,
    measured: &str,
) -> Result<f64> {
    let mut c = tokio::process::Command::new("sh");
    c.arg("-c")
        .arg(cmd)
        .stdin(std::process::Stdio::null())
        .kill_on_drop(true);
    for (k, v) in env {
        match v {
            Some(v) => c.env(k, v),
            None => c.env_remove(k),
        };
    }
    let out = tokio::time::timeout(timeout, c.output())
        .await
        .map_err(|_| {
            anyhow::anyhow!(
                "the measure command `{cmd}` took longer than {} s {at} (--measure-timeout-s); nothing written",
                timeout.as_secs()
            )
        })?
        .with_context(|| format!("cannot run the measure command `{cmd}` {at}"))?;
    let stdout = String::from_utf8_lossy(&out.stdout);
    if !out.status.success() {
        let stderr = String::from_utf8_lossy(&out.stderr);
        let tail: Vec<&str> = stderr.trim().lines().collect();
        bail!(
            "the measure command `{cmd}` failed {at} ({}){}; calibration stopped, nothing written",
            out.status,
            match tail.len() {
                0 => String::new(),
                n => format!(": {}", tail[n.saturating_sub(5)..].join(" | ")),
            }
        );
    }
    let last = stdout.lines().map(str::trim).rfind(|l| !l.is_empty());
    last.and_then(|l| l.parse::<f64>().ok())
        .filter(|v| v.is_finite())
        .with_context(|| {
            format!(
                "the measure command `{cmd}` printed {:?} {at}: its last line must be {measured}; nothing written",
                last.unwrap_or("")
            )
        })
}
