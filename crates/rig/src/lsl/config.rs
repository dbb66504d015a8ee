//! `[lsl]`: whether the rig opens Lab Streaming Layer outlets, and the name their streams
//! take; its defaults and checks.

use serde::{Deserialize, Serialize};

use crate::config::error::{invalid, ConfigError};

/// `[lsl]` in the rig config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LslConfig {
    #[serde(default)]
    pub enabled: bool,
    /// The streams are `<name>-gaze`, `<name>-lens` and `<name>-markers`; their source ids
    /// derive from it, so a consumer picks the streams up again after a restart.
    #[serde(default = "default_name")]
    pub name: String,
}

fn default_name() -> String {
    "dioptra".into()
}

impl Default for LslConfig {
    fn default() -> Self {
        LslConfig {
            enabled: false,
            name: default_name(),
        }
    }
}

impl LslConfig {
    /// The name goes into the streams' names and source ids.
    pub fn check(&self) -> Result<(), ConfigError> {
        let name = &self.name;
        if name.is_empty()
            || name.len() > 64
            || !name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        {
            return Err(invalid(
                "lsl.name",
                format!("{name:?}: expected 1 to 64 letters, digits, '-' or '_' (it names the LSL streams)"),
            ));
        }
        Ok(())
    }
}
