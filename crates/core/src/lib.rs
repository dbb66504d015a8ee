//! dioptra-core: units, time, optics, images, device traits and errors.
//! Everything here is pure: no I/O, no device libraries.

pub mod clock_sync;
pub mod device;
pub mod distortion;
pub mod error;
pub mod image;
pub mod optics;
pub mod optics_map;
pub mod sampling;
pub mod sync;
mod table_csv;
pub mod time;
pub mod transfer;
pub mod units;

pub use clock_sync::ClockMapper;
pub use device::{
    DeviceWarning, EyeRay, GazeSample, GazeSource, LensState, LightEdge, LightEvent, LightQueue,
    Photodiode, PlaneSchedule, PlaneSequencer, SequencerEvent, SequencerFault, Side, VarifocalLens,
};
pub use error::{DeviceError, InputError, LinkError};
pub use image::{DepthMap, Plane, RgbImage, Rgbd};
pub use optics::EyeModel;
pub use optics_map::OpticsMap;
pub use sync::lock;
pub use time::{Clock, SimClock, SystemClock, Timestamp};
pub use units::{Diopters, Meters, Millimeters, PowerRange};
