//! Maximum-likelihood estimation from periodic (multisine) data in the frequency domain.
//!
//! The record is cut into P whole periods. Per period, the DFT gives `U_p(k)`, `Y_p(k)`; the
//! period means `Ū(k)`, `Ȳ(k)` carry the signal, and the scatter between periods measures the
//! noise (co)variances of those means at every frequency — no noise model is assumed. The
//! scatter of single bins (P − 1 complex degrees of freedom each) is averaged over
//! neighbouring bins, because weights estimated from two periods alone would be too noisy
//! to be efficient.
//!
//! With the excited lines `k ∈ K`, the ML cost for Gaussian noise on both channels is
//! `V(θ) = Σ_K |Ȳ − G(θ)Ū|² / (σ²_Y + |G|²σ²_U − 2 Re(Ḡ σ_YU))`, minimised over log-parameters.
//! `G` is evaluated through [`Sampling`], so the fitted model is the one consistent with how the
//! data were sampled. At the minimum `JᵀJ` of the normalised residuals is the Fisher
//! information: its inverse is the covariance, and at the truth it is the Cramér–Rao bound.

use super::lm::{Evaluation, LmOptions};
use super::start::{grid_starts, log_grid, with_prior};
use super::{check_signals, solve_from_starts, Diagnostics, Estimate, EstimateError, Method};
use crate::discrete::Sampling;
use crate::linalg::spd_inverse;
use crate::prony::PronySeries;
use nalgebra::{DMatrix, DVector};
use rustfft::num_complex::Complex64;
use rustfft::FftPlanner;

/// Which DFT lines the fit uses.
#[derive(Debug, Clone, PartialEq)]
pub enum LineSelection {
    /// Lines whose input amplitude is at least `relative` × the largest one and stands
    /// clear of the input noise.
    Auto { relative: f64 },
    /// These frequencies (Hz), each snapped to the nearest per-period DFT line.
    Explicit(Vec<f64>),
}

/// Settings of the frequency-domain fit.
#[derive(Debug, Clone)]
pub struct FrequencyFitOptions {
    /// Number of Prony terms n.
    pub order: usize,
    pub sampling: Sampling,
    /// Number of whole periods in the record.
    pub periods: usize,
    pub lines: LineSelection,
    /// Half-width, in bins, of the window over which noise variances are averaged.
    pub noise_smoothing_bins: usize,
    /// Points of the τ grid used for start values.
    pub grid_size: usize,
    /// How many of the best grid starts to refine.
    pub starts: usize,
    /// An additional start (a prior estimate, or an ARX fit).
    pub extra_start: Option<PronySeries>,
    pub lm: LmOptions,
}

impl FrequencyFitOptions {
    /// Defaults for a Tustin-sampled record of `periods` periods at `fs_hz`.
    pub fn new(order: usize, fs_hz: f64, periods: usize) -> Self {
        Self {
            order,
            sampling: Sampling::Tustin { fs_hz },
            periods,
            lines: LineSelection::Auto { relative: 1e-3 },
            noise_smoothing_bins: 16,
            grid_size: 16,
            starts: 6,
            extra_start: None,
            lm: LmOptions::default(),
        }
    }
}

/// One DFT line: period means and the (co)variances *of those means*.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpectralLine {
    /// Index on the per-period DFT grid.
    pub bin: usize,
    pub freq_hz: f64,
    pub u: Complex64,
    pub y: Complex64,
    pub var_u: f64,
    pub var_y: f64,
    /// `E[(Y − Ȳ)·conj(U − Ū)]` of the means.
    pub cov_yu: Complex64,
}

/// The excited lines of a periodic record.
#[derive(Debug, Clone)]
pub struct PeriodicSpectra {
    pub fs_hz: f64,
    pub period_samples: usize,
    pub periods: usize,
    pub lines: Vec<SpectralLine>,
    /// True when the period-to-period scatter is at rounding level: the data are noise-free.
    pub noise_free: bool,
}

/// Splits `u`, `y` into `periods` periods and extracts the excited lines with their noise.
pub fn periodic_spectra(
    u: &[f64],
    y: &[f64],
    fs_hz: f64,
    periods: usize,
    selection: &LineSelection,
    smoothing_bins: usize,
) -> Result<PeriodicSpectra, EstimateError> {
    check_signals(u, y)?;
    if periods == 0 || !u.len().is_multiple_of(periods) || u.len() / periods < 4 {
        return Err(EstimateError::NotWholePeriods {
            samples: u.len(),
            periods,
        });
    }
    let np = u.len() / periods;
    let half = np / 2; // bins 1..half are positive frequencies (half itself only if np odd)
    let mut planner = FftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(np);
    let spectra = |x: &[f64]| -> Vec<Vec<Complex64>> {
        x.chunks(np)
            .map(|chunk| {
                let mut buf: Vec<Complex64> =
                    chunk.iter().map(|v| Complex64::new(*v, 0.0)).collect();
                fft.process(&mut buf);
                buf
            })
            .collect()
    };
    let us = spectra(u);
    let ys = spectra(y);
    let p = periods as f64;
    let mean = |s: &Vec<Vec<Complex64>>, k: usize| s.iter().map(|v| v[k]).sum::<Complex64>() / p;
    let nb = half.max(1);
    let mut um = vec![Complex64::new(0.0, 0.0); nb];
    let mut ym = um.clone();
    let mut vu = vec![0.0; nb];
    let mut vy = vec![0.0; nb];
    let mut cyu = vec![Complex64::new(0.0, 0.0); nb];
    for k in 1..nb {
        um[k] = mean(&us, k);
        ym[k] = mean(&ys, k);
        if periods >= 2 {
            for q in 0..periods {
                let du = us[q][k] - um[k];
                let dy = ys[q][k] - ym[k];
                vu[k] += du.norm_sqr();
                vy[k] += dy.norm_sqr();
                cyu[k] += dy * du.conj();
            }
            // Sample variance of one period, then of the mean of P periods.
            let norm = (p - 1.0) * p;
            vu[k] /= norm;
            vy[k] /= norm;
            cyu[k] /= norm;
        }
    }
    let max_u = (1..nb).map(|k| um[k].norm()).fold(0.0, f64::max);
    if max_u == 0.0 {
        return Err(EstimateError::NoExcitation(
            "the input spectrum is zero on every line".into(),
        ));
    }
    let excited: Vec<usize> = match selection {
        LineSelection::Auto { relative } => (1..nb)
            .filter(|&k| um[k].norm() >= relative * max_u)
            .filter(|&k| periods < 2 || um[k].norm_sqr() > 100.0 * smooth(&vu, k, smoothing_bins))
            .collect(),
        LineSelection::Explicit(freqs) => {
            let mut b: Vec<usize> = freqs
                .iter()
                .map(|f| (f * np as f64 / fs_hz).round() as usize)
                .filter(|&k| k >= 1 && k < nb)
                .collect();
            b.sort_unstable();
            b.dedup();
            b
        }
    };
    let is_excited = {
        let mut v = vec![false; nb];
        for &k in &excited {
            v[k] = true;
        }
        v
    };
    let max_y = excited
        .iter()
        .map(|&k| ym[k].norm_sqr())
        .fold(0.0, f64::max);
    let lines: Vec<SpectralLine> = excited
        .iter()
        .map(|&k| {
            let (var_u, var_y, cov_yu) = if periods >= 2 {
                (
                    smooth(&vu, k, smoothing_bins),
                    smooth(&vy, k, smoothing_bins),
                    smooth_c(&cyu, k, smoothing_bins),
                )
            } else {
                // One period: the noise level is what the non-excited neighbours hold.
                (
                    0.0,
                    neighbours_power(&ym, &is_excited, k, 2 * smoothing_bins),
                    Complex64::new(0.0, 0.0),
                )
            };
            SpectralLine {
                bin: k,
                freq_hz: k as f64 * fs_hz / np as f64,
                u: um[k],
                y: ym[k],
                var_u,
                var_y,
                cov_yu,
            }
        })
        .collect();
    let noise_free = lines.iter().all(|l| l.var_y <= 1e-24 * max_y);
    Ok(PeriodicSpectra {
        fs_hz,
        period_samples: np,
        periods,
        lines,
        noise_free,
    })
}

fn window(k: usize, w: usize, len: usize) -> std::ops::Range<usize> {
    k.saturating_sub(w).max(1)..(k + w + 1).min(len)
}

fn smooth(v: &[f64], k: usize, w: usize) -> f64 {
    let r = window(k, w, v.len());
    let n = r.len() as f64;
    v[r].iter().sum::<f64>() / n
}

fn smooth_c(v: &[Complex64], k: usize, w: usize) -> Complex64 {
    let r = window(k, w, v.len());
    let n = r.len() as f64;
    v[r].iter().sum::<Complex64>() / n
}

fn neighbours_power(y: &[Complex64], excited: &[bool], k: usize, w: usize) -> f64 {
    let r = window(k, w, y.len());
    let vals: Vec<f64> = r
        .filter(|&j| !excited[j])
        .map(|j| y[j].norm_sqr())
        .collect();
    if vals.is_empty() {
        0.0
    } else {
        vals.iter().sum::<f64>() / vals.len() as f64
    }
}

/// Removes a linear drift from a record of `periods` whole periods: the slope is fitted to the
/// period means (a periodic signal has the same mean in every period, so only drift moves
/// them) and the line through them is subtracted. Thermal drift and actuator creep otherwise
/// leak into the lowest lines as a 1/k skirt. With fewer than two periods the record is
/// returned unchanged.
pub fn remove_linear_drift(x: &[f64], periods: usize) -> Vec<f64> {
    if periods < 2 || !x.len().is_multiple_of(periods) {
        return x.to_vec();
    }
    let np = x.len() / periods;
    let means: Vec<f64> = x
        .chunks(np)
        .map(|c| c.iter().sum::<f64>() / np as f64)
        .collect();
    let pc = (periods as f64 - 1.0) / 2.0;
    let num: f64 = means
        .iter()
        .enumerate()
        .map(|(p, m)| (p as f64 - pc) * m)
        .sum();
    let den: f64 = (0..periods).map(|p| (p as f64 - pc).powi(2)).sum();
    let slope_per_sample = num / den / np as f64;
    let centre = (x.len() as f64 - 1.0) / 2.0;
    x.iter()
        .enumerate()
        .map(|(i, v)| v - slope_per_sample * (i as f64 - centre))
        .collect()
}

/// Pools the excited lines of several records of the same material (e.g. the successive
/// iterations of a design loop) into one set, so that one fit uses all the information
/// gathered so far. Each line keeps its own record's noise. `None` for an empty slice or
/// records at different sample rates.
pub fn pool_spectra(records: &[PeriodicSpectra]) -> Option<PeriodicSpectra> {
    let first = records.first()?;
    if records.iter().any(|r| r.fs_hz != first.fs_hz) {
        return None;
    }
    Some(PeriodicSpectra {
        fs_hz: first.fs_hz,
        period_samples: first.period_samples,
        periods: records.iter().map(|r| r.periods).min().unwrap_or(1),
        lines: records
            .iter()
            .flat_map(|r| r.lines.iter().copied())
            .collect(),
        noise_free: records.iter().all(|r| r.noise_free),
    })
}

/// Fits a Prony series of `opts.order` terms to periodic data.
pub fn fit_periodic(
    u: &[f64],
    y: &[f64],
    fs_hz: f64,
    opts: &FrequencyFitOptions,
) -> Result<Estimate, EstimateError> {
    let spectra = periodic_spectra(
        u,
        y,
        fs_hz,
        opts.periods,
        &opts.lines,
        opts.noise_smoothing_bins,
    )?;
    fit_spectra(&spectra, opts)
}

/// `G` and `∂G/∂ln θ` for log-parameters in the solver's (unsorted) order.
fn response(p: &[f64], n: usize, sampling: &Sampling, freq_hz: f64) -> (Complex64, Vec<Complex64>) {
    let j0 = p[0].exp();
    let mut g = Complex64::new(j0, 0.0);
    let mut d = vec![Complex64::new(0.0, 0.0); p.len()];
    d[0] = Complex64::new(j0, 0.0);
    for i in 0..n {
        let (ji, tau) = (p[1 + i].exp(), p[1 + n + i].exp());
        let (h, dh) = sampling.term(tau, freq_hz);
        g -= ji * h;
        d[1 + i] = -ji * h;
        d[1 + n + i] = -ji * dh;
    }
    (g, d)
}

/// Fits the excited lines of `spectra`.
pub fn fit_spectra(
    spectra: &PeriodicSpectra,
    opts: &FrequencyFitOptions,
) -> Result<Estimate, EstimateError> {
    let n = opts.order;
    if n == 0 {
        return Err(EstimateError::Order(0));
    }
    let n_params = 2 * n + 1;
    let lines = &spectra.lines;
    let needed = n_params.div_ceil(2);
    if lines.len() < needed {
        return Err(EstimateError::UnderDetermined {
            lines: lines.len(),
            observations: 2 * lines.len(),
            params: n_params,
            order: n,
            needed,
        });
    }
    // Without measurable noise, weight each line by its own size so every line counts.
    let floor: Vec<f64> = lines
        .iter()
        .map(|l| {
            if spectra.noise_free {
                1e-12 * l.y.norm_sqr()
            } else {
                0.0
            }
        })
        .collect();
    let variance = |i: usize, g: Complex64| -> f64 {
        let l = &lines[i];
        if spectra.noise_free {
            floor[i]
        } else {
            (l.var_y + g.norm_sqr() * l.var_u - 2.0 * (g.conj() * l.cov_yu).re).max(1e-300)
        }
    };
    let m = lines.len();
    let eval = |p: &[f64]| -> Evaluation {
        if p.iter().any(|v| !v.is_finite() || v.abs() > 700.0) {
            return None;
        }
        let mut r = DVector::zeros(2 * m);
        let mut jac = DMatrix::zeros(2 * m, p.len());
        for (i, l) in lines.iter().enumerate() {
            let (g, dg) = response(p, n, &opts.sampling, l.freq_hz);
            let d = variance(i, g);
            let num = l.y - g * l.u;
            let sd = d.sqrt();
            let e = num / sd * std::f64::consts::SQRT_2;
            r[i] = e.re;
            r[m + i] = e.im;
            for (k, dgk) in dg.iter().enumerate() {
                let dnum = -dgk * l.u;
                let dd = if spectra.noise_free {
                    0.0
                } else {
                    2.0 * (g.conj() * dgk).re * l.var_u - 2.0 * (dgk.conj() * l.cov_yu).re
                };
                let de = (dnum / sd - num * (0.5 * dd / (d * sd))) * std::f64::consts::SQRT_2;
                jac[(i, k)] = de.re;
                jac[(m + i, k)] = de.im;
            }
        }
        Some((r, jac))
    };

    // Start values: τ grid spanning the excited band, scored by variable projection.
    let f_lo = lines
        .iter()
        .map(|l| l.freq_hz)
        .fold(f64::INFINITY, f64::min);
    let f_hi = lines.iter().map(|l| l.freq_hz).fold(0.0, f64::max);
    let two_pi = 2.0 * std::f64::consts::PI;
    let taus = log_grid(
        0.25 / (two_pi * f_hi),
        4.0 / (two_pi * f_lo),
        opts.grid_size.max(n),
    );
    let w: Vec<f64> = (0..m)
        .map(|i| 1.0 / variance(i, lines[i].y / lines[i].u).sqrt())
        .collect();
    let stack = |z: &dyn Fn(usize) -> Complex64| -> Vec<f64> {
        (0..m)
            .map(|i| z(i).re * w[i])
            .chain((0..m).map(|i| z(i).im * w[i]))
            .collect()
    };
    let target = stack(&|i| lines[i].y);
    let j0_col = stack(&|i| lines[i].u);
    let columns: Vec<Vec<f64>> = taus
        .iter()
        .map(|&t| stack(&|i| -lines[i].u * opts.sampling.term(t, lines[i].freq_hz).0))
        .collect();
    let starts = with_prior(
        grid_starts(&target, &j0_col, &columns, &taus, n, opts.starts),
        opts.extra_start.as_ref(),
        n,
    )?;
    let (best, rcond) = solve_from_starts(&starts, eval, opts.lm)?;
    let dof = (2 * m).saturating_sub(n_params);
    let mut diagnostics = Diagnostics {
        cost: best.cost,
        dof,
        cost_per_dof: if dof > 0 {
            best.cost / dof as f64
        } else {
            f64::NAN
        },
        iterations: best.iterations,
        observations: m,
        noise_free: spectra.noise_free,
        warnings: Vec::new(),
    };
    let mut cov = spd_inverse(&best.jtj).ok_or(EstimateError::IllConditioned { rcond })?;
    if spectra.noise_free {
        // Weights were arbitrary: scale by the residual variance instead.
        let s2 = if dof > 0 { best.cost / dof as f64 } else { 0.0 };
        cov *= s2;
        diagnostics
            .warnings
            .push("no measurable noise between periods: intervals from residuals".into());
    } else if dof > 0 && best.cost > dof as f64 + 3.0 * (2.0 * dof as f64).sqrt() {
        // The residuals exceed the measured noise: model error or unmodelled noise.
        // Widen the intervals by the excess rather than report false precision.
        cov *= best.cost / dof as f64;
        diagnostics.warnings.push(format!(
            "residuals are {:.2}× the measured noise (cost/dof); intervals widened accordingly",
            best.cost / dof as f64
        ));
    }
    if spectra.periods < 2 {
        diagnostics
            .warnings
            .push("one period only: noise taken from non-excited neighbouring lines".into());
    }
    Ok(Estimate::from_log_fit(
        Method::FrequencyMl,
        &best.params,
        cov,
        diagnostics,
    ))
}

/// Cramér–Rao bound (relative, log-parameters) of the lines in `spectra` at `model`, with the
/// spectra's own noise: what the fit's covariance would be at the truth.
pub fn crlb_for_spectra(
    model: &PronySeries,
    spectra: &PeriodicSpectra,
    sampling: &Sampling,
) -> Option<Vec<f64>> {
    let p = model.n_params();
    let mut fim = DMatrix::<f64>::zeros(p, p);
    let lp: Vec<f64> = model.to_vec().iter().map(|v| v.ln()).collect();
    for l in &spectra.lines {
        let (g, dg) = response(&lp, model.order(), sampling, l.freq_hz);
        let d = l.var_y + g.norm_sqr() * l.var_u - 2.0 * (g.conj() * l.cov_yu).re;
        for i in 0..p {
            for j in 0..p {
                fim[(i, j)] += 2.0 * ((dg[i] * l.u).conj() * dg[j] * l.u).re / d;
            }
        }
    }
    crate::fisher::relative_crlb(&fim)
}
