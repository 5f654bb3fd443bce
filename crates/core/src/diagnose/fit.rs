//! Fitting a model to the recording: Levenberg–Marquardt on the twin's simulation, and a
//! cheap screening step that ranks candidates before the full refits.
//!
//! The solver is the textbook one (as in [`crate::estimate::lm`]) but with a finite-difference
//! Jacobian computed only at accepted points: each Jacobian costs one twin simulation per
//! parameter, so evaluating it at rejected trial points (as the shared solver's interface
//! requires) would double the cost of a diagnosis.

use super::model::{Evaluation, ModelSpec, Problem};
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
    pub iterations: usize,
}

fn fd_step(i: usize) -> f64 {
    // θ is in log units except the contact point (in 10 nm): 1e-4 is 0.01 % or 1 pm.
    let _ = i;
    1e-4
}

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
        let mut h = fd_step(i);
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

/// Minimises χ²_train over the parameters `free` (others held), from `th0`.
pub fn fit_params(
    problem: &Problem,
    spec: &ModelSpec,
    th0: &[f64],
    free: &[usize],
    opts: FitOptions,
    project_out: Option<&DMatrix<f64>>,
) -> Option<(Vec<f64>, Evaluation, DMatrix<f64>, usize)> {
    // With `project_out` (an orthonormal basis Q), the objective is ‖(I − QQᵀ) r‖²: the
    // residual after a linearised refit of the directions Q spans (the nominal parameters).
    let project = |r: &[f64]| -> Vec<f64> {
        match project_out {
            None => r.to_vec(),
            Some(q) => {
                let rv = DVector::from_column_slice(r);
                let c = q.transpose() * &rv;
                (rv - q * c).iter().copied().collect()
            }
        }
    };
    let mut th = th0.to_vec();
    let mut eval = problem.evaluate(spec, &th)?;
    let mut r = project(&eval.train_residuals);
    let mut cost: f64 = r.iter().map(|v| v * v).sum();
    let mut lambda = 1e-3;
    let mut iterations = 0;
    let mut jac_raw = jacobian(problem, spec, &th, &eval.train_residuals, free)?;
    let proj_jac = |j: &DMatrix<f64>| -> DMatrix<f64> {
        match project_out {
            None => j.clone(),
            Some(q) => j - q * (q.transpose() * j),
        }
    };
    let mut jac = proj_jac(&jac_raw);
    let n = free.len();
    while iterations < opts.max_iterations && n > 0 {
        iterations += 1;
        let rv = DVector::from_column_slice(&r);
        let g = jac.transpose() * &rv;
        let jtj = jac.transpose() * &jac;
        let mut accepted = false;
        let mut converged = false;
        while lambda < 1e12 {
            let mut a = jtj.clone();
            for i in 0..n {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let mut step = -chol.solve(&g);
            let big = step.amax();
            if big > opts.max_step {
                step *= opts.max_step / big;
            }
            let mut trial = th.clone();
            for (c, &i) in free.iter().enumerate() {
                trial[i] += step[c];
            }
            match problem.evaluate(spec, &trial) {
                Some(e) => {
                    let rt = project(&e.train_residuals);
                    let ct: f64 = rt.iter().map(|v| v * v).sum();
                    if ct < cost {
                        let gain = cost - ct;
                        th = trial;
                        eval = e;
                        r = rt;
                        // χ² is in units of the noise floor: a gain of 0.01 is statistically nothing.
                        converged = gain <= 0.01 || gain <= 1e-7 * cost || step.amax() < 1e-7;
                        cost = ct;
                        lambda = (lambda / 4.0).max(1e-9);
                        accepted = true;
                        break;
                    }
                    lambda *= 8.0;
                }
                None => lambda *= 8.0,
            }
        }
        if !accepted || converged {
            break;
        }
        jac_raw = jacobian(problem, spec, &th, &eval.train_residuals, free)?;
        jac = proj_jac(&jac_raw);
    }
    Some((th, eval, jac_raw, iterations))
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
        let Some((theta, eval, jacobian, iterations)) =
            fit_params(problem, spec, s, &free, opts, None)
        else {
            continue;
        };
        if best
            .as_ref()
            .is_some_and(|b| b.eval.chi2_train <= eval.chi2_train)
        {
            continue;
        }
        let dof = (problem.train.len() as f64 - free.len() as f64).max(1.0);
        let scale = (eval.chi2_train / dof).max(1.0);
        let jtj = jacobian.transpose() * &jacobian;
        let sd = match crate::linalg::spd_inverse(&jtj) {
            Some(inv) => (0..free.len())
                .map(|i| (inv[(i, i)].max(0.0) * scale).sqrt())
                .collect(),
            None => vec![f64::NAN; free.len()],
        };
        best = Some(Fitted {
            spec: spec.clone(),
            theta,
            eval,
            sd,
            jacobian,
            iterations,
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
            fit_params(problem, spec, s, &free, opts, Some(q)).map(|(th, e, _, _)| {
                let rv = DVector::from_column_slice(&e.train_residuals);
                let c = q.transpose() * &rv;
                ((rv - q * c).norm_squared(), th)
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
