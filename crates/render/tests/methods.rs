//! Methods against analytic cases and against each other where physics says they agree.

use dioptra_core::{DepthMap, Diopters, EyeModel, Plane, RgbImage, Rgbd};
use dioptra_render::gather::gather;
use dioptra_render::lightfield::lightfield;
use dioptra_render::metrics::psnr;
use dioptra_render::retina::retina_varifocal;
use dioptra_render::{backend, DefocusMethod, LightFieldParams, RenderError};

fn texture(w: usize, h: usize) -> RgbImage {
    let f = |k: f32| -> Plane {
        let d = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                0.45 + 0.4 * ((x * 0.31 * k).sin() * (y * 0.23 + k).cos())
            })
            .collect();
        Plane::from_vec(w, h, d).unwrap()
    };
    RgbImage::from_planes(f(1.0), f(1.7), f(0.6)).unwrap()
}

fn flat_depth(w: usize, h: usize, d: f32) -> DepthMap {
    DepthMap::from_diopters(Plane::new(w, h, d)).unwrap()
}

#[test]
fn in_focus_plane_is_unchanged() {
    let (w, h) = (48, 40);
    let input = Rgbd::new(texture(w, h), flat_depth(w, h, 1.5)).unwrap();
    let eye = EyeModel::default();
    let g = gather(&input, Diopters(1.5), &eye).unwrap();
    let l = lightfield(&input, Diopters(1.5), &eye, LightFieldParams::default()).unwrap();
    assert!(psnr(&g, &input.color, None).unwrap() > 80.0);
    assert!(psnr(&l, &input.color, None).unwrap() > 80.0);
}

#[test]
fn defocused_plane_matches_disk_convolution() {
    // A single fronto-parallel plane: the thin-lens image is the input convolved with the
    // disk of the eye model's CoC, which is what the varifocal retina computes.
    let (w, h) = (128, 96);
    let eye = EyeModel::default();
    let input = Rgbd::new(texture(w, h), flat_depth(w, h, 3.0)).unwrap();
    let q = Diopters(0.5);
    let truth = retina_varifocal(&input.color, Diopters(3.0), q, &eye).unwrap();
    let g = gather(&input, q, &eye).unwrap();
    let l = lightfield(
        &input,
        q,
        &eye,
        LightFieldParams {
            views: 64,
            mip: true,
        },
    )
    .unwrap();
    let (pg, pl) = (
        psnr(&g, &truth, None).unwrap(),
        psnr(&l, &truth, None).unwrap(),
    );
    assert!(pg > 40.0, "gather {pg} dB");
    assert!(pl > 35.0, "lightfield {pl} dB");
}

#[test]
fn more_views_converge() {
    // Sampling error of the lens falls with the number of views.
    let (w, h) = (64, 64);
    let eye = EyeModel::default();
    let mut depth = Plane::new(w, h, 0.3);
    for (i, v) in depth.data_mut().iter_mut().enumerate() {
        if (i % w) > 20 && (i % w) < 40 {
            *v = 3.5;
        }
    }
    let input = Rgbd::new(texture(w, h), DepthMap::from_diopters(depth).unwrap()).unwrap();
    let q = Diopters(0.3);
    let reference = lightfield(
        &input,
        q,
        &eye,
        LightFieldParams {
            views: 256,
            mip: true,
        },
    )
    .unwrap();
    let e4 = psnr(
        &lightfield(
            &input,
            q,
            &eye,
            LightFieldParams {
                views: 4,
                mip: false,
            },
        )
        .unwrap(),
        &reference,
        None,
    )
    .unwrap();
    let e36 = psnr(
        &lightfield(
            &input,
            q,
            &eye,
            LightFieldParams {
                views: 36,
                mip: true,
            },
        )
        .unwrap(),
        &reference,
        None,
    )
    .unwrap();
    assert!(e36 > e4 + 3.0, "4 views {e4} dB, 36 views {e36} dB");
}

#[test]
fn backend_seam_and_bad_input() {
    let cpu = backend("cpu").unwrap();
    assert_eq!(cpu.name(), "cpu");
    // The GPU backend opens when an adapter exists and says so clearly when none does.
    match backend("wgpu") {
        Ok(g) => assert_eq!(g.name(), "gpu"),
        Err(e) => assert!(
            matches!(e, RenderError::Gpu(dioptra_render::GpuError::NoAdapter)),
            "{e}"
        ),
    }
    assert!(backend("nope").is_err());
    let input = Rgbd::new(texture(8, 8), flat_depth(8, 8, 1.0)).unwrap();
    let eye = EyeModel::default();
    for q in [f32::NAN, -2000.0, f32::INFINITY] {
        assert!(cpu
            .defocus(&input, &[Diopters(q)], &eye, DefocusMethod::Gather, &|_| {})
            .is_err());
    }
    let bad = LightFieldParams {
        views: 0,
        mip: true,
    };
    assert!(cpu
        .defocus(
            &input,
            &[Diopters(1.0)],
            &eye,
            DefocusMethod::LightField(bad),
            &|_| {}
        )
        .is_err());
    let bad_eye = EyeModel {
        fov_horizontal_deg: f32::NAN,
        ..eye
    };
    assert!(gather(&input, Diopters(1.0), &bad_eye).is_err());
    // A focal stack calls progress once per slice and returns one image per focus.
    let done = std::sync::atomic::AtomicUsize::new(0);
    let foci = [Diopters(0.5), Diopters(1.0), Diopters(2.0)];
    let stack = cpu
        .defocus(
            &input,
            &foci,
            &eye,
            DefocusMethod::LightField(LightFieldParams::default()),
            &|n| done.store(n, std::sync::atomic::Ordering::Relaxed),
        )
        .unwrap();
    assert_eq!(stack.len(), 3);
    assert_eq!(done.load(std::sync::atomic::Ordering::Relaxed), 3);
}

#[test]
fn focus_at_and_beyond_infinity_blurs_by_the_same_formula() {
    // A plane at 1 D seen focused at -1 D is as far out of focus (2 D) as one focused at
    // 3 D: the same CoC, the same image. 0 D (optical infinity) blurs it by 1 D.
    let (w, h) = (64, 48);
    // A 3 degree field: 1 D of defocus blurs over about 5 pixels.
    let eye = EyeModel {
        fov_horizontal_deg: 3.0,
        ..EyeModel::default()
    };
    let input = Rgbd::new(texture(w, h), flat_depth(w, h, 1.0)).unwrap();
    let params = LightFieldParams {
        views: 24,
        mip: true,
    };
    for (beyond, near) in [(-1.0, 3.0), (0.0, 2.0)] {
        let g = gather(&input, Diopters(beyond), &eye).unwrap();
        assert_eq!(
            g,
            gather(&input, Diopters(near), &eye).unwrap(),
            "gather at {beyond} D"
        );
        let truth = retina_varifocal(&input.color, Diopters(1.0), Diopters(beyond), &eye).unwrap();
        let truth_near =
            retina_varifocal(&input.color, Diopters(1.0), Diopters(near), &eye).unwrap();
        assert!(psnr(&truth, &truth_near, None).unwrap() > 60.0);
        assert!(psnr(&g, &truth, None).unwrap() > 30.0);
        // The light field samples the pupil mirrored: as accurate, not bit-identical.
        let l = lightfield(&input, Diopters(beyond), &eye, params).unwrap();
        let l_near = lightfield(&input, Diopters(near), &eye, params).unwrap();
        let (pb, pn) = (
            psnr(&l, &truth, None).unwrap(),
            psnr(&l_near, &truth, None).unwrap(),
        );
        assert!(
            pb > 35.0 && pn > 35.0,
            "light field at {beyond} D: {pb} vs {pn} dB"
        );
        // Blurred: not the input.
        assert!(psnr(&g, &input.color, None).unwrap() < 30.0);
    }
    // Display planes stay at optical infinity or nearer.
    assert!(retina_varifocal(&input.color, Diopters(-0.5), Diopters(1.0), &eye).is_err());
}
