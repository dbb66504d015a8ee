//! Pins the CPU pyramid render's and the foveated render's outputs bit for bit (issue 54's
//! speed-ups must not change a single bit): checksums of the images of a scene with occlusions
//! (a near square and a mid disk over a slanted textured wall, with patches of one depth where
//! the exact pass takes its flat path) at several foci, full, foveated (three layers and more)
//! and over an annulus. The checksums were recorded from the implementation before the
//! speed-ups; a change that alters the numerics on purpose must measure its accuracy against
//! gather and the thin-lens truth and then record new ones.

use dioptra_core::{DepthMap, Diopters, EyeModel, Plane, RgbImage, Rgbd};
use dioptra_render::foveated::{foveated, Foveation, FoveationPlan, DEFAULT_MAR_SLOPE};
use dioptra_render::pyramid::{pyramid, render_region, Region};

const W: usize = 240;
const H: usize = 200;

fn scene() -> Rgbd {
    let noise = |i: usize, c: usize| {
        let x = (i * 3 + c) as u32;
        (x.wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32
    };
    let plane = |c: usize| {
        let v = (0..W * H)
            .map(|i| {
                let (x, y) = ((i % W) as f32, (i / W) as f32);
                0.5 + 0.25 * (0.19 * x + 1.1 * c as f32).sin() * (0.13 * y).cos()
                    + 0.15 * noise(i, c)
            })
            .collect();
        Plane::from_vec(W, H, v).unwrap()
    };
    let depth = (0..W * H)
        .map(|i| {
            let (x, y) = (i % W, i / W);
            let (dx, dy) = (x as f32 - 170.0, y as f32 - 60.0);
            if (40..110).contains(&x) && (50..140).contains(&y) {
                3.0
            } else if dx * dx + dy * dy < 35.0 * 35.0 {
                1.2
            } else if y >= 160 {
                // A floor of one depth.
                0.5
            } else {
                0.2 + 0.004 * x as f32 + 0.001 * y as f32
            }
        })
        .collect();
    Rgbd::new(
        RgbImage::from_planes(plane(0), plane(1), plane(2)).unwrap(),
        DepthMap::from_diopters(Plane::from_vec(W, H, depth).unwrap()).unwrap(),
    )
    .unwrap()
}

/// FNV-1a over the bits of the planes, red then green then blue.
fn checksum(img: &RgbImage) -> u64 {
    img.channels
        .iter()
        .flat_map(|p| p.data())
        .fold(0xcbf2_9ce4_8422_2325, |h, v| {
            (h ^ u64::from(v.to_bits())).wrapping_mul(0x100_0000_01b3)
        })
}

#[test]
fn pyramid_and_foveated_outputs_are_pinned_bit_for_bit() {
    let input = scene();
    // 48 px/deg, as a 960 px panel over 20 degrees: blur radii up to ~100 px at 3 D.
    let eye = EyeModel {
        fov_horizontal_deg: 5.0,
        ..EyeModel::default()
    };
    let mut got = Vec::new();
    for q in [0.4f32, 1.2, 2.0, 3.0] {
        got.push((
            format!("pyramid {q} D"),
            checksum(&pyramid(&input, Diopters(q), &eye).unwrap()),
        ));
    }
    let fov = Foveation {
        gaze: [90.0, 110.0],
        radius_deg: 0.5,
        mar_slope: DEFAULT_MAR_SLOPE,
    };
    let plan = FoveationPlan::new(W, H, &eye, &fov).unwrap();
    assert!(plan.layers.len() >= 3, "{:?}", plan.layers);
    for q in [0.4f32, 1.2, 3.0] {
        let f = foveated(&input, Diopters(q), &eye, &fov).unwrap();
        got.push((format!("foveated {q} D"), checksum(&f.image)));
    }
    let annulus = Region {
        x0: 20,
        y0: 10,
        x1: 230,
        y1: 190,
        centre: [120.0, 90.0],
        inner: 25.0,
        outer: 80.0,
    };
    got.push((
        "annulus 2 D".to_string(),
        checksum(&render_region(&input, Diopters(2.0), &eye, &annulus).unwrap()),
    ));
    for (name, sum) in &got {
        eprintln!("{name}: {sum:#018x}");
    }
    let want: [u64; 8] = [
        0xc19fa2090fb829ac,
        0x4ee814d5ea571d68,
        0x91a635effb96eea6,
        0x6fda8d3c5efa2645,
        0x5e7df793682db852,
        0x2de4d37f499d866a,
        0x2247a94fb36fc533,
        0x7e1131188d4d281d,
    ];
    for ((name, sum), want) in got.iter().zip(want) {
        assert_eq!(
            *sum, want,
            "{name}: checksum {sum:#018x}, pinned {want:#018x}"
        );
    }
}
