//! How a serial-line photodiode identifies itself. There is no USB match table: the common lab
//! build is any microcontroller board (Arduino, Teensy, a Raspberry Pi Pico), whose vendor and
//! product ids say nothing about the sketch it runs, so the device is recognised by its hello
//! line instead (`dioptra-photodiode,1,...`).

/// The driver's name in the rig config (`[devices.photodiode] driver = "serial-line"`) and on
/// the command line.
pub const DRIVER: &str = "serial-line";

/// The first field of the hello line.
pub const HELLO_NAME: &str = "dioptra-photodiode";

/// The line protocol version this driver speaks (firmware-protocol/photodiode/README.md).
pub const LINE_PROTOCOL_VERSION: u32 = 1;

/// The line settings for a UART bridge (a CDC-ACM port ignores them).
pub const BAUD: u32 = 115_200;
