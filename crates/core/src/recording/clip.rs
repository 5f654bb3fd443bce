//! A deflection channel that saturated: samples pinned at the detector's or its converter's
//! limit.
//!
//! A photodiode driven past its range, or an ADC past its input range, writes the same
//! value sample after sample while the force goes on changing. No model of the lever
//! explains a flat top, and the users of a recording fitted one anyway: a clean twin's
//! record clipped at 85 % of its peak was named `detector_nonlinearity` by the diagnosis,
//! and `viscoprobe fit` put J0 7 % off the truth with an interval that excluded it.
//! [`find_clipped`] finds such stretches; the diagnosis leaves them out of every χ²
//! ([`reach`], [`leave_out`]), the offline fit ends its window before them, and both say so
//! ([`Clip::describe`]).
//!
//! A value repeated at the very extreme of a record is the sign: noise of several
//! quantisation steps makes two samples alike rarely, and the largest value of the record
//! alike on [`MIN_RUN`] consecutive samples never, unless something held it there. A record
//! whose noise is under [`MIN_NOISE_IN_STEPS`] of its quantisation steps can repeat any value,
//! its extremes too, and is not judged.

/// Consecutive samples at the record's extreme that make a clip.
pub const MIN_RUN: usize = 4;

/// The least noise, in quantisation steps (the smallest difference between two values the
/// record holds), for a repeated extreme to be read as a clip.
pub const MIN_NOISE_IN_STEPS: f64 = 2.0;

/// Samples pinned at one limit of the deflection channel.
#[derive(Debug, Clone, PartialEq)]
pub struct Clip {
    /// The value they sit at, V.
    pub level_v: f64,
    /// Pinned at the record's largest value (else its smallest).
    pub high: bool,
    /// The samples at that value (indices, ascending).
    pub samples: Vec<usize>,
    /// The longest run of consecutive ones.
    pub longest_run: usize,
}

impl Clip {
    /// Where the channel sat pinned and how much of it, for a sentence the caller ends with
    /// what it did about it.
    pub fn describe(&self, n: usize, fs_hz: f64) -> String {
        let first = self.samples.first().copied().unwrap_or(0);
        let last = self.samples.last().copied().unwrap_or(0);
        format!(
            "deflection_v: pinned at its {} value, {:.4} V, on {} of {n} samples ({:.1} %, \
             the longest run {} samples), from t = {:.4} s (CSV row {}) to {:.4} s: the \
             detector or its converter saturated there",
            if self.high { "largest" } else { "smallest" },
            self.level_v,
            self.samples.len(),
            100.0 * self.samples.len() as f64 / n.max(1) as f64,
            self.longest_run,
            first as f64 / fs_hz,
            first + 2,
            last as f64 / fs_hz,
        )
    }
}

/// The clips of `y` (none, one or two: at its largest and at its smallest value), given the
/// noise `sigma_v` of its free lever.
pub fn find_clipped(y: &[f64], sigma_v: f64) -> Vec<Clip> {
    if y.len() < MIN_RUN || y.iter().any(|v| !v.is_finite()) {
        return vec![];
    }
    let step = quantisation_step(y);
    if step > 0.0 && sigma_v < MIN_NOISE_IN_STEPS * step {
        return vec![];
    }
    let top = y.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let bottom = y.iter().copied().fold(f64::INFINITY, f64::min);
    [(top, true), (bottom, false)]
        .into_iter()
        .filter_map(|(level_v, high)| {
            let samples: Vec<usize> = (0..y.len()).filter(|&k| y[k] == level_v).collect();
            let longest_run = longest_run(&samples);
            (longest_run >= MIN_RUN).then_some(Clip {
                level_v,
                high,
                samples,
                longest_run,
            })
        })
        .collect()
}

/// The smallest positive difference between two values of `y`; 0 where all are equal.
fn quantisation_step(y: &[f64]) -> f64 {
    let mut v = y.to_vec();
    v.sort_by(f64::total_cmp);
    v.windows(2)
        .map(|w| w[1] - w[0])
        .filter(|&d| d > 0.0)
        .fold(0.0, |m: f64, d| if m == 0.0 { d } else { m.min(d) })
}

/// The longest run of consecutive indices in the ascending `samples`.
fn longest_run(samples: &[usize]) -> usize {
    let mut best = 0;
    let mut run = 0;
    for (i, &k) in samples.iter().enumerate() {
        run = if i > 0 && samples[i - 1] + 1 == k {
            run + 1
        } else {
            1
        };
        best = best.max(run);
    }
    best
}

/// The `clipped` samples (ascending) and the `lags` samples after each, below `n`: a whitening
/// filter of order `lags` carries a sample's residual into that many after it.
pub fn reach(clipped: &[usize], lags: usize, n: usize) -> Vec<usize> {
    let mut out = vec![false; n];
    for &k in clipped {
        out[k.min(n)..(k + lags + 1).min(n)].fill(true);
    }
    (0..n).filter(|&k| out[k]).collect()
}

/// `indices` (ascending) without those in `left_out` (ascending).
pub fn leave_out(indices: &[usize], left_out: &[usize]) -> Vec<usize> {
    let mut out = left_out.iter().peekable();
    indices
        .iter()
        .copied()
        .filter(|&k| {
            while out.next_if(|&&o| o < k).is_some() {}
            out.peek() != Some(&&k)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A noisy ramp through a limit: the samples past it, and only those, are found.
    fn clipped_ramp(limit: f64) -> (Vec<f64>, Vec<usize>) {
        let mut state = 12345u64;
        let mut noise = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.01
        };
        let y: Vec<f64> = (0..2000)
            .map(|k| (k as f64 / 1000.0 + noise()).min(limit))
            .collect();
        let pinned = (0..y.len()).filter(|&k| y[k] == limit).collect();
        (y, pinned)
    }

    #[test]
    fn a_flat_top_is_found_and_only_it() {
        let (y, pinned) = clipped_ramp(1.5);
        assert!(pinned.len() > 400, "{}", pinned.len());
        let clips = find_clipped(&y, 0.003);
        assert_eq!(clips.len(), 1, "{clips:?}");
        assert!(clips[0].high);
        assert_eq!(clips[0].level_v, 1.5);
        assert_eq!(clips[0].samples, pinned);
        assert!(clips[0].describe(y.len(), 1000.0).contains("1.5000 V"));
    }

    #[test]
    fn a_noisy_record_without_a_limit_has_no_clip() {
        let (y, pinned) = clipped_ramp(10.0);
        assert!(pinned.is_empty());
        assert!(find_clipped(&y, 0.003).is_empty());
    }

    #[test]
    fn a_coarsely_quantised_record_is_not_judged() {
        let (y, _) = clipped_ramp(1.5);
        // Steps of 0.1 against noise of 0.003: any value repeats, the extremes too.
        let coarse: Vec<f64> = y.iter().map(|v| (v * 10.0).round() / 10.0).collect();
        assert!(find_clipped(&coarse, 0.003).is_empty());
        // Steps of 10⁻⁴, 30 to the noise: the clip is found as on unquantised values.
        let fine: Vec<f64> = y.iter().map(|v| (v * 1e4).round() / 1e4).collect();
        let clips = find_clipped(&fine, 0.003);
        assert_eq!(clips.len(), 1, "{clips:?}");
        assert_eq!(clips[0].level_v, 1.5);
    }

    #[test]
    fn leaving_out_takes_the_whitening_lags_too() {
        let gone = reach(&[2, 3, 9], 2, 10);
        assert_eq!(gone, vec![2, 3, 4, 5, 9]);
        let kept = leave_out(&[0, 1, 2, 3, 4, 5, 6, 7, 9], &gone);
        assert_eq!(kept, vec![0, 1, 6, 7]);
        assert!(leave_out(&[], &gone).is_empty());
    }
}
