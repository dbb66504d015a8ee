//! The control API: HTTP JSON commands and a WebSocket stream.
//!
//! | method | path | body | does |
//! |---|---|---|---|
//! | GET | `/status` | | mode, method, focus, devices, frames, latency, recording |
//! | POST | `/mode` | `{"mode": "varifocal"}` | varifocal, multifocal or lightfield |
//! | POST | `/method` | `{"method": "gather"}` | a render method that fits the mode, or `auto` (varifocal) |
//! | POST | `/focus` | `{"diopters": 1.5}` or `{"diopters": null}` | manual focus, or back to gaze (`diopters` is required) |
//! | POST | `/marker` | `{"marker": "stimulus_on"}` or `{"marker": {...}}`; or none | marks now: recorded, streamed, sent to LSL, and the marker patch toggled where it listens; answers its `host_ns`. Without a body: the patch toggle alone |
//! | POST | `/recording/start` | none, or `{"name": "vergence", "subject": "s01", "trial": 3}` | starts an MCAP recording in `recording.dir` |
//! | POST | `/recording/stop` | | finishes it; answers with its path and message count |
//! | POST | `/shutdown` | | parks the lens, finishes files, exits |
//! | POST | `/sim/{lens,gaze,sync}/{unplug,replug}` | | simulated devices only: pull or restore the cable |
//! | GET | `/stream` | | WebSocket: one JSON text message per gaze sample, focus change and frame |
//! | GET, POST, PUT | `/frame/ring`, `/frame` | | `[content] source = "stream"`: see [`super::frame`] |
//!
//! Errors are `{"error": "...", "key": "..."}` with a 4xx status: 400 for a body that is not
//! JSON, 422 for JSON of the wrong shape or a value out of range, 404 for an unknown path,
//! 405 for a wrong method, 409 when the request conflicts with the daemon's state.
//! Before any endpoint runs, [`super::guard`] refuses requests a web page could send (Host,
//! Origin, Content-Type) and checks the token.

use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::Response;
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Deserialize;
use serde_json::json;
use tokio::sync::broadcast;

use dioptra_rig::config::{methods, Method, Mode};
use dioptra_rig::{Control, RigState};

use super::error::{body, ApiError};

type Shared = RigState;

pub fn router(shared: Arc<Shared>) -> Router {
    Router::new()
        .route("/status", get(status))
        .route("/mode", post(set_mode))
        .route("/method", post(set_method))
        .route("/focus", post(set_focus))
        .route("/marker", post(marker))
        .route("/recording/start", post(recording_start))
        .route("/recording/stop", post(recording_stop))
        .route("/shutdown", post(shutdown))
        .route("/sim/{device}/{action}", post(sim_plug))
        .route("/stream", get(websocket))
        .route(
            "/frame",
            post(super::frame::from_slot).put(super::frame::put),
        )
        .route("/frame/ring", get(super::frame::ring))
        .fallback(|| async {
            ApiError::new(
                StatusCode::NOT_FOUND,
                "no such endpoint; see GET /status, POST /mode, /method, /focus, /marker, \
                 /recording/start, /recording/stop, /shutdown, GET /stream (WebSocket), and \
                 for a streaming rig POST/PUT /frame and GET /frame/ring",
            )
        })
        .method_not_allowed_fallback(|| async {
            ApiError::new(
                StatusCode::METHOD_NOT_ALLOWED,
                "wrong method for this endpoint: GET /status and /stream, POST for commands",
            )
        })
        .with_state(shared)
}

async fn status(State(s): State<Arc<Shared>>) -> Json<serde_json::Value> {
    Json(s.status_json())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ModeBody {
    mode: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MethodBody {
    method: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FocusBody {
    /// Diopters; `null` hands focus back to gaze. Required: `{}` says neither.
    #[serde(default, deserialize_with = "present")]
    diopters: Option<Option<f64>>,
}

/// A field that must be given, `null` included: `Some(None)` for `null`, `None` when absent.
fn present<'de, D: serde::Deserializer<'de>, T: Deserialize<'de>>(
    d: D,
) -> Result<Option<Option<T>>, D::Error> {
    Option::<T>::deserialize(d).map(Some)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MarkerBody {
    /// Text, or a JSON object of the experiment's own fields.
    marker: serde_json::Value,
}

/// The longest marker text, characters.
const MAX_MARKER_TEXT: usize = 1024;

async fn set_mode(
    State(s): State<Arc<Shared>>,
    b: Bytes,
) -> Result<Json<serde_json::Value>, ApiError> {
    let m: ModeBody = body(&b)?;
    let mode = Mode::parse(&m.mode).ok_or_else(|| {
        ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!(
                "unknown mode {:?}: expected varifocal, multifocal or lightfield",
                m.mode
            ),
        )
        .at("mode")
    })?;
    if mode == Mode::Multifocal && s.cfg().devices.sync.is_none() {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "multifocal mode needs a sync board, and the rig config has no [devices.sync]",
        )
        .at("mode"));
    }
    s.control(Control::Mode(mode)).await?;
    if mode != Mode::Varifocal {
        set_auto(&s, false);
    }
    // The method the new mode renders with (its default when the old one does not fit).
    let method = s.loop_status().method.map(|m| m.as_str());
    Ok(Json(json!({ "mode": mode.as_str(), "method": method })))
}

async fn set_method(
    State(s): State<Arc<Shared>>,
    b: Bytes,
) -> Result<Json<serde_json::Value>, ApiError> {
    let m: MethodBody = body(&b)?;
    let mode = s.loop_status().mode.unwrap_or(s.cfg().mode);
    let auto = m.method == "auto";
    let method = if auto {
        if mode != Mode::Varifocal {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                format!(
                    "auto plans varifocal frames; the rig is in {} mode (POST /mode first)",
                    mode.as_str()
                ),
            )
            .at("method"));
        }
        // The planner chooses per frame; the scheduler runs the mode's default method.
        Method(dioptra_sched::RenderMethod::default_for(mode.sched()))
    } else {
        Method::parse(&m.method).ok_or_else(|| {
            ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                format!(
                    "unknown method {:?}: expected auto or one of {}",
                    m.method,
                    methods()
                ),
            )
            .at("method")
        })?
    };
    if let Some(why) = method.unavailable(mode) {
        return Err(ApiError::new(StatusCode::CONFLICT, why).at("method"));
    }
    s.control(Control::Method(method)).await?;
    set_auto(&s, auto);
    Ok(Json(
        json!({ "method": if auto { "auto" } else { method.as_str() } }),
    ))
}

/// Turns the planner on or off; off, its last choice no longer describes the frames.
fn set_auto(s: &Shared, auto: bool) {
    s.render().set_auto(auto);
}

async fn set_focus(
    State(s): State<Arc<Shared>>,
    b: Bytes,
) -> Result<Json<serde_json::Value>, ApiError> {
    let f: FocusBody = body(&b)?;
    let Some(diopters) = f.diopters else {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "diopters is required: a focus the lens reaches (see /status focus.focus_range_d) \
             for manual focus, or null to hand focus back to gaze",
        )
        .at("diopters"));
    };
    if diopters.is_some() {
        lens_must_be_up(&s)?;
    }
    // The focus the lens range reaches through the optics map (the identity: the range).
    let d = match (diopters, s.optics().focus_range_d()) {
        (None, _) => None,
        (Some(_), None) => {
            let ranges: Vec<String> = s
                .optics()
                .focus_ranges_d()
                .iter()
                .zip(["left", "right"])
                .map(|([a, b], eye)| format!("{eye} {a}..{b} D"))
                .collect();
            return Err(ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                format!(
                    "the two eyes' lenses reach no focus in common ({}: each lens's range \
                     through its eye's optics map); manual focus needs one both reach",
                    ranges.join(", ")
                ),
            )
            .at("diopters"));
        }
        // f32 round trips through the map: a range end asked for is inside.
        (Some(d), Some([lo, hi]))
            if d.is_finite() && (f64::from(lo) - 1e-4..=f64::from(hi) + 1e-4).contains(&d) =>
        {
            Some(d as f32)
        }
        (Some(d), Some([lo, hi])) => {
            let r = s.cfg().optics.lens_range;
            return Err(ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                format!(
                    "focus {d} D is outside what the lens reaches, {lo}..{hi} D (optics.lens_range {}..{} D through the optics map: {})",
                    r.min,
                    r.max,
                    s.optics().of(dioptra_rig::devices::LensId::FIRST).describe()
                ),
            )
            .at("diopters"));
        }
    };
    s.control(Control::ManualFocus(d)).await?;
    let mode = s.loop_status().mode.unwrap_or(s.cfg().mode);
    let effect = match (d, mode) {
        (None, _) => "focus follows gaze again",
        (Some(_), Mode::Multifocal) => {
            "the varifocal lens holds this power; the multifocal planes (optics.planes) are \
             unchanged"
        }
        (Some(_), _) => "the lens holds this power; gaze no longer moves it",
    };
    Ok(Json(json!({ "manual_focus_d": d, "effect": effect })))
}

/// 503 while a required lens (`devices.lens.required`, true for a real port; each eye's with
/// a lens per eye) is not connected: a focus would be held, not shown, until it is back.
fn lens_must_be_up(s: &Shared) -> Result<(), ApiError> {
    let snap = s.devices().registry().snapshot();
    let down = s.cfg().devices.list().into_iter().find_map(|d| {
        let st = snap.get(&d.name)?;
        (d.name.starts_with("lens") && d.required && st.state != dioptra_rig::devices::State::Ok)
            .then(|| (d, st.clone()))
    });
    let Some((lens, st)) = down else {
        return Ok(());
    };
    Err(ApiError::new(
        StatusCode::SERVICE_UNAVAILABLE,
        format!(
            "the lens ({}.port = \"{}\") is {}: {}; the focus would not be shown until it is \
             back (the daemon reconnects it)",
            lens.section,
            lens.port,
            serde_json::to_value(st.state)
                .ok()
                .and_then(|v| v.as_str().map(str::to_string))
                .unwrap_or_default(),
            st.last_error.as_deref().unwrap_or("no answer yet")
        ),
    )
    .at("diopters"))
}

/// Marks this moment for the experiment (`{"marker": text or object}`): the marker goes
/// into the recording (`/marker`), onto `/stream` and to LSL's marker outlet, with the host
/// time it arrived; and where `display.marker_patch.toggle_on` names "api-marker", the patch
/// toggles at the next presented frame, so a photodiode sees the event. Without a body: the
/// patch toggle alone (409 when no patch listens for it).
async fn marker(
    State(s): State<Arc<Shared>>,
    b: Bytes,
) -> Result<Json<serde_json::Value>, ApiError> {
    use dioptra_rig::config::MarkerEvent;
    let patch = s.cfg().display.marker_patch.as_ref();
    let toggles = patch.is_some_and(|p| p.toggle_on.contains(&MarkerEvent::ApiMarker));
    if b.iter().all(u8::is_ascii_whitespace) {
        if patch.is_none() {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                "the rig draws no marker patch: add display.marker_patch = { corner = \"top-left\", size = 8, toggle_on = [\"api-marker\"] }, or send {\"marker\": \"...\"} to record and stream a marker",
            ));
        }
        if !toggles {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                "display.marker_patch.toggle_on does not name \"api-marker\", so an API marker would not show: add it there",
            ));
        }
        let n = s.display().marker().api_marker();
        return Ok(Json(json!({ "markers": n })));
    }
    let m: MarkerBody = body(&b)?;
    let ok = match &m.marker {
        serde_json::Value::String(t) => !t.is_empty() && t.chars().count() <= MAX_MARKER_TEXT,
        serde_json::Value::Object(_) => true,
        _ => false,
    };
    if !ok {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!(
                "a marker is a text of 1 to {MAX_MARKER_TEXT} characters or a JSON object, \
                 e.g. {{\"marker\": \"stimulus_on\"}} or {{\"marker\": {{\"trial\": 3}}}}"
            ),
        )
        .at("marker"));
    }
    let t = s.lab_marker(m.marker);
    let n = toggles.then(|| s.display().marker().api_marker());
    Ok(Json(json!({ "host_ns": t.0, "markers": n })))
}

async fn recording_start(
    State(s): State<Arc<Shared>>,
    b: Bytes,
) -> Result<Json<serde_json::Value>, ApiError> {
    // The body is optional: nothing, `{}`, or the experiment's names.
    let meta: dioptra_rig::RecordingMeta = if b.iter().all(u8::is_ascii_whitespace) {
        Default::default()
    } else {
        body(&b)?
    };
    if let Some((key, why)) = meta.invalid() {
        return Err(ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, why).at(key));
    }
    let path = s.start_recording_mid_run(&meta).await?;
    Ok(Json(json!({ "recording": path })))
}

async fn recording_stop(State(s): State<Arc<Shared>>) -> Result<Json<serde_json::Value>, ApiError> {
    let stats = s.stop_recording().await?;
    Ok(Json(json!({
        "path": stats.path,
        "messages": stats.messages,
        "dropped": stats.dropped,
    })))
}

/// Simulated rigs only: unplug or replug a simulated device, as its cable would.
async fn sim_plug(
    State(s): State<Arc<Shared>>,
    Path((device, action)): Path<(String, String)>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let sims = s.devices().sims();
    let lenses = &s.cfg().devices.lens;
    let plug = sims.and_then(|sims| match device.as_str() {
        "gaze" => sims.gaze.as_ref(),
        "sync" => sims.sync.as_ref(),
        "photodiode" => sims.photodiode.as_ref(),
        // `lens`, or `lens_left` and `lens_right` with a lens per eye.
        name => (0..lenses.count())
            .find(|&i| lenses.name(i) == name)
            .and_then(|i| sims.lenses.get(i)?.as_ref()),
    });
    let plug = plug.map(|slot| &slot.plug);
    let Some(plug) = plug else {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            format!("{device:?} is not a simulated device of this rig (lens, or lens_left and lens_right, gaze, sync or photodiode with port = \"sim\")"),
        )
        .at("device"));
    };
    match action.as_str() {
        "unplug" => plug.unplug(),
        "replug" => plug.replug(),
        _ => {
            return Err(ApiError::new(
                StatusCode::NOT_FOUND,
                format!("unknown action {action:?}: expected unplug or replug"),
            )
            .at("action"))
        }
    }
    Ok(Json(
        json!({ "device": device, "plugged": plug.is_plugged() }),
    ))
}

async fn shutdown(State(s): State<Arc<Shared>>) -> (StatusCode, Json<serde_json::Value>) {
    tracing::info!("shutdown requested through the API");
    s.cancel().cancel();
    (
        StatusCode::ACCEPTED,
        Json(json!({ "status": "stopping: parking the lens and finishing files" })),
    )
}

async fn websocket(State(s): State<Arc<Shared>>, ws: WebSocketUpgrade) -> Response {
    let rx = s.websocket().subscribe();
    let cancel = s.cancel().clone();
    ws.on_upgrade(move |socket| forward(socket, rx, cancel))
}

async fn forward(
    mut socket: WebSocket,
    mut rx: broadcast::Receiver<Arc<str>>,
    cancel: tokio_util::sync::CancellationToken,
) {
    loop {
        let msg = tokio::select! {
            _ = cancel.cancelled() => break,
            m = rx.recv() => m,
            incoming = socket.recv() => match incoming {
                // The client closed, or went away.
                None | Some(Err(_)) | Some(Ok(Message::Close(_))) => return,
                Some(Ok(_)) => continue,
            },
        };
        let text = match msg {
            Ok(t) => t.to_string(),
            Err(broadcast::error::RecvError::Lagged(n)) => {
                json!({ "type": "lagged", "skipped": n }).to_string()
            }
            Err(broadcast::error::RecvError::Closed) => break,
        };
        if socket.send(Message::Text(text.into())).await.is_err() {
            return;
        }
    }
    let _ = socket.send(Message::Close(None)).await;
}
