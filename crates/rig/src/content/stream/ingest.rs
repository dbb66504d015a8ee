//! Frames in: the stream source ([`StreamFrames`]) takes a frame from the shared-memory ring
//! or `PUT /frame`, decodes it, files a part of one among its frame's parts, and keeps the
//! newest complete one for the display; what it counts is its [`StreamStatus`].

use std::path::Path;
use std::sync::{Arc, Mutex};

use dioptra_core::{lock, DepthMap, Plane, RgbImage, Rgbd, Side, Timestamp};
use serde::Serialize;

use super::assembly::{
    drop_parts, next_seq, part_of, parts_name, per_eye, Decoded, Pairing, Part, Pending,
};
use super::decode::{decode_frame_into, ColorFormat, DepthKind, FrameDesc, FrameError};
use super::pool::Planes;
use crate::content::frame::Arrival;
use crate::content::ring::{
    eye_of_code, layout_json, Ring, RingHeader, SlotHeader, EYE_CODES, RING_HEADER, RING_MAGIC,
    RING_SLOTS, RING_VERSION, SLOT_FIELDS, SLOT_HEADER,
};

fn count_refusal(st: &mut StreamStatus, e: FrameError) -> FrameError {
    *st.refused.entry(e.kind()).or_default() += 1;
    st.last_error = Some(e.to_string());
    st.refusing = Some(e.config_key());
    e
}

/// What `/status` shows under `content` for a stream.
#[derive(Debug, Clone, Default, Serialize)]
pub struct StreamStatus {
    pub source: &'static str,
    /// A stereo rig: frames may be one eye's half, a pair shown once both arrived.
    pub stereo: bool,
    /// Frames accepted (on a stereo rig a pair counts once, when its second half arrives).
    pub received: u64,
    /// Accepted frames the display took up.
    pub shown: u64,
    /// Accepted frames a newer one replaced before the display took them up.
    pub replaced: u64,
    /// One eye's halves accepted (stereo rig).
    pub halves_received: u64,
    /// Light-field content: views of a grid accepted (`content.views`).
    pub views_received: u64,
    /// Halves (and views of a grid) waiting for the rest of their frame's.
    pub halves_waiting: u64,
    /// Halves whose partner never came: dropped, never shown, when a newer pair or frame
    /// completed (or more than `MAX_WAITING` sequence numbers waited).
    pub halves_dropped: u64,
    /// Frames refused, by reason; the newest reason in `last_error`.
    pub refused: std::collections::BTreeMap<&'static str, u64>,
    pub last_error: Option<String>,
    /// Sequence number of the newest frame (or half) accepted, and of the one on show.
    pub newest_seq: Option<u64>,
    pub on_show_seq: Option<u64>,
    /// Host time (ns) the newest accepted frame arrived, and its application time.
    pub newest_received_ns: Option<u64>,
    pub newest_app_time_ns: Option<u64>,
    /// How old the newest accepted frame is, ms (at the time of asking).
    pub newest_age_ms: Option<f64>,
    pub ring: Option<String>,
    /// Light-field content: views per side of a frame's grid.
    pub views: Option<usize>,
    #[serde(skip)]
    newest_at: Option<std::time::Instant>,
    /// The newest frame was refused, and the config key its reason is about (the next frame
    /// accepted clears it).
    #[serde(skip)]
    pub refusing: Option<&'static str>,
}

/// The stream source: the newest accepted frame, waiting for the display.
pub struct StreamFrames {
    /// One eye's image (the display's on a mono rig).
    size: (usize, usize),
    stereo: bool,
    /// Light-field content: views per side and each view's position (metres, row by row).
    grid: Option<(usize, Vec<[f32; 2]>)>,
    pub(super) ring: Option<Ring>,
    pending: Mutex<Option<Pending>>,
    pub(super) status: Mutex<StreamStatus>,
    /// Locked only while `status` is.
    pairing: Mutex<Pairing>,
    /// Memory of frames done with, for the next ones.
    pub(super) planes: Planes,
    /// The same for side-by-side frames (2 x width), before they are split.
    wide_planes: Planes,
    /// Notified at each accepted frame: the loop takes it up then.
    pub(super) arrivals: Arc<tokio::sync::Notify>,
    /// The views on show (given back for reuse when the next are taken up), and how many
    /// frames the loop has been handed.
    pub(super) on_show: Mutex<(Vec<Arc<Rgbd>>, u64)>,
}

impl std::fmt::Debug for StreamFrames {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StreamFrames")
            .field("size", &self.size)
            .field("stereo", &self.stereo)
            .finish_non_exhaustive()
    }
}

impl StreamFrames {
    /// A stream of `width` x `height` frames with its ring at `ring` (`None`: `PUT /frame`
    /// only).
    pub fn open(width: usize, height: usize, ring: Option<&Path>) -> std::io::Result<Self> {
        Self::with_eyes(width, height, false, ring)
    }

    /// [`StreamFrames::open`] for a rig whose display is `stereo` (`width` x `height` is then
    /// one eye's image): frames may be one eye's half or both eyes side by side.
    pub fn with_eyes(
        width: usize,
        height: usize,
        stereo: bool,
        ring: Option<&Path>,
    ) -> std::io::Result<Self> {
        let header = RingHeader::for_eyes(width, height, stereo);
        let ring = ring.map(|p| Ring::create(p, header)).transpose()?;
        Ok(StreamFrames {
            size: (width, height),
            stereo,
            grid: None,
            status: Mutex::new(StreamStatus {
                source: "stream",
                stereo,
                ring: ring.as_ref().map(|r| r.path.display().to_string()),
                ..Default::default()
            }),
            ring,
            pending: Mutex::new(None),
            pairing: Mutex::new(Pairing::default()),
            planes: Planes::new(width * height),
            wide_planes: Planes::new(2 * width * height),
            arrivals: Arc::new(tokio::sync::Notify::new()),
            on_show: Mutex::new((Vec::new(), 0)),
        })
    }

    /// The stream with light-field content: frames may be a grid of `views` x `views` views
    /// over a square of `span_mm`, each sent on its own naming its view.
    pub fn with_view_grid(mut self, views: usize, span_mm: f64) -> Result<Self, String> {
        let positions = dioptra_sim::scene::light_field_positions(views, (span_mm * 1e-3) as f32)
            .map_err(|e| e.to_string())?;
        self.grid = Some((views, positions));
        lock(&self.status).views = Some(views);
        Ok(self)
    }

    /// Views per eye of a grid (1 without one).
    fn per_eye(&self) -> usize {
        per_eye(self.grid.as_ref())
    }

    /// The view `PUT /frame?view=ROW_COLUMN` names (`None`: a whole frame), or why it is
    /// refused.
    pub fn parse_view(&self, view: Option<&str>) -> Result<Option<usize>, FrameError> {
        let Some(name) = view else {
            return Ok(None);
        };
        let n = self.grid.as_ref().map_or(0, |(n, _)| *n);
        let parsed = name
            .split_once('_')
            .and_then(|(r, c)| Some((r.parse::<usize>().ok()?, c.parse::<usize>().ok()?)));
        match parsed {
            Some((r, c)) if r < n && c < n => self.check_view(Some(r * n + c)),
            _ if n == 0 => self.check_view(Some(0)),
            _ => Err(FrameError::View(format!(
                "view={name:?}: expected ROW_COLUMN, each 0 to {} (content.views = {n})",
                n - 1
            ))),
        }
    }

    /// A view is refused on a rig without a grid, and past its grid.
    fn check_view(&self, view: Option<usize>) -> Result<Option<usize>, FrameError> {
        match (view, &self.grid) {
            (None, _) => Ok(None),
            (Some(_), None) => Err(FrameError::View(
                "this rig's content is one view a frame: send frames without a view, or set \
                 content.views for light-field content"
                    .into(),
            )),
            (Some(v), Some((n, _))) if v >= n * n => Err(FrameError::View(format!(
                "view {v}: the grid has views 0 to {} (content.views = {n})",
                n * n - 1
            ))),
            (Some(v), _) => Ok(Some(v)),
        }
    }

    /// The frame shown before any arrives: black at optical infinity.
    pub fn placeholder(&self) -> Rgbd {
        let (w, h) = self.size;
        let zero = || Plane::from_vec(w, h, vec![0.0; w * h]).expect("sized plane");
        Rgbd::new(
            RgbImage::from_planes(zero(), zero(), zero()).expect("equal planes"),
            DepthMap::from_diopters(zero()).expect("0 D is valid"),
        )
        .expect("equal sizes")
    }

    /// `GET /frame/ring`: where the ring is and its layout.
    pub fn ring_json(&self) -> serde_json::Value {
        match &self.ring {
            None => serde_json::json!({
                "path": null,
                "width": self.size.0,
                "height": self.size.1,
                "stereo": self.stereo,
                "views": self.grid.as_ref().map(|(n, _)| n),
            }),
            Some(r) => serde_json::json!({
                "path": r.path.display().to_string(),
                "magic": String::from_utf8_lossy(RING_MAGIC),
                "version": RING_VERSION,
                "slots": RING_SLOTS,
                "width": self.size.0,
                "height": self.size.1,
                "stereo": self.stereo,
                "views": self.grid.as_ref().map(|(n, _)| n),
                "header_bytes": RING_HEADER,
                "slot_header_bytes": SLOT_HEADER,
                "slot_bytes": r.slot_bytes,
                "slot_header": layout_json(SLOT_FIELDS),
                "eyes": EYE_CODES.iter().map(|&(n, c)| (n.to_string(), c.into()))
                    .collect::<serde_json::Map<_, _>>(),
            }),
        }
    }

    /// The eye `PUT /frame?eye=` names (`None`: no eye), or why it is refused.
    pub fn parse_eye(&self, eye: Option<&str>) -> Result<Option<Side>, FrameError> {
        let Some(name) = eye else {
            return Ok(None);
        };
        let side = Side::parse(name).ok_or_else(|| {
            FrameError::Eye(format!(
                "eye={name:?}: expected left or right (or no eye: a mono frame, or on a \
                 stereo rig both eyes side by side)"
            ))
        })?;
        self.check_eye(Some(side))
    }

    /// `eye` is refused on a rig that shows one image.
    fn check_eye(&self, eye: Option<Side>) -> Result<Option<Side>, FrameError> {
        match eye {
            Some(e) if !self.stereo => Err(FrameError::Eye(format!(
                "eye {}: this rig shows one image (display.layout = \"one\"); send frames \
                 without an eye",
                e.as_str()
            ))),
            _ => Ok(eye),
        }
    }

    /// Whether a frame of `width` x `height` for `eye` is both eyes side by side (a stereo
    /// rig's 2 x width frame without an eye), or why its size is refused.
    pub fn side_by_side(
        &self,
        width: usize,
        height: usize,
        eye: Option<Side>,
    ) -> Result<bool, FrameError> {
        let (w, h) = self.size;
        if (width, height) == (w, h) {
            return Ok(false);
        }
        if self.stereo && eye.is_none() && (width, height) == (2 * w, h) {
            return Ok(true);
        }
        Err(if self.stereo {
            FrameError::WrongEyeSize {
                eye,
                got_w: width,
                got_h: height,
                want_w: w,
                want_h: h,
            }
        } else {
            FrameError::WrongSize {
                got_w: width,
                got_h: height,
                want_w: w,
                want_h: h,
            }
        })
    }

    /// A frame from `PUT /frame` (no eye: mono, or on a stereo rig possibly side by side).
    pub fn submit(
        &self,
        desc: &FrameDesc,
        color: &[u8],
        depth: &[u8],
        now: Timestamp,
    ) -> Result<u64, FrameError> {
        self.submit_eye(desc, None, color, depth, now)
    }

    /// A frame from `PUT /frame?eye=`: `eye`'s half of a pair, or (`None`) a whole frame.
    pub fn submit_eye(
        &self,
        desc: &FrameDesc,
        eye: Option<Side>,
        color: &[u8],
        depth: &[u8],
        now: Timestamp,
    ) -> Result<u64, FrameError> {
        self.submit_part(desc, eye, None, color, depth, now)
    }

    /// A frame from `PUT /frame?eye=&view=`: a view of a grid (`view`; `eye`'s own grid on a
    /// stereo rig), `eye`'s half of a pair, or (both `None`) a whole frame.
    pub fn submit_part(
        &self,
        desc: &FrameDesc,
        eye: Option<Side>,
        view: Option<usize>,
        color: &[u8],
        depth: &[u8],
        now: Timestamp,
    ) -> Result<u64, FrameError> {
        let t0 = std::time::Instant::now();
        let r = self
            .check_eye(eye)
            .and_then(|eye| Ok((eye, self.check_view(view)?)))
            .and_then(|(eye, view)| Ok((self.check_seq(desc.seq, part_of(eye, view))?, eye, view)))
            .and_then(|(seq, eye, view)| Ok((seq, self.decode(desc, eye, view, color, depth)?)));
        self.accept(r, desc.app_time_ns, now, t0)
    }

    /// Decodes a frame for `eye` (and `view`): a side-by-side one split into the two eyes'.
    fn decode(
        &self,
        desc: &FrameDesc,
        eye: Option<Side>,
        view: Option<usize>,
        color: &[u8],
        depth: &[u8],
    ) -> Result<Decoded, FrameError> {
        if let Some(v) = view {
            let (w, h) = self.size;
            if (desc.width, desc.height) != (w, h) {
                return Err(FrameError::View(format!(
                    "the view's frame is {}x{}; a view is one eye's image, {w}x{h}",
                    desc.width, desc.height
                )));
            }
            let frame = decode_frame_into(desc, color, depth, self.size, &self.planes)?;
            return Ok(Decoded::View(eye, v, frame));
        }
        if self.side_by_side(desc.width, desc.height, eye)? {
            let (w, h) = self.size;
            let wide = decode_frame_into(desc, color, depth, (2 * w, h), &self.wide_planes)?;
            return Ok(Decoded::Pair(self.split(wide)?));
        }
        let frame = decode_frame_into(desc, color, depth, self.size, &self.planes)?;
        Ok(match eye {
            Some(e) => Decoded::Half(e, frame),
            None => Decoded::Whole(frame),
        })
    }

    /// A side-by-side frame's left and right halves.
    fn split(&self, wide: Rgbd) -> Result<[Rgbd; 2], FrameError> {
        let (w, h) = self.size;
        let Rgbd { color, depth } = wide;
        let [r, g, b] = color.channels;
        let mut halves: [Vec<Plane>; 2] = [Vec::new(), Vec::new()];
        let bad = |e: dioptra_core::InputError| FrameError::Invalid(e.to_string());
        for plane in [r, g, b, depth.into_plane()] {
            let src = plane.into_vec();
            let (mut left, mut right) = (self.planes.take(), self.planes.take());
            for ((row, l), r) in src
                .chunks_exact(2 * w.max(1))
                .zip(left.chunks_exact_mut(w.max(1)))
                .zip(right.chunks_exact_mut(w.max(1)))
            {
                l.copy_from_slice(&row[..w]);
                r.copy_from_slice(&row[w..]);
            }
            self.wide_planes.give(src);
            halves[0].push(Plane::from_vec(w, h, left).map_err(bad)?);
            halves[1].push(Plane::from_vec(w, h, right).map_err(bad)?);
        }
        let view = |planes: Vec<Plane>| -> Result<Rgbd, FrameError> {
            let [r, g, b, d]: [Plane; 4] = planes
                .try_into()
                .map_err(|_| FrameError::Invalid("four planes".into()))?;
            let color = RgbImage::from_planes(r, g, b).map_err(bad)?;
            Rgbd::new(color, DepthMap::from_diopters(d).map_err(bad)?).map_err(bad)
        };
        let [left, right] = halves;
        Ok([view(left)?, view(right)?])
    }

    /// A frame the application wrote into ring slot `slot` with sequence number `seq`.
    pub fn submit_slot(&self, slot: usize, seq: u64, now: Timestamp) -> Result<u64, FrameError> {
        let t0 = std::time::Instant::now();
        let r = self.read_slot(slot, seq);
        let app = r.as_ref().ok().and_then(|(_, _, a)| *a);
        self.accept(r.map(|(s, f, _)| (s, f)), app, now, t0)
    }

    fn read_slot(&self, slot: usize, seq: u64) -> Result<(u64, Decoded, Option<u64>), FrameError> {
        self.read_slot_then(slot, seq, || {})
    }

    /// [`StreamFrames::read_slot`], calling `copied` once the slot's bytes are copied (a test
    /// rewrites the slot there, as an application that does not wait for the answer might).
    pub(super) fn read_slot_then(
        &self,
        slot: usize,
        seq: u64,
        copied: impl FnOnce(),
    ) -> Result<(u64, Decoded, Option<u64>), FrameError> {
        let ring = self.ring.as_ref().ok_or_else(|| {
            FrameError::Invalid("this daemon has no shared-memory ring: use PUT /frame".into())
        })?;
        if slot >= RING_SLOTS {
            return Err(FrameError::Invalid(format!(
                "slot {slot}: the ring has slots 0 to {}",
                RING_SLOTS - 1
            )));
        }
        let base = RING_HEADER + slot * ring.slot_bytes;
        let in_slot = ring.seq(slot);
        if in_slot != seq {
            return Err(FrameError::Invalid(format!(
                "slot {slot} holds sequence number {in_slot}, not {seq} (write the sequence \
                 number last, after the frame)"
            )));
        }
        let mut bytes = [0u8; SLOT_HEADER];
        bytes.copy_from_slice(&ring.read(base, SLOT_HEADER));
        let h = SlotHeader::decode(&bytes);
        let eye = eye_of_code(h.eye).ok_or_else(|| {
            FrameError::Eye(format!(
                "slot {slot}: unknown eye {} (0 none, 1 left, 2 right)",
                h.eye
            ))
        })?;
        let eye = self.check_eye(eye)?;
        let view = self.check_view(h.view.checked_sub(1).map(|v| v as usize))?;
        let seq = self.check_seq(Some(seq), part_of(eye, view))?;
        let color = ColorFormat::from_code(h.color_format).ok_or_else(|| {
            FrameError::Invalid(format!(
                "slot {slot}: unknown colour format {}",
                h.color_format
            ))
        })?;
        let depth = DepthKind::from_code(h.depth_kind).ok_or_else(|| {
            FrameError::Invalid(format!("slot {slot}: unknown depth kind {}", h.depth_kind))
        })?;
        let desc = FrameDesc {
            width: h.width as usize,
            height: h.height as usize,
            color,
            depth,
            near: Some(h.near),
            far: Some(h.far),
            seq: Some(seq),
            app_time_ns: Some(h.app_time_ns).filter(|&t| t != 0),
        };
        let (cb, db) = (h.color_bytes as usize, h.depth_bytes as usize);
        let room = ring.slot_bytes - SLOT_HEADER;
        if cb.checked_add(db).is_none_or(|total| total > room) {
            return Err(FrameError::Invalid(format!(
                "slot {slot}: {cb} colour and {db} depth bytes do not fit its {room}"
            )));
        }
        let color_bytes = ring.read(base + SLOT_HEADER, cb);
        let depth_bytes = ring.read(base + SLOT_HEADER + cb, db);
        copied();
        if ring.seq(slot) != seq {
            return Err(FrameError::Torn(slot));
        }
        let frame = self.decode(&desc, eye, view, &color_bytes, &depth_bytes)?;
        Ok((seq, frame, desc.app_time_ns))
    }

    /// The sequence number a frame (or a part of one) gets: its own if new, or the next.
    fn check_seq(&self, seq: Option<u64>, part: Option<Part>) -> Result<u64, FrameError> {
        let st = lock(&self.status);
        let pairing = lock(&self.pairing);
        next_seq(st.newest_seq, &pairing, seq, part)
    }

    fn accept(
        &self,
        r: Result<(u64, Decoded), FrameError>,
        app_time_ns: Option<u64>,
        now: Timestamp,
        started: std::time::Instant,
    ) -> Result<u64, FrameError> {
        // Ready once copied and converted: the request's arrival plus that work.
        let arrival = Arrival {
            arrived: now,
            ready: now + started.elapsed(),
        };
        let mut st = lock(&self.status);
        let (seq, decoded) = match r {
            Err(e) => return Err(count_refusal(&mut st, e)),
            Ok(r) => r,
        };
        let mut pairing = lock(&self.pairing);
        // Two requests may race past check_seq: the newer wins. A part must fit the parts
        // of its frame already in (a grid's view with an eye, or without, as the first).
        let per_eye = self.per_eye();
        let misfit = decoded.part().and_then(|part| {
            let (parts, _) = part.place(per_eye);
            let first = pairing.waiting.get(&seq).map(|w| w.parts)?;
            (first != parts).then(|| {
                FrameError::View(format!(
                    "frame {seq}'s parts so far are {}, and this one is {}: send each eye's \
                     views with eye= (or none with it), for every view of a frame alike",
                    parts_name(first),
                    parts_name(parts)
                ))
            })
        });
        if let Some(e) = next_seq(st.newest_seq, &pairing, Some(seq), decoded.part())
            .err()
            .or(misfit)
        {
            drop(pairing);
            self.give_back(decoded);
            return Err(count_refusal(&mut st, e));
        }
        st.newest_seq = Some(st.newest_seq.map_or(seq, |n| n.max(seq)));
        st.refusing = None;
        st.newest_received_ns = Some(now.0);
        st.newest_at = Some(std::time::Instant::now());
        st.newest_app_time_ns = app_time_ns;
        let complete = match decoded {
            Decoded::Whole(f) => Some((Arc::new(f), None, None)),
            Decoded::Pair([l, r]) => {
                let l = Arc::new(l);
                Some((l.clone(), Some([l, Arc::new(r)]), None))
            }
            Decoded::Half(eye, f) => {
                st.halves_received += 1;
                pairing.add_part(
                    self.grid.as_ref(),
                    &self.planes,
                    &mut st.halves_dropped,
                    seq,
                    Part {
                        eye: Some(eye),
                        view: None,
                    },
                    f,
                )
            }
            Decoded::View(eye, v, f) => {
                st.views_received += 1;
                pairing.add_part(
                    self.grid.as_ref(),
                    &self.planes,
                    &mut st.halves_dropped,
                    seq,
                    Part { eye, view: Some(v) },
                    f,
                )
            }
        };
        if let Some((frame, eyes, views)) = complete {
            // Parts older than a complete frame can no longer be shown.
            let newer = pairing.waiting.split_off(&(seq + 1));
            let older = std::mem::replace(&mut pairing.waiting, newer);
            for (_, parts) in older {
                st.halves_dropped += drop_parts(&self.planes, parts);
            }
            pairing.floor = Some(seq);
            st.received += 1;
            let old = lock(&self.pending).replace(Pending {
                frame,
                eyes,
                views,
                seq,
                arrival,
            });
            if let Some(old) = old {
                self.give_pending(old);
                st.replaced += 1;
            }
            self.arrivals.notify_one();
        }
        st.halves_waiting = pairing.halves_waiting();
        Ok(seq)
    }

    fn give_back(&self, d: Decoded) {
        match d {
            Decoded::Whole(f) | Decoded::Half(_, f) | Decoded::View(_, _, f) => {
                self.planes.give_frame(Arc::new(f))
            }
            Decoded::Pair(p) => p
                .into_iter()
                .for_each(|f| self.planes.give_frame(Arc::new(f))),
        }
    }

    fn give_pending(&self, p: Pending) {
        // A pair's `frame` is one of its eyes' views, a grid's one of its views: each image
        // is given back once.
        for image in p.images() {
            self.planes.give_frame(image);
        }
    }

    /// A frame the display is done with: its memory is reused for the next ones when no one
    /// else holds it.
    pub fn recycle(&self, frame: Arc<Rgbd>) {
        self.planes.give_frame(frame);
    }

    /// Counts a frame refused before it was read (a request that does not describe one, or
    /// one of the wrong size), as [`StreamFrames::submit`] counts its own refusals.
    pub fn refuse(&self, e: FrameError) -> FrameError {
        count_refusal(&mut lock(&self.status), e)
    }

    /// The newest frame not yet taken up by the display, if any, and when it arrived (a pair:
    /// the left eye's view; `Content::poll` gives both).
    pub fn take_new(&self) -> Option<(Arc<Rgbd>, Arrival)> {
        self.take_pending().map(|p| (p.frame, p.arrival))
    }

    pub(super) fn take_pending(&self) -> Option<Pending> {
        let p = lock(&self.pending).take()?;
        let mut st = lock(&self.status);
        st.shown += 1;
        st.on_show_seq = Some(p.seq);
        Some(p)
    }

    pub fn status(&self) -> StreamStatus {
        let mut st = lock(&self.status).clone();
        st.newest_age_ms = st.newest_at.map(|t| t.elapsed().as_secs_f64() * 1e3);
        st
    }
}
