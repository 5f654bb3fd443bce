//! Single-sample glitches of the deflection channel: one sample far off a smooth run, its
//! neighbours agreeing with each other (a converter's or a transfer's error, not a force).
//!
//! Such a sample sat in the fits as an outlier of thousands of σ: two of them, ±9.9 V in a
//! corpus record, lifted its nominal fit to 1800 χ² per train sample and left the
//! diagnosis `unexplained`, and ended the offline fit's window at the second one (read as
//! the loss of contact) with the order chosen down to one term.
//!
//! [`find_glitches`] reads the second difference `d₂[k] = y[k−1] − 2y[k] + y[k+1]`. A
//! glitch of size A on a smooth run gives `(A, −2A, A)` about it: the middle one of the
//! opposite sign and about twice the outer two. It is a glitch where that middle one is
//! over [`OVER_LOCAL`] times the run's own scale there: the median of `|d₂|` over
//! [`WINDOW`] samples either side (the three it spoils left out), and at least the
//! record's median `|d₂|` (the noise's, where the record is mostly smooth). Physics does
//! not do that: a step (a pull-off, a snap-in) gives `(S, −S)`, and a fast line or a
//! resonance keeps its scale over its whole run. On the concealed corpus's 59 files, the
//! independent simulator's 32 recordings and the shared JPK file the largest ratio came to
//! 6.8 (by a port of this rule to Python); on the glitches above, over 1000.

use super::Recording;
use crate::analysis::median;

/// How many times the local scale of the second difference a glitch's must exceed.
pub const OVER_LOCAL: f64 = 30.0;

/// Samples either side over which the local scale is read.
pub const WINDOW: usize = 32;

/// One glitch: where, and how far off its neighbours' mean it sat.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Glitch {
    pub index: usize,
    pub off_v: f64,
}

/// The glitches of `y`, ascending.
pub fn find_glitches(y: &[f64]) -> Vec<Glitch> {
    let n = y.len();
    if n < 2 * WINDOW + 3 || y.iter().any(|v| !v.is_finite()) {
        return vec![];
    }
    let mut d2 = vec![0.0; n];
    for k in 1..n - 1 {
        d2[k] = y[k - 1] - 2.0 * y[k] + y[k + 1];
    }
    let size: Vec<f64> = d2.iter().map(|d| d.abs()).collect();
    let record_scale = median(&mut size[1..n - 1].to_vec());
    // y is finite, so the scale is a finite number ≥ 0: zero for a record without noise.
    if record_scale <= 0.0 {
        return vec![];
    }
    let mut window = Vec::with_capacity(2 * WINDOW);
    (2..n - 2)
        .filter(|&k| {
            let (a, b, c) = (d2[k - 1], d2[k], d2[k + 1]);
            let shaped = |outer: f64| outer * b < 0.0 && (0.25..0.75).contains(&(outer / b).abs());
            if !(shaped(a) && shaped(c) && size[k] > OVER_LOCAL * record_scale) {
                return false;
            }
            window.clear();
            window.extend_from_slice(&size[k.saturating_sub(WINDOW).max(1)..k - 1]);
            window.extend_from_slice(&size[k + 2..(k + WINDOW + 1).min(n - 1)]);
            size[k] > OVER_LOCAL * median(&mut window).max(record_scale)
        })
        .map(|k| Glitch {
            index: k,
            off_v: y[k] - 0.5 * (y[k - 1] + y[k + 1]),
        })
        .collect()
}

/// `rec` with each glitch of its deflection replaced by the mean of its neighbours, and the
/// glitches; `rec` itself (borrowed) where there are none.
pub fn with_glitches_mended(rec: &Recording) -> (std::borrow::Cow<'_, Recording>, Vec<Glitch>) {
    let glitches = find_glitches(&rec.deflection_v);
    if glitches.is_empty() {
        return (std::borrow::Cow::Borrowed(rec), glitches);
    }
    let mut mended = rec.clone();
    for g in &glitches {
        let y = &mut mended.deflection_v;
        y[g.index] = 0.5 * (y[g.index - 1] + y[g.index + 1]);
    }
    (std::borrow::Cow::Owned(mended), glitches)
}

/// Where the glitches were and how large, for a sentence the caller ends with what it did.
pub fn describe(glitches: &[Glitch], fs_hz: f64) -> String {
    let first = glitches.first().map_or(0, |g| g.index);
    let largest = glitches.iter().fold(0.0f64, |m, g| m.max(g.off_v.abs()));
    format!(
        "deflection_v: {} single-sample glitch{} (the first at t = {:.4} s, CSV row {}; up to \
         {largest:.3e} V off the mean of its neighbours, where the run about it is smooth)",
        glitches.len(),
        if glitches.len() == 1 { "" } else { "es" },
        first as f64 / fs_hz,
        first + 2,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A noisy multisine-like run sampled at five points a period at its fastest line:
    /// a smooth run no single-sample glitch hides in.
    fn busy_run(n: usize) -> Vec<f64> {
        let mut state = 99u64;
        (0..n)
            .map(|k| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let noise = ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.01;
                let t = k as f64;
                0.3 * (t * 2.0 * std::f64::consts::PI / 5.0).sin() + 0.5 * (t / 300.0).sin() + noise
            })
            .collect()
    }

    #[test]
    fn a_glitch_is_found_where_it_is_and_nowhere_else() {
        let mut y = busy_run(4000);
        assert!(find_glitches(&y).is_empty());
        y[1000] += 9.9;
        y[3000] -= 4.0;
        let g = find_glitches(&y);
        assert_eq!(
            g.iter().map(|g| g.index).collect::<Vec<_>>(),
            vec![1000, 3000]
        );
        assert!((g[0].off_v - 9.9).abs() < 0.5, "{g:?}");
    }

    #[test]
    fn a_step_is_not_a_glitch() {
        // A pull-off: the lever drops by a hundred noise levels in one sample and stays.
        let mut y = busy_run(4000);
        for v in &mut y[2000..] {
            *v -= 1.0;
        }
        assert!(find_glitches(&y).is_empty());
    }

    #[test]
    fn a_mended_glitch_takes_its_neighbours_mean() {
        let y = busy_run(4000);
        let mut rec = crate::diagnose::corpus::simulate(
            &crate::diagnose::corpus::nominal_twin(1),
            &vec![0.0; y.len()],
            1000.0,
            None,
        );
        rec.deflection_v = y.clone();
        rec.deflection_v[1234] = 9.9;
        let (mended, glitches) = with_glitches_mended(&rec);
        assert_eq!(glitches.len(), 1);
        assert_eq!(mended.deflection_v[1234], 0.5 * (y[1233] + y[1235]));
        assert!(describe(&glitches, 1000.0).contains("CSV row 1236"));
        let (same, none) = with_glitches_mended(&mended);
        assert!(none.is_empty() && matches!(same, std::borrow::Cow::Borrowed(_)));
    }
}
