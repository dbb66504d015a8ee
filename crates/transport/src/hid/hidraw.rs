//! HID devices through hidapi's pure-Rust hidraw backend (no libudev, no libusb).

use std::ffi::CString;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use dioptra_core::LinkError;
use hidapi::{HidApi, HidDevice, HidError};

use super::{descriptor_uses_report_ids, HidLink};
use crate::blocking;

/// Largest report descriptor HID allows.
const MAX_DESCRIPTOR: usize = 4096;

/// hidapi's context: it enumerates hidraw devices through sysfs.
pub(crate) fn hid_api() -> Result<HidApi, LinkError> {
    HidApi::new().map_err(|e| LinkError::Unavailable(format!("HID unavailable: {e}")))
}

/// An open hidraw device. Blocking hidapi calls run on tokio's blocking pool; reads wait in
/// short slices so a cancelled read frees the device quickly.
pub struct HidapiLink {
    device: Arc<Mutex<HidDevice>>,
    /// Whether the device's reports carry report ids (see the module's convention).
    numbered: bool,
    descriptor: Vec<u8>,
    name: String,
}

impl std::fmt::Debug for HidapiLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.name)
    }
}

fn lock(device: &Mutex<HidDevice>) -> MutexGuard<'_, HidDevice> {
    // A panic inside hidapi leaves no half-updated state of ours behind.
    device.lock().unwrap_or_else(|p| p.into_inner())
}

fn hid_error(e: HidError, what: &str, name: &str) -> LinkError {
    let errno = match &e {
        HidError::IoError { error } => error.raw_os_error(),
        _ => None,
    };
    let text = e.to_string();
    // hidapi reports most failures as text; the errno names survive in it.
    let has = |s: &str| text.contains(s);
    if matches!(
        errno,
        Some(libc::ENODEV | libc::EIO | libc::ESHUTDOWN | libc::ENXIO)
    ) || has("disconnected")
        || has("ENODEV")
        || has("ESHUTDOWN")
    {
        LinkError::Disconnected(format!("{name} was unplugged ({what}: {text})"))
    } else if errno == Some(libc::EPIPE) || has("EPIPE") {
        LinkError::Io(format!(
            "{name} refused the {what} (it stalled the request: {text})"
        ))
    } else {
        LinkError::Io(format!("{name}: {what} failed: {text}"))
    }
}

impl HidapiLink {
    /// Opens a hidraw node, e.g. `/dev/hidraw3`.
    pub fn open_path(path: &str) -> Result<Self, LinkError> {
        let api = hid_api()?;
        Self::open_path_with(&api, path)
    }

    /// Opens the first HID device with this VID:PID (and serial number, if given). On a
    /// device with several HID interfaces, prefer [`HidapiLink::open_path`] with the path
    /// `dioptra devices` lists.
    pub fn open(vid: u16, pid: u16, serial: Option<&str>) -> Result<Self, LinkError> {
        let api = hid_api()?;
        let found = api.device_list().find(|d| {
            d.vendor_id() == vid
                && d.product_id() == pid
                && serial.is_none_or(|s| d.serial_number() == Some(s))
        });
        let Some(info) = found else {
            return Err(LinkError::Unavailable(format!(
                "no HID device {vid:04x}:{pid:04x}{} connected: check the cable \
                 (`dioptra devices` lists what is connected)",
                serial.map(|s| format!(" serial {s}")).unwrap_or_default()
            )));
        };
        let path = info.path().to_string_lossy().into_owned();
        Self::open_path_with(&api, &path)
    }

    fn open_path_with(api: &HidApi, path: &str) -> Result<Self, LinkError> {
        let Ok(c_path) = CString::new(path) else {
            return Err(LinkError::Unavailable(format!(
                "HID device path {path:?} contains a NUL byte"
            )));
        };
        let device = api.open_path(&c_path).map_err(|e| open_error(path, e))?;
        let mut descriptor = vec![0u8; MAX_DESCRIPTOR];
        let n = device
            .get_report_descriptor(&mut descriptor)
            .map_err(|e| hid_error(e, "report descriptor read", path))?;
        descriptor.truncate(n);
        let numbered = descriptor_uses_report_ids(&descriptor);
        let name = match device.get_device_info() {
            Ok(info) => {
                let ids = format!("{:04x}:{:04x}", info.vendor_id(), info.product_id());
                match info.product_string().filter(|p| !p.is_empty()) {
                    Some(product) => format!("HID {path} ({ids} {product})"),
                    None => format!("HID {path} ({ids})"),
                }
            }
            Err(_) => format!("HID {path}"),
        };
        tracing::debug!(device = %name, numbered, "HID device open");
        Ok(HidapiLink {
            device: Arc::new(Mutex::new(device)),
            numbered,
            descriptor,
            name,
        })
    }

    /// Runs one blocking hidapi call on the blocking pool.
    async fn call<T, F>(&self, what: &'static str, f: F) -> Result<T, LinkError>
    where
        F: FnOnce(&HidDevice) -> Result<T, HidError> + Send + 'static,
        T: Send + 'static,
    {
        let device = self.device.clone();
        let name = self.name.clone();
        blocking::run(move || f(&lock(&device)).map_err(|e| hid_error(e, what, &name))).await
    }
}

/// Says why a hidraw node could not be opened, and what to do.
fn open_error(path: &str, e: HidError) -> LinkError {
    // hidapi folds the OS error into text; opening once more recovers its kind.
    let probe = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(path);
    match probe.err().map(|p| p.kind()) {
        Some(std::io::ErrorKind::NotFound) => LinkError::Unavailable(format!(
            "no HID device at {path}: check that it is plugged in (`dioptra devices` lists \
             what is connected)"
        )),
        Some(std::io::ErrorKind::PermissionDenied) => LinkError::Unavailable(format!(
            "permission denied on {path}: install udev/70-dioptra.rules (its KERNEL==\"hidraw*\" \
             rules) and replug the device"
        )),
        _ => LinkError::Unavailable(format!("cannot open HID device {path}: {e}")),
    }
}

impl HidLink for HidapiLink {
    async fn read_input_report(
        &mut self,
        buf: &mut [u8],
        timeout: Duration,
    ) -> Result<usize, LinkError> {
        if buf.is_empty() {
            return Ok(0);
        }
        // Without report ids hidraw gives the bare report: leave room for the 0 id byte.
        let offset = usize::from(!self.numbered);
        let len = buf.len().max(offset + 1);
        let device = self.device.clone();
        let name = self.name.clone();
        let report = blocking::read_in_slices(timeout, move |wait| {
            let mut data = vec![0u8; len];
            let ms = i32::try_from(wait.as_millis()).unwrap_or(i32::MAX);
            match lock(&device).read_timeout(&mut data[offset..], ms) {
                Ok(0) => Ok(None),
                Ok(n) => {
                    data.truncate(offset + n);
                    Ok(Some(data))
                }
                Err(e) => Err(hid_error(e, "input report read", &name)),
            }
        })
        .await?;
        let n = report.len().min(buf.len());
        buf[..n].copy_from_slice(&report[..n]);
        Ok(n)
    }

    async fn write_output_report(&mut self, report: &[u8]) -> Result<(), LinkError> {
        if report.is_empty() {
            return Err(empty_report(&self.name));
        }
        let data = report.to_vec();
        let sent = self
            .call("output report write", move |d| d.write(&data))
            .await?;
        if sent != report.len() {
            return Err(LinkError::Io(format!(
                "{}: output report write sent {sent} of {} bytes",
                self.name,
                report.len()
            )));
        }
        Ok(())
    }

    async fn get_feature_report(
        &mut self,
        report_id: u8,
        buf: &mut [u8],
    ) -> Result<usize, LinkError> {
        if buf.is_empty() {
            return Err(empty_report(&self.name));
        }
        let mut data = vec![0u8; buf.len()];
        data[0] = report_id;
        let (data, n) = self
            .call("feature report read", move |d| {
                let n = d.get_feature_report(&mut data)?;
                Ok((data, n))
            })
            .await?;
        let n = n.min(buf.len());
        buf[..n].copy_from_slice(&data[..n]);
        Ok(n)
    }

    async fn send_feature_report(&mut self, report: &[u8]) -> Result<(), LinkError> {
        if report.is_empty() {
            return Err(empty_report(&self.name));
        }
        let data = report.to_vec();
        self.call("feature report write", move |d| {
            d.send_feature_report(&data)
        })
        .await
    }

    async fn report_descriptor(&mut self) -> Result<Vec<u8>, LinkError> {
        Ok(self.descriptor.clone())
    }

    fn describe(&self) -> String {
        self.name.clone()
    }
}

pub(crate) fn empty_report(name: &str) -> LinkError {
    LinkError::Io(format!(
        "{name}: a report buffer must hold at least the report id byte"
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn opening_an_absent_node_is_unavailable_and_named() {
        match HidapiLink::open_path("/dev/hidraw_dioptra_absent") {
            Err(LinkError::Unavailable(msg)) => {
                assert!(
                    msg.contains("/dev/hidraw_dioptra_absent")
                        || msg.starts_with("HID unavailable"),
                    "{msg}"
                )
            }
            other => panic!("expected Unavailable, got {other:?}"),
        }
        match HidapiLink::open(0xffff, 0xfffe, Some("none")) {
            Err(LinkError::Unavailable(msg)) => assert!(
                msg.contains("ffff:fffe serial none") || msg.starts_with("HID unavailable"),
                "{msg}"
            ),
            other => panic!("expected Unavailable, got {other:?}"),
        }
    }

    #[test]
    fn unplug_and_stall_are_told_apart() {
        let gone = hid_error(
            HidError::HidApiError {
                message: "unexpected poll error (device disconnected)".into(),
            },
            "input report read",
            "HID /dev/hidraw0",
        );
        assert!(matches!(gone, LinkError::Disconnected(_)));
        let stall = hid_error(
            HidError::HidApiError {
                message: "ioctl (GFEATURE): EPIPE: Broken pipe".into(),
            },
            "feature report read",
            "HID /dev/hidraw0",
        );
        assert!(
            matches!(&stall, LinkError::Io(m) if m.contains("refused")),
            "{stall:?}"
        );
    }
}
