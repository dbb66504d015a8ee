//! Stereo and view-grid assembly: a frame sent in parts (a stereo rig's two halves, a light
//! field's views) is collected until every part arrived; the sequence numbers that make a
//! part stale.

use std::sync::Arc;

use dioptra_core::{Rgbd, Side};

use super::decode::FrameError;
use super::pool::Planes;
use crate::content::frame::{Arrival, ContentView};
use crate::content::ring::eye_code;

/// Sequence numbers whose halves may wait for their partner at once; one more drops the
/// oldest (each waiting half holds a frame's memory).
pub const MAX_WAITING: usize = 4;

/// A frame ready to show: one view, or (`eyes`) a pair whose `frame` is the left eye's; with
/// `views`, a grid's (each eye's) whose `frame` and `eyes` are its central views.
pub(super) struct Pending {
    pub frame: Arc<Rgbd>,
    pub eyes: Option<[Arc<Rgbd>; 2]>,
    pub views: Option<Arc<[ContentView]>>,
    pub seq: u64,
    pub arrival: Arrival,
}

impl Pending {
    /// Every image it holds, once each (for giving their memory back).
    pub(super) fn images(self) -> Vec<Arc<Rgbd>> {
        match (self.views, self.eyes) {
            (Some(views), _) => views.iter().map(|v| v.rgbd.clone()).collect(),
            (None, Some([l, r])) => vec![l, r],
            (None, None) => vec![self.frame],
        }
    }
}

/// A frame decoded, before it is paired or shown.
#[derive(Debug)]
pub(super) enum Decoded {
    /// One view (a mono rig's frame, or a mono frame on a stereo rig).
    Whole(Rgbd),
    /// Both eyes, from a side-by-side frame.
    Pair([Rgbd; 2]),
    /// One eye's half of a pair.
    Half(Side, Rgbd),
    /// One view of a grid (index row by row; an eye's own grid, or the one grid).
    View(Option<Side>, usize, Rgbd),
}

impl Decoded {
    /// The part of a frame it is; `None`: a whole frame.
    pub(super) fn part(&self) -> Option<Part> {
        match self {
            Decoded::Half(e, _) => Some(Part {
                eye: Some(*e),
                view: None,
            }),
            Decoded::View(eye, v, _) => Some(Part {
                eye: *eye,
                view: Some(*v),
            }),
            _ => None,
        }
    }
}

/// A part of a frame sent on its own: an eye's half (`view` `None`) or a view of a grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Part {
    pub eye: Option<Side>,
    pub view: Option<usize>,
}

impl Part {
    /// The key of its newest sequence number.
    pub(super) fn key(self) -> (u32, Option<usize>) {
        (eye_code(self.eye), self.view)
    }

    /// What its frame is made of, and its place there, for a grid of `per_eye` views.
    pub(super) fn place(self, per_eye: usize) -> (Parts, usize) {
        match (self.eye, self.view) {
            (Some(e), None) => (Parts::Halves, eye_index(e)),
            (None, Some(v)) => (Parts::Grid, v),
            (Some(e), Some(v)) => (Parts::EyeGrids, eye_index(e) * per_eye + v),
            // Not a part: never asked.
            (None, None) => (Parts::Halves, 0),
        }
    }
}

/// What a frame sent in parts is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Parts {
    /// A stereo pair's two halves.
    Halves,
    /// The views of one grid.
    Grid,
    /// Each eye's views of its own grid, the left eye's first.
    EyeGrids,
}

impl Parts {
    pub(super) fn count(self, per_eye: usize) -> usize {
        match self {
            Parts::Halves => 2,
            Parts::Grid => per_eye,
            Parts::EyeGrids => 2 * per_eye,
        }
    }
}

/// A frame's parts as they arrive.
pub(super) struct Waiting {
    pub parts: Parts,
    pub got: Vec<Option<Arc<Rgbd>>>,
}

/// The part of a frame an eye and a view name (`None`: a whole frame).
pub(super) fn part_of(eye: Option<Side>, view: Option<usize>) -> Option<Part> {
    (eye.is_some() || view.is_some()).then_some(Part { eye, view })
}

pub(super) fn eye_index(e: Side) -> usize {
    match e {
        Side::Left => 0,
        Side::Right => 1,
    }
}

/// The collecting of frames sent in parts (a stereo rig's halves, a grid's views), and the
/// sequence numbers that make a part stale.
#[derive(Default)]
pub(super) struct Pairing {
    /// Each part's newest accepted (an eye's half, a view of a grid), by [`Part::key`].
    pub newest_part: std::collections::BTreeMap<(u32, Option<usize>), u64>,
    /// Frames up to this number can no longer be shown: the newest frame complete (accepted
    /// whole, or its last part arrived), or the newest dropped incomplete.
    pub floor: Option<u64>,
    /// Parts waiting for the rest of their frame's (the same sequence number).
    pub waiting: std::collections::BTreeMap<u64, Waiting>,
}

impl Pairing {
    pub(super) fn halves_waiting(&self) -> u64 {
        self.waiting
            .values()
            .map(|w| w.got.iter().flatten().count() as u64)
            .sum()
    }
}

/// A frame complete: its view, its eyes' views, every view of its grid.
pub(super) type Complete = (
    Arc<Rgbd>,
    Option<[Arc<Rgbd>; 2]>,
    Option<Arc<[ContentView]>>,
);

/// Views per eye of a grid (1 without one).
pub(super) fn per_eye(grid: Option<&(usize, Vec<[f32; 2]>)>) -> usize {
    grid.map_or(1, |(n, _)| n * n)
}

impl Pairing {
    /// Files `part` of frame `seq` among its frame's parts: the frame (its view, its eyes'
    /// views and every view of a grid) when it was the last one missing.
    /// `grid`: a light field's views per side and their positions; a frame's parts dropped
    /// (their memory given back to `planes`) are counted in `dropped`.
    pub(super) fn add_part(
        &mut self,
        grid: Option<&(usize, Vec<[f32; 2]>)>,
        planes: &Planes,
        dropped: &mut u64,
        seq: u64,
        part: Part,
        frame: Rgbd,
    ) -> Option<Complete> {
        let pairing = self;
        let per_eye = per_eye(grid);
        let (parts, i) = part.place(per_eye);
        pairing.newest_part.insert(part.key(), seq);
        let waiting = pairing.waiting.entry(seq).or_insert_with(|| Waiting {
            parts,
            got: vec![None; parts.count(per_eye)],
        });
        waiting.got[i] = Some(Arc::new(frame));
        if waiting.got.iter().any(Option::is_none) {
            if pairing.waiting.len() > MAX_WAITING {
                if let Some((k, oldest)) = pairing.waiting.pop_first() {
                    *dropped += drop_parts(planes, oldest);
                    pairing.floor = pairing.floor.max(Some(k));
                }
            }
            return None;
        }
        // The frame arrives with its last part.
        let got: Vec<Arc<Rgbd>> = pairing
            .waiting
            .remove(&seq)?
            .got
            .into_iter()
            .flatten()
            .collect();
        let centre = grid.map_or(0, |(n, _)| (n / 2) * n + n / 2);
        Some(match parts {
            Parts::Halves => (got[0].clone(), Some([got[0].clone(), got[1].clone()]), None),
            Parts::Grid | Parts::EyeGrids => {
                let positions = grid.map_or(&[][..], |(_, p)| &p[..]);
                let eyes: &[Option<Side>] = if parts == Parts::Grid {
                    &[None]
                } else {
                    &[Some(Side::Left), Some(Side::Right)]
                };
                let views = ContentView::grid(eyes, positions, &got);
                let pair = (parts == Parts::EyeGrids)
                    .then(|| [got[centre].clone(), got[per_eye + centre].clone()]);
                (got[centre].clone(), pair, Some(views))
            }
        })
    }
}

/// Gives back the memory of a frame's parts dropped; how many there were.
pub(super) fn drop_parts(planes: &Planes, waiting: Waiting) -> u64 {
    let mut n = 0;
    for h in waiting.got.into_iter().flatten() {
        planes.give_frame(h);
        n += 1;
    }
    n
}

/// The sequence number a frame (or a part of one) gets: its own if newer than the newest
/// accepted (a part: than the newest of the same part and the newest complete frame), else
/// stale; a frame without one gets the next. A part must carry its own.
pub(super) fn next_seq(
    newest_seq: Option<u64>,
    pairing: &Pairing,
    seq: Option<u64>,
    part: Option<Part>,
) -> Result<u64, FrameError> {
    let Some(part) = part else {
        return match (seq, newest_seq) {
            (Some(s), Some(n)) if s <= n => Err(FrameError::Stale { seq: s, newest: n }),
            (Some(s), _) => Ok(s),
            (None, n) => Ok(n.map_or(1, |n| n + 1)),
        };
    };
    let seq = seq.ok_or_else(|| {
        FrameError::Request(match (part.eye, part.view) {
            (Some(eye), None) => format!(
                "the {} eye's frame needs its sequence number (seq=N): a pair's two halves \
                 share it",
                eye.as_str()
            ),
            _ => {
                "a view needs its frame's sequence number (seq=N): a frame's views share it".into()
            }
        })
    })?;
    let newest = pairing
        .newest_part
        .get(&part.key())
        .copied()
        .max(pairing.floor);
    match (newest, part.eye, part.view) {
        (Some(n), Some(eye), None) if seq <= n => Err(FrameError::StaleHalf {
            eye,
            seq,
            newest: n,
        }),
        (Some(n), eye, Some(v)) if seq <= n => Err(FrameError::StaleView {
            view: match eye {
                Some(e) => format!("{v} of the {} eye", e.as_str()),
                None => v.to_string(),
            },
            seq,
            newest: n,
        }),
        _ => Ok(seq),
    }
}

/// What a frame's parts are, in an error's words.
pub(super) fn parts_name(parts: Parts) -> &'static str {
    match parts {
        Parts::Halves => "an eye's halves",
        Parts::Grid => "views of one grid",
        Parts::EyeGrids => "views of each eye's grid",
    }
}
