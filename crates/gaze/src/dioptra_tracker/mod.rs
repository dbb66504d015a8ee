//! Driver for the dioptra binocular eye tracker: a vendor HID device whose input report
//! carries one dioptra-protocol `BinocularSample` (layout in [`protocol`]), at 120-1000 Hz.

pub mod protocol;

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{Clock, ClockMapper, DeviceError, GazeSample, GazeSource, LinkError};
use dioptra_transport::HidLink;
use tokio::time::Instant;

use crate::eye_hid::{protocol_error, read_descriptor};
use crate::timing::{deadline, Stamper};
use protocol::{StreamControl, CONTROL_REPORT_ID, CONTROL_REPORT_LEN, SAMPLE_REPORT_ID};

/// The tracker's supported rates.
pub const MIN_RATE_HZ: u16 = 120;
pub const MAX_RATE_HZ: u16 = 1000;

#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct DioptraTrackerConfig {
    /// Rate to request, Hz (120-1000); `None` keeps the device's.
    pub rate_hz: Option<u16>,
    /// No sample for this long means the device stopped sending; `None`: 20 sample
    /// periods, at least 100 ms.
    pub stall_timeout: Option<Duration>,
}

/// A connected, streaming dioptra tracker.
pub struct DioptraTracker<H: HidLink> {
    link: H,
    name: String,
    rate_hz: u16,
    stall: Duration,
    stamper: Stamper,
    buf: [u8; 128],
    skipped_reports: u64,
}

impl<H: HidLink> std::fmt::Debug for DioptraTracker<H> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DioptraTracker")
            .field("device", &self.name)
            .field("rate_hz", &self.rate_hz)
            .finish_non_exhaustive()
    }
}

impl<H: HidLink> DioptraTracker<H> {
    /// Checks the descriptor, sets the rate and starts the stream.
    pub async fn connect(
        mut link: H,
        cfg: DioptraTrackerConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, DeviceError> {
        let name = link.describe();
        if let Some(r) = cfg.rate_hz {
            if !(MIN_RATE_HZ..=MAX_RATE_HZ).contains(&r) {
                return Err(DeviceError::OutOfRange {
                    what: "tracker rate (Hz)",
                    requested: f64::from(r),
                    min: f64::from(MIN_RATE_HZ),
                    max: f64::from(MAX_RATE_HZ),
                });
            }
        }
        let descriptor = read_descriptor(&mut link).await?;
        protocol::check_descriptor(&descriptor).map_err(|e| protocol_error(&name, e))?;
        let start = StreamControl {
            streaming: true,
            rate_hz: cfg.rate_hz.unwrap_or(0),
            version: protocol::REPORT_VERSION,
        };
        link.send_feature_report(&start.encode()).await?;
        let mut buf = [0u8; CONTROL_REPORT_LEN];
        let n = link.get_feature_report(CONTROL_REPORT_ID, &mut buf).await?;
        let state = StreamControl::decode(&buf[..n]).map_err(|e| protocol_error(&name, e))?;
        if !state.streaming {
            return Err(DeviceError::Refused {
                code: 0,
                detail: format!("{name} did not start streaming"),
            });
        }
        if !(MIN_RATE_HZ..=MAX_RATE_HZ).contains(&state.rate_hz) {
            return Err(protocol_error(
                &name,
                format!("device reports a rate of {} Hz", state.rate_hz),
            ));
        }
        let stall = cfg
            .stall_timeout
            .unwrap_or_else(|| Duration::from_secs_f64((20.0 / f64::from(state.rate_hz)).max(0.1)));
        Ok(DioptraTracker {
            link,
            name,
            rate_hz: state.rate_hz,
            stall,
            stamper: Stamper::new(clock),
            buf: [0; 128],
            skipped_reports: 0,
        })
    }

    pub fn clock_mapper(&self) -> &ClockMapper {
        self.stamper.mapper()
    }

    /// Input reports with another id, skipped.
    pub fn skipped_reports(&self) -> u64 {
        self.skipped_reports
    }

    pub fn describe(&self) -> &str {
        &self.name
    }

    /// Stops the stream (the device keeps running).
    pub async fn stop(&mut self) -> Result<(), DeviceError> {
        let stop = StreamControl {
            streaming: false,
            rate_hz: 0,
            version: protocol::REPORT_VERSION,
        };
        Ok(self.link.send_feature_report(&stop.encode()).await?)
    }
}

impl<H: HidLink> GazeSource for DioptraTracker<H> {
    fn rate_hz(&self) -> f32 {
        f32::from(self.rate_hz)
    }

    async fn next_sample(&mut self) -> Result<GazeSample, DeviceError> {
        let deadline = deadline(self.stall);
        let timeout = || {
            DeviceError::from(LinkError::Timeout {
                ms: self.stall.as_millis() as u64,
            })
        };
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(timeout());
            }
            let n = match self.link.read_input_report(&mut self.buf, left).await {
                Err(LinkError::Timeout { .. }) => return Err(timeout()),
                r => r?,
            };
            let host_receive = self.stamper.now();
            let report = &self.buf[..n];
            if report.first() != Some(&SAMPLE_REPORT_ID) {
                self.skipped_reports += 1;
                continue;
            }
            let s = protocol::decode_sample_report(report)
                .map_err(|e| protocol_error(&self.name, e))?;
            let t = self.stamper.stamp(s.device_time_us, host_receive);
            return Ok(GazeSample {
                device_time: t.device,
                host_receive_time: t.host_receive,
                host_time: t.host,
                left: protocol::eye_ray(&s.left),
                right: protocol::eye_ray(&s.right),
            });
        }
    }
}
