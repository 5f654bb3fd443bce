//! Output-error fit in the time domain, for inputs that are not periodic (ramps, holds,
//! steps, stress-relaxation records).
//!
//! The model output is simulated exactly as the Tustin model does it
//! ([`crate::discrete::simulate_tustin`]): `ŷ = J0·u − Σ Ji·HP_τi(u)`, starting from the
//! steady state of a constant input `u[0]`. The fit minimises `Σ (y − ŷ)²` over
//! log-parameters; the noise variance comes from the residuals, so the intervals assume white
//! output noise (the diagnostics report the lag-1 residual correlation to check that).

use super::lm::{Evaluation, LmOptions};
use super::start::{grid_starts, log_grid, with_prior};
use super::{check_signals, solve_from_starts, Diagnostics, Estimate, EstimateError, Method};
use crate::discrete::{foh_highpass, tustin_highpass, Sampling};
use crate::linalg::spd_inverse;
use crate::prony::PronySeries;
use nalgebra::{DMatrix, DVector};

/// Settings of the time-domain fit.
#[derive(Debug, Clone)]
pub struct TimeFitOptions {
    pub order: usize,
    /// How the model is discretised: Tustin (the paper's simulations) or first-order hold
    /// (continuous physics under a force linear between samples: real data, the twin).
    /// `Continuous` is treated as first-order hold; the rate inside is ignored (the fit's
    /// `fs_hz` is used).
    pub sampling: Sampling,
    pub grid_size: usize,
    pub starts: usize,
    pub extra_start: Option<PronySeries>,
    pub lm: LmOptions,
}

impl TimeFitOptions {
    pub fn new(order: usize) -> Self {
        Self {
            order,
            sampling: Sampling::Tustin { fs_hz: 0.0 },
            grid_size: 16,
            starts: 6,
            extra_start: None,
            lm: LmOptions::default(),
        }
    }
}

/// RMS of the output: the unit the residuals are scaled to.
fn output_scale(y: &[f64]) -> f64 {
    (y.iter().map(|v| v * v).sum::<f64>() / y.len().max(1) as f64)
        .sqrt()
        .max(1e-300)
}

/// The Prony term's high-pass response to `x` in the sampling model's discretisation.
fn highpass(sampling: Sampling, x: &[f64], tau: f64, fs_hz: f64) -> Vec<f64> {
    match sampling {
        Sampling::Tustin { .. } => tustin_highpass(x, tau, fs_hz),
        Sampling::FirstOrderHold { .. } | Sampling::Continuous => foh_highpass(x, tau, fs_hz),
    }
}

/// The start values of [`fit_time_domain`] (log-parameters, best first): variable projection
/// over a τ grid from 2 samples to half the record, plus `opts.extra_start`.
pub fn time_domain_starts(
    u: &[f64],
    y: &[f64],
    fs_hz: f64,
    opts: &TimeFitOptions,
) -> Result<Vec<Vec<f64>>, EstimateError> {
    let n = opts.order;
    let len = u.len();
    let scale = output_scale(y);
    let duration = len as f64 / fs_hz;
    let taus = log_grid(2.0 / fs_hz, duration / 2.0, opts.grid_size.max(n));
    let target: Vec<f64> = y.iter().map(|v| v / scale).collect();
    let j0_col: Vec<f64> = u.iter().map(|v| v / scale).collect();
    let columns: Vec<Vec<f64>> = taus
        .iter()
        .map(|&t| {
            highpass(opts.sampling, u, t, fs_hz)
                .iter()
                .map(|v| -v / scale)
                .collect()
        })
        .collect();
    with_prior(
        grid_starts(&target, &j0_col, &columns, &taus, n, opts.starts),
        opts.extra_start.as_ref(),
        n,
    )
}

/// Fits a Prony series to `u → y` sampled at `fs_hz`.
pub fn fit_time_domain(
    u: &[f64],
    y: &[f64],
    fs_hz: f64,
    opts: &TimeFitOptions,
) -> Result<Estimate, EstimateError> {
    let n = opts.order;
    if n == 0 {
        return Err(EstimateError::Order(0));
    }
    check_signals(u, y)?;
    let n_params = 2 * n + 1;
    let len = u.len();
    if len < 4 * n_params {
        return Err(EstimateError::TooFewSamples {
            samples: len,
            params: n_params,
        });
    }
    let u_range = u.iter().fold(f64::NEG_INFINITY, |a, &b| a.max(b))
        - u.iter().fold(f64::INFINITY, |a, &b| a.min(b));
    if u_range <= 0.0 {
        return Err(EstimateError::NoExcitation(
            "the input is constant over the record".into(),
        ));
    }
    let scale = output_scale(y);
    let highpass = |x: &[f64], tau: f64, fs: f64| highpass(opts.sampling, x, tau, fs);
    let eval = |p: &[f64]| -> Evaluation {
        if p.iter().any(|v| !v.is_finite() || v.abs() > 700.0) {
            return None;
        }
        let j0 = p[0].exp();
        let mut yhat: Vec<f64> = u.iter().map(|x| j0 * x).collect();
        let mut jac = DMatrix::zeros(len, p.len());
        for (t, x) in u.iter().enumerate() {
            jac[(t, 0)] = -j0 * x / scale;
        }
        const H: f64 = 1e-5;
        for i in 0..n {
            let (ji, tau) = (p[1 + i].exp(), p[1 + n + i].exp());
            let hp = highpass(u, tau, fs_hz);
            let hp_up = highpass(u, tau * H.exp(), fs_hz);
            let hp_dn = highpass(u, tau * (-H).exp(), fs_hz);
            for t in 0..len {
                yhat[t] -= ji * hp[t];
                jac[(t, 1 + i)] = ji * hp[t] / scale;
                jac[(t, 1 + n + i)] = ji * (hp_up[t] - hp_dn[t]) / (2.0 * H) / scale;
            }
        }
        let r = DVector::from_fn(len, |t, _| (y[t] - yhat[t]) / scale);
        Some((r, jac))
    };

    let starts = time_domain_starts(u, y, fs_hz, opts)?;
    let (best, rcond) = solve_from_starts(&starts, eval, opts.lm)?;
    let dof = len - n_params;
    let s2 = best.cost / dof as f64;
    let cov = spd_inverse(&best.jtj).ok_or(EstimateError::IllConditioned { rcond })? * s2;
    let r = &best.residuals;
    let lag1 = (1..len).map(|t| r[t] * r[t - 1]).sum::<f64>() / best.cost.max(1e-300);
    let mut warnings = Vec::new();
    if lag1.abs() > 3.0 / (len as f64).sqrt() {
        warnings.push(format!(
            "residuals are correlated (lag-1 correlation {lag1:.3}); intervals assume white noise and may be too narrow"
        ));
    }
    let diagnostics = Diagnostics {
        cost: best.cost,
        dof,
        cost_per_dof: s2,
        iterations: best.iterations,
        observations: len,
        noise_free: s2 <= 1e-24,
        warnings,
    };
    Ok(Estimate::from_log_fit(
        Method::TimeOutputError,
        &best.params,
        cov,
        diagnostics,
    ))
}
