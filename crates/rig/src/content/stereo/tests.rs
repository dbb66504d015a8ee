use super::*;
use crate::config::{RigConfig, EXAMPLE_SIM_BINOCULAR_RIG};
use dioptra_core::Timestamp;

fn binocular() -> RigConfig {
    RigConfig::parse(&(EXAMPLE_SIM_BINOCULAR_RIG.to_string() + "\n[content]\nanimate = false\n"))
        .unwrap()
}

/// The horizontal disparity (pixels, left image minus right) of a point at `d` diopters
/// for parallel eyes `ipd` metres apart: by hand, x = (X - e) / (Z * pitch).
fn disparity_px(cfg: &RigConfig, d: f32) -> f32 {
    let eye = cfg.eye_model().validated().unwrap();
    cfg.eye.ipd_mm * 1e-3 * d / eye.pixel_pitch_tan()
}

#[test]
fn a_point_appears_in_the_two_eyes_shifted_by_the_disparity_the_geometry_predicts() {
    use dioptra_sim::scene::{Object, Pattern, Rot, Scene, Shape, Texture};
    let cfg = binocular();
    assert!(cfg.display.stereo());
    // Two fronto-parallel plates (front faces at 0.4 m and 1.25 m, the far one lower in the
    // field, +y down), before a wall at 2 m.
    let plate = |x: f32, y: f32, z: f32, half: f32| Object {
        shape: Shape::Box {
            center: [x, y, z + 0.001],
            half: [half, half, 0.001],
            rot: Rot::IDENTITY,
        },
        texture: Texture {
            a: [0.8; 3],
            b: [0.2; 3],
            pattern: Pattern::Solid,
        },
        alpha: 1.0,
    };
    let scene = Scene {
        objects: vec![plate(0.0, 0.0, 0.4, 0.02), plate(0.01, 0.08, 1.25, 0.03)],
        wall_depth: 2.0,
        wall: Texture {
            a: [0.5; 3],
            b: [0.5; 3],
            pattern: Pattern::Solid,
        },
        seed: 0,
    };
    let depth = dioptra_core::DepthMap::from_meters(96, 96, &[2.0; 96 * 96]).unwrap();
    let frame = ContentFrame {
        scene: Some(Arc::new(scene)),
        ..ContentFrame::new(
            1,
            Arc::new(Rgbd {
                color: dioptra_core::RgbImage::new(96, 96, [0.0; 3]),
                depth,
            }),
        )
    };
    let views = EyeViews::new(&cfg.eye, &cfg.display).unwrap();
    let ([l, r], source) = views.of(&frame).unwrap();
    assert_eq!(source, ViewSource::SceneRayCast);
    // 63 mm at 20 degrees over 96 px: 17.1 px per diopter, by hand.
    assert!((disparity_px(&cfg, 1.0) - 17.147).abs() < 0.01);
    // The columns of `img`'s row `row` at depth `d`: its first and last.
    let span = |img: &Rgbd, d: f32, row: usize| {
        let cols: Vec<usize> = (0..96)
            .filter(|&x| (img.depth.plane().get(x, row).unwrap() - d).abs() < 0.01)
            .collect();
        (*cols.first().unwrap(), *cols.last().unwrap())
    };
    for (d, row) in [(2.5f32, 48), (0.8, 68)] {
        let ((l0, l1), (r0, r1)) = (span(&l, d, row), span(&r, d, row));
        let predicted = disparity_px(&cfg, d);
        for (a, b) in [(l0, r0), (l1, r1)] {
            let measured = a as f32 - b as f32;
            assert!(
                (measured - predicted).abs() <= 1.0,
                "{d} D: edges at {a} (left) and {b} (right): {measured} px, predicted {predicted:.2}"
            );
        }
    }
    // The wall (0.5 D) is shifted by 8.6 px: where it shows beside the plates.
}

/// The lab's report: mono file content on the binocular example rig, a near object over a
/// far wall; each eye's strip of wall beside the object, which the one RGB-D never saw,
/// must be wall (its colour and depth), not a blend with the object.
#[test]
fn a_mono_frame_shows_each_eye_the_wall_beside_a_near_square_not_a_ghost_of_it() {
    let cfg = binocular();
    let (w, h) = (96usize, 96usize);
    // A red square at 2 D (0.5 m), rows and columns 32..64, before a grey-blue wall at
    // 0.5 D (2 m), with the antialiased edge a supersampled render leaves (the wall pixels
    // beside the square 71 % square, at the wall's depth).
    let wall = [0.0, 0.3, 0.6];
    let mut colour = Vec::with_capacity(3 * w * h);
    let mut depth = Vec::with_capacity(w * h);
    for i in 0..w * h {
        let (x, y) = (i % w, i / w);
        let inside = (32..64).contains(&y);
        let (c, d) = if inside && (32..64).contains(&x) {
            ([1.0, 0.0, 0.0], 2.0)
        } else if inside && (x == 31 || x == 64) {
            ([0.71, 0.29 * wall[1], 0.29 * wall[2]], 0.5)
        } else {
            (wall, 0.5)
        };
        colour.extend(c);
        depth.push(d);
    }
    let rgbd = Rgbd {
        color: dioptra_core::RgbImage::from_interleaved(w, h, &colour).unwrap(),
        depth: dioptra_core::DepthMap::from_diopters(
            dioptra_core::Plane::from_vec(w, h, depth).unwrap(),
        )
        .unwrap(),
    };
    let views = EyeViews::new(&cfg.eye, &cfg.display).unwrap();
    let ([l, r], source) = views.of(&ContentFrame::new(1, Arc::new(rgbd))).unwrap();
    assert_eq!(source, ViewSource::Synthesised);
    // By hand: 96 px over 20 degrees is 2 tan(10 deg) / 96 = 0.0036735 per pixel; an eye
    // 31.5 mm (IPD / 2) from the centre sees a point at D diopters shifted by
    // 0.0315 D / 0.0036735 = 8.575 D px. The square (2 D) shifts 17.15 px, the wall
    // 4.29 px: the strip of wall beside the square that only that eye sees is
    // 8.575 x 1.5 = 12.86 px wide (the lab's 13 px), at the square's left edge in the
    // left eye's view, [32 + 4.29, 32 + 17.15) = [36.29, 49.15), and at its right edge in
    // the right eye's, [64 - 17.15, 64 - 4.29) = [46.85, 59.71).
    let per_d = disparity_px(&cfg, 1.0) / 2.0;
    assert!((per_d - 8.575).abs() < 0.01, "{per_d}");
    let row = 48;
    for (name, view, from, to) in [
        ("left", &l, 32.0 + 0.5 * per_d, 32.0 + 2.0 * per_d),
        ("right", &r, 64.0 - 2.0 * per_d, 64.0 - 0.5 * per_d),
    ] {
        let at = |x: usize| {
            (
                view.color
                    .channels
                    .each_ref()
                    .map(|c| c.get(x, row).unwrap()),
                view.depth.plane().get(x, row).unwrap(),
            )
        };
        // Every pixel whose centre lies in the strip, a pixel in from each edge (the
        // splat places pixels to the pixel; its crack fill may widen the square by one),
        // is the wall: its depth and its very colour, no red.
        let inner = (from.ceil() as usize + 1)..(to.floor() as usize - 1);
        assert!(inner.len() >= 10, "{name}: {inner:?}");
        for x in inner {
            assert_eq!(
                at(x),
                (wall, 0.5),
                "{name} eye, column {x}: a ghost of the square"
            );
        }
        // The square itself is where the geometry puts it, to a pixel: beyond the strip.
        let square = if name == "left" {
            to.ceil() as usize
        } else {
            from.floor() as usize - 1
        };
        assert_eq!(
            at(square),
            ([1.0, 0.0, 0.0], 2.0),
            "{name} eye, column {square}"
        );
    }
}

#[test]
fn one_rgbd_gives_each_eye_a_view_close_to_the_one_ray_cast_there() {
    let cfg = binocular();
    let content = crate::content::open_simulated(&cfg);
    let scene_frame = content.poll(Timestamp::ZERO).unwrap();
    let views = EyeViews::new(&cfg.eye, &cfg.display).unwrap();
    let (cast, source) = views.of(&scene_frame).unwrap();
    // The animated scene cast them on its worker, as they are cast here.
    assert_eq!(source, ViewSource::SceneRayCast);
    let here = ContentFrame {
        scene: scene_frame.scene.clone(),
        ..ContentFrame::new(10, scene_frame.rgbd.clone())
    };
    let (cast_here, _) = views.of(&here).unwrap();
    assert_eq!(*cast_here[0], *cast[0]);
    assert_eq!(*cast_here[1], *cast[1]);
    // The same cyclopean RGB-D as a lab's one file: no scene behind it.
    let mono = ContentFrame::new(2, scene_frame.rgbd.clone());
    let (synth, source) = views.of(&mono).unwrap();
    assert_eq!(source, ViewSource::Synthesised);
    for (eye, (c, s)) in cast.iter().zip(&synth).enumerate() {
        let p = dioptra_render::metrics::psnr(&c.color, &s.color, None).unwrap();
        let unshifted = dioptra_render::metrics::psnr(&c.color, &mono.rgbd.color, None).unwrap();
        eprintln!("eye {eye}: {p:.1} dB, unshifted {unshifted:.1} dB");
        // Objects at 26 cm shift 66 px of 96 between the eyes: what only one eye sees is
        // filled from the background, so the synthesised view is far from exact; but it
        // is that eye's view (measured: 21.6 and 20.8 dB, left and right, against 14.4 and
        // 14.1 dB unshifted; 18.5 and 19.3 dB before the fill stopped spreading the near
        // surface's colour).
        assert!(
            p > unshifted + 3.0,
            "eye {eye}: {p:.1} dB, unshifted {unshifted:.1} dB"
        );
    }
    // Stereo content is used as it is.
    let stereo = ContentFrame {
        eyes: Some(cast.clone()),
        ..ContentFrame::new(3, mono.rgbd.clone())
    };
    let (own, source) = views.of(&stereo).unwrap();
    assert_eq!(source, ViewSource::Stereo);
    assert!(Arc::ptr_eq(&own[1], &cast[1]));
}
