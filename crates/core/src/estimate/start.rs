//! Start values by variable projection over a grid of retardation times.
//!
//! Given the τ's the Prony model is linear in `J0, J1..Jn`, so for every choice of n
//! retardation times from a log-spaced grid the best compliances follow from a small linear
//! least-squares problem. All choices are scored from one precomputed Gram matrix; the best
//! physical ones (every J positive, positive instantaneous compliance) seed the nonlinear fit.
//! This finds the basin of the global minimum without any prior on the material.

use nalgebra::{DMatrix, DVector};

/// A start value in log-parameters `[ln J0, ln J1.., ln τ1..]`, with its linear-fit cost.
#[derive(Debug, Clone)]
pub struct Start {
    pub log_params: Vec<f64>,
    pub cost: f64,
}

/// `n` log-spaced values from `lo` to `hi`.
pub fn log_grid(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    if n == 1 {
        return vec![(lo * hi).sqrt()];
    }
    (0..n)
        .map(|i| lo * (hi / lo).powf(i as f64 / (n - 1) as f64))
        .collect()
}

/// Scores every n-subset of `taus`. `j0_column` multiplies J0, `columns[k]` multiplies the J of
/// a term with τ = `taus[k]` (sign included), and `target` is the data, all real vectors of the
/// same length. Returns up to `keep` physical starts, best first.
pub fn grid_starts(
    target: &[f64],
    j0_column: &[f64],
    columns: &[Vec<f64>],
    taus: &[f64],
    order: usize,
    keep: usize,
) -> Vec<Start> {
    let m = columns.len();
    if order == 0 || order > m {
        return Vec::new();
    }
    let all: Vec<&[f64]> = std::iter::once(j0_column)
        .chain(columns.iter().map(|c| c.as_slice()))
        .collect();
    let gram = DMatrix::from_fn(m + 1, m + 1, |i, j| dot(all[i], all[j]));
    let rhs = DVector::from_fn(m + 1, |i, _| dot(all[i], target));
    let tt = dot(target, target);
    let mut best: Vec<Start> = Vec::new();
    let mut subset: Vec<usize> = (0..order).collect();
    loop {
        let idx: Vec<usize> = std::iter::once(0)
            .chain(subset.iter().map(|k| k + 1))
            .collect();
        let g = DMatrix::from_fn(order + 1, order + 1, |i, j| gram[(idx[i], idx[j])]);
        let b = DVector::from_fn(order + 1, |i, _| rhs[idx[i]]);
        if let Some(chol) = g.cholesky() {
            let x = chol.solve(&b);
            let j0 = x[0];
            let sum_j: f64 = x.iter().skip(1).sum();
            if j0 > 0.0 && x.iter().skip(1).all(|v| *v > 0.0) && j0 - sum_j > 0.0 {
                let cost = (tt - b.dot(&x)).max(0.0);
                let mut log_params = vec![j0.ln()];
                log_params.extend(x.iter().skip(1).map(|v| v.ln()));
                log_params.extend(subset.iter().map(|&k| taus[k].ln()));
                insert_best(&mut best, Start { log_params, cost }, keep);
            }
        }
        if !next_combination(&mut subset, m) {
            break;
        }
    }
    best
}

/// The log-parameter starts of a fit: the grid's, plus a prior (or ARX) model when it has the
/// right order and is physical. An empty set is [`super::EstimateError::NoStart`].
pub fn with_prior(
    grid: Vec<Start>,
    prior: Option<&crate::prony::PronySeries>,
    order: usize,
) -> Result<Vec<Vec<f64>>, super::EstimateError> {
    let mut starts: Vec<Vec<f64>> = grid.into_iter().map(|s| s.log_params).collect();
    if let Some(p) = prior.filter(|p| p.order() == order && p.is_physical()) {
        starts.push(p.to_vec().iter().map(|v| v.ln()).collect());
    }
    if starts.is_empty() {
        return Err(super::EstimateError::NoStart);
    }
    Ok(starts)
}

fn insert_best(best: &mut Vec<Start>, s: Start, keep: usize) {
    let pos = best.partition_point(|b| b.cost <= s.cost);
    if pos < keep {
        best.insert(pos, s);
        best.truncate(keep);
    }
}

fn next_combination(c: &mut [usize], m: usize) -> bool {
    let k = c.len();
    let mut i = k;
    while i > 0 {
        i -= 1;
        if c[i] < m - k + i {
            c[i] += 1;
            for j in i + 1..k {
                c[j] = c[j - 1] + 1;
            }
            return true;
        }
    }
    false
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn enumerates_all_subsets() {
        let mut c = vec![0, 1];
        let mut n = 1;
        while next_combination(&mut c, 5) {
            n += 1;
        }
        assert_eq!(n, 10);
    }

    /// Data built exactly from grid points 1 and 3 are recovered with zero cost.
    #[test]
    fn recovers_exact_grid_model() {
        let taus = log_grid(1e-3, 1.0, 4);
        let x0: Vec<f64> = (0..50).map(|i| (i as f64 * 0.37).sin() + 2.0).collect();
        let cols: Vec<Vec<f64>> = taus
            .iter()
            .map(|t| {
                x0.iter()
                    .enumerate()
                    .map(|(i, v)| -v * (-(i as f64) * 1e-2 / t).exp())
                    .collect()
            })
            .collect();
        let target: Vec<f64> = (0..50)
            .map(|i| 5.0 * x0[i] + 1.0 * cols[1][i] + 2.0 * cols[3][i])
            .collect();
        let s = grid_starts(&target, &x0, &cols, &taus, 2, 3);
        // The cost is |t|² − bᵀx: exact zero is lost to cancellation at ~1e-15·|t|².
        let tt: f64 = target.iter().map(|v| v * v).sum();
        assert!(s[0].cost < 1e-12 * tt, "{} vs {tt}", s[0].cost);
        assert!((s[0].log_params[0].exp() - 5.0).abs() < 1e-9);
        let mut t: Vec<f64> = s[0].log_params[3..].iter().map(|v| v.exp()).collect();
        t.sort_by(f64::total_cmp);
        assert!((t[0] - taus[1]).abs() < 1e-12 && (t[1] - taus[3]).abs() < 1e-12);
    }
}
