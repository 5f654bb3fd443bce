//! Estimators of the Prony creep compliance from (u, y) data.
//!
//! Three estimators share one result type, [`Estimate`]:
//!
//! * [`arx`] — the paper's equation-error least squares (eqs. 4–7) followed by the exact
//!   d2c map of [`crate::discrete::d2c`]. Exact on noise-free data, biased under output
//!   noise; kept as the reference method.
//! * [`frequency`] — maximum likelihood for periodic (multisine) data in the frequency domain:
//!   weighted nonlinear least squares on the excited lines, with the noise (co)variances
//!   measured from period-to-period variation. This is the estimator that reaches the
//!   Cramér–Rao bound.
//! * [`time_domain`] — output-error fit of the same model for non-periodic inputs
//!   (ramps, holds, steps).
//!
//! The nonlinear fits work on log-parameters (all Prony parameters of a creep compliance
//! are positive), are started from a variable-projection grid search over τ ([`start`]),
//! and are solved with Levenberg–Marquardt ([`lm`]). Each returns covariance and 95 %
//! intervals, or an [`EstimateError`] that says why it could not.

pub mod arx;
pub mod frequency;
pub mod lm;
pub mod start;
pub mod time_domain;

use crate::prony::PronySeries;
use nalgebra::DMatrix;
use serde::Serialize;
use thiserror::Error;

/// Which estimator produced an [`Estimate`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// The paper's ARX least squares.
    Arx,
    /// Frequency-domain maximum likelihood on periodic data.
    FrequencyMl,
    /// Time-domain output error.
    TimeOutputError,
}

/// How the 95 % intervals were formed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum IntervalKind {
    /// `θ ± 1.96σ` (ARX, whose parameters may come out negative).
    Symmetric,
    /// `θ·exp(±1.96σ_ln)`: the fit is in log-parameters, so the interval is too.
    LogNormal,
}

/// Estimated Prony parameters with their uncertainty.
#[derive(Debug, Clone)]
pub struct Estimate {
    pub method: Method,
    /// The estimate, terms slowest first.
    pub model: PronySeries,
    /// Covariance of `[J0, J1..Jn, τ1..τn]` in SI units (delta method for log fits).
    pub covariance: DMatrix<f64>,
    /// Covariance of the log-parameters (log fits only).
    pub log_covariance: Option<DMatrix<f64>>,
    /// Standard deviations in SI units, canonical order.
    pub std: Vec<f64>,
    /// 95 % confidence intervals in SI units, canonical order.
    pub ci95: Vec<[f64; 2]>,
    pub interval: IntervalKind,
    pub diagnostics: Diagnostics,
}

/// What a fit says about itself.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Diagnostics {
    /// Final value of the weighted cost (sum of squared normalised residuals).
    pub cost: f64,
    /// Degrees of freedom of the residuals (real observations minus parameters).
    pub dof: usize,
    /// `cost/dof`: ≈ 1 when the model and the noise estimate agree.
    pub cost_per_dof: f64,
    /// Iterations of the nonlinear solver (0 for linear methods).
    pub iterations: usize,
    /// Number of excited lines (frequency domain) or samples (time domain) used.
    pub observations: usize,
    /// True when the data carry no measurable noise; intervals then come from residuals.
    pub noise_free: bool,
    /// Plain-language remarks (unphysical values, noise assumptions).
    pub warnings: Vec<String>,
}

impl Estimate {
    /// Parameters in canonical order, SI units.
    pub fn values(&self) -> Vec<f64> {
        self.model.to_vec()
    }

    /// Canonical parameter names: `J0, J1.., tau1..`.
    pub fn names(&self) -> Vec<String> {
        PronySeries::param_names(self.model.order())
    }

    /// Adds a systematic uncertainty: `delta_log[i]` is the (fully correlated) shift of
    /// `ln θ_i` that one standard deviation of a calibration quantity causes. Its outer product
    /// joins the covariance and the intervals widen accordingly. Log fits only; others are
    /// returned unchanged.
    pub fn with_systematic(mut self, delta_log: &[f64], what: &str) -> Self {
        let Some(lcov) = self.log_covariance.as_mut() else {
            return self;
        };
        let n = lcov.nrows();
        if delta_log.len() != n || delta_log.iter().any(|d| !d.is_finite()) {
            return self;
        }
        for i in 0..n {
            for j in 0..n {
                lcov[(i, j)] += delta_log[i] * delta_log[j];
            }
        }
        let values = self.model.to_vec();
        let lcov = lcov.clone();
        self.covariance = DMatrix::from_fn(n, n, |i, j| lcov[(i, j)] * values[i] * values[j]);
        let log_std: Vec<f64> = (0..n).map(|i| lcov[(i, i)].max(0.0).sqrt()).collect();
        self.std = values.iter().zip(&log_std).map(|(v, s)| v * s).collect();
        self.ci95 = values
            .iter()
            .zip(&log_std)
            .map(|(v, s)| [v * (-Z95 * s).exp(), v * (Z95 * s).exp()])
            .collect();
        self.diagnostics.warnings.push(format!(
            "intervals include the calibration uncertainty of {what}"
        ));
        self
    }

    /// Builds an estimate from a log-parameter fit.
    pub(crate) fn from_log_fit(
        method: Method,
        log_params: &[f64],
        log_covariance: DMatrix<f64>,
        diagnostics: Diagnostics,
    ) -> Self {
        let n = (log_params.len() - 1) / 2;
        let mut values: Vec<f64> = log_params.iter().map(|x| x.exp()).collect();
        let mut lcov = log_covariance;
        // Sort the terms slowest first, permuting the covariance with them.
        let mut idx: Vec<usize> = (0..n).collect();
        idx.sort_by(|&a, &b| values[1 + n + b].total_cmp(&values[1 + n + a]));
        let perm: Vec<usize> = std::iter::once(0)
            .chain(idx.iter().map(|i| 1 + i))
            .chain(idx.iter().map(|i| 1 + n + i))
            .collect();
        values = perm.iter().map(|&i| values[i]).collect();
        lcov = DMatrix::from_fn(lcov.nrows(), lcov.ncols(), |i, j| lcov[(perm[i], perm[j])]);
        let covariance = DMatrix::from_fn(lcov.nrows(), lcov.ncols(), |i, j| {
            lcov[(i, j)] * values[i] * values[j]
        });
        let log_std: Vec<f64> = (0..values.len())
            .map(|i| lcov[(i, i)].max(0.0).sqrt())
            .collect();
        let std = values.iter().zip(&log_std).map(|(v, s)| v * s).collect();
        let ci95 = values
            .iter()
            .zip(&log_std)
            .map(|(v, s)| [v * (-Z95 * s).exp(), v * (Z95 * s).exp()])
            .collect();
        let model = PronySeries::from_vec(&values);
        Self {
            method,
            model,
            covariance,
            log_covariance: Some(lcov),
            std,
            ci95,
            interval: IntervalKind::LogNormal,
            diagnostics,
        }
    }
}

/// Two-sided 95 % quantile of the standard normal.
pub const Z95: f64 = 1.959_963_984_540_054;

/// Why an estimator refused to return an estimate.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum EstimateError {
    #[error(
        "under-determined: {lines} excited line(s) give {observations} real observations \
         for {params} parameters; a Prony series of order {order} needs at least {needed} lines"
    )]
    UnderDetermined {
        lines: usize,
        observations: usize,
        params: usize,
        order: usize,
        needed: usize,
    },
    #[error("not enough samples: {samples} for {params} parameters")]
    TooFewSamples { samples: usize, params: usize },
    #[error("input and output differ in length ({input} vs {output} samples)")]
    LengthMismatch { input: usize, output: usize },
    #[error("{samples} samples cannot be split into {periods} whole periods")]
    NotWholePeriods { samples: usize, periods: usize },
    #[error("the input has no excitation: {0}")]
    NoExcitation(String),
    #[error("data contain a non-finite value at sample {0}")]
    NonFinite(usize),
    #[error(
        "ill-conditioned: the information matrix has reciprocal condition {rcond:.1e}; the data \
         cannot separate the parameters (too few or badly placed lines, or too many terms)"
    )]
    IllConditioned { rcond: f64 },
    #[error(
        "not identified: the best fit (cost {cost:.4e}) has an information matrix of \
         reciprocal condition {rcond:.1e}; the data cannot separate its parameters (too many terms)"
    )]
    Unidentified {
        rcond: f64,
        /// The optimum's cost, as the estimator defines it (for order selection).
        cost: f64,
        /// The optimum (terms in the solver's order).
        model: PronySeries,
    },
    #[error("no convergence after {iterations} iterations (cost {cost:.4e})")]
    NoConvergence { iterations: usize, cost: f64 },
    #[error("no physical start value found: every τ-grid candidate gave a negative compliance")]
    NoStart,
    #[error("the ARX model has no Prony series behind it: {0}")]
    NotProny(#[from] crate::discrete::D2cError),
    #[error("model order must be at least 1 (got {0})")]
    Order(usize),
}

/// Checks an input/output pair: same length, every value finite.
pub(crate) fn check_signals(u: &[f64], y: &[f64]) -> Result<(), EstimateError> {
    if u.len() != y.len() {
        return Err(EstimateError::LengthMismatch {
            input: u.len(),
            output: y.len(),
        });
    }
    check_finite(u)?;
    check_finite(y)
}

/// Levenberg–Marquardt from every start, the best converged result kept, and refused when
/// its Gauss–Newton matrix cannot separate the parameters.
pub(crate) fn solve_from_starts(
    starts: &[Vec<f64>],
    eval: impl Fn(&[f64]) -> lm::Evaluation,
    opts: lm::LmOptions,
) -> Result<(lm::LmResult, f64), EstimateError> {
    let best = lm::best_of(starts, eval, opts)
        .map_err(|(iterations, cost)| EstimateError::NoConvergence { iterations, cost })?;
    let rcond = crate::linalg::scaled_rcond(&best.jtj);
    if rcond < crate::linalg::SINGULAR_RCOND {
        let v: Vec<f64> = best.params.iter().map(|x| x.exp()).collect();
        return Err(EstimateError::Unidentified {
            rcond,
            cost: best.cost,
            model: PronySeries::from_vec(&v),
        });
    }
    Ok((best, rcond))
}

/// Checks a signal for NaN/inf.
pub(crate) fn check_finite(x: &[f64]) -> Result<(), EstimateError> {
    match x.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(EstimateError::NonFinite(i)),
        None => Ok(()),
    }
}
