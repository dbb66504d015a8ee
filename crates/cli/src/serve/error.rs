//! The API's error answer, `{"error": "...", "key": "..."}` with its status, and the JSON body
//! parser that names the key that is wrong: what every endpoint and the guard answer with.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::de::DeserializeOwned;
use serde_json::json;

use dioptra_rig::ControlError;

/// A 4xx/5xx answer with a JSON body.
#[derive(Debug)]
pub struct ApiError {
    status: StatusCode,
    error: String,
    key: Option<String>,
}

impl ApiError {
    pub fn new(status: StatusCode, error: impl Into<String>) -> Self {
        ApiError {
            status,
            error: error.into(),
            key: None,
        }
    }
    /// What the answer says went wrong.
    pub fn message(&self) -> &str {
        &self.error
    }
    pub(super) fn at(mut self, key: &str) -> Self {
        self.key = Some(key.to_string());
        self
    }
}

impl From<ControlError> for ApiError {
    fn from(e: ControlError) -> Self {
        let status = match &e {
            ControlError::Conflict(_) => StatusCode::CONFLICT,
            ControlError::ShuttingDown => StatusCode::SERVICE_UNAVAILABLE,
            ControlError::Failed { .. } => StatusCode::INTERNAL_SERVER_ERROR,
        };
        ApiError::new(status, e.to_string())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut body = json!({ "error": self.error });
        if let Some(k) = self.key {
            body["key"] = json!(k);
        }
        (self.status, Json(body)).into_response()
    }
}

/// Parses a JSON body, naming the key that is wrong.
pub(super) fn body<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, ApiError> {
    if bytes.iter().all(u8::is_ascii_whitespace) {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "the request needs a JSON body",
        ));
    }
    let mut de = serde_json::Deserializer::from_slice(bytes);
    // Serde also reads a struct from an array of its fields; the API takes objects only.
    let first = bytes.iter().find(|b| !b.is_ascii_whitespace());
    if first.is_some_and(|b| *b != b'{')
        && serde_json::from_slice::<serde_json::Value>(bytes).is_ok()
    {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "expected a JSON object, e.g. {\"diopters\": 1.5}",
        ));
    }
    let r: Result<T, _> = serde_path_to_error::deserialize(&mut de);
    let v = r.map_err(|e| {
        let path = e.path().to_string();
        json_error(e.into_inner(), (path != ".").then_some(path))
    })?;
    // Trailing bytes after the value.
    de.end().map_err(|e| json_error(e, None))?;
    Ok(v)
}

fn json_error(inner: serde_json::Error, path: Option<String>) -> ApiError {
    let status = if inner.is_syntax() || inner.is_eof() {
        StatusCode::BAD_REQUEST
    } else {
        StatusCode::UNPROCESSABLE_ENTITY
    };
    let what = if status == StatusCode::BAD_REQUEST {
        format!("the body is not valid JSON: {inner}")
    } else {
        inner.to_string()
    };
    let err = ApiError::new(status, what);
    match path {
        Some(p) => err.at(&p),
        None => err,
    }
}
