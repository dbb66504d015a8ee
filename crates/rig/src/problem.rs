//! What is wrong with a running rig now, as `/status`'s `problems` lists it: each entry names
//! the part it is in and the config key to look at. Each part says its own ([`Problem`]s from
//! its status handle); the details stay in the part's own status object (its `last_error`).

use serde::Serialize;

/// One thing wrong now.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Problem {
    /// The part: `devices`, `content`, `render`, `display`, `optics`, `recording`, `lsl`.
    pub part: &'static str,
    /// The config key to look at (`devices.lens.port`, `display.scale`, ...).
    pub key: String,
    /// What is wrong, in words.
    pub problem: String,
}

impl Problem {
    pub fn new(part: &'static str, key: impl Into<String>, problem: impl Into<String>) -> Self {
        Problem {
            part,
            key: key.into(),
            problem: problem.into(),
        }
    }
}
