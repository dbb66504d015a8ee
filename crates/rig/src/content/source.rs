//! What a content source is ([`Content`]), why one does not open ([`ContentError`]), and the
//! simplest one, a [`Still`] frame.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use dioptra_core::{DepthMap, RgbImage, Rgbd, Timestamp};

use super::frame::ContentFrame;
use super::stream::ingest::StreamFrames;
use crate::problem::Problem;

/// A content source. Shared by the loop (which polls it), the API (status, frame ingest) and
/// the source's own worker threads, so it takes `&self`.
pub trait Content: Send + Sync + 'static {
    /// The frame to show at `now` when it is not the one returned last; always `Some` at the
    /// first call (which starts a sequence's clock).
    fn poll(&self, now: Timestamp) -> Option<ContentFrame>;
    /// When the next frame falls due on the source's own clock (a sequence, the animated
    /// scene): the loop polls then. `None`: no frame is due (a still frame, a stream).
    fn next_due(&self) -> Option<Timestamp> {
        None
    }
    /// Notified when a frame arrives from outside the loop (a stream's frame): the loop polls
    /// then.
    fn arrivals(&self) -> Option<Arc<tokio::sync::Notify>> {
        None
    }
    /// A render of the frame on show finished at `now`, taking `took` (both eyes, on the rig's
    /// clock): a source whose frames cost CPU to make (the procedural scene) makes them no
    /// faster than they are rendered.
    fn rendered(&self, _took: std::time::Duration, _now: Timestamp) {}
    /// What `/status` shows under `content`: the source and its counters.
    fn status(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
    /// What is wrong with the source now (its newest frame failed), under the key to look at;
    /// the details stay in its status's `last_error`.
    fn problems(&self) -> Vec<Problem> {
        Vec::new()
    }
    /// `source = "stream"`: where the API hands an application's frames.
    fn frame_ingest(&self) -> Option<&StreamFrames> {
        None
    }
}

/// Why a content source did not open.
#[derive(Debug, thiserror::Error)]
pub enum ContentError {
    #[error("content: {0}")]
    Config(String),
    /// A file the config names (`key`: `content.color`, ...) cannot be used; `reason` begins
    /// with its path.
    #[error("{key}: {reason}")]
    File {
        key: &'static str,
        path: std::path::PathBuf,
        reason: String,
    },
    #[error("cannot render the scene the display shows: {0}")]
    Scene(#[source] dioptra_render::RenderError),
}

/// One fixed frame: given once, then never changes.
#[derive(Debug)]
pub struct Still {
    frame: ContentFrame,
    given: AtomicBool,
}

impl Still {
    pub fn new(rgbd: Rgbd) -> Still {
        Still {
            frame: ContentFrame::new(1, Arc::new(rgbd)),
            given: AtomicBool::new(false),
        }
    }

    /// A black frame of `depth` (loop tests, where only the depth matters).
    pub fn of_depth(depth: &DepthMap) -> Still {
        Still::new(Rgbd {
            color: RgbImage::new(depth.width(), depth.height(), [0.0; 3]),
            depth: depth.clone(),
        })
    }
}

impl Content for Still {
    fn poll(&self, _now: Timestamp) -> Option<ContentFrame> {
        (!self.given.swap(true, Ordering::AcqRel)).then(|| self.frame.clone())
    }
    fn status(&self) -> serde_json::Value {
        serde_json::json!({ "source": "still" })
    }
}
