//! What can go wrong opening the window and drawing to it.

use thiserror::Error;

#[derive(Debug, Error)]
pub enum WindowError {
    #[error(
        "no display: set DISPLAY/WAYLAND_DISPLAY or use [display] kind = \"headless\" in the rig config"
    )]
    NoDisplay,
    #[error("cannot open the display ({detail}); check DISPLAY/WAYLAND_DISPLAY or use [display] kind = \"headless\"")]
    Open { detail: String },
    /// A monitor key (`display.monitor`, `monitor_left`, `monitor_right`) names no monitor.
    #[error("{key}: {detail}")]
    Monitor { key: &'static str, detail: String },
    #[error("cannot create the window: {0}")]
    Create(String),
    #[error("the window's GPU surface: {0}")]
    Gpu(String),
}
