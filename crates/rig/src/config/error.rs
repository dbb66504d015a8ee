//! The one error of a rig config, which every section's validation returns: the dotted key it
//! is about and what is wrong with it.

use std::path::PathBuf;

use thiserror::Error;

/// What went wrong with a rig config. `key` is the dotted path of the offending key.
#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("cannot read the rig config {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{key}: {message}")]
    Parse { key: String, message: String },
    #[error("{key}: {message}")]
    Invalid { key: String, message: String },
}

impl ConfigError {
    /// The dotted key the error is about (`.` for the whole file).
    #[cfg(test)]
    pub fn key(&self) -> &str {
        match self {
            ConfigError::Read { .. } => ".",
            ConfigError::Parse { key, .. } | ConfigError::Invalid { key, .. } => key,
        }
    }
}

pub(crate) fn invalid(key: &str, message: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        key: key.to_string(),
        message: message.into(),
    }
}

/// `s` on one line: its lines trimmed and joined with spaces (TOML's errors span lines).
pub(crate) fn one_line(s: &str) -> String {
    s.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join(" ")
}
