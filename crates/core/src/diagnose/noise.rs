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

use super::model::{MAINS_HARMONICS, MAINS_TOP_HARMONIC};

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

/// How far a mains harmonic above the third must stand out of the free lever's residual to
/// be removed from the floor, in units of that residual's variance: a χ² of two degrees of
/// freedom where there is no line, above 25 once in 270 000 (seven such lines are tried, from
/// 200 to 420 Hz: once in 39 000 stretches). The pair is not made orthogonal to the columns
/// already removed; for a line this far above the stretch's own lowest frequency the
/// difference is small, and this only decides whether to remove it.
const EXTRA_LINE_MIN_GAIN: f64 = 25.0;

/// The sum of squares the cosine and sine `pair` take up from `e` by least squares.
fn line_gain(e: &[f64], pair: &[Vec<f64>; 2]) -> f64 {
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let [c, s] = pair;
    let (cc, ss, cs) = (dot(c, c), dot(s, s), dot(c, s));
    let (ce, se) = (dot(c, e), dot(s, e));
    let det = cc * ss - cs * cs;
    if det <= 1e-12 * cc * ss {
        return 0.0;
    }
    // b = G⁻¹·[ce, se]; the gain is [ce, se]·b.
    (ss * ce * ce - 2.0 * cs * ce * se + cc * se * se) / det
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
    let line = |f: f64| -> [Vec<f64>; 2] {
        let w = 2.0 * std::f64::consts::PI * f;
        [
            t.iter().map(|t| (w * t).cos()).collect(),
            t.iter().map(|t| (w * t).sin()).collect(),
        ]
    };
    // Both mains frequencies with their second and third harmonics: mains pick-up is a
    // candidate with harmonics, and a floor that kept them would whiten them away (an AR
    // model of order 29 did, on an independent simulator's 60 Hz pick-up with its third
    // harmonic, and the harmonic's interval came out three times too wide).
    let harmonics = (1..=MAINS_HARMONICS).map(|h| h as f64);
    for f in harmonics.flat_map(|h| [50.0 * h, 60.0 * h]) {
        if f < fs_hz / 2.0 {
            cols.extend(line(f));
        }
    }
    let mut e = detrend(x, &cols);
    // Higher harmonics only where they stand out of this stretch by more than
    // `EXTRA_LINE_MIN_GAIN` (a floor without them is measured exactly as before): another
    // simulator's fifth harmonic, 1.5 times the floor, taught an AR model of order 32 a
    // notch at 300 Hz and raised the floor's σ by 45 %.
    let variance = e.iter().map(|v| v * v).sum::<f64>() / n as f64;
    let mut higher: Vec<f64> = (MAINS_HARMONICS + 1..=MAINS_TOP_HARMONIC)
        .flat_map(|h| [50.0 * h as f64, 60.0 * h as f64])
        .filter(|&f| f < fs_hz / 2.0)
        .collect();
    // 300 Hz is both grids' (the fifth of 60, the sixth of 50): one pair of columns, not two
    // equal ones, which would leave the normal equations singular.
    higher.sort_by(f64::total_cmp);
    higher.dedup();
    let extra: Vec<[Vec<f64>; 2]> = (higher.into_iter())
        .map(line)
        .filter(|pair| variance > 0.0 && line_gain(&e, pair) / variance > EXTRA_LINE_MIN_GAIN)
        .collect();
    if !extra.is_empty() {
        cols.extend(extra.into_iter().flatten());
        e = detrend(x, &cols);
    }
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

/// How much more the floor's power spectrum must be at the bottom of the band it was
/// measured on than at a quarter of the sampling rate for the floor to count as 1/f there:
/// an AR model that AIC gave a few orders on a white floor stays within a few tens of per
/// cent of flat, while a detector's 1/f noise at the white level rises by orders of
/// magnitude over that span.
const LOW_BAND_COLOR: f64 = 2.0;

impl NoiseModel {
    /// The lowest frequency this floor was measured at, Hz: two cycles of the free-lever
    /// window. Below it the AR model's spectrum is only its own extrapolation, flat.
    pub fn lowest_measured_hz(&self, fs_hz: f64) -> f64 {
        2.0 * fs_hz / self.samples.max(1) as f64
    }

    /// The AR model's power spectrum at `f_hz`, relative to its innovation variance.
    fn relative_psd(&self, f_hz: f64, fs_hz: f64) -> f64 {
        let w = 2.0 * std::f64::consts::PI * f_hz / fs_hz;
        let (re, im) = self
            .ar
            .iter()
            .enumerate()
            .fold((0.0, 0.0), |(re, im), (k, a)| {
                (re + a * (w * k as f64).cos(), im - a * (w * k as f64).sin())
            });
        1.0 / (re * re + im * im).max(1e-300)
    }

    /// Whether the floor rises towards the bottom of its measured band as 1/f noise does
    /// (twice its level at a quarter of the sampling rate, `LOW_BAND_COLOR`).
    pub fn rises_at_low_frequency(&self, fs_hz: f64) -> bool {
        let low = self.lowest_measured_hz(fs_hz);
        low < fs_hz / 4.0
            && self.relative_psd(low, fs_hz)
                > LOW_BAND_COLOR * self.relative_psd(fs_hz / 4.0, fs_hz)
    }

    /// How many times larger than the whitening assumes the floor's noise is along a
    /// whitened signature `signature_w`, sampled at `fs_hz`, once the floor's 1/f rise is
    /// continued below the band it was measured on: the signature's power spectrum averaged
    /// with weight `f_low/f` below `f_low` ([`Self::lowest_measured_hz`]) and 1 above.
    ///
    /// Why: the free lever before contact is a short window (86 ms of a 20 kHz record
    /// of an independent simulator), and the AR model measured on it is flat below two
    /// cycles of that window. A 1/f floor keeps rising there, so the record's slowest
    /// wander is far larger than the whitening expects, and a slow candidate (a drift of
    /// the zero, a creep, a long retardation time) fits that wander on train and held-out
    /// samples alike: a 1/f null at 2.5 times the white level was named `thermal_drift`
    /// with a held-out drop of 150 (2026-11-28). 1 when the floor does not rise at its
    /// bottom ([`Self::rises_at_low_frequency`]): a white floor changes nothing.
    pub fn low_band_inflation(&self, fs_hz: f64, signature_w: &[f64]) -> f64 {
        let n = signature_w.len();
        if n < 4 || !self.rises_at_low_frequency(fs_hz) {
            return 1.0;
        }
        let low = self.lowest_measured_hz(fs_hz);
        let buf = crate::miic::spectrum(signature_w);
        let bin_hz = fs_hz / n as f64;
        let (mut weighted, mut total) = (0.0, 0.0);
        for (k, c) in buf.iter().enumerate().take(n / 2 + 1) {
            let power = c.norm_sqr();
            // The offset (k = 0) is fitted with every model: its bin weighs as the lowest
            // frequency the record holds.
            let f = (k as f64 * bin_hz).max(bin_hz);
            weighted += power * (low / f).max(1.0);
            total += power;
        }
        if total > 0.0 {
            weighted / total
        } else {
            1.0
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
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

    /// A fifth mains harmonic where the lever is free is left out of the floor with the line
    /// and the third: the floor stays white at the noise's own σ. (With the third the
    /// highest removed, an AR model learned the fifth and σ came out 1.4 times too high.)
    #[test]
    fn a_fifth_mains_harmonic_does_not_enter_the_floor() {
        let mut rng = StdRng::seed_from_u64(9);
        let (fs, sigma) = (50_000.0, 2.7e-3);
        let x: Vec<f64> = (0..3000)
            .map(|k| {
                let z: f64 = StandardNormal.sample(&mut rng);
                let phase = 2.0 * std::f64::consts::PI * 59.92 * k as f64 / fs;
                sigma * z
                    + 40e-3 * (phase + 0.4).sin()
                    + 14e-3 * (3.0 * phase + 5.2).sin()
                    + 4e-3 * (5.0 * phase + 2.2).sin()
            })
            .collect();
        let m = measure(&x, fs).unwrap();
        assert!((m.sigma_v / sigma - 1.0).abs() < 0.05, "{m:?}");
        assert!((m.sigma_w_v / sigma - 1.0).abs() < 0.05, "{m:?}");
    }

    /// White noise of `sigma` plus 1/f noise of rms `pink` from `1/(n/fs)` to `fs/2` (shaped
    /// in frequency), `n` samples.
    pub(crate) fn white_and_pink(n: usize, sigma: f64, pink: f64, seed: u64) -> Vec<f64> {
        use rustfft::{num_complex::Complex64, FftPlanner};
        let mut rng = StdRng::seed_from_u64(seed);
        let mut gauss = || -> f64 { StandardNormal.sample(&mut rng) };
        let mut spectrum: Vec<Complex64> = (0..n)
            .map(|k| {
                let f = k.min(n - k) as f64;
                let g = if f > 0.0 { f.powf(-0.5) } else { 0.0 };
                Complex64::new(gauss() * g, gauss() * g)
            })
            .collect();
        FftPlanner::new().plan_fft_inverse(n).process(&mut spectrum);
        let shaped: Vec<f64> = spectrum.iter().map(|c| c.re).collect();
        let rms = (shaped.iter().map(|x| x * x).sum::<f64>() / n as f64).sqrt();
        shaped
            .iter()
            .map(|x| pink * x / rms + sigma * gauss())
            .collect()
    }

    /// A floor of 1/f noise measured on a short free-lever window underrates the record's
    /// slow wander, by about the ratio of the window's lowest frequency to the wander's; a
    /// white floor, or a signature inside the measured band, is taken as it is.
    #[test]
    fn a_one_over_f_floor_is_continued_below_its_window() {
        let (fs, n) = (20_000.0, 20_000);
        let ramp: Vec<f64> = (0..n).map(|k| k as f64 / n as f64 - 0.5).collect();
        let line: Vec<f64> = (0..n)
            .map(|k| (2.0 * std::f64::consts::PI * 500.0 * k as f64 / fs).sin())
            .collect();
        // A white floor: flat at its bottom, nothing to continue.
        let white = measure(&white_and_pink(n, 1e-3, 0.0, 1)[..2000], fs).unwrap();
        assert!(!white.rises_at_low_frequency(fs), "{:?}", white.ar);
        assert_eq!(white.low_band_inflation(fs, &whiten(&white.ar, &ramp)), 1.0);
        // 1/f at 2.5 times the white level, measured on 100 ms: it rises at 20 Hz, the
        // window's lowest frequency, and a ramp over the 1 s record sits mostly below it.
        let pink = measure(&white_and_pink(n, 1e-3, 2.5e-3, 2)[..2000], fs).unwrap();
        assert_eq!(pink.lowest_measured_hz(fs), 20.0);
        assert!(pink.rises_at_low_frequency(fs), "{:?}", pink.ar);
        let slow = pink.low_band_inflation(fs, &whiten(&pink.ar, &ramp));
        assert!(slow > 8.0, "ramp: {slow}");
        let fast = pink.low_band_inflation(fs, &whiten(&pink.ar, &line));
        assert!((1.0..1.01).contains(&fast), "500 Hz line: {fast}");
    }
}
