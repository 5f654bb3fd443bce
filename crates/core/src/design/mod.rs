//! Optimal input design: D-optimal multisines from the Fisher information (the paper's
//! Sec. II-B, eqs. 13–19), their synthesis as a time signal, and the design–measure–estimate
//! iteration.
//!
//! The pieces, in the order an experiment uses them:
//!
//! * [`DesignConfig`] states the experiment: sample rate, record length and number of
//!   periods (the candidate lines are the per-period DFT grid, spacing `1/period`), the search
//!   band, the lines that must stay dark ([`Exclusions`]: mains and its harmonics, user lines),
//!   the noise spectrum and the initial design F0.
//! * [`d_optimal`] runs the sequential design of eqs. 17–19 (Fedorov–Wynn) on the prior model
//!   and returns a [`Design`]: a few [`DesignLine`]s with power fractions and the
//!   Kiefer–Wolfowitz certificate `d_max_over_p = max_f d(f)/p` (exactly 1 at the optimum; the
//!   returned design always satisfies `≤ 1 + ε`). The algorithm is described in
//!   [`optimal`].
//! * [`synthesize`] turns a design into a [`Multisine`]: amplitudes `A_i = sqrt(2 P p_i)`,
//!   Schroeder phases improved by iterative clipping, an offset for the preload, and the
//!   sampled signal over whole periods, with its crest factor.
//! * [`DesignLoop`] is the iteration of Sec. II-B as a pure state machine (design → measure →
//!   estimate → redesign until the parameters stop moving); [`run_design_loop`] drives it with
//!   a caller-supplied measurement closure.
//! * [`paper_table2_design`] and [`table2_comparison`] put the paper's Table II design next to
//!   the same search and to a wide-band design, at equal input power and noise.
//!
//! All frequencies are in Hz, times in s, the input u in the caller's unit (the contact
//! transform's `u = 9P/(16√R)` or a force), and power means the mean square of u's AC part.
//! Nothing here panics on a bad configuration: every failure is a [`DesignError`].

pub mod iterate;
pub mod optimal;
pub mod paper;
pub mod synth;

pub use iterate::{
    run_design_loop, DesignLoop, Excitation, LoopConfig, LoopError, LoopOutcome, LoopRecord,
    LoopStep,
};
pub use optimal::{candidate_grid, d_max_over_p, d_optimal, predicted_crlb, Design};
pub use paper::{paper_table2_design, table2_comparison, Table2Comparison, Table2Row};
pub use synth::{synthesize, Level, Multisine, SynthConfig, SynthLine};

use crate::discrete::Sampling;
use crate::fisher::NoiseSpectrum;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// One line of a design: a frequency and the fraction of the input's AC power it carries.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DesignLine {
    /// Frequency, Hz.
    pub freq_hz: f64,
    /// Fraction of the total input power (the fractions of a design sum to 1).
    pub power_frac: f64,
}

/// A band of frequencies that must carry no excitation: `|f − center| ≤ half_width`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Exclusion {
    /// Centre, Hz.
    pub center_hz: f64,
    /// Half width, Hz (0 excludes only a line exactly at the centre).
    pub half_width_hz: f64,
}

/// Mains pick-up: the fundamental and every harmonic of it are excluded.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MainsExclusion {
    /// 50 or 60 Hz (any positive value is accepted).
    pub fundamental_hz: f64,
    /// Half width around each harmonic, Hz.
    pub half_width_hz: f64,
}

/// Lines that must never appear in a design.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Exclusions {
    /// Mains and all its harmonics, if set.
    pub mains: Option<MainsExclusion>,
    /// Further user-given bands.
    pub bands: Vec<Exclusion>,
}

impl Exclusions {
    /// True when a line at `freq_hz` is excluded.
    pub fn excludes(&self, freq_hz: f64) -> bool {
        if let Some(m) = self.mains {
            let h = (freq_hz / m.fundamental_hz).round().max(1.0);
            if (freq_hz - h * m.fundamental_hz).abs() <= m.half_width_hz {
                return true;
            }
        }
        self.bands
            .iter()
            .any(|b| (freq_hz - b.center_hz).abs() <= b.half_width_hz)
    }
}

/// How lines of the converged grid design are merged into a small support: neighbours
/// (in frequency order) closer than `max(abs_hz, rel·f)` become one line.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MergeRule {
    /// Relative distance (of the lower frequency); default 0.35.
    pub rel: f64,
    /// Absolute distance, Hz.
    pub abs_hz: f64,
}

impl Default for MergeRule {
    fn default() -> Self {
        Self {
            rel: 0.35,
            abs_hz: 0.0,
        }
    }
}

/// Everything [`d_optimal`] needs besides the prior model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DesignConfig {
    /// Sample rate, Hz.
    pub fs_hz: f64,
    /// How the model's response relates to the sampled data (the paper: Tustin at `fs_hz`).
    pub sampling: Sampling,
    /// Record length, s.
    pub duration_s: f64,
    /// Whole periods in the record (≥ 1; 2 lets the estimator measure the noise from
    /// period-to-period variation). The candidate grid spacing is `periods/duration_s`.
    pub periods: usize,
    /// Search band `[f_lo, f_hi]`, Hz.
    pub band_hz: (f64, f64),
    /// Keep this fraction of the Nyquist frequency free: no line above `(1 − guard)·fs/2`.
    pub nyquist_guard: f64,
    /// Lines that must stay dark.
    pub exclusions: Exclusions,
    /// Output noise the design is optimal for (only its shape matters for the design).
    pub noise: NoiseSpectrum,
    /// Initial design F0, snapped to the nearest allowed grid line. Empty: log-spaced lines.
    pub initial: Vec<DesignLine>,
    /// Wynn step sizes `α_k = 1/(k + alpha_offset)`, k = 1, 2, … (the paper: 3).
    pub alpha_offset: f64,
    /// Plain Wynn steps before switching to the accelerated (exact line search, away-step)
    /// iteration; `None` keeps the plain eq. 18–19 steps throughout.
    pub accelerate_after: Option<usize>,
    /// Certificate tolerance ε: stop when `max d(f)/p ≤ 1 + ε`.
    pub epsilon: f64,
    /// Iteration limit of the search.
    pub max_iterations: usize,
    /// Merging of neighbouring lines into the final support.
    pub merge: MergeRule,
}

impl DesignConfig {
    /// The paper's settings on a band: 8 kHz Tustin, 2 s in 2 periods, white noise,
    /// `α_k = 1/(k+3)`, no exclusions, F0 = {1, 10, 30, 60} Hz at 25 % each (snapped into the
    /// band; lines outside it are dropped and replaced by log-spaced ones if too few remain).
    pub fn new(band_hz: (f64, f64)) -> Self {
        Self {
            fs_hz: 8000.0,
            sampling: Sampling::Tustin { fs_hz: 8000.0 },
            duration_s: 2.0,
            periods: 2,
            band_hz,
            nyquist_guard: 0.05,
            exclusions: Exclusions::default(),
            noise: NoiseSpectrum::White { std: 1.0 },
            initial: [1.0, 10.0, 30.0, 60.0]
                .iter()
                .map(|&f| DesignLine {
                    freq_hz: f,
                    power_frac: 0.25,
                })
                .collect(),
            alpha_offset: 3.0,
            accelerate_after: Some(10),
            epsilon: 0.01,
            max_iterations: 20_000,
            merge: MergeRule::default(),
        }
    }

    /// The sampling model the Fisher information is computed with.
    pub fn sampling(&self) -> Sampling {
        self.sampling
    }

    /// One period, s.
    pub fn period_s(&self) -> f64 {
        self.duration_s / self.periods as f64
    }

    /// Samples in the whole record.
    pub fn n_samples(&self) -> usize {
        (self.fs_hz * self.duration_s).round() as usize
    }

    /// The highest frequency a line may have: `min(f_hi, (1 − guard)·fs/2)`, Hz.
    pub fn f_max_hz(&self) -> f64 {
        self.band_hz
            .1
            .min((1.0 - self.nyquist_guard) * self.fs_hz / 2.0)
    }

    /// Checks the configuration; every later step may assume it passed.
    pub fn validate(&self) -> Result<(), DesignError> {
        let bad = |m: String| Err(DesignError::InvalidConfig(m));
        if !(self.fs_hz.is_finite() && self.fs_hz > 0.0) {
            return bad(format!(
                "sample rate must be positive, got {} Hz",
                self.fs_hz
            ));
        }
        if !(self.duration_s.is_finite() && self.duration_s > 0.0) {
            return bad(format!(
                "duration must be positive, got {} s",
                self.duration_s
            ));
        }
        if self.periods == 0 {
            return bad("periods must be at least 1".into());
        }
        let per_samples = self.fs_hz * self.period_s();
        if (per_samples - per_samples.round()).abs() > 1e-6 * per_samples.max(1.0)
            || per_samples.round() < 4.0
        {
            return bad(format!(
                "a period of {} s at {} Hz is {} samples: the record must hold {} whole periods \
                 of an integer number (≥ 4) of samples",
                self.period_s(),
                self.fs_hz,
                per_samples,
                self.periods
            ));
        }
        let (lo, hi) = self.band_hz;
        if !(lo.is_finite() && hi.is_finite() && lo >= 0.0 && hi > lo) {
            return bad(format!(
                "band must satisfy 0 ≤ f_lo < f_hi, got [{lo}, {hi}] Hz"
            ));
        }
        if !(self.nyquist_guard.is_finite() && (0.0..1.0).contains(&self.nyquist_guard)) {
            return bad(format!(
                "Nyquist guard must lie in [0, 1), got {}",
                self.nyquist_guard
            ));
        }
        if !(self.alpha_offset.is_finite() && self.alpha_offset >= 0.0) {
            return bad(format!(
                "alpha offset must be ≥ 0 (α_1 ≤ 1), got {}",
                self.alpha_offset
            ));
        }
        if !(self.epsilon.is_finite() && self.epsilon > 0.0) {
            return bad(format!(
                "certificate tolerance ε must be positive, got {}",
                self.epsilon
            ));
        }
        if !(self.merge.rel.is_finite()
            && self.merge.rel >= 0.0
            && self.merge.abs_hz.is_finite()
            && self.merge.abs_hz >= 0.0)
        {
            return bad("merge distances must be finite and ≥ 0".into());
        }
        if let Some(m) = self.exclusions.mains {
            if !(m.fundamental_hz.is_finite()
                && m.fundamental_hz > 0.0
                && m.half_width_hz.is_finite()
                && m.half_width_hz >= 0.0)
            {
                return bad(format!(
                    "mains exclusion needs a positive fundamental and a width ≥ 0, got {m:?}"
                ));
            }
        }
        for b in &self.exclusions.bands {
            if !(b.center_hz.is_finite() && b.half_width_hz.is_finite() && b.half_width_hz >= 0.0) {
                return bad(format!(
                    "exclusion needs a finite centre and a width ≥ 0, got {b:?}"
                ));
            }
        }
        for l in &self.initial {
            if !(l.freq_hz.is_finite() && l.power_frac.is_finite() && l.power_frac >= 0.0) {
                return bad(format!("initial design line needs a finite frequency and power fraction ≥ 0, got {l:?}"));
            }
        }
        if !self.initial.is_empty() && self.initial.iter().map(|l| l.power_frac).sum::<f64>() <= 0.0
        {
            return bad("initial design has zero total power".into());
        }
        match &self.noise {
            NoiseSpectrum::White { std } => {
                if !(std.is_finite() && *std > 0.0) {
                    return bad(format!("noise std must be positive, got {std}"));
                }
            }
            NoiseSpectrum::Measured { freq_hz, variance } => {
                if freq_hz.is_empty()
                    || freq_hz.len() != variance.len()
                    || variance.iter().any(|v| !(v.is_finite() && *v > 0.0))
                    || freq_hz.iter().any(|f| !f.is_finite())
                    || freq_hz.windows(2).any(|w| w[1] <= w[0])
                {
                    return bad(
                        "measured noise spectrum needs ascending frequencies and as many positive variances".into(),
                    );
                }
            }
        }
        Ok(())
    }
}

/// Why no design (or no signal) could be produced.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum DesignError {
    #[error("invalid design configuration: {0}")]
    InvalidConfig(String),
    #[error(
        "no candidate line left in [{f_lo_hz}, {f_hi_hz}] Hz on the {spacing_hz} Hz grid after \
         the Nyquist guard and the exclusions"
    )]
    EmptyBand {
        f_lo_hz: f64,
        f_hi_hz: f64,
        spacing_hz: f64,
    },
    #[error(
        "only {have} candidate line(s) in the band after exclusions; a Prony series with \
         {params} parameters needs at least {need} distinct lines"
    )]
    TooFewCandidates {
        have: usize,
        need: usize,
        params: usize,
    },
    #[error(
        "the Fisher information of the design is singular: its lines cannot separate the \
         parameters (too few lines, or a degenerate prior model)"
    )]
    SingularInformation,
    #[error(
        "the design is not certified D-optimal after {iterations} iterations: \
         max d(f)/p = {d_max_over_p:.4} > 1 + {epsilon}"
    )]
    NotCertified {
        iterations: usize,
        d_max_over_p: f64,
        epsilon: f64,
        design: Box<Design>,
    },
    #[error("the prior model is not a physical creep compliance (positive J_i and τ_i): {0:?}")]
    NonPhysicalModel(crate::prony::PronySeries),
    #[error("invalid signal settings: {0}")]
    InvalidSignal(String),
    #[error("design loop used out of order: {0}")]
    LoopMisuse(String),
    #[error("the estimate has {got} retardation terms but the loop's model has {expected}")]
    OrderMismatch { expected: usize, got: usize },
}

#[cfg(test)]
mod tests;
