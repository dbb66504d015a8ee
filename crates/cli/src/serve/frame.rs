//! The stream content source's endpoints (`[content] source = "stream"`):
//!
//! | method | path | body | does |
//! |---|---|---|---|
//! | GET | `/frame/ring` | | the shared-memory ring's path and layout |
//! | POST | `/frame` | `{"slot": 0, "seq": 12}` | the frame written into ring slot 0 with sequence number 12 |
//! | PUT | `/frame?width=&height=&color=&depth=[&color_bytes=&near=&far=&seq=&app_time_ns=&eye=&view=]` | colour bytes, then depth bytes (`application/octet-stream`) | one frame, without the ring |
//!
//! `color` is `rgb8` or `rgba8` (sRGB) or `rgbf32` (linear, little-endian), the depth then
//! little-endian f32; or `png` (sRGB), `exr` or `pfm` (linear): the body is then a colour
//! image file of `color_bytes` bytes followed by a depth image file (EXR, PFM or 16-bit PNG),
//! both of the frame's size. `depth` says what the depth values are: `m`, `mm`, `D`, `gl`,
//! `gl-reversed`, `vulkan` (or `d3d`), `vulkan-reversed` (or `d3d-reversed`); a depth buffer
//! needs `near` and `far` (metres; `far=inf` for an infinite reversed-Z projection). The
//! answer is `{"seq": N}`, or the reason the frame was refused (422; 409 for a stale sequence
//! number or when the rig does not stream).
//!
//! On a stereo rig (`display.layout` side-by-side or two-outputs) `eye=left` or `eye=right`
//! makes the frame that eye's half of the pair numbered `seq` (required), shown once the
//! other half of the same `seq` arrived; without `eye` a frame of one eye's size is mono
//! (each eye's view synthesised) and one 2 x width wide is both eyes side by side. `eye` on a
//! mono rig, an unknown eye and a size that is none of these are refused (422).
//!
//! Light-field content (`content.views = N`): `view=ROW_COLUMN` (each 0 to N - 1) makes the
//! frame that view of frame `seq`'s grid (required; with `eye`, of that eye's grid), shown
//! once every view of the same `seq` arrived. A view on a rig without a grid, or outside it,
//! is refused (422); one older than the newest complete frame is stale (409).

use std::sync::Arc;

use axum::body::Body;
use axum::extract::{Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::Json;
use http_body_util::{BodyExt, Limited};
use serde::Deserialize;
use serde_json::json;

use dioptra_core::Side;
use dioptra_rig::content::stream::{ColorFormat, DepthKind, FrameDesc, FrameError, StreamFrames};
use dioptra_rig::RigState;

use super::error::ApiError;

fn refused(e: FrameError) -> ApiError {
    let status = match e {
        FrameError::Stale { .. }
        | FrameError::StaleHalf { .. }
        | FrameError::StaleView { .. }
        | FrameError::NotStreaming => StatusCode::CONFLICT,
        FrameError::MediaType => StatusCode::UNSUPPORTED_MEDIA_TYPE,
        FrameError::TooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
        FrameError::Timeout(_) => StatusCode::REQUEST_TIMEOUT,
        _ => StatusCode::UNPROCESSABLE_ENTITY,
    };
    ApiError::new(status, e.to_string())
}

fn not_streaming() -> ApiError {
    ApiError::new(
        StatusCode::CONFLICT,
        "the rig's content is not a stream: set [content] source = \"stream\"",
    )
}

pub async fn ring(State(s): State<Arc<RigState>>) -> Result<Json<serde_json::Value>, ApiError> {
    let stream = s
        .content()
        .source()
        .frame_ingest()
        .ok_or_else(not_streaming)?;
    Ok(Json(stream.ring_json()))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SlotBody {
    slot: usize,
    seq: u64,
}

pub async fn from_slot(
    State(s): State<Arc<RigState>>,
    b: axum::body::Bytes,
) -> Result<Json<serde_json::Value>, ApiError> {
    let stream = s
        .content()
        .source()
        .frame_ingest()
        .ok_or_else(not_streaming)?;
    let f: SlotBody = super::error::body(&b).inspect_err(|e| {
        stream.refuse(FrameError::Request(e.message().to_string()));
    })?;
    let now = s.clock().now();
    // Copying and converting a frame is CPU work: off the runtime's threads.
    let r = tokio::task::spawn_blocking(move || {
        let stream = s
            .content()
            .source()
            .frame_ingest()
            .ok_or(FrameError::NotStreaming)?;
        stream.submit_slot(f.slot, f.seq, now)
    })
    .await
    .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    r.map(|seq| Json(json!({ "seq": seq }))).map_err(refused)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameQuery {
    width: usize,
    height: usize,
    color: String,
    depth: String,
    near: Option<f32>,
    far: Option<f32>,
    seq: Option<u64>,
    app_time_ns: Option<u64>,
    /// With an encoded colour: the colour file's length, where the depth file starts.
    color_bytes: Option<usize>,
    /// A stereo rig: `left` or `right`, the eye whose half of pair `seq` this is.
    eye: Option<String>,
    /// Light-field content: `ROW_COLUMN`, the view of frame `seq`'s grid this is.
    view: Option<String>,
}

/// An encoded frame's body may hold this much more than the frame's f32 colour and depth
/// (file headers).
const ENCODED_SLACK: usize = 64 * 1024;

pub async fn put(
    State(s): State<Arc<RigState>>,
    query: Result<Query<FrameQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<serde_json::Value>, ApiError> {
    let Some(stream) = s.content().source().frame_ingest() else {
        return Err(not_streaming());
    };
    // Refusals before the frame is read are counted as the stream counts its own.
    let (desc, (eye, view), color_len, body) = match read_put(stream, query, &headers, body).await {
        Ok(r) => r,
        Err(e) => return Err(refused(stream.refuse(e))),
    };
    let now = s.clock().now();
    let r = tokio::task::spawn_blocking(move || {
        let stream = s
            .content()
            .source()
            .frame_ingest()
            .ok_or(FrameError::NotStreaming)?;
        // A color_bytes beyond the body leaves the depth file empty: refused as such.
        let split = color_len.min(body.len());
        stream.submit_part(&desc, eye, view, &body[..split], &body[split..], now)
    })
    .await
    .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    r.map(|seq| Json(json!({ "seq": seq }))).map_err(refused)
}

/// A `PUT /frame` request's frame: its description, its eye and view, where its colour ends,
/// and its body (bounded by the frame's size, which must be the display's).
async fn read_put(
    stream: &StreamFrames,
    query: Result<Query<FrameQuery>, axum::extract::rejection::QueryRejection>,
    headers: &HeaderMap,
    body: Body,
) -> Result<
    (
        FrameDesc,
        (Option<Side>, Option<usize>),
        usize,
        axum::body::Bytes,
    ),
    FrameError,
> {
    let Query(q) = query.map_err(|e| {
        FrameError::Request(format!(
            "{}; PUT /frame?width=W&height=H&color=rgb8&depth=m (or color=png&color_bytes=N)",
            e.body_text()
        ))
    })?;
    let color = ColorFormat::parse(&q.color).ok_or_else(|| {
        FrameError::Request(format!(
            "color={:?}: expected rgb8, rgba8 or rgbf32 (raw pixels), or png, exr or pfm (image files)",
            q.color
        ))
    })?;
    let depth = DepthKind::parse(&q.depth).ok_or_else(|| {
        FrameError::Request(format!(
            "depth={:?}: expected m, mm, D, gl, gl-reversed, vulkan (d3d) or vulkan-reversed (d3d-reversed)",
            q.depth
        ))
    })?;
    let eye = stream.parse_eye(q.eye.as_deref())?;
    let view = stream.parse_view(q.view.as_deref())?;
    let binary = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.trim().eq_ignore_ascii_case("application/octet-stream"));
    if !binary {
        return Err(FrameError::MediaType);
    }
    let px = q.width.saturating_mul(q.height);
    // Raw: exactly the frame's bytes. Files: at most f32 colour and depth and their headers.
    let (color_len, max) = match (color.bytes_per_px(), q.color_bytes) {
        (Some(bpp), None) => {
            let c = px.saturating_mul(bpp);
            (c, c.saturating_add(px.saturating_mul(4)))
        }
        (Some(_), Some(_)) => {
            return Err(FrameError::Request(format!(
                "color_bytes is for image files (color=png, exr or pfm), not color={}",
                q.color
            )))
        }
        (None, Some(c)) => (c, px.saturating_mul(16).saturating_add(ENCODED_SLACK)),
        (None, None) => {
            return Err(FrameError::Request(format!(
                "color={} sends the colour and depth as image files: color_bytes=N says where \
                 the colour file (its N bytes) ends and the depth file starts",
                q.color
            )))
        }
    };
    // The frame's own size bounds the body; a frame of the wrong size is refused unread.
    stream.side_by_side(q.width, q.height, eye)?;
    let limit = super::guard::BODY_TIMEOUT * 4;
    let body = match tokio::time::timeout(limit, Limited::new(body, max).collect()).await {
        Err(_) => return Err(FrameError::Timeout(limit.as_secs())),
        Ok(Err(e)) if e.is::<http_body_util::LengthLimitError>() => {
            return Err(FrameError::TooLarge {
                max,
                w: q.width,
                h: q.height,
            })
        }
        Ok(Err(e)) => {
            return Err(FrameError::Request(format!(
                "the body could not be read: {e}"
            )))
        }
        Ok(Ok(c)) => c.to_bytes(),
    };
    let desc = FrameDesc {
        width: q.width,
        height: q.height,
        color,
        depth,
        near: q.near,
        far: q.far,
        seq: q.seq,
        app_time_ns: q.app_time_ns,
    };
    Ok((desc, (eye, view), color_len, body))
}
