//! Issue 54: the foveated pyramid render against the thin-lens truth, in the fovea and in the
//! periphery separately, on both backends, at a panel's pixel density (256 px over 5.33
//! degrees: 48 px/deg, as a 960 px panel over 20 degrees). The fovea must be within 0.5 dB of
//! the full-resolution gather's fovea; the periphery, rendered coarser on purpose, is reported
//! beside the full-resolution figures and kept within a bound. Without a GPU adapter the GPU
//! half says so and is skipped (DIOPTRA_REQUIRE_GPU=1 makes that a failure).

use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use dioptra_render::defocus::PyramidParams;
use dioptra_render::foveated::{Foveation, FoveationPlan, DEFAULT_MAR_SLOPE};
use dioptra_render::metrics::{disk_mask, invert_mask, psnr};
use dioptra_render::{Backend, Cpu, DefocusMethod, Gpu, GpuError};
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, Split};

fn gpu() -> Option<Gpu> {
    match Gpu::new(None) {
        Ok(g) => Some(g),
        Err(GpuError::NoAdapter) if std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1") => {
            eprintln!("GPU half skipped: no GPU adapter");
            None
        }
        Err(e) => panic!("GPU required (DIOPTRA_REQUIRE_GPU=1) or failed to open: {e}"),
    }
}

#[test]
fn foveated_fovea_is_within_0_5_db_of_gather_and_the_periphery_is_bounded() {
    const SIZE: usize = 256;
    let eye = EyeModel {
        fov_horizontal_deg: 5.33,
        ..EyeModel::default()
    };
    let cam = Camera::square(eye, SIZE);
    let ppd = SIZE as f32 / 5.33;
    let g = gpu();
    for (seed, gaze) in [(0u64, [110.0f32, 140.0]), (1, [150.0, 100.0])] {
        let scene = Scene::generate(Split::Test.seed(seed));
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 6).unwrap();
        let input = Rgbd::new(color, depth).unwrap();
        // Varifocal: the lens focuses at the gazed depth.
        let focus = Diopters(input.depth.data()[gaze[1] as usize * SIZE + gaze[0] as usize]);
        let fov = Foveation {
            gaze,
            radius_deg: 1.5,
            mar_slope: DEFAULT_MAR_SLOPE,
        };
        let plan = FoveationPlan::new(SIZE, SIZE, &eye, &fov).unwrap();
        assert!(plan.layers.len() >= 2, "{:?}", plan.layers);
        let truth = render_thin_lens(&scene, &cam, focus, 64).unwrap();
        let fovea = disk_mask(SIZE, SIZE, gaze, fov.radius_deg * ppd);
        let periphery = invert_mask(&fovea);
        let score = |img: &RgbImage| {
            (
                psnr(img, &truth, Some(&fovea)).unwrap(),
                psnr(img, &truth, Some(&periphery)).unwrap(),
            )
        };
        let one = |b: &dyn Backend, m: DefocusMethod| {
            b.defocus(&input, &[focus], &eye, m, &|_| {})
                .unwrap()
                .remove(0)
        };
        let foveated = DefocusMethod::Pyramid(PyramidParams {
            foveation: Some(fov),
        });
        let full = DefocusMethod::Pyramid(PyramidParams::default());
        let (gf, gp) = score(&one(&Cpu, DefocusMethod::Gather));
        let (pf, pp) = score(&one(&Cpu, full));
        let mut runs = vec![("cpu", score(&one(&Cpu, foveated)))];
        if let Some(g) = &g {
            runs.push(("gpu", score(&one(g, foveated))));
        }
        for (backend, (ff, fp)) in runs {
            eprintln!(
                "scene {seed}, gaze {gaze:?}, focus {:.2} D, {:.0} % of the pixels computed: fovea gather {gf:.2} / pyramid {pf:.2} / foveated ({backend}) {ff:.2} dB; periphery {gp:.2} / {pp:.2} / {fp:.2} dB",
                focus.0,
                100.0 * plan.work_fraction()
            );
            assert!(
                ff >= gf - 0.5,
                "{backend}: fovea {ff} dB vs gather's {gf} dB"
            );
            // The periphery is coarser by design: at most 6 dB below the full render's.
            assert!(
                fp >= pp - 6.0,
                "{backend}: periphery {fp} dB vs the full render's {pp} dB"
            );
        }
    }
}
