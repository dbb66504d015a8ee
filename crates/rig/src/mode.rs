//! The rig's top-level `mode` and `method` keys: how the display shows depth, and the render
//! method, by the scheduler's names. Everything that runs a mode or a method (the scheduler's
//! adapter, the render worker, the loop, the API) speaks these.

use dioptra_sched::RenderMethod;
use serde::{Deserialize, Serialize};

use crate::config::error::{invalid, ConfigError};

/// How the display shows depth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    Varifocal,
    Multifocal,
    Lightfield,
}

impl Mode {
    pub fn parse(s: &str) -> Option<Mode> {
        match s {
            "varifocal" => Some(Mode::Varifocal),
            "multifocal" => Some(Mode::Multifocal),
            "lightfield" => Some(Mode::Lightfield),
            _ => None,
        }
    }
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Varifocal => "varifocal",
            Mode::Multifocal => "multifocal",
            Mode::Lightfield => "lightfield",
        }
    }
}

impl Mode {
    pub fn from_sched(m: dioptra_sched::Mode) -> Mode {
        match m {
            dioptra_sched::Mode::Varifocal => Mode::Varifocal,
            dioptra_sched::Mode::Multifocal => Mode::Multifocal,
            dioptra_sched::Mode::LightField => Mode::Lightfield,
        }
    }
    /// The scheduler's name for this mode.
    pub fn sched(self) -> dioptra_sched::Mode {
        match self {
            Mode::Varifocal => dioptra_sched::Mode::Varifocal,
            Mode::Multifocal => dioptra_sched::Mode::Multifocal,
            Mode::Lightfield => dioptra_sched::Mode::LightField,
        }
    }
}

/// The render method, by the scheduler's names: gather, pyramid (bounded cost per pixel,
/// foveated by `render.foveation`), lightfield-defocus (varifocal); linear, optimized,
/// spectral, hybrid (spectral around each eye's gaze, `render.hybrid`) (multifocal); views
/// (light field); network, refine (any).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(try_from = "String", into = "String")]
pub struct Method(pub RenderMethod);

impl TryFrom<String> for Method {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        Method::parse(&s)
            .ok_or_else(|| {
                format!("unknown method {s:?}: expected one of {}, or auto (varifocal: the planner chooses per frame)", methods())
            })
    }
}

impl From<Method> for String {
    fn from(m: Method) -> String {
        m.as_str().into()
    }
}

/// The methods the daemon renders.
pub const RENDERED: &str =
    "gather, pyramid, lightfield-defocus, network or refine (varifocal), linear, \
     optimized, spectral, hybrid, network or refine (multifocal), views or refine (light field)";

/// Every method's name, for messages.
pub fn methods() -> String {
    RenderMethod::ALL
        .iter()
        .map(|m| m.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

impl Method {
    pub fn parse(s: &str) -> Option<Method> {
        s.parse::<RenderMethod>().ok().map(Method)
    }
    pub fn as_str(self) -> &'static str {
        self.0.as_str()
    }
    /// Whether this method makes images for `mode`.
    pub fn fits(self, mode: Mode) -> bool {
        self.0.suits(mode.sched())
    }
    /// Why the daemon cannot render with this method in `mode`, if it cannot (the network's
    /// weights are checked when the daemon starts, by the render worker that loads them).
    pub fn unavailable(self, mode: Mode) -> Option<String> {
        match (self.0, mode) {
            (RenderMethod::Network, Mode::Lightfield) => Some(format!(
                "{} in lightfield mode (C5 views) is not rendered by `dioptra serve`; use {}",
                self.as_str(),
                RENDERED
            )),
            _ => None,
        }
    }
    /// The methods that fit `mode`, for messages.
    pub fn for_mode(mode: Mode) -> String {
        RenderMethod::ALL
            .iter()
            .filter(|m| m.suits(mode.sched()))
            .map(|m| m.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// `mode` and `method` together (`auto`: the planner chooses each frame's method, and
/// `method` holds the mode's default).
pub fn check(mode: Mode, method: Method, auto_method: bool) -> Result<(), ConfigError> {
    if auto_method && mode != Mode::Varifocal {
        return Err(invalid(
            "method",
            format!(
                "auto chooses a method per frame in varifocal mode only (in {} mode the planes or views are fixed by the hardware's program); expected {}",
                mode.as_str(),
                Method::for_mode(mode)
            ),
        ));
    }
    if !method.fits(mode) {
        return Err(invalid(
            "method",
            format!(
                "{} does not render for {} mode; expected {}",
                method.as_str(),
                mode.as_str(),
                Method::for_mode(mode)
            ),
        ));
    }
    if let Some(why) = method.unavailable(mode) {
        return Err(invalid("method", why));
    }
    Ok(())
}
