//! The paper's estimator: ARX least squares (eqs. 4–7), then d2c and partial fractions.
//!
//! `y[l] + Σ a_i y[l−i] = Σ_{i=0..n} b_i u[l−i]` (n = na = order, nb = n + 1 with direct
//! feed-through) is linear in `θ = [a, b]` and solved by least squares; the Prony parameters
//! follow from [`crate::discrete::d2c`]. Exact on noise-free data. With noise on the output
//! the regressors contain noisy past outputs and the estimate is biased — the failure of the
//! paper's Table I, Case 2. The covariance is the least-squares one, mapped by the delta
//! method; it describes the scatter, not that bias.

use super::{check_signals, Diagnostics, Estimate, EstimateError, IntervalKind, Method, Z95};
use crate::discrete::{d2c_by_pole, DiscreteTf};
use nalgebra::{DMatrix, DVector};

/// The least-squares ARX model before any continuous-time interpretation.
#[derive(Debug, Clone)]
pub struct ArxFit {
    pub tf: DiscreteTf,
    /// `θ = [a1..an, b0..bn]`.
    pub theta: Vec<f64>,
    /// Least-squares covariance of θ.
    pub cov_theta: DMatrix<f64>,
    /// Residual sum of squares and its degrees of freedom.
    pub rss: f64,
    pub dof: usize,
    pub rows: usize,
}

/// Solves the ARX least-squares problem (eqs. 6–7) of order `order`.
pub fn arx_least_squares(
    u: &[f64],
    y: &[f64],
    fs_hz: f64,
    order: usize,
) -> Result<ArxFit, EstimateError> {
    let n = order;
    if n == 0 {
        return Err(EstimateError::Order(0));
    }
    check_signals(u, y)?;
    let n_theta = 2 * n + 1;
    let rows = u.len().saturating_sub(n);
    if rows < 2 * n_theta {
        return Err(EstimateError::TooFewSamples {
            samples: u.len(),
            params: n_theta,
        });
    }
    // Column scaling keeps the regression well conditioned whatever the units of u and y.
    let su = rms(u).max(1e-300);
    let sy = rms(y).max(1e-300);
    let phi = DMatrix::from_fn(rows, n_theta, |r, c| {
        let l = r + n;
        if c < n {
            -y[l - 1 - c] / sy
        } else {
            u[l - (c - n)] / su
        }
    });
    let target = DVector::from_fn(rows, |r, _| y[r + n] / sy);
    let svd = phi.clone().svd(true, true);
    let smax = svd.singular_values.max();
    if svd.singular_values.min() <= 1e-13 * smax {
        return Err(EstimateError::NoExcitation(
            "the ARX regressors are linearly dependent (input not persistently exciting)".into(),
        ));
    }
    let theta_s = svd
        .solve(&target, 0.0)
        .map_err(|e| EstimateError::NoExcitation(e.to_string()))?;
    let resid = &target - &phi * &theta_s;
    let dof = rows - n_theta;
    let s2 = resid.norm_squared() / dof as f64;
    let v = svd.v_t.as_ref().expect("SVD computed with V").transpose();
    let inv_s2 = svd.singular_values.map(|s| 1.0 / (s * s));
    let cov_s = &v * DMatrix::from_diagonal(&inv_s2) * v.transpose() * s2;
    // Undo the column scaling: a_i = θ_i, b_i = θ_i·sy/su.
    let unscale: Vec<f64> = (0..n_theta)
        .map(|c| if c < n { 1.0 } else { sy / su })
        .collect();
    let theta: Vec<f64> = (0..n_theta).map(|c| theta_s[c] * unscale[c]).collect();
    let cov_theta = DMatrix::from_fn(n_theta, n_theta, |i, j| {
        cov_s[(i, j)] * unscale[i] * unscale[j]
    });
    Ok(ArxFit {
        tf: to_tf(&theta, n, fs_hz),
        theta,
        cov_theta,
        rss: resid.norm_squared() * sy * sy,
        dof,
        rows,
    })
}

fn to_tf(th: &[f64], n: usize, fs_hz: f64) -> DiscreteTf {
    DiscreteTf {
        a: std::iter::once(1.0)
            .chain(th[..n].iter().copied())
            .collect(),
        b: th[n..].to_vec(),
        fs_hz,
    }
}

/// Fits an ARX model of order `order` and maps it to a Prony series.
pub fn fit_arx(u: &[f64], y: &[f64], fs_hz: f64, order: usize) -> Result<Estimate, EstimateError> {
    let n = order;
    let fit = arx_least_squares(u, y, fs_hz, order)?;
    let ArxFit {
        theta,
        cov_theta,
        rss,
        dof,
        rows,
        ..
    } = fit;
    let n_theta = theta.len();
    let s2 = rss / dof as f64;
    let to_tf = |th: &[f64]| to_tf(th, n, fs_hz);
    let model = d2c_by_pole(&to_tf(&theta))?;
    let values = model.to_vec();
    // Delta method: numerical Jacobian of the d2c map.
    let mut jac = DMatrix::<f64>::zeros(n_theta, n_theta);
    let mut jac_ok = true;
    for c in 0..n_theta {
        let h = 1e-7 * theta[c].abs().max(1e-12);
        let mut up = theta.clone();
        let mut dn = theta.clone();
        up[c] += h;
        dn[c] -= h;
        match (d2c_by_pole(&to_tf(&up)), d2c_by_pole(&to_tf(&dn))) {
            (Ok(a), Ok(b)) => {
                for (r, (va, vb)) in a.to_vec().iter().zip(b.to_vec()).enumerate() {
                    jac[(r, c)] = (va - vb) / (2.0 * h);
                }
            }
            _ => jac_ok = false,
        }
    }
    let mut warnings = Vec::new();
    let covariance = if jac_ok {
        &jac * cov_theta * jac.transpose()
    } else {
        warnings.push(
            "the d2c map is not differentiable here (poles about to turn complex): no intervals"
                .into(),
        );
        DMatrix::from_element(n_theta, n_theta, f64::NAN)
    };
    if !model.is_physical() {
        warnings.push(
            "not a physical creep compliance (a negative J, τ or instantaneous compliance)".into(),
        );
    }
    let std: Vec<f64> = (0..n_theta)
        .map(|i| covariance[(i, i)].max(0.0).sqrt())
        .collect();
    let ci95 = values
        .iter()
        .zip(&std)
        .map(|(v, s)| [v - Z95 * s, v + Z95 * s])
        .collect();
    let diagnostics = Diagnostics {
        cost: rss,
        dof,
        cost_per_dof: s2,
        iterations: 0,
        observations: rows,
        noise_free: s2 <= 1e-24 * rms(y).powi(2),
        warnings,
    };
    Ok(Estimate {
        method: Method::Arx,
        model,
        covariance,
        log_covariance: None,
        std,
        ci95,
        interval: IntervalKind::Symmetric,
        diagnostics,
    })
}

fn rms(x: &[f64]) -> f64 {
    (x.iter().map(|v| v * v).sum::<f64>() / x.len() as f64).sqrt()
}
