//! A frame of content as the loop takes it up ([`ContentFrame`]): its RGB-D, each eye's and
//! each view's, and when it arrived.

use std::sync::Arc;

use dioptra_core::{DepthMap, Rgbd, Side, Timestamp};

/// When a content frame arrived (a stream frame's request, a file frame's due time, the
/// scene's frame time) and when it was ready to show, on the rig's clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Arrival {
    pub arrived: Timestamp,
    pub ready: Timestamp,
}

/// One view of light-field content: an RGB-D image seen from `position` (metres in the pupil
/// plane, x right and y down, from `eye`'s centre; `eye` `None`: from the centre between the
/// eyes, or a mono rig's eye).
#[derive(Debug, Clone)]
pub struct ContentView {
    pub eye: Option<Side>,
    pub position: [f32; 2],
    pub rgbd: Arc<Rgbd>,
}

impl ContentView {
    /// The views of an N x N grid per eye: `rgbds` holds each of `eyes`' grid in turn, in
    /// `positions`' order.
    pub fn grid(
        eyes: &[Option<Side>],
        positions: &[[f32; 2]],
        rgbds: &[Arc<Rgbd>],
    ) -> Arc<[ContentView]> {
        let per_eye = positions.len();
        eyes.iter()
            .enumerate()
            .flat_map(|(e, &eye)| {
                positions
                    .iter()
                    .enumerate()
                    .map(move |(k, &position)| ContentView {
                        eye,
                        position,
                        rgbd: rgbds[e * per_eye + k].clone(),
                    })
            })
            .collect()
    }
}

/// One frame of content, as the loop takes it up.
#[derive(Debug, Clone)]
pub struct ContentFrame {
    /// Counts the frames the source put on show, from 1; what is made from a frame (layers,
    /// a light-field panel) is kept under its number.
    pub number: u64,
    /// Colour (linear) and depth (diopters), spanning the eye's field: the view the
    /// scheduler reads fixation depth from (the cyclopean view; stereo content without one:
    /// the left eye's).
    pub rgbd: Arc<Rgbd>,
    /// Stereo content: the left and the right eye's views (`None`: one view; a stereo
    /// layout then synthesises each eye's from `rgbd`).
    pub eyes: Option<[Arc<Rgbd>; 2]>,
    /// The eye this frame is the view of (a frame [`ContentFrame::for_eye`] made); `None`: the
    /// cyclopean or only view.
    pub eye: Option<Side>,
    /// When it arrived (`None`: a still frame, or a source that does not know).
    pub arrival: Option<Arrival>,
    /// The procedural scene's time of the frame: recorded with its depth, so a replay renders
    /// the same frame.
    pub scene_time: Option<Timestamp>,
    /// The procedural scene as this frame shows it: light-field mode ray casts its own views
    /// from it instead of synthesising them from the RGB-D.
    pub scene: Option<Arc<dioptra_sim::scene::Scene>>,
    /// Light-field content (`content.views`): every view of the frame's grid (a stereo rig's
    /// `%e` grids: each eye's), from which light-field mode synthesises the panel's views;
    /// `rgbd` (and `eyes`) are the grid's central view. `None`: one view per eye.
    pub views: Option<Arc<[ContentView]>>,
}

impl ContentFrame {
    /// A frame with only its pixels (no arrival, no scene).
    pub fn new(number: u64, rgbd: Arc<Rgbd>) -> ContentFrame {
        ContentFrame {
            number,
            rgbd,
            eyes: None,
            eye: None,
            arrival: None,
            scene_time: None,
            scene: None,
            views: None,
        }
    }

    /// The frame as `side`'s eye sees it (`view`: that eye's RGB-D), for rendering that eye.
    pub fn for_eye(&self, side: Side, view: Arc<Rgbd>) -> ContentFrame {
        ContentFrame {
            rgbd: view,
            eyes: None,
            eye: Some(side),
            ..self.clone()
        }
    }

    /// Its depth map, for the scheduler.
    pub fn depth(&self) -> Arc<DepthMap> {
        Arc::new(self.rgbd.depth.clone())
    }
}
