//! A column written on a grid: its values whole steps apart, as a converter's codes are, or
//! as an export that kept two decimals leaves them.
//!
//! A 16-bit converter over ±10 V steps by 0.3 mV, a tenth of a lever's noise, and the
//! rounding is one more white noise. An export that kept two decimals of volts steps by
//! 10 mV, three times the noise of the concealed corpus's records: the record then holds the
//! rounding rather than the lever below a step, and the rounding's error follows the signal
//! (a slow creep walks through the steps as a staircase). Two of the corpus's nulls rounded
//! so came out `unexplained`; rounded to three decimals (1 mV), both stayed clean. Nothing
//! downstream can undo the rounding, so [`step`] only finds it, for a note that says so.

/// How far from a whole number of steps a difference may lie, in steps: the decimal
/// digits a grid is written with are not exact in binary, and a difference of two such
/// values is off by a few ulps of the values.
const OFF_GRID_STEPS: f64 = 1e-3;

/// The step of the grid every value of `v` lies on, where there is one: the smallest
/// change between successive samples, where every change is a whole number of it. `None`
/// for a column that never changes, holds a non-finite value, or moves off any grid (a
/// column written with all its digits).
///
/// Successive changes, rather than the values, are read, so that a grid offset from zero
/// (a converter's codes with a calibration's offset) is a grid too.
pub fn step(v: &[f64]) -> Option<f64> {
    if v.iter().any(|x| !x.is_finite()) {
        return None;
    }
    let changes = || {
        v.windows(2)
            .map(|w| (w[1] - w[0]).abs())
            .filter(|d| *d > 0.0)
    };
    let q = changes().fold(f64::INFINITY, f64::min);
    if !q.is_finite() {
        return None;
    }
    changes()
        .all(|d| {
            let steps = d / q;
            (steps - steps.round()).abs() < OFF_GRID_STEPS
        })
        .then_some(q)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A noisy sine, sampled densely: what a lever in contact reads (the noise is the
    /// diagnosis's test helper's).
    fn noisy_sine(n: usize, offset: f64) -> Vec<f64> {
        let noise = crate::diagnose::noise::tests::white_and_pink(n, 0.003, 0.0, 7);
        (noise.iter().enumerate())
            .map(|(k, e)| offset + 0.3 * (k as f64 * 0.01).sin() + e)
            .collect()
    }

    #[test]
    fn two_decimals_are_a_grid_of_a_hundredth() {
        let rounded: Vec<f64> = noisy_sine(5000, 0.0)
            .iter()
            .map(|x| format!("{x:.2}").parse().unwrap())
            .collect();
        let q = step(&rounded).expect("a grid");
        assert!((q - 0.01).abs() < 1e-12, "{q}");
    }

    #[test]
    fn a_converter_s_codes_with_an_offset_are_a_grid() {
        let lsb = 20.0 / 65536.0;
        let codes: Vec<f64> = noisy_sine(5000, 0.0)
            .iter()
            .map(|x| 0.1234567 + (x / lsb).round() * lsb)
            .collect();
        let q = step(&codes).expect("a grid");
        assert!((q / lsb - 1.0).abs() < 1e-9, "{q} against {lsb}");
    }

    #[test]
    fn all_the_digits_are_no_grid() {
        assert_eq!(step(&noisy_sine(5000, 0.0)), None);
        assert_eq!(step(&[0.5; 100]), None);
        let mut v = noisy_sine(100, 0.0);
        v[50] = f64::NAN;
        assert_eq!(step(&v), None);
    }
}
