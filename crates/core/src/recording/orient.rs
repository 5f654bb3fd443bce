//! Which way the base moves toward the sample. The format's drive is the displacement toward
//! the sample (`drive_nm`), or the voltage that the sidecar's gain turns into it (`drive_v`),
//! and its `measured_height_nm` is the actuator's position. An exporter may write a height
//! instead, which falls as the tip approaches; a sidecar may give the gain with the wrong
//! sign. The twin and the offline fitter both put the contact where the base has moved far
//! enough *up*, so such a record was read as nonsense without a word: a corpus record with
//! its `drive_nm` negated was named `thermal_drift` at 955 million χ² units with J0 at
//! 4·10⁻¹² Pa⁻¹, and the fit of another stopped at "no physical start value found"
//! (2026-11-30).
//!
//! [`toward_sample`] reads the direction from the record itself: the deflection peaks where
//! the tip presses hardest, so the base there lies toward the sample from where the record
//! began. A channel that lies the other way there is read with its sign reversed, and the
//! [`Reversal`] says so. A record whose deflection never rises is another fault, which
//! the contact search names.

use super::{Drive, Recording};
use crate::analysis::median;

/// A channel read with its sign reversed.
#[derive(Debug, Clone, PartialEq)]
pub struct Reversal {
    /// The column's name.
    pub column: &'static str,
    /// How far the base moved from the record's start to where the deflection peaks, in the
    /// column's unit as recorded (negative: away from where a displacement toward the
    /// sample would go).
    pub travel: f64,
    /// The column's unit.
    pub unit: &'static str,
    /// For `drive_v`, the sidecar's gain, nm/V.
    pub gain_nm_per_v: Option<f64>,
}

impl std::fmt::Display for Reversal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let way = if self.travel < 0.0 { "falls" } else { "rises" };
        write!(
            f,
            "{} {way} as the tip presses into the sample (where the deflection peaks it stands \
             {:.4e} {} from the record's start)",
            self.column, self.travel, self.unit,
        )?;
        match self.gain_nm_per_v {
            Some(g) => write!(
                f,
                ", which at the sidecar's gain of {g} nm/V moves the base away from it; read \
                 as if the gain were {} nm/V",
                -g
            ),
            None => write!(
                f,
                ", where the format's displacement toward the sample rises (a height, \
                 perhaps); read with its sign reversed"
            ),
        }
    }
}

/// `rec` with each base channel that moves away from the sample as the tip presses in read
/// with its sign reversed, and what was reversed (nothing for a record that already follows
/// the format, which is then borrowed as it is).
pub fn toward_sample(rec: &Recording) -> (std::borrow::Cow<'_, Recording>, Vec<Reversal>) {
    let Some(peak) = peak_of(&rec.deflection_v) else {
        return (std::borrow::Cow::Borrowed(rec), vec![]);
    };
    let gain = rec.meta.piezo.map(|p| p.gain_nm_per_v);
    let mut reversals = vec![];
    let drive_sign = match &rec.drive {
        Drive::Volts(_) => gain.map_or(1.0, f64::signum),
        Drive::Nanometres(_) => 1.0,
    };
    let drive_travel = travel_to(rec.drive.values(), peak);
    let flip_drive = drive_sign * drive_travel < 0.0;
    if flip_drive {
        reversals.push(Reversal {
            column: rec.drive.column_name(),
            travel: drive_travel,
            unit: rec.drive.unit(),
            gain_nm_per_v: match rec.drive {
                Drive::Volts(_) => gain,
                Drive::Nanometres(_) => None,
            },
        });
    }
    let height_travel = rec
        .measured_height_nm
        .as_deref()
        .map_or(0.0, |h| travel_to(h, peak));
    let flip_height = height_travel < 0.0;
    if flip_height {
        reversals.push(Reversal {
            column: super::gaps::HEIGHT,
            travel: height_travel,
            unit: "nm",
            gain_nm_per_v: None,
        });
    }
    if reversals.is_empty() {
        return (std::borrow::Cow::Borrowed(rec), reversals);
    }
    let mut oriented = rec.clone();
    let negate = |v: &mut Vec<f64>| v.iter_mut().for_each(|x| *x = -*x);
    if flip_drive {
        match &mut oriented.drive {
            Drive::Volts(v) | Drive::Nanometres(v) => negate(v),
        }
    }
    if flip_height {
        if let Some(h) = oriented.measured_height_nm.as_mut() {
            negate(h);
        }
    }
    (std::borrow::Cow::Owned(oriented), reversals)
}

/// The index of the deflection's largest finite value, `None` for a record with none.
fn peak_of(y: &[f64]) -> Option<usize> {
    (0..y.len())
        .filter(|&k| y[k].is_finite())
        .max_by(|&a, &b| y[a].total_cmp(&y[b]))
}

/// How far `x` stands at `peak` from its level over the record's first 2 % (at least 20
/// samples; the median, so a spike there does not decide it). 0 where that is not finite.
fn travel_to(x: &[f64], peak: usize) -> f64 {
    let head = (x.len() / 50).max(20).min(x.len());
    let mut start: Vec<f64> = x[..head]
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    if start.is_empty() {
        return 0.0;
    }
    let t = x.get(peak).copied().unwrap_or(f64::NAN) - median(&mut start);
    if t.is_finite() {
        t
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recording::{Cantilever, Piezo, Sample, Sidecar, Tip, FORMAT};

    /// A free lever over 1000 samples, then a contact that pushes it up as the base moves
    /// `direction` × 1 nm per sample past sample 1000.
    fn record(drive: Drive, gain: Option<f64>) -> Recording {
        let n = 2000;
        let deflection_v: Vec<f64> = (0..n)
            .map(|k| {
                if k < 1000 {
                    0.0
                } else {
                    1e-3 * (k - 1000) as f64
                }
            })
            .collect();
        Recording {
            sample_rate_hz: 1000.0,
            time_s: (0..n).map(|k| k as f64 / 1000.0).collect(),
            drive,
            deflection_v,
            reference_deflection_v: None,
            measured_height_nm: None,
            extra_columns: vec![],
            meta: Sidecar {
                format: FORMAT.to_owned(),
                sample_rate_hz: 1000.0,
                cantilever: Cantilever {
                    spring_constant_n_per_m: 0.1,
                    deflection_sensitivity_nm_per_v: 50.0,
                },
                tip: Tip::Sphere { radius_nm: 1000.0 },
                piezo: gain.map(|gain_nm_per_v| Piezo { gain_nm_per_v }),
                sample: Sample::default(),
                notes: None,
                truth: None,
            },
            warnings: vec![],
        }
    }

    fn ramp(direction: f64) -> Vec<f64> {
        (0..2000).map(|k| direction * k as f64).collect()
    }

    #[test]
    fn a_record_that_follows_the_format_is_borrowed_as_it_is() {
        let rec = record(Drive::Nanometres(ramp(1.0)), None);
        let (out, reversals) = toward_sample(&rec);
        assert!(matches!(out, std::borrow::Cow::Borrowed(_)));
        assert!(reversals.is_empty());
        // A negative gain the sidecar declares is the format's own: the voltage falls as
        // the base moves toward the sample.
        let rec = record(Drive::Volts(ramp(-0.01)), Some(-50.0));
        assert!(toward_sample(&rec).1.is_empty());
    }

    #[test]
    fn a_height_that_falls_on_approach_is_read_reversed_and_said_so() {
        let mut rec = record(Drive::Nanometres(ramp(-1.0)), None);
        rec.measured_height_nm = Some(ramp(-1.0));
        let (out, reversals) = toward_sample(&rec);
        assert_eq!(out.drive.values()[1999], 1999.0);
        assert_eq!(out.measured_height_nm.as_ref().unwrap()[1999], 1999.0);
        assert_eq!(reversals.len(), 2, "{reversals:?}");
        assert_eq!(reversals[0].column, "drive_nm");
        assert!((reversals[0].travel + 1980.0).abs() < 1.0, "{reversals:?}");
        let said = reversals[0].to_string();
        assert!(
            said.starts_with("drive_nm falls as the tip presses into"),
            "{said}"
        );
        assert!(said.contains("-1.9800e3 nm"), "{said}");
        assert_eq!(reversals[1].column, "measured_height_nm");
    }

    #[test]
    fn a_gain_of_the_wrong_sign_is_read_as_its_opposite() {
        let rec = record(Drive::Volts(ramp(-0.01)), Some(50.0));
        let (out, reversals) = toward_sample(&rec);
        assert!((out.drive.values()[1999] - 19.99).abs() < 1e-9);
        let said = reversals[0].to_string();
        assert!(said.contains("read as if the gain were -50 nm/V"), "{said}");
    }
}
