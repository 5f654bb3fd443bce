//! Small dense linear-algebra helpers on top of nalgebra, and a golden-section line search.

use nalgebra::DMatrix;

/// Reciprocal condition estimate below which a symmetric positive (semi)definite matrix is
/// treated as singular.
pub const SINGULAR_RCOND: f64 = 1e-13;

/// Inverse of a symmetric positive-definite matrix, after symmetric (Jacobi) scaling so that
/// parameters of very different size do not fake singularity. `None` when it is singular
/// to working precision.
pub fn spd_inverse(m: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = m.nrows();
    if (0..n).any(|i| !(m[(i, i)].is_finite() && m[(i, i)] > 0.0)) {
        return None;
    }
    let (scaled, s) = unit_diagonal(m);
    if rcond_sym(&scaled) < SINGULAR_RCOND {
        return None;
    }
    let inv = scaled.cholesky()?.inverse();
    Some(DMatrix::from_fn(n, n, |i, j| inv[(i, j)] * s[i] * s[j]))
}

/// `m` scaled symmetrically to unit diagonal, `S·m·S` with `S = diag(1/√mᵢᵢ)`, and the
/// factors `1/√mᵢᵢ` (a diagonal at or below zero is taken as 1e-300, which scales its row
/// and column to nothing).
fn unit_diagonal(m: &DMatrix<f64>) -> (DMatrix<f64>, Vec<f64>) {
    let n = m.nrows();
    let s: Vec<f64> = (0..n).map(|i| 1.0 / m[(i, i)].max(1e-300).sqrt()).collect();
    (DMatrix::from_fn(n, n, |i, j| m[(i, j)] * s[i] * s[j]), s)
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
    rcond_sym(&unit_diagonal(m).0)
}

/// The inverse of a symmetric positive-semidefinite matrix (a Gauss–Newton `JᵀJ`) over the
/// parameters it determines, with NaN in the rows and columns of those it does not.
///
/// [`spd_inverse`] gives all or nothing: one parameter the data say nothing about (a zero
/// column, such as the length of an adhesive neck, whose snap-off moves by whole samples
/// and so has no local derivative) cost every other parameter its interval too. Here such
/// parameters are set aside one by one — first those with no diagonal, then, while the rest
/// stays singular, the one that weighs most in the direction the matrix knows least — and
/// the rest is inverted. Their covariances are conditional on the set-aside parameters.
pub fn identified_inverse(m: &DMatrix<f64>) -> DMatrix<f64> {
    let n = m.nrows();
    let mut out = DMatrix::from_element(n, n, f64::NAN);
    let mut active: Vec<usize> = (0..n)
        .filter(|&i| m[(i, i)].is_finite() && m[(i, i)] > 0.0)
        .collect();
    while !active.is_empty() {
        let sub = DMatrix::from_fn(active.len(), active.len(), |a, b| m[(active[a], active[b])]);
        if let Some(inv) = spd_inverse(&sub) {
            for (a, &i) in active.iter().enumerate() {
                for (b, &j) in active.iter().enumerate() {
                    out[(i, j)] = inv[(a, b)];
                }
            }
            break;
        }
        let eig = unit_diagonal(&sub).0.symmetric_eigen();
        if eig.eigenvalues.iter().any(|v| !v.is_finite()) {
            break;
        }
        let weakest = eig.eigenvalues.imin();
        let worst = eig.eigenvectors.column(weakest).iamax();
        active.remove(worst);
    }
    out
}

/// Maximum of a concave (unimodal) function on `[lo, hi]` by golden-section search, each step
/// one evaluation; the ends themselves are candidates too. The design's away and toward steps
/// and the diagnosis's sensor lag search with it.
pub fn golden_max(f: impl Fn(f64) -> f64, lo: f64, hi: f64) -> f64 {
    golden_max_within(f, lo, hi, 1e-13 * hi.max(1e-300))
}

/// [`golden_max`] stopped once the bracket is `tol` wide: where each evaluation is a
/// simulation and the argument matters only to a tolerance (the hard reference's contact
/// offset, to 0.01 nm), the full relative precision would cost some 50 evaluations more.
pub fn golden_max_within(f: impl Fn(f64) -> f64, lo: f64, hi: f64, tol: f64) -> f64 {
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut a, mut b) = (lo, hi);
    let mut c = b - g * (b - a);
    let mut d = a + g * (b - a);
    let (mut fc, mut fd) = (f(c), f(d));
    for _ in 0..80 {
        if fc >= fd {
            b = d;
            d = c;
            fd = fc;
            c = b - g * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + g * (b - a);
            fd = f(d);
        }
        if b - a <= tol {
            break;
        }
    }
    let x = 0.5 * (a + b);
    // The ends themselves (a maximum at the edge: a full drop step of the design's away move).
    [lo, x, hi]
        .map(|t| (t, f(t)))
        .into_iter()
        .reduce(|best, c| if c.1 > best.1 { c } else { best })
        .map_or(x, |(t, _)| t)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A parameter with no column leaves the others their exact variances; a full-rank
    /// matrix gives its inverse; two parameters that are one leave only the third.
    #[test]
    fn undetermined_parameters_do_not_take_the_others_with_them() {
        let diagonal = |m: &DMatrix<f64>| -> Vec<f64> {
            let inv = identified_inverse(m);
            (0..m.nrows()).map(|i| inv[(i, i)]).collect()
        };
        let full = DMatrix::from_row_slice(2, 2, &[4.0, 1.0, 1.0, 2.0]);
        let inv = spd_inverse(&full).unwrap();
        let whole = identified_inverse(&full);
        assert!((whole - &inv).amax() < 1e-12, "{inv}");
        let d = diagonal(&full);
        assert!((d[0] - 2.0 / 7.0).abs() < 1e-12, "{d:?}");

        let with_zero =
            DMatrix::from_row_slice(3, 3, &[4.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 2.0]);
        let d = diagonal(&with_zero);
        assert!(d[1].is_nan());
        assert!(
            (d[0] - 2.0 / 7.0).abs() < 1e-12 && (d[2] - 4.0 / 7.0).abs() < 1e-12,
            "{d:?}"
        );
        // The covariance of the two it determines, and NaN across the one it does not.
        let c = identified_inverse(&with_zero);
        assert!((c[(0, 2)] + 1.0 / 7.0).abs() < 1e-12, "{c}");
        assert!((c[(2, 0)] + 1.0 / 7.0).abs() < 1e-12, "{c}");
        assert!(
            (0..3).all(|j| c[(1, j)].is_nan() && c[(j, 1)].is_nan()),
            "{c}"
        );

        // Parameters 0 and 1 enter only as their sum: one of them is set aside and the other
        // keeps the variance it has with that one fixed; the third is independent.
        let aliased = DMatrix::from_row_slice(3, 3, &[1.0, 1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 5.0]);
        let d = diagonal(&aliased);
        assert_eq!(d.iter().filter(|v| v.is_nan()).count(), 1, "{d:?}");
        assert!((d[2] - 0.2).abs() < 1e-12);
        assert!(d[..2].iter().any(|v| (v - 1.0).abs() < 1e-9), "{d:?}");
    }
}
