//! Modeling-free inversion-based iterative control (MIIC, Kim & Zou 2008) as a pure update on
//! spectra, and the tracking-error measures it is judged by.
//!
//! One period of drive `u` (V) produces one period of output `y` (here the deflection, V).
//! Per DFT line, `U_{k+1} = U_k · (1 + ρ·(Y_d/Y_k − 1))` — with ρ = 1 exactly the law
//! `U_{k+1} = U_k·Y_d/Y_k` — on the lines where both the desired and the measured output stand
//! clear of the noise. Lines where the output holds something the desired output does not
//! (harmonics of the contact nonlinearity, hysteresis) are driven to cancel it through the
//! inverse of the drive-to-output ratio measured on the neighbouring excited lines; every other
//! line of the drive is set to zero. It needs no model of the actuator: the measured ratios are
//! the model. The constant (DC) line is not multiplicative
//! (contact makes the static map affine), so it is corrected by an integral step through the
//! measured static slope. The drive it returns is only a proposal: the safety layer below it
//! clips and slew-limits whatever it outputs.

use rustfft::num_complex::Complex64;
use rustfft::FftPlanner;
use serde::Serialize;

/// MIIC settings.
#[derive(Debug, Clone, Copy)]
pub struct MiicConfig {
    /// Relaxation ρ in (0, 1]: 1 is the plain MIIC law.
    pub relaxation: f64,
    /// A line is updated only if |Y_d| and |Y_k| exceed this many noise standard deviations.
    pub snr_threshold: f64,
    /// Bound on the per-iteration change of a line's drive, factor (guards against a line
    /// hit by a noise spike).
    pub max_ratio: f64,
    /// An unwanted output line is cancelled only when it exceeds this many noise standard
    /// deviations (drift leakage and pick-up must not be chased).
    pub cancel_threshold: f64,
    /// Relaxation of the cancellation (its plant is interpolated, hence less certain).
    pub cancel_relaxation: f64,
    /// Relaxation of the integral correction of the mean: creep and the contact's slow
    /// relaxation make the static slope only an estimate, so half steps by default.
    pub dc_relaxation: f64,
}

impl Default for MiicConfig {
    fn default() -> Self {
        Self {
            relaxation: 1.0,
            snr_threshold: 5.0,
            max_ratio: 4.0,
            cancel_threshold: 10.0,
            cancel_relaxation: 0.5,
            dc_relaxation: 0.5,
        }
    }
}

/// Tracking errors of one period, in percent of the desired signal's AC part.
///
/// The excitation is judged on its shape: the error's own mean (a preload offset, which
/// drift moves between steps) is reported separately as `mean_error`, in the signal's units.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TrackingError {
    /// `‖e − mean(e)‖₂ / ‖y_d − mean(y_d)‖₂`, %, with `e = y − y_d`.
    pub err2_pct: f64,
    /// `max|e − mean(e)| / max|y_d − mean(y_d)|`, %.
    pub errinf_pct: f64,
    /// `mean(e)`: the offset of the mean (preload) from the desired one.
    pub mean_error: f64,
}

/// Tracking error of `measured` against `desired` (same length, one or more periods).
pub fn tracking_error(desired: &[f64], measured: &[f64]) -> TrackingError {
    let n = desired.len().min(measured.len()).max(1);
    let mean = desired[..n].iter().sum::<f64>() / n as f64;
    let mean_error = (0..n).map(|i| measured[i] - desired[i]).sum::<f64>() / n as f64;
    let (mut e2, mut d2, mut emax, mut dmax) = (0.0, 0.0, 0.0f64, 0.0f64);
    for i in 0..n {
        let e = measured[i] - desired[i] - mean_error;
        let d = desired[i] - mean;
        e2 += e * e;
        d2 += d * d;
        emax = emax.max(e.abs());
        dmax = dmax.max(d.abs());
    }
    TrackingError {
        err2_pct: 100.0 * (e2 / d2.max(1e-300)).sqrt(),
        errinf_pct: 100.0 * emax / dmax.max(1e-300),
        mean_error,
    }
}

/// Signed frequency of bin `k` of an `n`-point DFT at `fs_hz`: bins above n/2 are the
/// negative frequencies.
pub fn bin_frequency_hz(k: usize, n: usize, fs_hz: f64) -> f64 {
    let k = if k <= n / 2 {
        k as f64
    } else {
        k as f64 - n as f64
    };
    k * fs_hz / n as f64
}

/// DFT of one period (no scaling).
pub fn spectrum(x: &[f64]) -> Vec<Complex64> {
    let mut buf: Vec<Complex64> = x.iter().map(|v| Complex64::new(*v, 0.0)).collect();
    FftPlanner::<f64>::new()
        .plan_fft_forward(buf.len())
        .process(&mut buf);
    buf
}

/// Inverse of [`spectrum`] for a Hermitian spectrum: the real period.
pub fn inverse_spectrum(x: &[Complex64]) -> Vec<f64> {
    let n = x.len();
    let mut buf = x.to_vec();
    FftPlanner::<f64>::new()
        .plan_fft_inverse(n)
        .process(&mut buf);
    buf.iter().map(|z| z.re / n as f64).collect()
}

/// What one MIIC step did.
#[derive(Debug, Clone, PartialEq)]
pub struct MiicStep {
    /// The next drive period, V.
    pub drive: Vec<f64>,
    /// Lines (bins) updated by the ratio law.
    pub updated_lines: Vec<usize>,
}

/// One MIIC iteration on one period.
///
/// `drive`, `desired` and `measured` are one period each (the measured one ideally averaged
/// over several periods); `noise_std` is the per-bin standard deviation of the measured
/// spectrum (the same DFT scaling), e.g. from period-to-period scatter; `static_slope` is
/// d(output)/d(drive) at DC (V/V), used for the integral correction of the mean.
pub fn miic_step(
    drive: &[f64],
    desired: &[f64],
    measured: &[f64],
    noise_std: &[f64],
    static_slope: f64,
    cfg: &MiicConfig,
) -> MiicStep {
    miic_step_with_plant(drive, desired, measured, noise_std, static_slope, cfg, None)
}

/// [`miic_step`] with a denser measured plant for cancelling unwanted lines: `plant(bin)`
/// gives the drive → output ratio at a DFT bin (e.g. from a broadband calibration sweep);
/// without it, the ratios of the present step's excited lines are interpolated.
pub fn miic_step_with_plant(
    drive: &[f64],
    desired: &[f64],
    measured: &[f64],
    noise_std: &[f64],
    static_slope: f64,
    cfg: &MiicConfig,
    plant: Option<&dyn Fn(usize) -> Option<Complex64>>,
) -> MiicStep {
    let n = drive.len();
    let u = spectrum(drive);
    let yd = spectrum(desired);
    let y = spectrum(measured);
    let mut next = vec![Complex64::new(0.0, 0.0); n];
    let mut updated = Vec::new();
    // The plant as measured on the lines that carry the desired output (log-frequency
    // interpolation between them); lines driven only to cancel a harmonic would not tell it.
    let measured_plant: Vec<(f64, Complex64)> = (1..n.div_ceil(2))
        .filter(|&k| {
            let floor = cfg.snr_threshold * noise_std.get(k).copied().unwrap_or(0.0);
            u[k].norm() > 0.0 && yd[k].norm() > floor && y[k].norm() > floor
        })
        .map(|k| (k as f64, y[k] / u[k]))
        .collect();
    for k in 1..n.div_ceil(2) {
        let sigma = noise_std.get(k).copied().unwrap_or(0.0);
        let floor = cfg.snr_threshold * sigma;
        if yd[k].norm() > floor && y[k].norm() > floor && u[k].norm() > 0.0 {
            let mut ratio = yd[k] / y[k];
            let r = ratio.norm();
            if r > cfg.max_ratio {
                ratio *= cfg.max_ratio / r;
            } else if r < 1.0 / cfg.max_ratio {
                ratio *= 1.0 / (cfg.max_ratio * r);
            }
            next[k] = u[k] * (Complex64::new(1.0, 0.0) + cfg.relaxation * (ratio - 1.0));
            next[n - k] = next[k].conj();
            updated.push(k);
        } else if yd[k].norm() > floor {
            // A line not driven yet starts from the desired output (U_0 = α·Y_d, α = 1/slope).
            next[k] = yd[k] / static_slope.max(1e-12);
            next[n - k] = next[k].conj();
            updated.push(k);
        } else if y[k].norm() > cfg.cancel_threshold * sigma {
            // An unwanted component well above the noise: cancel it through the measured plant,
            // interpolated between excited lines (never extrapolated beyond them).
            let inside = measured_plant.first().is_some_and(|p| p.0 <= k as f64)
                && measured_plant.last().is_some_and(|p| p.0 >= k as f64);
            let g = match plant {
                Some(f) => f(k),
                None => interpolate_log(&measured_plant, k as f64).filter(|_| inside),
            };
            if let Some(g) = g.filter(|g| g.norm() > 0.0) {
                next[k] = u[k] - cfg.cancel_relaxation * (y[k] - yd[k]) / g;
                next[n - k] = next[k].conj();
                updated.push(k);
            }
        }
    }
    if n.is_multiple_of(2) {
        next[n / 2] = Complex64::new(0.0, 0.0);
    }
    // DC: integral correction through the static slope.
    let dc_err = (yd[0].re - y[0].re) / n as f64;
    let dc = u[0].re / n as f64 + cfg.dc_relaxation * dc_err / static_slope.max(1e-12);
    next[0] = Complex64::new(dc * n as f64, 0.0);
    MiicStep {
        drive: inverse_spectrum(&next),
        updated_lines: updated,
    }
}

/// Linear interpolation in log-frequency of a complex response known at ascending points;
/// constant beyond the ends.
pub fn interpolate_log(p: &[(f64, Complex64)], f: f64) -> Option<Complex64> {
    let first = p.first()?;
    let last = p.last()?;
    if f <= first.0 {
        return Some(first.1);
    }
    if f >= last.0 {
        return Some(last.1);
    }
    let i = p.partition_point(|q| q.0 < f);
    let (f0, g0) = p[i - 1];
    let (f1, g1) = p[i];
    let w = (f.ln() - f0.ln()) / (f1.ln() - f0.ln());
    Some(g0 * (1.0 - w) + g1 * w)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a linear plant with a resonance and an offset, MIIC converges to the desired output
    /// (it never sees the plant's model).
    #[test]
    fn converges_on_a_linear_resonant_plant() {
        let n = 800;
        let fs = 8000.0;
        // Plant: y = 0.3 + 0.8·(second-order, 900 Hz, Q 10)·u, simulated periodically in the
        // frequency domain.
        let plant = |u: &[f64]| -> Vec<f64> {
            let mut s = spectrum(u);
            for (k, z) in s.iter_mut().enumerate() {
                let f = bin_frequency_hz(k, n, fs);
                let w = f / 900.0;
                *z *= 0.8 / Complex64::new(1.0 - w * w, w / 10.0);
            }
            inverse_spectrum(&s).iter().map(|v| v + 0.3).collect()
        };
        let desired: Vec<f64> = (0..n)
            .map(|i| {
                let t = i as f64 / fs;
                1.0 + [10.0, 150.0, 880.0, 2000.0]
                    .iter()
                    .map(|f| 0.1 * (2.0 * std::f64::consts::PI * f * t + f).sin())
                    .sum::<f64>()
            })
            .collect();
        let mut drive = vec![0.0; n];
        let noise = vec![1e-9; n];
        let mut errs = Vec::new();
        for _ in 0..25 {
            let y = plant(&drive);
            errs.push(tracking_error(&desired, &y));
            drive = miic_step(&drive, &desired, &y, &noise, 0.8, &MiicConfig::default()).drive;
        }
        let last = tracking_error(&desired, &plant(&drive));
        assert!(
            last.err2_pct < 1e-4 && last.errinf_pct < 1e-4,
            "{errs:?} then {last:?}"
        );
    }

    /// A static nonlinearity makes harmonics the desired output does not have; MIIC cancels
    /// them through a calibrated plant (here the exact small-signal gain).
    #[test]
    fn cancels_harmonics_of_a_nonlinear_plant() {
        let n = 1000;
        let plant = |u: &[f64]| -> Vec<f64> { u.iter().map(|v| 2.0 * v + 0.3 * v * v).collect() };
        let desired: Vec<f64> = (0..n)
            .map(|i| {
                let t = i as f64 / n as f64;
                [3.0, 7.0, 20.0]
                    .iter()
                    .map(|f| 0.2 * (2.0 * std::f64::consts::PI * f * t + f).sin())
                    .sum::<f64>()
            })
            .collect();
        let mut drive = vec![0.0; n];
        let noise = vec![1e-9; n];
        for _ in 0..25 {
            let y = plant(&drive);
            let calibrated = |_k: usize| Some(Complex64::new(2.0, 0.0));
            drive = miic_step_with_plant(
                &drive,
                &desired,
                &y,
                &noise,
                2.0,
                &MiicConfig::default(),
                Some(&calibrated),
            )
            .drive;
        }
        let e = tracking_error(&desired, &plant(&drive));
        assert!(e.err2_pct < 0.1, "{e:?}");
    }

    #[test]
    fn tracking_error_of_a_scaled_signal() {
        let d: Vec<f64> = (0..100)
            .map(|i| 5.0 + (i as f64 * std::f64::consts::PI / 25.0).sin())
            .collect();
        let m: Vec<f64> = d.iter().map(|v| 5.0 + 1.01 * (v - 5.0)).collect();
        let e = tracking_error(&d, &m);
        assert!((e.err2_pct - 1.0).abs() < 1e-9 && (e.errinf_pct - 1.0).abs() < 1e-9);
    }
}
