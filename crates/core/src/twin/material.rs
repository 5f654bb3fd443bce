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
                let (a, c) = crate::discrete::foh_coefficients(term.tau_s, t);
                (term.j_per_pa, a, c)
            })
            .collect::<Vec<_>>();
        Self {
            j0: model.j0_per_pa,
            x: vec![0.0; terms.len()],
            terms,
            prev_u: 0.0,
        }
    }

    /// How many Prony terms the material has.
    pub fn terms(&self) -> usize {
        self.terms.len()
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

/// How a [`MaterialState`]'s output moves with its own parameters and with the inputs'
/// derivatives, carried forward sample by sample (forward sensitivities).
///
/// The parameters, in order: `ln J0`, each term's `ln J`, each term's `ln τ` (the terms in
/// the model's order, slowest first), then `extra` parameters that reach the material only
/// through its input `u` (a contact point, a gain). Differentiating the recursion gives
/// recursions of the same form: with `a = e^{−T/τ}` and `c = τ(1 − a)/T`,
/// `∂a/∂ln τ = −a·ln a` and `∂c/∂ln τ = c − a`, and
/// `∂x[k] = ∂a·x[k−1] + a·∂x[k−1] + ∂c·(u[k] − u[k−1]) + c·(∂u[k] − ∂u[k−1])`.
///
/// One run carrying these gives every column a finite-difference Jacobian takes one run
/// each for (`docs/diagnosis-speed.md`); the caller supplies `∂u` from its contact solve
/// (`∂d/∂θ = −g_θ/g_d`, with `g_θ` from [`Self::affine`]).
///
/// [`Self::carrying`] carries only some of the material's own parameters: a Jacobian split
/// in two runs on two cores (`diagnose::fit`) carries half its columns in each. Every column
/// is worked out apart from the others, in the same operations whichever others ride along,
/// so a column is the same to the bit in either run.
#[derive(Debug, Clone)]
pub struct MaterialSensitivity {
    /// Per term, `(∂a/∂ln τ, ∂c/∂ln τ)`: constants of the material, worked out once.
    rates: Vec<(f64, f64)>,
    /// The material's own parameter each leading column is, in the full order (`ln J0`,
    /// the terms' `ln J`, their `ln τ`); the columns after them are the `extra` ones.
    own: Vec<OwnParam>,
    /// Per term, the column of its `ln τ`, if carried.
    tau_column: Vec<Option<usize>>,
    /// `∂xᵢ/∂θ_q` at `i·params + q`.
    dx: Vec<f64>,
    /// `∂u/∂θ_q` of the last input: one per parameter.
    du_prev: Vec<f64>,
}

/// One of a material's own parameters, as a [`MaterialSensitivity`] column carries it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OwnParam {
    /// `ln J0`.
    LongTime,
    /// Term `i`'s `ln J`.
    Compliance(usize),
    /// Term `i`'s `ln τ`.
    Tau(usize),
}

impl OwnParam {
    /// Every parameter of a material of `terms` Prony terms, in the order
    /// [`MaterialSensitivity::new`] carries them: `ln J0`, each term's `ln J`, each `ln τ`.
    pub fn all(terms: usize) -> Vec<OwnParam> {
        std::iter::once(OwnParam::LongTime)
            .chain((0..terms).map(OwnParam::Compliance))
            .chain((0..terms).map(OwnParam::Tau))
            .collect()
    }
}

impl MaterialSensitivity {
    /// All derivatives zero: a material at rest, as [`MaterialState::new`] leaves it.
    pub fn new(state: &MaterialState, extra: usize) -> Self {
        Self::carrying(state, &OwnParam::all(state.terms.len()), extra)
    }

    /// [`Self::new`] carrying only the material's own parameters `own` (each term's index
    /// below [`MaterialState::terms`]), in that order, then `extra` others.
    pub fn carrying(state: &MaterialState, own: &[OwnParam], extra: usize) -> Self {
        let m = state.terms.len();
        let own = own.to_vec();
        debug_assert!(own.iter().all(|o| match *o {
            OwnParam::Compliance(i) | OwnParam::Tau(i) => i < m,
            OwnParam::LongTime => true,
        }));
        let tau_column = (0..m)
            .map(|i| own.iter().position(|&o| o == OwnParam::Tau(i)))
            .collect();
        let params = own.len() + extra;
        Self {
            own,
            tau_column,
            // A term far faster than the sampling has `a = e^{−T/τ}` = 0, where `−a·ln a`
            // is 0·∞: its limit, 0, is what `a·T/τ` gives.
            rates: (state.terms.iter())
                .map(|&(_, a, c)| (if a > 0.0 { -a * a.ln() } else { 0.0 }, c - a))
                .collect(),
            dx: vec![0.0; state.terms.len() * params],
            du_prev: vec![0.0; params],
        }
    }

    /// How many parameters are carried.
    pub fn params(&self) -> usize {
        self.du_prev.len()
    }

    /// `(∂α/∂θ_q, ∂β/∂θ_q)` for every parameter, written into `out` (one per parameter),
    /// where [`MaterialState::affine`] gives `y = α·u + β` for the next input: what the
    /// contact solve's `g_θ` needs. Into the caller's slice, as it is asked for every sample.
    pub fn affine(&self, state: &MaterialState, out: &mut [(f64, f64)]) {
        let params = self.params();
        let out = &mut out[..params];
        // Through the state and the last input, for every parameter: term by term over
        // contiguous rows (this runs every sample of a fit's tangent).
        for slot in out.iter_mut() {
            *slot = (0.0, 0.0);
        }
        for (i, &(j, a, c)) in state.terms.iter().enumerate() {
            let row = &self.dx[i * params..(i + 1) * params];
            for ((slot, &du), &dx) in out.iter_mut().zip(&self.du_prev).zip(row) {
                slot.1 += j * (c * du - a * dx);
            }
        }
        // And directly, for the material's own.
        for (slot, &own) in out.iter_mut().zip(&self.own) {
            match own {
                OwnParam::LongTime => slot.0 = state.j0,
                OwnParam::Compliance(i) => {
                    let (j, a, c) = state.terms[i];
                    slot.0 = -j * c;
                    slot.1 += j * (c * state.prev_u - a * state.x[i]);
                }
                OwnParam::Tau(i) => {
                    let (j, _, _) = state.terms[i];
                    let (da, dc) = self.rates[i];
                    slot.0 = -j * dc;
                    slot.1 += j * (dc * state.prev_u - da * state.x[i]);
                }
            }
        }
    }

    /// Advances the derivatives with this sample's input `u` and its derivatives `du` (one
    /// per parameter); `state` is the material *before* its own [`MaterialState::commit`]
    /// with `u`.
    pub fn commit(&mut self, state: &MaterialState, u: f64, du: &[f64]) {
        let params = self.params();
        debug_assert_eq!(du.len(), params, "one input derivative per parameter");
        for (i, ((_, a, c), x)) in state.terms.iter().zip(&state.x).enumerate() {
            let (da, dc) = self.rates[i];
            let row = &mut self.dx[i * params..(i + 1) * params];
            for (dxq, (&duq, du_prev)) in row.iter_mut().zip(du.iter().zip(&self.du_prev)) {
                *dxq = a * *dxq + c * (duq - du_prev);
            }
            // The term's own τ moves its rates too.
            if let Some(q) = self.tau_column[i] {
                row[q] += da * x + dc * (u - state.prev_u);
            }
        }
        for (p, &d) in self.du_prev.iter_mut().zip(du) {
            *p = d;
        }
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

    /// The forward sensitivities of a material in a feedback loop (its input depends on its
    /// last output, as a contact's force does on the indentation) are the derivatives of its
    /// output: against central differences of whole runs with each parameter moved, to the
    /// differences' own truncation error (7e-10 to 3.3e-9 of the column here, at a step of
    /// 1e-4). With `∂c/∂ln τ` taken as `c` rather than `c − a`, τ1's column is off by 2.2;
    /// with the last input's derivatives not carried, by 5e31.
    #[test]
    fn forward_sensitivities_are_the_outputs_derivatives() {
        use crate::prony::PronyTerm;
        let fs = 4000.0;
        let model = |p: &[f64]| {
            PronySeries::new(
                p[0].exp(),
                vec![
                    PronyTerm {
                        j_per_pa: p[1].exp(),
                        tau_s: p[3].exp(),
                    },
                    PronyTerm {
                        j_per_pa: p[2].exp(),
                        tau_s: p[4].exp(),
                    },
                ],
            )
        };
        // ln J0, ln J1, ln J2, ln τ1 (80 ms), ln τ2 (0.5 ms, two samples), slowest first.
        let p0 = [
            4e-6f64.ln(),
            1.5e-6f64.ln(),
            0.6e-6f64.ln(),
            0.08f64.ln(),
            5e-4f64.ln(),
        ];
        // u[k] = s[k] − κ·y[k−1]: the input answers the last output.
        let kappa = 3e4;
        let drive = |k: usize| {
            let t = k as f64 / fs;
            1.0 + 0.5 * (2.0 * std::f64::consts::PI * 7.0 * t).sin()
                + 0.2 * (2.0 * std::f64::consts::PI * 310.0 * t).sin()
        };
        let n = 2000;
        let run = |p: &[f64]| -> Vec<f64> {
            let mut s = MaterialState::new(&model(p), fs);
            let mut y = 0.0;
            (0..n)
                .map(|k| {
                    y = s.commit(drive(k) - kappa * y);
                    y
                })
                .collect()
        };
        let mut s = MaterialState::new(&model(&p0), fs);
        let mut sens = MaterialSensitivity::new(&s, 0);
        assert_eq!(sens.params(), 5);
        let (mut y, mut dy) = (0.0, vec![0.0; 5]);
        let mut moved = vec![(0.0, 0.0); 5];
        let mut columns: Vec<Vec<f64>> = (0..5).map(|_| Vec::with_capacity(n)).collect();
        for k in 0..n {
            let u = drive(k) - kappa * y;
            let du: Vec<f64> = dy.iter().map(|d| -kappa * d).collect();
            let (alpha, _) = s.affine();
            sens.affine(&s, &mut moved);
            sens.commit(&s, u, &du);
            y = s.commit(u);
            for (q, &(dalpha, dbeta)) in moved.iter().enumerate() {
                dy[q] = dalpha * u + alpha * du[q] + dbeta;
                columns[q].push(dy[q]);
            }
        }
        for (q, column) in columns.iter().enumerate() {
            let at = |h: f64| {
                let mut p = p0;
                p[q] += h;
                run(&p)
            };
            let (plus, minus) = (at(1e-4), at(-1e-4));
            let (mut off, mut size) = (0.0, 0.0);
            for k in 0..n {
                let central = (plus[k] - minus[k]) / 2e-4;
                off += (central - column[k]).powi(2);
                size += central.powi(2);
            }
            let off = (off / size).sqrt();
            assert!(off < 1e-6, "parameter {q}: {off:e}");
        }
    }

    /// A sensitivity carrying some of the material's parameters, in another order, gives
    /// each of them the same derivatives to the bit as one carrying all (a Jacobian's
    /// tangent split in two runs relies on it), and an extra parameter alike.
    #[test]
    fn a_few_parameters_carried_are_the_same_as_all() {
        use crate::prony::PronyTerm;
        let fs = 4000.0;
        let m = PronySeries::new(
            4e-6,
            vec![
                PronyTerm {
                    j_per_pa: 1.5e-6,
                    tau_s: 0.08,
                },
                PronyTerm {
                    j_per_pa: 0.6e-6,
                    tau_s: 5e-4,
                },
            ],
        );
        // Carried in another order than the full one (ln J0, ln J1, ln J2, ln τ1, ln τ2);
        // then one extra.
        let few = [
            OwnParam::Tau(1),
            OwnParam::Compliance(0),
            OwnParam::LongTime,
        ];
        let order = OwnParam::all(2);
        let full: Vec<usize> = (few.iter())
            .map(|o| order.iter().position(|a| a == o).unwrap())
            .collect();
        assert_eq!(full, [4, 1, 0]);
        let run = |own: Option<&[OwnParam]>| {
            let mut s = MaterialState::new(&m, fs);
            let mut sens = match own {
                Some(own) => MaterialSensitivity::carrying(&s, own, 1),
                None => MaterialSensitivity::new(&s, 1),
            };
            let params = sens.params();
            let mut moved = vec![(0.0, 0.0); params];
            let mut out = Vec::new();
            for k in 0..500 {
                let u = 1.0 + (k as f64 * 0.05).sin();
                // The extra parameter moves the input; the others' inputs move with their
                // own output (as a contact's would), differently for each.
                sens.affine(&s, &mut moved);
                let du: Vec<f64> = (0..params)
                    .map(|q| {
                        if q + 1 == params {
                            0.3
                        } else {
                            -0.1 * moved[q].1
                        }
                    })
                    .collect();
                sens.commit(&s, u, &du);
                s.commit(u);
                out.push(moved.clone());
            }
            out
        };
        let all = run(None);
        let some = run(Some(&few));
        for (k, (a, b)) in all.iter().zip(&some).enumerate() {
            for (q, &full) in full.iter().enumerate() {
                assert_eq!(
                    b[q].0.to_bits(),
                    a[full].0.to_bits(),
                    "sample {k}, ∂α {full}"
                );
                assert_eq!(
                    b[q].1.to_bits(),
                    a[full].1.to_bits(),
                    "sample {k}, ∂β {full}"
                );
            }
            assert_eq!(b[few.len()], a[order.len()], "sample {k}, the extra");
        }
        // And they move: a test of zeros would pass whatever was carried.
        assert!(some
            .last()
            .unwrap()
            .iter()
            .all(|&(a, b)| a != 0.0 || b != 0.0));
    }
}
