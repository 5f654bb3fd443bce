//! The Prony-series creep compliance and the viscoelastic functions derived from it.
//!
//! `J(t) = J0 − Σ Ji·exp(−t/τi)`; in Laplace form `G(s) = J0 − Σ Ji·s/(s + 1/τi)`.
//! Every quantity is in SI units: compliances in 1/Pa, retardation times in seconds,
//! angular frequencies in rad/s, moduli in Pa. Compliance here is the uniaxial (Young's)
//! compliance of an incompressible material (ν = 0.5), the convention of the paper's
//! Hertz–Lee–Radok transform; see [`crate::contact`] for other Poisson ratios.

use rustfft::num_complex::Complex64;
use serde::{Deserialize, Serialize};

/// One retardation term `Ji·exp(−t/τi)` of a Prony series.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PronyTerm {
    /// Compliance coefficient Ji, 1/Pa.
    pub j_per_pa: f64,
    /// Retardation time τi, s.
    pub tau_s: f64,
}

/// A truncated Prony series `J(t) = J0 − Σ Ji·exp(−t/τi)`.
///
/// Terms are kept sorted slowest first (τ1 > τ2 > …), the order of the paper's tables.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PronySeries {
    /// Fully relaxed (long-time) compliance J0, 1/Pa.
    pub j0_per_pa: f64,
    /// Retardation terms, slowest first.
    pub terms: Vec<PronyTerm>,
}

impl PronySeries {
    /// Builds a series and sorts its terms slowest first.
    pub fn new(j0_per_pa: f64, mut terms: Vec<PronyTerm>) -> Self {
        terms.sort_by(|a, b| b.tau_s.total_cmp(&a.tau_s));
        Self { j0_per_pa, terms }
    }

    /// The paper's PDMS material (Table I, "Act." column): J in µPa⁻¹ and τ in ms there.
    pub fn paper_pdms() -> Self {
        Self::new(
            9.11e-6,
            vec![
                PronyTerm {
                    j_per_pa: 2.08e-6,
                    tau_s: 25.28e-3,
                },
                PronyTerm {
                    j_per_pa: 1.53e-6,
                    tau_s: 2.9e-3,
                },
                PronyTerm {
                    j_per_pa: 1.51e-6,
                    tau_s: 0.474e-3,
                },
            ],
        )
    }

    /// Number of retardation terms n.
    pub fn order(&self) -> usize {
        self.terms.len()
    }

    /// Number of free parameters, 2n + 1.
    pub fn n_params(&self) -> usize {
        2 * self.terms.len() + 1
    }

    /// Parameters in the canonical order `[J0, J1..Jn, τ1..τn]` (SI).
    pub fn to_vec(&self) -> Vec<f64> {
        let mut v = Vec::with_capacity(self.n_params());
        v.push(self.j0_per_pa);
        v.extend(self.terms.iter().map(|t| t.j_per_pa));
        v.extend(self.terms.iter().map(|t| t.tau_s));
        v
    }

    /// Inverse of [`Self::to_vec`]; the result is re-sorted slowest first.
    pub fn from_vec(v: &[f64]) -> Self {
        assert!(
            v.len() % 2 == 1,
            "a Prony parameter vector has odd length 2n+1"
        );
        let n = (v.len() - 1) / 2;
        let terms = (0..n)
            .map(|i| PronyTerm {
                j_per_pa: v[1 + i],
                tau_s: v[1 + n + i],
            })
            .collect();
        Self::new(v[0], terms)
    }

    /// Parameter names in canonical order: `J0, J1.., tau1..`.
    pub fn param_names(order: usize) -> Vec<String> {
        let mut names = vec!["J0".to_string()];
        names.extend((1..=order).map(|i| format!("J{i}")));
        names.extend((1..=order).map(|i| format!("tau{i}")));
        names
    }

    /// Creep compliance J(t), 1/Pa, for t ≥ 0 s.
    pub fn creep_compliance(&self, t_s: f64) -> f64 {
        self.j0_per_pa
            - self
                .terms
                .iter()
                .map(|t| t.j_per_pa * (-t_s / t.tau_s).exp())
                .sum::<f64>()
    }

    /// Transfer function `G(s)` from u to y evaluated at a complex `s` (rad/s).
    pub fn transfer(&self, s: Complex64) -> Complex64 {
        let mut g = Complex64::new(self.j0_per_pa, 0.0);
        for t in &self.terms {
            g -= t.j_per_pa * s / (s + 1.0 / t.tau_s);
        }
        g
    }

    /// Complex compliance J*(ω) = G(jω), 1/Pa. Its imaginary part is negative (strain lags).
    pub fn complex_compliance(&self, omega_rad_s: f64) -> Complex64 {
        self.transfer(Complex64::new(0.0, omega_rad_s))
    }

    /// Instantaneous (glassy, t → 0) compliance `J0 − ΣJi`, 1/Pa.
    pub fn instantaneous_compliance(&self) -> f64 {
        self.j0_per_pa - self.terms.iter().map(|t| t.j_per_pa).sum::<f64>()
    }

    /// Relaxed (t → ∞) compliance J0, 1/Pa.
    pub fn relaxed_compliance(&self) -> f64 {
        self.j0_per_pa
    }

    /// Instantaneous modulus `1/(J0 − ΣJi)`, Pa.
    pub fn instantaneous_modulus(&self) -> f64 {
        1.0 / self.instantaneous_compliance()
    }

    /// Relaxed modulus `1/J0`, Pa.
    pub fn relaxed_modulus(&self) -> f64 {
        1.0 / self.relaxed_compliance()
    }

    /// Complex modulus E*(ω) = 1/J*(ω), Pa.
    pub fn complex_modulus(&self, omega_rad_s: f64) -> Complex64 {
        1.0 / self.complex_compliance(omega_rad_s)
    }

    /// Storage modulus E′(ω), Pa.
    pub fn storage_modulus(&self, omega_rad_s: f64) -> f64 {
        self.complex_modulus(omega_rad_s).re
    }

    /// Loss modulus E″(ω), Pa.
    pub fn loss_modulus(&self, omega_rad_s: f64) -> f64 {
        self.complex_modulus(omega_rad_s).im
    }

    /// Loss tangent tan δ = E″/E′ (dimensionless).
    pub fn loss_tangent(&self, omega_rad_s: f64) -> f64 {
        let e = self.complex_modulus(omega_rad_s);
        e.im / e.re
    }

    /// True when every coefficient and time is positive and finite and the instantaneous
    /// compliance is positive: the conditions for a physical creep compliance.
    pub fn is_physical(&self) -> bool {
        self.j0_per_pa.is_finite()
            && self
                .terms
                .iter()
                .all(|t| t.j_per_pa > 0.0 && t.tau_s > 0.0 && t.tau_s.is_finite())
            && self.instantaneous_compliance() > 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one_term() -> PronySeries {
        PronySeries::new(
            4e-6,
            vec![PronyTerm {
                j_per_pa: 1e-6,
                tau_s: 1e-2,
            }],
        )
    }

    #[test]
    fn creep_compliance_limits() {
        let p = one_term();
        assert!((p.creep_compliance(0.0) - 3e-6).abs() < 1e-18);
        assert!((p.creep_compliance(1.0) - 4e-6).abs() < 1e-18);
        let at_tau = 4e-6 - 1e-6 * (-1.0f64).exp();
        assert!((p.creep_compliance(1e-2) - at_tau).abs() < 1e-18);
    }

    /// One-term series = standard linear solid: E′, E″ and tan δ in closed form.
    #[test]
    fn one_term_moduli_are_analytic() {
        let (j0, j1, tau) = (4e-6, 1e-6, 1e-2);
        let p = one_term();
        let ju = j0 - j1; // instantaneous compliance
        for &w in &[0.0, 1.0, 37.0, 100.0, 1e3, 1e5] {
            // J*(ω) = J0 − J1·jωτ/(1 + jωτ) = J0 − J1·(ω²τ² + jωτ)/(1 + ω²τ²)
            let d = 1.0 + (w * tau) * (w * tau);
            let jr = j0 - j1 * (w * tau) * (w * tau) / d;
            let ji = -j1 * w * tau / d;
            let m2 = jr * jr + ji * ji;
            let (e1, e2) = (jr / m2, -ji / m2);
            assert!((p.storage_modulus(w) - e1).abs() <= 1e-12 * e1.abs());
            assert!((p.loss_modulus(w) - e2).abs() <= 1e-12 * e1.abs());
            if w > 0.0 {
                assert!((p.loss_tangent(w) - e2 / e1).abs() <= 1e-12);
            }
        }
        assert!((p.storage_modulus(0.0) - 1.0 / j0).abs() < 1e-6);
        assert!((p.storage_modulus(1e9) - 1.0 / ju).abs() / (1.0 / ju) < 1e-9);
        assert_eq!(p.relaxed_modulus(), 250_000.0);
        assert!((p.instantaneous_modulus() - 1.0 / 3e-6).abs() < 1e-6);
        // tan δ = J1ωτ/(J0 + Ju·ω²τ²) peaks at ω = sqrt(J0/Ju)/τ.
        let w_peak = (j0 / ju).sqrt() / tau;
        let tan_peak = p.loss_tangent(w_peak);
        assert!(tan_peak > p.loss_tangent(w_peak * 1.05));
        assert!(tan_peak > p.loss_tangent(w_peak / 1.05));
    }

    #[test]
    fn vector_round_trip_sorts_slowest_first() {
        let p = PronySeries::from_vec(&[9e-6, 1.0e-6, 2.0e-6, 1e-3, 1e-1]);
        assert_eq!(p.terms[0].tau_s, 1e-1);
        assert_eq!(p.terms[0].j_per_pa, 2.0e-6);
        assert_eq!(PronySeries::from_vec(&p.to_vec()), p);
        assert_eq!(
            PronySeries::param_names(2),
            ["J0", "J1", "J2", "tau1", "tau2"]
        );
    }
}
