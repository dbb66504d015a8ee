//! The winit side: the main thread opens the display and a borderless fullscreen window on
//! each chosen monitor (one, or one per eye), hands them to the daemon's thread and handles
//! window events until the daemon returns.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use dioptra_core::Side;

use super::error::WindowError;
use super::monitor::{choose_outputs, env_display_check, refresh_mismatch, MonitorInfo, Outputs};

/// A window on its monitor.
pub struct OutputWindow {
    pub window: Arc<winit::window::Window>,
    /// The monitor, for people (`monitor 1: "DP-2" 1920x1080 at (1920, 0)`).
    pub monitor: String,
    /// The monitor's size, physical pixels: what the surface should be.
    pub monitor_size: (u32, u32),
    /// The eye it shows (`layout = "two-outputs"`); `None`: the one window.
    pub eye: Option<Side>,
}

/// What the main thread hands the daemon's thread: the windows (one, or the left and the
/// right eye's).
pub struct WindowReady {
    pub outputs: Vec<OutputWindow>,
}

/// A message to the main thread's event loop.
#[derive(Debug)]
enum UserEvent {
    /// The daemon's thread has finished.
    DaemonDone,
}

/// Opens the display and a borderless fullscreen window on the chosen monitor on this (the
/// main) thread, runs `daemon` on a thread of its own with the window, and handles window
/// events here until it returns. Closing the window (or Escape in it) triggers `stop`, which
/// the daemon treats like Ctrl-C. Returns the daemon's result.
pub fn run_on_main_thread<F>(
    outputs: Outputs,
    stop: tokio_util::sync::CancellationToken,
    daemon: F,
) -> anyhow::Result<()>
where
    F: FnOnce(WindowReady) -> anyhow::Result<()> + Send + 'static,
{
    env_display_check()?;
    let event_loop = winit::event_loop::EventLoop::<UserEvent>::with_user_event()
        .build()
        .map_err(|e| WindowError::Open {
            detail: e.to_string(),
        })?;
    let mut app = App {
        outputs,
        stop,
        daemon: Some(Box::new(daemon)),
        proxy: event_loop.create_proxy(),
        thread: None,
        windows: Vec::new(),
        error: None,
        daemon_done: Arc::new(AtomicBool::new(false)),
    };
    event_loop
        .run_app(&mut app)
        .map_err(|e| anyhow::anyhow!("the window's event loop failed: {e}"))?;
    app.stop.cancel();
    let result = match app.thread.take() {
        Some(t) => t
            .join()
            .unwrap_or_else(|_| Err(anyhow::anyhow!("the daemon's thread panicked"))),
        None => Ok(()),
    };
    match app.error.take() {
        Some(e) => Err(e.into()),
        None => result,
    }
}

type DaemonFn = Box<dyn FnOnce(WindowReady) -> anyhow::Result<()> + Send>;

struct App {
    outputs: Outputs,
    stop: tokio_util::sync::CancellationToken,
    daemon: Option<DaemonFn>,
    proxy: winit::event_loop::EventLoopProxy<UserEvent>,
    thread: Option<std::thread::JoinHandle<anyhow::Result<()>>>,
    /// Held while the daemon runs, so the windows live as long as the event loop.
    windows: Vec<Arc<winit::window::Window>>,
    error: Option<WindowError>,
    daemon_done: Arc<AtomicBool>,
}

impl App {
    fn open(
        &mut self,
        event_loop: &winit::event_loop::ActiveEventLoop,
    ) -> Result<WindowReady, WindowError> {
        let monitors: Vec<winit::monitor::MonitorHandle> =
            event_loop.available_monitors().collect();
        let infos: Vec<MonitorInfo> = monitors
            .iter()
            .map(|m| MonitorInfo {
                name: m.name(),
                size: (m.size().width, m.size().height),
                position: (m.position().x, m.position().y),
            })
            .collect();
        let primary = event_loop
            .primary_monitor()
            .and_then(|p| monitors.iter().position(|m| *m == p));
        let chosen = choose_outputs(&infos, &self.outputs, primary)?;
        if let [(l, _), (r, _)] = chosen[..] {
            let rate = |i: usize| monitors[i].refresh_rate_millihertz();
            if let Some(warning) = refresh_mismatch(rate(l), rate(r)) {
                eprintln!("dioptra serve: warning: {warning}");
            }
        }
        let mut outputs = Vec::with_capacity(chosen.len());
        for (i, eye) in chosen {
            // The monitor's size and position as well as fullscreen: without a window manager
            // (which is what makes a window fullscreen on X11) the window still covers it.
            let (size, position) = (infos[i].size, infos[i].position);
            let attrs = winit::window::Window::default_attributes()
                .with_title(match eye {
                    Some(side) => format!("dioptra ({} eye)", side.as_str()),
                    None => "dioptra".into(),
                })
                .with_decorations(false)
                .with_inner_size(winit::dpi::PhysicalSize::new(size.0, size.1))
                .with_position(winit::dpi::PhysicalPosition::new(position.0, position.1))
                .with_fullscreen(Some(winit::window::Fullscreen::Borderless(Some(
                    monitors[i].clone(),
                ))));
            let window = event_loop
                .create_window(attrs)
                .map_err(|e| WindowError::Create(e.to_string()))?;
            window.set_cursor_visible(false);
            outputs.push(OutputWindow {
                window: Arc::new(window),
                monitor: format!("monitor {i}: {}", infos[i]),
                monitor_size: size,
                eye,
            });
        }
        Ok(WindowReady { outputs })
    }
}

impl winit::application::ApplicationHandler<UserEvent> for App {
    fn resumed(&mut self, event_loop: &winit::event_loop::ActiveEventLoop) {
        let Some(daemon) = self.daemon.take() else {
            return;
        };
        match self.open(event_loop) {
            Ok(ready) => {
                self.windows = ready.outputs.iter().map(|o| o.window.clone()).collect();
                let (proxy, done) = (self.proxy.clone(), self.daemon_done.clone());
                let spawned = std::thread::Builder::new()
                    .name("dioptra-daemon".into())
                    .spawn(move || {
                        let r = daemon(ready);
                        done.store(true, Ordering::SeqCst);
                        let _ = proxy.send_event(UserEvent::DaemonDone);
                        r
                    });
                match spawned {
                    Ok(t) => self.thread = Some(t),
                    Err(e) => {
                        self.error = Some(WindowError::Create(format!(
                            "cannot start the daemon's thread: {e}"
                        )));
                        event_loop.exit();
                    }
                }
            }
            Err(e) => {
                self.error = Some(e);
                event_loop.exit();
            }
        }
    }

    fn user_event(&mut self, event_loop: &winit::event_loop::ActiveEventLoop, e: UserEvent) {
        match e {
            UserEvent::DaemonDone => event_loop.exit(),
        }
    }

    fn window_event(
        &mut self,
        event_loop: &winit::event_loop::ActiveEventLoop,
        _id: winit::window::WindowId,
        event: winit::event::WindowEvent,
    ) {
        use winit::event::WindowEvent;
        use winit::keyboard::{Key, NamedKey};
        match event {
            WindowEvent::CloseRequested => self.stop.cancel(),
            WindowEvent::KeyboardInput { event, .. }
                if event.logical_key == Key::Named(NamedKey::Escape) =>
            {
                self.stop.cancel()
            }
            _ => {}
        }
        if self.daemon_done.load(Ordering::SeqCst) {
            event_loop.exit();
        }
    }
}
