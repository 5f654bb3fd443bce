//! Fisher information of a multisine experiment on the Prony model (the paper's eqs. 13–14).
//!
//! Parameters are the logarithms of `[J0, J1..Jn, τ1..τn]`, the parametrisation of the
//! maximum-likelihood estimator: the inverse Fisher matrix is then directly the squared
//! *relative* Cramér–Rao bound, and D-optimality does not depend on the units.
//!
//! Scaling, stated once: a multisine `u = Σ A_k sin(2π f_k t + φ_k)` sampled at N points that
//! span whole periods, with output noise whose DFT has `E|V(k)|² = N·σ²(f_k)` (σ² is the
//! per-sample variance for white noise), gives
//! `M = (N/2) Σ_k A_k²/σ²(f_k) · Re(g_kᴴ g_k)`, `g_k = ∂G(s_k)/∂ln θ`.

use crate::discrete::Sampling;
use crate::prony::PronySeries;
use nalgebra::DMatrix;
use rustfft::num_complex::Complex64;
use serde::{Deserialize, Serialize};

/// The output-noise spectrum an experiment is planned or analysed against.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum NoiseSpectrum {
    /// White noise with this per-sample standard deviation (units of y).
    White { std: f64 },
    /// A measured spectrum: at each frequency (Hz, ascending) the per-sample variance of the
    /// white noise that would have the same density there. Linear interpolation between
    /// points, constant beyond the ends.
    Measured {
        freq_hz: Vec<f64>,
        variance: Vec<f64>,
    },
}

impl NoiseSpectrum {
    /// Equivalent per-sample variance σ²(f).
    pub fn variance_at(&self, freq_hz: f64) -> f64 {
        match self {
            NoiseSpectrum::White { std } => std * std,
            NoiseSpectrum::Measured {
                freq_hz: f,
                variance: v,
            } => {
                if f.is_empty() {
                    return f64::NAN;
                }
                let i = f.partition_point(|x| *x < freq_hz);
                if i == 0 {
                    v[0]
                } else if i >= f.len() {
                    v[f.len() - 1]
                } else {
                    let w = (freq_hz - f[i - 1]) / (f[i] - f[i - 1]);
                    v[i - 1] * (1.0 - w) + v[i] * w
                }
            }
        }
    }
}

/// `∂G(s)/∂ln θ` at one line, canonical order `[J0, J1..Jn, τ1..τn]`.
pub fn log_sensitivity(model: &PronySeries, sampling: &Sampling, freq_hz: f64) -> Vec<Complex64> {
    let n = model.order();
    let mut g = vec![Complex64::new(0.0, 0.0); 2 * n + 1];
    g[0] = Complex64::new(model.j0_per_pa, 0.0);
    for (i, t) in model.terms.iter().enumerate() {
        let (h, dh) = sampling.term(t.tau_s, freq_hz);
        // ∂/∂ln Ji and ∂/∂ln τi of −Ji·HP_τi
        g[1 + i] = -t.j_per_pa * h;
        g[1 + n + i] = -t.j_per_pa * dh;
    }
    g
}

/// `Re(gᴴ g)` for one line: the information it carries per unit `A²N/(2σ²)`.
pub fn line_information(model: &PronySeries, sampling: &Sampling, freq_hz: f64) -> DMatrix<f64> {
    let g = log_sensitivity(model, sampling, freq_hz);
    let p = g.len();
    DMatrix::from_fn(p, p, |i, j| (g[i].conj() * g[j]).re)
}

/// One excited line: frequency (Hz) and sine amplitude in units of u.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Line {
    pub freq_hz: f64,
    pub amplitude: f64,
}

/// Fisher information (log-parameters) of a multisine with `n_samples` samples.
pub fn fisher_multisine(
    model: &PronySeries,
    sampling: &Sampling,
    lines: &[Line],
    n_samples: usize,
    noise: &NoiseSpectrum,
) -> DMatrix<f64> {
    let p = model.n_params();
    let mut m = DMatrix::<f64>::zeros(p, p);
    for line in lines {
        let w = n_samples as f64 * line.amplitude * line.amplitude
            / (2.0 * noise.variance_at(line.freq_hz));
        m += line_information(model, sampling, line.freq_hz) * w;
    }
    m
}

/// Relative Cramér–Rao bounds (fractions, not percent) from a log-parameter Fisher matrix:
/// `sqrt(diag(M⁻¹))`. `None` when M is singular (the design cannot identify the model).
pub fn relative_crlb(fisher: &DMatrix<f64>) -> Option<Vec<f64>> {
    let inv = crate::linalg::spd_inverse(fisher)?;
    Some(
        (0..inv.nrows())
            .map(|i| inv[(i, i)].max(0.0).sqrt())
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The analytic sensitivities agree with central differences of G.
    #[test]
    fn sensitivities_match_finite_differences() {
        let m = PronySeries::paper_pdms();
        let samp = Sampling::Tustin { fs_hz: 8000.0 };
        for f in [1.0, 55.0, 336.0, 2000.0] {
            let g = log_sensitivity(&m, &samp, f);
            let v = m.to_vec();
            for k in 0..v.len() {
                let h: f64 = 1e-6;
                let mut up = v.clone();
                let mut dn = v.clone();
                up[k] *= h.exp();
                dn[k] *= (-h).exp();
                let fd = (samp.response(&PronySeries::from_vec(&up), f)
                    - samp.response(&PronySeries::from_vec(&dn), f))
                    / (2.0 * h);
                assert!(
                    (fd - g[k]).norm() < 1e-6 * m.j0_per_pa,
                    "f {f} k {k}: {fd} vs {}",
                    g[k]
                );
            }
        }
    }

    /// One static parameter y = J0·u: the bound is σ/(A·J0·sqrt(N/2)), the textbook result.
    #[test]
    fn single_parameter_bound_is_textbook() {
        let m = PronySeries::new(2e-6, vec![]);
        let (a, n, std) = (3.0, 1000, 1e-7);
        let fim = fisher_multisine(
            &m,
            &Sampling::Continuous,
            &[Line {
                freq_hz: 10.0,
                amplitude: a,
            }],
            n,
            &NoiseSpectrum::White { std },
        );
        let rel = relative_crlb(&fim).unwrap()[0];
        let expected = std / (a * 2e-6 * (n as f64 / 2.0).sqrt());
        assert!((rel - expected).abs() < 1e-12 * expected);
    }

    #[test]
    fn too_few_lines_are_singular() {
        let m = PronySeries::paper_pdms();
        let lines: Vec<Line> = [1.0, 10.0, 100.0]
            .iter()
            .map(|&f| Line {
                freq_hz: f,
                amplitude: 1.0,
            })
            .collect();
        let fim = fisher_multisine(
            &m,
            &Sampling::Continuous,
            &lines,
            16000,
            &NoiseSpectrum::White { std: 1e-9 },
        );
        assert!(
            relative_crlb(&fim).is_none(),
            "3 lines cannot identify 7 parameters"
        );
    }
}
