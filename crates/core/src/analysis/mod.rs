//! From a recording to a Prony fit: the offline path of `viscoprobe fit`.
//!
//! [`prepare`] turns a [`Recording`] into the linear pair (u, y) over the in-contact window,
//! from the samples alone (no `[notes]`, no `[truth]`: a third-party file has neither):
//!
//! - the deflection baseline from the free approach: a constant, plus a tilt linear in the
//!   drive position when the approach shows one beyond its noise (virtual deflection, as on
//!   JPK heads; a tilt that is not significant is not extrapolated into the contact);
//! - the contact point where the force leaves the baseline noise, walked back to where it
//!   last sat within it;
//! - the end of the window where the final unloading begins (the drive falling at the retract
//!   speed toward the loss of contact): Lee–Radok holds while the contact grows or holds;
//! - the force `F = K·C·(v − baseline)` and the indentation — from the hard reference channel
//!   where there is one (the spec's `C·(v_ref − v)`), otherwise from the actuator position
//!   (the position sensor if recorded, else the commanded drive) minus the lever's deflection.
//!
//! [`fit_recording`] then picks the estimator for the excitation: when the in-contact drive
//! is periodic (whole periods found in the drive itself, [`periodic`]) the frequency-domain
//! maximum-likelihood fit on whole periods, with the noise measured between periods;
//! otherwise the time-domain output-error fit over the whole window. Both are discretised
//! with a first-order hold (continuous physics under a force linear between samples). The
//! order is fixed or chosen by the Bayesian information criterion; orders whose retardation
//! times fall outside what the record resolves are refused for selection.
//!
//! Both estimators see the detector noise in their input as well as their output (force and
//! indentation come from the same lever). The frequency-domain ML models that (input noise
//! and its correlation with the output's, measured between periods); the time-domain output
//! error does not, and biases the fastest terms. So a last stage, [`fn@refine`], fits the
//! measured deflection with the noise-free drive as input and the contact position as a
//! parameter: for every order of a non-periodic drive (its BIC is then the deflection's), and
//! for the chosen order of a periodic drive whose indentation comes from the drive (where the
//! contact position is otherwise read off one sample). It needs the drive to be the
//! actuator's position: a hard reference channel calibrates its scale (and refuses it when
//! the reference is not a straight line in the drive); a position-sensor channel is used as
//! before, without refinement.

pub mod periodic;
pub mod refine;
pub mod spikes;

use crate::discrete::{foh_highpass, Sampling};
use crate::estimate::frequency::{
    fit_spectra, periodic_spectra, remove_linear_drift, FrequencyFitOptions, LineSelection,
};
use crate::estimate::time_domain::{fit_time_domain, time_domain_starts, TimeFitOptions};
use crate::estimate::{Estimate, EstimateError, Method};
use crate::fan::{self, Fan, Serial};
use crate::prony::PronySeries;
use crate::recording::{Drive, Recording};
use nalgebra::{DMatrix, DVector};
use periodic::{detect_periodic, PeriodicRun};
use refine::{refine, Problem, Refined};
use thiserror::Error;

/// Why a recording could not be fitted.
#[derive(Debug, Error)]
pub enum FitError {
    #[error("no contact found: the force never leaves the baseline noise ({noise_n:.3e} N rms)")]
    NoContact { noise_n: f64 },
    #[error("no contact found: the force never rises out of the baseline noise ({noise_n:.3e} N rms), yet falls {drop_n:.3e} N below it; recording/1 counts deflection positive when the tip is pushed away from the sample: is the deflection channel's sign inverted?")]
    InvertedDeflection { noise_n: f64, drop_n: f64 },
    #[error("the recording has no drive in nm and no position sensor: set [piezo] gain_nm_per_v or record a reference channel")]
    NoIndentation,
    #[error("the in-contact window has only {0} samples")]
    TooShort(usize),
    #[error(transparent)]
    Record(#[from] RecordFault),
    #[error("the deflection sits pinned at {level_v:.4} V from t = {at_s:.4} s, {after} samples after the contact: the detector or its converter saturated, and a fit needs the force it hid; record within the detector's range (viscoprobe diagnose leaves such samples out)")]
    PinnedAtContact {
        level_v: f64,
        at_s: f64,
        after: usize,
    },
    #[error("estimation: {0}")]
    Estimate(#[from] EstimateError),
}

/// A recording neither the offline fit nor the diagnosis can read, for a reason in the
/// recording itself: one message each, whichever of the two met it.
#[derive(Debug, Error)]
pub enum RecordFault {
    #[error("the record seems to start in contact: its first {samples} samples scatter {first_v:.3e} V rms, over {ratio} times its last {samples} samples' {last_v:.3e} V rms (a free lever scatters alike at both ends); the baseline, the contact and the noise floor are read on the free lever before the contact, so record (or keep) the approach", ratio = START_IN_CONTACT_RATIO)]
    StartsInContact {
        samples: usize,
        first_v: f64,
        last_v: f64,
    },
    #[error("the {column} column never moves (every sample {value} {unit}): nothing in the recording pushed the tip into contact; is it the channel the instrument drove?")]
    StillDrive {
        column: &'static str,
        value: f64,
        unit: &'static str,
    },
    #[error("the lever deflects {deflection_nm:.4e} nm (deflection_sensitivity_nm_per_v times the deflection's rise above the record's start), {ratio:.3e} times the {base_nm:.4e} nm its base travels over the whole record ({base}): a tip cannot deflect further than the base pushed it, so a calibration or a column's unit is off; check the drive column's unit, piezo.gain_nm_per_v and cantilever.deflection_sensitivity_nm_per_v", ratio = deflection_nm / base_nm)]
    DeflectsPastBase {
        deflection_nm: f64,
        base_nm: f64,
        /// What the base's travel was read from.
        base: &'static str,
    },
}

/// Below the baseline by this many noise σ, a signal that never rises above it is a
/// deflection channel of the wrong sign rather than no contact.
const INVERTED_SIGMAS: f64 = 20.0;

/// Whether a deflection (or force) that never rises out of its baseline noise `noise` but
/// falls `drop` below the baseline was recorded with its sign inverted: the rule the offline
/// fit ([`prepare`]) and the diagnosis both apply.
pub(crate) fn looks_inverted(drop: f64, noise: f64) -> bool {
    drop > INVERTED_SIGMAS * noise
}

/// How many times the scatter of a record's last samples its first samples may scatter
/// before the record is read as starting in contact ([`check_starts_free`]). A free lever
/// scatters alike at both ends: on the concealed corpus, the independent simulator's
/// recordings and the shared JPK file, the first samples' scatter came to at most 1.27
/// times the last samples'; a corpus record cut to begin in contact, to 30 times.
const START_IN_CONTACT_RATIO: f64 = 5.0;

/// [`RecordFault::StartsInContact`] where the scatter (V rms, [`median_and_scatter`]) of the
/// first samples of `deflection_v` is over [`START_IN_CONTACT_RATIO`] times that of its last
/// (2 % of the record each, 20 to 256 samples: the window the offline fit takes its free
/// baseline from): a record cut to begin in contact (its retract ending free), which has no
/// free lever before the contact to find the contact and the noise floor from. The offline
/// fit took such a record's first samples for the free baseline and put J0 nine times off
/// the truth; the diagnosis found no contact.
pub(crate) fn check_starts_free(deflection_v: &[f64]) -> Result<(), RecordFault> {
    let n = deflection_v.len();
    let w = (n / 50).clamp(20, 256);
    if n < 2 * w {
        return Ok(());
    }
    let (_, first_v) = median_and_scatter(&deflection_v[..w]);
    let (_, last_v) = median_and_scatter(&deflection_v[n - w..]);
    match last_v > 0.0 && first_v > START_IN_CONTACT_RATIO * last_v {
        true => Err(RecordFault::StartsInContact {
            samples: w,
            first_v,
            last_v,
        }),
        false => Ok(()),
    }
}

/// [`RecordFault::StillDrive`] where `base` (the samples of the column `column`, in `unit`)
/// holds one value throughout: a column that cannot have pushed the tip into contact (a
/// channel exported from the wrong output, say).
pub(crate) fn check_moves(
    base: &[f64],
    column: &'static str,
    unit: &'static str,
) -> Result<(), RecordFault> {
    match base.first() {
        Some(&value) if base.iter().all(|&x| x == value) => Err(RecordFault::StillDrive {
            column,
            value,
            unit,
        }),
        _ => Ok(()),
    }
}

/// How many times its base's whole travel a lever may deflect before the record's
/// calibration reads as inconsistent ([`check_travel`]). A tip the base pushes deflects at
/// most as far as the base moved, less what the sample takes: over the 59 corpus files, 138
/// recordings of the independent simulator (five sets) and the shared JPK file the ratio
/// came to at most 0.48.
const DEFLECTS_PAST_BASE_RATIO: f64 = 1.5;

/// [`RecordFault::DeflectsPastBase`] where the lever deflects (nm: the sensitivity times
/// the deflection's rise above the median of the record's first 2 %, less 10 σ of its
/// scatter there) over [`DEFLECTS_PAST_BASE_RATIO`] times the largest travel of its base
/// that the record gives: the drive's range (through the gain, for a drive in volts), the
/// height sensor's, the hard reference's deflection. A drive written 10⁻³⁰⁰ times too
/// small was diagnosed as `thermal_drift` at 5446 χ² per sample, and its fit stopped at
/// "no physical start value found". Without a gain, sensor or reference nothing bounds it.
pub(crate) fn check_travel(rec: &Recording) -> Result<(), RecordFault> {
    let range = |x: &[f64]| {
        let (lo, hi) = x
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        hi - lo
    };
    let c = rec.meta.cantilever.deflection_sensitivity_nm_per_v;
    let drive = match &rec.drive {
        Drive::Nanometres(v) => Some(range(v)),
        Drive::Volts(v) => rec.meta.piezo.map(|p| p.gain_nm_per_v.abs() * range(v)),
    };
    let (base_nm, base) = [
        (drive, "the drive"),
        (
            rec.measured_height_nm.as_deref().map(range),
            "the height sensor",
        ),
        (
            rec.reference_deflection_v.as_deref().map(|r| c * range(r)),
            "the hard reference's deflection",
        ),
    ]
    .into_iter()
    .filter_map(|(t, what)| t.filter(|t| t.is_finite()).map(|t| (t, what)))
    .fold((0.0, "the drive"), |a, b| if b.0 > a.0 { b } else { a });
    let y = &rec.deflection_v;
    let head = (y.len() / 50).clamp(20.min(y.len()), y.len());
    if head == 0 || base_nm == 0.0 {
        return Ok(());
    }
    let (start, scatter) = median_and_scatter(&y[..head]);
    let top = y.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let deflection_nm = c * (top - start - 10.0 * scatter).max(0.0);
    match deflection_nm > DEFLECTS_PAST_BASE_RATIO * base_nm {
        true => Err(RecordFault::DeflectsPastBase {
            deflection_nm,
            base_nm,
            base,
        }),
        false => Ok(()),
    }
}

/// The error of a force that never rises out of the baseline noise `noise_n`: a sign
/// inverted where it falls far below it instead ([`looks_inverted`]), no contact otherwise.
fn no_contact(force: &[f64], noise_n: f64) -> FitError {
    let lowest = force.iter().copied().fold(0.0f64, f64::min);
    if looks_inverted(-lowest, noise_n) {
        FitError::InvertedDeflection {
            noise_n,
            drop_n: -lowest,
        }
    } else {
        FitError::NoContact { noise_n }
    }
}

/// The in-contact (u, y) pair of a recording.
#[derive(Debug, Clone)]
pub struct Prepared {
    pub u: Vec<f64>,
    pub y: Vec<f64>,
    pub fs_hz: f64,
    /// Sample index of the contact point and end of the fitted window (exclusive).
    pub contact_index: usize,
    /// Where the force last sat within the baseline noise; equals `contact_index` unless the
    /// contact point was searched for by fit (a slow rise out of the noise).
    pub contact_walkback_index: usize,
    pub end_index: usize,
    /// Free-lever deflection at the contact point, V, and its noise, V rms.
    pub baseline_v: f64,
    pub baseline_noise_v: f64,
    /// Standard error of that baseline level, V (`noise/√n` over the free approach): a
    /// constant force offset the contact window cannot tell from the compliance, carried
    /// into the intervals of the time-domain fit.
    pub baseline_level_sigma_v: f64,
    /// Baseline tilt, V per nm of drive (0 when the approach shows none beyond its noise).
    pub baseline_tilt_v_per_nm: f64,
    /// Where the indentation came from: `reference`, `measured_height` or `drive`.
    pub indentation_source: &'static str,
    /// Where the window was ended early at a deflection pinned at its limit: that clip
    /// ([`crate::recording::clip::Clip::describe`]).
    pub pinned: Option<String>,
    /// Over the window: recorded time, s; force, N; indentation, m; drive (its own units).
    pub time_s: Vec<f64>,
    pub force_n: Vec<f64>,
    pub indentation_m: Vec<f64>,
    pub drive: Vec<f64>,
}

/// The median of `x`, which it sorts.
pub(crate) fn median(x: &mut [f64]) -> f64 {
    x.sort_by(f64::total_cmp);
    x[x.len() / 2]
}

/// The median of `x` and its scatter about it, `1.4826·median|x − median|` (the σ of
/// Gaussian noise, untouched by a few outliers).
pub(crate) fn median_and_scatter(x: &[f64]) -> (f64, f64) {
    let m = median(&mut x.to_vec());
    let mut dev: Vec<f64> = x.iter().map(|v| (v - m).abs()).collect();
    (m, 1.4826 * median(&mut dev))
}

/// `v ≈ a + b·x` over the free approach; `b` only when it stands 4σ clear of zero.
#[derive(Debug, Clone, Copy)]
struct Baseline {
    a: f64,
    b: f64,
    x0: f64,
    noise: f64,
    /// Samples and `Σ(x − x̄)²` of the fit: the level's standard error at `x`.
    n: f64,
    sxx: f64,
}

impl Baseline {
    fn at(&self, x: f64) -> f64 {
        self.a + self.b * (x - self.x0)
    }

    /// Standard error of the level at `x`, V.
    fn sigma_at(&self, x: f64) -> f64 {
        let lever = if self.b != 0.0 && self.sxx > 0.0 {
            (x - self.x0).powi(2) / self.sxx
        } else {
            0.0
        };
        self.noise * (1.0 / self.n.max(1.0) + lever).sqrt()
    }

    fn fit(v: &[f64], x: &[f64], tilt: bool) -> Self {
        let n = v.len() as f64;
        let xm = x.iter().sum::<f64>() / n;
        let vm = v.iter().sum::<f64>() / n;
        let sxx: f64 = x.iter().map(|t| (t - xm).powi(2)).sum();
        let sxv: f64 = x.iter().zip(v).map(|(t, w)| (t - xm) * (w - vm)).sum();
        let b = if tilt && sxx > 0.0 { sxv / sxx } else { 0.0 };
        let res: Vec<f64> = x
            .iter()
            .zip(v)
            .map(|(t, w)| w - vm - b * (t - xm))
            .collect();
        let mut abs: Vec<f64> = res.iter().map(|r| r.abs()).collect();
        let noise = 1.4826 * median(&mut abs);
        let b_sigma = if sxx > 0.0 {
            noise / sxx.sqrt()
        } else {
            f64::INFINITY
        };
        if b != 0.0 && b.abs() < 4.0 * b_sigma {
            return Self::fit(v, x, false);
        }
        // The level: a mean, not a median. A median of quantised samples is itself a grid
        // value, off the true level by up to half a converter step even where the noise
        // dithers the mean to well below it; and the mean's uncertainty (`noise/√n`) is what
        // the fit propagates into its intervals. Samples beyond 4σ (spikes) are left out.
        let a = if b == 0.0 {
            let mid = median(&mut res.clone());
            let kept: Vec<f64> = res
                .iter()
                .copied()
                .filter(|r| (r - mid).abs() <= 4.0 * noise)
                .collect();
            vm + kept.iter().sum::<f64>() / kept.len().max(1) as f64
        } else {
            vm
        };
        Self {
            a,
            b,
            x0: xm,
            noise,
            n,
            sxx,
        }
    }
}

/// Baseline, contact point, window, force and indentation of a recording (see the module
/// documentation).
pub fn prepare(rec: &Recording) -> Result<Prepared, FitError> {
    prepare_with(rec, &Serial)
}

/// [`prepare`], its trial contact points' fits spread by `fan`: the same result, bit for
/// bit, on any fan.
pub fn prepare_with(rec: &Recording, fan: &dyn Fan) -> Result<Prepared, FitError> {
    let n = rec.len();
    let k = rec.meta.cantilever.spring_constant_n_per_m;
    let c_m = rec.meta.cantilever.deflection_sensitivity_nm_per_v * 1e-9;
    let drive = rec.drive.values();
    let defl = &rec.deflection_v;
    if n < 60 {
        return Err(FitError::TooShort(n));
    }
    check_starts_free(defl)?;
    check_travel(rec)?;
    // A reference or a height sensor reads the indentation where the drive does not.
    if rec.reference_deflection_v.is_none() && rec.measured_height_nm.is_none() {
        check_moves(drive, rec.drive.column_name(), rec.drive.unit())?;
    }
    let baseline_over = |upto: usize, tilt: bool| {
        let upto = upto.clamp(20.min(n), n);
        Baseline::fit(&defl[..upto], &drive[..upto], tilt)
    };
    // (contact, force, index of the maximum, threshold) for a baseline.
    let locate = |bl: &Baseline| -> Result<(usize, Vec<f64>, usize, f64), FitError> {
        let force: Vec<f64> = defl
            .iter()
            .zip(drive)
            .map(|(v, x)| k * c_m * (v - bl.at(*x)))
            .collect();
        let fmax = force.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let threshold = (5.0 * k * c_m * bl.noise).max(0.02 * fmax);
        let imax = force.iter().position(|f| *f == fmax).unwrap_or(0);
        let above = force[..=imax]
            .iter()
            .position(|f| *f > threshold)
            .ok_or_else(|| no_contact(&force, k * c_m * bl.noise))?;
        // Walk back to where the force last sat within the baseline noise: the window starts
        // there, at rest (the fit's initial state), so a force step at the next sample is in
        // the window.
        let floor = k * c_m * bl.noise.max(1e-12);
        let contact = force[..above]
            .iter()
            .rposition(|f| *f <= floor)
            .unwrap_or(above);
        Ok((contact, force, imax, threshold))
    };
    // A first baseline from the first 2 % of the record, at most 256 samples (the tip is free
    // there in any sane recording), contact from it; then the baseline again, tilt allowed, from everything
    // before that contact, twice (a tilt moves the contact, which moves the baseline).
    let mut bl = baseline_over((n / 50).clamp(20, 256), false);
    let (mut contact, _, _, _) = locate(&bl)?;
    for _ in 0..2 {
        bl = baseline_over(contact.saturating_sub(contact / 20), true);
        contact = locate(&bl)?.0;
    }
    let (walkback, force, imax, threshold) = locate(&bl)?;
    let above = (walkback..=imax)
        .find(|&i| force[i] > threshold)
        .unwrap_or(walkback);
    let end = window_end(drive, &force, walkback, imax, threshold);
    // A deflection pinned at its limit (`recording::clip`) says only that the force was
    // beyond it, and no force is known from there on: the window ends at the first pinned
    // sample after the contact.
    let clips = crate::recording::clip::find_clipped(defl, bl.noise);
    let pinned = (clips.iter())
        .filter_map(|c| Some((c.samples.iter().copied().find(|&k| k > walkback)?, c)))
        .min_by_key(|(k, _)| *k)
        .filter(|(k, _)| *k < end);
    if let Some((k, c)) = pinned.filter(|(k, _)| *k <= walkback + MIN_WINDOW) {
        return Err(FitError::PinnedAtContact {
            level_v: c.level_v,
            at_s: k as f64 / rec.sample_rate_hz,
            after: k - walkback,
        });
    }
    let end = pinned.map_or(end, |(k, _)| k);
    let pinned_note = pinned.map(|(_, c)| c.describe(n, rec.sample_rate_hz));
    let build = |contact: usize| {
        let p = build_window(rec, &bl, &force, contact, end, contact != walkback);
        p.map(|p| Prepared {
            pinned: pinned_note.clone(),
            ..p
        })
    };
    // Where the force rises slowly out of the noise (soft gels, long-range forces), the last
    // sample within the noise band is not the contact of a Hertz contact: the contact point
    // is then chosen, between that sample and the threshold crossing, as the one whose (u, y)
    // a one-term viscoelastic model follows best — the contact point as a model parameter,
    // as in a Hertz fit with a free contact point.
    // The trial points' fits are independent: spread by `fan`, then compared in order.
    if above > walkback + CONTACT_SEARCH_MIN {
        let steps = 24.min(above - walkback);
        let trials = fan::map(fan, steps + 1, |s| {
            let c = walkback + (above - walkback) * s / steps;
            let p = build(c).ok()?;
            let mut opts = TimeFitOptions::new(1);
            opts.sampling = Sampling::FirstOrderHold { fs_hz: p.fs_hz };
            let est = fit_time_domain(&p.u, &p.y, p.fs_hz, &opts).ok()?;
            Some((nrmse(&p.y, &simulate_foh(&est.model, &p.u, p.fs_hz)), p))
        });
        let mut best: Option<(f64, Prepared)> = None;
        for (e, p) in trials.into_iter().flatten() {
            if best.as_ref().is_none_or(|(b, _)| e < *b) {
                best = Some((e, p));
            }
        }
        if let Some((_, mut p)) = best {
            p.contact_walkback_index = walkback;
            return Ok(p);
        }
    }
    build(walkback)
}

/// Samples between the noise-band contact and the threshold crossing above which the contact
/// point is searched for by fit.
const CONTACT_SEARCH_MIN: usize = 20;

/// The fewest samples past the contact an in-contact window may hold.
const MIN_WINDOW: usize = 50;

fn build_window(
    rec: &Recording,
    bl: &Baseline,
    force: &[f64],
    contact: usize,
    end: usize,
    searched: bool,
) -> Result<Prepared, FitError> {
    let c_m = rec.meta.cantilever.deflection_sensitivity_nm_per_v * 1e-9;
    let drive = rec.drive.values();
    let defl = &rec.deflection_v;
    if end <= contact + MIN_WINDOW {
        return Err(FitError::TooShort(end.saturating_sub(contact)));
    }
    let (h, source): (Vec<f64>, &'static str) = if let Some(r) = &rec.reference_deflection_v {
        (
            (contact..end).map(|i| c_m * (r[i] - defl[i])).collect(),
            "reference",
        )
    } else {
        let (z, src) = match (&rec.measured_height_nm, rec.drive_nm()) {
            (Some(m), _) if m.iter().all(|v| v.is_finite()) => (m.clone(), "measured_height"),
            (_, Some(d)) => (d, "drive"),
            _ => return Err(FitError::NoIndentation),
        };
        let z0 = z[contact];
        // A searched contact sits on the slow rise out of the noise: the lever deflection
        // reached there is not indentation.
        let d0 = if searched {
            defl[contact] - bl.at(drive[contact])
        } else {
            0.0
        };
        (
            (contact..end)
                .map(|i| (z[i] - z0) * 1e-9 - c_m * (defl[i] - bl.at(drive[i]) - d0))
                .collect(),
            src,
        )
    };
    let contact_model = rec.meta.contact();
    let force_n = force[contact..end].to_vec();
    let u = force_n
        .iter()
        .map(|&f| contact_model.u_from_force(f.max(0.0)))
        .collect();
    let y = h
        .iter()
        .map(|&x| contact_model.y_from_indentation(x))
        .collect();
    Ok(Prepared {
        u,
        y,
        fs_hz: rec.sample_rate_hz,
        contact_index: contact,
        contact_walkback_index: contact,
        end_index: end,
        baseline_v: bl.at(drive[contact]),
        baseline_noise_v: bl.noise,
        baseline_level_sigma_v: bl.sigma_at(drive[contact]),
        baseline_tilt_v_per_nm: match &rec.drive {
            crate::recording::Drive::Nanometres(_) => bl.b,
            crate::recording::Drive::Volts(_) => rec
                .meta
                .piezo
                // A negative gain (an actuator extending on negative voltage) keeps its sign.
                .filter(|p| p.gain_nm_per_v != 0.0)
                .map_or(0.0, |p| bl.b / p.gain_nm_per_v),
        },
        indentation_source: source,
        pinned: None,
        time_s: rec.time_s[contact..end].to_vec(),
        force_n,
        indentation_m: h,
        drive: drive[contact..end].to_vec(),
    })
}

/// End of the loading window (exclusive): contact is lost after the force maximum where the
/// force falls below `threshold`; the final unloading (where the contact shrinks and
/// Lee–Radok no longer holds) is the run before that in which the drive falls at a good
/// fraction of its speed there. A record that never loses contact ends in contact.
fn window_end(drive: &[f64], force: &[f64], contact: usize, imax: usize, threshold: f64) -> usize {
    let n = force.len();
    let Some(lost) = (imax..n).find(|&i| force[i] < threshold) else {
        return n;
    };
    const M: usize = 5;
    if lost < contact + 2 * M {
        return lost;
    }
    let rate = |i: usize| (drive[i - M] - drive[i]) / M as f64;
    let speed = rate(lost);
    if speed <= 0.0 {
        return lost;
    }
    let mut i = lost;
    while i > contact + M && rate(i) >= 0.3 * speed {
        i -= 1;
    }
    // The window (i − M, i] holds less than ~30 % of descent: the unloading starts near
    // i − 0.3·M.
    (i + 1).saturating_sub(2).max(contact + 1)
}

/// How many Prony terms to fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Terms {
    Fixed(usize),
    /// Try 1..=max and keep the lowest BIC.
    Auto {
        max: usize,
    },
}

/// One candidate order.
#[derive(Debug, Clone, PartialEq)]
pub struct OrderCandidate {
    pub terms: usize,
    /// Bayesian information criterion, lower is better (see [`RecordingFit::criterion`]);
    /// NaN when the fit failed.
    pub bic: f64,
    /// NRMSE of this order's model over the fitted samples (NaN when the fit failed).
    pub nrmse: f64,
    /// Why this order was not eligible (failed fit, or a retardation time outside what the
    /// record resolves); `None` when it was.
    pub rejected: Option<String>,
}

/// Which estimator was used, decided from the drive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FitMethod {
    /// Periodic drive: frequency-domain maximum likelihood on whole periods.
    FrequencyMl,
    /// Anything else: time-domain output error over the window.
    TimeOutputError,
}

impl FitMethod {
    /// Stable name (`--json`'s `method`).
    pub fn name(self) -> &'static str {
        match self {
            FitMethod::FrequencyMl => "frequency_domain_ml",
            FitMethod::TimeOutputError => "time_domain_output_error",
        }
    }
}

/// Residual whiteness: autocorrelations and the Ljung–Box portmanteau test.
#[derive(Debug, Clone, PartialEq)]
pub struct Whiteness {
    /// Residual autocorrelation at lags 1..=`lags`.
    pub autocorrelation: Vec<f64>,
    /// Ljung–Box `Q = N(N+2) Σ r_k²/(N−k)` over `lags` lags.
    pub ljung_box_q: f64,
    /// χ²(`lags`) 95 % quantile: Q above it rejects whiteness at 5 %.
    pub critical_95: f64,
    pub white: bool,
}

/// Lags of the whiteness test.
pub const WHITENESS_LAGS: usize = 20;
/// χ²(20) 95 % quantile.
const CHI2_20_95: f64 = 31.410_432_844_230_9;

/// Ljung–Box over [`WHITENESS_LAGS`] lags.
pub fn whiteness(r: &[f64]) -> Whiteness {
    whiteness_with_gaps(r, &[])
}

/// Ljung–Box over [`WHITENESS_LAGS`] lags of the samples of `r` not in `gaps` (indices, in
/// any order; those past the end are ignored): the mean and the variance are the kept samples', each lag's sum runs over the
/// pairs both of whose samples are kept, and `N` counts the kept samples. Without gaps this
/// is [`whiteness`] to the bit.
///
/// A residual that holds zeros where samples were left out (spikes off the refined
/// deflection) read as one series counts those zeros as samples: off the mean, and
/// correlated with their neighbours at every lag. Six of them in 15 009 samples (the spike
/// test's record) move Q in its second decimal only, but a regular pattern of them, a tenth
/// of the samples, rejects a white residual outright: Q 2079 against 21 read as gaps
/// (`a_residuals_gaps_are_not_read_as_samples`).
pub fn whiteness_with_gaps(r: &[f64], gaps: &[usize]) -> Whiteness {
    let n_all = r.len();
    let mut kept = vec![true; n_all];
    for &k in gaps.iter().filter(|&&k| k < n_all) {
        kept[k] = false;
    }
    let n = kept.iter().filter(|&&k| k).count();
    let kept_values = || (r.iter().zip(&kept)).filter_map(|(v, &k)| k.then_some(*v));
    let m = kept_values().sum::<f64>() / n.max(1) as f64;
    let c0: f64 = kept_values().map(|v| (v - m).powi(2)).sum();
    let lags = WHITENESS_LAGS.min(n.saturating_sub(1));
    let ac: Vec<f64> = (1..=lags)
        .map(|l| {
            (l..n_all)
                .filter(|&t| kept[t] && kept[t - l])
                .map(|t| (r[t] - m) * (r[t - l] - m))
                .sum::<f64>()
                / c0.max(f64::MIN_POSITIVE)
        })
        .collect();
    let nf = n as f64;
    let q = nf
        * (nf + 2.0)
        * ac.iter()
            .enumerate()
            .map(|(i, rk)| rk * rk / (nf - (i + 1) as f64))
            .sum::<f64>();
    Whiteness {
        autocorrelation: ac,
        ljung_box_q: q,
        critical_95: CHI2_20_95,
        white: q <= CHI2_20_95,
    }
}

/// A fitted recording.
#[derive(Debug, Clone)]
pub struct RecordingFit {
    pub prepared: Prepared,
    pub method: FitMethod,
    /// The whole periods found in the window's drive (indices into the window), if any.
    pub periodic: Option<PeriodicRun>,
    /// Samples of the window the estimator used (whole periods, or all of it).
    pub fitted: std::ops::Range<usize>,
    pub estimate: Estimate,
    /// The model's output over the whole window, from the steady state at contact.
    pub yhat: Vec<f64>,
    /// Normalised RMS error of the fit over the fitted samples, `‖y − ŷ‖/‖y − ȳ‖`.
    pub nrmse: f64,
    /// Lag-1 autocorrelation of the residuals (≈ 0 for white residuals).
    pub residual_lag1: f64,
    pub whiteness: Whiteness,
    /// The order-selection criterion, as printed.
    pub criterion: &'static str,
    pub candidates: Vec<OrderCandidate>,
    /// The band the record resolves, Hz: from 1/(fitted duration) to the highest excited line
    /// (periodic) or fs/10 (otherwise).
    pub band_hz: [f64; 2],
    /// Plain-language remarks about the analysis (not the estimator's own warnings).
    pub notes: Vec<String>,
    /// The final refinement on the deflection with the drive as input ([`fn@refine`]), when it
    /// made the estimate.
    pub refinement: Option<Refinement>,
}

/// What the deflection refinement ([`fn@refine`]) found besides the Prony parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Refinement {
    /// Fitted contact position, nm of (calibrated) drive, and its standard error.
    pub contact_nm: f64,
    pub contact_sigma_nm: f64,
    /// Drive nm per nm of actuator motion (1, or the hard reference's slope).
    pub drive_scale: f64,
    /// Deflection samples fitted (the window and a few free samples before it).
    pub samples: usize,
    /// RMS deflection residual and detector noise (free lever), nm.
    pub residual_rms_nm: f64,
    pub noise_nm: f64,
    pub iterations: usize,
}

/// Criterion of the time-domain path.
pub const BIC_TIME: &str = "BIC = N·ln(RSS/N) + p·ln N (N samples, p = 2n+1 parameters)";
/// Criterion of the frequency-domain path.
pub const BIC_FREQUENCY: &str =
    "BIC = V + p·ln(2L) (V the noise-weighted ML cost, L excited lines, p = 2n+1 parameters)";

/// `ŷ = J0·u − Σ Ji·HP_τi(u)` with the first-order hold, from the steady state at `u[0]`.
pub fn simulate_foh(model: &PronySeries, u: &[f64], fs_hz: f64) -> Vec<f64> {
    let mut y: Vec<f64> = u.iter().map(|x| model.j0_per_pa * x).collect();
    for t in &model.terms {
        for (yh, x) in y.iter_mut().zip(foh_highpass(u, t.tau_s, fs_hz)) {
            *yh -= t.j_per_pa * x;
        }
    }
    y
}

fn nrmse(y: &[f64], yhat: &[f64]) -> f64 {
    let m = y.iter().sum::<f64>() / y.len() as f64;
    let syy: f64 = y.iter().map(|v| (v - m).powi(2)).sum();
    let rss: f64 = y.iter().zip(yhat).map(|(a, b)| (a - b).powi(2)).sum();
    (rss / syy.max(f64::MIN_POSITIVE)).sqrt()
}

/// `∂ŷ/∂ln θ` over the window (canonical order), by central differences.
fn log_jacobian(model: &PronySeries, u: &[f64], fs_hz: f64) -> DMatrix<f64> {
    let p = model.to_vec();
    let mut jac = DMatrix::zeros(u.len(), p.len());
    const H: f64 = 1e-6;
    for i in 0..p.len() {
        let at = |s: f64| {
            let mut q = p.clone();
            q[i] *= s.exp();
            simulate_foh(&PronySeries::from_vec(&q), u, fs_hz)
        };
        let (up, dn) = (at(H), at(-H));
        for t in 0..u.len() {
            jac[(t, i)] = (up[t] - dn[t]) / (2.0 * H);
        }
    }
    jac
}

/// Shift of the log-parameters of a time-domain fit that one standard error of the baseline
/// level causes. A baseline off by `ε` V lowers the force by `K·C·ε` over the whole window
/// (and raises a drive-derived indentation by `C·ε`): in a creep or relaxation record that
/// offset is all but collinear with J0·u, so the fit cannot find it, only carry it — the
/// fitted parameters move by `(JᵀJ)⁻¹Jᵀ·Δr`, which joins the covariance as a systematic term.
fn baseline_sensitivity(rec: &Recording, p: &Prepared, model: &PronySeries) -> Option<Vec<f64>> {
    let sigma = p.baseline_level_sigma_v;
    if !(sigma.is_finite() && sigma > 0.0) {
        return None;
    }
    let k = rec.meta.cantilever.spring_constant_n_per_m;
    let c_m = rec.meta.cantilever.deflection_sensitivity_nm_per_v * 1e-9;
    let contact = rec.meta.contact();
    let du = contact.u_from_force(k * c_m * sigma);
    let dh = if p.indentation_source == "reference" {
        0.0
    } else {
        c_m * sigma
    };
    // Δr = Δy − Δŷ = (y(h + dh) − y(h)) + J0·du (ŷ is linear and starts at rest).
    let dr = DVector::from_iterator(
        p.u.len(),
        p.indentation_m.iter().map(|&h| {
            contact.y_from_indentation((h + dh).max(0.0)) - contact.y_from_indentation(h.max(0.0))
                + model.j0_per_pa * du
        }),
    );
    let jac = log_jacobian(model, &p.u, p.fs_hz);
    let jtj = jac.transpose() * &jac;
    let delta = jtj.cholesky()?.solve(&(jac.transpose() * dr));
    Some(delta.iter().copied().collect())
}

/// `model` with terms added up to `n`, each faster than the last (a fifth of its τ, a tenth
/// of the instantaneous compliance left): a start for order `n` where the τ grid has no
/// physical one. `None` unless `model` has fewer than `n` terms and is physical.
fn one_more_term(model: &PronySeries, n: usize) -> Option<PronySeries> {
    if model.order() >= n || !model.is_physical() {
        return None;
    }
    let mut m = model.clone();
    while m.order() < n {
        let fastest = m
            .terms
            .iter()
            .map(|t| t.tau_s)
            .fold(f64::INFINITY, f64::min);
        let tau = if fastest.is_finite() {
            fastest / 5.0
        } else {
            1e-2
        };
        let mut terms = m.terms.clone();
        terms.push(crate::prony::PronyTerm {
            j_per_pa: 0.1 * m.instantaneous_compliance(),
            tau_s: tau,
        });
        m = PronySeries::new(m.j0_per_pa, terms);
    }
    Some(m)
}

/// One order's fit: its model, its BIC, and its estimate with intervals (or why none).
struct Fitted {
    model: PronySeries,
    bic: f64,
    estimate: Result<Estimate, EstimateError>,
    refined: Option<Refined>,
}

type OrderFit = Result<Fitted, EstimateError>;

/// What one pass of order selection found: every candidate, the chosen order's estimate (and
/// its refinement), and the last failure.
type Selection = (
    Vec<OrderCandidate>,
    Option<(Estimate, Option<Refined>)>,
    Option<EstimateError>,
);

impl Fitted {
    /// One order's fit from an estimator's answer, with `bic` of the optimum's cost. An order
    /// too many still has a cost: it loses on BIC, not by failing.
    fn from_estimate(res: Result<Estimate, EstimateError>, bic: impl Fn(f64) -> f64) -> OrderFit {
        match res {
            Ok(est) => Ok(Self {
                model: est.model.clone(),
                bic: bic(est.diagnostics.cost),
                estimate: Ok(est),
                refined: None,
            }),
            Err(e) => match &e {
                EstimateError::Unidentified { cost, model, .. } => Ok(Self {
                    model: model.clone(),
                    bic: bic(*cost),
                    estimate: Err(e.clone()),
                    refined: None,
                }),
                _ => Err(e),
            },
        }
    }
}

/// Criterion of the time-domain path with the deflection refinement.
pub const BIC_DEFLECTION: &str = "BIC = N·ln(RSS/N) + p·ln N (N deflection samples, p = 2n+2 \
                                  parameters: the Prony series and the contact position)";

/// Fits a recording (see the module documentation), refining on the deflection where the
/// drive allows it.
pub fn fit_recording(rec: &Recording, terms: Terms) -> Result<RecordingFit, FitError> {
    fit_recording_with(rec, terms, true, &Serial)
}

/// [`fit_recording`]; `refine_deflection: false` stops at the first estimate (the
/// output-error or frequency-domain fit of the linear pair). Independent fits are spread by
/// `fan` ([`prepare_with`]); the result does not depend on it.
pub fn fit_recording_with(
    rec: &Recording,
    terms: Terms,
    refine_deflection: bool,
    fan: &dyn Fan,
) -> Result<RecordingFit, FitError> {
    // An optional channel's missing samples (the indentation's reference, say) filled from
    // their neighbours, a single-sample glitch of the deflection mended, a base that falls
    // toward the sample read reversed (`recording::mended`); the notes say what was done.
    let (mended, m) = crate::recording::mended(rec);
    let prepared = prepare_with(&mended, fan)?;
    let mut fit = fit_prepared(&mended, prepared, terms, refine_deflection)?;
    let mended_note = (!m.glitches.is_empty()).then(|| {
        let d = crate::recording::glitch::describe(&m.glitches, rec.sample_rate_hz);
        format!("{d}: each replaced by the mean of its neighbours")
    });
    fit.notes.splice(
        0..0,
        (m.gaps.channels.iter().map(|g| g.to_string()))
            .chain(mended_note)
            .chain(m.reversals.iter().map(|r| r.to_string())),
    );
    Ok(fit)
}

/// [`fit_recording_with`] from the pair [`prepare_with`] made of `rec`, whose gaps are
/// already filled. For a caller that needs the pair even where the fit fails: the
/// diagnosis falls back on its contact point, and preparing twice cost it a second round
/// of the pair's fits.
pub(crate) fn fit_prepared(
    rec: &Recording,
    mut prepared: Prepared,
    terms: Terms,
    refine_deflection: bool,
) -> Result<RecordingFit, FitError> {
    let (u, y, fs) = (&prepared.u, &prepared.y, prepared.fs_hz);
    let len = u.len();
    let orders: Vec<usize> = match terms {
        Terms::Fixed(n) => vec![n],
        Terms::Auto { max } => (1..=max.max(1)).collect(),
    };
    let sampling = Sampling::FirstOrderHold { fs_hz: fs };
    let mut notes: Vec<String> = Vec::new();
    if let Some(pinned) = &prepared.pinned {
        let end_s = prepared.end_index as f64 / fs;
        notes.push(format!(
            "{pinned}; the in-contact window ends at its first pinned sample ({end_s:.4} s), and the contact after it is not fitted"
        ));
    }
    let periodic = detect_periodic(&prepared.drive);

    // One pass of order selection over `range` with `fit_order`.
    let select = |range: std::ops::Range<usize>,
                  fit_order: &dyn Fn(usize, Option<&PronySeries>) -> OrderFit|
     -> Selection {
        let span_s = range.len() as f64 / fs;
        let mut candidates = Vec::new();
        type Slot = Option<(f64, (Estimate, Option<Refined>))>;
        let mut best: Slot = None;
        let mut fallback: Slot = None;
        let mut last_err = None;
        // The previous order's optimum: with one more term, a start for this order.
        let mut prev: Option<PronySeries> = None;
        for &n in &orders {
            let start = prev.as_ref().and_then(|p| one_more_term(p, n));
            match fit_order(n, start.as_ref()) {
                Ok(Fitted {
                    model,
                    bic,
                    estimate,
                    refined,
                }) => {
                    prev = Some(model.clone());
                    let yhat = simulate_foh(&model, u, fs);
                    let e = nrmse(&y[range.clone()], &yhat[range.clone()]);
                    let out_of_range = model
                        .terms
                        .iter()
                        .find(|t| t.tau_s > span_s || t.tau_s < 0.5 / fs);
                    let rejected = if !model.is_physical() {
                        Some("not physical: negative instantaneous compliance".to_string())
                    } else if let Some(t) = out_of_range {
                        Some(format!(
                            "tau = {:.4e} s is outside what the record resolves ({:.1e} to {:.3e} s)",
                            t.tau_s,
                            0.5 / fs,
                            span_s
                        ))
                    } else {
                        estimate
                            .as_ref()
                            .err()
                            .map(|e| format!("not identified (no intervals): {e}"))
                    };
                    candidates.push(OrderCandidate {
                        terms: n,
                        bic,
                        nrmse: e,
                        rejected: rejected.clone(),
                    });
                    let est = match estimate {
                        Ok(est) => est,
                        Err(e) => {
                            // No intervals: not eligible, and the reason if none is.
                            last_err = Some(e);
                            continue;
                        }
                    };
                    let slot = if rejected.is_none() {
                        &mut best
                    } else {
                        &mut fallback
                    };
                    if slot.as_ref().is_none_or(|(b, _)| bic < *b) {
                        *slot = Some((bic, (est, refined)));
                    }
                }
                Err(e) => {
                    candidates.push(OrderCandidate {
                        terms: n,
                        bic: f64::NAN,
                        nrmse: f64::NAN,
                        rejected: Some(format!("fit failed: {e}")),
                    });
                    last_err = Some(e);
                }
            }
        }
        let chosen = best.or(fallback).map(|b| b.1);
        (candidates, chosen, last_err)
    };

    let time_opts = |n: usize, prior: Option<&PronySeries>| {
        let mut opts = TimeFitOptions::new(n);
        opts.sampling = sampling;
        opts.extra_start = prior.cloned();
        opts
    };
    let scale2 = y.iter().map(|v| v * v).sum::<f64>() / len as f64;
    let time_domain = |n: usize, prior: Option<&PronySeries>| -> OrderFit {
        let nf = len as f64;
        Fitted::from_estimate(fit_time_domain(u, y, fs, &time_opts(n, prior)), |cost| {
            let rss = cost * scale2;
            nf * (rss / nf).max(1e-300).ln() + (2 * n + 1) as f64 * nf.ln()
        })
    };
    // The deflection refinement, where the drive gives the actuator's position.
    let mut problem = if refine_deflection {
        match Problem::new(rec, &prepared) {
            Ok(p) => Some(p),
            Err(why) => {
                notes.push(format!("no refinement on the deflection: {why}"));
                None
            }
        }
    } else {
        None
    };
    // One order refined from `start`, intervals included.
    let refined = |prob: &Problem, start: &PronySeries| -> OrderFit {
        let r = refine(prob, start)?;
        Ok(Fitted {
            model: r.model.clone(),
            bic: r.bic(),
            estimate: r.estimate.clone(),
            refined: Some(r),
        })
    };

    // One order of the time-domain path: refined from its first estimate; where that fails
    // (an order too many), from the first estimate's own starts.
    let refined_order = |prob: &Problem, n: usize, prior: Option<&PronySeries>| -> OrderFit {
        let first = time_domain(n, prior);
        match first
            .as_ref()
            .map_err(Clone::clone)
            .map(|f| refined(prob, &f.model))
        {
            Ok(Ok(f)) => Ok(f),
            Ok(Err(e)) | Err(e) => {
                let first = first.err().unwrap_or(e);
                let opts = TimeFitOptions {
                    starts: 2,
                    ..time_opts(n, prior)
                };
                let starts = time_domain_starts(u, y, fs, &opts).unwrap_or_default();
                starts
                    .iter()
                    .map(|s| {
                        let v: Vec<f64> = s.iter().map(|x| x.exp()).collect();
                        refined(prob, &PronySeries::from_vec(&v))
                    })
                    .filter_map(Result::ok)
                    .min_by(|a, b| a.bic.total_cmp(&b.bic))
                    .ok_or(first)
            }
        }
    };

    let mut outcome = None;
    if let Some(run) = periodic {
        let p = run.period_samples;
        // The first period settles the material when there are enough of them; a second pass
        // drops more if the slowest fitted term has not decayed (5τ) before the first kept one.
        let mut skip = usize::from(run.periods >= 3);
        for pass in 0..2 {
            let kept = run.periods - skip;
            let range = run.start + skip * p..run.start + (skip + kept) * p;
            let up = remove_linear_drift(&u[range.clone()], kept);
            let yp = remove_linear_drift(&y[range.clone()], kept);
            let spectra = match periodic_spectra(
                &up,
                &yp,
                fs,
                kept,
                &LineSelection::Auto { relative: 1e-3 },
                16,
            ) {
                Ok(s) => s,
                Err(e) => {
                    notes.push(format!(
                        "periodic drive, but its spectrum could not be used ({e}): time-domain fit"
                    ));
                    break;
                }
            };
            let lines = spectra.lines.len() as f64;
            let freq = |n: usize, prior: Option<&PronySeries>| -> OrderFit {
                let mut opts = FrequencyFitOptions::new(n, fs, kept);
                opts.sampling = sampling;
                opts.extra_start = prior.cloned();
                let price = (2 * n + 1) as f64 * (2.0 * lines).ln();
                Fitted::from_estimate(fit_spectra(&spectra, &opts), |cost| cost + price)
            };
            let (candidates, chosen, err) = select(range.clone(), &freq);
            let Some((est, _)) = chosen else {
                notes.push(format!(
                    "periodic drive, but no order could be fitted in the frequency domain ({}): time-domain fit",
                    err.map_or("no start".into(), |e| e.to_string())
                ));
                break;
            };
            let slowest = est.model.terms.first().map_or(0.0, |t| t.tau_s);
            let settled_at = (5.0 * slowest * fs).ceil() as usize;
            let need = settled_at.saturating_sub(run.start).div_ceil(p);
            let f_hi = spectra.lines.iter().map(|l| l.freq_hz).fold(0.0, f64::max);
            if pass == 0 && need > skip && run.periods >= need + 2 {
                notes.push(format!(
                    "the first {need} period(s) fall within 5·tau1 of contact: dropped and refitted"
                ));
                skip = need;
                continue;
            }
            if need > skip {
                notes.push(format!(
                    "the first kept period starts {:.3} s after contact, less than 5·tau1 = {:.3} s: \
                     the material may not have settled into its periodic state",
                    (run.start + skip * p) as f64 / fs,
                    5.0 * slowest
                ));
            }
            // Where the indentation comes from the drive, the contact position is a constant
            // error of the indentation that no line sees: the refinement fits it.
            let mut est = est;
            let mut refined_fit = None;
            let mut range = range;
            if let Some(prob) = problem
                .as_ref()
                .filter(|_| prepared.indentation_source == "drive")
            {
                match refined(prob, &est.model) {
                    Ok(Fitted {
                        estimate: Ok(e),
                        refined: r,
                        ..
                    }) => {
                        est = e;
                        refined_fit = r;
                        range = 0..len;
                    }
                    Ok(Fitted { estimate: Err(e), .. }) | Err(e) => notes.push(format!(
                        "the refinement on the deflection failed ({e}): the frequency-domain estimate stands"
                    )),
                }
            }
            outcome = Some((
                FitMethod::FrequencyMl,
                range,
                candidates,
                (est, refined_fit),
                BIC_FREQUENCY,
                [fs / (kept * p) as f64, f_hi.min(fs / 2.0)],
            ));
            break;
        }
    }
    let (method, fitted, mut candidates, (mut estimate, mut refined_fit), criterion, band_hz) =
        match outcome {
            Some(o) => o,
            None => {
                let (candidates, chosen, err) = match problem.as_ref() {
                    Some(prob) => select(0..len, &|n, prior| refined_order(prob, n, prior)),
                    None => select(0..len, &time_domain),
                };
                let Some(est) = chosen else {
                    return Err(FitError::Estimate(err.unwrap_or(EstimateError::NoStart)));
                };
                (
                    FitMethod::TimeOutputError,
                    0..len,
                    candidates,
                    est,
                    if problem.is_some() {
                        BIC_DEFLECTION
                    } else {
                        BIC_TIME
                    },
                    [fs / len as f64, fs / 10.0],
                )
            }
        };
    if candidates
        .iter()
        .find(|c| c.terms == estimate.model.order())
        .is_some_and(|c| c.rejected.is_some())
    {
        notes.push(
            "every order has a retardation time outside what the record resolves: the slowest \
             term is not identified; read J(t) at the end of the window, not J0"
                .into(),
        );
    }
    if method == FitMethod::TimeOutputError && refined_fit.is_none() {
        if let Some(delta) = baseline_sensitivity(rec, &prepared, &estimate.model) {
            estimate = estimate.with_systematic(&delta, "the force baseline (free-lever level)");
        }
    }
    // Spikes off the refined deflection (a converter's or a transfer's error of one to three
    // samples, with the residual about them at the floor) are no force: refined again
    // without them, from the same optimum. Left in, six of 16 σ in a clean twin record
    // moved its two retardation times by 0.3 % and 0.4 % and its residual from 0.164 to
    // 0.172 nm rms with no word of why.
    if let (Some(rf), Some(prob)) = (&refined_fit, problem.as_mut()) {
        let spiked = spikes::isolated(&rf.residuals_nm, prob.sigma_nm, &[], &prob.z_nm);
        if !spiked.is_empty() {
            let said = spikes::describe(
                &spiked,
                &rf.residuals_nm,
                prob.sigma_nm,
                fs,
                prob.start,
                "the refined deflection",
            );
            prob.left_out = spiked;
            // Where the order was chosen by the refinements' BIC (the time-domain path, more
            // than one order tried), every order is refined again without the spikes and the
            // order chosen again: with them in, each order's BIC carried their squares (six
            // of 16 σ added 664 to 1444, `the_order_is_chosen_without_the_spikes`). A
            // periodic drive's order is chosen on its spectra, and is kept.
            let reselected = (method == FitMethod::TimeOutputError && orders.len() > 1)
                .then(|| select(0..len, &|n, prior| refined_order(prob, n, prior)))
                .and_then(|(c, chosen, _)| match chosen {
                    Some((e, Some(r))) => Some((c, e, r)),
                    _ => None,
                });
            // The estimate of the refit, or why it has none (an order the data no longer
            // separate): then the fit with the spikes stands.
            let again = match reselected {
                Some((c, e, r)) => {
                    candidates = c;
                    Ok((e, r, " and the order chosen again"))
                }
                None => {
                    refine(prob, &estimate.model).and_then(|a| Ok((a.estimate.clone()?, a, "")))
                }
            };
            match again {
                Ok((e, again, order)) => {
                    notes.push(format!(
                        "{said}; left out of the refinement, which was run again without them{order}"
                    ));
                    estimate = e;
                    refined_fit = Some(again);
                }
                Err(why) => {
                    prob.left_out.clear();
                    notes.push(format!(
                        "{said}; refined again without them the estimate has no intervals ({why}): \
                         the fit with them stands"
                    ));
                }
            }
        }
    }
    let mut refinement = None;
    let mut r: Vec<f64> = Vec::new();
    if let (Some(rf), Some(prob)) = (&refined_fit, &problem) {
        // The indentation of a drive-derived window, from the fitted contact position.
        if prepared.indentation_source == "drive" {
            let contact = rec.meta.contact();
            let (c, s) = (prepared.contact_index, prob.start);
            for (j, h) in prepared.indentation_m.iter_mut().enumerate() {
                let k = c + j - s;
                *h = (prob.z_nm[k] - rf.contact_nm - prob.d_nm[k]) * 1e-9;
            }
            prepared.y = prepared
                .indentation_m
                .iter()
                .map(|&h| contact.y_from_indentation(h))
                .collect();
        }
        let rss: f64 = rf.residuals_nm.iter().map(|v| v * v).sum();
        refinement = Some(Refinement {
            contact_nm: rf.contact_nm,
            contact_sigma_nm: rf.contact_sigma_nm,
            drive_scale: prob.drive_scale,
            samples: rf.samples,
            residual_rms_nm: (rss / rf.samples as f64).sqrt(),
            noise_nm: prob.sigma_nm,
            iterations: rf.iterations,
        });
        notes.push(format!(
            "refined on the deflection with the drive as input (errors in variables): contact \
             at {:.3} ± {:.3} nm of drive, deflection residual {:.4} nm rms against {:.4} nm of \
             detector noise",
            rf.contact_nm,
            rf.contact_sigma_nm,
            (rss / rf.samples as f64).sqrt(),
            prob.sigma_nm
        ));
        r = rf.residuals_nm.clone();
    }
    let (u, y) = (&prepared.u, &prepared.y);
    let yhat = simulate_foh(&estimate.model, u, fs);
    if r.is_empty() {
        r = fitted.clone().map(|i| y[i] - yhat[i]).collect();
    }
    // A refinement's residual holds zeros where it left samples out (spikes): they are no
    // samples of it. (Only the spike pass above sets them, and only where `r` is that
    // residual. The lag-1 product below has no mean to take off: a zero adds nothing to
    // either of its sums.)
    let gaps = problem.as_ref().map_or(&[][..], |prob| &prob.left_out[..]);
    let rss: f64 = r.iter().map(|v| v * v).sum();
    let lag1 = r.windows(2).map(|w| w[0] * w[1]).sum::<f64>() / rss.max(1e-300);
    Ok(RecordingFit {
        nrmse: nrmse(&y[fitted.clone()], &yhat[fitted.clone()]),
        residual_lag1: lag1,
        whiteness: whiteness_with_gaps(&r, gaps),
        refinement,
        method,
        periodic,
        fitted,
        prepared,
        estimate,
        yhat,
        criterion,
        candidates,
        band_hz,
        notes,
    })
}

impl RecordingFit {
    /// The estimator's own method tag.
    pub fn estimator(&self) -> Method {
        self.estimate.method
    }

    /// Duration of the fitted samples, s.
    pub fn fitted_duration_s(&self) -> f64 {
        self.fitted.len() as f64 / self.prepared.fs_hz
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::corpus::{nominal_twin, protocol_drive, saturated, simulate};
    use crate::fan::tests::Reversed;

    /// A contact that rises slowly out of the noise (a corpus twin at three times its
    /// detector noise) is searched for by fitting each trial point, on the caller's fan: the
    /// point chosen is not the noise band's last sample, and the window is the same, to the
    /// bit, when the fan runs the trials last to first.
    #[test]
    fn the_contact_search_is_the_same_on_any_fan() {
        let fs = 5000.0;
        let mut twin = nominal_twin(1);
        twin.detector.white_noise_v *= 3.0;
        let rec = simulate(&twin, &protocol_drive(fs).0, fs, None);
        let a = prepare_with(&rec, &Serial).unwrap();
        let b = prepare_with(&rec, &Reversed).unwrap();
        assert_ne!(a.contact_index, a.contact_walkback_index, "no search ran");
        assert_eq!(a.contact_index, b.contact_index);
        let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.u), bits(&b.u));
        assert_eq!(bits(&a.y), bits(&b.y));
    }

    /// A detector that saturates (the twin's `range_v`, at 85 % of the clean record's peak)
    /// pins the deflection while the force goes on rising. The window ends at the first
    /// pinned sample, the notes say so, and J0's interval holds the truth. Fitted through
    /// the flat top, the same record gave J0's interval as [6.55, 6.60] µPa⁻¹ against a
    /// truth of 6.13.
    #[test]
    fn a_window_ends_where_the_deflection_sits_pinned() {
        let twin = nominal_twin(1);
        let (_, rec, level) = saturated(&twin, 4000.0, 0.85);
        let first_pinned = rec.deflection_v.iter().position(|&v| v == level).unwrap();

        let fit = fit_recording(&rec, Terms::Fixed(2)).unwrap();
        assert_eq!(fit.prepared.end_index, first_pinned);
        assert!(
            fit.notes[0].contains("pinned at its largest value"),
            "{:?}",
            fit.notes
        );
        let truth = twin.sample.material.j0_per_pa;
        let [lo, hi] = fit.estimate.ci95[0];
        assert!(
            lo < truth && truth < hi,
            "J0 [{lo:e}, {hi:e}] against {truth:e} 1/Pa"
        );

        // Pinned almost at once, nothing is left to fit: the error says why.
        let (_, rec, _) = saturated(&twin, 4000.0, 0.02);
        let e = fit_recording(&rec, Terms::Fixed(2)).unwrap_err();
        assert!(matches!(e, FitError::PinnedAtContact { .. }), "{e}");
    }

    /// A fit of a recording whose optional channel dropped a sample says so first in its
    /// notes, whatever notes the fit itself adds after it.
    #[test]
    fn a_filled_gap_is_the_first_note_of_the_fit() {
        let fs = 5000.0;
        let mut rec = simulate(&nominal_twin(1), &protocol_drive(fs).0, fs, None);
        // A height sensor that reads the commanded position, and dropped one sample.
        let mut height = rec
            .drive_nm()
            .expect("the corpus twin declares its piezo gain");
        height[1234] = f64::NAN;
        rec.measured_height_nm = Some(height);
        let fit = fit_recording(&rec, Terms::Fixed(2)).unwrap();
        assert!(
            fit.notes[0].starts_with(crate::recording::gaps::HEIGHT),
            "{:?}",
            fit.notes
        );
        assert!(fit.notes[0].contains("1 of"), "{}", fit.notes[0]);
        assert!(fit.notes.len() > 1, "the fit's own notes are gone");
    }

    /// `clean` with six single-sample spikes of ±16 σ (`sigma`, V), one every 1000 samples
    /// from sample 5000, alternating in sign: what the spike tests leave out.
    fn with_six_spikes(clean: &Recording, sigma: f64) -> Recording {
        let mut rec = clean.clone();
        for (i, k) in (5000..=10_000).step_by(1000).enumerate() {
            rec.deflection_v[k] += if i % 2 == 0 { 16.0 } else { -16.0 } * sigma;
        }
        rec
    }

    /// With the order chosen by BIC over the refinements (`--terms auto`), the spikes left
    /// out are left out of every order's refinement and the order is chosen again: each
    /// order's BIC is the clean record's to within what six fewer samples move it (16 to 22
    /// here), where with the spikes in it carried their squares (664 to 1444 above it).
    #[test]
    fn the_order_is_chosen_without_the_spikes() {
        use crate::diagnose::corpus::FS_HZ;
        let twin = nominal_twin(41);
        // The protocol's multisine, its swing growing by half over the record, so that no
        // two periods repeat: a time-domain fit, its order chosen over the refinements.
        let (mut drive_v, _) = protocol_drive(FS_HZ);
        let (n, v0) = (drive_v.len() as f64, drive_v[(1.0 * FS_HZ) as usize]);
        for (k, v) in drive_v.iter_mut().enumerate() {
            *v = v0 + (*v - v0) * (1.0 + 0.5 * k as f64 / n);
        }
        let clean = simulate(&twin, &drive_v, FS_HZ, None);
        let rec = with_six_spikes(&clean, twin.detector.white_noise_v);
        let auto = Terms::Auto { max: 3 };
        let fit = fit_recording(&rec, auto).unwrap();
        let whole = fit_recording(&clean, auto).unwrap();
        assert!(
            fit.notes[0].contains("6 samples of spikes")
                && fit.notes[0].contains("the order chosen again"),
            "{:?}",
            fit.notes
        );
        assert_eq!(fit.method, FitMethod::TimeOutputError);
        assert_eq!(fit.estimate.model.order(), whole.estimate.model.order());
        assert_eq!(fit.candidates.len(), 3);
        for (a, b) in fit.candidates.iter().zip(&whole.candidates) {
            assert_eq!(a.terms, b.terms);
            if a.bic.is_finite() || b.bic.is_finite() {
                assert!((a.bic - b.bic).abs() < 100.0, "{a:?} against {b:?}");
            }
        }
    }

    /// A white residual about a mean of 3 σ with every tenth sample left out and held as a
    /// zero (as a refinement holds its spikes): read as samples, the zeros make a period of
    /// ten that rejects whiteness outright; read as gaps, the test sees the white samples,
    /// whatever the gaps hold. With and without gaps, Q is the textbook value on an
    /// alternating series.
    #[test]
    fn a_residuals_gaps_are_not_read_as_samples() {
        use rand::{rngs::StdRng, SeedableRng};
        use rand_distr::{Distribution, StandardNormal};
        let mut rng = StdRng::seed_from_u64(9);
        let white: Vec<f64> = (0..4000)
            .map(|_| {
                let z: f64 = StandardNormal.sample(&mut rng);
                3.0 + z
            })
            .collect();
        let gaps: Vec<usize> = (5..4000).step_by(10).collect();
        let holding = |v: f64| {
            let mut r = white.clone();
            gaps.iter().for_each(|&k| r[k] = v);
            r
        };
        let zeros = holding(0.0);
        let as_samples = whiteness(&zeros);
        assert!(
            as_samples.ljung_box_q > 1000.0,
            "{}",
            as_samples.ljung_box_q
        );
        let as_gaps = whiteness_with_gaps(&zeros, &gaps);
        assert!(as_gaps.white, "{}", as_gaps.ljung_box_q);
        let elsewhere = whiteness_with_gaps(&holding(-1e6), &gaps);
        assert_eq!(as_gaps, elsewhere);
        // Gaps past the end are no samples of it, and take none away.
        assert_eq!(
            whiteness_with_gaps(&white, &[4000, 5000]),
            whiteness(&white)
        );
        // Without gaps, the textbook statistic: ±1 alternating over N = 100 samples has
        // r_k = (−1)^k (N − k)/N, so Q = (N + 2)/N · Σ_{k=1}^{20} (N − k) = 1.02 · 1790.
        let alternating: Vec<f64> = (0..100)
            .map(|k| if k % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let q = whiteness(&alternating).ljung_box_q;
        assert!((q - 1825.8).abs() < 1e-9, "{q}");
        // With every sample from the 50th on a gap, the first 50 alone: 52/50 · Σ (50 − k).
        let half: Vec<usize> = (50..100).collect();
        let q = whiteness_with_gaps(&alternating, &half).ljung_box_q;
        assert!((q - 52.0 / 50.0 * 790.0).abs() < 1e-9, "{q}");
    }

    /// Six single-sample spikes of 16 σ in the excitation of a clean twin record (a fast
    /// multisine keeps them under the glitch rule's reach): the refinement leaves them out,
    /// runs again, and says where they were; the estimate and the residual's size are the
    /// clean record's, and the residual stays white.
    #[test]
    fn spikes_off_the_refined_deflection_are_left_out_and_said_so() {
        use crate::diagnose::corpus::FS_HZ;
        let twin = nominal_twin(41);
        let (drive_v, _) = protocol_drive(FS_HZ);
        let clean = simulate(&twin, &drive_v, FS_HZ, None);
        let rec = with_six_spikes(&clean, twin.detector.white_noise_v);
        assert!(crate::recording::glitch::find_glitches(&rec.deflection_v).is_empty());
        let fit = fit_recording(&rec, Terms::Fixed(2)).unwrap();
        let whole = fit_recording(&clean, Terms::Fixed(2)).unwrap();
        let note = &fit.notes[0];
        assert!(
            note.contains("6 samples of spikes")
                && note.contains("t = 1.2500 s")
                && note.contains("run again without them"),
            "{:?}",
            fit.notes
        );
        let (r, r_whole) = (fit.refinement.unwrap(), whole.refinement.unwrap());
        assert_eq!(r.samples + 6, r_whole.samples);
        // Left in, they moved tau2 by 3.7e-3 and J1 by 2.0e-3 of the clean record's value
        // and the residual to 0.1725 nm rms against 0.1644; left out, by 1.2e-4 at most.
        let (a, b) = (fit.estimate.model.to_vec(), whole.estimate.model.to_vec());
        for (i, (x, y)) in a.iter().zip(&b).enumerate() {
            assert!(
                (x / y - 1.0).abs() < 3e-4,
                "parameter {i}: {x:e} against {y:e}"
            );
        }
        let rms = r.residual_rms_nm / r_whole.residual_rms_nm;
        assert!((rms - 1.0).abs() < 1e-3, "{rms}");
        assert!(fit.whiteness.white, "{}", fit.whiteness.ljung_box_q);
        // The clean record has none.
        assert!(!whole.notes.iter().any(|n| n.contains("spikes")));
    }
}
