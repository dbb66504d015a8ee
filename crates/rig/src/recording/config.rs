//! `[recording]`: where MCAP recordings go, and whether the daemon starts recording.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

/// `[recording]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Recording {
    /// Directory for MCAP files (`dioptra-<unix seconds>.mcap`).
    pub dir: PathBuf,
    /// Start recording when the daemon starts.
    #[serde(default)]
    pub start: bool,
}
