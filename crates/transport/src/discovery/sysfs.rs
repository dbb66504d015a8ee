//! Serial ports and their USB identity, read from sysfs.
//!
//! `serialport` without libudev cannot say which USB device a tty belongs to, so this reads
//! it directly: `<sys>/class/tty/<name>/device` leads into the device tree, and the nearest
//! directory above it with `idVendor` and `idProduct` is the USB device (for ttyACM that is
//! the interface's parent; for ttyUSB one level more, past the usb-serial port).

use std::fs;
use std::path::{Path, PathBuf};

use super::{FoundDevice, Interface};

/// USB serial ports under `sys_root` (normally `/sys`). Ttys that are not on USB (virtual
/// consoles, ptys, on-board UARTs) are left out: open those by path. Err is a note saying
/// why nothing could be listed.
pub fn serial_ports(sys_root: &Path) -> Result<Vec<FoundDevice>, String> {
    let class = sys_root.join("class/tty");
    let entries = fs::read_dir(&class).map_err(|e| {
        format!(
            "serial ports not listed: cannot read {} ({e}); is sysfs mounted?",
            class.display()
        )
    })?;
    // Resolve the root too, so the walk up can tell when it leaves the tree.
    let root = fs::canonicalize(sys_root).unwrap_or_else(|_| sys_root.to_path_buf());
    let mut found = Vec::new();
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        // Virtual ttys have no `device` link.
        let Ok(device) = fs::canonicalize(entry.path().join("device")) else {
            continue;
        };
        let Some(usb) = usb_device_above(&device, &root) else {
            continue;
        };
        let hex = |attr| read_attr(&usb, attr).and_then(|s| u16::from_str_radix(&s, 16).ok());
        let mut d = FoundDevice::new(
            Interface::Serial,
            // sysfs writes '/' in device names as '!'.
            format!("/dev/{}", name.replace('!', "/")),
        );
        d.vid = hex("idVendor");
        d.pid = hex("idProduct");
        d.serial = read_attr(&usb, "serial");
        d.manufacturer = read_attr(&usb, "manufacturer");
        d.product = read_attr(&usb, "product");
        found.push(d);
    }
    Ok(found)
}

/// The one USB serial port under `sys_root` with this VID:PID, for configs that name a device
/// by identity rather than by a `/dev` path that can change between boots. Err says why not:
/// nothing listed, none plugged in, or several (then the path must be given).
pub fn serial_port_by_id(sys_root: &Path, vid: u16, pid: u16) -> Result<PathBuf, String> {
    let ports = serial_ports(sys_root)?;
    let mut hits: Vec<_> = ports
        .into_iter()
        .filter(|d| d.vid == Some(vid) && d.pid == Some(pid))
        .map(|d| d.location)
        .collect();
    hits.sort();
    match hits.len() {
        0 => Err(format!(
            "no USB serial device {vid:04x}:{pid:04x} is plugged in (`dioptra devices` lists what is)"
        )),
        1 => Ok(PathBuf::from(hits.remove(0))),
        _ => Err(format!(
            "several USB serial devices are {vid:04x}:{pid:04x} ({}): give the device path instead",
            hits.join(", ")
        )),
    }
}

/// The tty of the USB serial device whose serial number (its USB `iSerialNumber`, as
/// `/dev/serial/by-id/` names and `dioptra devices` show it) is `serial`, under `sys_root`:
/// wherever it came back after an unplug. Err says why not: nothing listed, no such device
/// plugged in, or several ttys with that serial number (a device with more than one serial
/// interface: give its path).
pub fn serial_port_by_usb_serial(sys_root: &Path, serial: &str) -> Result<PathBuf, String> {
    let ports = serial_ports(sys_root)?;
    let mut hits: Vec<_> = ports
        .into_iter()
        .filter(|d| d.serial.as_deref() == Some(serial))
        .map(|d| d.location)
        .collect();
    hits.sort();
    match hits.len() {
        0 => Err(format!(
            "no USB serial device with serial number {serial:?} is plugged in (`dioptra devices` lists what is)"
        )),
        1 => Ok(PathBuf::from(hits.remove(0))),
        _ => Err(format!(
            "several serial ports belong to the USB device with serial number {serial:?} ({}): give the port's path",
            hits.join(", ")
        )),
    }
}

/// The USB serial number of the device behind the tty at `tty` (`/dev/ttyACM0`, or a link
/// to one such as `/dev/serial/by-id/usb-...-if00`), read under `sys_root`. `Ok(None)` for a
/// tty that is not on USB (a pty, an on-board UART) or whose USB device has no serial number;
/// Err when `tty` does not exist.
pub fn usb_serial_of(sys_root: &Path, tty: &Path) -> Result<Option<String>, String> {
    let real = fs::canonicalize(tty).map_err(|e| format!("{}: {e}", tty.display()))?;
    // The class entry's name: the path below /dev with '/' written '!', as sysfs does.
    let name = match real.strip_prefix("/dev") {
        Ok(rest) => rest.to_string_lossy().replace('/', "!"),
        Err(_) => match real.file_name() {
            Some(n) => n.to_string_lossy().into_owned(),
            None => return Ok(None),
        },
    };
    let Ok(device) = fs::canonicalize(sys_root.join("class/tty").join(&name).join("device")) else {
        return Ok(None);
    };
    let root = fs::canonicalize(sys_root).unwrap_or_else(|_| sys_root.to_path_buf());
    Ok(usb_device_above(&device, &root).and_then(|usb| read_attr(&usb, "serial")))
}

fn usb_device_above(device: &Path, root: &Path) -> Option<PathBuf> {
    device
        .ancestors()
        .take_while(|dir| dir.starts_with(root) && *dir != root)
        .find(|dir| dir.join("idVendor").is_file() && dir.join("idProduct").is_file())
        .map(Path::to_path_buf)
}

/// A sysfs attribute, trimmed; `None` when absent, unreadable or empty.
fn read_attr(dir: &Path, attr: &str) -> Option<String> {
    let raw = fs::read(dir.join(attr)).ok()?;
    let text = String::from_utf8_lossy(&raw).trim().to_string();
    (!text.is_empty()).then_some(text)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::symlink;

    /// Builds `<root>/devices/...` and `<root>/class/tty/<name>` the way the kernel lays
    /// them out, with relative symlinks.
    struct FakeSys {
        dir: tempfile::TempDir,
    }

    impl FakeSys {
        fn new() -> Self {
            let dir = tempfile::tempdir().unwrap();
            fs::create_dir_all(dir.path().join("class/tty")).unwrap();
            FakeSys { dir }
        }
        fn root(&self) -> &Path {
            self.dir.path()
        }
        fn usb_device(&self, path: &str, attrs: &[(&str, &str)]) {
            let d = self.root().join(path);
            fs::create_dir_all(&d).unwrap();
            for (k, v) in attrs {
                fs::write(d.join(k), format!("{v}\n")).unwrap();
            }
        }
        /// A tty class entry whose `device` link points at `device_path` (or none).
        fn tty(&self, name: &str, device_path: Option<&str>) {
            let dev = self.root().join("devices/virtual/tty").join(name);
            fs::create_dir_all(&dev).unwrap();
            if let Some(p) = device_path {
                fs::create_dir_all(self.root().join(p)).unwrap();
                symlink(self.root().join(p), dev.join("device")).unwrap();
            }
            symlink(
                format!("../../devices/virtual/tty/{name}"),
                self.root().join("class/tty").join(name),
            )
            .unwrap();
        }
    }

    #[test]
    fn usb_serial_ports_get_ids_and_strings_from_the_usb_device() {
        let sys = FakeSys::new();
        let usb1 = "devices/pci0000:00/0000:00:14.0/usb1/1-2";
        sys.usb_device(
            usb1,
            &[
                ("idVendor", "03eb"),
                ("idProduct", "2018"),
                ("serial", "LD400123"),
                ("manufacturer", "Optotune"),
                ("product", "Lens Driver 4"),
                ("bInterfaceNumber", "00"),
            ],
        );
        // CDC-ACM: the tty's device is the USB interface, directly under the USB device.
        sys.tty("ttyACM0", Some(&format!("{usb1}/1-2:1.0")));
        // USB-serial (FTDI): interface, then the usb-serial port, then the tty.
        let usb2 = "devices/pci0000:00/0000:00:14.0/usb1/1-3";
        sys.usb_device(usb2, &[("idVendor", "0403"), ("idProduct", "faf0")]);
        sys.tty("ttyUSB0", Some(&format!("{usb2}/1-3:1.0/ttyUSB0")));
        // An on-board UART and a virtual console: not USB, not listed.
        sys.tty("ttyS0", Some("devices/platform/serial8250"));
        sys.tty("tty1", None);

        let mut ports = serial_ports(sys.root()).unwrap();
        ports.sort_by(|a, b| a.location.cmp(&b.location));
        assert_eq!(ports.len(), 2, "{ports:?}");
        let acm = &ports[0];
        assert_eq!(acm.location, "/dev/ttyACM0");
        assert_eq!((acm.vid, acm.pid), (Some(0x03eb), Some(0x2018)));
        assert_eq!(acm.serial.as_deref(), Some("LD400123"));
        assert_eq!(acm.manufacturer.as_deref(), Some("Optotune"));
        assert_eq!(acm.product.as_deref(), Some("Lens Driver 4"));
        assert_eq!(acm.interface, Interface::Serial);
        let ftdi = &ports[1];
        assert_eq!(ftdi.location, "/dev/ttyUSB0");
        assert_eq!((ftdi.vid, ftdi.pid), (Some(0x0403), Some(0xfaf0)));
        assert_eq!(ftdi.serial, None);
    }

    #[test]
    fn malformed_ids_and_odd_names_do_not_break_the_listing() {
        let sys = FakeSys::new();
        let usb = "devices/usb2/2-1";
        sys.usb_device(
            usb,
            &[
                ("idVendor", "zzzz"),
                ("idProduct", "12345"),
                ("serial", "  "),
            ],
        );
        sys.tty("ttyGS!0", Some(&format!("{usb}/2-1:1.0")));
        let ports = serial_ports(sys.root()).unwrap();
        assert_eq!(ports.len(), 1);
        assert_eq!(ports[0].location, "/dev/ttyGS/0");
        assert_eq!(
            (ports[0].vid, ports[0].pid, ports[0].serial.as_deref()),
            (None, None, None)
        );
    }

    #[test]
    fn the_walk_up_stops_at_the_sysfs_root() {
        // idVendor above the root must not be picked up.
        let outer = tempfile::tempdir().unwrap();
        fs::write(outer.path().join("idVendor"), "03eb\n").unwrap();
        fs::write(outer.path().join("idProduct"), "2018\n").unwrap();
        let root = outer.path().join("sys");
        fs::create_dir_all(root.join("class/tty")).unwrap();
        fs::create_dir_all(root.join("devices/x/tty9")).unwrap();
        fs::create_dir_all(root.join("devices/virtual/tty/tty9")).unwrap();
        symlink(
            root.join("devices/x/tty9"),
            root.join("devices/virtual/tty/tty9/device"),
        )
        .unwrap();
        symlink(
            root.join("devices/virtual/tty/tty9"),
            root.join("class/tty/tty9"),
        )
        .unwrap();
        assert_eq!(serial_ports(&root).unwrap(), vec![]);
    }

    #[test]
    fn a_port_is_found_by_vid_pid_only_when_exactly_one_matches() {
        let sys = FakeSys::new();
        let usb1 = "devices/usb1/1-2";
        sys.usb_device(usb1, &[("idVendor", "03eb"), ("idProduct", "2018")]);
        sys.tty("ttyACM0", Some(&format!("{usb1}/1-2:1.0")));
        let usb2 = "devices/usb1/1-3";
        sys.usb_device(usb2, &[("idVendor", "1209"), ("idProduct", "d10a")]);
        sys.tty("ttyACM1", Some(&format!("{usb2}/1-3:1.0")));
        assert_eq!(
            serial_port_by_id(sys.root(), 0x03eb, 0x2018).unwrap(),
            PathBuf::from("/dev/ttyACM0")
        );
        let none = serial_port_by_id(sys.root(), 0x03eb, 0x2019).unwrap_err();
        assert!(none.contains("no USB serial device 03eb:2019"), "{none}");
        // A second lens driver of the same model: ambiguous, so the path is asked for.
        let usb3 = "devices/usb1/1-4";
        sys.usb_device(usb3, &[("idVendor", "03eb"), ("idProduct", "2018")]);
        sys.tty("ttyACM2", Some(&format!("{usb3}/1-4:1.0")));
        let two = serial_port_by_id(sys.root(), 0x03eb, 0x2018).unwrap_err();
        assert!(
            two.contains("/dev/ttyACM0, /dev/ttyACM2") && two.contains("device path"),
            "{two}"
        );
    }

    #[test]
    fn a_port_is_found_by_usb_serial_number_wherever_it_is_now() {
        let sys = FakeSys::new();
        // Two Lens Driver 4s: same VID:PID, told apart by serial number only.
        let (a, b) = ("devices/usb1/1-2", "devices/usb1/1-3");
        for (usb, serial) in [(a, "LD4-A"), (b, "LD4-B")] {
            sys.usb_device(
                usb,
                &[
                    ("idVendor", "03eb"),
                    ("idProduct", "2018"),
                    ("serial", serial),
                ],
            );
        }
        sys.tty("ttyACM0", Some(&format!("{a}/1-2:1.0")));
        sys.tty("ttyACM1", Some(&format!("{b}/1-3:1.0")));
        assert_eq!(
            serial_port_by_usb_serial(sys.root(), "LD4-B").unwrap(),
            PathBuf::from("/dev/ttyACM1")
        );
        // VID:PID cannot tell them apart; the serial number can.
        assert!(serial_port_by_id(sys.root(), 0x03eb, 0x2018).is_err());
        let none = serial_port_by_usb_serial(sys.root(), "LD4-C").unwrap_err();
        assert!(
            none.contains("\"LD4-C\"") && none.contains("plugged in"),
            "{none}"
        );
        // B comes back on another tty after an unplug.
        fs::remove_file(sys.root().join("class/tty/ttyACM1")).unwrap();
        sys.tty("ttyACM2", Some(&format!("{b}/1-3:1.0")));
        assert_eq!(
            serial_port_by_usb_serial(sys.root(), "LD4-B").unwrap(),
            PathBuf::from("/dev/ttyACM2")
        );
        // A composite device with two serial interfaces: ambiguous.
        sys.tty("ttyACM3", Some(&format!("{b}/1-3:1.2")));
        let two = serial_port_by_usb_serial(sys.root(), "LD4-B").unwrap_err();
        assert!(two.contains("/dev/ttyACM2, /dev/ttyACM3"), "{two}");
    }

    #[test]
    fn the_serial_number_behind_a_tty_path_or_a_link_to_it() {
        let sys = FakeSys::new();
        let usb = "devices/usb1/1-2";
        sys.usb_device(
            usb,
            &[
                ("idVendor", "03eb"),
                ("idProduct", "2018"),
                ("serial", "LD4-A"),
            ],
        );
        sys.tty("ttyACM0", Some(&format!("{usb}/1-2:1.0")));
        sys.tty("ttyS0", Some("devices/platform/serial8250"));
        // A stand-in /dev: the tty, and a by-id link to it as udev makes them.
        let dev = tempfile::tempdir().unwrap();
        fs::write(dev.path().join("ttyACM0"), "").unwrap();
        fs::write(dev.path().join("ttyS0"), "").unwrap();
        let by_id = dev.path().join("serial/by-id");
        fs::create_dir_all(&by_id).unwrap();
        let link = by_id.join("usb-Optotune_Lens_Driver_4_LD4-A-if00");
        symlink("../../ttyACM0", &link).unwrap();
        let tty = dev.path().join("ttyACM0");
        assert_eq!(
            usb_serial_of(sys.root(), &tty).unwrap().as_deref(),
            Some("LD4-A")
        );
        assert_eq!(
            usb_serial_of(sys.root(), &link).unwrap().as_deref(),
            Some("LD4-A")
        );
        // Not on USB, not a tty sysfs knows: no serial number.
        assert_eq!(
            usb_serial_of(sys.root(), &dev.path().join("ttyS0")).unwrap(),
            None
        );
        assert_eq!(usb_serial_of(sys.root(), dev.path()).unwrap(), None);
        let gone = usb_serial_of(sys.root(), &dev.path().join("ttyACM9")).unwrap_err();
        assert!(gone.contains("ttyACM9"), "{gone}");
    }

    #[test]
    fn a_missing_sysfs_is_a_note_not_a_failure() {
        let empty = tempfile::tempdir().unwrap();
        let note = serial_ports(empty.path()).unwrap_err();
        assert!(note.starts_with("serial ports not listed"), "{note}");
    }
}
