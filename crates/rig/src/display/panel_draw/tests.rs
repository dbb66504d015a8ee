use super::*;
use crate::config::RigConfig;
use crate::display::blit::tests::{gpu_or_skip, read_target};
use crate::display::placement::{PlacementConfig, Placer};
use crate::display::{panel_images, DisplaySink, Frame, HeadlessSink};
use dioptra_core::{RgbImage, Timestamp};

/// The simulated HMD example: 480 x 270 per eye side by side, an eyepiece with distortion and
/// lateral colour, magnification compensation, a gamma-2.4 panel.
const HMD_RIG: &str = include_str!("../../../../cli/examples/rig-sim-hmd.toml");

/// A test image in linear light: smooth gradients (where the warp's interpolation shows as
/// small differences) with one-pixel lines every 24 pixels and a coloured square (sharp
/// edges, where a position error shows most), distinct per eye.
fn stimulus(w: usize, h: usize, tag: f32) -> RgbImage {
    let mut v = Vec::with_capacity(3 * w * h);
    for y in 0..h {
        for x in 0..w {
            let (fx, fy) = (x as f32 / w as f32, y as f32 / h as f32);
            let line = x % 24 == 0 || y % 24 == 0;
            let square = (200..260).contains(&x) && (100..160).contains(&y);
            let rgb = if line {
                [0.9, 0.9, 0.9]
            } else if square {
                [0.8, 0.1 * tag, 0.05]
            } else {
                [0.5 * fx, 0.4 * fy, 0.3 * tag * (1.0 - fx)]
            };
            v.extend_from_slice(&rgb);
        }
    }
    RgbImage::from_interleaved(w, h, &v).unwrap()
}

/// The window's passes (drawn into an offscreen texture as into its surface, read back) give
/// the headless sink's panel for the same frame and the example HMD's settings: both eyes
/// pre-warped per colour channel, scaled for their magnification compensation, encoded for
/// the gamma-2.4 panel, placed side by side, the marker patch over them.
///
/// Tolerance: one 8-bit step (1/255) at every pixel but those next to an edge of the
/// eyepiece's reach (where a triangle with an unreachable vertex is black, a pixel centre on
/// its edge may fall either side; none in this example, which the test checks). Both twins read the
/// same mesh and table; they differ by the rasteriser's interpolation of the source positions
/// (f32 barycentrics, about 1e-4 px here), by f32 rounding in the bilinear read and the table,
/// and by the conversion to 8 bits (the CPU rounds to nearest; a GPU may round within 0.6 of
/// a step), which alone can make one step.
#[test]
fn the_windows_passes_draw_what_the_headless_sink_writes() {
    let Some(ctx) = gpu_or_skip(GpuContext::shared(None)) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = RigConfig::parse(HMD_RIG).unwrap();
    cfg.display.png_every = 1;
    cfg.display.png_dir = Some(dir.path().to_path_buf());
    let (w, h) = (cfg.display.width as usize, cfg.display.height as usize);
    let panels = panel_images(&cfg).unwrap();
    assert_eq!(panels.len(), 2, "an image path per eye");
    let frame = Frame {
        number: 0,
        focus: dioptra_core::Diopters(0.5),
        layers: Arc::new(vec![FrameImage::Host(stimulus(w, h, 0.3))]),
        right: Some(Arc::new(vec![FrameImage::Host(stimulus(w, h, 1.0))])),
        marker: Some(MarkerDraw {
            corner: crate::config::Corner::TopLeft,
            size: 8,
            white: true,
        }),
        size_compensation: [Some(1.012), Some(0.985)],
    };

    // The CPU twin: the headless sink's PNG of the side-by-side panel.
    let mut sink = HeadlessSink::for_rig(&cfg).unwrap();
    sink.present(&frame, Timestamp(0)).unwrap();
    let (pw, ph, want) =
        dioptra_render::io::read_code_values(&dir.path().join("frame_000000.png")).unwrap();
    assert_eq!((pw, ph), (2 * w, h));
    let (pw, ph) = (pw as u32, ph as u32);

    // The window's passes, as the presenter runs them, on the render's context.
    let (device, queue) = (ctx.device(), ctx.queue());
    let format = wgpu::TextureFormat::Rgba8Unorm;
    let mut draw = PanelDraw::new(device, format, Some(ctx.clone()), &panels).unwrap();
    assert!(draw.corrects());
    draw.set_marker(frame.marker);
    let placer = Placer::new(PlacementConfig::from_display(&cfg.display));
    let placed = placer.place(&frame, 0, (pw, ph)).unwrap();
    let prepared: Vec<Prepared> = placed
        .iter()
        .enumerate()
        .map(|(slot, p)| {
            let c = frame.compensation_of(p.eye);
            draw.prepare(device, queue, slot, p, c).unwrap()
        })
        .collect();
    let got = read_target(device, queue, format, (pw, ph), |enc, view| {
        draw.encode(enc, view, (pw, ph), &prepared).unwrap()
    });

    // No vertex beyond the eyepiece's reach here: every pixel is compared.
    for p in &panels {
        assert_eq!(p.mesh().unwrap().unreachable(), 0);
    }
    let mut worst = (0u8, 0usize);
    let mut off_by_one = 0usize;
    for (i, px) in got.chunks(4).enumerate() {
        assert_eq!(px[3], 255, "pixel {i}: alpha");
        for c in 0..3 {
            let d = px[c].abs_diff(want[3 * i + c]);
            off_by_one += usize::from(d == 1);
            if d > worst.0 {
                worst = (d, i);
            }
        }
    }
    let (x, y) = (worst.1 % pw as usize, worst.1 / pw as usize);
    eprintln!(
        "window passes against the headless sink: worst {} step(s) at ({x}, {y}); {off_by_one} \
         channel values one step apart of {}",
        worst.0,
        3 * pw * ph
    );
    assert!(
        worst.0 <= 1,
        "pixel ({x}, {y}): drawn {:?}, written {:?}",
        &got[4 * worst.1..4 * worst.1 + 3],
        &want[3 * worst.1..3 * worst.1 + 3]
    );
    // The check can fail: the left eye without its compensation (drawn alone) differs, in
    // the left half, by far more.
    let uncompensated = draw.prepare(device, queue, 0, &placed[0], None).unwrap();
    let other = read_target(device, queue, format, (pw, ph), |enc, view| {
        draw.encode(enc, view, (pw, ph), &[uncompensated]).unwrap()
    });
    let far = (0..ph as usize * pw as usize)
        // The left half, past the marker patch's columns.
        .filter(|i| (8..w).contains(&(i % pw as usize)))
        .filter(|&i| (0..3).any(|c| other[4 * i + c].abs_diff(want[3 * i + c]) > 8))
        .count();
    assert!(far > 1000, "{far} pixels differ by more than 8 steps");
}
