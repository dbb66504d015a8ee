//! Image-level use of a network: build its normalised inputs from RGB-D, run it, and turn
//! its outputs back into images. Colours are linear light, as everywhere in dioptra.

use crate::arch::{Task, COC_NORM, DEPTH_NORM};
use crate::cpu::{Act, CpuNet};
use crate::error::{input, NetError};
use crate::infer::Infer;
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};
use dioptra_render::{check_focus, eye_for, Layers};

/// C3/C4 input: [R, G, B, depth / 4] per pixel.
pub fn rgbd_input(rgbd: &Rgbd) -> Result<Act, NetError> {
    let (w, h) = (rgbd.width(), rgbd.height());
    let c = &rgbd.color.channels;
    let d = rgbd.depth.data();
    let mut data = Vec::with_capacity(w * h * 4);
    for (i, &di) in d.iter().enumerate().take(w * h) {
        data.extend_from_slice(&[
            c[0].data()[i],
            c[1].data()[i],
            c[2].data()[i],
            di / DEPTH_NORM,
        ]);
    }
    Act::new(h, w, 4, data)
}

/// C1 input: [R, G, B, depth / 4, CoC(depth, focus) in pixels / 30] per pixel.
pub fn defocus_input(rgbd: &Rgbd, focus: Diopters, eye: &EyeModel) -> Result<Act, NetError> {
    check_focus(focus)?;
    let eye = eye_for(eye, rgbd.width())?;
    let base = rgbd_input(rgbd)?;
    let d = rgbd.depth.data();
    let mut data = Vec::with_capacity(base.data.len() / 4 * 5);
    for (px, &dd) in base.data.chunks_exact(4).zip(d) {
        data.extend_from_slice(px);
        data.push(eye.coc_px(Diopters(dd), focus) / COC_NORM);
    }
    Act::new(base.h, base.w, 5, data)
}

/// Channels `3k..3k+3` of an HWC activation as an image.
pub fn rgb_at(a: &Act, k: usize) -> Result<RgbImage, NetError> {
    if 3 * k + 3 > a.c {
        return Err(input(format!("no RGB image {k} in {} channels", a.c)));
    }
    let plane = |j: usize| {
        Plane::from_vec(
            a.w,
            a.h,
            a.data.chunks_exact(a.c).map(|p| p[3 * k + j]).collect(),
        )
    };
    Ok(RgbImage::from_planes(plane(0)?, plane(1)?, plane(2)?)?)
}

/// C1: what the eye focused at `focus` sees of `rgbd`.
pub(crate) fn defocus(
    net: &impl Infer,
    rgbd: &Rgbd,
    focus: Diopters,
    eye: &EyeModel,
) -> Result<RgbImage, NetError> {
    net.arch().expect_task("c1")?;
    rgb_at(&net.forward(&defocus_input(rgbd, focus, eye)?)?, 0)
}

/// C4: multifocal layers for the network's display planes.
pub(crate) fn decompose(net: &impl Infer, rgbd: &Rgbd) -> Result<Layers, NetError> {
    net.arch().expect_task("c4")?;
    let Task::C4 { planes, .. } = &net.arch().task else {
        return Err(input("not a multifocal network"));
    };
    let y = net.forward(&rgbd_input(rgbd)?)?;
    Ok(Layers {
        planes: planes.iter().map(|&p| Diopters(p)).collect(),
        images: (0..planes.len())
            .map(|k| rgb_at(&y, k))
            .collect::<Result<_, _>>()?,
    })
}

impl CpuNet {
    /// C1: what the eye focused at `focus` sees of `rgbd`.
    pub fn defocus(
        &self,
        rgbd: &Rgbd,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<RgbImage, NetError> {
        defocus(self, rgbd, focus, eye)
    }

    /// C3: the focal stack at the network's foci.
    pub fn focal_stack(&self, rgbd: &Rgbd) -> Result<(Vec<Diopters>, Vec<RgbImage>), NetError> {
        self.arch().expect_task("c3")?;
        let Task::C3 { foci } = &self.arch().task else {
            return Err(input("not a focal-stack network"));
        };
        let y = self.forward(&rgbd_input(rgbd)?)?;
        let imgs = (0..foci.len())
            .map(|k| rgb_at(&y, k))
            .collect::<Result<_, _>>()?;
        Ok((foci.iter().map(|&q| Diopters(q)).collect(), imgs))
    }

    /// C4: multifocal layers for the network's display planes.
    pub fn decompose(&self, rgbd: &Rgbd) -> Result<Layers, NetError> {
        decompose(self, rgbd)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Arch, Weights};
    use dioptra_core::DepthMap;

    fn rgbd(w: usize, h: usize) -> Rgbd {
        let c = RgbImage::new(w, h, [0.2, 0.4, 0.6]);
        let d: Vec<f32> = (0..w * h).map(|i| 0.5 + (i % w) as f32 * 0.1).collect();
        Rgbd::new(
            c,
            DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap(),
        )
        .unwrap()
    }

    #[test]
    fn defocus_input_normalises_depth_and_coc() {
        let eye = EyeModel::default();
        let x = defocus_input(&rgbd(8, 2), Diopters(0.5), &eye).unwrap();
        let e = eye.with_width(8);
        let px = |i: usize| &x.data[i * 5..][..5];
        assert_eq!(&px(0)[..4], &[0.2, 0.4, 0.6, 0.5 / 4.0]);
        assert_eq!(px(0)[4], 0.0); // in focus
        let want = e.coc_px(Diopters(0.5 + 0.3), Diopters(0.5)) / 30.0;
        assert!((px(3)[4] - want).abs() < 1e-6);
        assert!(defocus_input(&rgbd(8, 2), Diopters(f32::NAN), &eye).is_err());
    }

    #[test]
    fn tasks_refuse_the_wrong_network() {
        let c1 = CpuNet::new(Weights::random(&Arch::c1_small(), 0).unwrap()).unwrap();
        let e = c1.decompose(&rgbd(8, 8)).unwrap_err();
        assert!(matches!(e, NetError::WrongConfig { .. }), "{e}");
        let c4 = CpuNet::new(Weights::random(&Arch::preset("c4").unwrap(), 0).unwrap()).unwrap();
        let l = c4.decompose(&rgbd(10, 6)).unwrap();
        assert_eq!((l.images.len(), l.width(), l.height()), (4, 10, 6));
        let img = c1
            .defocus(&rgbd(10, 6), Diopters(1.0), &EyeModel::default())
            .unwrap();
        assert_eq!((img.width(), img.height()), (10, 6));
    }
}
