//! The instrument traits: one drive output and one or more inputs on one sample clock.
//!
//! The drive is written ahead into a queue; the inputs come back in blocks, each tagged with a
//! sequence number and the index of its first sample on the shared clock, so input sample
//! `first_sample + i` is exactly what drive sample `first_sample + i` produced.

use crate::error::HalError;
use serde::{Deserialize, Serialize};

/// Range and resolution of one converter channel.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ChannelRange {
    pub min_v: f64,
    pub max_v: f64,
    /// Resolution in bits (16 for a typical DAQ board).
    pub bits: u32,
}

impl ChannelRange {
    /// One LSB, V.
    pub fn lsb_v(&self) -> f64 {
        (self.max_v - self.min_v) / ((1u64 << self.bits) - 1) as f64
    }

    /// Rounds `v` to the converter grid and clips it to the range.
    pub fn quantise(&self, v: f64) -> f64 {
        let lsb = self.lsb_v();
        let c = v.clamp(self.min_v, self.max_v);
        self.min_v + ((c - self.min_v) / lsb).round() * lsb
    }
}

/// One input channel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InputChannel {
    /// `deflection_v`, `measured_height_nm`, … (the recording spec's column names).
    pub name: String,
    pub range: ChannelRange,
}

/// Which sample is under the tip, on instruments with a switchable stage.
pub use viscoprobe_core::twin::SampleSlot;

/// What an instrument can do, discovered at open.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Capabilities {
    /// Backend and model, e.g. `simulated SPM` or `viscoprobe-daq 1.2`.
    pub name: String,
    pub firmware: Option<String>,
    pub max_sample_rate_hz: f64,
    pub drive: ChannelRange,
    pub inputs: Vec<InputChannel>,
    /// Largest block the backend moves at once, samples.
    pub max_block: usize,
    /// Stage slots that can be selected (empty: no switchable stage).
    pub sample_slots: Vec<SampleSlot>,
}

/// How to stream.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StreamConfig {
    pub sample_rate_hz: f64,
    /// Samples per input block.
    pub block_len: usize,
}

/// One block of input samples.
#[derive(Debug, Clone, PartialEq)]
pub struct InputBlock {
    /// Block sequence number, from 0 after `start`.
    pub seq: u64,
    /// Index of the block's first sample on the shared clock.
    pub first_sample: u64,
    /// One vector per input channel, in [`Capabilities::inputs`] order.
    pub channels: Vec<Vec<f64>>,
    /// The drive samples that produced these inputs, as the converter output them.
    pub drive_v: Vec<f64>,
}

impl InputBlock {
    pub fn len(&self) -> usize {
        self.drive_v.len()
    }

    pub fn is_empty(&self) -> bool {
        self.drive_v.is_empty()
    }
}

/// An instrument: a drive output and inputs on one clock.
///
/// Usage: `configure`, `start`, then alternately `write_drive` (ahead) and `read_block`;
/// `stop` ends streaming and holds the last drive value.
pub trait Instrument {
    fn capabilities(&self) -> Capabilities;
    fn configure(&mut self, cfg: &StreamConfig) -> Result<(), HalError>;
    fn start(&mut self) -> Result<(), HalError>;
    /// Appends drive samples (V) to the output queue.
    fn write_drive(&mut self, samples: &[f64]) -> Result<(), HalError>;
    /// Samples written but not yet output.
    fn queued_drive(&self) -> usize;
    /// The next input block; waits for it (bounded by the backend's timeout).
    fn read_block(&mut self) -> Result<InputBlock, HalError>;
    fn stop(&mut self) -> Result<(), HalError>;
    /// The last drive value output (the actuator's present command), V.
    fn last_drive(&self) -> f64;
    /// Moves another stage slot under the tip.
    fn select_sample(&mut self, slot: SampleSlot) -> Result<(), HalError> {
        let _ = slot;
        Err(HalError::new(
            crate::error::HalErrorKind::Unsupported,
            "this instrument has no switchable stage",
        ))
    }
}

/// A boxed instrument is an instrument: lets the daemon pick the backend at run time.
impl<T: Instrument + ?Sized> Instrument for Box<T> {
    fn capabilities(&self) -> Capabilities {
        (**self).capabilities()
    }
    fn configure(&mut self, cfg: &StreamConfig) -> Result<(), HalError> {
        (**self).configure(cfg)
    }
    fn start(&mut self) -> Result<(), HalError> {
        (**self).start()
    }
    fn write_drive(&mut self, samples: &[f64]) -> Result<(), HalError> {
        (**self).write_drive(samples)
    }
    fn queued_drive(&self) -> usize {
        (**self).queued_drive()
    }
    fn read_block(&mut self) -> Result<InputBlock, HalError> {
        (**self).read_block()
    }
    fn stop(&mut self) -> Result<(), HalError> {
        (**self).stop()
    }
    fn last_drive(&self) -> f64 {
        (**self).last_drive()
    }
    fn select_sample(&mut self, slot: SampleSlot) -> Result<(), HalError> {
        (**self).select_sample(slot)
    }
}
