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

/// HUTRR74's name for a page 0x12 usage ("" for one it does not define).
pub fn usage_name(u: Usage) -> &'static str {
    if u.page() != 0x12 {
        return "";
    }
    match u.id() {
        0x01 => "Eye Tracker",
        0x02 => "Head Tracker",
        0x10 => "Tracking Data",
        0x11 => "Capabilities",
        0x12 => "Configuration",
        0x13 => "Status",
        0x14 => "Control",
        0x20 => "Timestamp",
        0x21 => "Position X",
        0x22 => "Position Y",
        0x23 => "Position Z",
        0x24 => "Gaze Point",
        0x25 => "Left Eye Position",
        0x26 => "Right Eye Position",
        0x27 => "Head Position",
        0x28 => "Head Direction",
        0x29 => "Rotation about X",
        0x2a => "Rotation about Y",
        0x2b => "Rotation about Z",
        0x100 => "Tracker Quality",
        0x101 => "Minimum Tracking Distance",
        0x102 => "Optimum Tracking Distance",
        0x103 => "Maximum Tracking Distance",
        0x104 => "Maximum Screen Plane Width",
        0x105 => "Maximum Screen Plane Height",
        0x200 => "Display Manufacturer ID",
        0x201 => "Display Product ID",
        0x202 => "Display Serial Number",
        0x203 => "Display Manufacturer Date",
        0x204 => "Calibrated Screen Width",
        0x205 => "Calibrated Screen Height",
        0x300 => "Sampling Frequency",
        0x301 => "Configuration Status",
        0x400 => "Mode Request",
        _ => "",
    }
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
    TooWide { what: String, bits: u32 },
    #[error("{what} field has HID unit {unit:#x}, which is not a {expected}")]
    UnsupportedUnit {
        what: String,
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
    /// What the driver reads it as, e.g. "Left Eye Position Z".
    pub name: String,
    pub field: Field,
    /// Multiplies the raw value into µm, µs, degrees, or leaves it (plain numbers).
    pub scale: f64,
    /// The unit `scale` leads to: "µm", "µs", "deg" or "" (plain numbers).
    pub page_unit: &'static str,
}

impl Located {
    fn new(field: &Field, name: String, q: Quantity) -> Result<Located, LayoutError> {
        if field.total_bits() > 64 {
            return Err(LayoutError::TooWide {
                what: name,
                bits: field.total_bits(),
            });
        }
        let exp = 10f64.powi(i32::from(field.unit_exponent));
        let bad = |expected| LayoutError::UnsupportedUnit {
            what: name.clone(),
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
        let page_unit = match q {
            Quantity::Length => "µm",
            Quantity::Time => "µs",
            Quantity::Angle => "deg",
            Quantity::Plain => "",
        };
        Ok(Located {
            name,
            field: field.clone(),
            scale,
            page_unit,
        })
    }

    /// The value in the page's units; `None` if the report is too short.
    pub fn get(&self, report: &[u8]) -> Option<f64> {
        self.field.read(report).map(|v| v as f64 * self.scale)
    }
}

/// The field with `usage` in a report of `kind` (of report `id`, when given) that lies inside
/// every collection of `within`. One also inside the collection carrying the report's usage
/// (`hint`) is preferred, but not required: descriptors with usage-less logical collections
/// are read too, so the hint only breaks ties.
fn pick<'a>(
    d: &'a ReportDescriptor,
    kind: ReportKind,
    id: Option<u8>,
    usage: Usage,
    within: &[Usage],
    hint: Usage,
) -> Option<&'a Field> {
    let matches = |f: &&Field| {
        f.kind == kind
            && f.usage == usage
            && id.is_none_or(|i| f.report_id == i)
            && within.iter().all(|c| f.in_collection(*c))
    };
    d.fields
        .iter()
        .filter(matches)
        .find(|f| f.in_collection(hint))
        .or_else(|| d.fields.iter().find(matches))
}

/// `pick` within report `id`; a match only in another report is [`LayoutError::SplitReport`].
fn pick_in<'a>(
    d: &'a ReportDescriptor,
    kind: ReportKind,
    id: u8,
    usage: Usage,
    within: &[Usage],
    hint: Usage,
    what: &'static str,
) -> Result<Option<&'a Field>, LayoutError> {
    if let Some(f) = pick(d, kind, Some(id), usage, within, hint) {
        return Ok(Some(f));
    }
    match pick(d, kind, None, usage, within, hint) {
        Some(f) => Err(LayoutError::SplitReport {
            what,
            a: id,
            b: f.report_id,
        }),
        None => Ok(None),
    }
}

/// An optional X/Y/Z group of the Tracking Data report: `None` when absent; dropped with a
/// note when its units cannot be read (DMF's VirtualEyeGaze declares Head Direction in cm).
fn xyz(
    d: &ReportDescriptor,
    id: u8,
    within: Usage,
    what: &'static str,
    usages: [Usage; 3],
    q: Quantity,
    notes: &mut Vec<String>,
) -> Result<Option<[Located; 3]>, LayoutError> {
    let td = usage::TRACKING_DATA;
    let mut found = Vec::with_capacity(3);
    for (axis, u) in ["X", "Y", "Z"].iter().zip(usages) {
        let Some(f) = pick_in(d, ReportKind::Input, id, u, &[within], td, what)? else {
            return Ok(None);
        };
        match Located::new(f, format!("{what} {axis}"), q) {
            Ok(l) => found.push(l),
            Err(e) => {
                notes.push(format!("{what} ignored: {e}"));
                return Ok(None);
            }
        }
    }
    Ok(found.try_into().ok())
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
    /// Finds the report: the one holding a `wanted` usage inside the collection carrying
    /// `report`, else the one holding an `anchor` (usages only this report has) anywhere.
    /// Then reads every wanted usage from that report, preferring the collection.
    fn locate(
        d: &ReportDescriptor,
        report: Usage,
        anchors: &[(Usage, Quantity)],
        extra: &[(Usage, Quantity)],
        what: &'static str,
    ) -> Result<Option<FeatureLayout>, LayoutError> {
        let kind = ReportKind::Feature;
        let wanted = || anchors.iter().chain(extra);
        let id = wanted()
            .find_map(|&(u, _)| d.find(kind, u, &[report]))
            .or_else(|| anchors.iter().find_map(|&(u, _)| d.find(kind, u, &[])))
            .map(|f| f.report_id);
        let Some(report_id) = id else { return Ok(None) };
        let mut fields = Vec::new();
        for (i, &(u, q)) in wanted().enumerate() {
            let f = if i < anchors.len() {
                pick_in(d, kind, report_id, u, &[], report, what)?
            } else {
                pick(d, kind, Some(report_id), u, &[], report)
            };
            if let Some(f) = f {
                fields.push((u, Located::new(f, usage_name(u).to_string(), q)?));
            }
        }
        let len = d.report_len(kind, report_id).unwrap_or(1);
        Ok(Some(FeatureLayout {
            report_id,
            len,
            fields,
        }))
    }

    /// The located fields, in the order the driver looks for them.
    pub fn fields(&self) -> impl Iterator<Item = &Located> {
        self.fields.iter().map(|(_, l)| l)
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
    /// Optional fields present but not used, and why.
    pub notes: Vec<String>,
}

impl TrackerLayout {
    /// Locates the reports. Required: Tracking Data with Timestamp and Gaze Point,
    /// Capabilities, Status with Configuration Status, Control with Mode Request. The first
    /// thing missing is the error; [`TrackerLayout::locate_all`] names all of them.
    pub fn locate(d: &ReportDescriptor) -> Result<TrackerLayout, LayoutError> {
        Self::locate_all(d).map_err(|mut e| e.swap_remove(0))
    }

    /// Like [`TrackerLayout::locate`], with every problem found (never an empty list).
    pub fn locate_all(d: &ReportDescriptor) -> Result<TrackerLayout, Vec<LayoutError>> {
        use usage::*;
        use Quantity::*;
        let td = TRACKING_DATA;
        let input = ReportKind::Input;
        let mut errors = Vec::new();
        let mut notes = Vec::new();
        let missing = |what, usage, kind| LayoutError::Missing { what, usage, kind };

        let tracking = (|| -> Result<TrackingLayout, LayoutError> {
            let ts = pick(d, input, None, TIMESTAMP, &[], td).ok_or(missing(
                "Timestamp",
                TIMESTAMP,
                input,
            ))?;
            let timestamp = Located::new(ts, "Timestamp".into(), Time)?;
            let id = ts.report_id;
            let gaze = |u, name: &'static str| -> Result<Located, LayoutError> {
                let f = pick_in(d, input, id, u, &[GAZE_POINT], td, "Tracking Data")?
                    .ok_or(missing(name, u, input))?;
                Located::new(f, name.into(), Length)
            };
            let gaze_point = [
                gaze(POSITION_X, "Gaze Point X")?,
                gaze(POSITION_Y, "Gaze Point Y")?,
            ];
            let pos = [POSITION_X, POSITION_Y, POSITION_Z];
            let rot = [ROTATION_X, ROTATION_Y, ROTATION_Z];
            let mut group =
                |within, what, usages, q| xyz(d, id, within, what, usages, q, &mut notes);
            Ok(TrackingLayout {
                report_id: id,
                len: d.report_len(input, id).unwrap_or(1),
                left_eye: group(LEFT_EYE_POSITION, "Left Eye Position", pos, Length)?,
                right_eye: group(RIGHT_EYE_POSITION, "Right Eye Position", pos, Length)?,
                head_position: group(HEAD_POSITION, "Head Position", pos, Length)?,
                head_direction: group(HEAD_DIRECTION, "Head Direction", rot, Angle)?,
                gaze_point,
                timestamp,
            })
        })()
        .map_err(|e| errors.push(e))
        .ok();

        let feature = ReportKind::Feature;
        let mut report = |r, anchors: &[(Usage, Quantity)], extra: &[(Usage, Quantity)], what| {
            FeatureLayout::locate(d, r, anchors, extra, what)
                .map_err(|e| errors.push(e))
                .ok()
                .flatten()
        };
        let capabilities = report(
            CAPABILITIES,
            &[
                (TRACKER_QUALITY, Plain),
                (MINIMUM_TRACKING_DISTANCE, Length),
                (OPTIMUM_TRACKING_DISTANCE, Length),
                (MAXIMUM_TRACKING_DISTANCE, Length),
                (MAXIMUM_SCREEN_PLANE_WIDTH, Length),
                (MAXIMUM_SCREEN_PLANE_HEIGHT, Length),
            ],
            &[(SAMPLING_FREQUENCY, Plain)],
            "Capabilities",
        );
        let configuration = report(
            CONFIGURATION,
            &[
                (CALIBRATED_SCREEN_WIDTH, Length),
                (CALIBRATED_SCREEN_HEIGHT, Length),
            ],
            &[],
            "Configuration",
        );
        let status = report(
            STATUS,
            &[(CONFIGURATION_STATUS, Plain)],
            &[(SAMPLING_FREQUENCY, Plain)],
            "Status",
        )
        .filter(|s| s.has(CONFIGURATION_STATUS));
        let control = report(CONTROL, &[(MODE_REQUEST, Plain)], &[], "Control");
        if capabilities.is_none() {
            errors.push(missing("Capabilities report", CAPABILITIES, feature));
        }
        if status.is_none() {
            errors.push(missing(
                "Configuration Status",
                CONFIGURATION_STATUS,
                feature,
            ));
        }
        if control.is_none() {
            errors.push(missing("Mode Request", MODE_REQUEST, feature));
        }
        match (tracking, capabilities, status, control) {
            (Some(tracking), Some(capabilities), Some(status), Some(control))
                if errors.is_empty() =>
            {
                Ok(TrackerLayout {
                    tracking,
                    capabilities,
                    configuration,
                    status,
                    control,
                    notes,
                })
            }
            _ => Err(errors),
        }
    }

    /// Every field the driver reads, with the report it is in.
    pub fn fields(&self) -> Vec<&Located> {
        let t = &self.tracking;
        let mut v: Vec<&Located> = vec![&t.timestamp, &t.gaze_point[0], &t.gaze_point[1]];
        for g in [
            &t.left_eye,
            &t.right_eye,
            &t.head_position,
            &t.head_direction,
        ]
        .into_iter()
        .flatten()
        {
            v.extend(g.iter());
        }
        for f in [
            Some(&self.capabilities),
            self.configuration.as_ref(),
            Some(&self.status),
            Some(&self.control),
        ]
        .into_iter()
        .flatten()
        {
            v.extend(f.fields());
        }
        v
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
