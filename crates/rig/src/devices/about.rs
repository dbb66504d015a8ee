//! Who each driver of the drivers' table says its device is ([`About`]), and which sequencers
//! can resume a session on a new link ([`Resume`]): what `dioptra lens|gaze|sync` print for
//! `info`, `temp` and `status` without knowing the driver.

use dioptra_core::{DeviceError, VarifocalLens};
use dioptra_gaze::dioptra_tracker::DioptraTracker;
use dioptra_gaze::eye_hid::HidEyeTracker;
use dioptra_gaze::pupil::PupilCapture;
use dioptra_lens::optotune::protocol::Status;
use dioptra_lens::{LensController, Optotune};
use dioptra_sync::board::SyncBoard;
use dioptra_sync::dlpc350::Dlpc350;
use dioptra_transport::{AnyByteLink, AnyHidLink};

use super::boxed::{About, BoxFuture, Facts, Resume};
use super::open::Link;

fn ready(facts: Facts) -> BoxFuture<'static, Result<Facts, DeviceError>> {
    Box::pin(async { Ok(facts) })
}

impl About for Optotune<AnyByteLink> {
    fn identity(&self) -> String {
        self.info().map_or("Optotune Lens Driver 4".into(), |i| {
            format!(
                "Optotune Lens Driver 4, serial {}, firmware type {} version {}",
                i.serial_number,
                char::from(i.firmware_type),
                i.firmware_version
            )
        })
    }

    fn about(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        Box::pin(async move {
            let temp = self.temperature_c().await?;
            let Some(i) = self.info() else {
                return Err(DeviceError::Invalid(
                    "the Lens Driver 4 is not connected".into(),
                ));
            };
            let r = self.power_range();
            Ok(vec![
                ("device", "Optotune Lens Driver 4".into()),
                (
                    "firmware",
                    format!(
                        "type {} version {}",
                        char::from(i.firmware_type),
                        i.firmware_version
                    ),
                ),
                ("serial", i.serial_number.clone()),
                ("device id", i.device_id.clone()),
                ("max current", format!("{:.2} mA", i.max_current_ma)),
                (
                    "device range",
                    format!(
                        "{:.3} .. {:.3} D (focal-power mode, over its temperature limits)",
                        i.device_range.min.0, i.device_range.max.0
                    ),
                ),
                (
                    "driving range",
                    format!("{:.3} .. {:.3} D", r.min.0, r.max.0),
                ),
                ("mode", format!("{:?}", self.mode())),
                ("temperature", format!("{temp:.2} °C")),
            ])
        })
    }

    /// Temperature and the firmware status word, its error bits marked (they stop
    /// focal-power control).
    fn condition(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        Box::pin(async move {
            let t = self.temperature_c().await?;
            let s = self.status().await?;
            Ok(vec![
                ("temperature", format!("{t:.2} °C")),
                ("status", format!("{:#010x}{}", s.0, describe_status(s))),
            ])
        })
    }
}

/// The status word's set bits in the device's words, errors marked.
pub(crate) fn describe_status(s: Status) -> String {
    let mut names: Vec<String> = s
        .errors()
        .names()
        .into_iter()
        .map(|n| format!("error: {n}"))
        .collect();
    names.extend(s.warnings().names());
    if names.is_empty() {
        String::new()
    } else {
        format!(" ({})", names.join(", "))
    }
}

impl About for LensController<AnyByteLink> {
    fn identity(&self) -> String {
        self.info().map_or("dioptra lens controller".into(), |i| {
            let v = i.firmware_version;
            format!(
                "dioptra lens controller ({:?}), serial {}, firmware {}.{}.{}",
                i.kind, i.serial, v.major, v.minor, v.patch
            )
        })
    }

    fn about(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        let mut facts = Facts::new();
        if let Some(i) = self.info() {
            let v = i.firmware_version;
            facts.push(("device", format!("dioptra lens controller ({:?})", i.kind)));
            facts.push(("serial", i.serial.to_string()));
            facts.push((
                "firmware",
                format!(
                    "{}.{}.{} (protocol {})",
                    v.major, v.minor, v.patch, i.protocol_version
                ),
            ));
            facts.push(("capabilities", format!("{:#x}", i.capabilities.0)));
        }
        if let Some(l) = self.device_limits() {
            facts.push((
                "device limits",
                format!(
                    "{:.3} .. {:.3} D, max current {:.2} mA",
                    l.min_power_d, l.max_power_d, l.max_current_ma
                ),
            ));
        }
        let r = self.power_range();
        facts.push((
            "driving range",
            format!("{:.3} .. {:.3} D", r.min.0, r.max.0),
        ));
        ready(facts)
    }

    fn condition(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        Box::pin(async move {
            let s = self.state().await?;
            Ok(vec![(
                "temperature",
                s.temperature_c
                    .map_or("not measured by this controller".into(), |t| {
                        format!("{t:.2} °C")
                    }),
            )])
        })
    }
}

impl About for DioptraTracker<AnyHidLink> {
    fn identity(&self) -> String {
        self.describe().to_string()
    }
    fn about(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        ready(vec![("device", self.describe().to_string())])
    }
}

impl About for HidEyeTracker<AnyHidLink> {
    fn identity(&self) -> String {
        self.info().device.clone()
    }
    fn about(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        let i = self.info();
        let mm = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{:.1} mm", v / 1000.0));
        let c = &i.capabilities;
        ready(vec![
            ("device", i.device.clone()),
            (
                "sampling frequency",
                i.sampling_frequency_hz
                    .map_or("unknown".into(), |f| format!("{f} Hz")),
            ),
            (
                "tracker quality",
                c.tracker_quality.map_or("-".into(), |q| q.to_string()),
            ),
            (
                "tracking distance",
                format!(
                    "min {} optimum {} max {}",
                    mm(c.min_tracking_distance_um),
                    mm(c.optimum_tracking_distance_um),
                    mm(c.max_tracking_distance_um)
                ),
            ),
            (
                "screen plane",
                format!(
                    "max {} x {}; used {:.1} x {:.1} mm",
                    mm(c.max_screen_width_um),
                    mm(c.max_screen_height_um),
                    i.screen_um.0 / 1000.0,
                    i.screen_um.1 / 1000.0
                ),
            ),
            ("modes requested", format!("{:#x}", i.modes.0)),
        ])
    }
}

impl About for PupilCapture {
    fn identity(&self) -> String {
        format!("Pupil Capture {}", self.version())
    }
    fn about(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        let o = self.clock_offset();
        ready(vec![
            (
                "device",
                format!(
                    "Pupil Capture {} (IPC publisher port {})",
                    self.version(),
                    self.sub_port()
                ),
            ),
            (
                "clock offset",
                format!(
                    "{:.6} s (Pupil minus host; sd {:.1} us over {} requests)",
                    o.mean_s,
                    o.std_s * 1e6,
                    o.samples
                ),
            ),
        ])
    }
}

impl About for SyncBoard<AnyByteLink> {
    fn identity(&self) -> String {
        match self.status().info {
            Some(info) => {
                let v = info.firmware_version;
                format!(
                    "dioptra sync board, serial {}, firmware {}.{}.{}, protocol v{}",
                    info.serial, v.major, v.minor, v.patch, info.protocol_version
                )
            }
            None => "dioptra sync board".into(),
        }
    }
    fn about(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        let synced = self.device_to_host(0).is_some();
        let loaded = self.status().schedule.is_some();
        ready(vec![
            ("device", self.identity()),
            (
                "clocks",
                if synced {
                    "synchronised"
                } else {
                    "not synchronised"
                }
                .into(),
            ),
            (
                "schedule",
                if loaded {
                    "loaded by this session"
                } else {
                    "none loaded by this session"
                }
                .into(),
            ),
        ])
    }
}

/// The sync board takes a new link and programs its schedule again (started if it was).
impl Resume for SyncBoard<AnyByteLink> {
    fn resumes(&self) -> bool {
        true
    }
    fn resume(&mut self, link: Link) -> BoxFuture<'_, Result<(), DeviceError>> {
        Box::pin(async move { self.reconnect(link.byte("sync board")?).await })
    }
}

impl About for Dlpc350<AnyHidLink> {
    fn identity(&self) -> String {
        "TI DLPC350".into()
    }
    fn about(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        Box::pin(async move {
            let v = self.version().await?;
            let s = self.status().await?;
            Ok(vec![
                (
                    "device",
                    format!(
                        "DLPC350 application {} API {} software config {} sequence config {}",
                        v.application, v.api, v.software_config, v.sequence_config
                    ),
                ),
                (
                    "state",
                    format!(
                        "hardware init {}, sequencer {}, DMD {}{}",
                        if s.hardware.init_ok() { "ok" } else { "FAILED" },
                        if s.main.sequencer_running() {
                            "running"
                        } else {
                            "stopped"
                        },
                        if s.main.dmd_parked() {
                            "parked"
                        } else {
                            "active"
                        },
                        if s.hardware.sequence_abort() || s.hardware.sequence_error() {
                            ", sequence error/abort flagged"
                        } else {
                            ""
                        }
                    ),
                ),
            ])
        })
    }
}

/// The DLPC350 is opened anew by running the command again.
impl Resume for Dlpc350<AnyHidLink> {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_words_are_described_in_the_devices_words() {
        assert_eq!(describe_status(Status(0)), "");
        let s = Status(Status::NO_TEMPERATURE_LIMITS | Status::TEMPERATURE_OUTSIDE_LIMITS);
        assert_eq!(
            describe_status(s),
            " (error: no temperature limits received, temperature outside the user's limits)"
        );
    }
}
