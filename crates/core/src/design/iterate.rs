//! The iteration of the paper's Sec. II-B as a pure state machine: design an excitation for
//! the current model, let the caller measure and estimate, redesign for the estimate, until
//! the parameters stop moving.
//!
//! [`DesignLoop`] does no I/O and owns no threads: [`DesignLoop::next_excitation`] hands out
//! the excitation to apply, [`DesignLoop::feed`] takes the estimate obtained with it and says
//! whether to go on. The relative change of an iteration is
//! `max_i |θ_i,new − θ_i,old|/|θ_i,old|` over the canonical parameters, `θ_old` being the model
//! the excitation was designed for (the prior in the first iteration).

use super::{d_optimal, synthesize, Design, DesignConfig, DesignError, Multisine, SynthConfig};
use crate::prony::PronySeries;
use serde::Serialize;
use thiserror::Error;

/// Settings of the design loop.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopConfig {
    /// The design problem (band, exclusions, record, noise …).
    pub design: DesignConfig,
    /// The signal (level, preload, crest-factor iterations).
    pub synth: SynthConfig,
    /// Stop when the relative parameter change falls to this (0.005 = 0.5 %).
    pub rel_change_tol: f64,
    /// Stop after this many estimates even if not converged (the paper's experiment: 15).
    pub max_iterations: usize,
}

impl LoopConfig {
    /// Defaults: 0.5 % relative change, at most 15 iterations.
    pub fn new(design: DesignConfig, synth: SynthConfig) -> Self {
        Self {
            design,
            synth,
            rel_change_tol: 0.005,
            max_iterations: 15,
        }
    }
}

/// One excitation to apply: the design for `model` and its synthesised signal.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Excitation {
    /// 1-based iteration number.
    pub iteration: usize,
    /// The model the design was computed for.
    pub model: PronySeries,
    pub design: Design,
    pub signal: Multisine,
}

/// What the loop wants after an estimate was fed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum LoopStep {
    /// Not converged: call [`DesignLoop::next_excitation`] again.
    Continue { rel_change: f64 },
    /// The relative change fell below the threshold; the last estimate is the result.
    Converged { rel_change: f64 },
    /// The iteration limit was reached without convergence.
    IterationLimit { rel_change: f64 },
}

impl LoopStep {
    /// The relative parameter change of this iteration.
    pub fn rel_change(&self) -> f64 {
        match *self {
            LoopStep::Continue { rel_change }
            | LoopStep::Converged { rel_change }
            | LoopStep::IterationLimit { rel_change } => rel_change,
        }
    }

    /// True unless the loop wants another iteration.
    pub fn is_finished(&self) -> bool {
        !matches!(self, LoopStep::Continue { .. })
    }
}

/// One completed iteration.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoopRecord {
    pub excitation: Excitation,
    /// The estimate obtained with it.
    pub estimate: PronySeries,
    /// Relative change from `excitation.model` to `estimate`.
    pub rel_change: f64,
}

/// The finished loop.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoopOutcome {
    /// Every iteration, in order.
    pub records: Vec<LoopRecord>,
    /// The last estimate (the prior if no iteration ran).
    pub final_model: PronySeries,
    /// True when stopped by the relative-change threshold rather than the iteration limit.
    pub converged: bool,
}

/// The design → measure → estimate → redesign iteration.
#[derive(Debug, Clone)]
pub struct DesignLoop {
    cfg: LoopConfig,
    model: PronySeries,
    pending: Option<Excitation>,
    records: Vec<LoopRecord>,
    finished: Option<LoopStep>,
}

impl DesignLoop {
    /// Starts a loop from a prior model; checks the configuration and the prior.
    pub fn new(prior: PronySeries, cfg: LoopConfig) -> Result<Self, DesignError> {
        cfg.design.validate()?;
        if !(cfg.rel_change_tol.is_finite() && cfg.rel_change_tol >= 0.0) || cfg.max_iterations == 0
        {
            return Err(DesignError::InvalidConfig(format!(
                "loop needs a relative-change threshold ≥ 0 and at least one iteration, got {} and {}",
                cfg.rel_change_tol, cfg.max_iterations
            )));
        }
        if !prior.is_physical() {
            return Err(DesignError::NonPhysicalModel(prior));
        }
        Ok(Self {
            cfg,
            model: prior,
            pending: None,
            records: Vec::new(),
            finished: None,
        })
    }

    /// The excitation to apply next (designed for the current model). Calling it again
    /// before [`Self::feed`] returns the same excitation.
    pub fn next_excitation(&mut self) -> Result<&Excitation, DesignError> {
        if let Some(step) = self.finished {
            return Err(DesignError::LoopMisuse(format!(
                "the loop has finished ({step:?})"
            )));
        }
        if self.pending.is_none() {
            let design = d_optimal(&self.model, &self.cfg.design)?;
            let signal = synthesize(&design, &self.cfg.synth)?;
            self.pending = Some(Excitation {
                iteration: self.records.len() + 1,
                model: self.model.clone(),
                design,
                signal,
            });
        }
        Ok(self.pending.as_ref().expect("set above"))
    }

    /// Takes the estimate obtained with the pending excitation. A non-physical estimate or
    /// one of a different order is refused and leaves the loop unchanged.
    pub fn feed(&mut self, estimate: PronySeries) -> Result<LoopStep, DesignError> {
        let Some(exc) = self.pending.as_ref() else {
            return Err(DesignError::LoopMisuse(
                "feed called without a pending excitation".into(),
            ));
        };
        if estimate.order() != exc.model.order() {
            return Err(DesignError::OrderMismatch {
                expected: exc.model.order(),
                got: estimate.order(),
            });
        }
        if !estimate.is_physical() {
            return Err(DesignError::NonPhysicalModel(estimate));
        }
        let rel_change = relative_change(&exc.model, &estimate);
        let exc = self.pending.take().expect("checked above");
        self.records.push(LoopRecord {
            excitation: exc,
            estimate: estimate.clone(),
            rel_change,
        });
        self.model = estimate;
        let step = if rel_change <= self.cfg.rel_change_tol {
            LoopStep::Converged { rel_change }
        } else if self.records.len() >= self.cfg.max_iterations {
            LoopStep::IterationLimit { rel_change }
        } else {
            LoopStep::Continue { rel_change }
        };
        if step.is_finished() {
            self.finished = Some(step);
        }
        Ok(step)
    }

    /// The model the next design will be computed for (the latest estimate, or the prior).
    pub fn current_model(&self) -> &PronySeries {
        &self.model
    }

    /// Completed iterations.
    pub fn records(&self) -> &[LoopRecord] {
        &self.records
    }

    /// `Some(step)` once converged or out of iterations.
    pub fn finished(&self) -> Option<LoopStep> {
        self.finished
    }

    /// The record of the loop so far.
    pub fn into_outcome(self) -> LoopOutcome {
        LoopOutcome {
            converged: matches!(self.finished, Some(LoopStep::Converged { .. })),
            final_model: self.model,
            records: self.records,
        }
    }
}

/// `max_i |new_i − old_i|/|old_i|` over the canonical parameter vectors.
pub fn relative_change(old: &PronySeries, new: &PronySeries) -> f64 {
    old.to_vec()
        .iter()
        .zip(new.to_vec())
        .map(|(o, n)| {
            if *o == 0.0 {
                (n - o).abs()
            } else {
                ((n - o) / o).abs()
            }
        })
        .fold(0.0, f64::max)
}

/// Why [`run_design_loop`] stopped early.
#[derive(Debug, Error)]
pub enum LoopError<E> {
    #[error("input design failed: {0}")]
    Design(#[from] DesignError),
    #[error("measurement or estimation failed in iteration {iteration}: {error}")]
    Measure { iteration: usize, error: E },
}

/// Runs the loop to the end: `measure` applies an excitation and returns the estimate made
/// from its data. Every iteration's excitation and estimate are recorded in the outcome.
pub fn run_design_loop<E>(
    prior: PronySeries,
    cfg: LoopConfig,
    mut measure: impl FnMut(&Excitation) -> Result<PronySeries, E>,
) -> Result<LoopOutcome, LoopError<E>> {
    let mut lp = DesignLoop::new(prior, cfg)?;
    loop {
        let exc = lp.next_excitation()?;
        let iteration = exc.iteration;
        let estimate = measure(exc).map_err(|error| LoopError::Measure { iteration, error })?;
        if lp.feed(estimate)?.is_finished() {
            return Ok(lp.into_outcome());
        }
    }
}
