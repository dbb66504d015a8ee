//! One link type per kind for code that opens devices by configuration: a driver generic over
//! [`ByteLink`] or [`HidLink`] is instantiated once with [`AnyByteLink`] or [`AnyHidLink`], and
//! the same driver value then runs on hardware or on an in-memory link to a simulator, chosen
//! at run time (the rig's `port = "sim"` or a device path).

use std::time::Duration;

use dioptra_core::LinkError;

use crate::hid::memory::MemoryHidLink;
use crate::hid::HidapiLink;
use crate::memory::MemoryLink;
use crate::serial::SerialLink;
use crate::usb::UsbBulkLink;
use crate::{ByteLink, HidLink};

/// A byte link to real hardware or to a simulator.
#[derive(Debug)]
pub enum AnyByteLink {
    Memory(MemoryLink),
    Serial(SerialLink),
    Usb(UsbBulkLink),
}

/// A HID link to real hardware or to a simulator.
#[derive(Debug)]
pub enum AnyHidLink {
    Memory(MemoryHidLink),
    Hidapi(HidapiLink),
}

macro_rules! each {
    ($self:ident, $l:ident => $e:expr, $($v:ident),+) => {
        match $self { $(Self::$v($l) => $e,)+ }
    };
}

impl ByteLink for AnyByteLink {
    async fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        each!(self, l => l.write_all(bytes).await, Memory, Serial, Usb)
    }
    async fn read(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        each!(self, l => l.read(buf, timeout).await, Memory, Serial, Usb)
    }
    async fn read_exact(&mut self, buf: &mut [u8], timeout: Duration) -> Result<(), LinkError> {
        each!(self, l => l.read_exact(buf, timeout).await, Memory, Serial, Usb)
    }
    async fn discard_input(&mut self) -> Result<usize, LinkError> {
        each!(self, l => l.discard_input().await, Memory, Serial, Usb)
    }
    fn describe(&self) -> String {
        each!(self, l => l.describe(), Memory, Serial, Usb)
    }
}

impl HidLink for AnyHidLink {
    async fn read_input_report(
        &mut self,
        buf: &mut [u8],
        timeout: Duration,
    ) -> Result<usize, LinkError> {
        each!(self, l => l.read_input_report(buf, timeout).await, Memory, Hidapi)
    }
    async fn write_output_report(&mut self, report: &[u8]) -> Result<(), LinkError> {
        each!(self, l => l.write_output_report(report).await, Memory, Hidapi)
    }
    async fn get_feature_report(
        &mut self,
        report_id: u8,
        buf: &mut [u8],
    ) -> Result<usize, LinkError> {
        each!(self, l => l.get_feature_report(report_id, buf).await, Memory, Hidapi)
    }
    async fn send_feature_report(&mut self, report: &[u8]) -> Result<(), LinkError> {
        each!(self, l => l.send_feature_report(report).await, Memory, Hidapi)
    }
    async fn report_descriptor(&mut self) -> Result<Vec<u8>, LinkError> {
        each!(self, l => l.report_descriptor().await, Memory, Hidapi)
    }
    fn describe(&self) -> String {
        each!(self, l => l.describe(), Memory, Hidapi)
    }
}

impl From<MemoryLink> for AnyByteLink {
    fn from(l: MemoryLink) -> Self {
        AnyByteLink::Memory(l)
    }
}
impl From<SerialLink> for AnyByteLink {
    fn from(l: SerialLink) -> Self {
        AnyByteLink::Serial(l)
    }
}
impl From<UsbBulkLink> for AnyByteLink {
    fn from(l: UsbBulkLink) -> Self {
        AnyByteLink::Usb(l)
    }
}
impl From<MemoryHidLink> for AnyHidLink {
    fn from(l: MemoryHidLink) -> Self {
        AnyHidLink::Memory(l)
    }
}
impl From<HidapiLink> for AnyHidLink {
    fn from(l: HidapiLink) -> Self {
        AnyHidLink::Hidapi(l)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn an_any_link_carries_bytes_and_errors_of_the_link_inside() {
        let (host, mut dev) = crate::memory::pair(64);
        let mut any = AnyByteLink::from(host);
        any.write_all(b"ping").await.unwrap();
        let mut buf = [0u8; 4];
        dev.read_exact(&mut buf, Duration::from_millis(10))
            .await
            .unwrap();
        assert_eq!(&buf, b"ping");
        dev.write_all(b"pong").await.unwrap();
        any.read_exact(&mut buf, Duration::from_millis(10))
            .await
            .unwrap();
        assert_eq!(&buf, b"pong");
        let e = any.read(&mut buf, Duration::from_millis(5)).await;
        assert!(matches!(e, Err(LinkError::Timeout { .. })), "{e:?}");
        drop(dev);
        let e = any.read(&mut buf, Duration::from_millis(5)).await;
        assert!(matches!(e, Err(LinkError::Disconnected(_))), "{e:?}");
    }
}
