//! A mode rung by the surroundings rather than by the drive.
//!
//! A mount or stage mode is rung by the room (footfall, a pump, sound) as well as by the
//! drive. The drive's part is a twin module ([`super::model::Effect::InstrumentResonance`]);
//! the room's part is not in the recorded drive at all, so no twin driven by that drive can
//! follow it, and a deterministic mode fitted to it runs to an absurd Q (an independent
//! simulator's 1949 Hz mount mode of Q 24, rung more by sound than by the drive, was fitted at
//! its frequency with Q 2.4·10⁶ and gained a quarter of what it took on the train samples on
//! the held-out ones). What can be modelled is its statistics: a second-order resonator
//! driven by white forcing while the lever touches the sample (the base's motion reaches the
//! deflection only through the contact; out of contact the floor was measured and holds
//! whatever rings there already). Its one-step prediction from the residual's own past is a
//! Kalman filter, and the fit is the prediction-error method: the residual's Gaussian
//! likelihood, `Σ ε²/S + ln S` over the innovations `ε` and their variances `S` (floor units),
//! which is the plain χ² where no mode rings. The held-out samples are scored the same way,
//! so the evidence is on the scale of every other candidate's.
//!
//! The fit is a Nelder–Mead search over three parameters (the mode's frequency, its Q and its
//! forcing), written here: the project's fitter takes twin models with residual vectors, and
//! a crate for one three-parameter likelihood would be a dependency for forty lines.

/// A mode rung by white forcing, in the whitened residual's units (the floor's σ = 1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AmbientMode {
    pub freq_hz: f64,
    pub q: f64,
    /// σ of the white forcing per sample, floor units.
    pub forcing: f64,
}

/// The fitted mode and what it does to the residual.
#[derive(Debug, Clone)]
pub struct AmbientFit {
    pub mode: AmbientMode,
    /// 95 % intervals of frequency (Hz) and Q, from the likelihood's curvature.
    pub freq_ci95: [f64; 2],
    pub q_ci95: [f64; 2],
    /// RMS of the mode while rung (its stationary spread), floor units.
    pub rms: f64,
    /// `Σ ε²/S + ln S` over the train and the held-out samples, and the plain χ² there
    /// without the mode.
    pub train: f64,
    pub held: f64,
    pub train_without: f64,
    pub held_without: f64,
    /// `Σ ε²/S` over the train and the held-out samples: the χ² of the normalised
    /// innovations, which a right model leaves at the floor's (1 per sample) while its
    /// likelihood keeps the `ln S` of what no prediction can know (the forcing).
    pub train_chi2: f64,
    pub held_chi2: f64,
    /// The normalised innovations `ε/√S` at each sample (0 at samples left out): white at
    /// the floor where the model is right.
    pub innovations: Vec<f64>,
    /// The one-step prediction of the mode at each sample, floor units (0 where not rung and
    /// at rest, and at samples left out).
    pub predicted: Vec<f64>,
}

/// The resonator's AR(2) coefficients at `fs_hz`: `m[k] = a1·m[k−1] + a2·m[k−2] + forcing`.
pub(super) fn ar2(mode: &AmbientMode, fs_hz: f64) -> (f64, f64) {
    let w0 = 2.0 * std::f64::consts::PI * mode.freq_hz / fs_hz;
    let zeta = 1.0 / (2.0 * mode.q);
    let r = (-zeta * w0).exp();
    let wd = w0 * (1.0 - zeta * zeta).max(0.0).sqrt();
    (2.0 * r * wd.cos(), -r * r)
}

/// Stationary variance of the AR(2) process with unit forcing, and its lag-1 covariance.
fn stationary(a1: f64, a2: f64) -> Option<(f64, f64)> {
    let d = (1.0 + a2) * ((1.0 - a2).powi(2) - a1 * a1);
    (d > 0.0).then(|| {
        let g0 = (1.0 - a2) / d;
        (g0, a1 * g0 / (1.0 - a2))
    })
}

/// What the filter gives at each sample: the predicted mode, the innovation over its σ, and
/// `ln S`.
struct Filtered {
    predicted: Vec<f64>,
    eps_norm: Vec<f64>,
    ln_s: Vec<f64>,
}

/// The Kalman filter of a mode rung (white forcing `σ = forcing`) where `rung`, seen in unit
/// white noise, over `z`; samples in `skipped` are predicted through without an update.
fn filter(z: &[f64], rung: &[bool], skipped: &[bool], mode: &AmbientMode, fs_hz: f64) -> Filtered {
    let (a1, a2) = ar2(mode, fs_hz);
    let g2 = mode.forcing * mode.forcing;
    let n = z.len();
    let (mut s0, mut s1) = (0.0, 0.0);
    let (mut p00, mut p01, mut p11) = (0.0, 0.0, 0.0);
    if rung.first() == Some(&true) {
        if let Some((c0, c1)) = stationary(a1, a2) {
            (p00, p01, p11) = (g2 * c0, g2 * c1, g2 * c0);
        }
    }
    let mut out = Filtered {
        predicted: vec![0.0; n],
        eps_norm: vec![0.0; n],
        ln_s: vec![0.0; n],
    };
    for k in 0..n {
        // Predict: s = F s, P = F P Fᵀ + G.
        let m = a1 * s0 + a2 * s1;
        s1 = s0;
        s0 = m;
        let q00 = a1 * a1 * p00 + 2.0 * a1 * a2 * p01 + a2 * a2 * p11;
        let q01 = a1 * p00 + a2 * p01;
        (p00, p01, p11) = (q00 + if rung[k] { g2 } else { 0.0 }, q01, p00);
        out.predicted[k] = s0;
        if skipped[k] {
            continue;
        }
        // Update with z = m + unit white noise.
        let s = p00 + 1.0;
        let eps = z[k] - s0;
        let (k0, k1) = (p00 / s, p01 / s);
        s0 += k0 * eps;
        s1 += k1 * eps;
        (p00, p01, p11) = (p00 - k0 * p00, p01 - k0 * p01, p11 - k1 * p01);
        out.eps_norm[k] = eps / s.sqrt();
        out.ln_s[k] = s.ln();
    }
    out
}

/// `Σ ε²/S + ln S` over `rows`.
fn score(f: &Filtered, rows: &[usize]) -> f64 {
    rows.iter()
        .map(|&k| f.eps_norm[k] * f.eps_norm[k] + f.ln_s[k])
        .sum()
}

/// Nelder–Mead minimisation of `f` from `x0` with initial steps `step`, `evals` evaluations
/// at most.
fn nelder_mead<const D: usize>(
    f: impl Fn(&[f64; D]) -> f64,
    x0: [f64; D],
    step: [f64; D],
    evals: usize,
) -> ([f64; D], f64) {
    let mut simplex: Vec<([f64; D], f64)> = (0..=D)
        .map(|i| {
            let mut x = x0;
            if i > 0 {
                x[i - 1] += step[i - 1];
            }
            (x, f(&x))
        })
        .collect();
    let mut used = D + 1;
    let along = |a: &[f64; D], b: &[f64; D], t: f64| -> [f64; D] {
        std::array::from_fn(|j| a[j] + t * (b[j] - a[j]))
    };
    while used < evals {
        simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
        let spread = simplex[D].1 - simplex[0].1;
        if spread.abs() < 1e-6 {
            break;
        }
        let centroid: [f64; D] =
            std::array::from_fn(|j| simplex[..D].iter().map(|p| p.0[j]).sum::<f64>() / D as f64);
        let worst = simplex[D];
        let reflected = along(&centroid, &worst.0, -1.0);
        let fr = f(&reflected);
        used += 1;
        if fr < simplex[0].1 {
            let expanded = along(&centroid, &worst.0, -2.0);
            let fe = f(&expanded);
            used += 1;
            simplex[D] = if fe < fr {
                (expanded, fe)
            } else {
                (reflected, fr)
            };
        } else if fr < simplex[D - 1].1 {
            simplex[D] = (reflected, fr);
        } else {
            let contracted = along(&centroid, &worst.0, 0.5);
            let fc = f(&contracted);
            used += 1;
            if fc < worst.1 {
                simplex[D] = (contracted, fc);
            } else {
                let best = simplex[0].0;
                for p in simplex.iter_mut().skip(1) {
                    p.0 = along(&best, &p.0, 0.5);
                    p.1 = f(&p.0);
                }
                used += D;
            }
        }
    }
    simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
    simplex[0]
}

/// The Q the fit may take: outside it the likelihood is infinite.
const Q_RANGE: (f64, f64) = (0.5, 1e5);

/// Fits a mode rung by white forcing where `rung`, to the whitened residual `z` (floor units),
/// on the `train` samples, starting from a peak at `peak_hz` of half-power width `width_hz`;
/// frequencies within `band_hz`. Scores it on `held`. `None` where nothing rings (the fit's
/// forcing vanishes) or the likelihood has no curvature to give intervals.
pub fn fit(
    z: &[f64],
    rung: &[bool],
    skipped: &[bool],
    (train, held): (&[usize], &[usize]),
    fs_hz: f64,
    (peak_hz, width_hz): (f64, f64),
    band_hz: (f64, f64),
) -> Option<AmbientFit> {
    let n_rung = rung
        .iter()
        .zip(skipped)
        .filter(|(r, s)| **r && !**s)
        .count();
    if n_rung < 64 {
        return None;
    }
    let mode_at = |x: &[f64; 3]| AmbientMode {
        freq_hz: x[0].exp(),
        q: x[1].exp(),
        forcing: x[2].exp(),
    };
    let inside = |m: &AmbientMode| {
        (band_hz.0..=band_hz.1).contains(&m.freq_hz) && (Q_RANGE.0..=Q_RANGE.1).contains(&m.q)
    };
    let objective = |x: &[f64; 3]| {
        let m = mode_at(x);
        if !inside(&m) {
            return f64::INFINITY;
        }
        score(&filter(z, rung, skipped, &m, fs_hz), train)
    };
    // The start: the peak's centre and width, and the forcing that gives the rung samples'
    // excess power over the floor.
    let q0 = (peak_hz / width_hz.max(1e-9)).clamp(1.0, 1e3);
    let excess = (rung.iter().zip(skipped).zip(z))
        .filter(|((r, s), _)| **r && !**s)
        .map(|(_, v)| v * v)
        .sum::<f64>()
        / n_rung as f64
        - 1.0;
    let start = AmbientMode {
        freq_hz: peak_hz,
        q: q0,
        forcing: 1.0,
    };
    let (a1, a2) = ar2(&start, fs_hz);
    let unit_var = stationary(a1, a2)?.0;
    let forcing0 = (excess.max(0.01) / unit_var).sqrt();
    let x0 = [peak_hz.ln(), q0.ln(), forcing0.ln()];
    let (x, best) = nelder_mead(objective, x0, [0.002, 0.3, 0.5], 400);
    // Once more from where it ended: Nelder–Mead can stall on a ridge.
    let (x, best) = {
        let (x2, b2) = nelder_mead(objective, x, [0.001, 0.1, 0.2], 200);
        if b2 < best {
            (x2, b2)
        } else {
            (x, best)
        }
    };
    if !best.is_finite() {
        return None;
    }
    let mode = mode_at(&x);
    // Intervals from the curvature of −2 ln L in (ln f, ln Q): covariance 2·H⁻¹.
    let h = [1e-4, 1e-2, 1e-2];
    let at = |dx: [f64; 3]| objective(&std::array::from_fn(|j| x[j] + dx[j]));
    let mut hess = nalgebra::Matrix3::<f64>::zeros();
    // Symmetric: each pair of parameters once (each entry is four filter runs).
    for i in 0..3 {
        for j in i..3 {
            let e = |a: usize, s: f64| {
                let mut d = [0.0; 3];
                d[a] += s * h[a];
                d
            };
            let add = |p: [f64; 3], q: [f64; 3]| std::array::from_fn(|k| p[k] + q[k]);
            hess[(i, j)] = (at(add(e(i, 1.0), e(j, 1.0)))
                - at(add(e(i, 1.0), e(j, -1.0)))
                - at(add(e(i, -1.0), e(j, 1.0)))
                + at(add(e(i, -1.0), e(j, -1.0))))
                / (4.0 * h[i] * h[j]);
            hess[(j, i)] = hess[(i, j)];
        }
    }
    let cov = hess.try_inverse()? * 2.0;
    let half = |i: usize| 1.96 * cov[(i, i)].max(0.0).sqrt();
    if !(0..3).all(|i| cov[(i, i)].is_finite() && cov[(i, i)] > 0.0) {
        return None;
    }
    let ci = |i: usize, v: f64| [v * (-half(i)).exp(), v * half(i).exp()];
    let f = filter(z, rung, skipped, &mode, fs_hz);
    let (a1, a2) = ar2(&mode, fs_hz);
    let rms = stationary(a1, a2).map_or(0.0, |(c0, _)| mode.forcing * c0.sqrt());
    let plain = |rows: &[usize]| rows.iter().map(|&k| z[k] * z[k]).sum::<f64>();
    let normalised = |rows: &[usize]| {
        (rows.iter())
            .map(|&k| f.eps_norm[k] * f.eps_norm[k])
            .sum::<f64>()
    };
    Some(AmbientFit {
        mode,
        freq_ci95: ci(0, mode.freq_hz),
        q_ci95: ci(1, mode.q),
        rms,
        train: best,
        held: score(&f, held),
        train_without: plain(train),
        held_without: plain(held),
        train_chi2: normalised(train),
        held_chi2: normalised(held),
        predicted: f.predicted,
        innovations: f.eps_norm,
    })
}

/// Undoes the whitening filter `a = [1, a1, …]` exactly as [`super::noise::whiten`] applies
/// it (the first sample repeated before the record): the raw-units series whose whitened
/// form is `w`.
pub fn unwhiten(a: &[f64], w: &[f64]) -> Vec<f64> {
    let dc: f64 = a.iter().sum();
    let before = match w.first() {
        Some(w0) if dc.abs() > 1e-12 => w0 / dc,
        _ => 0.0,
    };
    let mut x = vec![0.0; w.len()];
    for k in 0..w.len() {
        let past: f64 = (a.iter().enumerate().skip(1))
            .map(|(i, ai)| ai * if k >= i { x[k - i] } else { before })
            .sum();
        x[k] = w[k] - past;
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{rngs::StdRng, SeedableRng};
    use rand_distr::{Distribution, StandardNormal};

    /// Unit white noise, with a mode of `mode` rung over the second half.
    fn record(mode: Option<AmbientMode>, n: usize, fs: f64, seed: u64) -> (Vec<f64>, Vec<bool>) {
        let mut rng = StdRng::seed_from_u64(seed);
        let rung: Vec<bool> = (0..n).map(|k| k >= n / 2).collect();
        let mut m = (0.0, 0.0);
        let z = (0..n)
            .map(|k| {
                let w: f64 = StandardNormal.sample(&mut rng);
                let v: f64 = StandardNormal.sample(&mut rng);
                if let (Some(mode), true) = (mode, rung[k]) {
                    let (a1, a2) = ar2(&mode, fs);
                    m = (a1 * m.0 + a2 * m.1 + mode.forcing * v, m.0);
                } else {
                    m = (0.0, 0.0);
                }
                w + m.0
            })
            .collect();
        (z, rung)
    }

    fn split(n: usize) -> (Vec<usize>, Vec<usize>) {
        (0..n).partition(|k| (k / 50) % 3 != 2)
    }

    /// A 1949 Hz mode of Q 24 rung to about the floor's power is found where it is, with
    /// intervals that hold the truth, and the held-out samples gain by it; plain white noise
    /// gains nothing on its held-out samples.
    #[test]
    fn a_mode_rung_by_white_forcing_is_fitted_and_white_noise_is_not() {
        let (fs, n) = (10_000.0, 20_000);
        let truth = AmbientMode {
            freq_hz: 1949.0,
            q: 24.0,
            forcing: 0.2,
        };
        let (train, held) = split(n);
        let skipped = vec![false; n];
        let fitted = |(z, rung): (Vec<f64>, Vec<bool>)| {
            let peak = (1940.0, 120.0);
            fit(
                &z,
                &rung,
                &skipped,
                (&train, &held),
                fs,
                peak,
                (100.0, 4900.0),
            )
        };
        let f = fitted(record(Some(truth), n, fs, 3)).unwrap();
        assert!(
            (f.freq_ci95[0]..=f.freq_ci95[1]).contains(&truth.freq_hz),
            "{:?} {:?}",
            f.mode,
            f.freq_ci95
        );
        assert!(
            (f.q_ci95[0]..=f.q_ci95[1]).contains(&truth.q),
            "{:?} {:?}",
            f.mode,
            f.q_ci95
        );
        assert!((f.mode.freq_hz - 1949.0).abs() < 10.0, "{:?}", f.mode);
        let gain = f.held_without - f.held;
        assert!(gain > 500.0, "held-out gain {gain}");
        // Plain white noise: the fit finds little, and the held-out samples do not gain.
        if let Some(f) = fitted(record(None, n, fs, 4)) {
            let gain = f.held_without - f.held;
            assert!(
                gain < 10.0,
                "white noise, held-out gain {gain}: {:?}",
                f.mode
            );
        }
    }

    /// Unwhitening inverts the whitening filter.
    #[test]
    fn unwhiten_inverts_whiten() {
        let a = [1.0, -0.6, 0.2];
        let x: Vec<f64> = (0..50).map(|k| ((k * 7) % 11) as f64 - 5.0).collect();
        let w = crate::diagnose::noise::whiten(&a, &x);
        let back = unwhiten(&a, &w);
        assert!(
            (back.iter().zip(&x)).all(|(b, x)| (b - x).abs() < 1e-9),
            "{back:?}"
        );
    }
}
