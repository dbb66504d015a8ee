//! `dioptra serve --config rig.toml`: the display-control daemon: the rig runtime
//! ([`dioptra_rig::Rig`]: device tasks, loop, render worker, recordings) with the HTTP API
//! ([`api`]) on top, and the display window ([`window`]) when the config asks for one.
//!
//! Everything stops through the rig's one cancellation token (Ctrl-C, `POST /shutdown`, the
//! window closing): the loop carries out the scheduler's shutdown, the lens task parks the
//! lens, the sync task stops the sequence, and the recording is finished, before
//! [`Daemon::wait`] returns.
//!
//! Threads: with the headless sink the tokio runtime runs on the main thread. With
//! `display.kind = "window"` the main thread belongs to winit's event loop
//! ([`window::run_on_main_thread`]) and the runtime runs on a thread of its own.

pub mod api;
mod error;
mod frame;
pub mod guard;
mod head_limit;
pub mod systemd;
pub mod window;

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use dioptra_rig::config::{Listen, RigConfig, SinkKind};
use dioptra_rig::render::rgbd::RgbdRenderer;
use dioptra_rig::{Rig, RigSetup, RigState, ShutdownReport};
use tokio_util::sync::CancellationToken;

pub use guard::Listening;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The rig config (TOML); see crates/cli/examples/rig-sim.toml.
    #[arg(long)]
    pub config: PathBuf,
}

pub fn run(args: Args) -> Result<()> {
    let cfg = RigConfig::load(&args.config)
        .with_context(|| format!("in the rig config {}", args.config.display()))?;
    for note in cfg.notices() {
        eprintln!("dioptra serve: note: {note}");
    }
    let stop = CancellationToken::new();
    match cfg.display.kind {
        SinkKind::Headless => serve_blocking(cfg, None, stop),
        // The window's event loop takes this (the main) thread; the daemon runs on another.
        SinkKind::Window => {
            let outputs = window::Outputs::of(&cfg.display);
            window::run_on_main_thread(outputs, stop.clone(), move |ready| {
                serve_blocking(cfg, Some(ready), stop)
            })
        }
    }
}

/// Runs the daemon until Ctrl-C, `POST /shutdown` or `stop`.
fn serve_blocking(
    cfg: RigConfig,
    window: Option<window::WindowReady>,
    stop: CancellationToken,
) -> Result<()> {
    crate::common::rig_runtime()?.block_on(async {
        let mut setup = RigSetup::new(cfg);
        if let Some(w) = window {
            // The renderer first: the window draws with its GPU device when it has one.
            let c = setup.cfg.clone();
            let renderer = tokio::task::spawn_blocking(move || {
                RgbdRenderer::new(&c.render, &c.eye, &c.display, &c.optics)
            })
            .await
            .context("the renderer's start failed")?
            .context("cannot start the renderer")?;
            let placement =
                dioptra_rig::display::placement::PlacementConfig::from_display(&setup.cfg.display);
            let panels = dioptra_rig::display::panel_images(&setup.cfg)
                .context("the eyes' images on their panels")?;
            let sink = window::WindowSink::new(w, renderer.gpu_context(), placement, panels)
                .context("cannot draw to the display window")?;
            setup.sink = Some(Box::new(sink));
            setup.renderer = Some(Arc::new(renderer));
        }
        let service = systemd::Service::from_env(&mut setup);
        let daemon = Daemon::start(setup).await?;
        match daemon.listening() {
            Listening::Tcp(a) => eprintln!("dioptra serve: API on http://{a}"),
            Listening::Unix(p) => eprintln!("dioptra serve: API on unix:{}", p.display()),
        }
        service.ready(daemon.listening(), daemon.shared().cancel().clone());
        let status = daemon.shared().status_json();
        eprintln!("dioptra serve: display {}", status["display"]["sink"]);
        tokio::spawn(frame_budget(daemon.shared().clone()));
        let signals = Signals::new().context("cannot listen for SIGTERM, SIGINT and SIGHUP")?;
        tokio::spawn(on_signals(signals, daemon.shared().clone(), stop));
        let shared = daemon.shared().clone();
        let report = daemon.wait().await;
        let v = shared.status_json();
        eprintln!("dioptra serve: {}", shutdown_counts(&v));
        eprintln!("{}", report.summary());
        if report.ok() {
            Ok(())
        } else {
            anyhow::bail!(
                "the daemon did not stop cleanly: {}",
                report.problems().join("; ")
            )
        }
    })
}

/// The shutdown's one line of counts: distinct frames apart from the refreshes that repeated
/// one (a late frame).
fn shutdown_counts(v: &serde_json::Value) -> String {
    let up = v["uptime_s"].as_f64().unwrap_or(0.0);
    let d = &v["display"];
    let distinct = d["distinct_frames"].as_u64().unwrap_or(0);
    format!(
        "{} gaze samples, {} lens commands, {} distinct frames shown ({:.1}/s) and {} refreshes that repeated a frame, in {:.1} s",
        v["counts"]["gaze_samples"],
        v["counts"]["lens_commands"],
        distinct,
        if up > 0.0 { distinct as f64 / up } else { 0.0 },
        d["repeated_refreshes"].as_u64().unwrap_or(0),
        up
    )
}

/// Says at start whether a frame fits its period: the cost model's prediction at the rig's
/// size, method and backend, or, where it has none, the first render measured. A frame that
/// does not fit is a warning naming the keys that would make it fit.
async fn frame_budget(shared: Arc<RigState>) {
    use dioptra_rig::render::budget::{predict, Prediction};
    let cfg = shared.cfg().clone();
    let backend = shared.render().renderer().backend_status()["backend"]
        .as_str()
        .unwrap_or("cpu")
        .to_string();
    let p = match predict(&cfg, &backend) {
        Ok(p) => p,
        Err(why) => {
            // Measured instead: the first render the rig makes.
            let cancel = shared.cancel().clone();
            let first = async {
                loop {
                    if let Some(ms) = shared.render().status_now().last_render_ms {
                        return ms;
                    }
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            };
            let ms = tokio::select! {
                _ = cancel.cancelled() => return,
                ms = first => ms,
            };
            Prediction::measured(
                &cfg,
                ms,
                &format!(
                    "{why}, so the first frame was timed: {} in {} mode, {} eye(s) of {} x {} px on the {backend}",
                    cfg.method.as_str(),
                    cfg.mode.as_str(),
                    dioptra_rig::render::budget::eyes(&cfg),
                    cfg.display.width,
                    cfg.display.height
                ),
            )
        }
    };
    let line = p.line();
    if p.fits() {
        eprintln!("dioptra serve: {line}");
    } else {
        tracing::warn!("{line}");
    }
}

/// SIGTERM (systemd, `kill`), SIGINT (Ctrl-C) and SIGHUP (the terminal closed).
struct Signals {
    term: tokio::signal::unix::Signal,
    int: tokio::signal::unix::Signal,
    hup: tokio::signal::unix::Signal,
}

impl Signals {
    fn new() -> std::io::Result<Signals> {
        use tokio::signal::unix::{signal, SignalKind};
        Ok(Signals {
            term: signal(SignalKind::terminate())?,
            int: signal(SignalKind::interrupt())?,
            hup: signal(SignalKind::hangup())?,
        })
    }

    async fn next(&mut self) -> &'static str {
        tokio::select! {
            _ = self.term.recv() => "SIGTERM",
            _ = self.int.recv() => "SIGINT",
            _ = self.hup.recv() => "SIGHUP",
        }
    }
}

/// The first signal (or the window closing) stops the daemon as `POST /shutdown` does. A
/// second one during the shutdown exits as soon as the lens is parked, without waiting for
/// the rest (the recording keeps what its closed chunks hold).
async fn on_signals(mut signals: Signals, shared: Arc<RigState>, window_closed: CancellationToken) {
    let cancel = shared.cancel().clone();
    tokio::select! {
        name = signals.next() => {
            eprintln!("dioptra serve: stopping ({name}): parking the lens, finishing files; a second signal exits once the lens is parked");
        }
        _ = window_closed.cancelled() => eprintln!("dioptra serve: stopping (window closed)"),
        _ = cancel.cancelled() => {}
    }
    cancel.cancel();
    let name = signals.next().await;
    eprintln!("dioptra serve: {name} during shutdown: exiting once the lens is parked");
    let limit = shared.devices().settings().park_timeout + Duration::from_secs(1);
    let parked = tokio::time::timeout(limit, shared.devices().lens_parked().cancelled())
        .await
        .is_ok();
    if parked {
        eprintln!("dioptra serve: lens parked; exiting without finishing the shutdown");
    } else {
        eprintln!("dioptra serve: the lens did not park within {limit:?}; exiting");
    }
    std::process::exit(130);
}

/// A running daemon: the rig and its API server.
pub struct Daemon {
    rig: Rig,
    listening: Listening,
    server: tokio::task::JoinHandle<Result<(), std::io::Error>>,
}

impl Daemon {
    /// Starts the rig as its config describes it (headless sink); the API is listening when
    /// this returns.
    #[cfg(test)]
    pub async fn start_config(cfg: RigConfig) -> Result<Daemon> {
        Self::start(RigSetup::new(cfg)).await
    }

    /// Starts the rig of `setup` and the API; the API is listening when this returns.
    pub async fn start(setup: RigSetup) -> Result<Daemon> {
        let listen = setup.cfg.api.listen()?;
        let token = setup.cfg.api.bearer_token()?;
        // A required device whose path does not exist ends the start before its task could
        // log it as lost and retrying.
        dioptra_rig::devices::required_present(&setup.cfg.devices.list())
            .map_err(|why| anyhow::anyhow!("{why}"))?;
        let rig = Rig::start(setup).await?;
        let shared = rig.state().clone();
        // A required device (every real port, unless the config says otherwise) must be
        // there before the daemon takes commands.
        let devices = shared.cfg().devices.list();
        let timeout = shared.devices().settings().link.connect_timeout;
        if let Err(why) =
            dioptra_rig::devices::wait_for_required(shared.devices().registry(), &devices, timeout)
                .await
        {
            shared.cancel().cancel();
            let _ = rig.wait().await;
            anyhow::bail!("{why}");
        }
        let c = shared.cancel().clone();
        let bound = match listen {
            Listen::Tcp(addr) => tokio::net::TcpListener::bind(addr)
                .await
                .with_context(|| {
                    format!("cannot listen on {addr} (api.listen); is another daemon running?")
                })
                .and_then(|l| Ok((Listening::Tcp(l.local_addr()?), ApiListener::Tcp(l)))),
            Listen::Unix(path) => {
                bind_unix(&path).map(|l| (Listening::Unix(path), ApiListener::Unix(l)))
            }
        };
        let (listening, listener) = match bound {
            Ok(b) => b,
            Err(e) => {
                // The rig is running: stop it (and park the lens) before saying why.
                shared.cancel().cancel();
                let _ = rig.wait().await;
                return Err(e);
            }
        };
        let rules = Arc::new(guard::Rules::new(&listening, token));
        let app = api::router(shared.clone())
            .layer(axum::middleware::from_fn_with_state(rules, guard::check));
        let server = tokio::spawn(async move {
            match listener {
                ApiListener::Tcp(l) => serve_api(l, app, c).await,
                ApiListener::Unix(l) => serve_api(l, app, c).await,
            }
        });
        Ok(Daemon {
            rig,
            listening,
            server,
        })
    }

    pub fn listening(&self) -> &Listening {
        &self.listening
    }
    pub fn shared(&self) -> &Arc<RigState> {
        self.rig.state()
    }
    #[cfg(test)]
    pub fn cancel_token(&self) -> CancellationToken {
        self.rig.state().cancel().clone()
    }

    /// Waits until the daemon is told to stop, then stops the rig (the lens parked, the
    /// recording finished) and the API server.
    pub async fn wait(self) -> ShutdownReport {
        let Daemon {
            rig,
            listening,
            server,
        } = self;
        let mut report = rig.wait().await;
        match tokio::time::timeout(Duration::from_secs(5), server).await {
            Ok(Ok(Ok(()))) => {}
            Ok(Ok(Err(e))) => report
                .task_errors
                .push(format!("the API server failed: {e}")),
            Ok(Err(e)) => report
                .task_errors
                .push(format!("the API server task failed: {e}")),
            Err(_) => report
                .task_errors
                .push("the API server did not stop within 5 s".into()),
        }
        if let Listening::Unix(p) = &listening {
            let _ = std::fs::remove_file(p);
        }
        report
    }
}

enum ApiListener {
    Tcp(tokio::net::TcpListener),
    Unix(tokio::net::UnixListener),
}

/// Serves the API until `cancel`: HTTP/1 with WebSocket upgrades, headers bounded in time
/// (which also closes idle connections) and size. Open connections finish their request and
/// close; WebSocket streams end on the same token.
async fn serve_api<L: axum::serve::Listener>(
    mut listener: L,
    app: axum::Router,
    cancel: CancellationToken,
) -> Result<(), std::io::Error> {
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(hyper_util::rt::TokioTimer::new())
        .header_read_timeout(guard::HEADER_TIMEOUT)
        .max_buf_size(head_limit::HYPER_BUF)
        .max_headers(head_limit::HYPER_MAX_HEADERS);
    let mut connections = tokio::task::JoinSet::new();
    loop {
        let io = tokio::select! {
            _ = cancel.cancelled() => break,
            (io, _) = listener.accept() => io,
        };
        let service = hyper_util::service::TowerToHyperService::new(app.clone());
        let conn = http
            .serve_connection(
                hyper_util::rt::TokioIo::new(head_limit::HeadLimited::new(io)),
                service,
            )
            .with_upgrades();
        let cancel = cancel.clone();
        connections.spawn(async move {
            let mut conn = std::pin::pin!(conn);
            tokio::select! {
                _ = conn.as_mut() => return,
                _ = cancel.cancelled() => {}
            }
            conn.as_mut().graceful_shutdown();
            let _ = conn.await;
        });
        while connections.try_join_next().is_some() {}
    }
    while connections.join_next().await.is_some() {}
    Ok(())
}

/// Binds a Unix socket readable and writable by its owner only.
fn bind_unix(path: &std::path::Path) -> Result<tokio::net::UnixListener> {
    use std::os::unix::fs::{FileTypeExt, PermissionsExt};
    if let Ok(meta) = std::fs::symlink_metadata(path) {
        if meta.file_type().is_socket() {
            // A stale socket of a daemon that did not clean up.
            std::fs::remove_file(path)
                .with_context(|| format!("cannot remove the stale socket {}", path.display()))?;
        } else {
            anyhow::bail!(
                "{} exists and is not a socket; choose another api.unix path",
                path.display()
            );
        }
    }
    let l = tokio::net::UnixListener::bind(path)
        .with_context(|| format!("cannot listen on {} (api.unix)", path.display()))?;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600))
        .with_context(|| format!("cannot make {} private (0600)", path.display()))?;
    Ok(l)
}

#[cfg(test)]
mod tests;
