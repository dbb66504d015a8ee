//! The marker patch (`display.marker_patch`), present by present: [`Marker`] decides its
//! colour (toggled on every frame, or on the events the config names); [`MarkerControl`] is
//! how the API asks for a marker and how `dioptra hil` holds the patch black.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use super::config::{MarkerEvent, MarkerPatch};
use super::frame::MarkerDraw;

/// The patch's colour, present by present: the loop's own state.
#[derive(Debug, Clone)]
pub struct Marker {
    patch: MarkerPatch,
    white: bool,
    /// An event asked for a toggle at the next present.
    pending: bool,
    api_seen: u64,
}

impl Marker {
    /// Black until the first toggle.
    pub fn new(patch: &MarkerPatch) -> Marker {
        Marker {
            patch: patch.clone(),
            white: false,
            pending: false,
            api_seen: 0,
        }
    }

    /// `event` happened: the next present toggles the patch if the config names it.
    pub fn event(&mut self, event: MarkerEvent) {
        if self.patch.toggle_on.contains(&event) {
            self.pending = true;
        }
    }

    /// The patch for the next present.
    pub fn on_present(&mut self, control: &MarkerControl) -> MarkerDraw {
        let api = control.api_markers.load(Ordering::Relaxed);
        if api != self.api_seen {
            self.api_seen = api;
            self.event(MarkerEvent::ApiMarker);
        }
        if control.hold.load(Ordering::Relaxed) {
            // Held black: what happened meanwhile is not shown afterwards.
            self.white = false;
            self.pending = false;
        } else if self.pending || self.patch.toggle_on.contains(&MarkerEvent::Frame) {
            self.white = !self.white;
            self.pending = false;
        }
        MarkerDraw {
            corner: self.patch.corner,
            size: self.patch.size,
            white: self.white,
        }
    }
}

/// What outside the loop asks of the marker patch.
#[derive(Debug, Default)]
pub struct MarkerControl {
    hold: AtomicBool,
    api_markers: AtomicU64,
}

impl MarkerControl {
    /// Toggles the patch at the next present, where `toggle_on` names "api-marker" (the API's
    /// `POST /marker`). Returns the markers asked for so far.
    pub fn api_marker(&self) -> u64 {
        self.api_markers.fetch_add(1, Ordering::Relaxed) + 1
    }
    /// Holds the patch black (true) from the next present until released (false).
    pub fn hold_black(&self, hold: bool) {
        self.hold.store(hold, Ordering::Relaxed);
    }
}
