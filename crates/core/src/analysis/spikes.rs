//! Spikes: one to three samples of the deflection far off a fitted model (the diagnosis's
//! nominal twin, the fit's refinement on the deflection), with the residual about them at
//! the floor. A converter's or a transfer's error, or a burst of
//! pick-up, not a force: no physics in the catalog moves the lever by many σ for a sample
//! and puts it back.
//!
//! `recording::glitch` mends a single sample far off a *smooth run* of the record itself,
//! before any fit. In contact under a fast multisine the record is not smooth at the sample
//! scale (a 800 Hz line sampled at 4 kHz), and a glitch must be over thirty times that
//! curvature to be told from it: six single samples of 16 σ added to a clean corpus record
//! escaped that rule and left the diagnosis `unexplained` without a word of why. Against the
//! nominal twin's residual, which is at the floor about them, they stand out at once.

use super::median;

/// How far past the floor's σ a residual sample must lie: Gaussian noise passes 8 σ once in
/// 10¹⁵ samples.
pub const SPIKE_SIGMAS: f64 = 8.0;

/// The longest run of such samples that is a spike; a longer one is an event.
pub const SPIKE_RUN: usize = 3;

/// Samples either side of a run over which the residual must be at the floor: its RMS
/// under [`AT_FLOOR_RMS`] σ and no sample past [`AROUND_MAX`] σ (Gaussian noise passes 5 σ
/// in one of 60 000 such stretches). A snap-in, a pull-off or a ringing mode the nominal
/// twin lacks leaves a misfit over many samples about its largest ones, and is not a spike.
/// Nor is a misfit of high crest factor: a drag the nominal twin lacks, under a multisine
/// whose fastest line has five samples a period, left a residual of 2.4 σ RMS with peaks of
/// 10 σ in single samples (three corpus records; a median magnitude under 1.5 σ, tried
/// first, let them pass).
pub const REACH: usize = 16;

/// See [`REACH`].
pub const AT_FLOOR_RMS: f64 = 1.5;

/// See [`REACH`].
pub const AROUND_MAX: f64 = 5.0;

/// How far the drive's second difference may stand above its own median over [`REACH`]
/// samples either side, within three samples of a run: past it the drive turns there (an
/// approach ending, a step), where a twin discretised otherwise than the recording's
/// instrument misfits for a sample or two (an independent simulator's approach reversing
/// into a step left 9.1 σ on the sample after the turn).
pub const DRIVE_TURN: f64 = 10.0;

/// The spikes of a residual `r` (V) against a floor of `sigma_v`, ascending, where the
/// drive is `drive`; samples in `left_out` (ascending: pinned at a limit, mended) are not
/// residuals and are skipped.
pub fn isolated(r: &[f64], sigma_v: f64, left_out: &[usize], drive: &[f64]) -> Vec<usize> {
    let n = r.len();
    if sigma_v.is_nan() || sigma_v <= 0.0 {
        return vec![];
    }
    let over =
        |k: usize| left_out.binary_search(&k).is_err() && r[k].abs() > SPIKE_SIGMAS * sigma_v;
    let mut out = vec![];
    let mut k = 0;
    while k < n {
        if !over(k) {
            k += 1;
            continue;
        }
        let start = k;
        while k < n && over(k) {
            k += 1;
        }
        if k - start > SPIKE_RUN {
            continue;
        }
        // About the run, two samples clear of it (a spike through an anti-alias filter).
        let before = start.saturating_sub(REACH)..start.saturating_sub(2);
        let after = (k + 2).min(n)..(k + REACH).min(n);
        let around: Vec<f64> = before.chain(after).map(|j| r[j].abs()).collect();
        if around.len() < REACH {
            continue;
        }
        let rms = (around.iter().map(|v| v * v).sum::<f64>() / around.len() as f64).sqrt();
        let peak = around.iter().copied().fold(0.0, f64::max);
        if rms < AT_FLOOR_RMS * sigma_v
            && peak < AROUND_MAX * sigma_v
            && !drive_turns(drive, start, k)
        {
            out.extend(start..k);
        }
    }
    out
}

/// The drive's rounding, relative to its magnitude, below which a second difference is no
/// turn: far above a double's (10⁻¹⁶), far below any turn an instrument makes (an approach
/// starting from rest turns by its step per sample, 10⁻³ of the drive).
pub const DRIVE_ROUNDING: f64 = 1e-12;

/// Whether the drive turns within three samples of `start..end` ([`DRIVE_TURN`]).
fn drive_turns(drive: &[f64], start: usize, end: usize) -> bool {
    let n = drive.len();
    if n < 3 {
        return false;
    }
    let turn = |j: usize| (drive[j - 1] - 2.0 * drive[j] + drive[j + 1]).abs();
    let span = |a: usize, b: usize| a.max(1)..b.min(n - 1);
    let mut scale: Vec<f64> = span(start.saturating_sub(REACH), end + REACH)
        .map(turn)
        .collect();
    let typical = median(&mut scale);
    // A ramp computed in floating point has second differences of its rounding (4·10⁻¹⁶ V
    // on a 2.8 V approach), which a median of zero over a straight stretch would call a
    // turn: a turn must stand above the drive's own rounding too (a run of three samples
    // of 14–17 σ on a corpus null's approach was kept in the fit so, and left the null
    // `unexplained`).
    let rounding = span(start.saturating_sub(REACH), end + REACH)
        .map(|j| drive[j].abs())
        .fold(0.0, f64::max)
        * DRIVE_ROUNDING;
    let bar = (DRIVE_TURN * typical).max(rounding);
    span(start.saturating_sub(3), end + 3).any(|j| turn(j) > bar)
}

/// Where the spikes were and how large, for a note: `spikes` index `r`, whose first sample
/// is the recording's `offset`, and lie off `model` (what `r` is the residual of).
pub fn describe(
    spikes: &[usize],
    r: &[f64],
    sigma: f64,
    fs_hz: f64,
    offset: usize,
    model: &str,
) -> String {
    let first = offset + spikes.first().copied().unwrap_or(0);
    let largest = spikes.iter().fold(0.0f64, |m, &k| m.max(r[k].abs()));
    format!(
        "deflection_v: {} sample{} of spikes, runs of 1 to {SPIKE_RUN} samples (the first at t = {:.4} s, \
         CSV row {}; up to {:.1} σ of the floor off {model}, where the residual about \
         them is at the floor): no physics moves the lever so for a sample and puts it back",
        spikes.len(),
        if spikes.len() == 1 { "" } else { "s" },
        first as f64 / fs_hz,
        first + 2,
        largest / sigma,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::noise::tests::white_and_pink;

    #[test]
    fn spikes_are_found_and_events_are_not() {
        let sigma = 0.003;
        let mut r = white_and_pink(4000, sigma, 0.0, 3);
        // A single sample and a run of three, 12 σ.
        r[500] += 12.0 * sigma;
        for v in &mut r[1500..1503] {
            *v -= 12.0 * sigma;
        }
        // A run of five: an event, not a spike.
        for v in &mut r[2500..2505] {
            *v += 12.0 * sigma;
        }
        // A step, as a pull-off the twin lacks leaves.
        for v in &mut r[3000..3200] {
            *v += 12.0 * sigma;
        }
        // A misfit of high crest factor: a line of 2 σ amplitude five samples a period
        // (1.7 σ RMS with the floor) and single samples of about 10 σ on it.
        for (j, v) in r[3500..3600].iter_mut().enumerate() {
            let phase = j as f64 * 2.0 * std::f64::consts::PI / 5.0;
            *v += sigma * (2.0 * phase.sin() + if j % 37 == 0 { 8.0 } else { 0.0 });
        }
        // A ramp: the drive turns nowhere. Computed in floating point, as an approach is,
        // its second differences are rounding, not zero.
        let ramp: Vec<f64> = (0..4000).map(|k| 2.8 + k as f64 * 2.7e-3).collect();
        assert!(ramp.windows(3).any(|w| w[0] - 2.0 * w[1] + w[2] != 0.0));
        assert_eq!(isolated(&r, sigma, &[], &ramp), vec![500, 1500, 1501, 1502]);
        // A left-out sample is no residual.
        assert_eq!(isolated(&r, sigma, &[500], &ramp), vec![1500, 1501, 1502]);
        // The drive turning at the first: a twin's misfit there, not a spike.
        let turning: Vec<f64> = ramp.iter().map(|&t| (t - ramp[501]).abs()).collect();
        assert_eq!(isolated(&r, sigma, &[], &turning), vec![1500, 1501, 1502]);
        // The floor alone has none.
        let floor = white_and_pink(20_000, sigma, 0.0, 4);
        assert!(isolated(&floor, sigma, &[], &vec![0.0; 20_000]).is_empty());
    }
}
