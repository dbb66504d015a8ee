//! Serial ports (`/dev/ttyACM*`, `/dev/ttyUSB*`, pty slaves) as a [`ByteLink`].
//!
//! `serialport` opens and configures the tty (exclusive, raw, 8N1); its blocking I/O is not
//! used. Instead the fd is switched to O_NONBLOCK and driven by tokio's reactor, so waiting
//! costs no thread and a write returns as soon as the kernel has the bytes.

use std::path::Path;
use std::time::Duration;

use dioptra_core::LinkError;
use serialport::{ErrorKind, TTYPort};

use crate::fdio::{FdIo, Hangup};
use crate::ByteLink;

/// Line settings. Always 8 data bits, no parity, 1 stop bit, raw mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SerialSettings {
    pub baud: u32,
    pub flow_control: FlowControl,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FlowControl {
    None,
    /// Hardware handshake (e.g. Thorlabs APT controllers).
    RtsCts,
}

impl SerialSettings {
    /// 8N1 at `baud`, no flow control (e.g. `SerialSettings::baud(115_200)` for an
    /// Optotune Lens Driver 4).
    pub const fn baud(baud: u32) -> Self {
        SerialSettings {
            baud,
            flow_control: FlowControl::None,
        }
    }

    pub const fn rts_cts(self) -> Self {
        SerialSettings {
            flow_control: FlowControl::RtsCts,
            ..self
        }
    }
}

/// An open serial port. Opened exclusively: a second open of the same port fails as busy.
pub struct SerialLink {
    io: FdIo<TTYPort>,
    path: String,
    baud: u32,
}

impl std::fmt::Debug for SerialLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.describe())
    }
}

impl SerialLink {
    /// Opens and configures the port at `path`. Must be called inside a tokio runtime.
    ///
    /// Errors are [`LinkError::Unavailable`] with the path and what to do: no such port,
    /// permission denied, busy, or not a tty.
    pub fn open(path: impl AsRef<Path>, settings: SerialSettings) -> Result<Self, LinkError> {
        let path = path.as_ref();
        let shown = path.display().to_string();
        // serialport takes the path as a str; a non-UTF-8 path cannot name a tty we list.
        let Some(path_str) = path.to_str() else {
            return Err(LinkError::Unavailable(format!(
                "serial port path {shown} is not valid UTF-8"
            )));
        };
        if let Err(e) = std::fs::metadata(path) {
            if e.kind() == std::io::ErrorKind::NotFound {
                return Err(no_such_port(&shown));
            }
        }
        let flow = match settings.flow_control {
            FlowControl::None => serialport::FlowControl::None,
            FlowControl::RtsCts => serialport::FlowControl::Hardware,
        };
        let port = serialport::new(path_str, settings.baud)
            .data_bits(serialport::DataBits::Eight)
            .parity(serialport::Parity::None)
            .stop_bits(serialport::StopBits::One)
            .flow_control(flow)
            .open_native()
            .map_err(|e| open_error(&shown, e))?;
        use std::os::fd::AsRawFd;
        crate::fdio::set_nonblocking(port.as_raw_fd())
            .map_err(|e| LinkError::Io(format!("{shown}: cannot make non-blocking: {e}")))?;
        let io = FdIo::new(port, Hangup::Disconnect, format!("serial {shown}"))?;
        tracing::debug!(port = %shown, baud = settings.baud, "serial port open");
        Ok(SerialLink {
            io,
            path: shown,
            baud: settings.baud,
        })
    }

    /// The path the port was opened at.
    pub fn path(&self) -> &str {
        &self.path
    }
}

fn no_such_port(path: &str) -> LinkError {
    LinkError::Unavailable(format!(
        "no serial port at {path}: check that the device is plugged in and powered \
         (`dioptra devices` lists what is connected)"
    ))
}

fn open_error(path: &str, e: serialport::Error) -> LinkError {
    match e.kind() {
        ErrorKind::Io(std::io::ErrorKind::NotFound) => no_such_port(path),
        ErrorKind::Io(std::io::ErrorKind::PermissionDenied) => LinkError::Unavailable(format!(
            "permission denied on {path}: install udev/70-dioptra.rules \
             (then replug the device) or add yourself to group dialout and log in again"
        )),
        // EBUSY from TIOCEXCL or a held flock.
        ErrorKind::NoDevice => LinkError::Unavailable(format!(
            "{path} is busy: another program has it open ({}); close it, or stop \
             ModemManager probing it by installing udev/70-dioptra.rules",
            e.description
        )),
        ErrorKind::InvalidInput => {
            LinkError::Unavailable(format!("cannot open {path}: {}", e.description))
        }
        ErrorKind::Unknown => LinkError::Unavailable(format!(
            "{path} is not a usable serial port: {}",
            e.description
        )),
        ErrorKind::Io(_) => LinkError::Io(format!("cannot open {path}: {}", e.description)),
    }
}

impl ByteLink for SerialLink {
    async fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.io.write_all(bytes).await
    }

    async fn read(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        self.io.read(buf, timeout).await
    }

    async fn discard_input(&mut self) -> Result<usize, LinkError> {
        self.io.discard_input()
    }

    fn describe(&self) -> String {
        format!("{} at {} baud", self.io.name(), self.baud)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn missing_port_is_unavailable_and_names_the_path() {
        let e = SerialLink::open("/dev/ttyACM_dioptra_absent", SerialSettings::baud(115_200))
            .unwrap_err();
        match e {
            LinkError::Unavailable(msg) => {
                assert!(msg.contains("/dev/ttyACM_dioptra_absent"), "{msg}")
            }
            other => panic!("expected Unavailable, got {other:?}"),
        }
    }

    #[tokio::test]
    async fn a_regular_file_is_not_a_serial_port() {
        let file = tempfile::NamedTempFile::new().unwrap();
        let e = SerialLink::open(file.path(), SerialSettings::baud(9600)).unwrap_err();
        assert!(
            matches!(&e, LinkError::Unavailable(m) if m.contains("not a usable serial port")),
            "{e:?}"
        );
    }

    #[test]
    fn permission_denied_says_what_to_do() {
        let e = open_error(
            "/dev/ttyACM0",
            serialport::Error::new(
                ErrorKind::Io(std::io::ErrorKind::PermissionDenied),
                "Permission denied",
            ),
        );
        assert_eq!(
            e.to_string(),
            "permission denied on /dev/ttyACM0: install udev/70-dioptra.rules (then replug \
             the device) or add yourself to group dialout and log in again"
        );
    }
}
