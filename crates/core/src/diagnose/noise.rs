//! The noise floor of a recording, measured where the lever is free.
//!
//! Every significance in a diagnosis is judged against this floor, so it must be measured, not
//! assumed white: detectors have 1/f noise, and a model that "explains" 1/f noise with drift
//! would be a false positive. Where the lever is free (before contact) the deflection is
//! noise plus whatever is deterministic there: an offset, a slope (drift, or drag during a
//! constant-velocity approach) and mains lines with their harmonics. Those are removed by
//! least squares first (the floor must not contain what the diagnosis looks for), then an
//! autoregressive model, its order chosen by AIC, gives the whitening filter and the
//! whitened σ.

use super::model::MAINS_HARMONICS;

/// The measured noise floor.
#[derive(Debug, Clone)]
pub struct NoiseModel {
    /// Whitening filter `[1, a1, …, ap]`: `e[k] = Σ a_i·x[k−i]` is white.
    pub ar: Vec<f64>,
    /// σ of the whitened noise, V.
    pub sigma_w_v: f64,
    /// σ of the raw noise (after the deterministic terms), V.
    pub sigma_v: f64,
    /// Samples the floor was measured on.
    pub samples: usize,
    /// Where: `free lever before contact` or a fallback.
    pub source: &'static str,
}

pub(super) const MAX_ORDER: usize = 32;

/// Least-squares residual of `x` after the columns `cols`.
pub(super) fn detrend(x: &[f64], cols: &[Vec<f64>]) -> Vec<f64> {
    let m = cols.len();
    let mut ata = nalgebra::DMatrix::<f64>::zeros(m, m);
    let mut atb = nalgebra::DVector::<f64>::zeros(m);
    for k in 0..x.len() {
        for a in 0..m {
            atb[a] += cols[a][k] * x[k];
            for b in 0..m {
                ata[(a, b)] += cols[a][k] * cols[b][k];
            }
        }
    }
    for a in 0..m {
        ata[(a, a)] += 1e-12 * (1.0 + ata[(a, a)]);
    }
    let Some(chol) = ata.cholesky() else {
        return x.to_vec();
    };
    let beta = chol.solve(&atb);
    (0..x.len())
        .map(|k| x[k] - (0..m).map(|a| beta[a] * cols[a][k]).sum::<f64>())
        .collect()
}

/// Levinson–Durbin: AR coefficients `[1, a1..ap]` and prediction-error variances per order.
fn levinson(r: &[f64], p: usize) -> Vec<(Vec<f64>, f64)> {
    let mut out = vec![(vec![1.0], r[0])];
    let mut a = vec![1.0];
    let mut err = r[0];
    for m in 1..=p {
        if err <= 0.0 {
            break;
        }
        let acc: f64 = (0..m).map(|i| a[i] * r[m - i]).sum();
        let k = -acc / err;
        let mut next = a.clone();
        next.push(0.0);
        for i in 1..=m {
            next[i] = a.get(i).copied().unwrap_or(0.0) + k * a[m - i];
        }
        a = next;
        err *= 1.0 - k * k;
        out.push((a.clone(), err));
    }
    out
}

/// The AR model of a noise whose autocovariance at lags `0..=p` is `autocovariance`,
/// measured on `samples` samples: `([1, a1, …, ak], prediction-error variance)` of the order
/// `k ≤ p` with the least AIC. `None` where the variance is not positive.
pub(super) fn ar_by_aic(autocovariance: &[f64], samples: usize) -> Option<(Vec<f64>, f64)> {
    let power = *autocovariance.first()?;
    if power.is_nan() || power <= 0.0 {
        return None;
    }
    let aic = |f: &(Vec<f64>, f64)| samples as f64 * f.1.ln() + 2.0 * (f.0.len() - 1) as f64;
    levinson(autocovariance, autocovariance.len() - 1)
        .into_iter()
        .filter(|f| f.1 > 0.0)
        .min_by(|a, b| aic(a).total_cmp(&aic(b)))
}

/// Applies the whitening filter `a = [1, a1, …, ap]`: `x[k] + Σ_{i≥1} a_i·x[k−i]`, the first
/// sample repeated before the record (a record at rest).
///
/// Each output's sum runs over i in order, a chain of dependent additions as long as the
/// filter (22 on the corpus's 1/f floors): evaluated one output at a time, the chain's
/// latency made this a tenth of a diagnosis, as it runs on every residual. The sums are
/// taken a block of outputs at a time instead, term by term (`out += a_i·x` shifted by
/// i, which vectorises): each output still adds its terms in the same order, so the
/// result is the same to the bit.
pub fn whiten(a: &[f64], x: &[f64]) -> Vec<f64> {
    /// Outputs per block: 4 KiB of them, which stay in the L1 cache over the filter.
    const BLOCK: usize = 512;
    let p = a.len().saturating_sub(1);
    let n = x.len();
    let mut out = x.to_vec();
    for (k, o) in out.iter_mut().enumerate().take(p) {
        for (i, ai) in a.iter().enumerate().skip(1) {
            *o += ai * if k >= i { x[k - i] } else { x[0] };
        }
    }
    let mut k0 = p.min(n);
    while k0 < n {
        let k1 = (k0 + BLOCK).min(n);
        for (i, ai) in a.iter().enumerate().skip(1) {
            for (o, xv) in out[k0..k1].iter_mut().zip(&x[k0 - i..k1 - i]) {
                *o += ai * xv;
            }
        }
        k0 = k1;
    }
    out
}

/// Measures the floor on `x` (the free-lever samples), sampled at `fs_hz`.
pub fn measure(x: &[f64], fs_hz: f64) -> Option<NoiseModel> {
    let n = x.len();
    if n < 200 {
        return None;
    }
    let t: Vec<f64> = (0..n).map(|k| k as f64 / fs_hz).collect();
    let mut cols = vec![vec![1.0; n], t.clone()];
    // Both mains frequencies with their second and third harmonics: mains pick-up is a
    // candidate with harmonics, and a floor that kept them would whiten them away (an AR
    // model of order 29 did, on an independent simulator's 60 Hz pick-up with its third
    // harmonic, and the harmonic's interval came out three times too wide).
    let harmonics = (1..=MAINS_HARMONICS).map(|h| h as f64);
    for f in harmonics.flat_map(|h| [50.0 * h, 60.0 * h]) {
        if f < fs_hz / 2.0 {
            let w = 2.0 * std::f64::consts::PI * f;
            cols.push(t.iter().map(|t| (w * t).cos()).collect());
            cols.push(t.iter().map(|t| (w * t).sin()).collect());
        }
    }
    let e = detrend(x, &cols);
    let r: Vec<f64> = (0..=MAX_ORDER)
        .map(|lag| (lag..n).map(|k| e[k] * e[k - lag]).sum::<f64>() / n as f64)
        .collect();
    let (ar, err) = ar_by_aic(&r, n)?;
    Some(NoiseModel {
        ar,
        sigma_w_v: err.sqrt(),
        sigma_v: r[0].sqrt(),
        samples: n,
        source: "free lever before contact",
    })
}

/// A white floor from the whole record's first differences (robust: median absolute
/// deviation), when there is no free segment to measure on.
pub fn fallback(x: &[f64]) -> NoiseModel {
    let mut d: Vec<f64> = x.windows(2).map(|w| (w[1] - w[0]).abs()).collect();
    d.sort_by(f64::total_cmp);
    let mad = d.get(d.len() / 2).copied().unwrap_or(0.0);
    let sigma = (1.4826 * mad / std::f64::consts::SQRT_2).max(1e-12);
    NoiseModel {
        ar: vec![1.0],
        sigma_w_v: sigma,
        sigma_v: sigma,
        samples: x.len(),
        source: "first differences of the whole record (no free segment)",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{rngs::StdRng, SeedableRng};
    use rand_distr::{Distribution, StandardNormal};

    /// An AR(1) process is identified and whitened to its innovation σ; a slope and a 50 Hz
    /// line do not enter the floor.
    #[test]
    fn ar1_floor_without_slope_and_mains() {
        let mut rng = StdRng::seed_from_u64(4);
        let fs = 4000.0;
        let mut s = 0.0;
        let x: Vec<f64> = (0..4000)
            .map(|k| {
                let z: f64 = StandardNormal.sample(&mut rng);
                s = 0.8 * s + 1e-3 * z;
                let t = k as f64 / fs;
                s + 0.01 * t + 5e-3 * (2.0 * std::f64::consts::PI * 50.0 * t).sin()
            })
            .collect();
        let m = measure(&x, fs).unwrap();
        assert!((m.sigma_w_v / 1e-3 - 1.0).abs() < 0.05, "{}", m.sigma_w_v);
        assert!((m.ar[1] + 0.8).abs() < 0.05, "{:?}", m.ar);
    }
}
