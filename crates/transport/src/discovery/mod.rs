//! What is plugged in, and which dioptra driver handles it.
//!
//! Each driver crate declares a table of [`KnownDevice`]s; the CLI joins them and calls
//! [`discover`]. Serial ports come from sysfs (their USB identity read from the USB device
//! above the tty), USB devices from libusb, HID devices (with usage page and usage) from
//! hidapi's hidraw backend. A backend that cannot run here (no `/dev/bus/usb`, no sysfs)
//! adds a note to the [`Discovery`] instead of failing it.
//!
//! Discovery blocks briefly (sysfs reads, USB enumeration): from async code, run it through
//! `tokio::task::spawn_blocking`.

use std::fmt;
use std::path::Path;

mod identity;
mod sysfs;

pub use identity::SerialIdentity;
pub use sysfs::{serial_port_by_id, serial_port_by_usb_serial, serial_ports, usb_serial_of};

/// How a driver talks to a device.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Interface {
    /// A tty: USB CDC-ACM (`/dev/ttyACM*`) or a USB-serial adapter (`/dev/ttyUSB*`).
    Serial,
    /// USB bulk endpoints through libusb.
    UsbBulk,
    /// A hidraw node.
    Hid,
}

impl fmt::Display for Interface {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // `pad`, so that width and alignment in format strings apply.
        f.pad(match self {
            Interface::Serial => "serial",
            Interface::UsbBulk => "USB",
            Interface::Hid => "HID",
        })
    }
}

/// One line of a driver's match table.
///
/// `None` is a wildcard. `usage` counts only together with `usage_page`. An entry must set
/// at least a vendor id, a product id or a usage page; one that sets none matches nothing
/// (it would claim every device).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct KnownDevice {
    /// The driver's name, as used in device specs (`optotune:/dev/ttyACM0`).
    pub driver: &'static str,
    /// What the device is, for people.
    pub name: &'static str,
    pub vid: Option<u16>,
    pub pid: Option<u16>,
    pub usage_page: Option<u16>,
    pub usage: Option<u16>,
    pub interface: Interface,
}

impl KnownDevice {
    /// A device identified by USB vendor and product id.
    pub const fn usb(
        driver: &'static str,
        name: &'static str,
        vid: u16,
        pid: u16,
        interface: Interface,
    ) -> Self {
        KnownDevice {
            driver,
            name,
            vid: Some(vid),
            pid: Some(pid),
            usage_page: None,
            usage: None,
            interface,
        }
    }

    /// Any HID device with a top-level collection on `usage_page` (and `usage`, if given),
    /// whoever makes it: e.g. eye trackers on usage page 0x12.
    pub const fn hid_usage(
        driver: &'static str,
        name: &'static str,
        usage_page: u16,
        usage: Option<u16>,
    ) -> Self {
        KnownDevice {
            driver,
            name,
            vid: None,
            pid: None,
            usage_page: Some(usage_page),
            usage,
            interface: Interface::Hid,
        }
    }

    /// Narrows the entry to one HID collection (e.g. one interface of a composite device).
    pub const fn with_usage(self, usage_page: u16, usage: Option<u16>) -> Self {
        KnownDevice {
            usage_page: Some(usage_page),
            usage,
            ..self
        }
    }

    /// Whether this entry describes `device`.
    pub fn matches(&self, device: &FoundDevice) -> bool {
        if self.interface != device.interface
            || (self.vid.is_none() && self.pid.is_none() && self.usage_page.is_none())
        {
            return false;
        }
        let same = |want: Option<u16>, have: Option<u16>| want.is_none_or(|w| have == Some(w));
        if !same(self.vid, device.vid) || !same(self.pid, device.pid) {
            return false;
        }
        match self.usage_page {
            None => true,
            Some(page) => device
                .usages
                .iter()
                .any(|&(p, u)| p == page && self.usage.is_none_or(|w| w == u)),
        }
    }

    /// Ranks entries that match the same device: exact ids beat usage-only entries.
    fn specificity(&self) -> u8 {
        2 * (u8::from(self.vid.is_some()) + u8::from(self.pid.is_some()))
            + u8::from(self.usage_page.is_some())
            + u8::from(self.usage.is_some())
    }
}

/// A device found on this machine.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FoundDevice {
    pub interface: Interface,
    /// Where to open it: `/dev/ttyACM0`, `/dev/hidraw2`, or `USB bus 001 device 004`.
    pub location: String,
    pub vid: Option<u16>,
    pub pid: Option<u16>,
    pub serial: Option<String>,
    pub manufacturer: Option<String>,
    pub product: Option<String>,
    /// HID only: (usage page, usage) of each top-level collection.
    pub usages: Vec<(u16, u16)>,
    /// The most specific table entry that matches, if any.
    pub known: Option<KnownDevice>,
}

impl FoundDevice {
    pub(crate) fn new(interface: Interface, location: String) -> Self {
        FoundDevice {
            interface,
            location,
            vid: None,
            pid: None,
            serial: None,
            manufacturer: None,
            product: None,
            usages: Vec::new(),
            known: None,
        }
    }
}

/// Everything [`discover`] found, and notes on what it could not look at.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Discovery {
    /// Serial ports, then USB devices, then HID devices, each sorted by location.
    pub devices: Vec<FoundDevice>,
    /// Why a kind of device could not be listed, or a detail could not be read.
    pub notes: Vec<String>,
}

impl Discovery {
    /// The devices a driver handles.
    pub fn known(&self) -> impl Iterator<Item = &FoundDevice> {
        self.devices.iter().filter(|d| d.known.is_some())
    }

    /// A printable report: the known devices, or with `all` every device found.
    /// `Display` on [`Discovery`] is `report(false)`.
    pub fn report(&self, all: bool) -> Report<'_> {
        Report {
            discovery: self,
            all,
        }
    }

    /// Sets each device's [`FoundDevice::known`] from `table`.
    fn match_table(&mut self, table: &[KnownDevice]) {
        for device in &mut self.devices {
            device.known = table
                .iter()
                .filter(|k| k.matches(device))
                // max_by_key keeps the last of equals; reverse so the first entry wins ties.
                .rev()
                .max_by_key(|k| k.specificity())
                .copied();
        }
    }

    fn add(&mut self, listed: Result<Vec<FoundDevice>, String>) {
        match listed {
            Ok(mut found) => {
                found.sort_by(|a, b| a.location.cmp(&b.location));
                self.devices.extend(found);
            }
            Err(note) => self.notes.push(note),
        }
    }
}

/// Lists serial, USB and HID devices and matches them against `table`. Never fails: what
/// cannot be listed here becomes a note.
pub fn discover(table: &[KnownDevice]) -> Discovery {
    discover_in(table, Path::new("/sys"))
}

/// [`discover`] with serial ports read from the sysfs tree at `sys_root` (USB and HID come
/// from the system through libusb and hidapi).
pub fn discover_in(table: &[KnownDevice], sys_root: &Path) -> Discovery {
    let mut d = Discovery::default();
    d.add(serial_ports(sys_root));
    let mut usb_notes = Vec::new();
    d.add(usb_devices(table, &mut usb_notes));
    d.notes.extend(usb_notes);
    d.add(hid_devices());
    d.match_table(table);
    d
}

fn usb_devices(table: &[KnownDevice], notes: &mut Vec<String>) -> Result<Vec<FoundDevice>, String> {
    let ctx = crate::usb::context().map_err(|e| e.to_string())?;
    let list = crate::usb::devices(&ctx).map_err(|e| e.to_string())?;
    let mut found = Vec::new();
    for device in list.iter() {
        let Ok(desc) = device.device_descriptor() else {
            continue;
        };
        let mut d = FoundDevice::new(
            Interface::UsbBulk,
            format!(
                "USB bus {:03} device {:03}",
                device.bus_number(),
                device.address()
            ),
        );
        d.vid = Some(desc.vendor_id());
        d.pid = Some(desc.product_id());
        // Strings need the device opened; do that only for devices a driver wants, whose
        // serial number tells several units apart.
        if table.iter().any(|k| k.matches(&d)) {
            match device.open() {
                Ok(h) => {
                    d.serial = h.read_serial_number_string_ascii(&desc).ok();
                    d.manufacturer = h.read_manufacturer_string_ascii(&desc).ok();
                    d.product = h.read_product_string_ascii(&desc).ok();
                }
                Err(e) => notes.push(
                    crate::usb::usb_error(e, "read its serial number", &d.location).to_string(),
                ),
            }
        }
        found.push(d);
    }
    Ok(found)
}

fn hid_devices() -> Result<Vec<FoundDevice>, String> {
    let api = crate::hid::hid_api().map_err(|e| e.to_string())?;
    let mut found: Vec<FoundDevice> = Vec::new();
    // hidapi lists a device once per top-level collection: fold those into one entry.
    for info in api.device_list() {
        let location = info.path().to_string_lossy().into_owned();
        let usage = (info.usage_page(), info.usage());
        let i = match found.iter().position(|d| d.location == location) {
            Some(i) => i,
            None => {
                let mut d = FoundDevice::new(Interface::Hid, location);
                d.vid = Some(info.vendor_id());
                d.pid = Some(info.product_id());
                d.serial = info
                    .serial_number()
                    .filter(|s| !s.is_empty())
                    .map(String::from);
                d.manufacturer = info
                    .manufacturer_string()
                    .filter(|s| !s.is_empty())
                    .map(String::from);
                d.product = info
                    .product_string()
                    .filter(|s| !s.is_empty())
                    .map(String::from);
                found.push(d);
                found.len() - 1
            }
        };
        // (0, 0): hidapi could not read the report descriptor.
        if usage != (0, 0) && !found[i].usages.contains(&usage) {
            found[i].usages.push(usage);
        }
    }
    Ok(found)
}

/// A [`Discovery`] formatted for people (`dioptra devices`).
pub struct Report<'a> {
    discovery: &'a Discovery,
    all: bool,
}

impl fmt::Display for Report<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let d = self.discovery;
        let known = d.known().count();
        let others = d.devices.len() - known;
        if self.all && d.devices.is_empty() {
            writeln!(f, "no serial, USB or HID devices found")?;
        } else if known == 0 && !self.all {
            writeln!(f, "no devices found that dioptra has a driver for")?;
        }
        for device in d.devices.iter().filter(|x| self.all || x.known.is_some()) {
            writeln!(f, "{}", Line(device))?;
        }
        if others > 0 && !self.all {
            let count = |i| {
                d.devices
                    .iter()
                    .filter(|x| x.known.is_none() && x.interface == i)
                    .count()
            };
            writeln!(
                f,
                "({others} other device{} without a dioptra driver: {} serial, {} USB, {} HID)",
                if others == 1 { "" } else { "s" },
                count(Interface::Serial),
                count(Interface::UsbBulk),
                count(Interface::Hid)
            )?;
        }
        for note in &d.notes {
            writeln!(f, "note: {note}")?;
        }
        Ok(())
    }
}

impl fmt::Display for Discovery {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.report(false).fmt(f)
    }
}

/// One device on one line: driver, kind, location, ids, then what is known about it.
struct Line<'a>(&'a FoundDevice);

impl fmt::Display for Line<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let d = self.0;
        let driver = d.known.map_or("-", |k| k.driver);
        write!(f, "{driver:<12} {:<6} {}", d.interface, d.location)?;
        if let (Some(v), Some(p)) = (d.vid, d.pid) {
            write!(f, "  {v:04x}:{p:04x}")?;
        }
        if let Some(k) = d.known {
            write!(f, "  {}", k.name)?;
        }
        let product = [d.manufacturer.as_deref(), d.product.as_deref()]
            .into_iter()
            .flatten()
            .collect::<Vec<_>>()
            .join(" ");
        if !product.is_empty() {
            write!(f, "  \"{product}\"")?;
        }
        // The number a rig config's `serial = "..."` takes; a device a driver handles without
        // one can be told from another of its model only by where it is plugged.
        match (&d.serial, d.known) {
            (Some(s), _) => write!(f, "  serial {s}")?,
            (None, Some(_)) => write!(f, "  no serial number")?,
            (None, None) => {}
        }
        for (page, usage) in &d.usages {
            write!(f, "  usage {page:04x}:{usage:04x}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const OPTOTUNE: KnownDevice = KnownDevice::usb(
        "optotune",
        "Optotune Lens Driver 4",
        0x03eb,
        0x2018,
        Interface::Serial,
    );
    const EYE: KnownDevice =
        KnownDevice::hid_usage("gaze-hid", "HID eye tracker", 0x12, Some(0x01));
    const DIOPTRA_GAZE: KnownDevice = KnownDevice::usb(
        "dioptra-gaze",
        "dioptra binocular tracker",
        0x1209,
        0x0d10,
        Interface::Hid,
    )
    .with_usage(0x12, Some(0x01));
    const DLP: KnownDevice = KnownDevice::usb(
        "dlpc350",
        "TI DLP LightCrafter 4500",
        0x0451,
        0x6401,
        Interface::Hid,
    );

    fn dev(
        interface: Interface,
        location: &str,
        vid: u16,
        pid: u16,
        usages: &[(u16, u16)],
    ) -> FoundDevice {
        let mut d = FoundDevice::new(interface, location.into());
        d.vid = Some(vid);
        d.pid = Some(pid);
        d.usages = usages.to_vec();
        d
    }

    #[test]
    fn ids_and_interface_must_agree() {
        let acm = dev(Interface::Serial, "/dev/ttyACM0", 0x03eb, 0x2018, &[]);
        assert!(OPTOTUNE.matches(&acm));
        // Same ids seen as a raw USB device: not the serial driver's.
        assert!(!OPTOTUNE.matches(&dev(
            Interface::UsbBulk,
            "USB bus 001 device 002",
            0x03eb,
            0x2018,
            &[]
        )));
        assert!(!OPTOTUNE.matches(&dev(Interface::Serial, "/dev/ttyACM1", 0x03eb, 0x2019, &[])));
        let mut no_ids = acm.clone();
        no_ids.vid = None;
        assert!(!OPTOTUNE.matches(&no_ids));
    }

    #[test]
    fn usage_page_entries_match_any_vendor_and_usage_needs_its_page() {
        let tracker = dev(
            Interface::Hid,
            "/dev/hidraw1",
            0x2222,
            0x3333,
            &[(0x01, 0x06), (0x12, 0x01)],
        );
        assert!(EYE.matches(&tracker));
        let head_tracker = dev(
            Interface::Hid,
            "/dev/hidraw2",
            0x2222,
            0x3334,
            &[(0x12, 0x02)],
        );
        assert!(!EYE.matches(&head_tracker));
        assert!(KnownDevice::hid_usage("x", "any 0x12", 0x12, None).matches(&head_tracker));
        // A keyboard that happens to have usage 0x01 on another page.
        let keyboard = dev(
            Interface::Hid,
            "/dev/hidraw3",
            0x046d,
            0xc31c,
            &[(0x01, 0x01)],
        );
        assert!(!EYE.matches(&keyboard));
    }

    #[test]
    fn an_all_wildcard_entry_matches_nothing() {
        let mut everything = EYE;
        everything.usage_page = None;
        assert!(!everything.matches(&dev(Interface::Hid, "/dev/hidraw0", 1, 2, &[(0x12, 0x01)])));
    }

    #[test]
    fn the_most_specific_entry_wins_and_ties_go_to_the_first() {
        let mut d = Discovery {
            devices: vec![
                dev(
                    Interface::Hid,
                    "/dev/hidraw0",
                    0x1209,
                    0x0d10,
                    &[(0x12, 0x01)],
                ),
                dev(
                    Interface::Hid,
                    "/dev/hidraw1",
                    0x5555,
                    0x0001,
                    &[(0x12, 0x01)],
                ),
            ],
            notes: vec![],
        };
        let twin = KnownDevice {
            driver: "twin",
            ..EYE
        };
        d.match_table(&[EYE, twin, DIOPTRA_GAZE, DLP]);
        assert_eq!(d.devices[0].known.map(|k| k.driver), Some("dioptra-gaze"));
        assert_eq!(d.devices[1].known.map(|k| k.driver), Some("gaze-hid"));
    }

    #[test]
    fn report_lists_known_devices_counts_others_and_shows_notes() {
        let mut acm = dev(Interface::Serial, "/dev/ttyACM0", 0x03eb, 0x2018, &[]);
        acm.serial = Some("LD400123".into());
        acm.product = Some("Lens Driver".into());
        let mut d = Discovery {
            devices: vec![
                acm,
                dev(Interface::Serial, "/dev/ttyACM1", 0x03eb, 0x2018, &[]),
                dev(Interface::Hid, "/dev/hidraw0", 0x046d, 0xc31c, &[(1, 6)]),
            ],
            notes: vec!["USB unavailable: libusb could not start".into()],
        };
        d.match_table(&[OPTOTUNE, EYE]);
        let text = d.to_string();
        assert_eq!(
            text,
            "optotune     serial /dev/ttyACM0  03eb:2018  Optotune Lens Driver 4  \"Lens Driver\"  serial LD400123\n\
             optotune     serial /dev/ttyACM1  03eb:2018  Optotune Lens Driver 4  no serial number\n\
             (1 other device without a dioptra driver: 0 serial, 0 USB, 1 HID)\n\
             note: USB unavailable: libusb could not start\n"
        );
        let all = d.report(true).to_string();
        assert!(
            all.contains("-            HID    /dev/hidraw0  046d:c31c  usage 0001:0006"),
            "{all}"
        );
        assert!(!all.contains("other device"), "{all}");
    }

    #[test]
    fn empty_discovery_says_so() {
        let d = Discovery::default();
        assert_eq!(
            d.to_string(),
            "no devices found that dioptra has a driver for\n"
        );
        assert_eq!(
            d.report(true).to_string(),
            "no serial, USB or HID devices found\n"
        );
    }

    /// Whatever this machine has (here: no /dev/bus/usb, maybe no hidraw), discovery
    /// finishes and explains what it could not see.
    #[test]
    fn discovery_on_this_machine_does_not_panic() {
        let d = discover(&[OPTOTUNE, EYE, DLP]);
        let text = d.to_string();
        assert!(!text.is_empty());
        if !Path::new("/dev/bus/usb").exists() {
            assert!(
                d.notes.iter().any(|n| n.starts_with("USB unavailable: ")),
                "{text}"
            );
        }
    }
}
