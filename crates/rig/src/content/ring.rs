//! The shared-memory frame ring's byte layout, written down once ([RING.md](../../RING.md) is
//! its spec): the ring header, a slot's header, and the codes in them. The daemon creates the
//! ring with [`RingHeader::encode`], reads slots with [`SlotHeader::decode`], and describes the
//! layout to clients (`GET /frame/ring`) from [`SLOT_FIELDS`]; `ring-golden.json` holds bytes
//! that this module's tests and the Python client's tests both check.

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
        RingHeader {
            width: width as u32,
            height: height as u32,
            slot_bytes: (SLOT_HEADER + width * height * SLOT_BYTES_PER_PX) as u64,
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
    /// [`crate::content::stream::ColorFormat`] as a number (1 rgb8, 2 rgba8, 3 rgbf32).
    pub color_format: u32,
    /// [`crate::content::stream::DepthKind`] as a number.
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::content::stream::{ColorFormat, DepthKind};

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
        let v = &slot["values"];
        let u = |k: &str| v[k].as_u64().unwrap();
        let h = SlotHeader {
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
        };
        let bytes = h.encode();
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
        assert_eq!(ring["layout"], layout_json(RING_FIELDS));
        assert_eq!(slot["layout"], layout_json(SLOT_FIELDS));
        assert_eq!(g["slots"].as_u64(), Some(RING_SLOTS as u64));
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
