//! The shared-memory frame ring's byte layout, written down once ([RING.md](../../RING.md) is
//! its spec): the ring header, a slot's header, and the codes in them. The daemon creates the
//! ring with [`RingHeader::encode`], reads slots with [`SlotHeader::decode`], and describes the
//! layout to clients (`GET /frame/ring`) from [`SLOT_FIELDS`]; `ring-golden.json` holds bytes
//! that this module's tests and the Python client's tests both check.

use std::fs::OpenOptions;
use std::io::Write;
use std::path::{Path, PathBuf};

use dioptra_core::Side;

/// The ring file's first 8 bytes.
pub const RING_MAGIC: &[u8; 8] = b"DIOPTRA1";
pub const RING_VERSION: u32 = 1;
/// The ring header's size; slot `i` starts at `RING_HEADER + i * slot_bytes`.
pub const RING_HEADER: usize = 64;
/// A slot's header size; its colour bytes follow it, then its depth bytes.
pub const SLOT_HEADER: usize = 64;
/// Slots in the ring.
pub const RING_SLOTS: usize = 3;
/// A slot holds the largest frame: RGB f32 colour and f32 depth, 16 bytes a pixel.
pub const SLOT_BYTES_PER_PX: usize = 16;

/// A slot's `eye`: which eye's view its frame is (a stereo rig). 0, what a writer that does
/// not know the field leaves, is a frame of no one eye: mono, or both eyes side by side.
pub const EYE_CODES: [(&str, u32); 3] = [("none", 0), ("left", 1), ("right", 2)];

/// A slot's `eye` code for `eye`.
pub fn eye_code(eye: Option<Side>) -> u32 {
    match eye {
        None => 0,
        Some(Side::Left) => 1,
        Some(Side::Right) => 2,
    }
}

/// The eye a slot's `eye` code names (`Some(None)`: no eye); `None`: not a code.
pub fn eye_of_code(code: u32) -> Option<Option<Side>> {
    match code {
        0 => Some(None),
        1 => Some(Some(Side::Left)),
        2 => Some(Some(Side::Right)),
        _ => None,
    }
}

/// A field's place in a header: name, byte offset, little-endian type.
pub type Field = (&'static str, usize, &'static str);

/// The ring header (at offset 0 of the file), written once by the daemon.
pub const RING_FIELDS: &[Field] = &[
    ("magic", 0, "u8[8]"),
    ("version", 8, "u32"),
    ("slots", 12, "u32"),
    ("width", 16, "u32"),
    ("height", 20, "u32"),
    ("slot_bytes", 24, "u64"),
    ("header_bytes", 32, "u32"),
    ("slot_header_bytes", 36, "u32"),
];

/// A slot's header, written by the application; `seq` last (0 while the slot is written).
pub const SLOT_FIELDS: &[Field] = &[
    ("seq", 0, "u64"),
    ("color_format", 8, "u32"),
    ("depth_kind", 12, "u32"),
    ("near", 16, "f32"),
    ("far", 20, "f32"),
    ("width", 24, "u32"),
    ("height", 28, "u32"),
    ("app_time_ns", 32, "u64"),
    ("color_bytes", 40, "u64"),
    ("depth_bytes", 48, "u64"),
    ("eye", 56, "u32"),
    ("view", 60, "u32"),
];

fn offset(fields: &[Field], name: &str) -> usize {
    fields
        .iter()
        .find(|f| f.0 == name)
        .map(|f| f.1)
        .expect("a field of the layout")
}

fn put(buf: &mut [u8], fields: &[Field], name: &str, bytes: &[u8]) {
    let o = offset(fields, name);
    buf[o..o + bytes.len()].copy_from_slice(bytes);
}

fn get<const N: usize>(buf: &[u8], fields: &[Field], name: &str) -> [u8; N] {
    let o = offset(fields, name);
    buf[o..o + N].try_into().expect("N bytes")
}

/// The ring header's values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RingHeader {
    pub width: u32,
    pub height: u32,
    pub slot_bytes: u64,
}

impl RingHeader {
    /// The header of a ring for `width` x `height` frames.
    pub fn for_frames(width: usize, height: usize) -> Self {
        Self::for_eyes(width, height, false)
    }

    /// The header of a ring for `width` x `height` frames (one eye's, on a `stereo` rig): a
    /// stereo rig's slots have room for both eyes side by side, 2 x `width` wide.
    pub fn for_eyes(width: usize, height: usize, stereo: bool) -> Self {
        let views = if stereo { 2 } else { 1 };
        RingHeader {
            width: width as u32,
            height: height as u32,
            slot_bytes: (SLOT_HEADER + views * width * height * SLOT_BYTES_PER_PX) as u64,
        }
    }

    pub fn encode(&self) -> [u8; RING_HEADER] {
        let mut b = [0u8; RING_HEADER];
        let f = RING_FIELDS;
        put(&mut b, f, "magic", RING_MAGIC);
        put(&mut b, f, "version", &RING_VERSION.to_le_bytes());
        put(&mut b, f, "slots", &(RING_SLOTS as u32).to_le_bytes());
        put(&mut b, f, "width", &self.width.to_le_bytes());
        put(&mut b, f, "height", &self.height.to_le_bytes());
        put(&mut b, f, "slot_bytes", &self.slot_bytes.to_le_bytes());
        put(
            &mut b,
            f,
            "header_bytes",
            &(RING_HEADER as u32).to_le_bytes(),
        );
        put(
            &mut b,
            f,
            "slot_header_bytes",
            &(SLOT_HEADER as u32).to_le_bytes(),
        );
        b
    }
}

/// A slot header's values, as the application wrote them (codes not yet checked).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SlotHeader {
    pub seq: u64,
    /// [`crate::content::stream::decode::ColorFormat`] as a number (1 rgb8, 2 rgba8, 3 rgbf32).
    pub color_format: u32,
    /// [`crate::content::stream::decode::DepthKind`] as a number.
    pub depth_kind: u32,
    /// A depth buffer's planes, metres (NaN when the depth is not a buffer).
    pub near: f32,
    pub far: f32,
    pub width: u32,
    pub height: u32,
    /// The application's time for the frame, ns; 0 for none.
    pub app_time_ns: u64,
    pub color_bytes: u64,
    pub depth_bytes: u64,
    /// Which eye's view ([`EYE_CODES`]; 0: none).
    pub eye: u32,
    /// Which view of a view grid (`content.views`): 1 + row x views + column; 0: none.
    pub view: u32,
}

impl SlotHeader {
    pub fn encode(&self) -> [u8; SLOT_HEADER] {
        let mut b = [0u8; SLOT_HEADER];
        let f = SLOT_FIELDS;
        put(&mut b, f, "seq", &self.seq.to_le_bytes());
        put(&mut b, f, "color_format", &self.color_format.to_le_bytes());
        put(&mut b, f, "depth_kind", &self.depth_kind.to_le_bytes());
        put(&mut b, f, "near", &self.near.to_le_bytes());
        put(&mut b, f, "far", &self.far.to_le_bytes());
        put(&mut b, f, "width", &self.width.to_le_bytes());
        put(&mut b, f, "height", &self.height.to_le_bytes());
        put(&mut b, f, "app_time_ns", &self.app_time_ns.to_le_bytes());
        put(&mut b, f, "color_bytes", &self.color_bytes.to_le_bytes());
        put(&mut b, f, "depth_bytes", &self.depth_bytes.to_le_bytes());
        put(&mut b, f, "eye", &self.eye.to_le_bytes());
        put(&mut b, f, "view", &self.view.to_le_bytes());
        b
    }

    /// The header in `b` (a slot's first [`SLOT_HEADER`] bytes).
    pub fn decode(b: &[u8; SLOT_HEADER]) -> Self {
        let f = SLOT_FIELDS;
        SlotHeader {
            seq: u64::from_le_bytes(get(b, f, "seq")),
            color_format: u32::from_le_bytes(get(b, f, "color_format")),
            depth_kind: u32::from_le_bytes(get(b, f, "depth_kind")),
            near: f32::from_le_bytes(get(b, f, "near")),
            far: f32::from_le_bytes(get(b, f, "far")),
            width: u32::from_le_bytes(get(b, f, "width")),
            height: u32::from_le_bytes(get(b, f, "height")),
            app_time_ns: u64::from_le_bytes(get(b, f, "app_time_ns")),
            color_bytes: u64::from_le_bytes(get(b, f, "color_bytes")),
            depth_bytes: u64::from_le_bytes(get(b, f, "depth_bytes")),
            eye: u32::from_le_bytes(get(b, f, "eye")),
            view: u32::from_le_bytes(get(b, f, "view")),
        }
    }
}

/// The layout as JSON, `{name: [offset, type]}` (`GET /frame/ring`'s `slot_header`).
pub fn layout_json(fields: &[Field]) -> serde_json::Value {
    fields
        .iter()
        .map(|&(name, offset, ty)| (name.to_string(), serde_json::json!([offset, ty])))
        .collect::<serde_json::Map<_, _>>()
        .into()
}

/// The shared-memory ring: the file and its mapping.
pub(super) struct Ring {
    pub(super) path: PathBuf,
    map: memmap2::MmapRaw,
    pub(super) slot_bytes: usize,
}

impl Ring {
    pub(super) fn create(path: &Path, header: RingHeader) -> std::io::Result<Ring> {
        use std::os::unix::fs::OpenOptionsExt;
        let slot_bytes = header.slot_bytes as usize;
        if let Ok(meta) = std::fs::symlink_metadata(path) {
            if !meta.file_type().is_file() {
                return Err(std::io::Error::other(format!(
                    "{} exists and is not a regular file; choose another content.ring",
                    path.display()
                )));
            }
            // A ring an earlier daemon left.
            std::fs::remove_file(path)?;
        }
        let mut f = OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .mode(0o600)
            .custom_flags(libc_o_nofollow())
            .open(path)?;
        f.write_all(&header.encode())?;
        f.set_len((RING_HEADER + RING_SLOTS * slot_bytes) as u64)?;
        let map = memmap2::MmapOptions::new().map_raw(&f)?;
        Ok(Ring {
            path: path.to_path_buf(),
            map,
            slot_bytes,
        })
    }

    /// Copies `len` bytes at `offset`. The application may write the file at any time, so it
    /// is read through the raw pointer, never as a Rust reference.
    pub(super) fn read(&self, offset: usize, len: usize) -> Vec<u8> {
        let mut out = vec![0u8; len];
        debug_assert!(offset + len <= self.map.len());
        // SAFETY: offset + len is inside the mapping (checked by the callers against
        // slot_bytes); the bytes are copied, not referenced.
        unsafe {
            std::ptr::copy_nonoverlapping(self.map.as_ptr().add(offset), out.as_mut_ptr(), len);
        }
        out
    }

    pub(super) fn seq(&self, slot: usize) -> u64 {
        let b = self.read(RING_HEADER + slot * self.slot_bytes, 8);
        std::sync::atomic::fence(std::sync::atomic::Ordering::Acquire);
        u64::from_le_bytes(b.try_into().unwrap_or([0; 8]))
    }
}

impl Drop for Ring {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

fn libc_o_nofollow() -> i32 {
    // O_NOFOLLOW on Linux (x86-64, aarch64): do not open through a planted symlink.
    0o400000
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::content::stream::decode::{ColorFormat, DepthKind};

    const GOLDEN: &str = include_str!("../../ring-golden.json");

    fn golden() -> serde_json::Value {
        serde_json::from_str(GOLDEN).unwrap()
    }

    fn hex(b: &[u8]) -> String {
        b.iter().map(|x| format!("{x:02x}")).collect()
    }

    fn num(v: &serde_json::Value) -> f64 {
        match v.as_str() {
            Some("nan") => f64::NAN,
            Some("inf") => f64::INFINITY,
            _ => v.as_f64().unwrap(),
        }
    }

    /// Fields overlap nowhere, lie inside their header and are aligned to their size.
    #[test]
    fn the_layouts_are_packed_and_aligned() {
        for (fields, size) in [(RING_FIELDS, RING_HEADER), (SLOT_FIELDS, SLOT_HEADER)] {
            let mut used = vec![false; size];
            for &(name, o, ty) in fields {
                let (n, align) = match ty {
                    "u8[8]" => (8, 1),
                    "u32" | "f32" => (4, 4),
                    "u64" => (8, 8),
                    other => panic!("{name}: type {other}"),
                };
                assert_eq!(o % align, 0, "{name}");
                for u in &mut used[o..o + n] {
                    assert!(!*u, "{name} overlaps");
                    *u = true;
                }
            }
        }
    }

    /// A golden vector's slot header values.
    fn slot_of(v: &serde_json::Value) -> SlotHeader {
        let u = |k: &str| v[k].as_u64().unwrap();
        let eye = v["eye"].as_str().unwrap();
        SlotHeader {
            seq: u("seq"),
            color_format: ColorFormat::parse(v["color_format"].as_str().unwrap()).unwrap() as u32,
            depth_kind: DepthKind::parse(v["depth_kind"].as_str().unwrap()).unwrap() as u32,
            near: num(&v["near"]) as f32,
            far: num(&v["far"]) as f32,
            width: u("width") as u32,
            height: u("height") as u32,
            app_time_ns: u("app_time_ns"),
            color_bytes: u("color_bytes"),
            depth_bytes: u("depth_bytes"),
            eye: eye_code(if eye == "none" {
                None
            } else {
                Side::parse(eye)
            }),
            view: v.get("view").map_or(0, |x| x.as_u64().unwrap() as u32),
        }
    }

    #[test]
    fn the_golden_bytes_are_what_the_daemon_writes_and_reads() {
        let g = golden();
        let ring = &g["ring_header"];
        let v = &ring["values"];
        let header = RingHeader::for_frames(
            v["width"].as_u64().unwrap() as usize,
            v["height"].as_u64().unwrap() as usize,
        );
        assert_eq!(header.slot_bytes, v["slot_bytes"].as_u64().unwrap());
        assert_eq!(hex(&header.encode()), ring["hex"].as_str().unwrap());

        let slot = &g["slot_header"];
        let bytes = slot_of(&slot["values"]).encode();
        assert_eq!(hex(&bytes), slot["hex"].as_str().unwrap());
        assert_eq!(SlotHeader::decode(&bytes).encode(), bytes);

        // The codes and the layout the spec lists are this module's.
        for (name, code) in g["color_formats"].as_object().unwrap() {
            let f = ColorFormat::parse(name).unwrap();
            assert_eq!(f as u64, code.as_u64().unwrap(), "{name}");
            assert_eq!(ColorFormat::from_code(f as u32), Some(f));
        }
        for (name, code) in g["depth_kinds"].as_object().unwrap() {
            let k = DepthKind::parse(name).unwrap();
            assert_eq!(k as u64, code.as_u64().unwrap(), "{name}");
            assert_eq!(DepthKind::from_code(k as u32), Some(k));
        }
        for (name, code) in g["eyes"].as_object().unwrap() {
            let eye = if name == "none" {
                None
            } else {
                Some(Side::parse(name).unwrap())
            };
            assert_eq!(u64::from(eye_code(eye)), code.as_u64().unwrap(), "{name}");
            assert_eq!(eye_of_code(eye_code(eye)), Some(eye));
        }
        assert_eq!(ring["layout"], layout_json(RING_FIELDS));
        assert_eq!(slot["layout"], layout_json(SLOT_FIELDS));
        assert_eq!(g["slots"].as_u64(), Some(RING_SLOTS as u64));
    }

    /// A slot of one eye's view: its `eye` field's bytes, which the daemon reads back; a
    /// stereo rig's slots hold both eyes side by side.
    #[test]
    fn the_golden_eye_bytes_are_what_the_daemon_reads() {
        let g = golden();
        let slot = &g["slot_header_right_eye"];
        let h = slot_of(&slot["values"]);
        let want = slot["hex"].as_str().unwrap();
        assert_eq!(hex(&h.encode()), want);
        // The field's own bytes: u32 2 at offset 56.
        assert_eq!(&want[112..120], "02000000");
        let bytes: Vec<u8> = (0..SLOT_HEADER)
            .map(|i| u8::from_str_radix(&want[2 * i..2 * i + 2], 16).unwrap())
            .collect();
        let back = SlotHeader::decode(&bytes.try_into().unwrap());
        assert_eq!(eye_of_code(back.eye), Some(Some(Side::Right)));
        assert_eq!(back.encode(), h.encode());
        // A writer that leaves the field 0 sends a frame of no one eye.
        assert_eq!(eye_of_code(0), Some(None));
        assert_eq!(eye_of_code(3), None);
        let stereo = &g["ring_header_stereo"];
        let v = &stereo["values"];
        let header = RingHeader::for_eyes(
            v["width"].as_u64().unwrap() as usize,
            v["height"].as_u64().unwrap() as usize,
            true,
        );
        assert_eq!(header.slot_bytes, v["slot_bytes"].as_u64().unwrap());
        assert_eq!(hex(&header.encode()), stereo["hex"].as_str().unwrap());
    }

    /// A slot of one view of a grid: its `view` field's bytes, which the daemon reads back.
    #[test]
    fn the_golden_view_bytes_are_what_the_daemon_reads() {
        let slot = &golden()["slot_header_view"];
        let h = slot_of(&slot["values"]);
        let want = slot["hex"].as_str().unwrap();
        assert_eq!(hex(&h.encode()), want);
        // The field's own bytes: u32 6 (row 1, column 1 of a 4 x 4 grid) at offset 60.
        assert_eq!(&want[120..128], "06000000");
        let bytes: [u8; SLOT_HEADER] = (0..SLOT_HEADER)
            .map(|i| u8::from_str_radix(&want[2 * i..2 * i + 2], 16).unwrap())
            .collect::<Vec<_>>()
            .try_into()
            .unwrap();
        assert_eq!(SlotHeader::decode(&bytes).view, 6);
    }

    /// RING.md's tables are the layout's.
    #[test]
    fn the_spec_lists_this_layout() {
        let spec = include_str!("../../RING.md");
        for &(name, o, ty) in RING_FIELDS.iter().chain(SLOT_FIELDS) {
            let row = format!("| {o} | `{name}` | {ty} |");
            assert!(spec.contains(&row), "RING.md lacks the row {row}");
        }
    }
}
