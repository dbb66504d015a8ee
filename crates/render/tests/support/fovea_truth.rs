//! Ground truth in the fovea only: a centred crop of the thin-lens reference rendered with the
//! full image's pixel pitch, so it can afford hundreds of rays per pixel (a 128-192 px frame's
//! fovea is about 20-30 px across, and a full-frame reference with few rays is noisier than
//! the methods it judges). Shared by tests/planner.rs and examples/planner_calibration.rs.

use dioptra_core::{Diopters, EyeModel, Plane, RgbImage};
use dioptra_render::metrics::psnr;
use dioptra_sim::scene::{render_thin_lens, Camera, Scene};

/// Side of the centred crop for a `size` px square frame: the fovea (diameter 0.1 of the
/// diagonal) plus a pixel each side, with the frame's parity so the crop is pixel-aligned.
pub fn crop_side(size: usize) -> usize {
    let fovea = 0.1 * (2.0f32).sqrt() * size as f32;
    let mut c = fovea.ceil() as usize + 2;
    if c % 2 != size % 2 {
        c += 1;
    }
    c.min(size)
}

/// The thin-lens reference of the centred `crop_side(size)` square of a `size` px frame.
pub fn truth_crop(
    scene: &Scene,
    eye: &EyeModel,
    size: usize,
    focus: Diopters,
    samples: u32,
) -> Result<RgbImage, dioptra_core::InputError> {
    let full = eye.with_width(size as u32);
    let c = crop_side(size);
    let fov = 2.0 * (0.5 * c as f32 * full.pixel_pitch_tan()).atan();
    let eye_c = EyeModel {
        fov_horizontal_deg: fov.to_degrees(),
        ..full
    };
    render_thin_lens(scene, &Camera::square(eye_c, c), focus, samples)
}

/// The centred `c` x `c` square of `img`.
pub fn crop(img: &RgbImage, c: usize) -> RgbImage {
    let (w, h) = (img.width(), img.height());
    let (x0, y0) = ((w - c) / 2, (h - c) / 2);
    let ch = img.channels.each_ref().map(|p| {
        let mut v = Vec::with_capacity(c * c);
        for y in y0..y0 + c {
            v.extend_from_slice(&p.row(y)[x0..x0 + c]);
        }
        Plane::from_vec(c, c, v).expect("crop size")
    });
    let [r, g, b] = ch;
    RgbImage::from_planes(r, g, b).expect("crop planes")
}

/// PSNR in the fovea (a `size` px frame's, gaze at its centre) of `full` against the
/// reference crop `truth`.
pub fn fovea_psnr(full: &RgbImage, truth: &RgbImage, size: usize) -> f64 {
    let c = truth.width();
    let radius = 0.05 * (2.0f32).sqrt() * size as f32;
    let mut m = Plane::new(c, c, 0.0);
    for (i, v) in m.data_mut().iter_mut().enumerate() {
        let dx = (i % c) as f32 + 0.5 - 0.5 * c as f32;
        let dy = (i / c) as f32 + 0.5 - 0.5 * c as f32;
        if dx * dx + dy * dy <= radius * radius {
            *v = 1.0;
        }
    }
    psnr(&crop(full, c), truth, Some(&m)).unwrap_or(f64::NAN)
}
