//! The Prony material stepped in time, exact for a force that varies linearly between
//! samples (a first-order hold).
//!
//! Each term's state `x_i = HP_τi(u)` obeys `ẋ = −x/τ + u̇`; with `u̇` constant over a sample
//! interval T: `x[k] = a·x[k−1] + c·(u[k] − u[k−1])`, `a = e^{−T/τ}`, `c = τ(1 − a)/T`.
//! Then `y[k] = α·u[k] + β` with `α = J0 − Σ Ji·c_i` — affine in the unknown `u[k]`, which is
//! what lets the contact solve find force and indentation together in one scalar equation.
//! The matching frequency response is [`crate::discrete::Sampling::FirstOrderHold`].

use crate::prony::PronySeries;

/// Time-stepping state of a Prony material.
#[derive(Debug, Clone)]
pub struct MaterialState {
    j0: f64,
    /// (J, a, c) per term.
    terms: Vec<(f64, f64, f64)>,
    x: Vec<f64>,
    prev_u: f64,
}

impl MaterialState {
    pub fn new(model: &PronySeries, fs_hz: f64) -> Self {
        let t = 1.0 / fs_hz;
        let terms = model
            .terms
            .iter()
            .map(|term| {
                let a = (-t / term.tau_s).exp();
                (term.j_per_pa, a, term.tau_s * (1.0 - a) / t)
            })
            .collect::<Vec<_>>();
        Self {
            j0: model.j0_per_pa,
            x: vec![0.0; terms.len()],
            terms,
            prev_u: 0.0,
        }
    }

    /// `(α, β)` with `y = α·u + β` for the next sample's input `u`.
    pub fn affine(&self) -> (f64, f64) {
        let mut alpha = self.j0;
        let mut beta = 0.0;
        for ((j, a, c), x) in self.terms.iter().zip(&self.x) {
            alpha -= j * c;
            beta += j * (c * self.prev_u - a * x);
        }
        (alpha, beta)
    }

    /// Advances the state with this sample's input `u`; returns `y`.
    pub fn commit(&mut self, u: f64) -> f64 {
        let (alpha, beta) = self.affine();
        for ((_, a, c), x) in self.terms.iter().zip(self.x.iter_mut()) {
            *x = a * *x + c * (u - self.prev_u);
        }
        self.prev_u = u;
        alpha * u + beta
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prony::PronyTerm;

    /// A force step held constant creeps exactly as J(t) (one-term closed form), apart
    /// from the ramp over the first sample that a first-order hold implies.
    #[test]
    fn step_creep_matches_closed_form() {
        let m = PronySeries::new(
            4e-6,
            vec![PronyTerm {
                j_per_pa: 1.5e-6,
                tau_s: 2e-3,
            }],
        );
        let fs = 8000.0;
        let mut s = MaterialState::new(&m, fs);
        s.commit(0.0);
        let u0 = 2.0;
        for k in 1..200 {
            let y = s.commit(u0);
            // Response to a ramp 0 → u0 over [0, T] then hold, exactly:
            let t = k as f64 / fs;
            let tt = 1.0 / fs;
            let tau = 2e-3;
            let ramp = |t: f64| 4e-6 * t - 1.5e-6 * tau * (1.0 - (-t / tau).exp());
            let exact = u0 / tt * (ramp(t) - ramp(t - tt));
            assert!(
                (y - exact).abs() < 1e-12 * exact.abs(),
                "k {k}: {y} vs {exact}"
            );
            if k > 100 {
                let closed = u0 * m.creep_compliance(t - tt / 2.0);
                assert!((y - closed).abs() / closed < 1e-4);
            }
        }
    }
}
