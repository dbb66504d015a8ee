//! The render worker's side of the loop: what makes a frame's images from a content frame
//! ([`Renderer`]; the rig's own is [`rgbd::RgbdRenderer`]), and the job and result that travel
//! between the loop and the worker thread ([`job`]); `[render]` in [`config`]; what it
//! publishes in [`status`].

pub mod budget;
pub mod config;
pub mod job;
pub mod rgbd;
pub mod status;

pub use job::{
    error_kind, unblurred, EyesOnDevice, FrameImage, Planned, RenderJob, RenderOutput, Renderer,
};
pub use status::{RenderErrorNote, RenderHandle, RenderStatus};
