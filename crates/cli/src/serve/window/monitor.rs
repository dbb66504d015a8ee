//! Where the windows go: whether there is a display, which monitor (`display.monitor`; with
//! `layout = "two-outputs"`, `display.monitor_left` and `display.monitor_right`), and whether
//! the surface the system gave is the monitor's size where `display.scale = "exact"` needs it.

use dioptra_core::Side;
use dioptra_rig::config::{Display, DisplayLayout, MonitorChoice, Scale};

use super::error::WindowError;

/// Which monitors the windows go on: one window (`display.monitor`, default the primary), or
/// a window per eye (`layout = "two-outputs"`: `display.monitor_left`, `monitor_right`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outputs {
    One(Option<MonitorChoice>),
    PerEye {
        left: Option<MonitorChoice>,
        right: Option<MonitorChoice>,
    },
}

impl Outputs {
    pub fn of(d: &Display) -> Outputs {
        match d.layout {
            DisplayLayout::TwoOutputs => Outputs::PerEye {
                left: d.monitor_left.clone(),
                right: d.monitor_right.clone(),
            },
            DisplayLayout::One | DisplayLayout::SideBySide => Outputs::One(d.monitor.clone()),
        }
    }
}

/// The monitor (index in `monitors`) of each window, with its eye (`None`: the one window).
/// A window per eye needs each eye's monitor named, and two different ones; the errors name
/// the key and list what is there.
pub fn choose_outputs(
    monitors: &[MonitorInfo],
    outputs: &Outputs,
    primary: Option<usize>,
) -> Result<Vec<(usize, Option<Side>)>, WindowError> {
    let chosen = |key: &'static str, choice: Option<&MonitorChoice>| {
        choose_monitor(monitors, choice, primary)
            .map_err(|detail| WindowError::Monitor { key, detail })
    };
    match outputs {
        Outputs::One(choice) => Ok(vec![(chosen("display.monitor", choice.as_ref())?, None)]),
        Outputs::PerEye { left, right } => {
            let mut out = Vec::with_capacity(2);
            for (key, choice, side) in [
                ("display.monitor_left", left, Side::Left),
                ("display.monitor_right", right, Side::Right),
            ] {
                let Some(choice) = choice else {
                    return Err(WindowError::Monitor {
                        key,
                        detail: "layout = \"two-outputs\" needs each eye's monitor".into(),
                    });
                };
                out.push((chosen(key, Some(choice))?, Some(side)));
            }
            if out[0].0 == out[1].0 {
                return Err(WindowError::Monitor {
                    key: "display.monitor_right",
                    detail: format!(
                        "{} is monitor {}, the one display.monitor_left ({}) is: two outputs \
                         need two monitors",
                        right.as_ref().map_or(String::new(), |c| c.to_string()),
                        out[1].0,
                        left.as_ref().map_or(String::new(), |c| c.to_string()),
                    ),
                });
            }
            Ok(out)
        }
    }
}

/// What is said at start when the two windows' monitors refresh at different rates
/// (millihertz, as the system reports them; `None`: not reported, nothing said).
pub fn refresh_mismatch(left: Option<u32>, right: Option<u32>) -> Option<String> {
    let (l, r) = (left?, right?);
    if l == r {
        return None;
    }
    Some(format!(
        "display.monitor_left refreshes at {:.3} Hz and display.monitor_right at {:.3} Hz: \
         both windows are presented in the same pass of the presenter, each at its own \
         monitor's vsync, so the pair is paced by the slower monitor ({:.3} Hz) and the faster \
         one shows some frames twice; use two monitors at one rate",
        f64::from(l) / 1000.0,
        f64::from(r) / 1000.0,
        f64::from(l.min(r)) / 1000.0
    ))
}

/// Whether a display server is named in the environment. winit would say the same in its own
/// words; this names the rig config's alternative.
pub fn check_display_env(
    wayland_display: Option<&str>,
    wayland_socket: Option<&str>,
    x11_display: Option<&str>,
) -> Result<(), WindowError> {
    let set = |v: Option<&str>| v.is_some_and(|s| !s.is_empty());
    if set(wayland_display) || set(wayland_socket) || set(x11_display) {
        Ok(())
    } else {
        Err(WindowError::NoDisplay)
    }
}

pub(super) fn env_display_check() -> Result<(), WindowError> {
    let var = |k| std::env::var(k).ok();
    check_display_env(
        var("WAYLAND_DISPLAY").as_deref(),
        var("WAYLAND_SOCKET").as_deref(),
        var("DISPLAY").as_deref(),
    )
}

/// A monitor as the system lists it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MonitorInfo {
    pub name: Option<String>,
    pub size: (u32, u32),
    pub position: (i32, i32),
}

impl std::fmt::Display for MonitorInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:?} {}x{} at ({}, {})",
            self.name.as_deref().unwrap_or("(unnamed)"),
            self.size.0,
            self.size.1,
            self.position.0,
            self.position.1
        )
    }
}

/// Picks the monitor for `choice` (exact name, then the name ignoring case, or index); with no
/// choice, the primary monitor, else the first. The error lists what is there.
pub fn choose_monitor(
    monitors: &[MonitorInfo],
    choice: Option<&MonitorChoice>,
    primary: Option<usize>,
) -> Result<usize, String> {
    let list = || {
        if monitors.is_empty() {
            "the system lists no monitors".to_string()
        } else {
            let all: Vec<String> = monitors
                .iter()
                .enumerate()
                .map(|(i, m)| format!("{i}: {m}"))
                .collect();
            format!("available: {}", all.join(", "))
        }
    };
    match choice {
        None if monitors.is_empty() => Err(list()),
        None => Ok(primary.filter(|&p| p < monitors.len()).unwrap_or(0)),
        Some(MonitorChoice::Index(i)) if *i < monitors.len() => Ok(*i),
        Some(MonitorChoice::Index(i)) => Err(format!("there is no monitor {i}; {}", list())),
        Some(MonitorChoice::Name(n)) => {
            let by = |eq: &dyn Fn(&str) -> bool| {
                monitors
                    .iter()
                    .position(|m| m.name.as_deref().is_some_and(eq))
            };
            by(&|m| m == n)
                .or_else(|| by(&|m| m.eq_ignore_ascii_case(n)))
                .ok_or_else(|| format!("no monitor named {n:?}; {}", list()))
        }
    }
}

/// With `display.scale = "exact"` the surface must be its monitor's size (the panel the
/// offsets and places are measured on): the reason it is not, for `/status` and the log.
pub fn surface_check(
    scale: Scale,
    surface: (u32, u32),
    monitor: &str,
    monitor_size: (u32, u32),
) -> Result<(), String> {
    if scale == Scale::Fit || surface == monitor_size {
        return Ok(());
    }
    Err(format!(
        "the window's surface is {}x{} but {monitor} is {}x{} (no window manager made the \
         window fullscreen?): drawn 1:1 (display.scale = \"exact\") the images would not be \
         where the panel's places are; display.scale = \"fit\" shows them scaled to the \
         surface",
        surface.0, surface.1, monitor_size.0, monitor_size.1
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mon(name: &str, x: i32) -> MonitorInfo {
        MonitorInfo {
            name: Some(name.into()),
            size: (1920, 1080),
            position: (x, 0),
        }
    }

    #[test]
    fn no_display_in_the_environment_is_a_clear_error() {
        let e = check_display_env(None, None, None).unwrap_err();
        let s = e.to_string();
        assert!(s.contains("no display: set DISPLAY/WAYLAND_DISPLAY"), "{s}");
        assert!(s.contains("kind = \"headless\""), "{s}");
        // Empty counts as unset, as winit treats it.
        assert!(check_display_env(Some(""), None, Some("")).is_err());
        assert!(check_display_env(None, None, Some(":0")).is_ok());
        assert!(check_display_env(Some("wayland-0"), None, None).is_ok());
        assert!(check_display_env(None, Some("3"), None).is_ok());
    }

    #[test]
    fn monitors_are_chosen_by_name_index_or_primary() {
        let ms = [mon("HDMI-1", 0), mon("DP-2", 1920), mon("eDP-1", 3840)];
        let name = |n: &str| Some(MonitorChoice::Name(n.into()));
        assert_eq!(choose_monitor(&ms, name("DP-2").as_ref(), None), Ok(1));
        assert_eq!(choose_monitor(&ms, name("hdmi-1").as_ref(), None), Ok(0));
        assert_eq!(
            choose_monitor(&ms, Some(&MonitorChoice::Index(2)), None),
            Ok(2)
        );
        assert_eq!(choose_monitor(&ms, None, Some(2)), Ok(2));
        assert_eq!(choose_monitor(&ms, None, None), Ok(0));
        // A primary index the list does not have falls back to the first.
        assert_eq!(choose_monitor(&ms, None, Some(7)), Ok(0));
    }

    #[test]
    fn an_unknown_monitor_lists_the_available_ones() {
        let ms = [mon("HDMI-1", 0), mon("DP-2", 1920)];
        let e = choose_monitor(&ms, Some(&MonitorChoice::Name("DP-9".into())), None).unwrap_err();
        assert!(e.contains("no monitor named \"DP-9\""), "{e}");
        assert!(
            e.contains("0: \"HDMI-1\" 1920x1080 at (0, 0)")
                && e.contains("1: \"DP-2\" 1920x1080 at (1920, 0)"),
            "{e}"
        );
        let e = choose_monitor(&ms, Some(&MonitorChoice::Index(5)), None).unwrap_err();
        assert!(
            e.contains("there is no monitor 5") && e.contains("DP-2"),
            "{e}"
        );
        let e = choose_monitor(&[], None, None).unwrap_err();
        assert!(e.contains("no monitors"), "{e}");
    }

    #[test]
    fn exact_needs_the_surface_to_be_the_monitors_size() {
        assert_eq!(
            surface_check(Scale::Exact, (1920, 1080), "monitor 0", (1920, 1080)),
            Ok(())
        );
        // What Xvfb without a window manager gave: refused, saying both sizes and the way out.
        let e = surface_check(
            Scale::Exact,
            (800, 600),
            "monitor 0: \"screen\"",
            (1024, 768),
        )
        .unwrap_err();
        assert!(
            e.contains("surface is 800x600 but monitor 0: \"screen\" is 1024x768")
                && e.contains("display.scale = \"fit\""),
            "{e}"
        );
        // Fit draws on whatever surface there is.
        assert_eq!(
            surface_check(Scale::Fit, (800, 600), "monitor 0", (1024, 768)),
            Ok(())
        );
    }

    #[test]
    fn two_outputs_take_each_eyes_monitor_and_name_the_key_when_one_is_missing() {
        let ms = [mon("HDMI-1", 0), mon("DP-2", 1920)];
        let name = |n: &str| Some(MonitorChoice::Name(n.into()));
        let per_eye = |l, r| Outputs::PerEye { left: l, right: r };
        assert_eq!(
            choose_outputs(
                &ms,
                &per_eye(name("DP-2"), Some(MonitorChoice::Index(0))),
                None
            )
            .unwrap(),
            [(1, Some(Side::Left)), (0, Some(Side::Right))]
        );
        assert_eq!(
            choose_outputs(&ms, &Outputs::One(None), Some(1)).unwrap(),
            [(1, None)]
        );
        let e = choose_outputs(&ms, &per_eye(name("HDMI-1"), name("DP-9")), None)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("display.monitor_right: no monitor named \"DP-9\"")
                && e.contains("1: \"DP-2\""),
            "{e}"
        );
        let e = choose_outputs(
            &ms,
            &per_eye(Some(MonitorChoice::Index(2)), name("DP-2")),
            None,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.starts_with("display.monitor_left: there is no monitor 2"),
            "{e}"
        );
        // One monitor named twice (by name and by index) is refused.
        let e = choose_outputs(
            &ms,
            &per_eye(name("dp-2"), Some(MonitorChoice::Index(1))),
            None,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.starts_with("display.monitor_right: 1 is monitor 1")
                && e.contains("two outputs need two monitors"),
            "{e}"
        );
        let e = choose_outputs(&ms, &per_eye(name("HDMI-1"), None), None)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("display.monitor_right: "), "{e}");
        let e = choose_outputs(&ms, &Outputs::One(name("VGA-1")), None)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("display.monitor: no monitor named"), "{e}");
    }

    #[test]
    fn monitors_at_different_rates_are_said_once_with_the_pace() {
        assert_eq!(refresh_mismatch(Some(60_000), Some(60_000)), None);
        assert_eq!(refresh_mismatch(None, Some(60_000)), None);
        let s = refresh_mismatch(Some(60_000), Some(59_940)).unwrap();
        assert!(
            s.contains("60.000 Hz") && s.contains("paced by the slower monitor (59.940 Hz)"),
            "{s}"
        );
    }
}
