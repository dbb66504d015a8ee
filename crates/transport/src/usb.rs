//! USB bulk endpoints as a [`ByteLink`], through libusb (rusb).
//!
//! Always an explicit [`rusb::Context`]: rusb's global context panics where libusb cannot
//! start (no `/dev/bus/usb`, as in many containers), while `Context::new` returns an error
//! that becomes [`LinkError::Unavailable`] ("USB unavailable: ...").
//!
//! libusb's synchronous calls run on tokio's blocking pool. Reads wait in short slices, so
//! a cancelled read never holds the device for long; data a slice already received is kept.

use std::fmt;
use std::sync::Arc;
use std::time::Duration;

use dioptra_core::LinkError;
use rusb::{Context, DeviceHandle, Direction, TransferType, UsbContext};

use crate::{blocking, ByteLink};

/// Which USB device and interface to open.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UsbSelector {
    pub vid: u16,
    pub pid: u16,
    /// Only the device with this serial-number string.
    pub serial: Option<String>,
    /// This interface number; by default the first interface with a bulk IN and a bulk OUT
    /// endpoint.
    pub interface: Option<u8>,
}

impl UsbSelector {
    pub fn new(vid: u16, pid: u16) -> Self {
        UsbSelector {
            vid,
            pid,
            serial: None,
            interface: None,
        }
    }

    pub fn serial(mut self, serial: impl Into<String>) -> Self {
        self.serial = Some(serial.into());
        self
    }

    pub fn interface(mut self, number: u8) -> Self {
        self.interface = Some(number);
        self
    }
}

impl fmt::Display for UsbSelector {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "USB device {:04x}:{:04x}", self.vid, self.pid)?;
        if let Some(s) = &self.serial {
            write!(f, " serial {s}")?;
        }
        if let Some(i) = self.interface {
            write!(f, " interface {i}")?;
        }
        Ok(())
    }
}

/// Starts libusb. Fails (never panics) where USB is not accessible.
pub(crate) fn context() -> Result<Context, LinkError> {
    Context::new().map_err(|e| {
        LinkError::Unavailable(format!(
            "USB unavailable: libusb could not start ({e}); check that /dev/bus/usb exists \
             (in a container, pass the USB devices through)"
        ))
    })
}

/// Lists the devices, or says why USB cannot be used here.
pub(crate) fn devices(ctx: &Context) -> Result<rusb::DeviceList<Context>, LinkError> {
    ctx.devices().map_err(|e| {
        LinkError::Unavailable(format!("USB unavailable: cannot list USB devices: {e}"))
    })
}

/// Maps a libusb error during `what` on `device` to a [`LinkError`] that says what to do.
pub(crate) fn usb_error(e: rusb::Error, what: &str, device: &str) -> LinkError {
    match e {
        rusb::Error::NoDevice => {
            LinkError::Disconnected(format!("{device} was unplugged ({what})"))
        }
        rusb::Error::Timeout => LinkError::Timeout { ms: 0 },
        rusb::Error::Access => LinkError::Unavailable(format!(
            "permission denied on {device} ({what}): install udev/70-dioptra.rules \
             (SUBSYSTEM==\"usb\" rules) and replug the device"
        )),
        rusb::Error::Busy => LinkError::Unavailable(format!(
            "{device} is busy ({what}): another program or kernel driver has claimed the \
             interface; close that program"
        )),
        rusb::Error::Pipe => LinkError::Io(format!(
            "{device}: endpoint stalled ({what}); the device rejected the transfer"
        )),
        other => LinkError::Io(format!("{device}: {what} failed: {other}")),
    }
}

/// The device's bulk endpoint pair, as chosen at open.
#[derive(Debug, Clone, Copy)]
struct Endpoints {
    interface: u8,
    alt_setting: u8,
    ep_in: u8,
    ep_out: u8,
    max_packet_in: u16,
}

/// A claimed interface with a bulk IN and a bulk OUT endpoint. The interface is released
/// when the link is dropped.
pub struct UsbBulkLink {
    handle: Arc<DeviceHandle<Context>>,
    ep: Endpoints,
    /// Bytes of the last transfer not yet handed to the caller. Transfers are whole packets
    /// (a smaller buffer would overflow), often larger than the caller's read.
    pending: Vec<u8>,
    pending_pos: usize,
    write_timeout: Duration,
    name: String,
}

impl fmt::Debug for UsbBulkLink {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.name)
    }
}

/// How long a write may wait for the device to take the data, unless changed with
/// [`UsbBulkLink::set_write_timeout`].
pub const DEFAULT_WRITE_TIMEOUT: Duration = Duration::from_secs(1);

impl UsbBulkLink {
    /// Finds, opens and claims the device. Blocks for the enumeration (milliseconds); from a
    /// latency-sensitive task, call it through `tokio::task::spawn_blocking`.
    pub fn open(sel: &UsbSelector) -> Result<Self, LinkError> {
        let ctx = context()?;
        let list = devices(&ctx)?;
        let mut refusals = Vec::new();
        let mut serials_seen = Vec::new();
        for device in list.iter() {
            let Ok(desc) = device.device_descriptor() else {
                continue;
            };
            if desc.vendor_id() != sel.vid || desc.product_id() != sel.pid {
                continue;
            }
            let here = format!(
                "{sel} on bus {} address {}",
                device.bus_number(),
                device.address()
            );
            let handle = match device.open() {
                Ok(h) => h,
                Err(e) => {
                    refusals.push(usb_error(e, "open", &here));
                    continue;
                }
            };
            if let Some(want) = &sel.serial {
                match handle.read_serial_number_string_ascii(&desc) {
                    Ok(s) if s == *want => {}
                    Ok(s) => {
                        serials_seen.push(s);
                        continue;
                    }
                    Err(e) => {
                        refusals.push(usb_error(e, "read serial number", &here));
                        continue;
                    }
                }
            }
            let config = device
                .active_config_descriptor()
                .map_err(|e| usb_error(e, "read configuration", &here))?;
            let ep = find_bulk_pair(&config, sel.interface).ok_or_else(|| {
                LinkError::Unavailable(format!(
                    "{here} has no interface{} with a bulk IN and a bulk OUT endpoint; \
                     is this the right device?",
                    sel.interface
                        .map(|i| format!(" numbered {i}"))
                        .unwrap_or_default()
                ))
            })?;
            // Not every platform can detach kernel drivers; claiming reports the real
            // problem if one is attached.
            let _ = handle.set_auto_detach_kernel_driver(true);
            handle
                .claim_interface(ep.interface)
                .map_err(|e| usb_error(e, "claim interface", &here))?;
            if ep.alt_setting != 0 {
                handle
                    .set_alternate_setting(ep.interface, ep.alt_setting)
                    .map_err(|e| usb_error(e, "select alternate setting", &here))?;
            }
            tracing::debug!(device = %here, ?ep, "USB bulk link open");
            return Ok(UsbBulkLink {
                handle: Arc::new(handle),
                ep,
                pending: Vec::new(),
                pending_pos: 0,
                write_timeout: DEFAULT_WRITE_TIMEOUT,
                name: here,
            });
        }
        if let Some(e) = refusals.into_iter().next() {
            return Err(e);
        }
        if !serials_seen.is_empty() {
            return Err(LinkError::Unavailable(format!(
                "no {sel} connected (found serial numbers: {})",
                serials_seen.join(", ")
            )));
        }
        Err(LinkError::Unavailable(format!(
            "no {sel} connected: check the cable and power (`dioptra devices` lists what is \
             connected)"
        )))
    }

    /// How long a write may wait for the device to accept the data.
    pub fn set_write_timeout(&mut self, timeout: Duration) {
        self.write_timeout = timeout;
    }

    /// Bytes per read transfer: whole packets, several at a time.
    fn transfer_len(&self) -> usize {
        usize::from(self.ep.max_packet_in.max(8)) * 8
    }

    fn take_pending(&mut self, buf: &mut [u8]) -> usize {
        let avail = &self.pending[self.pending_pos..];
        let n = avail.len().min(buf.len());
        buf[..n].copy_from_slice(&avail[..n]);
        self.pending_pos += n;
        n
    }
}

/// The first interface setting (or the one numbered `want`) with bulk IN and OUT endpoints.
fn find_bulk_pair(config: &rusb::ConfigDescriptor, want: Option<u8>) -> Option<Endpoints> {
    for interface in config.interfaces() {
        for setting in interface.descriptors() {
            if want.is_some_and(|w| w != setting.interface_number()) {
                continue;
            }
            let bulk = |dir| {
                setting
                    .endpoint_descriptors()
                    .find(|e| e.transfer_type() == TransferType::Bulk && e.direction() == dir)
            };
            if let (Some(i), Some(o)) = (bulk(Direction::In), bulk(Direction::Out)) {
                return Some(Endpoints {
                    interface: setting.interface_number(),
                    alt_setting: setting.setting_number(),
                    ep_in: i.address(),
                    ep_out: o.address(),
                    max_packet_in: i.max_packet_size(),
                });
            }
        }
    }
    None
}

/// libusb treats a zero timeout as "wait forever".
fn usb_wait(d: Duration) -> Duration {
    d.max(Duration::from_millis(1))
}

impl ByteLink for UsbBulkLink {
    async fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        let handle = self.handle.clone();
        let ep = self.ep.ep_out;
        let timeout = usb_wait(self.write_timeout);
        let name = self.name.clone();
        let data = bytes.to_vec();
        blocking::run(move || {
            let mut sent = 0;
            while sent < data.len() {
                match handle.write_bulk(ep, &data[sent..], timeout) {
                    Ok(n) => sent += n,
                    Err(rusb::Error::Timeout) => return Err(crate::timeout_error(timeout)),
                    Err(e) => return Err(usb_error(e, "bulk write", &name)),
                }
            }
            Ok(())
        })
        .await
    }

    async fn read(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        if buf.is_empty() {
            return Ok(0);
        }
        if self.pending_pos < self.pending.len() {
            return Ok(self.take_pending(buf));
        }
        let handle = self.handle.clone();
        let ep = self.ep.ep_in;
        let len = self.transfer_len();
        let name = self.name.clone();
        let data = blocking::read_in_slices(timeout, move |wait| {
            let mut data = vec![0u8; len];
            match handle.read_bulk(ep, &mut data, usb_wait(wait)) {
                // A zero-length packet carries nothing; keep waiting.
                Ok(0) | Err(rusb::Error::Timeout) => Ok(None),
                Ok(n) => {
                    data.truncate(n);
                    Ok(Some(data))
                }
                Err(e) => Err(usb_error(e, "bulk read", &name)),
            }
        })
        .await?;
        self.pending = data;
        self.pending_pos = 0;
        Ok(self.take_pending(buf))
    }

    async fn discard_input(&mut self) -> Result<usize, LinkError> {
        let mut dropped = self.pending.len() - self.pending_pos;
        self.pending.clear();
        self.pending_pos = 0;
        // USB has no host-side buffer: what "already arrived" is what the device has queued.
        // Take it with the shortest waits; bounded so a streaming device cannot stall us.
        let handle = self.handle.clone();
        let ep = self.ep.ep_in;
        let len = self.transfer_len();
        let name = self.name.clone();
        dropped += blocking::run(move || {
            let mut data = vec![0u8; len];
            let mut total = 0;
            for _ in 0..64 {
                match handle.read_bulk(ep, &mut data, usb_wait(Duration::ZERO)) {
                    Ok(0) | Err(rusb::Error::Timeout) => break,
                    Ok(n) => total += n,
                    Err(e) => return Err(usb_error(e, "bulk read", &name)),
                }
            }
            Ok(total)
        })
        .await?;
        Ok(dropped)
    }

    fn describe(&self) -> String {
        self.name.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// This machine has no /dev/bus/usb: opening must fail cleanly, not panic.
    #[test]
    fn without_usb_access_open_is_unavailable() {
        if std::path::Path::new("/dev/bus/usb").exists() {
            eprintln!("skipped: this machine has /dev/bus/usb");
            return;
        }
        match UsbBulkLink::open(&UsbSelector::new(0x03eb, 0x2018)) {
            Err(LinkError::Unavailable(msg)) => {
                assert!(msg.starts_with("USB unavailable: "), "{msg}")
            }
            other => panic!("expected Unavailable, got {other:?}"),
        }
    }

    /// Wherever the test runs: a device nobody makes is never found, and the error names it.
    #[test]
    fn absent_device_is_unavailable_and_named() {
        match UsbBulkLink::open(&UsbSelector::new(0xffff, 0xfffe).serial("X1")) {
            Err(LinkError::Unavailable(msg)) => assert!(
                msg.starts_with("USB unavailable: ") || msg.contains("ffff:fffe serial X1"),
                "{msg}"
            ),
            other => panic!("expected Unavailable, got {other:?}"),
        }
    }

    #[test]
    fn errors_say_what_to_do() {
        let e = usb_error(rusb::Error::Access, "open", "USB device 03eb:2018");
        assert!(matches!(&e, LinkError::Unavailable(m) if m.contains("udev/70-dioptra.rules")));
        let e = usb_error(rusb::Error::NoDevice, "bulk read", "USB device 03eb:2018");
        assert!(e.needs_reconnect());
        assert_eq!(
            UsbSelector::new(0x0451, 0x6401)
                .serial("A")
                .interface(2)
                .to_string(),
            "USB device 0451:6401 serial A interface 2"
        );
    }
}
