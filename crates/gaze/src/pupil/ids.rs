//! How Pupil Capture (and Pupil Service) is reached: its network interface, Pupil Remote's
//! commands and the topics the driver reads. There is no USB match table: the cameras belong
//! to Capture, and dioptra talks to Capture over TCP.

/// The driver's name in the rig config and on the command line.
pub const DRIVER: &str = "pupil";

/// Pupil Remote's default port (Capture's "Pupil Remote" plugin).
pub const DEFAULT_REMOTE_PORT: u16 = 50020;

/// Pupil Remote commands (a REQ carrying one string; the reply is one string).
pub mod command {
    /// The port of the IPC backbone's publisher: where a SUB connects.
    pub const SUB_PORT: &str = "SUB_PORT";
    /// The port of the IPC backbone's subscriber: where a PUB connects to inject messages.
    pub const PUB_PORT: &str = "PUB_PORT";
    /// Current Pupil time, seconds, as a float's repr.
    pub const TIME: &str = "t";
    /// Capture's version string.
    pub const VERSION: &str = "v";
}

/// Every 3D gaze datum (binocular and both monocular topics start with it).
pub const GAZE_3D_TOPIC: &str = "gaze.3d.";
/// A gaze datum mapped from both eyes' pupil datums.
pub const BINOCULAR_TOPIC: &str = "gaze.3d.01.";
/// Monocular datums, one eye each.
pub const MONOCULAR_RIGHT_TOPIC: &str = "gaze.3d.0.";
pub const MONOCULAR_LEFT_TOPIC: &str = "gaze.3d.1.";

/// Pupil's eye ids: camera "eye0" films the right eye, "eye1" the left.
pub const RIGHT_EYE_ID: u8 = 0;
pub const LEFT_EYE_ID: u8 = 1;

/// Pupil Labs' documented threshold: gaze below 0.6 confidence is not to be trusted.
pub const RECOMMENDED_MIN_CONFIDENCE: f32 = 0.6;
