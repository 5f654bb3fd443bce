//! Missing values in a recording's optional channels.
//!
//! The format lets an optional column (`reference_deflection_v`, `measured_height_nm`) carry
//! empty or non-finite cells, read as missing values (NaN); a real export drops a sample now
//! and then. Where such a channel is an *input* — the indentation the offline fit reads from
//! the reference, the base position a diagnosis takes from the height sensor — one missing
//! value stopped the fit, or made the diagnosis drop the whole channel, silently: an
//! independent simulator's delay recording beside a height sensor lost its verdict to one
//! empty cell.
//!
//! [`with_gaps_filled`] fills missing values by linear interpolation between the nearest
//! values on either side ([`fill_gaps`]) and returns where they were ([`ChannelGaps`]), so
//! that a use which *scores* the channel (the diagnosis's witnesses) leaves those samples out
//! rather than score invented ones. A channel missing more than [`MAX_MISSING_FRACTION`] of
//! its samples is not filled but removed: that is no longer dropped samples but a channel
//! not recorded for long stretches, which interpolation would make up.

pub(crate) use super::csv::{HEIGHT, REFERENCE};
use super::Recording;
use std::borrow::Cow;

/// The largest fraction of a channel's samples that may be missing for it to be filled and
/// used: beyond it, the gaps are no longer dropped samples but a channel that was not
/// recorded for long stretches, which interpolation would make up.
pub const MAX_MISSING_FRACTION: f64 = 0.05;

/// What [`with_gaps_filled`] did to one optional channel.
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelGap {
    /// The column's name.
    pub channel: &'static str,
    /// Its length, samples.
    pub samples: usize,
    /// The samples (indices, ascending) that were missing.
    pub missing: Vec<usize>,
    /// Time of the first missing sample from the record's start, s.
    pub first_at_s: f64,
    /// Removed (too much missing) rather than filled.
    pub removed: bool,
}

impl std::fmt::Display for ChannelGap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (k, n) = (self.missing.len(), self.samples);
        if self.removed {
            write!(
                f,
                "{}: left out: {k} of {n} samples missing, more than the {:.0} % dropped samples account for",
                self.channel,
                100.0 * MAX_MISSING_FRACTION
            )
        } else {
            write!(
                f,
                "{}: {k} of {n} samples missing (the first at t = {:.4} s, CSV row {}): filled by linear interpolation",
                self.channel,
                self.first_at_s,
                self.missing.first().map_or(0, |i| i + 2)
            )
        }
    }
}

/// What [`with_gaps_filled`] did to the optional channels: one entry per channel filled or
/// removed.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ChannelGaps {
    pub channels: Vec<ChannelGap>,
}

impl ChannelGaps {
    /// The samples of `channel` that were missing and are now filled (none where it was
    /// complete or removed).
    pub fn filled(&self, channel: &str) -> &[usize] {
        self.channels
            .iter()
            .find(|g| g.channel == channel && !g.removed)
            .map_or(&[], |g| &g.missing)
    }
}

/// The samples (indices, ascending) of `column` that are missing: not finite.
pub fn missing_samples(column: &[f64]) -> Vec<usize> {
    (0..column.len())
        .filter(|&k| !column[k].is_finite())
        .collect()
}

/// `column` with its `missing` samples ([`missing_samples`]) filled by linear interpolation
/// between the nearest finite values on either side (the nearest one, at the ends); `None`
/// when more than [`MAX_MISSING_FRACTION`] are missing, or no value is finite.
pub fn fill_gaps(column: &[f64], missing: &[usize]) -> Option<Vec<f64>> {
    if missing.len() as f64 > MAX_MISSING_FRACTION * column.len() as f64 {
        return None;
    }
    let mut filled = column.to_vec();
    let mut k = 0;
    while k < filled.len() {
        if filled[k].is_finite() {
            k += 1;
            continue;
        }
        let end = (k..filled.len())
            .find(|&j| filled[j].is_finite())
            .unwrap_or(filled.len());
        let before = k.checked_sub(1).map(|j| (j, filled[j]));
        let after = filled.get(end).map(|&v| (end, v));
        for (j, slot) in filled.iter_mut().enumerate().take(end).skip(k) {
            *slot = match (before, after) {
                (Some((a, va)), Some((b, vb))) => va + (vb - va) * (j - a) as f64 / (b - a) as f64,
                (Some((_, v)), None) | (None, Some((_, v))) => v,
                (None, None) => return None,
            };
        }
        k = end;
    }
    Some(filled)
}

/// `rec` with the missing values of its optional channels filled ([`fill_gaps`]), or the
/// channel removed where too much of it is missing; borrowed unchanged where nothing is
/// missing.
pub fn with_gaps_filled(rec: &Recording) -> (Cow<'_, Recording>, ChannelGaps) {
    let t0 = rec.time_s.first().copied().unwrap_or(0.0);
    let treat = |channel: &'static str, column: Option<&Vec<f64>>| {
        let column = column?;
        let missing = missing_samples(column);
        let first = *missing.first()?;
        let filled = fill_gaps(column, &missing);
        let gap = ChannelGap {
            channel,
            samples: column.len(),
            first_at_s: rec.time_s.get(first).map_or(f64::NAN, |t| t - t0),
            missing,
            removed: filled.is_none(),
        };
        Some((gap, filled))
    };
    let reference = treat(REFERENCE, rec.reference_deflection_v.as_ref());
    let height = treat(HEIGHT, rec.measured_height_nm.as_ref());
    if reference.is_none() && height.is_none() {
        return (Cow::Borrowed(rec), ChannelGaps::default());
    }
    let mut out = rec.clone();
    let mut gaps = ChannelGaps::default();
    for (treated, slot) in [
        (reference, &mut out.reference_deflection_v),
        (height, &mut out.measured_height_nm),
    ] {
        if let Some((gap, filled)) = treated {
            *slot = filled;
            gaps.channels.push(gap);
        }
    }
    (Cow::Owned(out), gaps)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Gaps inside are interpolated, gaps at an end take the nearest value, and the
    /// missing samples are listed.
    #[test]
    fn gaps_are_filled_linearly_and_listed() {
        let nan = f64::NAN;
        let mut x: Vec<f64> = (0..100).map(|k| k as f64).collect();
        x[0] = nan;
        x[10] = nan;
        x[11] = f64::INFINITY;
        x[99] = nan;
        let missing = missing_samples(&x);
        assert_eq!(missing, vec![0, 10, 11, 99]);
        let filled = fill_gaps(&x, &missing).unwrap();
        assert_eq!(filled[0], 1.0);
        assert_eq!((filled[10], filled[11]), (10.0, 11.0));
        assert_eq!(filled[99], 98.0);
        assert!(filled.iter().all(|v| v.is_finite()));
        // Nothing missing: the column as it was.
        let clean: Vec<f64> = (0..100).map(|k| k as f64 * 0.5).collect();
        assert!(missing_samples(&clean).is_empty());
        assert_eq!(fill_gaps(&clean, &[]), Some(clean.clone()));
    }

    /// More than 5 % missing, or nothing at all there: not filled.
    #[test]
    fn a_channel_mostly_missing_is_not_filled() {
        let mut x = vec![1.0; 100];
        for v in x.iter_mut().take(6) {
            *v = f64::NAN;
        }
        assert_eq!(fill_gaps(&x, &missing_samples(&x)), None);
        x[5] = 1.0;
        assert!(fill_gaps(&x, &missing_samples(&x)).is_some());
        assert_eq!(fill_gaps(&[f64::NAN], &[0]), None);
    }
}
