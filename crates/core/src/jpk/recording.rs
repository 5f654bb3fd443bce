//! [`JpkForce`] → [`Recording`] (`recording/1`).

use toml::{Table, Value};

use super::{JpkError, JpkForce, Segment};
use crate::recording::{
    Cantilever, Drive, Recording, Sample, Sidecar, Tip, DEFAULT_POISSON_RATIO, FORMAT,
};

/// The tip shape assumed on conversion: JPK files do not record the tip geometry, so
/// [`JpkForce::to_recording`] writes a sphere whose radius the caller gives.
pub const DEFAULT_TIP_SHAPE: &str = "sphere";

/// Commanded piezo position channel.
const HEIGHT: &str = "height";
/// Deflection channel.
const DEFLECTION: &str = "vDeflection";
/// Piezo position sensor channel.
const MEASURED: &str = "measuredHeight";
/// Relative tolerance for "the same sample rate".
const RATE_TOLERANCE: f64 = 1e-9;

impl JpkForce {
    /// Converts the force-scan series to one `recording/1` recording.
    ///
    /// - The segments with points are concatenated in file (= time) order; all must have the
    ///   same sample rate (within 1e-9 relative), otherwise this refuses, naming the segments
    ///   and rates (no resampling). `time_s` is `k / rate` from 0.
    /// - `drive_nm` is the commanded piezo `height` channel, sign flipped and zeroed at the
    ///   first sample: `drive_nm = (height[0] − height) · 1e9`. JPK's height decreases as the
    ///   piezo moves toward the sample; the spec's drive is positive toward the sample.
    /// - `deflection_v` is `vDeflection` in volts, as recorded (JPK's sign is already the
    ///   spec's: positive when repulsive); the baseline is *not* subtracted — JPK's measured
    ///   baseline is in the notes.
    /// - `measured_height_nm`, when every segment has `measuredHeight`: the sensor position
    ///   with the same convention as the drive, `(measuredHeight[0] − measuredHeight) · 1e9`.
    /// - `[cantilever]` from the file's own calibration (required: refused without it).
    /// - `[tip]`: a sphere of `tip_radius_nm` ([`DEFAULT_TIP_SHAPE`]): the file has no tip.
    /// - `[sample]`: the name is the file's description name, if any; Poisson ratio 0.5.
    /// - `[notes]`: the JPK provenance (`jpk_*` keys), the conventions above, and `segments`,
    ///   one table per segment: `index`, `kind` (`extend`/`hold`/`retract`/other), `name`,
    ///   `start_index` (first sample in the recording), `num_points`, `start_s`,
    ///   `duration_s`, and when present `setpoint`, `feedback_mode`, `pause_option`,
    ///   `baseline_v`.
    pub fn to_recording(&self, tip_radius_nm: f64) -> Result<Recording, JpkError> {
        let fail = |detail: String| JpkError::Conversion { detail };
        let used: Vec<&Segment> = self.segments.iter().filter(|s| s.num_points > 0).collect();
        let Some(first) = used.first() else {
            return Err(fail("the file has no segment with data points".into()));
        };
        let rate = first.sample_rate_hz;
        for s in &used {
            if (s.sample_rate_hz - rate).abs() > RATE_TOLERANCE * rate {
                return Err(fail(format!(
                    "segment {} is sampled at {} Hz but segment {} at {} Hz; \
                     segments at different rates are not resampled",
                    s.index, s.sample_rate_hz, first.index, rate
                )));
            }
        }
        let channel = |s: &Segment, name: &str, unit: &str| -> Result<Vec<f64>, JpkError> {
            let c = s
                .channels
                .get(name)
                .ok_or_else(|| fail(format!("segment {} has no `{name}` channel", s.index)))?;
            if c.unit != unit {
                return Err(fail(format!(
                    "segment {}, channel `{name}` is in `{}`, expected `{unit}`",
                    s.index, c.unit
                )));
            }
            Ok(c.values.clone())
        };
        let mut height = Vec::new();
        let mut deflection_v = Vec::new();
        let mut measured = Some(Vec::new());
        let mut measured_note = None;
        for s in &used {
            height.extend(channel(s, HEIGHT, "m")?);
            deflection_v.extend(channel(s, DEFLECTION, "V")?);
            if let Some(m) = measured.as_mut() {
                if s.channels.contains_key(MEASURED) {
                    m.extend(channel(s, MEASURED, "m")?);
                } else {
                    measured = None;
                    measured_note = Some(format!(
                        "measured_height_nm omitted: segment {} has no `{MEASURED}` channel",
                        s.index
                    ));
                }
            }
        }
        let toward_sample_nm = |v: &[f64]| -> Vec<f64> {
            let zero = v.first().copied().unwrap_or(0.0);
            v.iter().map(|&x| (zero - x) * 1e9).collect()
        };
        let drive_nm = toward_sample_nm(&height);
        let measured_height_nm = measured.map(|m| toward_sample_nm(&m));
        let n = drive_nm.len();
        let time_s = (0..n).map(|k| k as f64 / rate).collect();

        let cal = &self.calibration;
        let spring = cal.spring_constant_n_per_m.ok_or_else(|| {
            fail(format!(
                "no spring constant: `{SHARED_KEY_HINT}.force` is not defined in the file"
            ))
        })?;
        let sensitivity = cal.sensitivity_m_per_v.ok_or_else(|| {
            fail(format!(
                "no deflection sensitivity: `{SHARED_KEY_HINT}.distance` is not defined in the file"
            ))
        })?;

        let mut notes = Table::new();
        let mut note = |k: &str, v: Value| {
            notes.insert(k.to_owned(), v);
        };
        let p = &self.provenance;
        note("source", Value::String("JPK .jpk-force".into()));
        for (key, value) in [
            ("jpk_data_file", &p.jpk_data_file),
            ("jpk_file_format_version", &p.file_format_version),
            ("jpk_type", &p.file_type),
            ("jpk_instrument", &p.instrument),
            ("jpk_source_software", &p.source_software),
            ("jpk_user_name", &p.user_name),
            ("jpk_comment", &p.comment),
        ] {
            if let Some(v) = value {
                note(key, Value::String(v.clone()));
            }
        }
        note(
            "drive",
            Value::String(
                "drive_nm = (height[0] - height) * 1e9 from JPK's commanded piezo `height` \
                 (calibrated slot), which decreases toward the sample"
                    .into(),
            ),
        );
        note(
            "measured_height",
            Value::String(measured_note.unwrap_or_else(|| {
                "measured_height_nm = (measuredHeight[0] - measuredHeight) * 1e9, \
                 positive toward the sample like the drive"
                    .into()
            })),
        );
        note(
            "deflection",
            Value::String("deflection_v = vDeflection in volts, baseline not subtracted".into()),
        );
        note(
            "tip",
            Value::String(format!(
                "not in the file: {DEFAULT_TIP_SHAPE} of radius {tip_radius_nm} nm assumed"
            )),
        );
        let mut rows = Vec::new();
        let mut start = 0usize;
        for s in &self.segments {
            let mut row = Table::new();
            row.insert("index".into(), Value::Integer(s.index as i64));
            row.insert("kind".into(), Value::String(s.kind.name().to_owned()));
            if let Some(name) = &s.name {
                row.insert("name".into(), Value::String(name.clone()));
            }
            row.insert("start_index".into(), Value::Integer(start as i64));
            row.insert("num_points".into(), Value::Integer(s.num_points as i64));
            row.insert("start_s".into(), Value::Float(start as f64 / rate));
            row.insert("duration_s".into(), Value::Float(s.duration_s));
            let st = &s.settings;
            let finite = |v: Option<f64>| v.filter(|x| x.is_finite()).map(Value::Float);
            let strings = [
                ("feedback_mode", &st.feedback_mode),
                ("segment_type", &st.segment_type),
                ("pause_option", &st.pause_option),
            ];
            for (k, v) in strings {
                if let Some(v) = v {
                    row.insert(k.into(), Value::String(v.clone()));
                }
            }
            for (k, v) in [("setpoint", st.setpoint), ("baseline_v", s.baseline_v)] {
                if let Some(v) = finite(v) {
                    row.insert(k.into(), v);
                }
            }
            rows.push(Value::Table(row));
            start += s.num_points;
        }
        note("segments", Value::Array(rows));

        let meta = Sidecar {
            format: FORMAT.to_owned(),
            sample_rate_hz: rate,
            cantilever: Cantilever {
                spring_constant_n_per_m: spring,
                deflection_sensitivity_nm_per_v: sensitivity * 1e9,
            },
            tip: Tip::Sphere {
                radius_nm: tip_radius_nm,
            },
            piezo: None,
            sample: Sample {
                name: p.name.clone(),
                poisson_ratio: DEFAULT_POISSON_RATIO,
            },
            notes: Some(notes),
            truth: None,
        };
        let recording = Recording {
            sample_rate_hz: rate,
            time_s,
            drive: Drive::Nanometres(drive_nm),
            deflection_v,
            reference_deflection_v: None,
            measured_height_nm,
            extra_columns: Vec::new(),
            meta,
            warnings: Vec::new(),
        };
        recording.validate()?;
        Ok(recording)
    }
}

/// Where the calibration slots live, for error messages.
const SHARED_KEY_HINT: &str = "lcd-info.K.conversion-set.conversion";
