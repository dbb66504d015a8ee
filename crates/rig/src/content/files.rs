//! A lab's own RGB-D content from files (`[content] source = "files"`): one frame, or a
//! numbered sequence (`color = "stim/color_%04d.png"`) played at `fps`, decoded ahead on a
//! worker thread so playback never waits for the disk.
//!
//! Stereo content (a stereo `display.layout`): `%e` in both patterns stands for `left` and
//! `right` (`"stim/%e/color_%04d.png"`), one pattern for the two eyes so their sequences are
//! numbered, started and played as one; each frame is then the two eyes' views
//! ([`ContentFrame::eyes`]), its `rgbd` the left eye's. Without `%e` a stereo rig shows one
//! view and each eye's is synthesised from it.
//!
//! Light-field content (`content.views = N`): `%v` in both patterns stands for each view's
//! `<row>_<column>` in an N x N grid (`"lf/%04d/view_%v.png"`: view_00_00.png ...), the views
//! `content.view_span_mm` apart over the square; each frame is then every view
//! ([`ContentFrame::views`]), its `rgbd` the grid's central one. With `%e` too, each eye has
//! its own grid, centred on that eye.
//!
//! At start every file of the sequence (each eye's) must exist and the first frame must decode
//! and match the display's (one eye's) size: otherwise the rig does not start, naming the path
//! and the reason. A frame that fails later (corrupt, wrong size) is skipped and counted, and
//! the frame before it stays on screen; one not decoded by the time it is due is counted late
//! (same).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use dioptra_core::{lock, Rgbd, Side, Timestamp};
use dioptra_render::io::{read_color, read_depth, DepthUnits};
use serde::Serialize;

use super::config::{ContentConfig, DEFAULT_VIEW_SPAN_MM, EYE_MARK, VIEW_MARK};
use super::frame::{Arrival, ContentFrame, ContentView};
use super::source::{Content, ContentError};
use crate::display::config::Display;
use crate::problem::Problem;

/// Frames decoded ahead of the one on show.
const AHEAD: usize = 4;

/// One frame's files: a colour and a depth file per view (one, or the left and the right
/// eye's; with a view grid, each eye's grid row by row).
type FrameFiles = Vec<(PathBuf, PathBuf)>;

/// One frame decoded: its views, in [`FrameFiles`]' order.
type Views = Arc<[Arc<Rgbd>]>;

/// What `/status` shows under `content`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ContentStatus {
    pub source: &'static str,
    /// Each frame a left and a right eye's view (`%e` in the patterns).
    pub stereo: bool,
    /// Light-field content: views per side of each frame's grid (`content.views`).
    pub views: Option<usize>,
    pub frames_in_sequence: usize,
    /// The sequence index on show.
    pub index: usize,
    /// Frames decoded (the first included).
    pub decoded: u64,
    /// Frames that failed to decode, or had the wrong size: skipped.
    pub skipped: u64,
    /// Frames not decoded when they were due: the previous one stayed on show.
    pub late: u64,
    pub last_error: Option<String>,
    /// Host time (ns) the frame on show became current.
    pub since_ns: u64,
    /// The newest frame due was skipped (the next one decoded clears it).
    #[serde(skip)]
    pub failing: bool,
}

/// A pattern's file of number `i` (`None`: the pattern is one file, not a sequence).
fn numbered(pattern: &str) -> Result<Option<impl Fn(usize) -> PathBuf + '_>, ContentError> {
    let Some(at) = pattern.find('%') else {
        return Ok(None);
    };
    // %d or %0Nd, once.
    let rest = &pattern[at + 1..];
    let digits: String = rest.chars().take_while(|c| c.is_ascii_digit()).collect();
    if !rest[digits.len()..].starts_with('d') || rest.contains('%') {
        return Err(ContentError::Config(format!(
            "{pattern:?}: a sequence pattern holds one %d or %0Nd (e.g. color_%04d.png)"
        )));
    }
    let width: usize = digits.parse().unwrap_or(0);
    let (head, tail) = (&pattern[..at], &rest[digits.len() + 1..]);
    Ok(Some(move |i: usize| {
        PathBuf::from(format!("{head}{i:0width$}{tail}"))
    }))
}

/// `pattern` for `eye` (`%e` replaced by `left` or `right`); unchanged for one view.
fn eye_pattern(pattern: &str, eye: Option<Side>) -> String {
    match eye {
        Some(e) => pattern.replace(EYE_MARK, e.as_str()),
        None => pattern.to_string(),
    }
}

/// `pattern` for the view at `row`, `column` of a grid (`%v` replaced by `<row>_<column>`).
fn view_pattern(pattern: &str, row: usize, column: usize) -> String {
    pattern.replace(VIEW_MARK, &format!("{row:02}_{column:02}"))
}

/// How each frame's views are laid out: one or two eyes, each one view or a grid.
#[derive(Debug, Clone)]
struct ViewLayout {
    eyes: Vec<Option<Side>>,
    /// Views per side and each view's position (metres, row by row); `None`: one view.
    grid: Option<(usize, Vec<[f32; 2]>)>,
}

impl ViewLayout {
    fn new(eyes: bool, grid: Option<usize>, span_mm: f64) -> Result<ViewLayout, ContentError> {
        let grid = grid
            .map(|n| {
                dioptra_sim::scene::light_field_positions(n, (span_mm * 1e-3) as f32)
                    .map(|p| (n, p))
                    .map_err(|e| ContentError::Config(format!("content.views: {e}")))
            })
            .transpose()?;
        Ok(ViewLayout {
            eyes: if eyes {
                vec![Some(Side::Left), Some(Side::Right)]
            } else {
                vec![None]
            },
            grid,
        })
    }

    /// Views per eye.
    fn per_eye(&self) -> usize {
        self.grid.as_ref().map_or(1, |(n, _)| n * n)
    }

    /// The index of an eye's central view among its views (0 without a grid).
    fn centre(&self) -> usize {
        self.grid.as_ref().map_or(0, |(n, _)| (n / 2) * n + n / 2)
    }

    /// Each view's pattern, in [`FrameFiles`]' order.
    fn patterns(&self, pattern: &str) -> Vec<String> {
        let mut out = Vec::new();
        for &eye in &self.eyes {
            let p = eye_pattern(pattern, eye);
            match &self.grid {
                None => out.push(p),
                Some((n, _)) => {
                    for k in 0..n * n {
                        out.push(view_pattern(&p, k / n, k % n));
                    }
                }
            }
        }
        out
    }

    /// The content frame `number` of the decoded `views`: each eye's central view as its
    /// RGB-D, every view of a grid as the frame's views.
    fn frame(&self, number: u64, views: &[Arc<Rgbd>]) -> ContentFrame {
        let per_eye = self.per_eye();
        let centre = self.centre();
        let central: Vec<Arc<Rgbd>> = (0..self.eyes.len())
            .map(|e| views[e * per_eye + centre].clone())
            .collect();
        ContentFrame {
            eyes: match &central[..] {
                [left, right] => Some([left.clone(), right.clone()]),
                _ => None,
            },
            views: self
                .grid
                .as_ref()
                .map(|(_, positions)| ContentView::grid(&self.eyes, positions, views)),
            ..ContentFrame::new(number, central[0].clone())
        }
    }
}

/// The files of a sequence, in order; `key` names the pattern's config key.
fn expand(key: &'static str, pattern: &str, first: usize) -> Result<Vec<PathBuf>, ContentError> {
    let Some(name) = numbered(pattern)? else {
        return Ok(vec![PathBuf::from(pattern)]);
    };
    let mut paths = Vec::new();
    let mut i = first;
    while name(i).exists() {
        paths.push(name(i));
        i += 1;
    }
    if paths.is_empty() {
        return Err(ContentError::File {
            key,
            reason: format!(
                "{}: not found: the sequence's first file must exist (set content.first to its \
                 number if it does not start at 0)",
                name(first).display(),
            ),
            path: name(first),
        });
    }
    Ok(paths)
}

/// A sequence as found on disk: its config key, its pattern (the eye's) and its files.
struct Found {
    key: &'static str,
    pattern: String,
    paths: Vec<PathBuf>,
}

impl Found {
    fn new(key: &'static str, pattern: String, first: usize) -> Result<Found, ContentError> {
        let paths = expand(key, &pattern, first)?;
        Ok(Found {
            key,
            pattern,
            paths,
        })
    }
}

/// Two sequences that must have the same frames (a colour and its depth, the left and the
/// right eye's): where one ends before the other, the first file it lacks is named.
fn pair_up(a: &Found, b: &Found, first: usize) -> Result<(), ContentError> {
    let (short, long) = match a.paths.len().cmp(&b.paths.len()) {
        std::cmp::Ordering::Equal => return Ok(()),
        std::cmp::Ordering::Less => (a, b),
        std::cmp::Ordering::Greater => (b, a),
    };
    let n = short.paths.len();
    let missing = match numbered(&short.pattern)? {
        Some(name) => name(first + n),
        None => PathBuf::from(&short.pattern),
    };
    Err(ContentError::File {
        key: short.key,
        reason: format!(
            "{}: not found, and {} ({}) is there: frame {} needs both",
            missing.display(),
            long.paths[n].display(),
            long.key,
            first + n
        ),
        path: missing,
    })
}

/// Each frame's files, one pair per view of `layout`.
fn sequence(
    color: &str,
    depth: &str,
    first: usize,
    layout: &ViewLayout,
) -> Result<Vec<FrameFiles>, ContentError> {
    let mut each = Vec::new();
    for (c, d) in layout
        .patterns(color)
        .into_iter()
        .zip(layout.patterns(depth))
    {
        let c = Found::new("content.color", c, first)?;
        let d = Found::new("content.depth", d, first)?;
        each.push((c, d));
    }
    // The first view's colour against its depth, then every other view's files against the
    // first view's: a missing file is named beside its partner.
    pair_up(&each[0].0, &each[0].1, first)?;
    for (c, d) in &each[1..] {
        pair_up(&each[0].0, c, first)?;
        pair_up(&each[0].1, d, first)?;
    }
    let n = each[0].0.paths.len();
    Ok((0..n)
        .map(|i| {
            each.iter()
                .map(|(c, d)| (c.paths[i].clone(), d.paths[i].clone()))
                .collect()
        })
        .collect())
}

/// A frame's views, each decoded and checked against one eye's size.
fn decode_views(
    files: &[(PathBuf, PathBuf)],
    units: Option<DepthUnits>,
    size: (usize, usize),
    stereo: bool,
) -> Result<Views, ContentError> {
    files
        .iter()
        .map(|(c, d)| decode(c, d, units, size, stereo).map(Arc::new))
        .collect()
}

/// One colour and depth file pair; `stereo`: the display's size is one eye's.
fn decode(
    color: &Path,
    depth: &Path,
    units: Option<DepthUnits>,
    size: (usize, usize),
    stereo: bool,
) -> Result<Rgbd, ContentError> {
    // One message per file: the config key, then the path once (the readers' errors start
    // with it), then why, in the config's words.
    let err = |key: &'static str, path: &Path, e: &dyn std::fmt::Display| {
        let shown = path.display().to_string();
        let e = e
            .to_string()
            .replace("pass --depth-units", "set content.depth_units")
            .replace("--depth-units", "content.depth_units");
        let reason = if e.starts_with(&shown) {
            e
        } else {
            format!("{shown}: {e}")
        };
        ContentError::File {
            key,
            path: path.to_path_buf(),
            reason,
        }
    };
    let c = read_color(color).map_err(|e| err("content.color", color, &e))?;
    let d = read_depth(depth, units).map_err(|e| err("content.depth", depth, &e))?;
    if (c.width(), c.height()) != size {
        return Err(err(
            "content.color",
            color,
            &format!(
                "it is {} x {} pixels, and display.width x display.height{} is {} x {}: set \
                 them to the content's size",
                c.width(),
                c.height(),
                if stereo { " (one eye's image)" } else { "" },
                size.0,
                size.1
            ),
        ));
    }
    if (d.width(), d.height()) != (c.width(), c.height()) {
        return Err(err(
            "content.depth",
            depth,
            &format!(
                "it is {} x {} pixels, and its colour image (content.color) {} x {}",
                d.width(),
                d.height(),
                c.width(),
                c.height()
            ),
        ));
    }
    Rgbd::new(c, d).map_err(|e| err("content.depth", depth, &e))
}

struct Shared {
    state: Mutex<Worker>,
    /// Wakes the worker: the loop wants another frame, or the sequence is dropped.
    wake: Condvar,
    /// Notified after each decode (for tests that wait for the worker).
    decoded: Condvar,
}

struct Worker {
    /// The index the loop shows; the worker decodes from here on.
    want: usize,
    cache: BTreeMap<usize, Result<Views, String>>,
    /// Frames decoded so far (the first included).
    decoded: u64,
    stop: bool,
}

/// A file sequence being played.
pub struct FileFrames {
    pairs: Arc<Vec<FrameFiles>>,
    layout: ViewLayout,
    fps: f64,
    looped: bool,
    shared: Arc<Shared>,
    /// (start time, index on show, frame on show).
    on_show: Mutex<(Option<Timestamp>, usize, Views)>,
    /// The index last counted late (each late frame counts once).
    late_index: Mutex<Option<usize>>,
    status: Mutex<ContentStatus>,
    /// The due time of the frame taken up last, and when it was, until the loop asks.
    arrival: Mutex<Option<Arrival>>,
    /// Frames handed to the loop, and the latest poll ([`Content::poll`]).
    polled: Mutex<(u64, Option<Timestamp>)>,
}

impl std::fmt::Debug for FileFrames {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FileFrames")
            .field("frames", &self.pairs.len())
            .field("fps", &self.fps)
            .finish_non_exhaustive()
    }
}

impl FileFrames {
    /// Opens the sequence of `[content]` and decodes its first frame at the display's size.
    pub fn open(c: &ContentConfig, display: &Display) -> Result<FileFrames, ContentError> {
        let (Some(color), Some(depth)) = (&c.color, &c.depth) else {
            return Err(ContentError::Config(
                "source = \"files\" needs content.color and content.depth".into(),
            ));
        };
        let units = c
            .depth_units
            .as_deref()
            .map(str::parse::<DepthUnits>)
            .transpose()
            .map_err(|e| ContentError::Config(format!("content.depth_units: {e}")))?;
        let first = c.first.unwrap_or(0);
        let stereo = display.stereo();
        // Config validation refuses %e on a mono layout; checked again for a config built by
        // hand.
        let eyes = color.contains(EYE_MARK);
        if eyes && !stereo {
            return Err(ContentError::Config(format!(
                "content.color: {EYE_MARK} names each eye's files, and display.layout shows \
                 one image"
            )));
        }
        let layout = ViewLayout::new(
            eyes,
            c.views,
            c.view_span_mm.unwrap_or(DEFAULT_VIEW_SPAN_MM),
        )?;
        let pairs = Arc::new(sequence(color, depth, first, &layout)?);
        let size = (display.width as usize, display.height as usize);
        let first_frame = decode_views(&pairs[0], units, size, stereo)?;
        let shared = Arc::new(Shared {
            state: Mutex::new(Worker {
                want: 0,
                cache: BTreeMap::from([(0, Ok(first_frame.clone()))]),
                decoded: 1,
                stop: false,
            }),
            wake: Condvar::new(),
            decoded: Condvar::new(),
        });
        if pairs.len() > 1 {
            let (pairs, shared) = (pairs.clone(), shared.clone());
            let looped = c.looped;
            std::thread::Builder::new()
                .name("dioptra-content".into())
                .spawn(move || decode_ahead(&pairs, &shared, units, size, stereo, looped))
                .map_err(|e| ContentError::Config(format!("cannot start the decoder: {e}")))?;
        }
        Ok(FileFrames {
            fps: c.fps,
            looped: c.looped,
            status: Mutex::new(ContentStatus {
                source: "files",
                stereo: eyes,
                views: c.views,
                frames_in_sequence: pairs.len(),
                decoded: 1,
                ..Default::default()
            }),
            pairs,
            layout,
            shared,
            on_show: Mutex::new((None, 0, first_frame)),
            late_index: Mutex::new(None),
            arrival: Mutex::new(None),
            polled: Mutex::new((0, None)),
        })
    }

    /// The due time of the frame the latest [`FileFrames::frame_at`] took up, once.
    pub fn take_arrival(&self) -> Option<Arrival> {
        lock(&self.arrival).take()
    }

    /// The frame on show now (stereo: the left eye's view; a grid: its central view).
    pub fn current(&self) -> Arc<Rgbd> {
        lock(&self.on_show).2[self.layout.centre()].clone()
    }

    /// The frame on show at `now` (stereo: the left eye's view), and whether it changed since
    /// the last call. The first call starts the sequence.
    pub fn frame_at(&self, now: Timestamp) -> (Arc<Rgbd>, bool) {
        let (views, changed) = self.views_at(now);
        (views[self.layout.centre()].clone(), changed)
    }

    /// [`FileFrames::frame_at`] with each of the frame's views.
    fn views_at(&self, now: Timestamp) -> (Views, bool) {
        let mut show = lock(&self.on_show);
        let n = self.pairs.len();
        let start = *show.0.get_or_insert(now);
        if n == 1 {
            return (show.2.clone(), false);
        }
        let count = (now.saturating_since(start).as_secs_f64() * self.fps) as usize;
        let k = if self.looped {
            count % n
        } else {
            count.min(n - 1)
        };
        if k == show.1 {
            return (show.2.clone(), false);
        }
        let got = {
            let mut w = lock(&self.shared.state);
            w.want = k;
            let got = w.cache.get(&k).cloned();
            self.shared.wake.notify_one();
            got
        };
        let mut st = lock(&self.status);
        match got {
            Some(Ok(frame)) => {
                st.index = k;
                st.since_ns = now.0;
                st.failing = false;
                // Its due time: where the sequence's clock put it (late if decoding lagged).
                let shown = if self.looped { count } else { k };
                *lock(&self.arrival) = Some(Arrival {
                    arrived: start + Duration::from_secs_f64(shown as f64 / self.fps),
                    ready: now,
                });
                *show = (show.0, k, frame);
                (show.2.clone(), true)
            }
            Some(Err(e)) => {
                // Skipped: counted once, the frame before stays.
                if st.index != k {
                    st.skipped += 1;
                    st.last_error = Some(e);
                    st.index = k;
                    st.failing = true;
                }
                show.1 = k;
                (show.2.clone(), false)
            }
            None => {
                let mut late = lock(&self.late_index);
                if *late != Some(k) {
                    *late = Some(k);
                    st.late += 1;
                }
                (show.2.clone(), false)
            }
        }
    }

    pub fn status(&self) -> ContentStatus {
        let mut st = lock(&self.status).clone();
        st.decoded = lock(&self.shared.state).decoded;
        st
    }
}

impl Content for FileFrames {
    fn poll(&self, now: Timestamp) -> Option<ContentFrame> {
        let (views, changed) = self.views_at(now);
        let mut polled = lock(&self.polled);
        polled.1 = Some(now);
        if !changed && polled.0 > 0 {
            return None;
        }
        polled.0 += 1;
        Some(ContentFrame {
            arrival: self.take_arrival(),
            ..self.layout.frame(polled.0, &views)
        })
    }
    fn next_due(&self) -> Option<Timestamp> {
        let n = self.pairs.len();
        let at = lock(&self.polled).1?;
        let start = lock(&self.on_show).0?;
        let count = (at.saturating_since(start).as_secs_f64() * self.fps) as usize;
        if n == 1 || (!self.looped && count + 1 >= n) {
            return None;
        }
        let due = start + Duration::from_nanos(((count + 1) as f64 * 1e9 / self.fps).ceil() as u64);
        // Never at or before the latest poll, whatever the rounding: the loop would spin.
        Some(due.max(at + Duration::from_nanos(1)))
    }
    fn status(&self) -> serde_json::Value {
        serde_json::to_value(FileFrames::status(self)).unwrap_or_default()
    }
    fn problems(&self) -> Vec<Problem> {
        let st = lock(&self.status);
        match (st.failing, &st.last_error) {
            (true, Some(e)) => vec![Problem::new(
                "content",
                "content.color",
                format!("the newest frame due was skipped (the one before stays): {e}"),
            )],
            _ => Vec::new(),
        }
    }
}

impl Drop for FileFrames {
    fn drop(&mut self) {
        lock(&self.shared.state).stop = true;
        self.shared.wake.notify_all();
    }
}

/// The worker: keeps frames `want..want + AHEAD` decoded, drops the ones behind.
fn decode_ahead(
    pairs: &[FrameFiles],
    shared: &Shared,
    units: Option<DepthUnits>,
    size: (usize, usize),
    stereo: bool,
    looped: bool,
) {
    let n = pairs.len();
    let mut w = lock(&shared.state);
    loop {
        if w.stop {
            return;
        }
        let window: Vec<usize> = (0..=AHEAD)
            .map(|i| w.want + i)
            .filter_map(|i| {
                if looped {
                    Some(i % n)
                } else {
                    (i < n).then_some(i)
                }
            })
            .collect();
        let keep_from = w.want;
        w.cache.retain(|k, _| window.contains(k) || *k == keep_from);
        let Some(&next) = window.iter().find(|k| !w.cache.contains_key(k)) else {
            w = shared.wake.wait(w).unwrap_or_else(|p| p.into_inner());
            continue;
        };
        drop(w);
        let r = decode_views(&pairs[next], units, size, stereo).map_err(|e| e.to_string());
        w = lock(&shared.state);
        if r.is_ok() {
            w.decoded += 1;
        }
        w.cache.insert(next, r);
        shared.decoded.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::RigConfig;
    use dioptra_core::{DepthMap, Plane, RgbImage};
    use dioptra_render::io::{write_color, write_depth};
    use std::time::Duration;

    fn frame(v: f32, w: usize, h: usize) -> (RgbImage, DepthMap) {
        let depth = DepthMap::from_diopters(Plane::new(w, h, 1.0 + v)).unwrap();
        (RgbImage::new(w, h, [v, 0.5, 0.25]), depth)
    }

    /// The file frames of `cfg`'s `[content]` at its display's size.
    fn open_cfg(cfg: &RigConfig) -> Result<FileFrames, ContentError> {
        FileFrames::open(&cfg.content, &cfg.display)
    }

    fn config(dir: &Path, color: &str, depth: &str, extra: &str) -> RigConfig {
        let text = crate::config::EXAMPLE_SIM_RIG.to_string()
            + &format!(
                "\n[content]\nsource = \"files\"\ncolor = {:?}\ndepth = {:?}\n{extra}\n",
                dir.join(color).display().to_string(),
                dir.join(depth).display().to_string()
            );
        RigConfig::parse(&text).unwrap()
    }

    fn write_sequence(dir: &Path, n: usize) {
        for i in 0..n {
            let (c, d) = frame(0.1 * i as f32, 96, 96);
            write_color(&dir.join(format!("c_{i:03}.exr")), &c).unwrap();
            write_depth(&dir.join(format!("d_{i:03}.exr")), &d).unwrap();
        }
    }

    /// Waits until the decoder thread has `n` frames in its cache (a wait for the thread, not
    /// a timing check: the 60 s bound only fails a broken decoder).
    fn cached(f: &FileFrames, n: usize) {
        let w = lock(&f.shared.state);
        let (w, _) = f
            .shared
            .decoded
            .wait_timeout_while(w, Duration::from_secs(60), |w| w.cache.len() < n)
            .unwrap_or_else(|p| p.into_inner());
        assert!(w.cache.len() >= n, "the decoder did not decode {n} frames");
    }

    #[test]
    fn a_sequence_plays_at_its_rate_and_loops() {
        let dir = tempfile::tempdir().unwrap();
        write_sequence(dir.path(), 3);
        let cfg = config(
            dir.path(),
            "c_%03d.exr",
            "d_%03d.exr",
            "fps = 10\nloop = true",
        );
        let f = FileFrames::open(&cfg.content, &cfg.display).unwrap();
        assert_eq!(f.status().frames_in_sequence, 3);
        let ms = |m: u64| Timestamp(m * 1_000_000);
        let (first, changed) = f.frame_at(ms(0));
        assert!(!changed);
        assert_eq!(first.color.channels[0].data()[0], 0.0);
        cached(&f, 3);
        // 10 fps: frame 1 from 100 ms, frame 2 from 200 ms, frame 0 again from 300 ms.
        assert!(!f.frame_at(ms(99)).1);
        // Each frame arrives when it is due (frame 2 at 200 ms although taken up at 250 ms).
        for (t, v, due) in [(100, 0.1, 100), (250, 0.2, 200), (300, 0.0, 300)] {
            let (fr, changed) = f.frame_at(ms(t));
            assert!(changed, "{t} ms");
            assert!((fr.color.channels[0].data()[0] - v).abs() < 1e-6, "{t} ms");
            let a = f.take_arrival().unwrap();
            assert_eq!((a.arrived, a.ready), (ms(due), ms(t)));
            assert!(f.take_arrival().is_none(), "given once");
            cached(&f, 3);
        }
        let st = f.status();
        assert_eq!((st.skipped, st.index), (0, 0), "{st:?}");
    }

    #[test]
    fn a_corrupt_frame_mid_sequence_is_skipped_and_counted() {
        let dir = tempfile::tempdir().unwrap();
        write_sequence(dir.path(), 3);
        std::fs::write(dir.path().join("c_001.exr"), b"not an exr").unwrap();
        let cfg = config(dir.path(), "c_%03d.exr", "d_%03d.exr", "fps = 10");
        let f = FileFrames::open(&cfg.content, &cfg.display).unwrap();
        f.frame_at(Timestamp(0));
        cached(&f, 3);
        let (fr, changed) = f.frame_at(Timestamp(150_000_000));
        assert!(!changed, "the corrupt frame is not shown");
        assert_eq!(
            fr.color.channels[0].data()[0],
            0.0,
            "the frame before stays"
        );
        let st = f.status();
        assert_eq!(st.skipped, 1, "{st:?}");
        assert!(
            st.last_error.as_deref().unwrap().contains("c_001.exr"),
            "{st:?}"
        );
        // The next good frame is shown; without loop the last one stays.
        let (fr, changed) = f.frame_at(Timestamp(250_000_000));
        assert!(changed && (fr.color.channels[0].data()[0] - 0.2).abs() < 1e-6);
        assert!(!f.frame_at(Timestamp(900_000_000)).1);
    }

    /// A frame skipped is one of `/status`'s `problems` (the content part, `content.color`)
    /// while it is the newest due, and leaves the list when the next good frame is shown.
    #[test]
    fn a_skipped_frame_is_a_problem_until_the_next_good_one() {
        let dir = tempfile::tempdir().unwrap();
        write_sequence(dir.path(), 3);
        std::fs::write(dir.path().join("c_001.exr"), b"not an exr").unwrap();
        let cfg = config(dir.path(), "c_%03d.exr", "d_%03d.exr", "fps = 10");
        let f = FileFrames::open(&cfg.content, &cfg.display).unwrap();
        f.frame_at(Timestamp(0));
        cached(&f, 3);
        assert_eq!(Content::problems(&f), Vec::new());
        f.frame_at(Timestamp(150_000_000));
        let p = Content::problems(&f);
        assert_eq!(p.len(), 1, "{p:?}");
        assert_eq!((p[0].part, p[0].key.as_str()), ("content", "content.color"));
        assert!(p[0].problem.contains("c_001.exr"), "{}", p[0].problem);
        let (_, changed) = f.frame_at(Timestamp(250_000_000));
        assert!(changed);
        assert_eq!(Content::problems(&f), Vec::new());
        // The details stay in the source's own status.
        assert!(f.status().last_error.is_some());
    }

    #[test]
    fn bad_content_stops_the_start_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        write_sequence(dir.path(), 1);
        let e = open_cfg(&config(dir.path(), "x_%03d.exr", "d_%03d.exr", ""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("x_000.exr") && e.contains("not found"), "{e}");
        std::fs::write(dir.path().join("bad.png"), b"\x89PNG garbage").unwrap();
        let e = open_cfg(&config(dir.path(), "bad.png", "d_000.exr", ""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("bad.png"), "{e}");
        let (c, d) = frame(0.3, 64, 48);
        write_color(&dir.path().join("small.exr"), &c).unwrap();
        write_depth(&dir.path().join("small_d.exr"), &d).unwrap();
        let e = open_cfg(&config(dir.path(), "small.exr", "small_d.exr", ""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("64 x 48") && e.contains("display.width"), "{e}");
        // Each message names the config key and the path once (issue 39 item 2).
        let once = |e: &str, key: &str, file: &str| {
            assert!(e.starts_with(&format!("{key}: ")), "{e}");
            assert_eq!(e.matches(file).count(), 1, "{e}");
        };
        let e = open_cfg(&config(dir.path(), "nope.png", "d_000.exr", ""))
            .unwrap_err()
            .to_string();
        once(&e, "content.color", "nope.png");
        assert!(e.contains("not found"), "{e}");
        let e = open_cfg(&config(dir.path(), "c_000.exr", "small_d.exr", ""))
            .unwrap_err()
            .to_string();
        once(&e, "content.depth", "small_d.exr");
        assert!(e.contains("64 x 48 pixels") && e.contains("96 x 96"), "{e}");
        // An 8-bit PNG depth: the fix in the config's words.
        let eight = RgbImage::new(96, 96, [0.5, 0.5, 0.5]);
        write_color(&dir.path().join("depth8.png"), &eight).unwrap();
        let e = open_cfg(&config(dir.path(), "c_000.exr", "depth8.png", ""))
            .unwrap_err()
            .to_string();
        once(&e, "content.depth", "depth8.png");
        assert!(
            e.contains("content.depth_units") && !e.contains("--"),
            "{e}"
        );
        // The config itself: files needs both paths.
        let text = crate::config::EXAMPLE_SIM_RIG.to_string() + "\n[content]\nsource = \"files\"\n";
        let e = RigConfig::parse(&text).unwrap_err();
        assert_eq!(e.key(), "content.color");
    }

    /// The example rig with a side-by-side panel and `[content]` naming files in `dir`.
    fn stereo_config(dir: &Path, color: &str, depth: &str) -> RigConfig {
        let text = crate::config::EXAMPLE_SIM_RIG.replacen(
            "[display]",
            "[display]\nlayout = \"side-by-side\"",
            1,
        ) + &format!(
            "\n[content]\nsource = \"files\"\ncolor = {:?}\ndepth = {:?}\nfps = 10\n",
            dir.join(color).display().to_string(),
            dir.join(depth).display().to_string()
        );
        RigConfig::parse(&text).unwrap()
    }

    /// Each eye's sequence in `dir/left` and `dir/right`: the left eye's frame i has red
    /// 0.1 i and 1 + 0.1 i D, the right eye's red 0.5 + 0.1 i and 2 + 0.1 i D.
    fn write_eyes(dir: &Path, n: usize) {
        for (eye, v0) in [("left", 0.0), ("right", 0.5)] {
            std::fs::create_dir_all(dir.join(eye)).unwrap();
            for i in 0..n {
                let (c, d) = frame(v0 + 0.1 * i as f32, 96, 96);
                write_color(&dir.join(format!("{eye}/c_{i:03}.exr")), &c).unwrap();
                write_depth(&dir.join(format!("{eye}/d_{i:03}.exr")), &d).unwrap();
            }
        }
    }

    /// Stereo files are shown as pairs: each ContentFrame's eyes hold the left and the right
    /// file's pixels (as `dioptra render` reads them), `rgbd` the left eye's.
    #[test]
    fn stereo_files_are_shown_as_pairs() {
        use dioptra_render::io::{read_color, read_depth};
        let dir = tempfile::tempdir().unwrap();
        write_eyes(dir.path(), 3);
        let cfg = stereo_config(dir.path(), "%e/c_%03d.exr", "%e/d_%03d.exr");
        assert!(cfg.display.stereo());
        let f = FileFrames::open(&cfg.content, &cfg.display).unwrap();
        let st = f.status();
        assert!(st.stereo && st.frames_in_sequence == 3, "{st:?}");
        let ms = |m: u64| Timestamp(m * 1_000_000);
        let first = f.poll(ms(0)).expect("the first frame");
        cached(&f, 3);
        let second = f.poll(ms(100)).expect("frame 1 at 100 ms");
        for (frame, i) in [(first, 0), (second, 1)] {
            let [left, right] = frame.eyes.clone().expect("a pair");
            for (eye, view) in [("left", &left), ("right", &right)] {
                let file = |kind: &str| dir.path().join(format!("{eye}/{kind}_{i:03}.exr"));
                assert_eq!(view.color, read_color(&file("c")).unwrap(), "{eye} {i}");
                assert_eq!(
                    view.depth.data(),
                    read_depth(&file("d"), None).unwrap().data(),
                    "{eye} {i}"
                );
            }
            assert!(
                Arc::ptr_eq(&frame.rgbd, &left),
                "rgbd is the left eye's view"
            );
            assert!(frame.eye.is_none());
            let red = |v: &Rgbd| v.color.channels[0].data()[0];
            assert!((red(&left) - 0.1 * i as f32).abs() < 1e-6);
            assert!((red(&right) - (0.5 + 0.1 * i as f32)).abs() < 1e-6);
        }
        assert!(f.poll(ms(150)).is_none(), "no new frame before 200 ms");
    }

    /// A right eye's file missing for frame N, or of the wrong size, stops the start naming
    /// the key and the path; a mono layout refuses `%e`; without `%e` a stereo rig's frames
    /// are one view.
    #[test]
    fn a_missing_or_misfit_eye_file_is_refused_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        write_eyes(dir.path(), 3);
        let open = || open_cfg(&stereo_config(dir.path(), "%e/c_%03d.exr", "%e/d_%03d.exr"));
        let right = |name: &str| dir.path().join("right").join(name);
        std::fs::rename(right("c_002.exr"), dir.path().join("aside.exr")).unwrap();
        let e = open().unwrap_err();
        let text = e.to_string();
        assert!(
            matches!(&e, ContentError::File { key: "content.color", path, .. } if *path == right("c_002.exr")),
            "{text}"
        );
        assert!(
            text.contains("not found") && text.contains("left/c_002.exr"),
            "{text}"
        );
        std::fs::rename(dir.path().join("aside.exr"), right("c_002.exr")).unwrap();
        // The right depth sequence one frame longer: the left's frame 3 is missing.
        let (c, d) = frame(0.9, 96, 96);
        write_depth(&right("d_003.exr"), &d).unwrap();
        let e = open().unwrap_err().to_string();
        assert!(
            e.starts_with("content.depth: ") && e.contains("left/d_003.exr: not found"),
            "{e}"
        );
        std::fs::remove_file(right("d_003.exr")).unwrap();
        // The right eye's first frame of another size than one eye's image.
        let (small, _) = frame(0.2, 64, 48);
        write_color(&right("c_000.exr"), &small).unwrap();
        let e = open().unwrap_err().to_string();
        assert!(
            e.starts_with("content.color: ")
                && e.contains("right/c_000.exr")
                && e.contains("64 x 48")
                && e.contains("one eye's image"),
            "{e}"
        );
        write_color(&right("c_000.exr"), &c).unwrap();
        assert!(open().is_ok());
        // %e on a mono layout (a config built by hand: parsing refuses it already).
        let mut mono = config(dir.path(), "c.exr", "d.exr", "");
        mono.content.color = Some(dir.path().join("%e/c_%03d.exr").display().to_string());
        mono.content.depth = Some(dir.path().join("%e/d_%03d.exr").display().to_string());
        let e = FileFrames::open(&mono.content, &mono.display)
            .unwrap_err()
            .to_string();
        assert!(e.contains("content.color") && e.contains("%e"), "{e}");
        // No %e on a stereo rig: one view.
        let one = stereo_config(dir.path(), "left/c_%03d.exr", "left/d_%03d.exr");
        let f = FileFrames::open(&one.content, &one.display).unwrap();
        let fr = f.poll(Timestamp(0)).unwrap();
        assert!(fr.eyes.is_none() && !f.status().stereo);
    }

    /// A view grid's files in `dir` (`c_<frame>_<row>_<col>.exr`, `d_...`; `eye`: in that
    /// eye's folder): view k of frame i has red `v0 + 0.1 i + 0.01 k` and depth 1 + that D.
    fn write_grid(dir: &Path, eye: Option<&str>, v0: f32, side: usize, frames: usize) {
        let dir = eye.map_or(dir.to_path_buf(), |e| dir.join(e));
        std::fs::create_dir_all(&dir).unwrap();
        for i in 0..frames {
            for k in 0..side * side {
                let (c, d) = frame(v0 + 0.1 * i as f32 + 0.01 * k as f32, 96, 96);
                let name = |kind: &str| {
                    dir.join(format!("{kind}_{i:03}_{:02}_{:02}.exr", k / side, k % side))
                };
                write_color(&name("c"), &c).unwrap();
                write_depth(&name("d"), &d).unwrap();
            }
        }
    }

    fn red(v: &Rgbd) -> f32 {
        v.color.channels[0].data()[0]
    }

    /// `content.views`: each frame brings every view of its grid, row by row, at its place
    /// over `view_span_mm` (x right, y down, from the centre), its `rgbd` the central view;
    /// a view file missing for one frame stops the start naming it.
    #[test]
    fn a_view_grid_is_every_view_of_each_frame() {
        let dir = tempfile::tempdir().unwrap();
        write_grid(dir.path(), None, 0.0, 3, 2);
        let extra = "views = 3\nview_span_mm = 6\nfps = 10";
        let cfg = config(dir.path(), "c_%03d_%v.exr", "d_%03d_%v.exr", extra);
        let f = FileFrames::open(&cfg.content, &cfg.display).unwrap();
        let st = f.status();
        assert_eq!((st.views, st.frames_in_sequence), (Some(3), 2), "{st:?}");
        let ms = |m: u64| Timestamp(m * 1_000_000);
        let first = f.poll(ms(0)).expect("the first frame");
        cached(&f, 2);
        let second = f.poll(ms(100)).expect("frame 1 at 100 ms");
        for (frame, i) in [(first, 0), (second, 1)] {
            let views = frame.views.clone().expect("a view grid");
            assert_eq!(views.len(), 9);
            for (k, v) in views.iter().enumerate() {
                let (row, col) = ((k / 3) as f32, (k % 3) as f32);
                let want = [(col - 1.0) * 3e-3, (row - 1.0) * 3e-3];
                assert!(
                    (v.position[0] - want[0]).abs() < 1e-7
                        && (v.position[1] - want[1]).abs() < 1e-7,
                    "view {k}: {:?} against {want:?}",
                    v.position
                );
                assert!(v.eye.is_none());
                let r = 0.1 * i as f32 + 0.01 * k as f32;
                assert!((red(&v.rgbd) - r).abs() < 1e-6, "frame {i} view {k}");
                assert!((v.rgbd.depth.data()[0] - (1.0 + r)).abs() < 1e-6);
            }
            assert!(
                Arc::ptr_eq(&frame.rgbd, &views[4].rgbd),
                "rgbd is the centre"
            );
            assert!(frame.eyes.is_none());
        }
        assert!(
            (red(&f.current()) - 0.14).abs() < 1e-6,
            "current is the centre"
        );
        drop(f);
        std::fs::remove_file(dir.path().join("c_001_02_01.exr")).unwrap();
        let e = FileFrames::open(&cfg.content, &cfg.display).unwrap_err();
        assert!(
            matches!(&e, ContentError::File { key: "content.color", path, .. }
                if path.ends_with("c_001_02_01.exr")),
            "{e}"
        );
    }

    /// With `%e` and `%v` each eye has its own grid: the frame's views are the left eye's
    /// then the right eye's, each tagged with its eye, and `eyes` their central views.
    #[test]
    fn each_eye_may_have_its_own_view_grid() {
        let dir = tempfile::tempdir().unwrap();
        write_grid(dir.path(), Some("left"), 0.0, 2, 1);
        write_grid(dir.path(), Some("right"), 0.5, 2, 1);
        let text = crate::config::EXAMPLE_SIM_RIG.replacen(
            "[display]",
            "[display]\nlayout = \"two-outputs\"",
            1,
        ) + &format!(
            "\n[content]\nsource = \"files\"\ncolor = {:?}\ndepth = {:?}\nviews = 2\n",
            dir.path().join("%e/c_%03d_%v.exr").display().to_string(),
            dir.path().join("%e/d_%03d_%v.exr").display().to_string()
        );
        let f = open_cfg(&RigConfig::parse(&text).unwrap()).unwrap();
        let frame = f.poll(Timestamp(0)).unwrap();
        let views = frame.views.clone().unwrap();
        assert_eq!(views.len(), 8);
        for (k, v) in views.iter().enumerate() {
            let (eye, v0) = if k < 4 {
                (Side::Left, 0.0)
            } else {
                (Side::Right, 0.5)
            };
            assert_eq!(v.eye, Some(eye), "view {k}");
            assert!(
                (red(&v.rgbd) - (v0 + 0.01 * (k % 4) as f32)).abs() < 1e-6,
                "view {k}"
            );
            // 10 mm by default: the corners 5 mm from the eye's centre.
            assert!(
                (v.position[0].abs() - 5e-3).abs() < 1e-7,
                "{:?}",
                v.position
            );
        }
        let [left, right] = frame.eyes.unwrap();
        assert!(Arc::ptr_eq(&left, &views[3].rgbd) && Arc::ptr_eq(&right, &views[7].rgbd));
        assert!(Arc::ptr_eq(&frame.rgbd, &left));
    }
}
