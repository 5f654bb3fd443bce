//! Fitting a model to the recording: Levenberg–Marquardt on the twin's simulation, and a
//! cheap screening step that ranks candidates before the full refits.
//!
//! The solver is the project's Levenberg–Marquardt ([`crate::estimate::lm::solve_lazy`]) with
//! a finite-difference Jacobian, which that entry point asks for only at accepted points: each
//! Jacobian costs one twin simulation per parameter.

use super::model::{Evaluation, ModelSpec, Problem};
use crate::estimate::lm::{solve_lazy, Damping, LmOptions};
use nalgebra::{DMatrix, DVector};

/// A fitted model.
#[derive(Debug, Clone)]
pub struct Fitted {
    pub spec: ModelSpec,
    pub theta: Vec<f64>,
    pub eval: Evaluation,
    /// Standard errors of θ (fitting coordinates), from `(JᵀJ)⁻¹` scaled by the reduced χ².
    pub sd: Vec<f64>,
    /// Jacobian of the train residuals at θ (rows: train samples).
    pub jacobian: DMatrix<f64>,
}

/// Finite-difference step in θ: θ is in log units except the contact point (in 10 nm), so
/// 1e-4 is 0.01 % or 1 pm.
const FD_STEP: f64 = 1e-4;

/// Jacobian of the train residuals over the parameters `which`, by forward differences.
fn jacobian(
    problem: &Problem,
    spec: &ModelSpec,
    th: &[f64],
    r0: &[f64],
    which: &[usize],
) -> Option<DMatrix<f64>> {
    let mut jac = DMatrix::<f64>::zeros(r0.len(), which.len());
    for (c, &i) in which.iter().enumerate() {
        // Forward difference; backward where the forward point is not physical (a bound).
        let mut h = FD_STEP;
        let mut tp = th.to_vec();
        tp[i] += h;
        let e = match problem.evaluate(spec, &tp) {
            Some(e) => e,
            None => {
                h = -h;
                tp[i] = th[i] + h;
                problem.evaluate(spec, &tp)?
            }
        };
        for (k, v) in e.train_residuals.iter().enumerate() {
            jac[(k, c)] = (v - r0[k]) / h;
        }
    }
    Some(jac)
}

/// Options of one fit.
#[derive(Debug, Clone, Copy)]
pub struct FitOptions {
    pub max_iterations: usize,
    /// Largest step of any θ component per iteration (log units: a factor e^max).
    pub max_step: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            max_iterations: 30,
            max_step: 1.0,
        }
    }
}

/// What [`fit_params`] reached.
pub struct ParamFit {
    pub theta: Vec<f64>,
    /// The model at `theta` (its train residuals unprojected).
    pub eval: Evaluation,
    /// Gauss–Newton matrix of the (projected) objective at `theta`, over the free parameters.
    pub jtj: DMatrix<f64>,
    /// Jacobian of the (projected) train residuals at `theta`, over the free parameters.
    pub jacobian: DMatrix<f64>,
}

/// Minimises χ²_train over the parameters `free` (others held), from `th0`. With
/// `project_out` (an orthonormal basis Q), the objective is ‖(I − QQᵀ) r‖²: the residual after
/// a linearised refit of the directions Q spans (the nominal parameters).
pub fn fit_params(
    problem: &Problem,
    spec: &ModelSpec,
    th0: &[f64],
    free: &[usize],
    opts: FitOptions,
    project_out: Option<&DMatrix<f64>>,
) -> Option<ParamFit> {
    let project = |r: DVector<f64>| match project_out {
        None => r,
        Some(q) => {
            let c = q.transpose() * &r;
            r - q * c
        }
    };
    let full = |x: &[f64]| {
        let mut th = th0.to_vec();
        for (&i, v) in free.iter().zip(x) {
            th[i] = *v;
        }
        th
    };
    // Every evaluation with a lower cost than all before is the solver's current point (it
    // accepts exactly those), so the best one seen is the model at the solution, and the raw
    // residuals the finite differences start from.
    let best: std::cell::RefCell<Option<(f64, Evaluation)>> = Default::default();
    let residuals = |x: &[f64]| {
        let e = problem.evaluate(spec, &full(x))?;
        let r = project(DVector::from_column_slice(&e.train_residuals));
        let cost = r.norm_squared();
        let mut b = best.borrow_mut();
        if b.as_ref().is_none_or(|(c, _)| cost < *c) {
            *b = Some((cost, e));
        }
        Some(r)
    };
    let jacobian_at = |x: &[f64], _: &DVector<f64>| {
        let b = best.borrow();
        let r0 = &b.as_ref()?.1.train_residuals;
        let j = jacobian(problem, spec, &full(x), r0, free)?;
        Some(match project_out {
            None => j,
            Some(q) => &j - q * (q.transpose() * &j),
        })
    };
    let lm_opts = LmOptions {
        max_iterations: opts.max_iterations,
        max_step: opts.max_step,
        cost_tolerance: 1e-7,
        cost_tolerance_abs: 0.01,
        step_tolerance: 1e-7,
        // Gentler than the estimators' default: on a real record far from the nominal model
        // (the shared JPK gel) the default schedule settles in worse basins.
        damping: Damping {
            down: 4.0,
            up: 8.0,
            min: 1e-9,
            max: 1e12,
            diag_floor: 1e-12,
        },
    };
    let x0: Vec<f64> = free.iter().map(|&i| th0[i]).collect();
    let res = solve_lazy(&x0, residuals, jacobian_at, lm_opts)?;
    let (_, eval) = best.into_inner()?;
    Some(ParamFit {
        theta: full(&res.params),
        eval,
        jtj: res.jtj,
        jacobian: res.jacobian,
    })
}

/// Fits every nonlinear parameter of `spec` from each start; keeps the lowest χ²_train.
pub fn fit_model(
    problem: &Problem,
    spec: &ModelSpec,
    starts: &[Vec<f64>],
    opts: FitOptions,
) -> Option<Fitted> {
    let free: Vec<usize> = (0..spec.n_nonlinear()).collect();
    let mut best: Option<Fitted> = None;
    for s in starts {
        let Some(f) = fit_params(problem, spec, s, &free, opts, None) else {
            continue;
        };
        if best
            .as_ref()
            .is_some_and(|b| b.eval.chi2_train <= f.eval.chi2_train)
        {
            continue;
        }
        let dof = (problem.train.len() as f64 - free.len() as f64).max(1.0);
        let scale = (f.eval.chi2_train / dof).max(1.0);
        let sd = match crate::linalg::spd_inverse(&f.jtj) {
            Some(inv) => (0..free.len())
                .map(|i| (inv[(i, i)].max(0.0) * scale).sqrt())
                .collect(),
            None => vec![f64::NAN; free.len()],
        };
        best = Some(Fitted {
            spec: spec.clone(),
            theta: f.theta,
            eval: f.eval,
            sd,
            jacobian: f.jacobian,
        });
    }
    best
}

/// Screening χ² of a candidate: only its own parameters move, the nominal ones are refitted
/// to first order by projecting out the nominal Jacobian `q` (orthonormal). Returns the
/// screened χ²_train and the candidate parameters reached.
pub fn screen(
    problem: &Problem,
    spec: &ModelSpec,
    starts: &[Vec<f64>],
    q: &DMatrix<f64>,
) -> Option<(f64, Vec<f64>)> {
    let n_nom = spec.n_nominal();
    let free: Vec<usize> = (n_nom..spec.n_nonlinear()).collect();
    let opts = FitOptions {
        max_iterations: 10,
        max_step: 1.5,
    };
    let mut best: Option<(f64, Vec<f64>)> = None;
    for s in starts {
        let r = if free.is_empty() {
            let e = problem.evaluate(spec, s)?;
            let rv = DVector::from_column_slice(&e.train_residuals);
            let c = q.transpose() * &rv;
            Some(((rv - q * c).norm_squared(), s.clone()))
        } else {
            fit_params(problem, spec, s, &free, opts, Some(q)).map(|f| {
                let rv = DVector::from_column_slice(&f.eval.train_residuals);
                let c = q.transpose() * &rv;
                ((rv - q * c).norm_squared(), f.theta)
            })
        };
        if let Some((c, th)) = r {
            if best.as_ref().is_none_or(|b| c < b.0) {
                best = Some((c, th));
            }
        }
    }
    best
}

/// An orthonormal basis of the columns of `j` (thin QR), for [`screen`].
pub fn orthonormal_basis(j: &DMatrix<f64>) -> DMatrix<f64> {
    j.clone().qr().q()
}
