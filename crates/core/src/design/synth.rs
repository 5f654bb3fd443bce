//! Multisine synthesis: from a design's power fractions to a sampled, periodic input signal.
//!
//! `u(t) = offset + Σ A_i·sin(2π f_i t + φ_i)` with `A_i = sqrt(2·P·p_i)`, so that the AC part
//! has mean square `P`. The phases start from Schroeder's formula for unequal powers,
//! `φ_k = −2π Σ_{l<k} (k − l)·p_l`, and are then improved by iterative clipping: the signal is
//! clipped at 70 %, later 80 % and 90 % of its peak, its spectrum is taken, the phases at the design lines are kept,
//! the amplitudes are re-imposed exactly and every other bin is zeroed; the phases with the
//! lowest crest factor seen are kept. The clipping runs from Schroeder's phases and from four
//! reproducible pseudo-random phase sets. One period is computed by an inverse FFT (the lines sit
//! exactly on the period's DFT bins) and repeated over the record, so the signal is exactly
//! periodic and its spectrum has energy only at the design lines.

use super::{Design, DesignError, DesignLine};
use crate::fisher::Line;
use rustfft::num_complex::Complex64;
use rustfft::FftPlanner;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Extra clipping runs from pseudo-random phases, besides the one from Schroeder's phases.
const RESTARTS: usize = 4;

/// How loud the multisine is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", content = "value", rename_all = "snake_case")]
pub enum Level {
    /// RMS of the AC part (units of u): total power `P = rms²`.
    Rms(f64),
    /// Peak deviation `max |u − offset|` of the sampled signal (units of u).
    Peak(f64),
}

/// Signal settings for [`synthesize`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SynthConfig {
    pub level: Level,
    /// If set, the offset is chosen so that the signal's minimum equals this preload (the
    /// tip never loses contact); otherwise the offset is 0.
    pub preload_min: Option<f64>,
    /// Clipping iterations of the crest-factor reduction (0: Schroeder phases only).
    pub clip_iterations: usize,
}

impl Default for SynthConfig {
    fn default() -> Self {
        Self {
            level: Level::Rms(1.0),
            preload_min: None,
            clip_iterations: 200,
        }
    }
}

/// One synthesised line: `A·sin(2π f t + φ)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SynthLine {
    /// Hz.
    pub freq_hz: f64,
    /// Sine amplitude, units of u.
    pub amplitude: f64,
    /// Phase, rad.
    pub phase_rad: f64,
}

/// A periodic multisine, sampled.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Multisine {
    /// Sample rate, Hz.
    pub fs_hz: f64,
    /// One period, s.
    pub period_s: f64,
    /// Periods in `samples`.
    pub periods: usize,
    /// Constant offset (preload), units of u.
    pub offset: f64,
    /// The lines, ascending frequency.
    pub lines: Vec<SynthLine>,
    /// `u` at `t = k/fs`, k = 0 … periods·period·fs − 1.
    pub samples: Vec<f64>,
    /// RMS of the AC part, units of u.
    pub rms: f64,
    /// `max |u − offset|`, units of u.
    pub peak: f64,
    /// `peak/rms` of the AC part.
    pub crest_factor: f64,
    /// Crest factor of the Schroeder phases alone (before clipping iterations).
    pub schroeder_crest_factor: f64,
}

impl Multisine {
    /// The lines as the Fisher-information module wants them.
    pub fn fisher_lines(&self) -> Vec<Line> {
        self.lines
            .iter()
            .map(|l| Line {
                freq_hz: l.freq_hz,
                amplitude: l.amplitude,
            })
            .collect()
    }

    /// Total AC power (mean square of `u − offset`), units of u².
    pub fn power(&self) -> f64 {
        self.lines
            .iter()
            .map(|l| l.amplitude * l.amplitude / 2.0)
            .sum()
    }
}

/// Synthesises the multisine of a design (its sample rate, period and periods).
pub fn synthesize(design: &Design, cfg: &SynthConfig) -> Result<Multisine, DesignError> {
    synthesize_lines(
        &design.lines,
        design.fs_hz,
        design.period_s,
        design.periods,
        cfg,
    )
}

/// Synthesises a multisine from arbitrary lines, which must lie on the DFT grid of one period
/// (`f·period` an integer) strictly between 0 and `fs/2`.
pub fn synthesize_lines(
    lines: &[DesignLine],
    fs_hz: f64,
    period_s: f64,
    periods: usize,
    cfg: &SynthConfig,
) -> Result<Multisine, DesignError> {
    let bad = |m: String| Err(DesignError::InvalidSignal(m));
    let len_f = fs_hz * period_s;
    if !(len_f.is_finite() && len_f >= 4.0)
        || (len_f - len_f.round()).abs() > 1e-6 * len_f
        || periods == 0
    {
        return bad(format!(
            "{period_s} s at {fs_hz} Hz is not a whole number (≥ 4) of samples, or no periods"
        ));
    }
    let len = len_f.round() as usize;
    match cfg.level {
        Level::Rms(x) | Level::Peak(x) if !(x.is_finite() && x > 0.0) => {
            return bad(format!("signal level must be positive, got {x}"));
        }
        _ => {}
    }
    if let Some(pre) = cfg.preload_min {
        if !pre.is_finite() {
            return bad(format!("preload must be finite, got {pre}"));
        }
    }
    let mut sorted: Vec<DesignLine> = lines
        .iter()
        .copied()
        .filter(|l| l.power_frac > 0.0)
        .collect();
    sorted.sort_by(|a, b| a.freq_hz.total_cmp(&b.freq_hz));
    let total: f64 = sorted.iter().map(|l| l.power_frac).sum();
    if sorted.is_empty() || !total.is_finite() {
        return bad("a multisine needs at least one line with positive power".into());
    }
    let mut bins = Vec::with_capacity(sorted.len());
    for l in &sorted {
        let m = l.freq_hz * period_s;
        if !((m - m.round()).abs() <= 1e-6 * m.max(1.0)
            && m.round() >= 1.0
            && 2.0 * m.round() < len as f64)
        {
            return bad(format!(
                "line {} Hz is not on the {} Hz grid of the period strictly inside (0, fs/2)",
                l.freq_hz,
                1.0 / period_s
            ));
        }
        let m = m.round() as usize;
        if bins.last() == Some(&m) {
            return bad(format!("two lines on the same DFT bin ({} Hz)", l.freq_hz));
        }
        bins.push(m);
    }
    let fracs: Vec<f64> = sorted.iter().map(|l| l.power_frac / total).collect();
    // Unit power: A_i = sqrt(2 p_i).
    let amps: Vec<f64> = fracs.iter().map(|p| (2.0 * p).sqrt()).collect();
    let mut phases: Vec<f64> = (0..fracs.len())
        .map(|k| -2.0 * PI * (0..k).map(|l| (k - l) as f64 * fracs[l]).sum::<f64>())
        .collect();

    let mut planner = FftPlanner::<f64>::new();
    let inv = planner.plan_fft_inverse(len);
    let fwd = planner.plan_fft_forward(len);
    let render = |phases: &[f64]| -> Vec<f64> {
        let mut x = vec![Complex64::new(0.0, 0.0); len];
        for ((&m, &a), &ph) in bins.iter().zip(&amps).zip(phases) {
            // A·sin(θ + φ) = Re{A·e^{j(θ + φ − π/2)}}: half of it in bin m, its conjugate in L − m.
            let c = Complex64::from_polar(a / 2.0, ph - PI / 2.0);
            x[m] += c;
            x[len - m] += c.conj();
        }
        inv.process(&mut x);
        x.iter().map(|c| c.re).collect()
    };
    let peak_of = |u: &[f64]| u.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let rms_of = |u: &[f64]| (u.iter().map(|x| x * x).sum::<f64>() / u.len() as f64).sqrt();

    let schroeder_crest = {
        let u = render(&phases);
        peak_of(&u) / rms_of(&u)
    };
    let mut best = (schroeder_crest, phases.clone());
    // Clipping from the Schroeder phases and from a few deterministic pseudo-random phase
    // sets (xorshift; the result is reproducible); the lowest crest factor wins.
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    for start in 0..=RESTARTS {
        if start > 0 {
            for ph in phases.iter_mut() {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                *ph = 2.0 * PI * (state >> 11) as f64 / (1u64 << 53) as f64;
            }
        }
        let mut u = render(&phases);
        for it in 0..cfg.clip_iterations {
            // hard clipping first (explores), gentle at the end (refines)
            let ratio = [0.7, 0.8, 0.9][(3 * it / cfg.clip_iterations).min(2)];
            let level = ratio * peak_of(&u);
            let mut x: Vec<Complex64> = u
                .iter()
                .map(|v| Complex64::new(v.clamp(-level, level), 0.0))
                .collect();
            fwd.process(&mut x);
            for (ph, &m) in phases.iter_mut().zip(&bins) {
                if x[m].norm() > 0.0 {
                    *ph = x[m].arg() + PI / 2.0;
                }
            }
            u = render(&phases);
            let crest = peak_of(&u) / rms_of(&u);
            if crest < best.0 {
                best = (crest, phases.clone());
            }
        }
        if cfg.clip_iterations == 0 {
            break;
        }
    }
    let phases = best.1;
    let u_unit = render(&phases);
    let scale = match cfg.level {
        Level::Rms(r) => r / rms_of(&u_unit),
        Level::Peak(pk) => pk / peak_of(&u_unit),
    };
    let ac: Vec<f64> = u_unit.iter().map(|x| x * scale).collect();
    let mut offset = match cfg.preload_min {
        Some(pre) => pre - ac.iter().fold(f64::INFINITY, |m, x| m.min(*x)),
        None => 0.0,
    };
    if let Some(pre) = cfg.preload_min {
        // rounding of offset + u may land an ulp below the preload
        for _ in 0..4 {
            let lowest = ac.iter().fold(f64::INFINITY, |m, x| m.min(offset + x));
            if lowest >= pre {
                break;
            }
            offset += (pre - lowest).max(f64::EPSILON * offset.abs().max(pre.abs()));
        }
    }
    let one: Vec<f64> = ac.iter().map(|x| offset + x).collect();
    let samples = one.repeat(periods);
    let rms = rms_of(&ac);
    let peak = peak_of(&ac);
    let lines = sorted
        .iter()
        .zip(&amps)
        .zip(&phases)
        .map(|((l, a), ph)| SynthLine {
            freq_hz: l.freq_hz,
            amplitude: a * scale,
            phase_rad: ph.rem_euclid(2.0 * PI),
        })
        .collect();
    Ok(Multisine {
        fs_hz,
        period_s,
        periods,
        offset,
        lines,
        samples,
        rms,
        peak,
        crest_factor: peak / rms,
        schroeder_crest_factor: schroeder_crest,
    })
}
