//! What the commands share, in one place: the runtimes they run on, the error that ends a
//! command with its own exit code, progress bars, the charts' font, the `--device` spec of
//! the device commands. A command imports this, never another command's module or
//! `main.rs` (`crates/cli/LAYERS`).

pub mod charts;
pub mod device_spec;
pub mod measure;
pub mod progress;

use dioptra_core::Diopters;

/// Runs a device command on a single-threaded tokio runtime: one device, one task at a time.
pub fn block_on<T>(
    work: impl std::future::Future<Output = anyhow::Result<T>>,
) -> anyhow::Result<T> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?
        .block_on(work)
}

/// The runtime a rig runs on (`serve`, `hil`): one thread for the rig's tasks and the API, so
/// that a gaze sample, the loop and the lens task hand over without waking another thread
/// (the host path's largest cost on a multi-threaded runtime); renders run on tokio's
/// blocking threads.
pub fn rig_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?)
}

/// An error that ends the command with its own exit code (1 is every other error's).
#[derive(Debug)]
pub struct Exit {
    pub code: u8,
    pub message: String,
}

impl Exit {
    pub fn new(code: u8, message: impl Into<String>) -> Exit {
        Exit {
            code,
            message: message.into(),
        }
    }
}

impl std::fmt::Display for Exit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for Exit {}

/// A focal-stack slice's file name: `focus_1.50D.png`.
pub fn slice_name(q: Diopters, ext: &str) -> String {
    format!("focus_{:.2}D.{ext}", q.0)
}
