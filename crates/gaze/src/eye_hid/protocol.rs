//! Usage page 0x12 (HUTRR74) report layouts, located from the report descriptor; never
//! assumed. Values come out in the units the usage page defines: positions in micrometres,
//! time in microseconds, rotations in degrees, frequency in Hz. A field that declares a HID
//! unit (SI or English length, SI time, degrees or radians) is converted from it.

use thiserror::Error;

use crate::hid_descriptor::{Field, ReportDescriptor, ReportKind, Usage};

/// Usages of page 0x12.
pub mod usage {
    use crate::hid_descriptor::Usage;
    const fn u(id: u16) -> Usage {
        Usage::new(0x12, id)
    }
    pub const EYE_TRACKER: Usage = u(0x01);
    pub const TRACKING_DATA: Usage = u(0x10);
    pub const CAPABILITIES: Usage = u(0x11);
    pub const CONFIGURATION: Usage = u(0x12);
    pub const STATUS: Usage = u(0x13);
    pub const CONTROL: Usage = u(0x14);
    pub const TIMESTAMP: Usage = u(0x20);
    pub const POSITION_X: Usage = u(0x21);
    pub const POSITION_Y: Usage = u(0x22);
    pub const POSITION_Z: Usage = u(0x23);
    pub const GAZE_POINT: Usage = u(0x24);
    pub const LEFT_EYE_POSITION: Usage = u(0x25);
    pub const RIGHT_EYE_POSITION: Usage = u(0x26);
    pub const HEAD_POSITION: Usage = u(0x27);
    pub const HEAD_DIRECTION: Usage = u(0x28);
    pub const ROTATION_X: Usage = u(0x29);
    pub const ROTATION_Y: Usage = u(0x2a);
    pub const ROTATION_Z: Usage = u(0x2b);
    pub const TRACKER_QUALITY: Usage = u(0x100);
    pub const MINIMUM_TRACKING_DISTANCE: Usage = u(0x101);
    pub const OPTIMUM_TRACKING_DISTANCE: Usage = u(0x102);
    pub const MAXIMUM_TRACKING_DISTANCE: Usage = u(0x103);
    pub const MAXIMUM_SCREEN_PLANE_WIDTH: Usage = u(0x104);
    pub const MAXIMUM_SCREEN_PLANE_HEIGHT: Usage = u(0x105);
    pub const CALIBRATED_SCREEN_WIDTH: Usage = u(0x204);
    pub const CALIBRATED_SCREEN_HEIGHT: Usage = u(0x205);
    pub const SAMPLING_FREQUENCY: Usage = u(0x300);
    pub const CONFIGURATION_STATUS: Usage = u(0x301);
    pub const MODE_REQUEST: Usage = u(0x400);
}

/// The descriptor lacks something the driver needs, or uses it in a way we cannot read.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum LayoutError {
    #[error("report descriptor has no {what} (usage {usage}) in a {kind:?} report")]
    Missing {
        what: &'static str,
        usage: Usage,
        kind: ReportKind,
    },
    #[error("{what} is split over reports {a} and {b}; it must be in one report")]
    SplitReport { what: &'static str, a: u8, b: u8 },
    #[error("{what} field is {bits} bits wide; at most 64 are supported")]
    TooWide { what: &'static str, bits: u32 },
    #[error("{what} field has HID unit {unit:#x}, which is not a {expected}")]
    UnsupportedUnit {
        what: &'static str,
        unit: u32,
        expected: &'static str,
    },
}

/// A report that does not match its layout.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum ReportError {
    #[error("report id {got}, expected {expected}")]
    WrongId { expected: u8, got: u8 },
    #[error("report {id} is {got} bytes, its layout needs {needed}")]
    Short { id: u8, needed: usize, got: usize },
    #[error("empty report")]
    Empty,
    #[error("report {id}: {detail}")]
    Malformed { id: u8, detail: String },
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Quantity {
    Length,
    Time,
    Angle,
    Plain,
}

/// A located field with the factor that takes its raw value to the page's unit.
#[derive(Debug, Clone, PartialEq)]
pub struct Located {
    pub field: Field,
    /// Multiplies the raw value into µm, µs, degrees, or leaves it (plain numbers).
    pub scale: f64,
}

impl Located {
    fn new(field: &Field, what: &'static str, q: Quantity) -> Result<Located, LayoutError> {
        if field.total_bits() > 64 {
            return Err(LayoutError::TooWide {
                what,
                bits: field.total_bits(),
            });
        }
        let exp = 10f64.powi(i32::from(field.unit_exponent));
        let bad = |expected| LayoutError::UnsupportedUnit {
            what,
            unit: field.unit,
            expected,
        };
        // Without a unit item the page's own units apply, unscaled.
        let scale = match (q, field.unit) {
            (_, 0) => 1.0,
            (Quantity::Length, 0x11) => exp * 1e4,      // cm
            (Quantity::Length, 0x13) => exp * 25_400.0, // inch
            (Quantity::Length, _) => return Err(bad("length")),
            (Quantity::Time, 0x1001) => exp * 1e6, // s
            (Quantity::Time, _) => return Err(bad("time")),
            (Quantity::Angle, 0x14) => exp,              // degree
            (Quantity::Angle, 0x12) => exp.to_degrees(), // radian
            (Quantity::Angle, _) => return Err(bad("rotation")),
            (Quantity::Plain, _) => exp,
        };
        Ok(Located {
            field: field.clone(),
            scale,
        })
    }

    /// The value in the page's units; `None` if the report is too short.
    pub fn get(&self, report: &[u8]) -> Option<f64> {
        self.field.read(report).map(|v| v as f64 * self.scale)
    }
}

fn find(
    d: &ReportDescriptor,
    kind: ReportKind,
    report: Usage,
    usage: Usage,
    within: Option<Usage>,
) -> Option<&Field> {
    // Prefer the report's own collection; fall back to any report of that kind.
    let mut path = vec![report];
    path.extend(within);
    d.find(kind, usage, &path)
        .or_else(|| d.find(kind, usage, within.as_slice()))
}

fn required(
    d: &ReportDescriptor,
    kind: ReportKind,
    report: Usage,
    usage: Usage,
    within: Option<Usage>,
    what: &'static str,
    q: Quantity,
) -> Result<Located, LayoutError> {
    let f =
        find(d, kind, report, usage, within).ok_or(LayoutError::Missing { what, usage, kind })?;
    Located::new(f, what, q)
}

fn xyz(
    d: &ReportDescriptor,
    report: Usage,
    within: Usage,
    what: &'static str,
    usages: [Usage; 3],
    q: Quantity,
) -> Result<Option<[Located; 3]>, LayoutError> {
    let in_collection = |u| d.find(ReportKind::Input, u, &[report, within]);
    let (Some(x), Some(y), Some(z)) = (
        in_collection(usages[0]),
        in_collection(usages[1]),
        in_collection(usages[2]),
    ) else {
        return Ok(None);
    };
    Ok(Some([
        Located::new(x, what, q)?,
        Located::new(y, what, q)?,
        Located::new(z, what, q)?,
    ]))
}

/// Where every field of the Tracking Data input report is.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackingLayout {
    pub report_id: u8,
    pub len: usize,
    pub timestamp: Located,
    pub gaze_point: [Located; 2],
    pub left_eye: Option<[Located; 3]>,
    pub right_eye: Option<[Located; 3]>,
    pub head_position: Option<[Located; 3]>,
    pub head_direction: Option<[Located; 3]>,
}

/// One Tracking Data report in the page's units.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TrackingData {
    pub timestamp_us: u64,
    /// On the screen plane, µm from its top-left corner; `None` when the tracker reports
    /// (0, 0), its way of saying "not tracked".
    pub gaze_point_um: Option<[f64; 2]>,
    /// Eye positions, µm, screen frame; `None` when absent from the layout or all zero.
    pub left_eye_um: Option<[f64; 3]>,
    pub right_eye_um: Option<[f64; 3]>,
    pub head_position_um: Option<[f64; 3]>,
    /// Rotation about x, y, z, degrees.
    pub head_direction_deg: Option<[f64; 3]>,
}

fn read3(l: &Option<[Located; 3]>, r: &[u8]) -> Result<Option<[f64; 3]>, ()> {
    let Some(l) = l else { return Ok(None) };
    let v = [
        l[0].get(r).ok_or(())?,
        l[1].get(r).ok_or(())?,
        l[2].get(r).ok_or(())?,
    ];
    Ok((v != [0.0; 3]).then_some(v))
}

impl TrackingLayout {
    /// Parses one input report (report id first).
    pub fn parse(&self, report: &[u8]) -> Result<TrackingData, ReportError> {
        let &id = report.first().ok_or(ReportError::Empty)?;
        if id != self.report_id {
            return Err(ReportError::WrongId {
                expected: self.report_id,
                got: id,
            });
        }
        let short = ReportError::Short {
            id,
            needed: self.len,
            got: report.len(),
        };
        if report.len() < self.len {
            return Err(short);
        }
        let ts = self.timestamp.field.read(report).ok_or(short.clone())?;
        let gx = self.gaze_point[0].get(report).ok_or(short.clone())?;
        let gy = self.gaze_point[1].get(report).ok_or(short.clone())?;
        let e = |_| short.clone();
        let timestamp_us = if self.timestamp.scale == 1.0 {
            ts as u64
        } else {
            (ts as f64 * self.timestamp.scale).max(0.0) as u64
        };
        Ok(TrackingData {
            timestamp_us,
            gaze_point_um: (gx != 0.0 || gy != 0.0).then_some([gx, gy]),
            left_eye_um: read3(&self.left_eye, report).map_err(e)?,
            right_eye_um: read3(&self.right_eye, report).map_err(e)?,
            head_position_um: read3(&self.head_position, report).map_err(e)?,
            head_direction_deg: read3(&self.head_direction, report).map_err(e)?,
        })
    }
}

/// Capabilities feature report, page units (µm).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Capabilities {
    pub tracker_quality: Option<u8>,
    pub min_tracking_distance_um: Option<f64>,
    pub optimum_tracking_distance_um: Option<f64>,
    pub max_tracking_distance_um: Option<f64>,
    pub max_screen_width_um: Option<f64>,
    pub max_screen_height_um: Option<f64>,
    /// When the device puts it here rather than in Status.
    pub sampling_frequency_hz: Option<f64>,
}

/// Configuration feature report: the calibrated screen, µm.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Configuration {
    pub calibrated_screen_width_um: Option<f64>,
    pub calibrated_screen_height_um: Option<f64>,
}

/// Configuration Status values (HUTRR74).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConfigStatus {
    Ready,
    Configuring,
    ScreenSetupNeeded,
    UserCalibrationNeeded,
    Other(u8),
}

impl ConfigStatus {
    pub fn from_raw(v: i64) -> Self {
        match v {
            1 => ConfigStatus::Ready,
            2 => ConfigStatus::Configuring,
            3 => ConfigStatus::ScreenSetupNeeded,
            4 => ConfigStatus::UserCalibrationNeeded,
            v => ConfigStatus::Other(v.clamp(0, 255) as u8),
        }
    }
    pub fn code(self) -> u8 {
        match self {
            ConfigStatus::Ready => 1,
            ConfigStatus::Configuring => 2,
            ConfigStatus::ScreenSetupNeeded => 3,
            ConfigStatus::UserCalibrationNeeded => 4,
            ConfigStatus::Other(v) => v,
        }
    }
}

/// Status feature report.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Status {
    pub config_status: ConfigStatus,
    pub sampling_frequency_hz: Option<f64>,
}

/// Mode Request bits of the Control report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ModeRequest(pub u8);

impl ModeRequest {
    pub const GAZE_POINT: ModeRequest = ModeRequest(1);
    pub const EYE_POSITION: ModeRequest = ModeRequest(2);
    pub const HEAD_POSITION: ModeRequest = ModeRequest(4);
    pub const fn with(self, o: ModeRequest) -> ModeRequest {
        ModeRequest(self.0 | o.0)
    }
    pub const fn contains(self, o: ModeRequest) -> bool {
        self.0 & o.0 == o.0
    }
}

/// One feature report's id, length and located fields.
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureLayout {
    pub report_id: u8,
    pub len: usize,
    fields: Vec<(Usage, Located)>,
}

impl FeatureLayout {
    fn locate(
        d: &ReportDescriptor,
        report: Usage,
        wanted: &[(Usage, Quantity)],
        what: &'static str,
    ) -> Result<Option<FeatureLayout>, LayoutError> {
        let mut fields = Vec::new();
        let mut id = None;
        for &(u, q) in wanted {
            let Some(f) = d.find(ReportKind::Feature, u, &[report]) else {
                continue;
            };
            match id {
                None => id = Some(f.report_id),
                Some(a) if a != f.report_id => {
                    return Err(LayoutError::SplitReport {
                        what,
                        a,
                        b: f.report_id,
                    })
                }
                Some(_) => {}
            }
            fields.push((u, Located::new(f, what, q)?));
        }
        let Some(report_id) = id else { return Ok(None) };
        let len = d.report_len(ReportKind::Feature, report_id).unwrap_or(1);
        Ok(Some(FeatureLayout {
            report_id,
            len,
            fields,
        }))
    }

    fn check(&self, report: &[u8]) -> Result<(), ReportError> {
        let &id = report.first().ok_or(ReportError::Empty)?;
        if id != self.report_id {
            return Err(ReportError::WrongId {
                expected: self.report_id,
                got: id,
            });
        }
        if report.len() < self.len {
            return Err(ReportError::Short {
                id,
                needed: self.len,
                got: report.len(),
            });
        }
        Ok(())
    }

    fn get(&self, u: Usage, report: &[u8]) -> Option<f64> {
        self.fields.iter().find(|f| f.0 == u)?.1.get(report)
    }

    pub fn has(&self, u: Usage) -> bool {
        self.fields.iter().any(|f| f.0 == u)
    }
}

/// Everything the driver needs, located from one descriptor.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackerLayout {
    pub tracking: TrackingLayout,
    pub capabilities: FeatureLayout,
    pub configuration: Option<FeatureLayout>,
    pub status: FeatureLayout,
    pub control: FeatureLayout,
}

impl TrackerLayout {
    /// Locates the reports. Required: Tracking Data with Timestamp and Gaze Point,
    /// Capabilities, Status with Configuration Status, Control with Mode Request.
    pub fn locate(d: &ReportDescriptor) -> Result<TrackerLayout, LayoutError> {
        use usage::*;
        use Quantity::*;
        let td = TRACKING_DATA;
        let input = ReportKind::Input;
        let timestamp = required(d, input, td, TIMESTAMP, None, "Timestamp", Time)?;
        let gx = required(
            d,
            input,
            td,
            POSITION_X,
            Some(GAZE_POINT),
            "Gaze Point X",
            Length,
        )?;
        let gy = required(
            d,
            input,
            td,
            POSITION_Y,
            Some(GAZE_POINT),
            "Gaze Point Y",
            Length,
        )?;
        let pos = [POSITION_X, POSITION_Y, POSITION_Z];
        let rot = [ROTATION_X, ROTATION_Y, ROTATION_Z];
        let tracking = TrackingLayout {
            report_id: timestamp.field.report_id,
            len: d.report_len(input, timestamp.field.report_id).unwrap_or(1),
            left_eye: xyz(d, td, LEFT_EYE_POSITION, "Left Eye Position", pos, Length)?,
            right_eye: xyz(d, td, RIGHT_EYE_POSITION, "Right Eye Position", pos, Length)?,
            head_position: xyz(d, td, HEAD_POSITION, "Head Position", pos, Length)?,
            head_direction: xyz(d, td, HEAD_DIRECTION, "Head Direction", rot, Angle)?,
            gaze_point: [gx, gy],
            timestamp,
        };
        let id = tracking.report_id;
        let all = [&tracking.gaze_point[..]]
            .into_iter()
            .chain(tracking.left_eye.as_ref().map(|v| &v[..]))
            .chain(tracking.right_eye.as_ref().map(|v| &v[..]))
            .chain(tracking.head_position.as_ref().map(|v| &v[..]))
            .chain(tracking.head_direction.as_ref().map(|v| &v[..]))
            .flatten();
        for l in all {
            if l.field.report_id != id {
                return Err(LayoutError::SplitReport {
                    what: "Tracking Data",
                    a: id,
                    b: l.field.report_id,
                });
            }
        }
        let missing = |what, usage| LayoutError::Missing {
            what,
            usage,
            kind: ReportKind::Feature,
        };
        let capabilities = FeatureLayout::locate(
            d,
            CAPABILITIES,
            &[
                (TRACKER_QUALITY, Plain),
                (MINIMUM_TRACKING_DISTANCE, Length),
                (OPTIMUM_TRACKING_DISTANCE, Length),
                (MAXIMUM_TRACKING_DISTANCE, Length),
                (MAXIMUM_SCREEN_PLANE_WIDTH, Length),
                (MAXIMUM_SCREEN_PLANE_HEIGHT, Length),
                (SAMPLING_FREQUENCY, Plain),
            ],
            "Capabilities",
        )?
        .ok_or(missing("Capabilities report", CAPABILITIES))?;
        let configuration = FeatureLayout::locate(
            d,
            CONFIGURATION,
            &[
                (CALIBRATED_SCREEN_WIDTH, Length),
                (CALIBRATED_SCREEN_HEIGHT, Length),
            ],
            "Configuration",
        )?;
        let status = FeatureLayout::locate(
            d,
            STATUS,
            &[(CONFIGURATION_STATUS, Plain), (SAMPLING_FREQUENCY, Plain)],
            "Status",
        )?
        .filter(|s| s.has(CONFIGURATION_STATUS))
        .ok_or(missing("Configuration Status", CONFIGURATION_STATUS))?;
        let control = FeatureLayout::locate(d, CONTROL, &[(MODE_REQUEST, Plain)], "Control")?
            .ok_or(missing("Mode Request", MODE_REQUEST))?;
        Ok(TrackerLayout {
            tracking,
            capabilities,
            configuration,
            status,
            control,
        })
    }

    pub fn parse_capabilities(&self, r: &[u8]) -> Result<Capabilities, ReportError> {
        use usage::*;
        let c = &self.capabilities;
        c.check(r)?;
        Ok(Capabilities {
            tracker_quality: c.get(TRACKER_QUALITY, r).map(|v| v.clamp(0.0, 255.0) as u8),
            min_tracking_distance_um: c.get(MINIMUM_TRACKING_DISTANCE, r),
            optimum_tracking_distance_um: c.get(OPTIMUM_TRACKING_DISTANCE, r),
            max_tracking_distance_um: c.get(MAXIMUM_TRACKING_DISTANCE, r),
            max_screen_width_um: c.get(MAXIMUM_SCREEN_PLANE_WIDTH, r),
            max_screen_height_um: c.get(MAXIMUM_SCREEN_PLANE_HEIGHT, r),
            sampling_frequency_hz: c.get(SAMPLING_FREQUENCY, r),
        })
    }

    pub fn parse_configuration(&self, r: &[u8]) -> Result<Option<Configuration>, ReportError> {
        let Some(c) = &self.configuration else {
            return Ok(None);
        };
        c.check(r)?;
        Ok(Some(Configuration {
            calibrated_screen_width_um: c.get(usage::CALIBRATED_SCREEN_WIDTH, r),
            calibrated_screen_height_um: c.get(usage::CALIBRATED_SCREEN_HEIGHT, r),
        }))
    }

    pub fn parse_status(&self, r: &[u8]) -> Result<Status, ReportError> {
        let s = &self.status;
        s.check(r)?;
        let raw = s.fields.iter().find(|f| f.0 == usage::CONFIGURATION_STATUS);
        let code = raw
            .and_then(|f| f.1.field.read(r))
            .ok_or(ReportError::Short {
                id: s.report_id,
                needed: s.len,
                got: r.len(),
            })?;
        Ok(Status {
            config_status: ConfigStatus::from_raw(code),
            sampling_frequency_hz: s.get(usage::SAMPLING_FREQUENCY, r),
        })
    }

    /// The Control report requesting `modes`.
    pub fn control_report(&self, modes: ModeRequest) -> Vec<u8> {
        let c = &self.control;
        let mut r = vec![0u8; c.len.max(1)];
        r[0] = c.report_id;
        if let Some((_, l)) = c.fields.iter().find(|f| f.0 == usage::MODE_REQUEST) {
            l.field.write(&mut r, i64::from(modes.0));
        }
        r
    }
}
