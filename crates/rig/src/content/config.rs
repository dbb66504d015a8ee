//! `[content]`: what the rig shows (the procedural scene, a lab's RGB-D files, or frames an
//! application streams in), its defaults and checks.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::api::Api;
use crate::config::error::{invalid, ConfigError};

/// What the rig shows.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ContentSource {
    /// The procedural scene of `display.scene_seed`.
    #[default]
    Scene,
    /// RGB-D files: one frame, or a numbered sequence.
    Files,
    /// Frames pushed by a running application (shared-memory ring or `PUT /frame`).
    Stream,
}

/// In `content.color` and `content.depth`: the eye, `left` or `right` (a stereo rig's left
/// and right sequences, e.g. `"stim/%e/color_%04d.png"`).
pub const EYE_MARK: &str = "%e";

/// In `content.color` and `content.depth` with `content.views`: the view's place in its grid,
/// `<row>_<column>` with two digits each from `00_00` at the top left (the names `dioptra
/// lightfield` and `dioptra sim scene` give a light field's views: `"lf/view_%v.png"`).
pub const VIEW_MARK: &str = "%v";

/// The largest view grid (`content.views`): the light-field panel warps every input view for
/// each of its views, so the cost grows with the square of the grid.
pub const MAX_CONTENT_VIEWS: usize = 9;

/// The square a view grid spans when `content.view_span_mm` is not given (DeepFocus's and
/// the independent light-field set's 10 mm).
pub const DEFAULT_VIEW_SPAN_MM: f64 = 10.0;

/// `[content]`: the rig's RGB-D content.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContentConfig {
    #[serde(default)]
    pub source: ContentSource,
    /// Colour: PNG (8/16-bit sRGB) or EXR/PFM (linear); `%04d` makes it a sequence; `%e`
    /// (a stereo layout) stands for `left` and `right`, each eye's files.
    pub color: Option<String>,
    /// Depth: EXR/PFM metres or 16-bit PNG millimetres; a sequence (and `%e`) like `color`.
    pub depth: Option<String>,
    /// Override the depth files' units: m, mm or D.
    pub depth_units: Option<String>,
    /// A sequence's frame rate, Hz.
    #[serde(default = "default_content_fps")]
    pub fps: f64,
    /// Play a sequence again from its start (otherwise its last frame stays).
    #[serde(default, rename = "loop")]
    pub looped: bool,
    /// A sequence's first number (default 0).
    pub first: Option<usize>,
    /// Light-field content: each frame is a `views` x `views` grid of RGB-D views over a
    /// square of the eye's pupil plane, `%v` in `color` and `depth` naming each view's file
    /// (a stream: each view sent naming its place, `view=ROW_COLUMN`); light-field
    /// mode synthesises the panel's views from all of them, other modes show the grid's
    /// central view (for an even grid, the one right and below the centre).
    pub views: Option<usize>,
    /// The side of the square the view grid spans, millimetres (default 10): views are
    /// `view_span_mm / (views - 1)` apart, row 0 at the top, column 0 at the left.
    pub view_span_mm: Option<f64>,
    /// `source = "scene"`: move some of its objects, as the demo does (default true).
    pub animate: Option<bool>,
    /// `source = "stream"`: the shared-memory ring's file (default: beside `api.unix`, or
    /// `/dev/shm/dioptra-<pid>.frames`); `"none"` for `PUT /frame` only.
    pub ring: Option<PathBuf>,
}

impl Default for ContentConfig {
    fn default() -> Self {
        ContentConfig {
            source: ContentSource::Scene,
            color: None,
            depth: None,
            depth_units: None,
            fps: default_content_fps(),
            looped: false,
            first: None,
            views: None,
            view_span_mm: None,
            animate: None,
            ring: None,
        }
    }
}

fn default_content_fps() -> f64 {
    30.0
}

impl ContentConfig {
    /// The stream's shared-memory ring file (`None`: `ring = "none"`, `PUT /frame` only).
    pub fn ring_path(&self, api: &Api) -> Option<PathBuf> {
        match &self.ring {
            Some(p) if p.as_os_str() == "none" => None,
            Some(p) => Some(p.clone()),
            None => Some(match &api.unix {
                Some(sock) => {
                    let mut p = sock.clone().into_os_string();
                    p.push(".frames");
                    PathBuf::from(p)
                }
                None => {
                    let shm = std::path::Path::new("/dev/shm");
                    let dir = if shm.is_dir() {
                        shm.to_path_buf()
                    } else {
                        std::env::temp_dir()
                    };
                    dir.join(format!("dioptra-{}.frames", std::process::id()))
                }
            }),
        }
    }

    /// The source's keys: files need their patterns (`%e` only on a `stereo` display layout,
    /// `%v` with a view grid); the scene's and the stream's own keys only with them.
    pub fn check(&self, stereo: bool) -> Result<(), ConfigError> {
        let c = self;
        match c.source {
            ContentSource::Files => {
                for (key, v) in [("content.color", &c.color), ("content.depth", &c.depth)] {
                    if v.as_deref().is_none_or(str::is_empty) {
                        return Err(invalid(
                            key,
                            "source = \"files\" needs content.color and content.depth (a file, or a pattern such as \"stim/color_%04d.png\")",
                        ));
                    }
                }
                if !(c.fps.is_finite() && c.fps > 0.0 && c.fps <= 1000.0) {
                    return Err(invalid(
                        "content.fps",
                        "expected a frame rate of 0 to 1000 Hz",
                    ));
                }
                self.check_eye_patterns(stereo)?;
                self.check_view_grid()?;
                if let Some(u) = &c.depth_units {
                    if !["m", "mm", "D"].contains(&u.as_str()) {
                        return Err(invalid(
                            "content.depth_units",
                            format!("{u:?}: expected m, mm or D"),
                        ));
                    }
                }
            }
            ContentSource::Scene | ContentSource::Stream => {
                if c.color.is_some() || c.depth.is_some() {
                    return Err(invalid(
                        "content.source",
                        "content.color and content.depth are read with source = \"files\"",
                    ));
                }
                if c.source == ContentSource::Stream {
                    self.check_view_grid()?;
                } else if c.views.is_some() || c.view_span_mm.is_some() {
                    return Err(invalid(
                        "content.views",
                        "a view grid comes from files (source = \"files\", %v in content.color \
                         and content.depth) or a stream (source = \"stream\")",
                    ));
                }
            }
        }
        if c.animate.is_some() && c.source != ContentSource::Scene {
            return Err(invalid(
                "content.animate",
                "the procedural scene is animated (source = \"scene\"); files and streams move as their frames do",
            ));
        }
        if c.ring.is_some() && c.source != ContentSource::Stream {
            return Err(invalid(
                "content.ring",
                "the shared-memory ring is made with source = \"stream\"",
            ));
        }
        Ok(())
    }

    /// `%e` in `content.color`/`content.depth` (a left and a right sequence): only on a
    /// stereo layout, and in both patterns or neither.
    fn check_eye_patterns(&self, stereo: bool) -> Result<(), ConfigError> {
        let c = self;
        let keys = [("content.color", &c.color), ("content.depth", &c.depth)];
        let has = |v: &Option<String>| v.as_deref().is_some_and(|p| p.contains(EYE_MARK));
        for (key, v) in keys {
            if has(v) && !stereo {
                return Err(invalid(
                    key,
                    format!(
                        "{EYE_MARK} names the eye (a left and a right sequence), and \
                         display.layout is \"one\" (one image): set display.layout = \
                         \"side-by-side\" or \"two-outputs\", or name one sequence without \
                         {EYE_MARK}"
                    ),
                ));
            }
        }
        if has(&c.color) != has(&c.depth) {
            let (key, other) = if has(&c.color) {
                ("content.depth", "content.color")
            } else {
                ("content.color", "content.depth")
            };
            return Err(invalid(
                key,
                format!(
                    "{other} names each eye's files with {EYE_MARK}, so this must too: each \
                     eye's colour needs that eye's depth"
                ),
            ));
        }
        Ok(())
    }

    /// `content.views` and `content.view_span_mm`, and (files) `%v` in the patterns.
    fn check_view_grid(&self) -> Result<(), ConfigError> {
        let c = self;
        let has = |v: &Option<String>| v.as_deref().is_some_and(|p| p.contains(VIEW_MARK));
        match c.views {
            None => {
                for (key, v) in [("content.color", &c.color), ("content.depth", &c.depth)] {
                    if has(v) {
                        return Err(invalid(
                            key,
                            format!(
                                "{VIEW_MARK} names the views of a light field's grid: set \
                                 content.views to the grid's side (views per row)"
                            ),
                        ));
                    }
                }
                if c.view_span_mm.is_some() {
                    return Err(invalid(
                        "content.view_span_mm",
                        "it is the span of a view grid: set content.views too, or remove it",
                    ));
                }
            }
            Some(n) => {
                if !(2..=MAX_CONTENT_VIEWS).contains(&n) {
                    return Err(invalid(
                        "content.views",
                        format!(
                            "{n}: expected 2 to {MAX_CONTENT_VIEWS} views per side (every view \
                             is warped for each of the light-field panel's views)"
                        ),
                    ));
                }
                for (key, v) in [("content.color", &c.color), ("content.depth", &c.depth)] {
                    if c.source == ContentSource::Files && !has(v) {
                        return Err(invalid(
                            key,
                            format!(
                                "content.views = {n} needs {VIEW_MARK} in the pattern, where each \
                                 view's <row>_<column> goes (e.g. \"lf/view_{VIEW_MARK}.png\" for \
                                 view_00_00.png ...)"
                            ),
                        ));
                    }
                }
                if let Some(s) = c.view_span_mm {
                    if !(s.is_finite() && s > 0.0 && s <= 100.0) {
                        return Err(invalid(
                            "content.view_span_mm",
                            format!("{s}: expected a span of 0 to 100 mm"),
                        ));
                    }
                }
            }
        }
        Ok(())
    }
}
