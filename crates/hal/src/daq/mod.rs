//! The serial DAQ board: its wire protocol (docs/daq-protocol.md), the host-side backend
//! [`SerialDaq`], and the device-side state machine the emulator `viscoprobe-daq-emu` runs.
//!
//! * [`frame`] — COBS framing with a CRC-32 per frame, and a decoder that never panics;
//! * [`protocol`] — the messages of protocol version 1 and their byte layout;
//! * [`device`] — the firmware's state machine over a [`device::Plant`] (the digital twin);
//! * [`serial`] — [`SerialDaq`], the [`crate::Instrument`] over a serial port.

pub mod device;
pub mod frame;
pub mod protocol;
pub mod serial;

pub use serial::{DaqStats, SerialDaq, SerialOptions};
