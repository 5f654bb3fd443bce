//! Simulation studies of the paper, as pure functions of a seed: the data behind
//! `viscoprobe reproduce`. Each study simulates the Tustin-discretised truth (the paper's
//! simulation model), adds seeded noise, runs the estimators and returns numbers; printing
//! is the caller's business.

pub mod design_loop;
pub mod table1;

use crate::discrete::simulate_tustin;
use crate::prony::PronySeries;
use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

/// A sum of sines `Σ A_k sin(2π f_k t)` in units of u, sampled at `fs_hz`, `n` samples
/// starting at sample index `start`.
pub fn sum_of_sines(lines: &[(f64, f64)], fs_hz: f64, start: usize, n: usize) -> Vec<f64> {
    (start..start + n)
        .map(|l| {
            let t = l as f64 / fs_hz;
            lines
                .iter()
                .map(|(f, a)| a * (2.0 * std::f64::consts::PI * f * t).sin())
                .sum()
        })
        .collect()
}

/// Periodic steady-state response of the Tustin model to a periodic input: one period of
/// warm-up is simulated and dropped, so every recorded period is the same.
pub fn steady_state_response(
    model: &PronySeries,
    u_one_period: &[f64],
    periods: usize,
    fs_hz: f64,
) -> Vec<f64> {
    let np = u_one_period.len();
    // Warm up long enough for the slowest term to die out (e^-40) and at least one period.
    let slowest = model.terms.iter().map(|t| t.tau_s).fold(0.0, f64::max);
    let warm_periods = ((40.0 * slowest * fs_hz) / np as f64).ceil().max(1.0) as usize;
    let u: Vec<f64> = u_one_period
        .iter()
        .copied()
        .cycle()
        .take(np * (warm_periods + periods))
        .collect();
    let y = simulate_tustin(model, &u, fs_hz);
    y[np * warm_periods..].to_vec()
}

/// White Gaussian noise of standard deviation `std`, seeded.
pub fn white_noise(n: usize, std: f64, seed: u64) -> Vec<f64> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let z: f64 = StandardNormal.sample(&mut rng);
            std * z
        })
        .collect()
}

/// Root mean square.
pub fn rms(x: &[f64]) -> f64 {
    (x.iter().map(|v| v * v).sum::<f64>() / x.len().max(1) as f64).sqrt()
}
