//! A small HID report-descriptor parser (HID 1.11, 6.2.2): enough to locate every variable
//! field of every report by usage and collection path, with its bit position, size, logical
//! range and unit.
//!
//! Our own rather than a crate: usage page 0x12 puts a 64-bit timestamp in one field
//! (descriptor crates extract at most 32 bits), and we need each field's collection path to
//! tell "Position X in Left Eye Position" from "Position X in Gaze Point". It never panics
//! and bounds its work on any input (see the fuzz target).

use thiserror::Error;

/// A usage with its page: `page << 16 | id`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Usage(pub u32);

impl Usage {
    pub const fn new(page: u16, id: u16) -> Self {
        Usage(((page as u32) << 16) | id as u32)
    }
    pub const fn page(self) -> u16 {
        (self.0 >> 16) as u16
    }
    pub const fn id(self) -> u16 {
        self.0 as u16
    }
}

impl std::fmt::Display for Usage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:#04x}:{:#04x}", self.page(), self.id())
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ReportKind {
    Input,
    Output,
    Feature,
}

/// One variable field: `count` elements of `size` bits from `bit_offset` (counted from the
/// first byte after the report id, if the device uses ids).
#[derive(Debug, Clone, PartialEq)]
pub struct Field {
    pub kind: ReportKind,
    pub report_id: u8,
    pub usage: Usage,
    pub bit_offset: u32,
    pub bit_size: u32,
    /// More than one when a main item gives fewer usages than its report count: the last
    /// usage then spans the remaining elements, which we read as one little-endian integer.
    pub count: u32,
    pub logical_min: i32,
    pub logical_max: i32,
    /// HID unit code (0 = none) and unit exponent (-8..=7).
    pub unit: u32,
    pub unit_exponent: i8,
    /// Usages of the enclosing collections, outermost first (0 for a usage-less one).
    pub collections: Vec<Usage>,
    /// Main item flag bit 0. Microsoft's eye-tracker descriptors mark real data Constant
    /// (`Input (Cnst,Var,Abs)`), so this is kept for display, never used to drop a field.
    pub constant: bool,
}

impl Field {
    /// Total bits spanned.
    pub fn total_bits(&self) -> u32 {
        self.bit_size.saturating_mul(self.count)
    }
    pub fn is_signed(&self) -> bool {
        self.logical_min < 0
    }
    pub fn in_collection(&self, u: Usage) -> bool {
        self.collections.contains(&u)
    }

    /// The raw value from `report` (report id first, 0 for devices without ids, as
    /// [`dioptra_transport::HidLink`] gives it), sign-extended when the logical minimum is
    /// negative. `None` when the report is too short or the field wider than 64 bits.
    pub fn read(&self, report: &[u8]) -> Option<i64> {
        let bits = self.total_bits();
        if bits == 0 || bits > 64 {
            return None;
        }
        let start = u64::from(self.bit_offset) + 8;
        let end = start + u64::from(bits);
        if end > report.len() as u64 * 8 {
            return None;
        }
        let mut v: u64 = 0;
        // Byte-wise when aligned (the common case), bit-wise otherwise.
        if start % 8 == 0 && bits.is_multiple_of(8) {
            let b = (start / 8) as usize;
            for (i, byte) in report[b..b + (bits / 8) as usize].iter().enumerate() {
                v |= u64::from(*byte) << (8 * i);
            }
        } else {
            for i in 0..u64::from(bits) {
                let bit = start + i;
                let byte = report[(bit / 8) as usize];
                v |= u64::from((byte >> (bit % 8)) & 1) << i;
            }
        }
        if self.is_signed() && bits < 64 && v >> (bits - 1) & 1 == 1 {
            v |= u64::MAX << bits;
        }
        Some(v as i64)
    }

    /// Writes `value` into `report` (the inverse of [`Field::read`]); false if it does not fit.
    pub fn write(&self, report: &mut [u8], value: i64) -> bool {
        let bits = self.total_bits();
        if bits == 0 || bits > 64 {
            return false;
        }
        let start = u64::from(self.bit_offset) + 8;
        if start + u64::from(bits) > report.len() as u64 * 8 {
            return false;
        }
        let v = value as u64;
        for i in 0..u64::from(bits) {
            let bit = start + i;
            let byte = &mut report[(bit / 8) as usize];
            let mask = 1u8 << (bit % 8);
            if v >> i & 1 == 1 {
                *byte |= mask;
            } else {
                *byte &= !mask;
            }
        }
        true
    }
}

/// A parsed report descriptor.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ReportDescriptor {
    pub fields: Vec<Field>,
    /// Every report starts with a report id byte.
    pub uses_report_ids: bool,
    /// (kind, id, bits after the id byte) for every report declared.
    pub report_bits: Vec<(ReportKind, u8, u32)>,
    /// Usages of the top-level (application) collections.
    pub applications: Vec<Usage>,
}

impl ReportDescriptor {
    /// The first field with `usage` in a report of `kind` whose collection path contains
    /// every usage of `within`.
    pub fn find(&self, kind: ReportKind, usage: Usage, within: &[Usage]) -> Option<&Field> {
        self.fields.iter().find(|f| {
            f.kind == kind && f.usage == usage && within.iter().all(|c| f.in_collection(*c))
        })
    }

    /// Length in bytes of report `id` of `kind`, including the id byte (always counted,
    /// following the [`dioptra_transport::HidLink`] convention).
    pub fn report_len(&self, kind: ReportKind, id: u8) -> Option<usize> {
        self.report_bits
            .iter()
            .find(|r| r.0 == kind && r.1 == id)
            .map(|r| 1 + r.2.div_ceil(8) as usize)
    }
}

/// Why a descriptor could not be parsed.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum DescriptorError {
    #[error("report descriptor truncated at byte {offset}")]
    Truncated { offset: usize },
    #[error("report descriptor: End Collection without a Collection at byte {offset}")]
    UnbalancedCollection { offset: usize },
    #[error("report descriptor: Pop without Push at byte {offset}")]
    PopWithoutPush { offset: usize },
    #[error("report descriptor: {what} exceeds the parser's limit of {limit}")]
    TooLarge { what: &'static str, limit: usize },
    #[error("report descriptor: report {id} is longer than {limit} bits")]
    ReportTooLong { id: u8, limit: u32 },
    #[error("report descriptor: Report ID outside 1..=255 at byte {offset}")]
    BadReportId { offset: usize },
}

const MAX_FIELDS: usize = 4096;
const MAX_DEPTH: usize = 32;
const MAX_USAGES: usize = 1024;
/// 64 KiB per report: far beyond any real device, small enough to bound the work.
const MAX_REPORT_BITS: u32 = 8 * 65_536;

#[derive(Debug, Clone, Copy, Default)]
struct Globals {
    page: u16,
    logical_min: i32,
    logical_max: i32,
    unit: u32,
    unit_exponent: i8,
    report_size: u32,
    report_id: u8,
    report_count: u32,
}

/// Parses `bytes`.
pub fn parse(bytes: &[u8]) -> Result<ReportDescriptor, DescriptorError> {
    let mut out = ReportDescriptor::default();
    let mut g = Globals::default();
    let mut stack: Vec<Globals> = Vec::new();
    let mut usages: Vec<Usage> = Vec::new();
    let mut usage_min: Option<u32> = None;
    let mut collections: Vec<Usage> = Vec::new();
    let mut i = 0usize;
    while i < bytes.len() {
        let offset = i;
        let prefix = bytes[i];
        if prefix == 0xfe {
            // Long item (none are defined): skip it.
            let size = *bytes
                .get(i + 1)
                .ok_or(DescriptorError::Truncated { offset })?;
            i += 3 + usize::from(size);
            if i > bytes.len() {
                return Err(DescriptorError::Truncated { offset });
            }
            continue;
        }
        let size = [0usize, 1, 2, 4][usize::from(prefix & 3)];
        let data = bytes
            .get(i + 1..i + 1 + size)
            .ok_or(DescriptorError::Truncated { offset })?;
        i += 1 + size;
        let mut raw = [0u8; 4];
        raw[..size].copy_from_slice(data);
        let u = u32::from_le_bytes(raw);
        // Signed value for logical ranges: sign-extend from the item's size.
        let s = match size {
            1 => i32::from(data[0] as i8),
            2 => i32::from(i16::from_le_bytes([data[0], data[1]])),
            4 => u as i32,
            _ => 0,
        };
        let tag = prefix & 0xfc;
        match tag {
            // Main items.
            0x80 | 0x90 | 0xb0 => {
                let kind = match tag {
                    0x80 => ReportKind::Input,
                    0x90 => ReportKind::Output,
                    _ => ReportKind::Feature,
                };
                add_main(&mut out, &g, kind, u, &usages, &collections)?;
                usages.clear();
                usage_min = None;
            }
            0xa0 => {
                if collections.len() >= MAX_DEPTH {
                    return Err(DescriptorError::TooLarge {
                        what: "collection nesting",
                        limit: MAX_DEPTH,
                    });
                }
                let c = usages.first().copied().unwrap_or(Usage(0));
                if collections.is_empty() {
                    out.applications.push(c);
                }
                collections.push(c);
                usages.clear();
                usage_min = None;
            }
            0xc0 => {
                if collections.pop().is_none() {
                    return Err(DescriptorError::UnbalancedCollection { offset });
                }
                usages.clear();
                usage_min = None;
            }
            // Global items.
            0x04 => g.page = u as u16,
            0x14 => g.logical_min = s,
            0x24 => {
                // A maximum read as negative with a non-negative minimum is really unsigned.
                g.logical_max = if s < 0 && g.logical_min >= 0 {
                    u as i32
                } else {
                    s
                };
            }
            0x34 | 0x44 => {} // physical range: not needed
            0x54 => {
                // 4-bit two's complement nibble (HID 1.11, 6.2.2.7).
                let n = (u & 0xf) as i8;
                g.unit_exponent = if n > 7 { n - 16 } else { n };
            }
            0x64 => g.unit = u,
            0x74 => g.report_size = u,
            0x84 => {
                if u == 0 || u > 255 {
                    return Err(DescriptorError::BadReportId { offset });
                }
                g.report_id = u as u8;
                out.uses_report_ids = true;
            }
            0x94 => g.report_count = u,
            0xa4 => {
                if stack.len() >= MAX_DEPTH {
                    return Err(DescriptorError::TooLarge {
                        what: "Push depth",
                        limit: MAX_DEPTH,
                    });
                }
                stack.push(g);
            }
            0xb4 => {
                g = stack
                    .pop()
                    .ok_or(DescriptorError::PopWithoutPush { offset })?
            }
            // Local items.
            0x08 => push_usage(&mut usages, full_usage(u, size, g.page))?,
            0x18 => usage_min = Some(full_usage(u, size, g.page).0),
            0x28 => {
                let max = full_usage(u, size, g.page).0;
                if let Some(min) = usage_min.take() {
                    if max >= min {
                        if max - min >= MAX_USAGES as u32 {
                            return Err(DescriptorError::TooLarge {
                                what: "usage range",
                                limit: MAX_USAGES,
                            });
                        }
                        for v in min..=max {
                            push_usage(&mut usages, Usage(v))?;
                        }
                    }
                }
            }
            _ => {} // designators, strings, delimiters, reserved: ignored
        }
    }
    Ok(out)
}

fn full_usage(u: u32, size: usize, page: u16) -> Usage {
    // A 4-byte usage carries its own page.
    if size == 4 {
        Usage(u)
    } else {
        Usage::new(page, u as u16)
    }
}

fn push_usage(usages: &mut Vec<Usage>, u: Usage) -> Result<(), DescriptorError> {
    if usages.len() >= MAX_USAGES {
        return Err(DescriptorError::TooLarge {
            what: "usages per item",
            limit: MAX_USAGES,
        });
    }
    usages.push(u);
    Ok(())
}

fn add_main(
    out: &mut ReportDescriptor,
    g: &Globals,
    kind: ReportKind,
    flags: u32,
    usages: &[Usage],
    collections: &[Usage],
) -> Result<(), DescriptorError> {
    let total = g.report_size.saturating_mul(g.report_count);
    let idx = match out
        .report_bits
        .iter()
        .position(|r| r.0 == kind && r.1 == g.report_id)
    {
        Some(i) => i,
        None => {
            out.report_bits.push((kind, g.report_id, 0));
            out.report_bits.len() - 1
        }
    };
    let offset = out.report_bits[idx].2;
    let end = offset.saturating_add(total);
    if end > MAX_REPORT_BITS {
        return Err(DescriptorError::ReportTooLong {
            id: g.report_id,
            limit: MAX_REPORT_BITS,
        });
    }
    out.report_bits[idx].2 = end;
    let constant = flags & 1 != 0;
    let variable = flags & 2 != 0;
    // Padding is a main item without usages, whatever its flags: Linux's hid-core
    // (hid_add_field) does the same. Constant fields with usages carry data: Microsoft's
    // GazeHid and DMF VirtualEyeGaze descriptors declare the gaze point that way.
    if !variable || usages.is_empty() || g.report_size == 0 {
        return Ok(()); // padding, or an array (selectors: not needed by these drivers)
    }
    // Usage i labels element i; the last usage labels all remaining elements.
    let n = usages.len().min(g.report_count as usize);
    for (i, usage) in usages.iter().take(n).enumerate() {
        if out.fields.len() >= MAX_FIELDS {
            return Err(DescriptorError::TooLarge {
                what: "fields",
                limit: MAX_FIELDS,
            });
        }
        let count = if i + 1 == n {
            g.report_count - i as u32
        } else {
            1
        };
        out.fields.push(Field {
            kind,
            report_id: g.report_id,
            usage: *usage,
            bit_offset: offset + i as u32 * g.report_size,
            bit_size: g.report_size,
            count,
            logical_min: g.logical_min,
            logical_max: g.logical_max,
            unit: g.unit,
            unit_exponent: g.unit_exponent,
            collections: collections.to_vec(),
            constant,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_fields_offsets_ids_and_collections() {
        #[rustfmt::skip]
        let d = [
            0x05, 0x12, 0x09, 0x01, 0xa1, 0x01,       // page 0x12, Eye Tracker, Application
            0x85, 0x10, 0x09, 0x10, 0xa1, 0x02,       //   report 0x10, Tracking Data, Logical
            0x09, 0x20, 0x75, 0x40, 0x95, 0x01,       //     Timestamp, 64 bits
            0x81, 0x02,
            0x09, 0x25, 0xa1, 0x00,                   //     Left Eye Position, Physical
            0x09, 0x21, 0x09, 0x22, 0x09, 0x23,       //       X Y Z
            0x17, 0x00, 0x00, 0x00, 0x80,             //       logical min i32::MIN
            0x27, 0xff, 0xff, 0xff, 0x7f,
            0x75, 0x20, 0x95, 0x03, 0x81, 0x02,
            0xc0,
            0x75, 0x03, 0x95, 0x01, 0x81, 0x03,       //     3 bits padding
            0x15, 0x00, 0x25, 0x03,
            0x0b, 0x00, 0x04, 0x12, 0x00,             //     4-byte usage 0x12:0x400
            0x75, 0x05, 0x81, 0x02,
            0xc0,
            0xc0,
        ];
        let r = parse(&d).unwrap();
        assert!(r.uses_report_ids);
        assert_eq!(r.applications, vec![Usage::new(0x12, 1)]);
        let ts = r
            .find(ReportKind::Input, Usage::new(0x12, 0x20), &[])
            .unwrap();
        assert_eq!((ts.bit_offset, ts.bit_size, ts.report_id), (0, 64, 0x10));
        let left = Usage::new(0x12, 0x25);
        let z = r
            .find(ReportKind::Input, Usage::new(0x12, 0x23), &[left])
            .unwrap();
        assert_eq!((z.bit_offset, z.bit_size), (128, 32));
        assert!(z.is_signed());
        let m = r
            .find(ReportKind::Input, Usage::new(0x12, 0x400), &[])
            .unwrap();
        assert_eq!((m.bit_offset, m.bit_size, m.is_signed()), (163, 5, false));
        assert_eq!(r.report_len(ReportKind::Input, 0x10), Some(1 + 21));

        let mut report = vec![0u8; 22];
        report[0] = 0x10;
        assert!(z.write(&mut report, -5));
        assert!(m.write(&mut report, 17));
        assert!(ts.write(&mut report, 1 << 40));
        assert_eq!(z.read(&report), Some(-5));
        assert_eq!(m.read(&report), Some(17));
        assert_eq!(ts.read(&report), Some(1 << 40));
        assert_eq!(z.read(&report[..16]), None);
    }

    #[test]
    fn constant_fields_with_usages_are_data_and_without_are_padding() {
        #[rustfmt::skip]
        let d = [
            0x05, 0x12, 0x85, 0x10, 0x75, 0x08, 0x95, 0x01,
            0x81, 0x03,                               // usage-less Constant: padding
            0x09, 0x21, 0x81, 0x03,                   // Position X, Constant: data
            0x09, 0x22, 0x81, 0x02,                   // Position Y, Data
        ];
        let r = parse(&d).unwrap();
        let usages: Vec<_> = r
            .fields
            .iter()
            .map(|f| (f.usage.id(), f.constant))
            .collect();
        assert_eq!(usages, vec![(0x21, true), (0x22, false)]);
        assert_eq!(r.fields[0].bit_offset, 8);
        assert_eq!(r.report_len(ReportKind::Input, 0x10), Some(1 + 3));
    }

    #[test]
    fn repeated_usage_spans_the_remaining_elements() {
        // Timestamp as 8 x 8 bits: one 64-bit little-endian value.
        let d = [0x05, 0x12, 0x09, 0x20, 0x75, 0x08, 0x95, 0x08, 0x81, 0x02];
        let r = parse(&d).unwrap();
        assert!(!r.uses_report_ids);
        let f = &r.fields[0];
        assert_eq!((f.count, f.total_bits()), (8, 64));
        let report = [0, 1, 2, 3, 4, 5, 6, 7, 8];
        assert_eq!(f.read(&report), Some(0x0807060504030201));
    }

    #[test]
    fn usage_ranges_push_pop_and_unit_exponent() {
        #[rustfmt::skip]
        let d = [
            0x05, 0x12, 0x19, 0x21, 0x29, 0x23,       // usages 0x21..=0x23
            0x55, 0x0e, 0x66, 0x11, 0x00,             // exponent -2, unit cm
            0xa4, 0x75, 0x10, 0x95, 0x03, 0x81, 0x02, // push; 3 x 16 bits
            0xb4, 0x09, 0x24, 0x75, 0x08, 0x95, 0x01, // pop: size 0 again -> 8 below
            0x81, 0x02,
        ];
        let r = parse(&d).unwrap();
        assert_eq!(r.fields.len(), 4);
        assert_eq!(r.fields[2].usage, Usage::new(0x12, 0x23));
        assert_eq!((r.fields[2].unit, r.fields[2].unit_exponent), (0x11, -2));
        assert_eq!(r.fields[3].bit_offset, 48);
    }

    #[test]
    fn malformed_descriptors_are_errors() {
        assert_eq!(
            parse(&[0x05]),
            Err(DescriptorError::Truncated { offset: 0 })
        );
        assert_eq!(
            parse(&[0xfe, 0x05, 0x00, 1]),
            Err(DescriptorError::Truncated { offset: 0 })
        );
        assert_eq!(
            parse(&[0xc0]),
            Err(DescriptorError::UnbalancedCollection { offset: 0 })
        );
        assert_eq!(
            parse(&[0xb4]),
            Err(DescriptorError::PopWithoutPush { offset: 0 })
        );
        assert_eq!(
            parse(&[0x85, 0x00]),
            Err(DescriptorError::BadReportId { offset: 0 })
        );
        assert!(matches!(
            parse(&[0xa1, 0x01].repeat(40)),
            Err(DescriptorError::TooLarge { .. })
        ));
        // 255 bits x 65535 elements: too long.
        assert!(matches!(
            parse(&[0x75, 0xff, 0x96, 0xff, 0xff, 0x81, 0x02, 0x81, 0x02]),
            Err(DescriptorError::ReportTooLong { .. })
        ));
        assert!(matches!(
            parse(&[0x19, 0x00, 0x2a, 0xff, 0xff]),
            Err(DescriptorError::TooLarge { .. })
        ));
        assert_eq!(parse(&[]), Ok(ReportDescriptor::default()));
    }
}
