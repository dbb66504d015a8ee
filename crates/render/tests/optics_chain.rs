//! The image through the rig's optics, end to end: the pre-warp and the transfer pass
//! (this crate), the magnification compensation (dioptra-core's optics map), seen by the
//! simulator's camera at the eye (dioptra-sim's own eyepiece, lens and panel models).
//!
//! The rig: a 960 x 540 panel behind an eyepiece (93 degrees across; a magnifier's pincushion
//! and 1 % lateral colour each way), a tunable lens 15 mm from the eye with a 19 D fixed lens,
//! the display 50 mm away, lens range -1..+1 D; a gamma-2.4 panel with a black of 0.3 cd/m²
//! under 120. The camera sees the same field at half the resolution.

use dioptra_core::distortion::{ChannelModel, Coefficients, EyepieceModel, Intrinsics};
use dioptra_core::optics_map::{Prescription, ThinLensLayout};
use dioptra_core::transfer::{Transfer, TransferFit};
use dioptra_core::{Diopters, OpticsMap, Plane, PowerRange, RgbImage};
use dioptra_render::transfer::EncodeLut;
use dioptra_render::warp::{warp_cpu, WarpDraw, WarpMesh, DEFAULT_STEP_PX};
use dioptra_sim::eye_camera::{
    EyeCamera, EyepieceChannel, PanelResponse, Photometer, SimOptics, ThinLenses, TrueEyepiece,
};

const PANEL: [usize; 2] = [960, 540];
const F: f64 = 450.0;
const CX: f64 = 479.5;
const CY: f64 = 269.5;
/// Lateral colour: each channel's focal length against green's.
const CHANNEL_SCALE: [f64; 3] = [1.01, 1.0, 0.99];
const K1: f64 = -0.18;
const K2: f64 = 0.03;
const P1: f64 = 0.0005;
const P2: f64 = -0.0004;

/// The eyepiece as the rig config would give it (dioptra-core's model).
fn config_model() -> EyepieceModel {
    let render = Intrinsics {
        fx: F,
        fy: F,
        cx: CX,
        cy: CY,
    };
    let ch = |s: f64| ChannelModel {
        camera: Intrinsics {
            fx: F * s,
            fy: F * s,
            cx: CX,
            cy: CY,
        },
        coefficients: Coefficients {
            k1: K1,
            k2: K2,
            p1: P1,
            p2: P2,
            ..Default::default()
        },
    };
    EyepieceModel {
        render,
        channels: CHANNEL_SCALE.map(ch),
    }
    .checked("optics.distortion")
    .unwrap()
}

/// The same eyepiece as the simulator knows it (its own code).
fn true_optics() -> SimOptics {
    let ch = |s: f64| EyepieceChannel {
        fx: F * s,
        fy: F * s,
        cx: CX,
        cy: CY,
        k1: K1,
        k2: K2,
        k3: 0.0,
        p1: P1,
        p2: P2,
    };
    SimOptics {
        lenses: ThinLenses {
            display_distance_m: 0.05,
            eye_relief_m: 0.015,
            fixed_power_d: 19.0,
        },
        eyepiece: TrueEyepiece(CHANNEL_SCALE.map(ch)),
        reference_power_d: -1.0,
    }
}

fn optics_map() -> OpticsMap {
    OpticsMap::new(
        Some(ThinLensLayout::new(0.05, 0.015, 19.0).unwrap()),
        None,
        Prescription::default(),
        PowerRange::new(Diopters(-1.0), Diopters(1.0)).unwrap(),
    )
    .unwrap()
}

fn camera() -> EyeCamera {
    EyeCamera {
        width: 480,
        height: 270,
        f_px: F / 2.0,
        cx: 239.5,
        cy: 134.5,
        pupil_mm: 4.0,
        supersample: 4,
    }
}

/// The panel's response above black is q^2.4: its transfer.
fn panel_lut() -> EncodeLut {
    EncodeLut::new(&Transfer::gamma(2.4, 0.0).unwrap())
}

/// An ideal (render) image: white where `lit(x, y)`, black elsewhere.
fn ideal(lit: impl Fn(usize, usize) -> bool) -> RgbImage {
    let [w, h] = PANEL;
    let d: Vec<f32> = (0..w * h)
        .map(|i| if lit(i % w, i / w) { 1.0 } else { 0.0 })
        .collect();
    let p = Plane::from_vec(w, h, d).unwrap();
    RgbImage::from_planes(p.clone(), p.clone(), p).unwrap()
}

/// What the panel shows: the ideal image pre-warped (or not) and encoded for the panel.
fn panel_image(source: &RgbImage, prewarp: bool, scale: f32, lut: &EncodeLut) -> RgbImage {
    let mesh = if prewarp {
        WarpMesh::new(&config_model(), PANEL, PANEL, DEFAULT_STEP_PX).unwrap()
    } else {
        WarpMesh::identity(PANEL, PANEL, [CX, CY]).unwrap()
    };
    warp_cpu(
        source,
        &mesh,
        &WarpDraw {
            scale,
            encode: Some(lut),
        },
    )
    .unwrap()
}

/// The light above black in channel `c` of a camera image, as a fraction of white's.
fn above_black(img: &RgbImage, c: usize, x: usize, y: usize) -> f64 {
    let p = PanelResponse::example();
    (f64::from(img.channels[c].get(x, y).unwrap()) - p.black_cd_m2)
        / (p.white_cd_m2 - p.black_cd_m2)
}

/// The centroid row of a horizontal line in each camera column where all of it is seen
/// (rows `band`), channel `c`, averaged over 9 columns: (column, row). The average takes out
/// the panel's pixel staircase (a line drawn on pixels steps by a fraction of one wherever it
/// is not level on the panel, as the pre-warped line is not); a bend or a fringe from the
/// optics is smooth across the field and stays.
fn line_rows(img: &RgbImage, c: usize, band: std::ops::Range<usize>) -> Vec<(f64, f64)> {
    let rows = column_centroids(img, c, band);
    rows.windows(9)
        .filter(|w| w[8].0 - w[0].0 == 8.0)
        .map(|w| (w[4].0, w.iter().map(|p| p.1).sum::<f64>() / 9.0))
        .collect()
}

fn column_centroids(img: &RgbImage, c: usize, band: std::ops::Range<usize>) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    let mut mass = Vec::new();
    for x in 0..img.width() {
        let (mut m, mut my) = (0.0, 0.0);
        for y in band.clone() {
            let v = above_black(img, c, x, y).max(0.0);
            m += v;
            my += v * y as f64;
        }
        mass.push(m);
        out.push((x as f64, my / m.max(1e-12)));
    }
    // Where all of the line is in the field (the camera samples the panel's pixels, so the
    // mass varies a few percent from column to column).
    let full = mass[img.width() / 2];
    out.into_iter()
        .zip(mass)
        .filter(|(_, m)| (m - full).abs() < 0.1 * full)
        .map(|(p, _)| p)
        .collect()
}

/// The largest distance of points from their least-squares straight line.
fn off_straight(points: &[(f64, f64)]) -> f64 {
    let n = points.len() as f64;
    let (mx, my) = (
        points.iter().map(|p| p.0).sum::<f64>() / n,
        points.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let sxy: f64 = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = points.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let slope = sxy / sxx;
    points
        .iter()
        .map(|p| (p.1 - (my + slope * (p.0 - mx))).abs())
        .fold(0.0, f64::max)
}

#[test]
fn lines_are_straight_and_fringes_gone_after_the_prewarp() {
    let optics = true_optics();
    let lut = panel_lut();
    // A 4 px line 210 px above the centre (22 degrees), across the whole field.
    let source = ideal(|_, y| (57..61).contains(&y));
    let cam = EyeCamera {
        supersample: 8,
        ..camera()
    };
    let seen = |prewarp: bool| {
        cam.see(
            &panel_image(&source, prewarp, 1.0, &lut),
            &PanelResponse::example(),
            &optics,
            -1.0,
            // Focused on the display's image at -1 D: sharp.
            optics.lenses.demand_d(-1.0),
        )
    };
    let (warped, bare) = (seen(true), seen(false));
    let green = line_rows(&warped, 1, 10..60);
    assert!(
        green.len() > 300,
        "the line is seen over {} columns",
        green.len()
    );
    let bend = off_straight(&green);
    let bend_bare = off_straight(&line_rows(&bare, 1, 0..80));
    eprintln!("line bend: {bend:.4} camera px pre-warped, {bend_bare:.2} px without");
    assert!(bend < 0.05, "pre-warped, the line bends by {bend} px");
    assert!(bend_bare > 2.0, "without the pre-warp, {bend_bare} px");
    // Colour fringes: red's and blue's rows against green's, column by column.
    let fringe = |img: &RgbImage, band: std::ops::Range<usize>| {
        let g = line_rows(img, 1, band.clone());
        [0, 2]
            .iter()
            .flat_map(|&c| {
                let other = line_rows(img, c, band.clone());
                g.iter()
                    .filter_map(move |a| {
                        other.iter().find(|b| b.0 == a.0).map(|b| (a.1 - b.1).abs())
                    })
                    .collect::<Vec<_>>()
            })
            .fold(0.0, f64::max)
    };
    let (f, f_bare) = (fringe(&warped, 10..60), fringe(&bare, 0..80));
    eprintln!("colour fringe: {f:.4} camera px pre-warped, {f_bare:.2} px without");
    assert!(f < 0.05, "fringes of {f} px after the pre-warp");
    assert!(f_bare > 0.5, "{f_bare}");
}

/// The side of a lit square in a camera image, tangent units: the light above black summed
/// over the frame, as a fraction of white's per pixel, is its area.
fn square_side(img: &RgbImage, f_px: f64) -> f64 {
    let mut area = 0.0;
    for y in 0..img.height() {
        for x in 0..img.width() {
            area += above_black(img, 1, x, y);
        }
    }
    area.sqrt() / f_px
}

#[test]
fn a_compensated_square_keeps_its_angular_size_over_the_lens_range() {
    let optics = true_optics();
    let map = optics_map();
    let reference = map.magnification_reference().unwrap();
    assert_eq!(reference, Diopters(-1.0));
    let lut = panel_lut();
    // 200 ideal pixels across at 450 px per tangent: 0.4444 by hand.
    let source = ideal(|x, y| (380..580).contains(&x) && (170..370).contains(&y));
    let want = 200.0 / F;
    let cam = camera();
    let mut sizes = Vec::new();
    for p in [-1.0, -0.5, 0.0, 0.5, 1.0] {
        let c = map
            .size_compensation(Diopters(p as f32), reference)
            .unwrap();
        // The eye stays focused at 1 D while the lens moves: the blur changes too.
        let look = |scale: f32| {
            square_side(
                &cam.see(
                    &panel_image(&source, true, scale, &lut),
                    &PanelResponse::example(),
                    &optics,
                    p,
                    1.0,
                ),
                cam.f_px,
            )
        };
        let (compensated, bare) = (look((1.0 / c) as f32), look(1.0));
        sizes.push((p, compensated, bare));
    }
    eprintln!("(lens power, compensated side, uncompensated side): {sizes:?}");
    for &(p, side, bare) in &sizes {
        assert!(
            ((side - want) / want).abs() < 1e-3,
            "at {p} D: {side} against {want}"
        );
        // Uncompensated it grows as the layout's magnification, by hand:
        // M(P) / M(-1) = 0.0515 / (0.05075 - 0.00075 P).
        let grows = 0.0515 / (0.05075 - 0.00075 * p);
        assert!(
            ((bare / want) / grows - 1.0).abs() < 1e-3,
            "at {p} D: {bare}"
        );
    }
}

#[test]
fn blended_layers_add_in_light_on_a_calibrated_panel() {
    // A 10-bit panel: at 8 bits the code values' rounding alone moves half + half from whole
    // by up to 1.4 % at a linear 0.1 (measured with the exact gamma-2.4 inverse), whatever
    // the calibration.
    let panel = PanelResponse {
        bits: 10,
        ..PanelResponse::example()
    };
    // Calibrate from 17 photometer readings with 0.2 % noise.
    let meter = Photometer {
        panel,
        noise: 0.002,
        seed: 55,
    };
    let readings: Vec<(f64, f64)> = (0..17)
        .map(|k| {
            let q = k as f64 / 16.0;
            (q, meter.read(q, k))
        })
        .collect();
    let fit = TransferFit::fit(&readings, Default::default()).unwrap();
    let calibrated = EncodeLut::new(&Transfer::Table(fit.table("sim", 255).unwrap()));
    let optics = true_optics();
    let cam = EyeCamera {
        width: 48,
        height: 27,
        f_px: F / 20.0,
        cx: 23.5,
        cy: 13.5,
        pupil_mm: 4.0,
        supersample: 2,
    };
    // A flat field of linear value v in one layer (near plane, lens at +0.5 D) or split
    // half and half between the near and the far layer (-0.5 D), as linear blending splits a
    // point midway between them.
    let flat = |v: f32| RgbImage::new(PANEL[0], PANEL[1], [v; 3]);
    let worst = |lut: &EncodeLut| {
        let mut worst = 0.0f64;
        for v in [0.1f32, 0.3, 0.6, 1.0] {
            let shown = |a: f32, b: f32| {
                let (near, far) = (
                    panel_image(&flat(a), false, 1.0, lut),
                    panel_image(&flat(b), false, 1.0, lut),
                );
                let seen = cam.see_layers(&[(&near, 0.5), (&far, -0.5)], &panel, &optics, 1.0);
                f64::from(seen.channels[1].get(24, 13).unwrap())
            };
            let (whole, split) = (shown(v, 0.0), shown(v / 2.0, v / 2.0));
            // Both include each layer's black once.
            worst = worst.max(((split - whole) / (whole - 2.0 * panel.black_cd_m2)).abs());
        }
        worst
    };
    let (calibrated_err, srgb_err) = (worst(&calibrated), worst(&EncodeLut::new(&Transfer::Srgb)));
    eprintln!(
        "half + half against whole: {:.3} % calibrated, {:.2} % encoding sRGB",
        100.0 * calibrated_err,
        100.0 * srgb_err
    );
    assert!(calibrated_err < 0.01, "{calibrated_err}");
    // Without the calibration (encoding sRGB for a gamma-2.4 panel) they do not add.
    assert!(srgb_err > 0.03, "{srgb_err}");
}
