//! From a recording to a Prony fit: the offline path of `viscoprobe fit`.
//!
//! [`prepare`] turns a [`Recording`] into the linear pair (u, y) over the in-contact window:
//! the deflection baseline from the free approach, the contact point where the force leaves
//! the baseline noise, the force `F = K·C·(v − v₀)`, and the indentation — from the hard
//! reference channel where there is one (the spec's `C·(v_ref − v)`), otherwise from the
//! actuator position (the position sensor if recorded, else the commanded drive) minus the
//! lever's deflection. [`fit_recording`] then fits the time-domain output-error model (any
//! excitation: multisine, ramp, hold), discretised with a first-order hold (continuous physics
//! under a force linear between samples), for a fixed number of terms or picks the order by
//! the Bayesian information criterion.

use crate::estimate::time_domain::{fit_time_domain, TimeFitOptions};
use crate::estimate::{Estimate, EstimateError};
use crate::recording::Recording;
use thiserror::Error;

/// Why a recording could not be fitted.
#[derive(Debug, Error)]
pub enum FitError {
    #[error("no contact found: the force never leaves the baseline noise ({noise_n:.3e} N rms)")]
    NoContact { noise_n: f64 },
    #[error("the recording has no drive in nm and no position sensor: set [piezo] gain_nm_per_v or record a reference channel")]
    NoIndentation,
    #[error("the in-contact window has only {0} samples")]
    TooShort(usize),
    #[error("estimation: {0}")]
    Estimate(#[from] EstimateError),
}

/// The in-contact (u, y) pair of a recording.
#[derive(Debug, Clone)]
pub struct Prepared {
    pub u: Vec<f64>,
    pub y: Vec<f64>,
    pub fs_hz: f64,
    /// Sample index of the contact point and end of the fitted window (exclusive).
    pub contact_index: usize,
    pub end_index: usize,
    /// Free-lever deflection, V, and its noise, V rms.
    pub baseline_v: f64,
    pub baseline_noise_v: f64,
    /// Where the indentation came from: `reference`, `measured_height` or `drive`.
    pub indentation_source: &'static str,
}

fn median(x: &mut [f64]) -> f64 {
    x.sort_by(f64::total_cmp);
    x[x.len() / 2]
}

/// Baseline, contact point, force and indentation; the window ends where a segment table in
/// `[notes]` says the retract starts (Lee–Radok holds while the contact grows or holds), or at
/// the force maximum's last in-contact sample otherwise.
pub fn prepare(rec: &Recording) -> Result<Prepared, FitError> {
    let n = rec.len();
    let k = rec.meta.cantilever.spring_constant_n_per_m;
    let c_m = rec.meta.cantilever.deflection_sensitivity_nm_per_v * 1e-9;
    // A first baseline from the first 2 % of the record (the tip is free there in any sane
    // recording), contact from it, then the baseline again from everything before contact.
    let baseline_of = |upto: usize| {
        let upto = upto.clamp(2, n);
        let mut v: Vec<f64> = rec.deflection_v[..upto].to_vec();
        let b = median(&mut v);
        let mut dev: Vec<f64> = rec.deflection_v[..upto]
            .iter()
            .map(|x| (x - b).abs())
            .collect();
        (b, 1.4826 * median(&mut dev))
    };
    let locate =
        |baseline_v: f64, noise_v: f64| -> Result<(usize, Vec<f64>, usize, f64), FitError> {
            let force: Vec<f64> = rec
                .deflection_v
                .iter()
                .map(|v| k * c_m * (v - baseline_v))
                .collect();
            let fmax = force.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let threshold = (5.0 * k * c_m * noise_v).max(0.02 * fmax);
            let imax = force.iter().position(|f| *f == fmax).unwrap_or(0);
            let above =
                force[..=imax]
                    .iter()
                    .position(|f| *f > threshold)
                    .ok_or(FitError::NoContact {
                        noise_n: k * c_m * noise_v,
                    })?;
            // Walk back to where the force last sat within the baseline noise.
            let floor = k * c_m * noise_v.max(1e-12);
            let contact = force[..above]
                .iter()
                .rposition(|f| *f <= floor)
                .map_or(above, |i| i + 1);
            Ok((contact, force, imax, threshold))
        };
    let (b0, s0) = baseline_of((n / 50).max(20));
    let (c0, _, _, _) = locate(b0, s0)?;
    let (baseline_v, noise_v) = baseline_of(c0.saturating_sub(c0 / 20).max(20));
    let (contact, force, imax, threshold) = locate(baseline_v, noise_v)?;
    let retract_start = rec
        .meta
        .notes
        .as_ref()
        .and_then(|t| t.get("segments"))
        .and_then(|s| s.as_array())
        .and_then(|segs| {
            segs.iter().find_map(|s| {
                let t = s.as_table()?;
                (t.get("kind")?.as_str()?.eq_ignore_ascii_case("retract"))
                    .then(|| t.get("start_index")?.as_integer())?
            })
        })
        .map(|i| i as usize);
    let end = retract_start.unwrap_or_else(|| {
        // Contact lost after the maximum; the final unloading (where the contact shrinks and
        // Lee–Radok no longer holds) is the run of non-increasing drive that leads there.
        let lost = force
            .iter()
            .enumerate()
            .skip(imax)
            .find(|(_, f)| **f < threshold)
            .map_or(n, |(i, _)| i);
        let drive = rec.drive.values();
        let mut i = lost.min(n - 1);
        while i > contact + 1 && drive[i - 1] >= drive[i] {
            i -= 1;
        }
        i
    });
    let end = end.min(n);
    if end <= contact + 50 {
        return Err(FitError::TooShort(end.saturating_sub(contact)));
    }
    let (h, source): (Vec<f64>, &'static str) = if let Some(r) = &rec.reference_deflection_v {
        (
            (contact..end)
                .map(|i| c_m * (r[i] - rec.deflection_v[i]))
                .collect(),
            "reference",
        )
    } else {
        let (z, src) = match (&rec.measured_height_nm, rec.drive_nm()) {
            (Some(m), _) if m.iter().all(|v| v.is_finite()) => (m.clone(), "measured_height"),
            (_, Some(d)) => (d, "drive"),
            _ => return Err(FitError::NoIndentation),
        };
        let z0 = z[contact];
        (
            (contact..end)
                .map(|i| (z[i] - z0) * 1e-9 - c_m * (rec.deflection_v[i] - baseline_v))
                .collect(),
            src,
        )
    };
    let contact_model = rec.meta.contact();
    let u = force[contact..end]
        .iter()
        .map(|&f| contact_model.u_from_force(f.max(0.0)))
        .collect();
    let y = h
        .iter()
        .map(|&x| contact_model.y_from_indentation(x))
        .collect();
    Ok(Prepared {
        u,
        y,
        fs_hz: rec.sample_rate_hz,
        contact_index: contact,
        end_index: end,
        baseline_v,
        baseline_noise_v: noise_v,
        indentation_source: source,
    })
}

/// How many Prony terms to fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Terms {
    Fixed(usize),
    /// Try 1..=max and keep the lowest BIC.
    Auto {
        max: usize,
    },
}

/// One candidate order of `--terms auto`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrderCandidate {
    pub terms: usize,
    /// `N·ln(RSS/N) + p·ln N`; lower is better.
    pub bic: f64,
    pub nrmse: f64,
}

/// A fitted recording.
#[derive(Debug, Clone)]
pub struct RecordingFit {
    pub prepared: Prepared,
    pub estimate: Estimate,
    /// Normalised RMS error of the fit, `‖y − ŷ‖/‖y − ȳ‖`.
    pub nrmse: f64,
    /// Lag-1 autocorrelation of the residuals (≈ 0 for white residuals).
    pub residual_lag1: f64,
    pub candidates: Vec<OrderCandidate>,
}

/// Fits a recording.
pub fn fit_recording(rec: &Recording, terms: Terms) -> Result<RecordingFit, FitError> {
    let prepared = prepare(rec)?;
    let (u, y, fs) = (&prepared.u, &prepared.y, prepared.fs_hz);
    let orders: Vec<usize> = match terms {
        Terms::Fixed(n) => vec![n],
        Terms::Auto { max } => (1..=max.max(1)).collect(),
    };
    let ym = y.iter().sum::<f64>() / y.len() as f64;
    let syy: f64 = y.iter().map(|v| (v - ym).powi(2)).sum();
    let n_obs = y.len() as f64;
    let mut best: Option<(f64, Estimate)> = None;
    let mut candidates = Vec::new();
    let mut last_err = None;
    for n in orders {
        let mut opts = TimeFitOptions::new(n);
        opts.sampling = crate::discrete::Sampling::FirstOrderHold { fs_hz: fs };
        match fit_time_domain(u, y, fs, &opts) {
            Ok(est) => {
                let scale = (y.iter().map(|v| v * v).sum::<f64>() / n_obs).sqrt();
                let rss = est.diagnostics.cost * scale * scale;
                let p = (2 * n + 1) as f64;
                let bic = n_obs * (rss / n_obs).max(1e-300).ln() + p * n_obs.ln();
                candidates.push(OrderCandidate {
                    terms: n,
                    bic,
                    nrmse: (rss / syy).sqrt(),
                });
                if best.as_ref().is_none_or(|(b, _)| bic < *b) {
                    best = Some((bic, est));
                }
            }
            Err(e) => last_err = Some(e),
        }
    }
    let Some((_, estimate)) = best else {
        return Err(FitError::Estimate(
            last_err.unwrap_or(EstimateError::NoStart),
        ));
    };
    let mut yhat: Vec<f64> = u.iter().map(|x| estimate.model.j0_per_pa * x).collect();
    for t in &estimate.model.terms {
        for (yh, x) in yhat
            .iter_mut()
            .zip(crate::discrete::foh_highpass(u, t.tau_s, fs))
        {
            *yh -= t.j_per_pa * x;
        }
    }
    let r: Vec<f64> = y.iter().zip(&yhat).map(|(a, b)| a - b).collect();
    let rss: f64 = r.iter().map(|v| v * v).sum();
    let lag1 = r.windows(2).map(|w| w[0] * w[1]).sum::<f64>() / rss.max(1e-300);
    Ok(RecordingFit {
        nrmse: (rss / syy).sqrt(),
        residual_lag1: lag1,
        prepared,
        estimate,
        candidates,
    })
}
