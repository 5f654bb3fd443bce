//! Small dense linear-algebra helpers on top of nalgebra.

use nalgebra::DMatrix;

/// Reciprocal condition estimate below which a symmetric positive (semi)definite matrix is
/// treated as singular.
pub const SINGULAR_RCOND: f64 = 1e-13;

/// Inverse of a symmetric positive-definite matrix, after symmetric (Jacobi) scaling so that
/// parameters of very different size do not fake singularity. `None` when it is singular
/// to working precision.
pub fn spd_inverse(m: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = m.nrows();
    let d: Vec<f64> = (0..n).map(|i| m[(i, i)]).collect();
    if d.iter().any(|x| x.is_nan() || *x <= 0.0 || !x.is_finite()) {
        return None;
    }
    let s: Vec<f64> = d.iter().map(|x| 1.0 / x.sqrt()).collect();
    let scaled = DMatrix::from_fn(n, n, |i, j| m[(i, j)] * s[i] * s[j]);
    if rcond_sym(&scaled) < SINGULAR_RCOND {
        return None;
    }
    let inv = scaled.cholesky()?.inverse();
    Some(DMatrix::from_fn(n, n, |i, j| inv[(i, j)] * s[i] * s[j]))
}

/// Reciprocal 2-norm condition number of a symmetric matrix (smallest/largest |eigenvalue|).
pub fn rcond_sym(m: &DMatrix<f64>) -> f64 {
    let ev = m.clone().symmetric_eigenvalues();
    let max = ev.iter().fold(0.0f64, |a, b| a.max(b.abs()));
    let min = ev.iter().fold(f64::INFINITY, |a, b| a.min(b.abs()));
    if max == 0.0 {
        0.0
    } else {
        min / max
    }
}

/// Reciprocal condition of a symmetric matrix after scaling it to unit diagonal: how well a
/// Gauss–Newton matrix separates the parameters, whatever their units.
pub fn scaled_rcond(m: &DMatrix<f64>) -> f64 {
    let n = m.nrows();
    let d: Vec<f64> = (0..n).map(|i| m[(i, i)].max(1e-300).sqrt()).collect();
    rcond_sym(&DMatrix::from_fn(n, n, |i, j| m[(i, j)] / (d[i] * d[j])))
}
