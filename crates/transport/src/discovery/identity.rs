//! A serial device known by who it is, not by the tty it happened to get: a path (a tty, or a
//! stable link such as `/dev/serial/by-id/usb-Optotune_..._LD4-A-if00`), its USB serial number,
//! or both. Two units of one model share a VID:PID, so only the serial number tells them apart,
//! and after an unplug the kernel may hand the device another tty.

use std::fmt;
use std::path::{Path, PathBuf};

use dioptra_core::LinkError;

use super::sysfs::{serial_port_by_usb_serial, usb_serial_of};

/// Which serial device is meant. [`SerialIdentity::locate`] says which tty it is on now.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct SerialIdentity {
    /// Where it is expected: a tty path or a link to one.
    pub path: Option<PathBuf>,
    /// Its USB serial number (`iSerialNumber`): with it, the device is looked up wherever it
    /// is, and a different device on `path` is refused.
    pub usb_serial: Option<String>,
}

impl fmt::Display for SerialIdentity {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (&self.path, &self.usb_serial) {
            (Some(p), Some(s)) => write!(f, "{} (USB serial number {s:?})", p.display()),
            (Some(p), None) => write!(f, "{}", p.display()),
            (None, Some(s)) => write!(f, "the USB serial device with serial number {s:?}"),
            (None, None) => f.write_str("no serial device (neither a path nor a serial number)"),
        }
    }
}

impl SerialIdentity {
    /// The device at `path`, whatever it is (a `/dev/serial/by-id/` link is followed at every
    /// open, so it finds the device again on a new tty by itself).
    pub fn at(path: impl Into<PathBuf>) -> Self {
        SerialIdentity {
            path: Some(path.into()),
            usb_serial: None,
        }
    }

    /// The USB device with serial number `serial`, on whatever tty it is.
    pub fn usb_serial(serial: impl Into<String>) -> Self {
        SerialIdentity {
            path: None,
            usb_serial: Some(serial.into()),
        }
    }

    /// This identity with its USB serial number.
    pub fn with_usb_serial(mut self, serial: impl Into<String>) -> Self {
        self.usb_serial = Some(serial.into());
        self
    }

    /// The tty to open now ([`Self::locate_in`] over `/sys`). Blocks briefly on sysfs reads:
    /// from async code, run it through `tokio::task::spawn_blocking`.
    pub fn locate(&self) -> Result<PathBuf, LinkError> {
        self.locate_in(Path::new("/sys"))
    }

    /// The tty to open now, with sysfs at `sys_root`:
    /// - a path alone: the path;
    /// - a serial number alone: the one tty whose USB device has it;
    /// - both: the path when the device behind it has that serial number; else the tty that
    ///   has it, wherever it is now; else refused, naming both the serial number found on
    ///   the path (or none) and the one configured, so that another unit of the same model
    ///   that took the path is never driven in its place.
    ///
    /// Errors are [`LinkError::Unavailable`]: the device is not there now (a retry may find it).
    pub fn locate_in(&self, sys_root: &Path) -> Result<PathBuf, LinkError> {
        let unavailable = |m: String| LinkError::Unavailable(m);
        let Some(serial) = &self.usb_serial else {
            return self
                .path
                .clone()
                .ok_or_else(|| unavailable(format!("{self}: nothing to open")));
        };
        let Some(path) = &self.path else {
            return serial_port_by_usb_serial(sys_root, serial).map_err(unavailable);
        };
        // What is on the configured path now, if anything.
        let on_path = match usb_serial_of(sys_root, path) {
            Ok(found) if found.as_deref() == Some(serial.as_str()) => return Ok(path.clone()),
            Ok(found) => Some(found),
            Err(_) => None,
        };
        match serial_port_by_usb_serial(sys_root, serial) {
            Ok(tty) => {
                tracing::info!(
                    configured = %path.display(),
                    found = %tty.display(),
                    usb_serial = %serial,
                    "serial device found on another tty than configured"
                );
                Ok(tty)
            }
            Err(why) => Err(unavailable(match on_path {
                Some(found) => format!(
                    "the device at {} has {}, not the configured {serial:?}: refused, so as \
                     not to drive another device in its place ({why})",
                    path.display(),
                    match found {
                        Some(f) => format!("USB serial number {f:?}"),
                        None => "no USB serial number".into(),
                    }
                ),
                None => format!("{} is not there, and {why}", path.display()),
            })),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;
    use std::os::unix::fs::symlink;

    /// A sysfs tree with USB serial devices `(tty name, USB serial number)`, and a stand-in
    /// `/dev` with a file per tty.
    struct Rig {
        sys: tempfile::TempDir,
        dev: tempfile::TempDir,
    }

    impl Rig {
        fn new() -> Self {
            let r = Rig {
                sys: tempfile::tempdir().unwrap(),
                dev: tempfile::tempdir().unwrap(),
            };
            fs::create_dir_all(r.sys.path().join("class/tty")).unwrap();
            r
        }
        fn plug(&self, tty: &str, serial: &str) {
            let usb = self.sys.path().join("devices/usb1").join(serial);
            fs::create_dir_all(usb.join("if0")).unwrap();
            for (k, v) in [
                ("idVendor", "03eb"),
                ("idProduct", "2018"),
                ("serial", serial),
            ] {
                fs::write(usb.join(k), format!("{v}\n")).unwrap();
            }
            let class = self.sys.path().join("devices/virtual/tty").join(tty);
            fs::create_dir_all(&class).unwrap();
            symlink(usb.join("if0"), class.join("device")).unwrap();
            symlink(&class, self.sys.path().join("class/tty").join(tty)).unwrap();
            fs::write(self.dev.path().join(tty), "").unwrap();
        }
        fn unplug(&self, tty: &str) {
            fs::remove_file(self.sys.path().join("class/tty").join(tty)).unwrap();
            fs::remove_dir_all(self.sys.path().join("devices/virtual/tty").join(tty)).unwrap();
            fs::remove_file(self.dev.path().join(tty)).unwrap();
        }
        fn tty(&self, tty: &str) -> PathBuf {
            self.dev.path().join(tty)
        }
        fn locate(&self, id: &SerialIdentity) -> Result<PathBuf, LinkError> {
            id.locate_in(self.sys.path())
        }
    }

    #[test]
    fn a_serial_number_finds_the_device_on_whatever_tty_it_comes_back_on() {
        let rig = Rig::new();
        rig.plug("ttyACM0", "LD4-A");
        rig.plug("ttyACM1", "LD4-B");
        let right = SerialIdentity::usb_serial("LD4-B");
        assert_eq!(rig.locate(&right).unwrap(), PathBuf::from("/dev/ttyACM1"));
        rig.unplug("ttyACM1");
        let e = rig.locate(&right).unwrap_err();
        assert!(
            matches!(&e, LinkError::Unavailable(m) if m.contains("\"LD4-B\"")),
            "{e:?}"
        );
        assert!(e.needs_reconnect(), "a retry may find it");
        rig.plug("ttyACM3", "LD4-B");
        assert_eq!(rig.locate(&right).unwrap(), PathBuf::from("/dev/ttyACM3"));
    }

    #[test]
    fn a_configured_path_is_checked_against_the_serial_number() {
        let rig = Rig::new();
        rig.plug("ttyACM0", "LD4-A");
        rig.plug("ttyACM1", "LD4-B");
        // The right device on the path: the path.
        let right = SerialIdentity::at(rig.tty("ttyACM1")).with_usb_serial("LD4-B");
        assert_eq!(rig.locate(&right).unwrap(), rig.tty("ttyACM1"));
        // It came back on ttyACM2 and the left unit took ttyACM1: the right one is found
        // where it is now, never the left one on its old path.
        rig.unplug("ttyACM1");
        rig.unplug("ttyACM0");
        rig.plug("ttyACM1", "LD4-A");
        rig.plug("ttyACM2", "LD4-B");
        assert_eq!(rig.locate(&right).unwrap(), PathBuf::from("/dev/ttyACM2"));
        // And while it is not plugged in at all, the device on its path is refused, naming
        // both serial numbers.
        rig.unplug("ttyACM2");
        let e = rig.locate(&right).unwrap_err().to_string();
        assert!(
            e.contains("ttyACM1")
                && e.contains("\"LD4-A\"")
                && e.contains("\"LD4-B\"")
                && e.contains("refused"),
            "{e}"
        );
        // A path that is gone: says so.
        let gone = SerialIdentity::at(rig.tty("ttyACM7")).with_usb_serial("LD4-B");
        let e = rig.locate(&gone).unwrap_err().to_string();
        assert!(e.contains("ttyACM7 is not there"), "{e}");
        // A tty with no USB serial number (a pty, a UART) is not the configured device.
        fs::write(rig.tty("ttyS0"), "").unwrap();
        let uart = SerialIdentity::at(rig.tty("ttyS0")).with_usb_serial("LD4-B");
        let e = rig.locate(&uart).unwrap_err().to_string();
        assert!(e.contains("no USB serial number"), "{e}");
    }

    #[test]
    fn a_path_alone_is_opened_as_given() {
        let rig = Rig::new();
        let by_id = PathBuf::from("/dev/serial/by-id/usb-Optotune_LD4-A-if00");
        assert_eq!(rig.locate(&SerialIdentity::at(&by_id)).unwrap(), by_id);
        assert!(rig.locate(&SerialIdentity::default()).is_err());
        assert_eq!(
            SerialIdentity::at("/dev/ttyACM0")
                .with_usb_serial("X1")
                .to_string(),
            "/dev/ttyACM0 (USB serial number \"X1\")"
        );
    }
}
