//! Each eye's view of a content frame on a stereo layout (`display.layout` side-by-side or
//! two-outputs), made once per content frame:
//! - stereo content (a lab's left and right files, a stream's two halves): its own views;
//! - the procedural scene: ray cast from each eye's position, IPD apart on the horizontal,
//!   both looking straight ahead (parallel, as a stereo HMD's displays are: the eyes verge,
//!   the cameras do not): the rig's animated scene casts them on its own worker thread, ahead
//!   of the loop ([`super::scene`]); a frame that brings its scene but not its eyes' views (the
//!   demo's) has them cast here;
//! - one RGB-D (mono files or stream): each eye's view synthesised from it at that eye's
//!   position (`dioptra_render::views`), so a lab with one RGB-D still gets disparity.
//!   Disoccluded pixels are filled from the background side, as the light-field method's are.

use std::sync::{Arc, Mutex};

use dioptra_core::{lock, EyeModel, Rgbd, Side};
use dioptra_render::views::{synthesize_rgbd_view, RgbdView};
use dioptra_render::RenderError;
use dioptra_sim::scene::Camera;

use super::ContentFrame;
use crate::display::config::Display;
use crate::optics::config::Eye;

/// Where each eye's view comes from, for the `/status` and the log.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ViewSource {
    /// The content's own two views.
    Stereo,
    /// Ray cast from the procedural scene at each eye.
    SceneRayCast,
    /// Synthesised from one RGB-D.
    Synthesised,
}

/// The views made from one content frame (its number).
type Made = (u64, [Arc<Rgbd>; 2], ViewSource);

/// Makes (and keeps, for the newest content frame) each eye's view.
pub struct EyeViews {
    cam: Camera,
    eye: EyeModel,
    half_ipd_m: f32,
    newest: Mutex<Option<Made>>,
    status: Mutex<EyeViewsStatus>,
}

/// What `/status` shows under `eye_views`.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct EyeViewsStatus {
    /// Where the newest views came from.
    pub source: Option<ViewSource>,
    /// Content frames whose views were made, and how many failed (the newest reason).
    pub made: u64,
    pub failed: u64,
    pub last_error: Option<String>,
    /// What making the newest took, ms (wall clock; both eyes).
    pub last_ms: Option<f64>,
    /// Half the interpupillary distance, mm: each eye's distance from the cyclopean eye.
    pub half_ipd_mm: f32,
}

impl std::fmt::Debug for EyeViews {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EyeViews")
            .field("half_ipd_m", &self.half_ipd_m)
            .finish_non_exhaustive()
    }
}

impl EyeViews {
    /// The eyes of `[eye]`: `ipd_mm` apart, seeing the display's field.
    pub fn new(eye: &Eye, display: &Display) -> Result<EyeViews, RenderError> {
        Ok(EyeViews {
            cam: super::scene::camera(eye, display)?,
            eye: eye.model(display.width).validated()?,
            half_ipd_m: eye.ipd_mm * 0.5e-3,
            newest: Mutex::new(None),
            status: Mutex::new(EyeViewsStatus {
                half_ipd_mm: eye.ipd_mm * 0.5,
                ..EyeViewsStatus::default()
            }),
        })
    }

    pub fn status(&self) -> serde_json::Value {
        serde_json::to_value(&*lock(&self.status)).unwrap_or_default()
    }

    /// An eye's position, metres from the cyclopean eye (+x right).
    pub fn position(&self, side: Side) -> [f32; 2] {
        match side {
            Side::Left => [-self.half_ipd_m, 0.0],
            Side::Right => [self.half_ipd_m, 0.0],
        }
    }

    /// The left and right eye's views of `frame`, and where they came from. CPU work (a ray
    /// cast or a synthesis per eye on a new frame): call it from a blocking thread.
    pub fn of(&self, frame: &ContentFrame) -> Result<([Arc<Rgbd>; 2], ViewSource), RenderError> {
        if let Some((n, views, source)) = lock(&self.newest).as_ref() {
            if *n == frame.number {
                return Ok((views.clone(), *source));
            }
        }
        let started = std::time::Instant::now();
        let made = self.make(frame);
        let mut st = lock(&self.status);
        match &made {
            Ok((_, source)) => {
                st.made += 1;
                st.source = Some(*source);
                st.last_ms = Some(started.elapsed().as_secs_f64() * 1e3);
            }
            Err(e) => {
                st.failed += 1;
                st.last_error = Some(e.to_string());
            }
        }
        made
    }

    fn make(&self, frame: &ContentFrame) -> Result<([Arc<Rgbd>; 2], ViewSource), RenderError> {
        let (views, source) = match (&frame.eyes, &frame.scene) {
            // The rig's scene casts its eyes' views on its own worker.
            (Some(eyes), Some(_)) => (eyes.clone(), ViewSource::SceneRayCast),
            (Some(eyes), None) => (eyes.clone(), ViewSource::Stereo),
            (None, Some(scene)) => (
                super::scene::cast_eyes(scene, &self.cam, self.half_ipd_m)?,
                ViewSource::SceneRayCast,
            ),
            (None, None) => {
                let input = [RgbdView {
                    position: [0.0, 0.0],
                    rgbd: frame.rgbd.as_ref().clone(),
                }];
                let synth = |side| -> Result<Arc<Rgbd>, RenderError> {
                    Ok(Arc::new(synthesize_rgbd_view(
                        &input,
                        self.position(side),
                        &self.eye,
                    )?))
                };
                let (l, r) = rayon::join(|| synth(Side::Left), || synth(Side::Right));
                ([l?, r?], ViewSource::Synthesised)
            }
        };
        let mut newest = lock(&self.newest);
        if newest.as_ref().is_none_or(|(n, _, _)| *n <= frame.number) {
            *newest = Some((frame.number, views.clone(), source));
        }
        Ok((views, source))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{RigConfig, EXAMPLE_SIM_BINOCULAR_RIG};
    use crate::content::scene::Pacing;
    use dioptra_core::Timestamp;

    fn binocular() -> RigConfig {
        RigConfig::parse(
            &(EXAMPLE_SIM_BINOCULAR_RIG.to_string() + "\n[content]\nanimate = false\n"),
        )
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

    #[test]
    fn one_rgbd_gives_each_eye_a_view_close_to_the_one_ray_cast_there() {
        let cfg = binocular();
        let content = crate::content::open(
            &cfg.content,
            &cfg.display,
            &cfg.eye,
            &cfg.api,
            Pacing::Simulated,
        )
        .unwrap();
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
            let unshifted =
                dioptra_render::metrics::psnr(&c.color, &mono.rgbd.color, None).unwrap();
            eprintln!("eye {eye}: {p:.1} dB, unshifted {unshifted:.1} dB");
            // Objects at 26 cm shift 66 px of 96 between the eyes: what only one eye sees is
            // filled from the background, so the synthesised view is far from exact; but it
            // is that eye's view (measured: 18.5 and 19.3 dB, left and right, against 14.4 and
            // 14.1 dB unshifted).
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
}
