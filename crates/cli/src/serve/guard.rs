//! The API's rules for who may talk to it, checked before any endpoint runs.
//!
//! A browser on the rig PC can reach `127.0.0.1`, so every request is treated as possibly
//! sent by a web page:
//! - `Host` must name the API itself (the listen address, `localhost`, `127.0.0.1` or
//!   `[::1]`, with the port): a page that rebinds its own DNS name to 127.0.0.1 is refused.
//! - An `Origin`, which browsers send with every POST and WebSocket upgrade, must be the
//!   API's own.
//! - A POST must say `Content-Type: application/json`, which no page can send without a
//!   CORS preflight, and the API grants none.
//! - With a token configured, every request carries `Authorization: Bearer <token>`.
//!
//! Over a Unix socket (which no browser reaches) only the token applies. Every refusal is
//! JSON, like the API's other errors.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use http_body_util::{BodyExt, LengthLimitError, Limited};

use super::error::ApiError;

/// Where the API ended up listening.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Listening {
    Tcp(SocketAddr),
    Unix(PathBuf),
}

/// The longest request body the API reads; its bodies are a few bytes of JSON.
pub const MAX_BODY: usize = 64 * 1024;
/// Longer request targets get 414: the API's paths are short.
pub const MAX_URI: usize = 2048;
/// Larger header sections get 431.
pub const MAX_HEADERS: usize = 8 * 1024;
/// A request's headers must arrive within this, and an idle connection is closed after it.
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(5);
/// A request's body must arrive within this.
pub const BODY_TIMEOUT: Duration = Duration::from_secs(5);

/// Who may talk to the API.
#[derive(Debug, Clone)]
pub struct Rules {
    /// Accepted `Host` values (lower case, with the port); `None`: any (a Unix socket).
    hosts: Option<Vec<String>>,
    /// The bearer token every request must carry.
    token: Option<String>,
}

impl Rules {
    pub fn new(listening: &Listening, token: Option<String>) -> Rules {
        let hosts = match listening {
            Listening::Unix(_) => None,
            Listening::Tcp(addr) => {
                let port = addr.port();
                let mut hosts = vec![
                    format!("localhost:{port}"),
                    format!("127.0.0.1:{port}"),
                    format!("[::1]:{port}"),
                ];
                if !addr.ip().is_unspecified() {
                    hosts.push(addr.to_string());
                }
                // Listening on every interface (which needs a token): any name of this
                // machine, on the right port; the token keeps pages out.
                if addr.ip().is_unspecified() {
                    hosts.push(format!("*:{port}"));
                }
                Some(hosts)
            }
        };
        Rules { hosts, token }
    }

    fn host_ok(&self, host: &str) -> bool {
        let Some(hosts) = &self.hosts else {
            return true;
        };
        let host = host.to_ascii_lowercase();
        hosts.iter().any(|h| match h.strip_prefix('*') {
            Some(port) => host.ends_with(port) && host.len() > port.len(),
            None => *h == host,
        })
    }

    /// An `Origin` is the API's own when it is `http://` and an accepted host.
    fn origin_ok(&self, origin: &str) -> bool {
        origin
            .strip_prefix("http://")
            .is_some_and(|host| self.host_ok(host))
    }

    fn token_ok(&self, headers: &HeaderMap) -> bool {
        let Some(token) = &self.token else {
            return true;
        };
        let given = headers
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .unwrap_or("");
        constant_time_eq(given.as_bytes(), token.as_bytes())
    }
}

/// Compares without stopping at the first difference, so timing does not reveal the token.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

fn refuse(status: StatusCode, error: impl Into<String>) -> Response {
    ApiError::new(status, error).into_response()
}

/// The middleware: checks `req` against the rules, reads a POST body (bounded in size and
/// time), then runs the endpoint.
pub async fn check(
    State(rules): State<std::sync::Arc<Rules>>,
    req: Request,
    next: Next,
) -> Response {
    let uri_len = req.uri().to_string().len();
    if uri_len > MAX_URI {
        return refuse(
            StatusCode::URI_TOO_LONG,
            format!("the request target is {uri_len} bytes; the API takes at most {MAX_URI}"),
        );
    }
    let header_bytes: usize = req
        .headers()
        .iter()
        .map(|(k, v)| k.as_str().len() + v.len() + 4)
        .sum();
    if header_bytes > MAX_HEADERS {
        return refuse(
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            format!("the headers are {header_bytes} bytes; the API takes at most {MAX_HEADERS}"),
        );
    }
    let headers = req.headers();
    if rules.hosts.is_some() {
        let host = headers.get(header::HOST).and_then(|v| v.to_str().ok());
        match host {
            Some(h) if rules.host_ok(h) => {}
            Some(h) => {
                return refuse(
                    StatusCode::FORBIDDEN,
                    format!(
                        "Host {h:?} is not this API's address: use localhost, 127.0.0.1 or \
                         [::1] with the port (a page on another site cannot use the API)"
                    ),
                )
            }
            None => return refuse(StatusCode::BAD_REQUEST, "the request has no Host header"),
        }
    }
    if let Some(origin) = headers.get(header::ORIGIN) {
        let origin = origin.to_str().unwrap_or("");
        if !rules.origin_ok(origin) {
            return refuse(
                StatusCode::FORBIDDEN,
                format!(
                    "requests from web pages are refused (Origin {origin:?}); \
                     drive the rig from a script, not a browser"
                ),
            );
        }
    }
    if !rules.token_ok(headers) {
        let mut r = refuse(
            StatusCode::UNAUTHORIZED,
            "this API needs its token: send Authorization: Bearer <api.token>",
        );
        r.headers_mut().insert(
            header::WWW_AUTHENTICATE,
            header::HeaderValue::from_static("Bearer"),
        );
        return r;
    }
    if req.method() != Method::POST {
        return next.run(req).await;
    }
    let json = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.split(';').next())
        .is_some_and(|mime| mime.trim().eq_ignore_ascii_case("application/json"));
    if !json {
        return refuse(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "a POST needs Content-Type: application/json (its body may be empty)",
        );
    }
    let declared = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|n| n > MAX_BODY as u64) {
        return refuse(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!("the body is larger than {MAX_BODY} bytes"),
        );
    }
    let (parts, body) = req.into_parts();
    let bytes = match read_body(body).await {
        Ok(b) => b,
        Err(r) => return r,
    };
    next.run(Request::from_parts(parts, Body::from(bytes)))
        .await
}

async fn read_body(body: Body) -> Result<Bytes, Response> {
    let read = Limited::new(body, MAX_BODY).collect();
    match tokio::time::timeout(BODY_TIMEOUT, read).await {
        Err(_) => Err(refuse(
            StatusCode::REQUEST_TIMEOUT,
            format!(
                "the body did not arrive within {} s",
                BODY_TIMEOUT.as_secs()
            ),
        )),
        Ok(Err(e)) if e.downcast_ref::<LengthLimitError>().is_some() => Err(refuse(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!("the body is larger than {MAX_BODY} bytes"),
        )),
        Ok(Err(e)) => Err(refuse(
            StatusCode::BAD_REQUEST,
            format!("cannot read the body: {e}"),
        )),
        Ok(Ok(collected)) => Ok(collected.to_bytes()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hosts_are_the_listen_address_and_loopback_names_with_the_port() {
        let r = Rules::new(&Listening::Tcp("127.0.0.1:7420".parse().unwrap()), None);
        for ok in [
            "localhost:7420",
            "LOCALHOST:7420",
            "127.0.0.1:7420",
            "[::1]:7420",
        ] {
            assert!(r.host_ok(ok), "{ok}");
        }
        for bad in [
            "evil.example",
            "evil.example:7420",
            "localhost",
            "127.0.0.1:80",
            "",
        ] {
            assert!(!r.host_ok(bad), "{bad}");
        }
        assert!(r.origin_ok("http://localhost:7420"));
        assert!(!r.origin_ok("null"));
        assert!(!r.origin_ok("http://evil.example"));
        assert!(!r.origin_ok("https://localhost:7420"));
        let any = Rules::new(&Listening::Tcp("0.0.0.0:7420".parse().unwrap()), None);
        assert!(any.host_ok("rig-pc.lab:7420"));
        assert!(!any.host_ok(":7420"));
        assert!(!any.host_ok("rig-pc.lab:80"));
        let unix = Rules::new(&Listening::Unix("/tmp/x.sock".into()), None);
        assert!(unix.host_ok("anything"));
    }

    #[test]
    fn the_token_is_compared_whole() {
        let r = Rules::new(
            &Listening::Unix("/tmp/x.sock".into()),
            Some("0123456789abcdef".into()),
        );
        let with = |v: &str| {
            let mut h = HeaderMap::new();
            h.insert(header::AUTHORIZATION, v.parse().unwrap());
            h
        };
        assert!(r.token_ok(&with("Bearer 0123456789abcdef")));
        assert!(!r.token_ok(&with("Bearer 0123456789abcde")));
        assert!(!r.token_ok(&with("Bearer 0123456789abcdeg")));
        assert!(!r.token_ok(&with("0123456789abcdef")));
        assert!(!r.token_ok(&HeaderMap::new()));
    }
}
