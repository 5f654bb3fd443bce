//! Is the in-contact drive periodic, and where are its whole periods?
//!
//! Decided from the drive alone (a third-party file says nothing about its excitation):
//! candidate periods are the highest peaks of the drive's autocorrelation (FFT, zero-padded);
//! a candidate `P` is accepted when `d[k] = d[k + P]` holds, within the drive's own
//! repetition noise, over a run of at least two whole periods, and the drive actually moves
//! within one period (a hold, a ramp or noise around a constant are not an excitation). The
//! smallest accepted `P` is the fundamental.

use rustfft::num_complex::Complex64;
use rustfft::FftPlanner;

/// Whole periods of a periodic drive, as indices into the slice that was searched.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PeriodicRun {
    /// First sample of the first whole period.
    pub start: usize,
    pub period_samples: usize,
    /// Whole periods from `start` on.
    pub periods: usize,
}

/// Shortest period considered, samples.
const MIN_PERIOD: usize = 8;
/// How many autocorrelation peaks are tried.
const CANDIDATES: usize = 12;

/// Finds the whole periods of `drive`, or `None` when it is not periodic (at least two whole
/// periods of a moving drive).
pub fn detect_periodic(drive: &[f64]) -> Option<PeriodicRun> {
    let n = drive.len();
    if n < 2 * MIN_PERIOD {
        return None;
    }
    let mean = drive.iter().sum::<f64>() / n as f64;
    let x: Vec<f64> = drive.iter().map(|v| v - mean).collect();
    let energy: f64 = x.iter().map(|v| v * v).sum();
    if energy <= 0.0 {
        return None;
    }
    let m = (2 * n).next_power_of_two();
    let mut planner = FftPlanner::<f64>::new();
    let mut buf: Vec<Complex64> = x
        .iter()
        .map(|&v| Complex64::new(v, 0.0))
        .chain(std::iter::repeat(Complex64::new(0.0, 0.0)))
        .take(m)
        .collect();
    planner.plan_fft_forward(m).process(&mut buf);
    for z in buf.iter_mut() {
        *z = Complex64::new(z.norm_sqr(), 0.0);
    }
    planner.plan_fft_inverse(m).process(&mut buf);
    let r: Vec<f64> = buf[..=n / 2]
        .iter()
        .map(|z| z.re / (m as f64 * energy))
        .collect();
    // Past the main lobe (the first zero crossing) the highest peaks are the period and its
    // multiples; inside it, ripples of the high lines would crowd them out.
    let lobe = r.iter().position(|v| *v < 0.0).unwrap_or(r.len());
    let mut peaks: Vec<usize> = (MIN_PERIOD.max(lobe)..r.len().saturating_sub(1))
        .filter(|&p| r[p] > 0.0 && r[p] >= r[p - 1] && r[p] >= r[p + 1])
        .collect();
    peaks.sort_by(|&a, &b| r[b].total_cmp(&r[a]));
    peaks.truncate(CANDIDATES);
    // Local maxima can sit one sample off a fractional-looking period: try neighbours too.
    let mut candidates: Vec<usize> = peaks
        .iter()
        .flat_map(|&p| [p.saturating_sub(1), p, p + 1])
        .filter(|&p| p >= MIN_PERIOD && 2 * p <= n)
        .collect();
    candidates.sort_unstable();
    candidates.dedup();
    let range = drive.iter().copied().fold(f64::NEG_INFINITY, f64::max)
        - drive.iter().copied().fold(f64::INFINITY, f64::min);
    candidates
        .into_iter()
        .find_map(|p| check_period(drive, p, range))
}

/// The longest run of whole periods of length `p`, if it is a real excitation.
fn check_period(d: &[f64], p: usize, range: f64) -> Option<PeriodicRun> {
    let n = d.len();
    let e: Vec<f64> = (0..n - p).map(|k| (d[k] - d[k + p]).abs()).collect();
    let mut sorted = e.clone();
    sorted.sort_by(f64::total_cmp);
    // Repetition noise from the 20th percentile of the mismatch (|N(0, s²)| has it at
    // 0.2533·s), so that a fifth of the window repeating is enough to measure it.
    let sigma = sorted[sorted.len() / 5] / 0.2533;
    let tol = 1e-9 * range.max(f64::MIN_POSITIVE) + 4.0 * sigma;
    let (mut best_a, mut best_len, mut a) = (0usize, 0usize, 0usize);
    for (k, &ek) in e.iter().enumerate() {
        if ek > tol {
            a = k + 1;
        } else if k + 1 - a > best_len {
            best_len = k + 1 - a;
            best_a = a;
        }
    }
    let span = best_len + p;
    let periods = span / p;
    if periods < 2 {
        return None;
    }
    let one = &d[best_a..best_a + p];
    let m = one.iter().sum::<f64>() / p as f64;
    let rms = (one.iter().map(|v| (v - m).powi(2)).sum::<f64>() / p as f64).sqrt();
    (rms > 10.0 * tol && rms > 1e-6 * range).then_some(PeriodicRun {
        start: best_a,
        period_samples: p,
        periods,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn multisine(np: usize) -> Vec<f64> {
        (0..np)
            .map(|k| {
                let t = k as f64 / np as f64;
                let w = 2.0 * std::f64::consts::PI;
                (w * t).sin() + 0.5 * (w * 7.0 * t + 1.0).sin() + 0.3 * (w * 31.0 * t).cos()
            })
            .collect()
    }

    #[test]
    fn finds_whole_periods_between_hold_and_retract() {
        let np = 1000;
        let mut d: Vec<f64> = (0..300).map(|k| k as f64 / 300.0).collect();
        d.extend(std::iter::repeat_n(1.0, 500));
        let one = multisine(np);
        for _ in 0..3 {
            d.extend(one.iter().map(|v| 1.0 + 0.2 * v));
        }
        d.extend((0..200).map(|k| 1.0 - k as f64 / 200.0));
        let run = detect_periodic(&d).expect("periodic");
        assert_eq!(run.period_samples, np);
        assert_eq!(run.periods, 3);
        // The first whole period may start anywhere the repetition starts.
        assert!((run.start as i64 - 800).abs() <= 1, "{run:?}");
    }

    #[test]
    fn holds_ramps_and_steps_are_not_periodic() {
        let ramp_hold: Vec<f64> = (0..5000).map(|k| (k as f64 / 500.0).min(1.0)).collect();
        assert_eq!(detect_periodic(&ramp_hold), None);
        let step: Vec<f64> = (0..5000).map(|k| if k < 10 { 0.0 } else { 2.0 }).collect();
        assert_eq!(detect_periodic(&step), None);
        // Noise around a slow creep.
        let mut s = 1u64;
        let noisy: Vec<f64> = (0..5000)
            .map(|k| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                k as f64 * 1e-4 + ((s >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 1e-3
            })
            .collect();
        assert_eq!(detect_periodic(&noisy), None);
    }
}
