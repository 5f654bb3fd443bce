//! The simulated SPM: the digital twin of `viscoprobe_core::twin` behind the [`Instrument`]
//! traits, in simulated time (as fast as the CPU allows) or paced to the wall clock.
//!
//! It behaves like the DAQ board: 16-bit converters, a drive queue that must be written ahead
//! (running dry is an underrun), blocks with sequence numbers. It also records what only a
//! simulator knows — the true force and indentation of every sample — for tests and for the
//! `[truth]` of a simulated recording.

use crate::error::{HalError, HalErrorKind};
use crate::instrument::{
    Capabilities, ChannelRange, InputBlock, InputChannel, Instrument, SampleSlot, StreamConfig,
};
use std::collections::VecDeque;
use std::time::{Duration, Instant};
use viscoprobe_core::twin::{TruthSample, Twin, TwinConfig};

/// Time base of the simulation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pacing {
    /// As fast as the CPU allows.
    Simulated,
    /// Each block is delivered no earlier than the wall-clock time its last sample is due.
    WallClock,
}

const RANGE: ChannelRange = ChannelRange {
    min_v: -10.0,
    max_v: 10.0,
    bits: 16,
};

/// The deflection channel's range: the converter's, or the twin's detector's own
/// (`detector.range_v`) where that saturates first, as a real instrument would declare it.
fn deflection_range(twin: &TwinConfig) -> ChannelRange {
    let r = twin.detector.range_v;
    match r > 0.0 && r < RANGE.max_v {
        true => ChannelRange {
            min_v: -r,
            max_v: r,
            bits: RANGE.bits,
        },
        false => RANGE,
    }
}

/// The simulated instrument.
pub struct SimulatedSpm {
    config: TwinConfig,
    twin: Option<Twin>,
    pacing: Pacing,
    stream: Option<StreamConfig>,
    queue: VecDeque<f64>,
    running: bool,
    started: Option<Instant>,
    sample: u64,
    seq: u64,
    last_drive: f64,
    slot: SampleSlot,
    truth: Vec<TruthSample>,
    truth_log: Vec<TruthSample>,
}

impl SimulatedSpm {
    /// A simulated instrument over a validated twin configuration.
    pub fn new(config: TwinConfig, pacing: Pacing) -> Self {
        Self {
            config,
            twin: None,
            pacing,
            stream: None,
            queue: VecDeque::new(),
            running: false,
            started: None,
            sample: 0,
            seq: 0,
            last_drive: 0.0,
            slot: SampleSlot::Soft,
            truth: Vec::new(),
            truth_log: Vec::new(),
        }
    }

    pub fn twin_config(&self) -> &TwinConfig {
        &self.config
    }

    /// The true force and indentation of the samples of the last block.
    pub fn last_truth(&self) -> &[TruthSample] {
        &self.truth
    }

    /// The truth of every sample since the last `start`.
    pub fn last_truth_log(&self) -> &[TruthSample] {
        &self.truth_log
    }
}

impl Instrument for SimulatedSpm {
    fn capabilities(&self) -> Capabilities {
        let mut inputs = vec![InputChannel {
            name: "deflection_v".into(),
            range: deflection_range(&self.config),
        }];
        if self.config.height_sensor.is_some() {
            inputs.push(InputChannel {
                name: "measured_height_nm".into(),
                range: ChannelRange {
                    min_v: -1e5,
                    max_v: 1e5,
                    bits: 24,
                },
            });
        }
        Capabilities {
            name: "simulated SPM (viscoprobe digital twin)".into(),
            firmware: None,
            max_sample_rate_hz: 200_000.0,
            drive: RANGE,
            inputs,
            max_block: 65_536,
            sample_slots: vec![SampleSlot::Soft, SampleSlot::Reference],
        }
    }

    fn configure(&mut self, cfg: &StreamConfig) -> Result<(), HalError> {
        let caps = self.capabilities();
        if !(cfg.sample_rate_hz > 0.0 && cfg.sample_rate_hz <= caps.max_sample_rate_hz) {
            return Err(HalError::new(
                HalErrorKind::InvalidConfig,
                format!(
                    "sample rate {} Hz outside (0, {}] Hz",
                    cfg.sample_rate_hz, caps.max_sample_rate_hz
                ),
            ));
        }
        if cfg.block_len == 0 || cfg.block_len > caps.max_block {
            return Err(HalError::new(
                HalErrorKind::InvalidConfig,
                format!(
                    "block length {} outside 1..={}",
                    cfg.block_len, caps.max_block
                ),
            ));
        }
        let mut twin = Twin::new(&self.config, cfg.sample_rate_hz);
        twin.select(self.slot);
        twin.settle(self.last_drive);
        self.twin = Some(twin);
        self.stream = Some(*cfg);
        Ok(())
    }

    fn start(&mut self) -> Result<(), HalError> {
        if self.stream.is_none() {
            return Err(HalError::new(HalErrorKind::State, "start before configure"));
        }
        self.running = true;
        self.seq = 0;
        self.truth_log.clear();
        self.started = Some(Instant::now());
        Ok(())
    }

    fn write_drive(&mut self, samples: &[f64]) -> Result<(), HalError> {
        if let Some(i) = samples.iter().position(|v| !v.is_finite()) {
            return Err(HalError::new(
                HalErrorKind::InvalidConfig,
                format!("drive sample {i} is not finite"),
            ));
        }
        self.queue
            .extend(samples.iter().map(|&v| RANGE.quantise(v)));
        Ok(())
    }

    fn queued_drive(&self) -> usize {
        self.queue.len()
    }

    fn read_block(&mut self) -> Result<InputBlock, HalError> {
        let (Some(cfg), true) = (self.stream, self.running) else {
            return Err(HalError::new(HalErrorKind::State, "read before start"));
        };
        if self.queue.len() < cfg.block_len {
            return Err(HalError::new(
                HalErrorKind::Underrun,
                format!(
                    "drive queue holds {} samples, a block needs {}",
                    self.queue.len(),
                    cfg.block_len
                ),
            ));
        }
        let deflection = deflection_range(&self.config);
        let twin = self.twin.as_mut().expect("configured");
        let mut defl = Vec::with_capacity(cfg.block_len);
        let mut height = Vec::new();
        let mut drive = Vec::with_capacity(cfg.block_len);
        self.truth.clear();
        for _ in 0..cfg.block_len {
            let v = self.queue.pop_front().expect("length checked");
            let s = twin.step(v);
            defl.push(deflection.quantise(s.deflection_v));
            if let Some(h) = s.measured_height_nm {
                height.push(h);
            }
            drive.push(v);
            self.truth.push(s.truth);
            self.truth_log.push(s.truth);
            self.last_drive = v;
        }
        let first_sample = self.sample;
        self.sample += cfg.block_len as u64;
        if self.pacing == Pacing::WallClock {
            if let Some(t0) = self.started {
                let due = t0
                    + Duration::from_secs_f64(
                        (self.seq + 1) as f64 * cfg.block_len as f64 / cfg.sample_rate_hz,
                    );
                let now = Instant::now();
                if due > now {
                    std::thread::sleep(due - now);
                }
            }
        }
        let mut channels = vec![defl];
        if !height.is_empty() {
            channels.push(height);
        }
        let block = InputBlock {
            seq: self.seq,
            first_sample,
            channels,
            drive_v: drive,
        };
        self.seq += 1;
        Ok(block)
    }

    fn stop(&mut self) -> Result<(), HalError> {
        self.running = false;
        self.queue.clear();
        Ok(())
    }

    fn last_drive(&self) -> f64 {
        self.last_drive
    }

    fn select_sample(&mut self, slot: SampleSlot) -> Result<(), HalError> {
        if self.running {
            return Err(HalError::new(
                HalErrorKind::State,
                "stop streaming before moving the stage",
            ));
        }
        self.slot = slot;
        if let Some(t) = self.twin.as_mut() {
            t.select(slot);
            t.settle(self.last_drive);
        }
        Ok(())
    }
}
