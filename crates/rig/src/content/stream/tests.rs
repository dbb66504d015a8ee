use super::decode::srgb_lut;
use super::*;
use crate::content::ring::{Ring, SlotHeader};
use dioptra_core::{DepthMap, Plane, RgbImage, Rgbd, Side};

fn desc(w: usize, h: usize, color: ColorFormat, depth: DepthKind) -> FrameDesc {
    FrameDesc {
        width: w,
        height: h,
        color,
        depth,
        near: Some(0.1),
        far: Some(100.0),
        seq: None,
        app_time_ns: None,
    }
}

fn f32s(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// A depth buffer value of a point at `z` metres, by each API's projection.
fn buffer_value(kind: DepthKind, z: f64, n: f64, f: f64) -> f32 {
    let vk = if f.is_infinite() {
        1.0 - n / z
    } else {
        f * (z - n) / (z * (f - n))
    };
    let gl = if f.is_infinite() {
        1.0 - 2.0 * n / z
    } else {
        (f + n - 2.0 * f * n / z) / (f - n)
    };
    (match kind {
        DepthKind::Vulkan => vk,
        DepthKind::VulkanReversed => 1.0 - vk,
        DepthKind::Gl => gl,
        DepthKind::GlReversed => -gl,
        _ => unreachable!(),
    }) as f32
}

#[test]
fn every_depth_convention_gives_the_same_diopters() {
    for kind in [
        DepthKind::Gl,
        DepthKind::GlReversed,
        DepthKind::Vulkan,
        DepthKind::VulkanReversed,
    ] {
        for far in [100.0f64, f64::INFINITY] {
            for z in [0.25f64, 0.5, 1.0, 2.0, 10.0] {
                let v = buffer_value(kind, z, 0.1, far);
                let d = kind.diopters(v, 0.1, far as f32).unwrap();
                let want = 1.0 / z;
                assert!(
                    (f64::from(d) - want).abs() < 2e-3 * want.max(1.0),
                    "{kind:?} far {far} z {z}: {d} D, want {want}"
                );
            }
        }
    }
    assert_eq!(
        DepthKind::VulkanReversed.diopters(0.0, 0.1, f32::INFINITY),
        Ok(0.0)
    );
    assert_eq!(DepthKind::Metres.diopters(0.5, 0.0, 0.0), Ok(2.0));
    assert_eq!(DepthKind::Metres.diopters(f32::INFINITY, 0.0, 0.0), Ok(0.0));
    assert_eq!(DepthKind::Diopters.diopters(1.5, 0.0, 0.0), Ok(1.5));
}

#[test]
fn bad_depth_is_refused_naming_the_pixel() {
    let d = desc(2, 2, ColorFormat::Rgb8, DepthKind::Metres);
    let color = vec![0u8; 12];
    let e = decode_frame(&d, &color, &f32s(&[1.0, 1.0, f32::NAN, 1.0]), (2, 2)).unwrap_err();
    assert!(matches!(e, FrameError::Depth { x: 0, y: 1, .. }), "{e}");
    let e = decode_frame(&d, &color, &f32s(&[1.0, -1.0, 1.0, 1.0]), (2, 2)).unwrap_err();
    assert!(matches!(e, FrameError::Depth { x: 1, y: 0, .. }), "{e}");
    let vk = desc(2, 2, ColorFormat::Rgb8, DepthKind::Vulkan);
    let e = decode_frame(&vk, &color, &f32s(&[0.5, 1.5, 0.5, 0.5]), (2, 2)).unwrap_err();
    assert!(e.to_string().contains("[0, 1]"), "{e}");
    let mut no_planes = vk;
    no_planes.near = None;
    let e = decode_frame(&no_planes, &color, &f32s(&[0.5; 4]), (2, 2)).unwrap_err();
    assert!(e.to_string().contains("near and far"), "{e}");
}

#[test]
fn wrong_sizes_and_lengths_are_refused() {
    let d = desc(2, 2, ColorFormat::Rgba8, DepthKind::Diopters);
    let depth = f32s(&[1.0; 4]);
    let e = decode_frame(&d, &[0u8; 16], &depth, (3, 2)).unwrap_err();
    assert!(matches!(e, FrameError::WrongSize { .. }), "{e}");
    let e = decode_frame(&d, &[0u8; 12], &depth, (2, 2)).unwrap_err();
    assert!(
        matches!(
            e,
            FrameError::Length {
                what: "colour",
                got: 12,
                want: 16,
                ..
            }
        ),
        "{e}"
    );
    let e = decode_frame(&d, &[0u8; 16], &depth[..15], (2, 2)).unwrap_err();
    assert!(matches!(e, FrameError::Length { what: "depth", .. }), "{e}");
}

#[test]
fn colour_is_decoded_from_srgb_or_taken_linear() {
    let d = desc(1, 1, ColorFormat::Rgb8, DepthKind::Diopters);
    let f = decode_frame(&d, &[255, 0, 188], &f32s(&[1.0]), (1, 1)).unwrap();
    let px: Vec<f32> = f.color.channels.iter().map(|p| p.data()[0]).collect();
    assert_eq!(px[0], 1.0);
    assert_eq!(px[1], 0.0);
    assert!((px[2] - 0.5).abs() < 0.01, "{px:?}");
    let d = desc(1, 1, ColorFormat::Rgbf32, DepthKind::Diopters);
    let f = decode_frame(&d, &f32s(&[0.25, 0.5, 0.75]), &f32s(&[1.0]), (1, 1)).unwrap();
    assert_eq!(f.color.channels[1].data()[0], 0.5);
    assert_eq!(f.depth.plane().data()[0], 1.0);
}

#[test]
fn image_files_decode_as_dioptra_render_reads_them() {
    use dioptra_render::io::{read_color, read_depth, write_color, write_depth};
    let dir = tempfile::tempdir().unwrap();
    let vals: Vec<f32> = (0..18).map(|i| i as f32 / 17.0).collect();
    let color = RgbImage::from_interleaved(3, 2, &vals).unwrap();
    let depth = DepthMap::from_diopters(
        Plane::from_vec(3, 2, vec![0.5, 1.0, 2.0, 4.0, 0.25, 1.0]).unwrap(),
    )
    .unwrap();
    let file = |name: &str| dir.path().join(name);
    write_color(&file("c.png"), &color).unwrap();
    write_color(&file("c.exr"), &color).unwrap();
    write_depth(&file("d.png"), &depth).unwrap();
    write_depth(&file("d.exr"), &depth).unwrap();
    let bytes = |name: &str| std::fs::read(file(name)).unwrap();
    for (c, fmt, d, kind) in [
        ("c.png", ColorFormat::Png, "d.png", DepthKind::Millimetres),
        ("c.exr", ColorFormat::Exr, "d.exr", DepthKind::Metres),
    ] {
        let f = decode_frame(&desc(3, 2, fmt, kind), &bytes(c), &bytes(d), (3, 2)).unwrap();
        assert_eq!(f.color, read_color(&file(c)).unwrap(), "{c}");
        let want = read_depth(&file(d), None).unwrap();
        for (a, b) in f.depth.data().iter().zip(want.data()) {
            assert!((a - b).abs() <= 1e-6 * b.max(1.0), "{d}: {a} vs {b}");
        }
    }
    let png = desc(3, 2, ColorFormat::Png, DepthKind::Millimetres);
    // The colour part is not the format named.
    let e = decode_frame(&png, &bytes("c.exr"), &bytes("d.png"), (3, 2)).unwrap_err();
    assert!(
        matches!(
            e,
            FrameError::Encoding {
                what: "colour file",
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("color=png"), "{e}");
    // A file of another size than the frame: refused from its header.
    write_depth(
        &file("small.png"),
        &DepthMap::from_diopters(Plane::new(2, 2, 1.0)).unwrap(),
    )
    .unwrap();
    let e = decode_frame(&png, &bytes("c.png"), &bytes("small.png"), (3, 2)).unwrap_err();
    assert!(
        e.to_string()
            .contains("depth file: it is 2x2; the frame is 3x2"),
        "{e}"
    );
    // A depth file cut short, and NaN depth named by pixel.
    let cut = bytes("d.png");
    let e = decode_frame(&png, &bytes("c.png"), &cut[..cut.len() / 2], (3, 2)).unwrap_err();
    assert!(
        matches!(
            e,
            FrameError::Encoding {
                what: "depth file",
                ..
            }
        ),
        "{e}"
    );
    // A PFM's rows run bottom to top: its second value is pixel (1, 1).
    let mut nan_pfm = b"Pf\n3 2\n-1.0\n".to_vec();
    nan_pfm.extend(f32s(&[1.0, f32::NAN, 1.0, 1.0, 1.0, 1.0]));
    let metres = desc(3, 2, ColorFormat::Png, DepthKind::Metres);
    let e = decode_frame(&metres, &bytes("c.png"), &nan_pfm, (3, 2)).unwrap_err();
    assert!(matches!(e, FrameError::Depth { x: 1, y: 1, .. }), "{e}");
}

#[test]
fn the_newest_frame_wins_and_every_frame_is_accounted_for() {
    let s = StreamFrames::open(1, 1, None).unwrap();
    let d = FrameDesc {
        seq: Some(5),
        ..desc(1, 1, ColorFormat::Rgb8, DepthKind::Diopters)
    };
    let depth = f32s(&[1.0]);
    assert_eq!(s.submit(&d, &[1, 2, 3], &depth, Timestamp(10)), Ok(5));
    // A stale one is refused, the newer one replaces the first before the display took it.
    let e = s.submit(&d, &[1, 2, 3], &depth, Timestamp(11)).unwrap_err();
    assert!(matches!(e, FrameError::Stale { seq: 5, newest: 5 }));
    let d7 = FrameDesc { seq: Some(7), ..d };
    assert_eq!(s.submit(&d7, &[9, 9, 9], &depth, Timestamp(12)), Ok(7));
    assert!(s.take_new().is_some());
    assert!(s.take_new().is_none(), "taken once");
    let st = s.status();
    assert_eq!((st.received, st.shown, st.replaced), (2, 1, 1));
    assert_eq!(st.refused.get("stale"), Some(&1));
    assert_eq!(st.on_show_seq, Some(7));
    assert!(st.newest_age_ms.is_some());
    // Unnumbered frames continue the numbering.
    let auto = FrameDesc { seq: None, ..d };
    assert_eq!(s.submit(&auto, &[0, 0, 0], &depth, Timestamp(13)), Ok(8));
}

/// Frames given back are reused only when no one else holds them: a frame still held
/// keeps its pixels whatever comes after it, and reused memory holds the new frame whole.
#[test]
fn reused_memory_never_changes_a_frame_still_held() {
    let s = StreamFrames::open(2, 1, None).unwrap();
    let d = desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters);
    let send = |v: u8, depth: f32| {
        s.submit(&d, &[v; 6], &f32s(&[depth; 2]), Timestamp(0))
            .unwrap();
    };
    send(255, 1.0);
    let held = s.take_new().unwrap().0;
    let kept = held.clone();
    // Given back while `kept` holds it: not reused.
    s.recycle(held);
    for (k, v) in [(0u8, 2.0f32), (128, 3.0), (64, 4.0)] {
        send(k, v);
        // Replaced before shown: its memory goes to the next frame.
        send(k / 2, v + 0.5);
        let f = s.take_new().unwrap().0;
        assert_eq!(f.depth.data(), &[v + 0.5; 2]);
        assert_eq!(
            f.color.channels[0].data()[0],
            srgb_lut()[usize::from(k / 2)]
        );
        s.recycle(f);
    }
    assert_eq!(kept.color.channels[0].data(), &[1.0, 1.0]);
    assert_eq!(kept.depth.data(), &[1.0, 1.0]);
    assert!(
        !lock(&s.planes.spare).is_empty(),
        "frames given back are kept for reuse"
    );
}

/// Writes a frame into a ring slot the way a client does: sequence number last.
fn write_slot(ring: &Ring, slot: usize, seq: u64, w: u32, h: u32, color: &[u8], depth: &[u8]) {
    write_eye_slot(ring, slot, (seq, 0), w, h, color, depth)
}

/// [`write_slot`] with the slot's `eye` code.
fn write_eye_slot(
    ring: &Ring,
    slot: usize,
    (seq, eye): (u64, u32),
    w: u32,
    h: u32,
    color: &[u8],
    depth: &[u8],
) {
    write_part_slot(ring, slot, (seq, eye, 0), w, h, color, depth)
}

/// [`write_slot`] with the slot's `eye` and `view` codes.
fn write_part_slot(
    ring: &Ring,
    slot: usize,
    (seq, eye, view): (u64, u32, u32),
    w: u32,
    h: u32,
    color: &[u8],
    depth: &[u8],
) {
    let base = RING_HEADER + slot * ring.slot_bytes;
    let head = SlotHeader {
        seq,
        color_format: ColorFormat::Rgb8 as u32,
        depth_kind: DepthKind::Diopters as u32,
        near: f32::NAN,
        far: f32::NAN,
        width: w,
        height: h,
        app_time_ns: 0,
        color_bytes: color.len() as u64,
        depth_bytes: depth.len() as u64,
        eye,
        view,
    };
    let mut bytes = head.encode().to_vec();
    bytes.extend_from_slice(color);
    bytes.extend_from_slice(depth);
    let f = std::fs::OpenOptions::new()
        .write(true)
        .open(&ring.path)
        .unwrap();
    use std::os::unix::fs::FileExt;
    f.write_all_at(&bytes[8..], (base + 8) as u64).unwrap();
    f.write_all_at(&seq.to_le_bytes(), base as u64).unwrap();
}

#[test]
fn a_ring_slot_is_read_and_checked() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("frames");
    let s = StreamFrames::open(2, 1, Some(&path)).unwrap();
    use std::os::unix::fs::PermissionsExt;
    let mode = std::fs::metadata(&path).unwrap().permissions().mode();
    assert_eq!(mode & 0o777, 0o600);
    let ring = s.ring.as_ref().unwrap();
    let header = std::fs::read(&path).unwrap();
    assert_eq!(&header[..8], RING_MAGIC);
    write_slot(ring, 1, 3, 2, 1, &[255; 6], &f32s(&[0.5, 2.0]));
    assert_eq!(s.submit_slot(1, 3, Timestamp(1)), Ok(3));
    let (f, _) = s.take_new().unwrap();
    assert_eq!(f.depth.plane().data(), &[0.5, 2.0]);
    // The wrong sequence number, a slot out of range, sizes that overflow the slot.
    assert!(s.submit_slot(1, 4, Timestamp(2)).is_err());
    assert!(s.submit_slot(RING_SLOTS, 4, Timestamp(2)).is_err());
    write_slot(ring, 0, 9, 2, 1, &[0; 6], &vec![0; ring.slot_bytes]);
    let e = s.submit_slot(0, 9, Timestamp(3)).unwrap_err();
    assert!(e.to_string().contains("do not fit"), "{e}");
    // A truncated slot: its header says fewer depth bytes than the frame needs.
    write_slot(ring, 2, 10, 2, 1, &[0; 6], &f32s(&[1.0]));
    let e = s.submit_slot(2, 10, Timestamp(4)).unwrap_err();
    assert!(matches!(e, FrameError::Length { what: "depth", .. }), "{e}");
    // A slot rewritten while it was copied out is torn.
    write_slot(ring, 2, 11, 2, 1, &[0; 6], &f32s(&[1.0, 1.0]));
    let e = s
        .read_slot_then(2, 11, || {
            write_slot(ring, 2, 12, 2, 1, &[1; 6], &f32s(&[2.0, 2.0]))
        })
        .unwrap_err();
    assert_eq!(e, FrameError::Torn(2));
    let st = s.status();
    assert_eq!(st.received, 1);
    assert_eq!(st.refused.values().sum::<u64>(), 4);
    drop(s);
    assert!(!path.exists(), "the ring is removed with the stream");
}

#[test]
fn a_ring_path_that_is_a_symlink_is_not_followed() {
    let dir = tempfile::tempdir().unwrap();
    let target = dir.path().join("target");
    std::fs::write(&target, b"keep").unwrap();
    let link = dir.path().join("frames");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    let e = StreamFrames::open(2, 2, Some(&link)).unwrap_err();
    assert!(e.to_string().contains("not a regular file"), "{e}");
    assert_eq!(std::fs::read(&target).unwrap(), b"keep");
}

/// A 2 x 1 stereo stream's halves: one eye's frame of `v` (sRGB byte) at `d` D.
fn half(s: &StreamFrames, eye: Side, seq: u64, v: u8, d: f32) -> Result<u64, FrameError> {
    let desc = FrameDesc {
        seq: Some(seq),
        ..desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters)
    };
    s.submit_eye(&desc, Some(eye), &[v; 6], &f32s(&[d; 2]), Timestamp(seq))
}

/// The views of the frame the display takes up next (left, right), as (red, depth).
fn pair_of(s: &StreamFrames) -> Option<(u64, [(f32, f32); 2])> {
    let f = s.poll(Timestamp(0))?;
    let [l, r] = f.eyes.clone().expect("a pair");
    assert!(Arc::ptr_eq(&f.rgbd, &l), "rgbd is the left eye's view");
    let px = |v: &Rgbd| (v.color.channels[0].data()[0], v.depth.data()[0]);
    Some((s.status().on_show_seq.unwrap(), [px(&l), px(&r)]))
}

/// On a stereo rig halves are paired by sequence number: a lone half is not shown; a pair
/// is, once both halves arrived in either order; a half whose partner never came is
/// dropped when a newer pair completes, and refused if it comes after that.
#[test]
fn halves_are_paired_by_sequence_number() {
    let s = StreamFrames::with_eyes(2, 1, true, None).unwrap();
    let lut = srgb_lut();
    // The placeholder first, then nothing while only the left half of 1 is in.
    assert!(s.poll(Timestamp(0)).unwrap().eyes.is_none());
    assert_eq!(half(&s, Side::Left, 1, 10, 1.0), Ok(1));
    assert!(s.poll(Timestamp(0)).is_none(), "a lone half is not shown");
    let st = s.status();
    assert_eq!((st.received, st.halves_waiting), (0, 1), "{st:?}");
    assert_eq!(half(&s, Side::Right, 1, 20, 2.0), Ok(1));
    assert_eq!(
        pair_of(&s),
        Some((1, [(lut[10], 1.0), (lut[20], 2.0)])),
        "each eye its own half"
    );
    // Late: the right half of 2 never comes before pair 3 completes.
    half(&s, Side::Left, 2, 30, 1.5).unwrap();
    half(&s, Side::Left, 3, 40, 1.25).unwrap();
    assert!(
        s.poll(Timestamp(0)).is_none(),
        "2 and 3 wait for their right halves"
    );
    half(&s, Side::Right, 3, 50, 2.5).unwrap();
    assert_eq!(pair_of(&s), Some((3, [(lut[40], 1.25), (lut[50], 2.5)])));
    let st = s.status();
    assert_eq!((st.halves_dropped, st.halves_waiting), (1, 0), "{st:?}");
    // The late half after its pair was overtaken: refused, never shown.
    let e = half(&s, Side::Right, 2, 60, 3.0).unwrap_err();
    assert_eq!(
        e,
        FrameError::StaleHalf {
            eye: Side::Right,
            seq: 2,
            newest: 3
        }
    );
    assert!(
        e.to_string().contains("right eye's sequence number 2"),
        "{e}"
    );
    // Right before left; pair 4 completes, then 5, before the display looks: 4 is
    // replaced by 5.
    half(&s, Side::Right, 4, 1, 0.5).unwrap();
    half(&s, Side::Left, 4, 3, 0.5).unwrap();
    half(&s, Side::Left, 5, 2, 0.75).unwrap();
    half(&s, Side::Right, 5, 4, 0.75).unwrap();
    assert_eq!(pair_of(&s), Some((5, [(lut[2], 0.75), (lut[4], 0.75)])));
    assert!(s.poll(Timestamp(0)).is_none());
    // A half again for an eye's number already in, and a half without a number.
    let e = half(&s, Side::Left, 5, 0, 1.0).unwrap_err();
    assert!(matches!(e, FrameError::StaleHalf { seq: 5, .. }), "{e}");
    let unnumbered = desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters);
    let e = s
        .submit_eye(
            &unnumbered,
            Some(Side::Left),
            &[0; 6],
            &f32s(&[1.0; 2]),
            Timestamp(0),
        )
        .unwrap_err();
    assert!(e.to_string().contains("needs its sequence number"), "{e}");
    let st = s.status();
    assert_eq!(
        (st.received, st.shown, st.replaced, st.halves_received),
        (4, 3, 1, 9),
        "{st:?}"
    );
    assert_eq!(st.refused.get("stale"), Some(&2), "{st:?}");
    assert_eq!(st.refused.get("request"), Some(&1), "{st:?}");
    assert_eq!(st.newest_seq, Some(5));
}

/// Halves waiting for more than MAX_WAITING sequence numbers drop the oldest; a whole
/// frame on a stereo rig (mono: its eyes are synthesised) drops every older half.
#[test]
fn waiting_halves_are_bounded_and_a_whole_frame_overtakes_them() {
    let s = StreamFrames::with_eyes(2, 1, true, None).unwrap();
    for seq in 1..=MAX_WAITING as u64 + 1 {
        half(&s, Side::Left, seq, 0, 1.0).unwrap();
    }
    let st = s.status();
    assert_eq!(
        (st.halves_waiting, st.halves_dropped),
        (MAX_WAITING as u64, 1),
        "{st:?}"
    );
    // The oldest (1) is gone: its right half can no longer make a pair.
    let e = half(&s, Side::Right, 1, 0, 1.0).unwrap_err();
    assert!(matches!(e, FrameError::StaleHalf { newest: 1, .. }), "{e}");
    half(&s, Side::Right, 2, 0, 1.0).unwrap();
    assert!(
        s.take_new().is_some(),
        "pair 2, whose left half still waited"
    );
    let mono = FrameDesc {
        seq: Some(10),
        ..desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters)
    };
    s.submit(&mono, &[9; 6], &f32s(&[2.0; 2]), Timestamp(0))
        .unwrap();
    let f = s.poll(Timestamp(0)).unwrap();
    assert!(f.eyes.is_none(), "a mono frame: eyes synthesised later");
    let st = s.status();
    assert_eq!(
        (st.halves_waiting, st.halves_dropped, st.on_show_seq),
        (0, MAX_WAITING as u64, Some(10)),
        "{st:?}"
    );
}

/// A frame 2 x width wide without an eye is both eyes side by side: its left half is the
/// left eye's. Sizes that fit neither, an unknown eye and an eye on a mono rig are
/// refused.
#[test]
fn a_side_by_side_frame_is_split_and_bad_eyes_are_refused() {
    let s = StreamFrames::with_eyes(2, 1, true, None).unwrap();
    let wide = desc(4, 1, ColorFormat::Rgb8, DepthKind::Diopters);
    let color = [10, 10, 10, 20, 20, 20, 30, 30, 30, 40, 40, 40];
    s.submit(&wide, &color, &f32s(&[1.0, 2.0, 3.0, 4.0]), Timestamp(0))
        .unwrap();
    let f = s.poll(Timestamp(0)).unwrap();
    let [l, r] = f.eyes.clone().expect("a pair");
    let lut = srgb_lut();
    assert_eq!(l.color.channels[1].data(), &[lut[10], lut[20]]);
    assert_eq!(r.color.channels[2].data(), &[lut[30], lut[40]]);
    assert_eq!(l.depth.data(), &[1.0, 2.0]);
    assert_eq!(r.depth.data(), &[3.0, 4.0]);
    assert_eq!((l.width(), r.width()), (2, 2));
    // One eye's half must be one eye's size; a whole frame one of the two sizes.
    let e = s
        .submit_eye(
            &FrameDesc {
                seq: Some(9),
                ..wide
            },
            Some(Side::Left),
            &color,
            &f32s(&[1.0; 4]),
            Timestamp(0),
        )
        .unwrap_err();
    assert!(
        e.to_string()
            .contains("left eye's frame is 4x1; one eye's image is 2x1"),
        "{e}"
    );
    assert_eq!(e.kind(), "wrong_size");
    let e = s.side_by_side(3, 1, None).unwrap_err();
    assert!(
        e.to_string().contains("or 4x1 for both eyes side by side"),
        "{e}"
    );
    let e = s.parse_eye(Some("middle")).unwrap_err();
    assert!(e.to_string().contains("expected left or right"), "{e}");
    assert_eq!(s.parse_eye(Some("right")), Ok(Some(Side::Right)));
    let mono = StreamFrames::open(2, 1, None).unwrap();
    let e = mono.parse_eye(Some("left")).unwrap_err();
    assert!(e.to_string().contains("display.layout = \"one\""), "{e}");
    assert_eq!(e.kind(), "eye");
    let e = mono.side_by_side(4, 1, None).unwrap_err();
    assert!(
        matches!(e, FrameError::WrongSize { .. }),
        "a mono rig takes no pair: {e}"
    );
}

/// A ring slot's `eye`: two slots of the same number make a pair; a stereo ring's slots
/// hold a side-by-side frame; an unknown eye, or an eye on a mono rig, is refused.
#[test]
fn ring_slots_name_their_eye() {
    let dir = tempfile::tempdir().unwrap();
    let s = StreamFrames::with_eyes(2, 1, true, Some(&dir.path().join("stereo"))).unwrap();
    let ring = s.ring.as_ref().unwrap();
    assert_eq!(ring.slot_bytes, SLOT_HEADER + 2 * 2 * 16);
    write_eye_slot(ring, 0, (7, 1), 2, 1, &[255; 6], &f32s(&[1.0; 2]));
    write_eye_slot(ring, 1, (7, 2), 2, 1, &[0; 6], &f32s(&[2.0; 2]));
    assert_eq!(s.submit_slot(0, 7, Timestamp(1)), Ok(7));
    assert_eq!(s.status().received, 0, "the left half waits");
    assert_eq!(s.submit_slot(1, 7, Timestamp(2)), Ok(7));
    let f = s.poll(Timestamp(2)).unwrap();
    let [l, r] = f.eyes.expect("a pair");
    assert_eq!((l.depth.data()[0], r.depth.data()[0]), (1.0, 2.0));
    assert_eq!(
        f.arrival.map(|a| a.arrived),
        Some(Timestamp(2)),
        "with its second half"
    );
    // Both eyes in one slot (eye 0, 2 x width).
    write_eye_slot(
        ring,
        2,
        (8, 0),
        4,
        1,
        &[9; 12],
        &f32s(&[1.0, 1.0, 3.0, 3.0]),
    );
    assert_eq!(s.submit_slot(2, 8, Timestamp(3)), Ok(8));
    let [l, r] = s.poll(Timestamp(3)).unwrap().eyes.expect("a pair");
    assert_eq!(
        (l.depth.data(), r.depth.data()),
        (&[1.0, 1.0][..], &[3.0, 3.0][..])
    );
    write_eye_slot(ring, 0, (9, 3), 2, 1, &[0; 6], &f32s(&[1.0; 2]));
    let e = s.submit_slot(0, 9, Timestamp(4)).unwrap_err();
    assert!(e.to_string().contains("unknown eye 3"), "{e}");
    let mono = StreamFrames::open(2, 1, Some(&dir.path().join("mono"))).unwrap();
    let ring = mono.ring.as_ref().unwrap();
    assert_eq!(ring.slot_bytes, SLOT_HEADER + 2 * 16);
    write_eye_slot(ring, 0, (1, 2), 2, 1, &[0; 6], &f32s(&[1.0; 2]));
    let e = mono.submit_slot(0, 1, Timestamp(0)).unwrap_err();
    assert_eq!(e.kind(), "eye", "{e}");
    assert_eq!(mono.status().refused.get("eye"), Some(&1));
}

/// A 2 x 1 stream's view `v` of frame `seq` (`eye`'s grid, or the one grid): red `r`
/// (sRGB byte), `d` D.
fn view(
    s: &StreamFrames,
    eye: Option<Side>,
    v: &str,
    seq: u64,
    r: u8,
    d: f32,
) -> Result<u64, FrameError> {
    let desc = FrameDesc {
        seq: Some(seq),
        ..desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters)
    };
    let v = s.parse_view(Some(v))?;
    s.submit_part(&desc, eye, v, &[r; 6], &f32s(&[d; 2]), Timestamp(seq))
}

/// Light-field content (`content.views = 2`): a frame's views, sent in any order, are
/// shown together once the last arrives, each at its place in the grid, the central one
/// as the frame's RGB-D; one view twice, a view of a frame overtaken by a newer one, a
/// view outside the grid or of another size is refused; views of an overtaken frame are
/// dropped and counted.
#[test]
fn a_grids_views_are_shown_together_once_all_arrived() {
    let s = StreamFrames::open(2, 1, None)
        .unwrap()
        .with_view_grid(2, 4.0)
        .unwrap();
    let lut = srgb_lut();
    assert!(
        s.poll(Timestamp(0)).unwrap().views.is_none(),
        "the placeholder"
    );
    for (k, name) in [(3, "1_1"), (0, "0_0"), (2, "1_0")] {
        assert_eq!(view(&s, None, name, 1, 10 + k, 1.0 + f32::from(k)), Ok(1));
        assert!(s.poll(Timestamp(0)).is_none(), "view {name} of 4: not yet");
    }
    assert_eq!(s.status().halves_waiting, 3);
    view(&s, None, "0_1", 1, 11, 2.0).unwrap();
    let f = s.poll(Timestamp(0)).expect("frame 1 complete");
    let views = f.views.clone().expect("its views");
    assert_eq!(views.len(), 4);
    let positions = dioptra_sim::scene::light_field_positions(2, 0.004).unwrap();
    for (k, v) in views.iter().enumerate() {
        assert_eq!(v.position, positions[k], "view {k}");
        assert!(v.eye.is_none());
        assert_eq!(v.rgbd.color.channels[0].data()[0], lut[10 + k], "view {k}");
        assert_eq!(v.rgbd.depth.data()[0], 1.0 + k as f32, "view {k}");
    }
    // Row 1, column 1: the central view of an even grid (right of and below the centre).
    assert!(Arc::ptr_eq(&f.rgbd, &views[3].rgbd));
    let st = s.status();
    assert_eq!(
        (st.views_received, st.received, st.halves_waiting),
        (4, 1, 0),
        "{st:?}"
    );
    // The same view again for frame 1: stale.
    let e = view(&s, None, "0_0", 1, 0, 1.0).unwrap_err();
    assert!(
        matches!(
            e,
            FrameError::StaleView {
                seq: 1,
                newest: 1,
                ..
            }
        ),
        "{e}"
    );
    // Frame 2 half in, then a whole frame 3: 2's views are dropped, later ones refused.
    view(&s, None, "0_0", 2, 0, 1.0).unwrap();
    view(&s, None, "1_1", 2, 0, 1.0).unwrap();
    let whole = FrameDesc {
        seq: Some(3),
        ..desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters)
    };
    s.submit(&whole, &[7; 6], &f32s(&[0.5; 2]), Timestamp(3))
        .unwrap();
    let f = s.poll(Timestamp(0)).unwrap();
    assert!(f.views.is_none(), "a whole frame is one view");
    let st = s.status();
    assert_eq!((st.halves_dropped, st.halves_waiting), (2, 0), "{st:?}");
    assert!(matches!(
        view(&s, None, "0_1", 2, 0, 1.0),
        Err(FrameError::StaleView {
            seq: 2,
            newest: 3,
            ..
        })
    ));
    // Outside the grid, no sequence number, another size: refused naming why.
    for bad in ["2_0", "0", "a_b", "0_-1"] {
        let e = view(&s, None, bad, 4, 0, 1.0).unwrap_err();
        assert!(matches!(e, FrameError::View(_)), "{bad}: {e}");
        assert!(e.to_string().contains("content.views = 2"), "{e}");
    }
    let no_seq = desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters);
    let e = s
        .submit_part(
            &no_seq,
            None,
            Some(0),
            &[0; 6],
            &f32s(&[1.0; 2]),
            Timestamp(5),
        )
        .unwrap_err();
    assert!(
        matches!(e, FrameError::Request(_)) && e.to_string().contains("seq=N"),
        "{e}"
    );
    let wide = FrameDesc {
        seq: Some(6),
        ..desc(4, 1, ColorFormat::Rgb8, DepthKind::Diopters)
    };
    let e = s
        .submit_part(
            &wide,
            None,
            Some(0),
            &[0; 12],
            &f32s(&[1.0; 4]),
            Timestamp(6),
        )
        .unwrap_err();
    assert!(e.to_string().contains("one eye's image, 2x1"), "{e}");
    // (A view=... that does not parse is counted by PUT /frame, before the frame is read.)
    assert_eq!(s.status().refused.get("view"), Some(&1));
    // A rig without a grid refuses views.
    let plain = StreamFrames::open(2, 1, None).unwrap();
    let e = view(&plain, None, "0_0", 1, 0, 1.0).unwrap_err();
    assert!(e.to_string().contains("content.views"), "{e}");
}

/// A stereo rig: each eye's own grid (views with `eye`), the frame's eyes their central
/// views; a frame's views with and without an eye do not mix. Ring slots name their view.
#[test]
fn each_eye_may_stream_its_own_grid_and_slots_name_their_view() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("frames");
    let s = StreamFrames::with_eyes(2, 1, true, Some(&path))
        .unwrap()
        .with_view_grid(2, 10.0)
        .unwrap();
    assert_eq!(s.ring_json()["views"], 2);
    s.poll(Timestamp(0));
    for (eye, base) in [(Side::Left, 20u8), (Side::Right, 40)] {
        for k in 0..4u8 {
            let name = format!("{}_{}", k / 2, k % 2);
            view(&s, Some(eye), &name, 1, base + k, 1.0).unwrap();
        }
    }
    let f = s.poll(Timestamp(0)).expect("both grids complete");
    let views = f.views.clone().unwrap();
    assert_eq!(views.len(), 8);
    let lut = srgb_lut();
    for (k, v) in views.iter().enumerate() {
        let (eye, base) = if k < 4 {
            (Side::Left, 20)
        } else {
            (Side::Right, 40)
        };
        assert_eq!(v.eye, Some(eye));
        assert_eq!(v.rgbd.color.channels[0].data()[0], lut[base + k % 4]);
    }
    let [l, r] = f.eyes.clone().unwrap();
    assert!(Arc::ptr_eq(&l, &views[3].rgbd) && Arc::ptr_eq(&r, &views[7].rgbd));
    // Frame 2: a view of the one grid, then one of an eye's: refused.
    view(&s, None, "0_0", 2, 0, 1.0).unwrap();
    let e = view(&s, Some(Side::Left), "0_1", 2, 0, 1.0).unwrap_err();
    assert!(e.to_string().contains("views of one grid"), "{e}");
    // Frame 3 through the ring: slot `view` 1 + index, the right eye's.
    let ring = s.ring.as_ref().unwrap();
    for k in 0..4u32 {
        write_part_slot(
            ring,
            0,
            (3, 0, 1 + k),
            2,
            1,
            &[60 + k as u8; 6],
            &f32s(&[1.0; 2]),
        );
        s.submit_slot(0, 3, Timestamp(3)).unwrap();
    }
    let f = s.poll(Timestamp(0)).expect("frame 3 from the ring");
    let views = f.views.clone().unwrap();
    assert!(views.iter().all(|v| v.eye.is_none()) && views.len() == 4);
    assert_eq!(views[2].rgbd.color.channels[0].data()[0], lut[62]);
    write_part_slot(ring, 1, (4, 0, 5), 2, 1, &[0; 6], &f32s(&[1.0; 2]));
    let e = s.submit_slot(1, 4, Timestamp(4)).unwrap_err();
    assert!(matches!(e, FrameError::View(_)), "{e}");
}
