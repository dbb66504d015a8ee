//! RGB-D frames pushed by a running application (`[content] source = "stream"`).
//!
//! Two ways in, one decoder ([`decode_frame`]):
//! - the fast path, a shared-memory ring of frame slots: a file (0600) the daemon creates and
//!   maps, which the application maps too, writes a frame into a slot and names it with
//!   `POST /frame {"slot", "seq"}`. The daemon copies the slot out before it answers, so the
//!   slot is the application's again once the answer arrives. Layout: [`super::ring`] (spec:
//!   RING.md); `GET /frame/ring` says it too.
//! - the slow, simple path, `PUT /frame?width=&height=&color=&depth=[&near=&far=&seq=]` with
//!   the colour bytes then the depth bytes as the body; or, with `color=png|exr|pfm` and
//!   `color_bytes=N`, a colour image file (N bytes) then a depth image file (EXR, PFM or
//!   16-bit PNG), decoded by `dioptra render`'s readers. One body, so one frame is atomic.
//!
//! A frame is refused, with the reason, counted and never shown when: its size is not the
//! display's, a buffer is shorter or longer than its size says, a depth is NaN or outside its
//! convention's range, its sequence number is not newer than the newest accepted, or its slot
//! was rewritten while it was read. The frame on show stays until a good one replaces it.
//!
//! On a stereo rig (`display.layout` side-by-side or two-outputs) a frame is one of: a mono
//! frame of one eye's size (each eye's view synthesised from it); both eyes side by side,
//! 2 x width wide (split here, the left half the left eye's); or one eye's half (`eye=left`,
//! `eye=right`, a slot's `eye`), numbered with `seq`, the pair's two halves sharing it. A
//! pair is shown only once both halves arrived, in either order; a half waits until its
//! partner comes or a newer pair or whole frame completes (then it is dropped, counted under
//! `halves_dropped`); a half older than the newest complete pair is refused as stale.
//!
//! Light-field content (`content.views = N`): a frame may be an N x N grid of views, each sent
//! on its own naming its view (`view=ROW_COLUMN`, a slot's `view`) and the frame's `seq` (on a
//! stereo rig also its eye: each eye's own grid), collected as halves are and shown once
//! every view arrived ([`ContentFrame::views`]).
//!
//! - [`decode`]: pixel decoding (raw pixels or image files, to linear light and diopters);
//! - `pool`: the planes of frames done with, reused for the next;
//! - `assembly`: a frame sent in parts (a pair's halves, a grid's views) collected;
//! - [`ingest`]: the stream source, [`StreamFrames`], which the API hands frames to;
//! - the shared-memory ring's layout and file: [`super::ring`].

mod assembly;
pub mod decode;
pub mod ingest;
mod pool;
#[cfg(test)]
mod tests;

use std::sync::Arc;

use dioptra_core::{lock, Timestamp};

use super::frame::{Arrival, ContentFrame};
pub use super::ring::{RING_HEADER, RING_MAGIC, RING_SLOTS, RING_VERSION, SLOT_HEADER};
use super::source::Content;
use crate::problem::Problem;
use assembly::Pending;
pub use assembly::MAX_WAITING;
pub use decode::{decode_frame, ColorFormat, DepthKind, FrameDesc, FrameError};
pub use ingest::{StreamFrames, StreamStatus};

impl Content for StreamFrames {
    /// The newest accepted frame (or complete pair) not taken up yet; at the first call, the
    /// black placeholder if none arrived. The views it replaces are given back for reuse.
    fn poll(&self, _now: Timestamp) -> Option<ContentFrame> {
        let mut on_show = lock(&self.on_show);
        let (p, arrival) = match self.take_pending() {
            Some(p) => {
                let arrival = Some(p.arrival);
                (p, arrival)
            }
            None if on_show.1 == 0 => (
                Pending {
                    frame: Arc::new(self.placeholder()),
                    eyes: None,
                    views: None,
                    seq: 0,
                    arrival: Arrival {
                        arrived: Timestamp::ZERO,
                        ready: Timestamp::ZERO,
                    },
                },
                None,
            ),
            None => return None,
        };
        let frame = ContentFrame {
            arrival,
            eyes: p.eyes.clone(),
            views: p.views.clone(),
            ..ContentFrame::new(on_show.1 + 1, p.frame.clone())
        };
        for old in std::mem::replace(&mut on_show.0, p.images()) {
            self.recycle(old);
        }
        on_show.1 += 1;
        Some(frame)
    }
    fn arrivals(&self) -> Option<Arc<tokio::sync::Notify>> {
        Some(self.arrivals.clone())
    }
    fn status(&self) -> serde_json::Value {
        serde_json::to_value(StreamFrames::status(self)).unwrap_or_default()
    }
    fn problems(&self) -> Vec<Problem> {
        let st = lock(&self.status);
        match (st.refusing, &st.last_error) {
            (Some(key), Some(e)) => vec![Problem::new(
                "content",
                key,
                format!("the newest frame streamed in was refused (the one before stays): {e}"),
            )],
            _ => Vec::new(),
        }
    }
    fn frame_ingest(&self) -> Option<&StreamFrames> {
        Some(self)
    }
}
