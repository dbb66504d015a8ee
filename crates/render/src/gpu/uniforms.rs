//! The uniform layouts of the shaders checked against the Rust structs the host writes (tests
//! only): a module of its own above `kernels` and `spectral`, whose structs it reads.

use super::context::{with_shared, Kernel};
use super::kernels::{FovP, GatherP, LensletP, LfP, OptP, SizeP};
use super::pyramid::{FoveatedP, PyramidP};
use super::spectral::SpecP;

/// The uniform `Params` of a shader file of this crate, as naga lays it out: (member, offset,
/// size) and the struct's size. Also for the passes outside the backend (`transfer::gpu`,
/// `warp::gpu`).
pub(crate) fn wgsl_uniform(src: &str) -> (Vec<(String, u32, u32)>, u32) {
    let module = naga::front::wgsl::parse_str(&with_shared(src))
        .unwrap_or_else(|e| panic!("WGSL does not parse: {e}"));
    let mut layouter = naga::proc::Layouter::default();
    layouter.update(module.to_ctx()).expect("layout");
    let (_, ty) = module
        .types
        .iter()
        .find(|(_, t)| t.name.as_deref() == Some("Params"))
        .expect("a uniform struct named Params");
    match &ty.inner {
        naga::TypeInner::Struct { members, span } => (
            members
                .iter()
                .map(|m| {
                    (
                        m.name.clone().unwrap_or_default(),
                        m.offset,
                        layouter[m.ty].size,
                    )
                })
                .collect(),
            *span,
        ),
        other => panic!("Params is {other:?}"),
    }
}

/// A uniform struct of the host code in [`wgsl_uniform`]'s form: each listed field's name,
/// offset and size, and the struct's size.
macro_rules! rust_uniform {
    ($t:ty; $($f:ident),* $(,)?) => {{
        let z: $t = bytemuck::Zeroable::zeroed();
        let fields: Vec<(String, u32, u32)> = vec![$((
            stringify!($f).to_string(),
            std::mem::offset_of!($t, $f) as u32,
            std::mem::size_of_val(&z.$f) as u32,
        )),*];
        (fields, std::mem::size_of::<$t>() as u32)
    }};
}
pub(crate) use rust_uniform;

/// Every shader's uniform as naga lays it out is the Rust struct the host writes: the
/// same members (by name, where the struct is the shader's own) at the same offsets.
#[test]
fn uniform_layouts_match_the_shaders() {
    let sizes = || rust_uniform!(SizeP; w, h, k, _pad);
    let named = [
        (
            Kernel::Gather,
            rust_uniform!(GatherP; w, h, n_off, reach, focus, pupil_m, pitch, _pad),
        ),
        (
            Kernel::LfPrefilter,
            rust_uniform!(LfP; w, h, nv, v0, focus, pupil_m, pitch, spacing, lens_f, top,
                nlev, dstride),
        ),
        (
            Kernel::OptStep,
            rust_uniform!(OptP; pw, ph, np, nf, step, mom, len, _pad),
        ),
        (
            Kernel::Lenslet,
            rust_uniform!(LensletP; w, h, vw, vh, grid, _pad0, _pad1, _pad2),
        ),
        (
            Kernel::FovMask,
            rust_uniform!(FovP; w, h, rings, angles, cx, cy, gw, gh),
        ),
        (
            Kernel::PyCompose,
            rust_uniform!(PyramidP; w, h, top, level, k, q, kind, n_off, region, annulus, rec,
                out, edges, levels),
        ),
        (
            Kernel::FvBlend,
            rust_uniform!(FoveatedP; w, h, a, b, top, present, _pad0, _pad1, offsets),
        ),
        (
            Kernel::SpFftPass,
            rust_uniform!(SpecP; n, lines, ns, radix, tw_off, inverse, pw, ph, hw, count, w,
                h, margin, rows, cols, off, row_pitch, plane_pitch, dst, img_pitch, scale,
                step, mom, flag),
        ),
    ];
    // Kernels whose shader reads SizeP under names of its own (w, h, a count, padding).
    let sized = [
        Kernel::LinearBlend,
        Kernel::Convolve,
        Kernel::BlurH,
        Kernel::PsnrSum,
        Kernel::ViewResolve,
    ];
    let mut checked = Vec::new();
    for (k, (rust, size)) in &named {
        let (wgsl, wsize) = wgsl_uniform(k.spec().0);
        assert_eq!(&wgsl, rust, "{k:?}'s Params against the host's");
        assert_eq!(wsize, *size, "{k:?}'s Params size");
        checked.push(k.spec().0.as_ptr());
    }
    for k in sized {
        let (wgsl, wsize) = wgsl_uniform(k.spec().0);
        let (rust, size) = sizes();
        let layout = |v: &[(String, u32, u32)]| v.iter().map(|m| (m.1, m.2)).collect::<Vec<_>>();
        assert_eq!(layout(&wgsl), layout(&rust), "{k:?}'s Params against SizeP");
        assert_eq!(wsize, size, "{k:?}'s Params size");
        checked.push(k.spec().0.as_ptr());
    }
    for k in Kernel::ALL {
        assert!(
            checked.contains(&k.spec().0.as_ptr()),
            "{k:?}'s shader has no uniform check"
        );
    }
}
