//! Driver for HID "Eye and Head Trackers" (usage page 0x12, HUTRR74) over any [`HidLink`].
//!
//! On connect: read and parse the report descriptor, locate the reports
//! ([`protocol::TrackerLayout`]), read Capabilities and Configuration, request modes through
//! Control, and poll Status until the tracker is ready. Then every Tracking Data input report
//! becomes a [`TrackingSample`] (page units) and, through [`GazeSource`], a [`GazeSample`].
//!
//! # From the page's data to eye rays
//! The page gives a gaze point on the screen plane (µm from its top-left corner, y down)
//! and eye positions (µm, same origin, z the distance in front of the screen). We express
//! both in dioptra's head-frame convention with the origin at the screen centre: +x right,
//! +y up, +z from the eyes towards the screen, in mm. Each eye's ray runs from its position
//! to the gaze point, so vergence is at the screen plane: a page 0x12 tracker reports no
//! depth of its own. Without eye positions, eyes sit at ±32 mm at the optimum tracking
//! distance. The screen size comes from Configuration (calibrated) or else Capabilities
//! (maximum); with neither, the origin stays at the top-left corner. The page has no validity flag; a tracker reports all-zero values for what it
//! does not see, so those are read as invalid.

pub mod protocol;

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{Clock, ClockMapper, DeviceError, EyeRay, GazeSample, GazeSource, LinkError};
use dioptra_transport::HidLink;
use tokio::time::Instant;

use crate::hid_descriptor::{self, ReportDescriptor};
use crate::timing::{deadline, Stamper};
use protocol::{
    Capabilities, ConfigStatus, Configuration, ModeRequest, ReportError, TrackerLayout,
    TrackingData,
};

/// How the driver runs a page 0x12 tracker.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HidTrackerConfig {
    pub modes: ModeRequest,
    /// How long the tracker may stay "configuring" after the mode request.
    pub ready_timeout: Duration,
    pub status_poll_interval: Duration,
    /// No input report for this long means the device stopped sending; `None`: 20 sample
    /// periods, at least 100 ms.
    pub stall_timeout: Option<Duration>,
    /// Sample rate to assume when the device reports none, Hz.
    pub fallback_rate_hz: f32,
}

impl Default for HidTrackerConfig {
    fn default() -> Self {
        HidTrackerConfig {
            modes: ModeRequest::GAZE_POINT.with(ModeRequest::EYE_POSITION),
            ready_timeout: Duration::from_secs(3),
            status_poll_interval: Duration::from_millis(20),
            stall_timeout: None,
            fallback_rate_hz: 60.0,
        }
    }
}

/// What the tracker said about itself at connect.
#[derive(Debug, Clone, PartialEq)]
pub struct HidTrackerInfo {
    pub device: String,
    pub capabilities: Capabilities,
    pub configuration: Option<Configuration>,
    pub sampling_frequency_hz: Option<f64>,
    pub modes: ModeRequest,
    /// Screen plane used to centre coordinates, µm (calibrated, else the maximum).
    pub screen_um: (f64, f64),
}

/// One Tracking Data report with its times.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackingSample {
    pub data: TrackingData,
    pub host_receive_time: dioptra_core::Timestamp,
    pub host_time: dioptra_core::Timestamp,
}

/// A connected page 0x12 eye tracker.
pub struct HidEyeTracker<H: HidLink> {
    link: H,
    layout: TrackerLayout,
    info: HidTrackerInfo,
    cfg: HidTrackerConfig,
    stamper: Stamper,
    buf: Vec<u8>,
    skipped_reports: u64,
}

impl<H: HidLink> std::fmt::Debug for HidEyeTracker<H> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HidEyeTracker")
            .field("info", &self.info)
            .finish_non_exhaustive()
    }
}

pub(crate) fn protocol_error(link: &str, e: impl std::fmt::Display) -> DeviceError {
    DeviceError::Protocol(format!("{link}: {e}"))
}

/// Reads and parses the descriptor of `link`.
pub(crate) async fn read_descriptor<H: HidLink>(
    link: &mut H,
) -> Result<ReportDescriptor, DeviceError> {
    let bytes = link.report_descriptor().await?;
    hid_descriptor::parse(&bytes).map_err(|e| protocol_error(&link.describe(), e))
}

impl<H: HidLink> HidEyeTracker<H> {
    pub async fn connect(
        mut link: H,
        cfg: HidTrackerConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, DeviceError> {
        let name = link.describe();
        let descriptor = read_descriptor(&mut link).await?;
        let layout = TrackerLayout::locate(&descriptor).map_err(|e| protocol_error(&name, e))?;
        for note in &layout.notes {
            tracing::warn!("{name}: {note}");
        }
        let perr = |e: ReportError| protocol_error(&name, e);

        let mut buf = vec![0u8; layout.capabilities.len];
        let n = link
            .get_feature_report(layout.capabilities.report_id, &mut buf)
            .await?;
        let capabilities = layout.parse_capabilities(&buf[..n]).map_err(perr)?;
        // Configuration is optional: a tracker that stalls its read is still usable.
        let configuration = match &layout.configuration {
            Some(c) => {
                let mut buf = vec![0u8; c.len];
                match link.get_feature_report(c.report_id, &mut buf).await {
                    Ok(n) => layout.parse_configuration(&buf[..n]).map_err(perr)?,
                    Err(LinkError::Io(e)) => {
                        tracing::warn!(
                            "{name}: Configuration report unreadable ({e}); using Capabilities"
                        );
                        None
                    }
                    Err(e) => return Err(e.into()),
                }
            }
            None => None,
        };
        link.send_feature_report(&layout.control_report(cfg.modes))
            .await?;

        let deadline = deadline(cfg.ready_timeout);
        let mut buf = vec![0u8; layout.status.len];
        let status = loop {
            let n = link
                .get_feature_report(layout.status.report_id, &mut buf)
                .await?;
            let status = layout.parse_status(&buf[..n]).map_err(perr)?;
            match status.config_status {
                ConfigStatus::Ready => break status,
                ConfigStatus::Configuring if Instant::now() < deadline => {
                    tokio::time::sleep(cfg.status_poll_interval).await;
                }
                s => {
                    let detail = match s {
                        ConfigStatus::Configuring => format!(
                            "{name} was still configuring after {} ms",
                            cfg.ready_timeout.as_millis()
                        ),
                        ConfigStatus::ScreenSetupNeeded => {
                            format!("{name} needs its screen set up first")
                        }
                        ConfigStatus::UserCalibrationNeeded => {
                            format!("{name} needs a user calibration first")
                        }
                        _ => format!("{name} reported an unknown configuration status"),
                    };
                    return Err(DeviceError::Refused {
                        code: u16::from(s.code()),
                        detail,
                    });
                }
            }
        };
        let screen_um = (
            configuration
                .and_then(|c| c.calibrated_screen_width_um)
                .or(capabilities.max_screen_width_um)
                .unwrap_or(0.0),
            configuration
                .and_then(|c| c.calibrated_screen_height_um)
                .or(capabilities.max_screen_height_um)
                .unwrap_or(0.0),
        );
        let info = HidTrackerInfo {
            device: name,
            capabilities,
            configuration,
            sampling_frequency_hz: status
                .sampling_frequency_hz
                .or(capabilities.sampling_frequency_hz)
                .filter(|f| *f > 0.0),
            modes: cfg.modes,
            screen_um,
        };
        let buf = vec![0u8; layout.tracking.len.max(64)];
        Ok(HidEyeTracker {
            link,
            layout,
            info,
            cfg,
            stamper: Stamper::new(clock),
            buf,
            skipped_reports: 0,
        })
    }

    pub fn info(&self) -> &HidTrackerInfo {
        &self.info
    }

    pub fn layout(&self) -> &TrackerLayout {
        &self.layout
    }

    pub fn clock_mapper(&self) -> &ClockMapper {
        self.stamper.mapper()
    }

    /// Input reports that were not Tracking Data.
    pub fn skipped_reports(&self) -> u64 {
        self.skipped_reports
    }

    fn stall_timeout(&self) -> Duration {
        self.cfg.stall_timeout.unwrap_or_else(|| {
            let period = 1.0 / f64::from(self.rate_hz()).max(1.0);
            Duration::from_secs_f64((20.0 * period).max(0.1))
        })
    }

    /// The next Tracking Data report. Other input reports are skipped; none within the
    /// stall timeout is [`LinkError::Timeout`].
    pub async fn next_tracking(&mut self) -> Result<TrackingSample, DeviceError> {
        let timeout = self.stall_timeout();
        let deadline = deadline(timeout);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(LinkError::Timeout {
                    ms: timeout.as_millis() as u64,
                }
                .into());
            }
            let n = match self.link.read_input_report(&mut self.buf, left).await {
                Err(LinkError::Timeout { .. }) => {
                    return Err(LinkError::Timeout {
                        ms: timeout.as_millis() as u64,
                    }
                    .into())
                }
                r => r?,
            };
            let host_receive = self.stamper.now();
            let report = &self.buf[..n];
            if report.first() != Some(&self.layout.tracking.report_id) {
                self.skipped_reports += 1;
                continue;
            }
            let data = self
                .layout
                .tracking
                .parse(report)
                .map_err(|e| protocol_error(&self.info.device, e))?;
            let stamps = self.stamper.stamp(data.timestamp_us, host_receive);
            return Ok(TrackingSample {
                data,
                host_receive_time: stamps.host_receive,
                host_time: stamps.host,
            });
        }
    }

    /// Rays from the eye positions to the gaze point, head-frame convention (see module docs).
    pub fn to_gaze_sample(&self, s: &TrackingSample) -> GazeSample {
        let (w, h) = self.info.screen_um;
        let to_mm = |p: [f64; 3]| {
            [
                (p[0] - w / 2.0) / 1000.0,
                (h / 2.0 - p[1]) / 1000.0,
                -p[2] / 1000.0,
            ]
        };
        let eye_z = self
            .info
            .capabilities
            .optimum_tracking_distance_um
            .unwrap_or(600_000.0);
        let gaze = s.data.gaze_point_um.map(|g| to_mm([g[0], g[1], 0.0]));
        let ray = |pos: Option<[f64; 3]>, nominal_x_mm: f64, have_layout: bool| {
            let origin = match (pos, have_layout) {
                (Some(p), _) if p[2] > 0.0 => Some(to_mm(p)),
                (_, true) => None,
                (_, false) => Some([nominal_x_mm, 0.0, -eye_z / 1000.0]),
            };
            let (Some(o), Some(g)) = (origin, gaze) else {
                return EyeRay {
                    pupil_mm: f32::NAN,
                    ..EyeRay::default()
                };
            };
            let d = [g[0] - o[0], g[1] - o[1], g[2] - o[2]];
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let valid = n.is_finite() && n > 1e-6;
            let n = if valid { n } else { 1.0 };
            EyeRay {
                origin_mm: [o[0] as f32, o[1] as f32, o[2] as f32],
                direction: [(d[0] / n) as f32, (d[1] / n) as f32, (d[2] / n) as f32],
                pupil_mm: f32::NAN,
                valid,
            }
        };
        GazeSample {
            device_time: dioptra_core::Timestamp::from_micros(s.data.timestamp_us),
            host_receive_time: s.host_receive_time,
            host_time: s.host_time,
            left: ray(
                s.data.left_eye_um,
                -32.0,
                self.layout.tracking.left_eye.is_some(),
            ),
            right: ray(
                s.data.right_eye_um,
                32.0,
                self.layout.tracking.right_eye.is_some(),
            ),
        }
    }
}

impl<H: HidLink> GazeSource for HidEyeTracker<H> {
    fn rate_hz(&self) -> f32 {
        self.info
            .sampling_frequency_hz
            .map_or(self.cfg.fallback_rate_hz, |f| f as f32)
    }

    async fn next_sample(&mut self) -> Result<GazeSample, DeviceError> {
        let s = self.next_tracking().await?;
        Ok(self.to_gaze_sample(&s))
    }
}
