//! The safety layer: wraps any [`Instrument`] and enforces drive voltage, slew rate and force
//! limits below every controller, and retracts the actuator on abort or fault.
//!
//! Drive samples outside the voltage range are clipped and steps faster than the slew limit
//! are slowed (both counted in [`SafetyStats`]); a force above the limit trips the layer: the
//! queued drive is dropped, the actuator ramps to the retract voltage at the slew limit, and
//! every later call fails with [`HalErrorKind::SafetyLimit`] until [`Guarded::reset`].
//!
//! So does a deflection reading at the top of its channel's declared range (within one
//! LSB): the detector or its converter has saturated, the force it reads is a floor, not the
//! force, and the force limit can no longer see the sample. A simulated detector saturating
//! at 6.6 nN under a 40 nN limit let the calibration's approach push on to the end of the
//! drive range, the force limit blind the whole way.

use crate::error::{HalError, HalErrorKind};
use crate::instrument::{Capabilities, InputBlock, Instrument, SampleSlot, StreamConfig};
use serde::{Deserialize, Serialize};

/// How a deflection reading becomes a force.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ForceCalibration {
    pub spring_constant_n_per_m: f64,
    pub deflection_sensitivity_nm_per_v: f64,
    /// Index of the deflection channel in the instrument's inputs.
    pub channel: usize,
    /// Deflection reading with no force (free lever), V.
    pub zero_v: f64,
}

impl ForceCalibration {
    /// Force in newtons for a deflection reading in volts.
    pub fn force_n(&self, deflection_v: f64) -> f64 {
        self.spring_constant_n_per_m
            * self.deflection_sensitivity_nm_per_v
            * 1e-9
            * (deflection_v - self.zero_v)
    }
}

/// The limits the layer enforces.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SafetyLimits {
    pub min_drive_v: f64,
    pub max_drive_v: f64,
    pub max_slew_v_per_s: f64,
    /// Largest repulsive force allowed on the sample, N.
    pub max_force_n: f64,
    /// The drive at which the tip is safely away from the sample, V.
    pub retract_drive_v: f64,
    pub force: ForceCalibration,
}

/// What the layer had to do.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct SafetyStats {
    pub clipped_samples: u64,
    pub slew_limited_samples: u64,
    pub trips: u64,
    pub retracts: u64,
}

/// An instrument behind the safety layer.
pub struct Guarded<I: Instrument> {
    inner: I,
    limits: SafetyLimits,
    fs_hz: Option<f64>,
    block_len: usize,
    tail_v: Option<f64>,
    stats: SafetyStats,
    tripped: Option<String>,
    /// The deflection channel's declared top and its LSB, V, read at `configure`.
    deflection_top: Option<(f64, f64)>,
}

impl<I: Instrument> Guarded<I> {
    pub fn new(inner: I, limits: SafetyLimits) -> Self {
        Self {
            inner,
            limits,
            fs_hz: None,
            block_len: 0,
            tail_v: None,
            stats: SafetyStats::default(),
            tripped: None,
            deflection_top: None,
        }
    }

    pub fn inner(&self) -> &I {
        &self.inner
    }

    pub fn inner_mut(&mut self) -> &mut I {
        &mut self.inner
    }

    pub fn limits(&self) -> &SafetyLimits {
        &self.limits
    }

    /// Updates the force zero (after the free-lever baseline was measured).
    pub fn set_force_zero(&mut self, zero_v: f64) {
        self.limits.force.zero_v = zero_v;
    }

    pub fn stats(&self) -> SafetyStats {
        self.stats
    }

    /// Why the layer tripped, if it did.
    pub fn tripped(&self) -> Option<&str> {
        self.tripped.as_deref()
    }

    /// Re-arms the layer after a trip (the actuator is already retracted).
    pub fn reset(&mut self) {
        self.tripped = None;
    }

    fn check_armed(&self) -> Result<(), HalError> {
        match &self.tripped {
            Some(why) => Err(HalError::new(
                HalErrorKind::SafetyLimit,
                format!("safety layer tripped earlier: {why}"),
            )),
            None => Ok(()),
        }
    }

    /// Clips and slew-limits `samples` as they would be output after the current queue tail.
    fn shape(&mut self, samples: &[f64]) -> Vec<f64> {
        let max_step = self
            .fs_hz
            .map_or(f64::INFINITY, |fs| self.limits.max_slew_v_per_s / fs);
        let mut prev = self.tail_v.unwrap_or_else(|| self.inner.last_drive());
        samples
            .iter()
            .map(|&v| {
                let mut x = if v.is_nan() { prev } else { v };
                if x < self.limits.min_drive_v || x > self.limits.max_drive_v {
                    x = x.clamp(self.limits.min_drive_v, self.limits.max_drive_v);
                    self.stats.clipped_samples += 1;
                }
                if (x - prev).abs() > max_step {
                    x = prev + max_step.copysign(x - prev);
                    self.stats.slew_limited_samples += 1;
                }
                prev = x;
                x
            })
            .collect()
    }

    /// Drops what is queued and ramps the actuator to the retract voltage at the slew limit,
    /// streaming until the ramp has been output. Leaves streaming stopped.
    pub fn retract(&mut self) -> Result<(), HalError> {
        self.stats.retracts += 1;
        let fs = self.fs_hz.unwrap_or(1.0);
        let start = self.inner.last_drive();
        let step = self.limits.max_slew_v_per_s / fs;
        let target = self.limits.retract_drive_v;
        let n = ((target - start).abs() / step).ceil() as usize;
        let mut ramp: Vec<f64> = (1..=n)
            .map(|k| start + (target - start) * k as f64 / n as f64)
            .collect();
        let block = self.block_len.max(1);
        // Whole blocks, holding the retract voltage at the end.
        let total = ramp.len().div_ceil(block).max(1) * block;
        ramp.resize(total, target);
        let _ = self.inner.stop();
        self.inner.start()?;
        self.inner.write_drive(&ramp)?;
        self.tail_v = Some(target);
        let mut guard = 0;
        while self.inner.queued_drive() > 0 && guard < total / block + 4 {
            self.inner.read_block()?;
            guard += 1;
        }
        self.inner.stop()
    }

    /// Abort: retract and stop. Safe to call in any state.
    pub fn abort(&mut self) -> Result<(), HalError> {
        self.retract()
    }
}

impl<I: Instrument> Instrument for Guarded<I> {
    fn capabilities(&self) -> Capabilities {
        self.inner.capabilities()
    }

    fn configure(&mut self, cfg: &StreamConfig) -> Result<(), HalError> {
        self.inner.configure(cfg)?;
        self.fs_hz = Some(cfg.sample_rate_hz);
        self.block_len = cfg.block_len;
        let inputs = self.inner.capabilities().inputs;
        // A range a backend declares without a finite top or step (no converter behind it)
        // gives no check rather than one that trips on every reading.
        self.deflection_top = (inputs.get(self.limits.force.channel))
            .map(|c| (c.range.max_v, c.range.lsb_v()))
            .filter(|(top, lsb)| top.is_finite() && lsb.is_finite() && *lsb >= 0.0);
        Ok(())
    }

    fn start(&mut self) -> Result<(), HalError> {
        self.check_armed()?;
        self.tail_v = None;
        self.inner.start()
    }

    fn write_drive(&mut self, samples: &[f64]) -> Result<(), HalError> {
        self.check_armed()?;
        let shaped = self.shape(samples);
        self.inner.write_drive(&shaped)?;
        self.tail_v = shaped.last().copied().or(self.tail_v);
        Ok(())
    }

    fn queued_drive(&self) -> usize {
        self.inner.queued_drive()
    }

    fn read_block(&mut self) -> Result<InputBlock, HalError> {
        self.check_armed()?;
        let block = match self.inner.read_block() {
            Ok(b) => b,
            Err(e) if !e.is_transient() => {
                // A fatal fault: make the actuator safe if the link still allows it.
                let _ = self.retract();
                return Err(e);
            }
            Err(e) => return Err(e),
        };
        let cal = self.limits.force;
        if let Some(ch) = block.channels.get(cal.channel) {
            let over = |v: f64| cal.force_n(v) > self.limits.max_force_n;
            let pinned = |v: f64| {
                self.deflection_top
                    .is_some_and(|(top, lsb)| v >= top - lsb && cal.force_n(v) > 0.0)
            };
            if let Some((i, v)) =
                (ch.iter().copied().enumerate()).find(|&(_, v)| over(v) || pinned(v))
            {
                let sample = block.first_sample + i as u64;
                let limit_nn = self.limits.max_force_n * 1e9;
                let why = match over(v) {
                    true => format!(
                        "force {:.3} nN at sample {sample} exceeds the limit {limit_nn:.3} nN",
                        cal.force_n(v) * 1e9,
                    ),
                    false => format!(
                        "deflection {v:.4} V at sample {sample} is at the top of its channel's range: the detector or its converter saturated, and the force on the sample, {:.3} nN or more, is no longer known against the limit {limit_nn:.3} nN",
                        cal.force_n(v) * 1e9,
                    ),
                };
                self.stats.trips += 1;
                let retract = self.retract();
                self.tripped = Some(why.clone());
                let suffix = match retract {
                    Ok(()) => "; actuator retracted".to_string(),
                    Err(e) => format!("; retract failed: {e}"),
                };
                return Err(HalError::new(HalErrorKind::SafetyLimit, why + &suffix));
            }
        }
        Ok(block)
    }

    fn stop(&mut self) -> Result<(), HalError> {
        self.inner.stop()
    }

    fn last_drive(&self) -> f64 {
        self.inner.last_drive()
    }

    fn select_sample(&mut self, slot: SampleSlot) -> Result<(), HalError> {
        self.inner.select_sample(slot)
    }
}
