//! The hardware abstraction layer of viscoprobe.
//!
//! [`Instrument`] is the one trait every backend implements: a piezo drive output (DAC) and
//! deflection inputs (ADC) on one sample clock, streamed in blocks — drive written ahead, inputs
//! read back with sequence numbers and sample-exact alignment — with discoverable
//! [`Capabilities`]. Errors are [`HalError`]s whose kind says whether retrying can help.
//!
//! [`Guarded`] wraps any instrument and enforces the drive voltage, slew-rate and force limits
//! below every controller, retracting the actuator on abort or fault. Backends:
//!
//! * [`sim::SimulatedSpm`] — the digital twin of `viscoprobe_core::twin`, in simulated time
//!   or paced to the wall clock;
//! * [`daq::SerialDaq`] — the serial DAQ board over `serialport`, speaking the protocol of
//!   `docs/daq-protocol.md`; the `viscoprobe-daq-emu` binary emulates the board on a
//!   pseudo-terminal with the twin behind it.
//!
//! This crate does blocking I/O and may sleep (wall-clock pacing); it knows nothing of tokio,
//! configuration files or run storage, which belong to the daemon.

pub mod acquire;
pub mod daq;
pub mod error;
pub mod instrument;
pub mod safety;
pub mod sim;

pub use daq::{DaqStats, SerialDaq, SerialOptions};
pub use error::{HalError, HalErrorKind};
pub use instrument::{
    Capabilities, ChannelRange, InputBlock, InputChannel, Instrument, SampleSlot, StreamConfig,
};
pub use safety::{ForceCalibration, Guarded, SafetyLimits, SafetyStats};
