//! `[api]`: where the binary's HTTP API listens (TCP or a Unix socket) and the bearer token
//! it asks for; its defaults and checks. The API itself is the binary's.

use std::net::SocketAddr;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::config::error::{invalid, ConfigError};

/// `[api]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Api {
    /// TCP address; loopback unless `allow_remote` is true.
    pub listen: Option<String>,
    /// Unix socket path (created with 0600 permissions), instead of `listen`.
    pub unix: Option<PathBuf>,
    #[serde(default)]
    pub allow_remote: bool,
    /// A bearer token every request must carry (`Authorization: Bearer ...`); required with
    /// `allow_remote = true`. Prefer `token_file`, which keeps it out of the config.
    pub token: Option<String>,
    /// A file holding the token (surrounding whitespace ignored); instead of `token`.
    pub token_file: Option<PathBuf>,
}

impl Default for Api {
    fn default() -> Self {
        Api {
            listen: Some(DEFAULT_LISTEN.into()),
            unix: None,
            allow_remote: false,
            token: None,
            token_file: None,
        }
    }
}

pub const DEFAULT_LISTEN: &str = "127.0.0.1:7420";

/// Where the API listens, validated.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Listen {
    Tcp(SocketAddr),
    Unix(PathBuf),
}

impl Api {
    /// Where it listens, and its token.
    pub fn check(&self) -> Result<(), ConfigError> {
        self.listen()?;
        self.bearer_token()?;
        Ok(())
    }

    /// Where the API listens (`listen` or `unix`). A non-loopback address needs
    /// `api.allow_remote = true` and a token.
    pub fn listen(&self) -> Result<Listen, ConfigError> {
        let a = self;
        match (&a.listen, &a.unix) {
            (Some(_), Some(_)) => Err(invalid(
                "api",
                "give either listen (TCP) or unix (a socket path), not both",
            )),
            (None, Some(p)) => Ok(Listen::Unix(p.clone())),
            (listen, None) => {
                let s = listen.as_deref().unwrap_or(DEFAULT_LISTEN);
                let addr: SocketAddr = s.parse().map_err(|_| {
                    invalid(
                        "api.listen",
                        format!(
                            "{s:?} is not an address: expected IP:PORT, e.g. \"127.0.0.1:7420\""
                        ),
                    )
                })?;
                if !addr.ip().is_loopback() && !a.allow_remote {
                    return Err(invalid(
                        "api.listen",
                        format!(
                            "{addr} is reachable from other machines; use 127.0.0.1, or set \
                             api.allow_remote = true and an api.token_file if you mean it"
                        ),
                    ));
                }
                if !addr.ip().is_loopback() && a.token.is_none() && a.token_file.is_none() {
                    return Err(invalid(
                        "api.token_file",
                        format!(
                            "{addr} is reachable from other machines: the API needs a token \
                             (api.token_file, or api.token) that every request must carry"
                        ),
                    ));
                }
                Ok(Listen::Tcp(addr))
            }
        }
    }

    /// The bearer token, read from `api.token_file` or taken from `api.token`.
    pub fn bearer_token(&self) -> Result<Option<String>, ConfigError> {
        let a = self;
        let token = match (&a.token, &a.token_file) {
            (Some(_), Some(_)) => {
                return Err(invalid(
                    "api.token",
                    "give either token or token_file, not both",
                ))
            }
            (Some(t), None) => t.trim().to_string(),
            (None, Some(p)) => std::fs::read_to_string(p)
                .map_err(|e| {
                    invalid(
                        "api.token_file",
                        format!("cannot read {}: {e}", p.display()),
                    )
                })?
                .trim()
                .to_string(),
            (None, None) => return Ok(None),
        };
        // Short tokens can be guessed; a header value cannot hold control characters.
        if token.len() < 16 || !token.bytes().all(|b| b.is_ascii_graphic()) {
            let key = if a.token.is_some() {
                "api.token"
            } else {
                "api.token_file"
            };
            return Err(invalid(
                key,
                "the token must be at least 16 printable ASCII characters without spaces \
                 (e.g. the output of `openssl rand -hex 16`)",
            ));
        }
        Ok(Some(token))
    }
}
