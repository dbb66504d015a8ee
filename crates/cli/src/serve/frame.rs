//! The stream content source's endpoints (`[content] source = "stream"`):
//!
//! | method | path | body | does |
//! |---|---|---|---|
//! | GET | `/frame/ring` | | the shared-memory ring's path and layout |
//! | POST | `/frame` | `{"slot": 0, "seq": 12}` | the frame written into ring slot 0 with sequence number 12 |
//! | PUT | `/frame?width=&height=&color=&depth=[&near=&far=&seq=&app_time_ns=]` | colour bytes, then depth bytes (`application/octet-stream`) | one frame, without the ring |
//!
//! `color` is `rgb8` or `rgba8` (sRGB) or `rgbf32` (linear, little-endian); `depth` is `m`,
//! `D`, `gl`, `gl-reversed`, `vulkan` (or `d3d`), `vulkan-reversed` (or `d3d-reversed`), as
//! little-endian f32; a depth buffer needs `near` and `far` (metres; `far=inf` for an infinite
//! reversed-Z projection). The answer is `{"seq": N}`, or the reason the frame was refused
//! (422; 409 for a stale sequence number or when the rig does not stream).

use std::sync::Arc;

use axum::body::Body;
use axum::extract::{Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::Json;
use http_body_util::{BodyExt, Limited};
use serde::Deserialize;
use serde_json::json;

use dioptra_rig::stream::{ColorFormat, DepthKind, FrameDesc, FrameError};
use dioptra_rig::RigState;

use super::api::ApiError;

fn refused(e: FrameError) -> ApiError {
    let status = match e {
        FrameError::Stale { .. } | FrameError::NotStreaming => StatusCode::CONFLICT,
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
    let stream = s.renderer.stream().ok_or_else(not_streaming)?;
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
    let f: SlotBody = super::api::body(&b)?;
    s.renderer.stream().ok_or_else(not_streaming)?;
    let now = s.clock.now();
    // Copying and converting a frame is CPU work: off the runtime's threads.
    let r = tokio::task::spawn_blocking(move || {
        let stream = s.renderer.stream().ok_or(FrameError::NotStreaming)?;
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
}

pub async fn put(
    State(s): State<Arc<RigState>>,
    query: Result<Query<FrameQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<serde_json::Value>, ApiError> {
    let Query(q) = query.map_err(|e| {
        ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!(
                "{}; PUT /frame?width=W&height=H&color=rgb8&depth=m",
                e.body_text()
            ),
        )
    })?;
    if s.renderer.stream().is_none() {
        return Err(not_streaming());
    }
    let color = ColorFormat::parse(&q.color).ok_or_else(|| {
        ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!("color={:?}: expected rgb8, rgba8 or rgbf32", q.color),
        )
    })?;
    let depth = DepthKind::parse(&q.depth).ok_or_else(|| {
        ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!(
                "depth={:?}: expected m, D, gl, gl-reversed, vulkan (d3d) or vulkan-reversed (d3d-reversed)",
                q.depth
            ),
        )
    })?;
    let binary = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.trim().eq_ignore_ascii_case("application/octet-stream"));
    if !binary {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "PUT /frame needs Content-Type: application/octet-stream",
        ));
    }
    let px = q.width.saturating_mul(q.height);
    let color_len = px.saturating_mul(color.bytes_per_px());
    let want = color_len.saturating_add(px.saturating_mul(4));
    // The frame's own size bounds the body; a frame of the wrong size is refused unread.
    let (dw, dh) = (s.cfg.display.width as usize, s.cfg.display.height as usize);
    if (q.width, q.height) != (dw, dh) {
        let e = FrameError::WrongSize {
            got_w: q.width,
            got_h: q.height,
            want_w: dw,
            want_h: dh,
        };
        return Err(refused(e));
    }
    let read = Limited::new(body, want).collect();
    let bytes = match tokio::time::timeout(super::guard::BODY_TIMEOUT * 4, read).await {
        Err(_) => {
            return Err(ApiError::new(
                StatusCode::REQUEST_TIMEOUT,
                "the frame did not arrive within 20 s",
            ))
        }
        Ok(Err(_)) => {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                format!("the body is larger than the frame's {want} bytes"),
            ))
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
    let now = s.clock.now();
    let r = tokio::task::spawn_blocking(move || {
        let stream = s.renderer.stream().ok_or(FrameError::NotStreaming)?;
        let split = color_len.min(bytes.len());
        stream.submit(&desc, &bytes[..split], &bytes[split..], now)
    })
    .await
    .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    r.map(|seq| Json(json!({ "seq": seq }))).map_err(refused)
}
