//! The charts' font: every chart (demo, eval, hil) is drawn with plotters and a bundled font
//! (DejaVu Sans, see assets/DejaVuSans.LICENSE), so it needs no system library.

use std::sync::Once;

use plotters::style::FontStyle;

static FONT: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");
static REGISTER: Once = Once::new();

/// Registers the bundled font with plotters (once); every chart calls it first.
pub fn font() {
    REGISTER.call_once(|| {
        // A font that fails to load only costs the charts their text.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}
