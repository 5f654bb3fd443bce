//! The sequential D-optimal design of the paper's eqs. 17–19, made to terminate with a
//! certificate.
//!
//! **Normalised design.** A design ξ puts power fractions `p_i` (Σ p_i = 1) on grid lines
//! `f_i`. With `w(f) = 1/σ²(f)` from the noise spectrum and `I(f) = Re(g(f)ᴴ g(f))`
//! ([`crate::fisher::line_information`], log-parameters), the information per unit input
//! power and sample is `M(ξ) = Σ p_i·w(f_i)·I(f_i)`; the Fisher matrix of
//! [`crate::fisher`] is `N·P·M(ξ)` for total input power P, so the design does not depend on
//! the power or the record length. The variance function is
//! `d(f, ξ) = tr(M(ξ)⁻¹·w(f)·I(f))` (eq. 17). By the Kiefer–Wolfowitz equivalence theorem
//! ξ maximises `det M` iff `max_f d(f, ξ) = p` (the number of parameters), and for any ξ
//! its D-efficiency `(det M(ξ)/det M*)^{1/p}` is at least `exp(1 − max d/p)`; so
//! `d_max_over_p = max d/p ≤ 1 + ε` is the stopping certificate, always evaluated on **all**
//! candidate lines.
//!
//! Since `I(f) = a aᵀ + b bᵀ` with `a = Re g`, `b = Im g` (rank 2), every quantity is computed
//! from the two real vectors per line, and `det M` along a step changes by the 2×2
//! determinant `det(I₂ + t·Q)`, `Q = w·[a b]ᵀ M⁻¹ [a b]`: this gives the exact line search.
//!
//! **Algorithm.**
//! 1. The paper's Wynn steps (eqs. 18–19): `f* = argmax d`, `p ← (1−α_k)p`, `p(f*) += α_k`,
//!    `α_k = 1/(k + 3)` by default, for [`DesignConfig::accelerate_after`] steps (all steps
//!    if `None`).
//! 2. Then Frank–Wolfe with away steps and exact line search (the Wolfe–Atwood
//!    vertex-direction method): either move towards the line of largest `d` or away from the
//!    support line of smallest `d`, whichever gap `d_max − p` or `p − d_min` is larger, with
//!    the step that maximises `log det M` exactly. Plain Wynn steps with `1/(k+3)` converge
//!    sublinearly (their weights decay only harmonically, so spurious early lines linger);
//!    away steps can remove such lines in one step and the method converges linearly, so the
//!    certificate `1 + ε` is reached in tens to hundreds of steps instead of tens of thousands.
//!    The search runs to `1 + ε/4` to leave room for step 3.
//! 3. The D-optimal information matrix is unique but the design measure is not: the optimum
//!    is flat, and the converged grid design spreads over clusters of lines around each
//!    optimal frequency. To get a small support, neighbours closer than [`MergeRule`]
//!    (`max(abs_hz, rel·f)`) are merged into one line (at the allowed grid line nearest their
//!    power-weighted mean), for a ladder of merge distances from the configured one down to
//!    1/8 of it; after each merge the weights on the merged support are re-optimised (same
//!    method, restricted to the support) and the certificate is re-checked on all candidates.
//!    The certified merge with the fewest lines is kept, and then the weakest line is dropped
//!    (with re-optimisation) as long as the certificate still holds. These simplifications
//!    must pass `1 + ε/2`; if none does, the unmerged design is returned. The returned
//!    design's `d_max_over_p` is the certificate of exactly the returned lines.

use super::{DesignConfig, DesignError, DesignLine, MergeRule};
use crate::fisher::{fisher_multisine, log_sensitivity, relative_crlb, Line, NoiseSpectrum};
use crate::linalg::golden_max;
use crate::prony::PronySeries;
use nalgebra::DMatrix;
use serde::Serialize;

/// A D-optimal (or, with `certified = false`, partially optimised) multisine design.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Design {
    /// Lines in ascending frequency; power fractions sum to 1.
    pub lines: Vec<DesignLine>,
    /// Kiefer–Wolfowitz certificate of `lines`: `max_f d(f)/p` over all candidate lines
    /// (1 at the D-optimum).
    pub d_max_over_p: f64,
    /// `d_max_over_p ≤ 1 + epsilon`.
    pub certified: bool,
    /// The tolerance ε the design was certified against.
    pub epsilon: f64,
    /// Search iterations (Wynn plus accelerated steps), excluding the final re-optimisation.
    pub iterations: usize,
    /// How many of them were plain Wynn steps (eqs. 18–19).
    pub wynn_steps: usize,
    /// Lines of the converged grid design before merging.
    pub lines_before_merge: usize,
    /// Number of model parameters p = 2n + 1.
    pub n_params: usize,
    /// Candidate lines searched (after band, Nyquist guard and exclusions).
    pub n_candidates: usize,
    /// Grid spacing `1/period`, Hz.
    pub grid_hz: f64,
    /// Sample rate, Hz.
    pub fs_hz: f64,
    /// One period of the multisine, s.
    pub period_s: f64,
    /// Periods in the record.
    pub periods: usize,
}

impl Design {
    /// Sine amplitudes `A_i = sqrt(2·P·p_i)` for total AC power `P` (mean square of u).
    pub fn lines_at_power(&self, total_power: f64) -> Vec<Line> {
        self.lines
            .iter()
            .map(|l| Line {
                freq_hz: l.freq_hz,
                amplitude: (2.0 * total_power * l.power_frac).sqrt(),
            })
            .collect()
    }
}

/// The allowed candidate lines of `cfg`, ascending, in Hz: the multiples of `1/period` in
/// `[f_lo, min(f_hi, (1 − guard)·fs/2)]` that no exclusion covers.
pub fn candidate_grid(cfg: &DesignConfig) -> Result<Vec<f64>, DesignError> {
    cfg.validate()?;
    let df = 1.0 / cfg.period_s();
    let (lo, hi) = (cfg.band_hz.0, cfg.f_max_hz());
    let k_lo = ((lo / df) - 1e-9).ceil().max(1.0);
    let k_hi = ((hi / df) + 1e-9).floor();
    let empty = DesignError::EmptyBand {
        f_lo_hz: lo,
        f_hi_hz: hi,
        spacing_hz: df,
    };
    if k_hi < k_lo {
        return Err(empty);
    }
    if k_hi - k_lo > 4.0e6 {
        return Err(DesignError::InvalidConfig(format!(
            "{} candidate lines is too many; shorten the record or narrow the band",
            k_hi - k_lo + 1.0
        )));
    }
    let freqs: Vec<f64> = (k_lo as u64..=k_hi as u64)
        .map(|k| k as f64 * df)
        .filter(|&f| !cfg.exclusions.excludes(f))
        .collect();
    if freqs.is_empty() {
        return Err(empty);
    }
    Ok(freqs)
}

/// Runs the sequential D-optimal design for `prior` (see the module documentation).
///
/// Errors: a bad configuration, an empty band, too few candidate lines for the model order,
/// a singular information matrix, or [`DesignError::NotCertified`] (carrying the best design
/// found) when `max_iterations` did not reach `1 + ε`.
pub fn d_optimal(prior: &PronySeries, cfg: &DesignConfig) -> Result<Design, DesignError> {
    let prob = Problem::new(prior, cfg)?;
    let eps = cfg.epsilon;
    let mut p = prob.initial_weights(cfg)?;
    let all: Vec<usize> = (0..prob.freqs.len()).collect();
    let run = prob.optimise(
        &mut p,
        &all,
        RunOpts {
            plain_steps: cfg.accelerate_after,
            alpha_offset: cfg.alpha_offset,
            tol: eps / 4.0,
            max_iter: cfg.max_iterations,
        },
    )?;
    prune(&mut p, 1e-9);
    let lines_before_merge = p.iter().filter(|x| **x > 0.0).count();
    let make = |p: &[f64], d: f64| Design {
        lines: prob.lines(p),
        d_max_over_p: d,
        certified: d <= 1.0 + eps,
        epsilon: eps,
        iterations: run.iterations,
        wynn_steps: run.wynn_steps,
        lines_before_merge,
        n_params: prob.np,
        n_candidates: prob.freqs.len(),
        grid_hz: 1.0 / cfg.period_s(),
        fs_hz: cfg.fs_hz,
        period_s: cfg.period_s(),
        periods: cfg.periods,
    };
    let d_unmerged = prob.d_max_over_p(&p)?;
    if d_unmerged > 1.0 + eps {
        return Err(DesignError::NotCertified {
            iterations: run.iterations,
            d_max_over_p: d_unmerged,
            epsilon: eps,
            design: Box::new(make(&p, d_unmerged)),
        });
    }
    // Simplification keeps half of the tolerance in reserve: accepted at 1 + ε/2.
    let accept = 1.0 + eps / 2.0;
    let mut best = (p.clone(), d_unmerged);
    let n_lines = |q: &[f64]| q.iter().filter(|x| **x > 0.0).count();
    let MergeRule { rel, abs_hz } = cfg.merge;
    if rel > 0.0 || abs_hz > 0.0 {
        for shrink in [1.0, 0.7, 0.5, 0.35, 0.25, 0.125] {
            let rule = MergeRule {
                rel: rel * shrink,
                abs_hz: abs_hz * shrink,
            };
            let Some((q, d)) = prob.reoptimise(prob.merge(&p, rule), cfg.alpha_offset) else {
                continue; // merged support not informative enough: merge less
            };
            if d <= accept
                && (n_lines(&q) < n_lines(&best.0) || n_lines(&q) == n_lines(&best.0) && d < best.1)
            {
                best = (q, d);
            }
        }
    }
    // Greedy support reduction: drop the weakest line while the certificate still holds.
    while n_lines(&best.0) > prob.np.div_ceil(2) {
        let weakest = (0..best.0.len())
            .filter(|&j| best.0[j] > 0.0)
            .min_by(|&i, &j| best.0[i].total_cmp(&best.0[j]))
            .expect("support is not empty");
        let mut q = best.0.clone();
        q[weakest] = 0.0;
        match prob.reoptimise(q, cfg.alpha_offset) {
            Some((q, d)) if d <= accept => best = (q, d),
            _ => break,
        }
    }
    Ok(make(&best.0, best.1))
}

/// The certificate `max_f d(f)/p` of an arbitrary design (lines need not lie on the grid;
/// the fractions are normalised) over the candidate grid of `cfg`. A value of 1 means
/// D-optimal on that grid; `d_max_over_p − 1` bounds how far `det M` is from its maximum.
pub fn d_max_over_p(
    model: &PronySeries,
    cfg: &DesignConfig,
    lines: &[DesignLine],
) -> Result<f64, DesignError> {
    let prob = Problem::new(model, cfg)?;
    let total: f64 = lines.iter().map(|l| l.power_frac).sum();
    if lines.is_empty() || total.is_nan() || total <= 0.0 {
        return Err(DesignError::SingularInformation);
    }
    let mut m = DMatrix::<f64>::zeros(prob.np, prob.np);
    for l in lines {
        let (a, b) = prob.sens(l.freq_hz);
        let w = l.power_frac / total;
        m += (&a * a.transpose() + &b * b.transpose()) * w;
    }
    let minv = crate::linalg::spd_inverse(&m).ok_or(DesignError::SingularInformation)?;
    let d = prob.d_values(&minv);
    Ok(d.iter().fold(0.0f64, |x, y| x.max(*y)) / prob.np as f64)
}

/// Relative Cramér–Rao bounds (fractions, canonical order) of the multisine with the design's
/// lines at total AC input power `total_power`, `n_samples` samples and output `noise`.
/// `None` when the design cannot identify the model.
pub fn predicted_crlb(
    model: &PronySeries,
    sampling: &crate::discrete::Sampling,
    lines: &[DesignLine],
    total_power: f64,
    n_samples: usize,
    noise: &NoiseSpectrum,
) -> Option<Vec<f64>> {
    let total: f64 = lines.iter().map(|l| l.power_frac).sum();
    let ls: Vec<Line> = lines
        .iter()
        .map(|l| Line {
            freq_hz: l.freq_hz,
            amplitude: (2.0 * total_power * l.power_frac / total).sqrt(),
        })
        .collect();
    relative_crlb(&fisher_multisine(model, sampling, &ls, n_samples, noise))
}

/// Sets weights below `tiny` to zero and renormalises.
fn prune(p: &mut [f64], tiny: f64) {
    for x in p.iter_mut() {
        if *x < tiny {
            *x = 0.0;
        }
    }
    let s: f64 = p.iter().sum();
    if s > 0.0 {
        p.iter_mut().for_each(|x| *x /= s);
    }
}

#[derive(Debug, Clone, Copy)]
struct RunOpts {
    /// Plain Wynn steps before acceleration (`None`: plain throughout).
    plain_steps: Option<usize>,
    alpha_offset: f64,
    tol: f64,
    max_iter: usize,
}

#[derive(Debug, Clone, Copy)]
struct Run {
    iterations: usize,
    wynn_steps: usize,
}

/// The candidate lines with their noise-weighted, scaled sensitivities.
struct Problem {
    freqs: Vec<f64>,
    np: usize,
    /// `sqrt(w(f)/w_ref)·Re g(f)/J0` as columns (np × n_cand); `b` likewise for `Im g`.
    a: DMatrix<f64>,
    b: DMatrix<f64>,
    /// The model, sampling, noise and scaling, for lines off the grid.
    model: PronySeries,
    sampling: crate::discrete::Sampling,
    noise: NoiseSpectrum,
    w_ref: f64,
}

impl Problem {
    fn new(model: &PronySeries, cfg: &DesignConfig) -> Result<Self, DesignError> {
        cfg.validate()?;
        if !model.is_physical() || model.j0_per_pa.is_nan() || model.j0_per_pa <= 0.0 {
            return Err(DesignError::NonPhysicalModel(model.clone()));
        }
        let freqs = candidate_grid(cfg)?;
        let np = model.n_params();
        let need = np.div_ceil(2);
        if freqs.len() < need {
            return Err(DesignError::TooFewCandidates {
                have: freqs.len(),
                need,
                params: np,
            });
        }
        let w_ref = freqs
            .iter()
            .map(|&f| 1.0 / cfg.noise.variance_at(f))
            .fold(0.0f64, f64::max);
        if !(w_ref.is_finite() && w_ref > 0.0) {
            return Err(DesignError::InvalidConfig(
                "noise variance must be positive and finite".into(),
            ));
        }
        let mut prob = Self {
            freqs: Vec::new(),
            np,
            a: DMatrix::zeros(np, freqs.len()),
            b: DMatrix::zeros(np, freqs.len()),
            model: model.clone(),
            sampling: cfg.sampling(),
            noise: cfg.noise.clone(),
            w_ref,
        };
        for (j, &f) in freqs.iter().enumerate() {
            let (a, b) = prob.sens(f);
            prob.a.set_column(j, &a);
            prob.b.set_column(j, &b);
        }
        prob.freqs = freqs;
        Ok(prob)
    }

    /// Scaled `(Re g, Im g)·sqrt(w/w_ref)/J0` at any frequency; `a aᵀ + b bᵀ` is
    /// `line_information·w/(w_ref·J0²)`.
    fn sens(&self, f: f64) -> (nalgebra::DVector<f64>, nalgebra::DVector<f64>) {
        let g = log_sensitivity(&self.model, &self.sampling, f);
        let s = (1.0 / (self.noise.variance_at(f) * self.w_ref)).sqrt() / self.model.j0_per_pa;
        (
            nalgebra::DVector::from_iterator(self.np, g.iter().map(|c| c.re * s)),
            nalgebra::DVector::from_iterator(self.np, g.iter().map(|c| c.im * s)),
        )
    }

    fn information(&self, p: &[f64]) -> DMatrix<f64> {
        let mut m = DMatrix::<f64>::zeros(self.np, self.np);
        for (j, &pj) in p.iter().enumerate() {
            if pj > 0.0 {
                let a = self.a.column(j);
                let b = self.b.column(j);
                m.ger(pj, &a, &a, 1.0);
                m.ger(pj, &b, &b, 1.0);
            }
        }
        m
    }

    fn minv(&self, p: &[f64]) -> Result<DMatrix<f64>, DesignError> {
        crate::linalg::spd_inverse(&self.information(p)).ok_or(DesignError::SingularInformation)
    }

    /// `d(f)` at every candidate.
    fn d_values(&self, minv: &DMatrix<f64>) -> Vec<f64> {
        let ma = minv * &self.a;
        let mb = minv * &self.b;
        (0..self.freqs.len())
            .map(|j| self.a.column(j).dot(&ma.column(j)) + self.b.column(j).dot(&mb.column(j)))
            .collect()
    }

    fn d_max_over_p(&self, p: &[f64]) -> Result<f64, DesignError> {
        let d = self.d_values(&self.minv(p)?);
        Ok(d.iter().fold(0.0f64, |x, y| x.max(*y)) / self.np as f64)
    }

    /// `Q = [a b]ᵀ M⁻¹ [a b]` of candidate j as (q11, q12, q22).
    fn q(&self, minv: &DMatrix<f64>, j: usize) -> (f64, f64, f64) {
        let a = self.a.column(j);
        let b = self.b.column(j);
        let ma = minv * a;
        let mb = minv * b;
        (a.dot(&ma), a.dot(&mb), b.dot(&mb))
    }

    fn lines(&self, p: &[f64]) -> Vec<DesignLine> {
        p.iter()
            .enumerate()
            .filter(|(_, x)| **x > 0.0)
            .map(|(j, x)| DesignLine {
                freq_hz: self.freqs[j],
                power_frac: *x,
            })
            .collect()
    }

    fn nearest(&self, f: f64) -> usize {
        let i = self.freqs.partition_point(|x| *x < f);
        if i == 0 {
            0
        } else if i >= self.freqs.len() {
            self.freqs.len() - 1
        } else if f - self.freqs[i - 1] <= self.freqs[i] - f {
            i - 1
        } else {
            i
        }
    }

    /// F0 snapped to the grid; log-spaced lines are mixed in when F0 is empty or singular.
    fn initial_weights(&self, cfg: &DesignConfig) -> Result<Vec<f64>, DesignError> {
        let n = self.freqs.len();
        let mut p = vec![0.0; n];
        for l in &cfg.initial {
            p[self.nearest(l.freq_hz)] += l.power_frac;
        }
        prune(&mut p, 0.0);
        let singular = p.iter().all(|x| *x == 0.0) || self.minv(&p).is_err();
        if singular {
            // log-spaced fill with one line more than the minimum (index-spaced if the log
            // spacing collapses onto fewer distinct grid lines)
            let k = (self.np.div_ceil(2) + 1).min(n);
            let (f0, f1) = (self.freqs[0], self.freqs[n - 1]);
            let spaced = |i: usize| {
                if k > 1 {
                    i as f64 / (k - 1) as f64
                } else {
                    0.0
                }
            };
            let mut fill = vec![0.0; n];
            for i in 0..k {
                fill[self.nearest(f0 * (f1 / f0).powf(spaced(i)))] = 1.0;
            }
            if fill.iter().filter(|x| **x > 0.0).count() < k {
                fill = vec![0.0; n];
                for i in 0..k {
                    fill[(spaced(i) * (n - 1) as f64).round() as usize] = 1.0;
                }
            }
            prune(&mut fill, 0.0);
            let had_f0 = p.iter().any(|x| *x > 0.0);
            for (x, y) in p.iter_mut().zip(&fill) {
                *x = if had_f0 { 0.5 * *x + 0.5 * y } else { *y };
            }
            self.minv(&p)?;
        }
        Ok(p)
    }

    /// Wynn steps, then Frank–Wolfe with away steps, on the candidates `allowed`.
    fn optimise(
        &self,
        p: &mut [f64],
        allowed: &[usize],
        opts: RunOpts,
    ) -> Result<Run, DesignError> {
        let np = self.np as f64;
        let mut wynn = 0;
        for it in 0..=opts.max_iter {
            let minv = self.minv(p)?;
            let d = self.d_values(&minv);
            let (mut imax, mut dmax) = (allowed[0], f64::NEG_INFINITY);
            let (mut imin, mut dmin) = (usize::MAX, f64::INFINITY);
            for &j in allowed {
                if d[j] > dmax {
                    (imax, dmax) = (j, d[j]);
                }
                if p[j] > 0.0 && d[j] < dmin {
                    (imin, dmin) = (j, d[j]);
                }
            }
            if dmax / np <= 1.0 + opts.tol || it == opts.max_iter {
                return Ok(Run {
                    iterations: it,
                    wynn_steps: wynn,
                });
            }
            let plain = opts.plain_steps.is_none_or(|k| it < k);
            if plain {
                let alpha = 1.0 / ((it + 1) as f64 + opts.alpha_offset);
                p.iter_mut().for_each(|x| *x *= 1.0 - alpha);
                p[imax] += alpha;
                wynn += 1;
                continue;
            }
            let away = imin != usize::MAX && p[imin] < 1.0 && np - dmin > dmax - np;
            if away {
                let (q11, q12, q22) = self.q(&minv, imin);
                let amax = p[imin] / (1.0 - p[imin]);
                let obj = |al: f64| {
                    let t = al / (1.0 + al);
                    let det = (1.0 - t * q11) * (1.0 - t * q22) - t * t * q12 * q12;
                    if det <= 0.0 {
                        f64::NEG_INFINITY
                    } else {
                        np * (1.0 + al).ln() + det.ln()
                    }
                };
                let al = golden_max(obj, 0.0, amax);
                p.iter_mut().for_each(|x| *x *= 1.0 + al);
                p[imin] -= al;
                if p[imin] <= 1e-12 * (1.0 + al) || al >= amax * (1.0 - 1e-9) {
                    p[imin] = 0.0;
                }
            } else {
                let (q11, q12, q22) = self.q(&minv, imax);
                let obj = |al: f64| {
                    let t = al / (1.0 - al);
                    let det = (1.0 + t * q11) * (1.0 + t * q22) - t * t * q12 * q12;
                    np * (1.0 - al).ln() + det.ln()
                };
                let al = golden_max(obj, 0.0, 1.0 - 1e-9);
                p.iter_mut().for_each(|x| *x *= 1.0 - al);
                p[imax] += al;
            }
            let s: f64 = p.iter().sum();
            p.iter_mut().for_each(|x| *x /= s);
        }
        unreachable!("the loop returns at it == max_iter")
    }

    /// Re-optimises the weights on the support of `q` and returns them with the certificate
    /// over all candidates; `None` if the support is not informative.
    fn reoptimise(&self, mut q: Vec<f64>, alpha_offset: f64) -> Option<(Vec<f64>, f64)> {
        prune(&mut q, 0.0);
        let support: Vec<usize> = (0..q.len()).filter(|&i| q[i] > 0.0).collect();
        if support.is_empty() {
            return None;
        }
        let opts = RunOpts {
            plain_steps: Some(0),
            alpha_offset,
            tol: 1e-7,
            max_iter: 5000,
        };
        self.optimise(&mut q, &support, opts).ok()?;
        prune(&mut q, 1e-9);
        let d = self.d_max_over_p(&q).ok()?;
        Some((q, d))
    }

    /// Merges neighbouring support lines closer than the rule into single lines.
    fn merge(&self, p: &[f64], rule: MergeRule) -> Vec<f64> {
        let support: Vec<usize> = (0..p.len()).filter(|&j| p[j] > 0.0).collect();
        let mut out = vec![0.0; p.len()];
        let mut cluster: Vec<usize> = Vec::new();
        let flush = |cluster: &mut Vec<usize>, out: &mut Vec<f64>| {
            if cluster.is_empty() {
                return;
            }
            let w: f64 = cluster.iter().map(|&j| p[j]).sum();
            let f = cluster.iter().map(|&j| p[j] * self.freqs[j]).sum::<f64>() / w;
            out[self.nearest(f)] += w;
            cluster.clear();
        };
        for &j in &support {
            if let Some(&last) = cluster.last() {
                let gap = self.freqs[j] - self.freqs[last];
                if gap > rule.abs_hz.max(rule.rel * self.freqs[last]) {
                    flush(&mut cluster, &mut out);
                }
            }
            cluster.push(j);
        }
        flush(&mut cluster, &mut out);
        out
    }
}
