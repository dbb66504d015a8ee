//! A defocus render that is exact where depth is smooth: the light field only on the pixels a
//! blurred depth step reaches, and gather's value ([`gather_smooth`]: the colour's mean over
//! the pixel's own CoC disk) everywhere else. There the depth within each blur disk is smooth,
//! so the disk blur is what the thin lens sees and the light field's few views would only add
//! their sampling of the pupil and their prefilter. C1R refines this render
//! (`dioptra_net::refine`), and the spectral decomposition can fit a focal stack of it
//! ([`crate::spectral::SpectralTargets::Composite`]).

use crate::common::{check_focus, eye_for};
use crate::error::{invalid, mismatch, RenderError};
use crate::gather::gather_smooth;
use crate::lightfield::{LightFieldParams, LightFieldPrep};
use dioptra_core::{DepthMap, Diopters, EyeModel, RgbImage, Rgbd};
use rayon::prelude::*;

/// A depth step between neighbouring pixels matters when the two depths' blurs differ by
/// this many pixels (CoC diameter of the step itself): below it the single-layer assumption
/// of gather holds.
pub const EDGE_BLUR_PX: f32 = 1.0;

/// Where the blurred depth steps of a depth map reach at one focus (see [`step_reach`]).
#[derive(Debug, Clone, PartialEq)]
pub struct StepReach {
    pub width: usize,
    pub height: usize,
    /// Per pixel, row-major: whether a blurred depth step's disk reaches it.
    pub reached: Vec<bool>,
    /// Per pixel: reached, and missing something a single view cannot show (see
    /// [`step_reach`]), and blurred by at least the asked own-blur threshold itself.
    pub lacking: Vec<bool>,
}

/// A depth step from a pixel to its right or lower neighbour (see [`StepScan`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Step {
    /// The pixel's column (its row is the row scanned).
    pub x: usize,
    /// Reach (pixels) of the nearer side's blur, when it blurs by half a pixel or more: its
    /// disk (radius CoC / 2, plus one pixel) covers the box [x - r, x + 1 + r] x
    /// [y - r, y + 1 + r].
    pub near: Option<usize>,
    /// Reach of the farther side's blur, likewise.
    pub far: Option<usize>,
    /// The step's middle, diopters.
    pub middle: f32,
}

/// The depth-edge scan of a depth map at one focus: the one definition of which pairs of
/// neighbouring pixels are blurred depth steps and how far their blur reaches, used by
/// [`step_reach`] and by the refinement nets' plain reference of it (`dioptra_net`).
pub struct StepScan<'a> {
    depth: &'a [f32],
    width: usize,
    height: usize,
    focus: f32,
    /// CoC diameter (pixels) per diopter of defocus.
    px_per_d: f32,
}

impl<'a> StepScan<'a> {
    pub fn new(depth: &'a DepthMap, focus: Diopters, eye: &EyeModel) -> Result<Self, RenderError> {
        check_focus(focus)?;
        let eye = eye_for(eye, depth.width())?;
        Ok(StepScan {
            depth: depth.data(),
            width: depth.width(),
            height: depth.height(),
            focus: focus.0,
            px_per_d: eye.coc_px(Diopters(1.0), Diopters(0.0)),
        })
    }

    /// CoC diameter (pixels) per diopter of defocus.
    pub fn px_per_d(&self) -> f32 {
        self.px_per_d
    }

    /// The steps from each pixel of row `y` to its right and lower neighbours: a pair is a
    /// step when their depths differ by at least [`EDGE_BLUR_PX`] of blur and one side blurs
    /// by half a pixel or more.
    pub fn row(&self, y: usize) -> Vec<Step> {
        let (w, h, d, q, px_per_d) = (
            self.width,
            self.height,
            self.depth,
            self.focus,
            self.px_per_d,
        );
        let mut row = Vec::new();
        if y >= h {
            return row;
        }
        for x in 0..w {
            let a = d[y * w + x];
            for (nx, ny) in [(x + 1, y), (x, y + 1)] {
                if nx >= w || ny >= h {
                    continue;
                }
                let b = d[ny * w + nx];
                if (a - b).abs() * px_per_d < EDGE_BLUR_PX {
                    continue;
                }
                // Diopters: the nearer side is the larger.
                let (near, far) = (a.max(b), a.min(b));
                let r_near = 0.5 * (near - q).abs() * px_per_d;
                let r_far = 0.5 * (far - q).abs() * px_per_d;
                if r_near.max(r_far) < 0.5 {
                    continue;
                }
                let reach = |r: f32| (r >= 0.5).then(|| r.ceil() as usize + 1);
                row.push(Step {
                    x,
                    near: reach(r_near),
                    far: reach(r_far),
                    middle: 0.5 * (near + far),
                });
            }
        }
        row
    }
}

/// The pixels the blurred depth steps reach at focus `focus`, from depth alone (BokehMe's
/// error map). A pair of neighbouring pixels is a step when their depths differ by at least
/// [`EDGE_BLUR_PX`] of blur; it can affect the pixels its sides' blur disks reach (radius
/// CoC / 2, plus one pixel), and nothing when neither side blurs by half a pixel.
///
/// `lacking` keeps, of those, what a single view lacks. The farther side's blur counts only
/// on its own pixels: behind a sharp occluder the occluder's pixels are what a single view and
/// the thin lens both see. The nearer side's blur counts on both sides when the farther side
/// blurs too, but only on its own pixels when the farther side is sharp: a sharp pixel beside
/// a blurred occluder sees itself and the occluder along every ray through the pupil, both in
/// the image, while the occluder's own pixels hide the background its blur uncovers. A pixel
/// blurred by less than `min_own_blur_px` (CoC diameter, pixels) itself never lacks anything.
pub fn step_reach(
    depth: &DepthMap,
    focus: Diopters,
    eye: &EyeModel,
    min_own_blur_px: f32,
) -> Result<StepReach, RenderError> {
    check_focus(focus)?;
    if !(min_own_blur_px.is_finite() && min_own_blur_px >= 0.0) {
        return Err(invalid(format!(
            "the own-blur threshold must be a finite number of pixels >= 0, not {min_own_blur_px}"
        )));
    }
    let scan = StepScan::new(depth, focus, eye)?;
    let (w, h) = (depth.width(), depth.height());
    let px_per_d = scan.px_per_d();
    let d = depth.data();
    let q = focus.0;
    // Pass 1, rows in parallel: the steps from each pixel to its right and lower neighbours
    // that blur by half a pixel or more.
    let steps: Vec<Vec<Step>> = (0..h).into_par_iter().map(|y| scan.row(y)).collect();
    let mut out = StepReach {
        width: w,
        height: h,
        reached: vec![false; w * h],
        lacking: vec![false; w * h],
    };
    let reach_max = steps
        .iter()
        .flatten()
        .map(|s| s.near.max(s.far).unwrap_or(0))
        .max()
        .unwrap_or(0);
    if steps.iter().all(|r| r.is_empty()) {
        return Ok(out);
    }
    // Pass 2, output rows in parallel: a pixel lacks something when a nearer side's disk
    // reaches it and either that step's farther side blurs or the pixel lies before its
    // middle, or a farther side's disk reaches it and the pixel lies behind that step's
    // middle. A step at (x, sy) with reach r covers the box [x - r, x + 1 + r] x
    // [sy - r, sy + 1 + r].
    out.lacking
        .par_chunks_mut(w)
        .zip(out.reached.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (lacking, reached))| {
            let mut near_reach = vec![false; w];
            let mut near_middle = vec![f32::INFINITY; w];
            let mut far_middle = vec![f32::NEG_INFINITY; w];
            let span = |x: usize, r: usize| x.saturating_sub(r)..(x + 2 + r).min(w);
            for (sy, row) in steps
                .iter()
                .enumerate()
                .take(y + reach_max + 1)
                .skip(y.saturating_sub(reach_max + 1))
            {
                let covers = |r: usize| y + r >= sy && y <= sy + 1 + r;
                for s in row {
                    if let Some(r) = s.near.filter(|&r| covers(r)) {
                        if s.far.is_some() {
                            near_reach[span(s.x, r)].fill(true);
                        } else {
                            for m in &mut near_middle[span(s.x, r)] {
                                *m = m.min(s.middle);
                            }
                        }
                    }
                    if let Some(r) = s.far.filter(|&r| covers(r)) {
                        for m in &mut far_middle[span(s.x, r)] {
                            *m = m.max(s.middle);
                        }
                    }
                }
            }
            for (x, (p, r)) in lacking.iter_mut().zip(reached.iter_mut()).enumerate() {
                let v = d[y * w + x];
                *p = (near_reach[x] || v > near_middle[x] || v < far_middle[x])
                    && (v - q).abs() * px_per_d >= min_own_blur_px;
                *r = near_reach[x] || near_middle[x].is_finite() || far_middle[x].is_finite();
            }
        });
    Ok(out)
}

/// `light` (a light-field render at `focus`, or any render right across depth steps) on the
/// pixels in `reached`, [`gather_smooth`]'s value on the rest.
pub fn compose(
    rgbd: &Rgbd,
    light: &RgbImage,
    reached: &[bool],
    focus: Diopters,
    eye: &EyeModel,
) -> Result<RgbImage, RenderError> {
    let (w, h) = (rgbd.width(), rgbd.height());
    if (light.width(), light.height()) != (w, h) || reached.len() != w * h {
        return Err(mismatch(format!(
            "a {}x{} render and a mask of {} pixels for a {w}x{h} RGB-D",
            light.width(),
            light.height(),
            reached.len()
        )));
    }
    let smooth: Vec<bool> = reached.iter().map(|r| !r).collect();
    if !smooth.contains(&true) {
        return Ok(light.clone());
    }
    let mut out = gather_smooth(rgbd, focus, eye, &smooth)?;
    for (o, c) in out.channels.iter_mut().zip(&light.channels) {
        for ((v, &k), &r) in o.data_mut().iter_mut().zip(c.data()).zip(reached) {
            if r {
                *v = k;
            }
        }
    }
    Ok(out)
}

/// The composite focal stack of `input` at `foci` on the CPU: the light field (only at the
/// foci where some blurred step reaches a pixel, and there only on the reached pixels)
/// composed with [`gather_smooth`].
pub fn composite_stack(
    input: &Rgbd,
    foci: &[Diopters],
    eye: &EyeModel,
    light: LightFieldParams,
) -> Result<Vec<RgbImage>, RenderError> {
    composite_stack_with(input, foci, eye, |need, masks| {
        let prep = LightFieldPrep::new(input, eye, light)?;
        need.iter()
            .zip(masks)
            .map(|(&q, m)| prep.render_masked(q, Some(m)))
            .collect()
    })
}

/// [`composite_stack`] with the light field rendered by `light` at the foci given it, each
/// with the mask of the pixels that will be kept from it (a renderer may fill only those).
pub fn composite_stack_with(
    input: &Rgbd,
    foci: &[Diopters],
    eye: &EyeModel,
    light: impl FnOnce(&[Diopters], &[&[bool]]) -> Result<Vec<RgbImage>, RenderError>,
) -> Result<Vec<RgbImage>, RenderError> {
    let reach: Vec<StepReach> = foci
        .iter()
        .map(|&q| step_reach(&input.depth, q, eye, 0.0))
        .collect::<Result<_, _>>()?;
    let (need, masks): (Vec<Diopters>, Vec<&[bool]>) = foci
        .iter()
        .zip(&reach)
        .filter(|(_, r)| r.reached.contains(&true))
        .map(|(&q, r)| (q, r.reached.as_slice()))
        .unzip();
    let mut lf = if need.is_empty() {
        Vec::new()
    } else {
        light(&need, &masks)?
    }
    .into_iter();
    let blank = RgbImage::new(input.width(), input.height(), [0.0; 3]);
    let light: Vec<RgbImage> = reach
        .iter()
        .map(|r| {
            if r.reached.contains(&true) {
                lf.next()
                    .ok_or_else(|| mismatch("the light field made fewer images than foci"))
            } else {
                Ok(blank.clone())
            }
        })
        .collect::<Result<_, _>>()?;
    foci.par_iter()
        .zip(&reach)
        .zip(&light)
        .map(|((&q, r), l)| compose(input, l, &r.reached, q, eye))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_core::Plane;

    /// 4 px of blur per diopter at 64 px.
    fn eye() -> EyeModel {
        EyeModel {
            fov_horizontal_deg: 5.0,
            ..EyeModel::default()
        }
    }

    fn rgbd(w: usize, h: usize, depth: impl Fn(usize) -> f32) -> Rgbd {
        let ch = |k: usize| {
            Plane::from_vec(
                w,
                h,
                (0..w * h)
                    .map(|i| 0.2 + 0.6 * ((i * k) % 13) as f32 / 13.0)
                    .collect(),
            )
            .unwrap()
        };
        let d = (0..w * h).map(|i| depth(i % w)).collect();
        Rgbd::new(
            RgbImage::from_planes(ch(7), ch(31), ch(5)).unwrap(),
            DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap(),
        )
        .unwrap()
    }

    #[test]
    fn the_light_field_is_asked_for_only_where_a_blurred_step_reaches() {
        let (w, h) = (64, 24);
        let eye = eye();
        // A 1 D step at column 32, focused on its near side (1.5 D) and at 0.5 D: the near
        // focus blurs the far side, the far focus the near side.
        let input = rgbd(w, h, |x| if x < 32 { 1.5 } else { 0.5 });
        let foci = [Diopters(1.5), Diopters(0.5)];
        let light = RgbImage::new(w, h, [2.0; 3]);
        let mut asked = Vec::new();
        let mut masks = Vec::new();
        let stack = composite_stack_with(&input, &foci, &eye, |need, m| {
            asked = need.to_vec();
            masks = m.iter().map(|m| m.to_vec()).collect();
            Ok(vec![light.clone(); need.len()])
        })
        .unwrap();
        assert_eq!(asked, foci.to_vec());
        for ((img, &q), mask) in stack.iter().zip(&foci).zip(&masks) {
            let reach = step_reach(&input.depth, q, &eye, 0.0).unwrap();
            assert_eq!(
                mask, &reach.reached,
                "the light field is told which pixels are kept"
            );
            let smooth: Vec<bool> = reach.reached.iter().map(|r| !r).collect();
            let g = gather_smooth(&input, q, &eye, &smooth).unwrap();
            assert!(reach.reached.contains(&true) && smooth.contains(&true));
            for c in 0..3 {
                for (i, &v) in img.channels[c].data().iter().enumerate() {
                    let want = if reach.reached[i] {
                        2.0
                    } else {
                        g.channels[c].data()[i]
                    };
                    assert_eq!(v, want, "focus {q}, pixel {i}");
                }
            }
            // The reached pixels lie about the step, within its blur's reach.
            let r = (0.5
                * eye
                    .with_width(w as u32)
                    .coc_px(Diopters(1.5), Diopters(0.5)))
            .ceil() as usize
                + 1;
            for x in 0..w {
                assert_eq!(
                    reach.reached[x],
                    (31usize.saturating_sub(r)..=32 + r).contains(&x),
                    "focus {q}, column {x}"
                );
            }
        }
        // Smooth depth (a slope far below a pixel of blur per pixel): no light field at all.
        let slope = rgbd(w, h, |x| 0.5 + x as f32 / w as f32);
        let stack = composite_stack_with(&slope, &foci, &eye, |need, _| {
            assert!(need.is_empty(), "light field asked for at {need:?}");
            Ok(Vec::new())
        })
        .unwrap();
        let all = vec![true; w * h];
        for (img, &q) in stack.iter().zip(&foci) {
            assert_eq!(img, &gather_smooth(&slope, q, &eye, &all).unwrap());
        }
    }

    #[test]
    fn the_masked_light_field_makes_the_same_stack_as_the_full_one() {
        let eye = eye();
        let input = rgbd(64, 24, |x| if (20..40).contains(&x) { 2.0 } else { 0.3 });
        let foci = [Diopters(0.3), Diopters(1.2), Diopters(2.0)];
        let light = LightFieldParams {
            views: 12,
            mip: true,
        };
        let full = composite_stack_with(&input, &foci, &eye, |need, _| {
            let prep = LightFieldPrep::new(&input, &eye, light)?;
            need.iter().map(|&q| prep.render(q)).collect()
        })
        .unwrap();
        let masked = composite_stack(&input, &foci, &eye, light).unwrap();
        assert_eq!(masked, full);
        // The mask keeps the light field where it is true and the input colour elsewhere.
        let prep = LightFieldPrep::new(&input, &eye, light).unwrap();
        let mask: Vec<bool> = (0..64 * 24).map(|i| i % 64 < 32).collect();
        let half = prep.render_masked(Diopters(1.2), Some(&mask)).unwrap();
        let all = prep.render(Diopters(1.2)).unwrap();
        for c in 0..3 {
            for (i, &v) in half.channels[c].data().iter().enumerate() {
                let want = if mask[i] {
                    all.channels[c].data()[i]
                } else {
                    input.color.channels[c].data()[i]
                };
                assert_eq!(v, want, "pixel {i}");
            }
        }
        assert!(prep.render_masked(Diopters(1.2), Some(&mask[1..])).is_err());
    }

    #[test]
    fn bad_input_is_an_error() {
        let input = rgbd(16, 8, |_| 1.0);
        let e = eye();
        for bad in [-1.0, f32::NAN, f32::INFINITY] {
            assert!(step_reach(&input.depth, Diopters(1.0), &e, bad).is_err());
        }
        assert!(step_reach(&input.depth, Diopters(f32::NAN), &e, 0.0).is_err());
        let light = RgbImage::new(16, 8, [0.5; 3]);
        assert!(compose(&input, &light, &[false; 16 * 7], Diopters(1.0), &e).is_err());
        let small = RgbImage::new(15, 8, [0.5; 3]);
        assert!(compose(&input, &small, &[false; 16 * 8], Diopters(1.0), &e).is_err());
        // A light field that renders too few images is an error, not a panic.
        let step = rgbd(16, 8, |x| if x < 8 { 3.0 } else { 0.2 });
        assert!(composite_stack_with(&step, &[Diopters(0.2)], &e, |_, _| Ok(Vec::new())).is_err());
    }
}
