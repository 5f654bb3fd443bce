//! The recording interchange format, version 1 (`recording/1`,
//! see `spec/recording-format.md`): reading and writing, without any I/O of its own.
//!
//! A recording is two files with the same stem: the samples (`run.csv`) and the metadata, or
//! sidecar (`run.toml`). In memory it is one [`Recording`]:
//!
//! - the sample columns: `time_s`, the [`Drive`] (either `drive_v`, volts to the piezo, or
//!   `drive_nm`, commanded displacement), `deflection_v`, and the optional
//!   `reference_deflection_v` and `measured_height_nm`; any other column is kept in
//!   [`Recording::extra_columns`] and reported once as ignored;
//! - [`Recording::meta`], the [`Sidecar`]: sample rate, [`Cantilever`] calibration, [`Tip`],
//!   optional [`Piezo`] gain (required with `drive_v`), [`Sample`], and the free-form `[notes]`
//!   and `[truth]` tables kept verbatim;
//! - [`Recording::warnings`]: what the reader ignored or assumed, one line per key or column.
//!
//! [`Recording::read`] takes any two [`std::io::Read`]ers (the daemon opens the files), and
//! [`Recording::write`] any two [`std::io::Write`]rs; both fail with a [`RecordingError`],
//! which says which file, where in it (row and column, sidecar key path, or TOML line and
//! column), and what is wrong ([`ErrorKind`]). The reader never panics, whatever the bytes.
//! Written values round-trip bit for bit. [`Recording::force_n`],
//! [`Recording::indentation_m`] and [`Recording::drive_nm`] apply the spec's conventions.
//!
//! Decisions where the spec is silent, all documented where they apply: `sample.poisson_ratio`
//! defaults to 0.5 with a warning (the spec does not mark it required); TOML integers are
//! accepted for floats; optional and extra columns may hold `NaN`, `inf` or an empty cell (read
//! as `NaN`), only the required columns must be finite; a wrong sample rate is reported once
//! against the median time step before single uneven steps are looked for. The users of a
//! recording fill such gaps in the optional channels with [`gaps::with_gaps_filled`], which
//! says where it did, find a deflection pinned at a saturated detector's limit with
//! [`clip::find_clipped`], mend its single-sample glitches with
//! [`glitch::with_glitches_mended`], and read a drive that falls toward the sample (a
//! height) the format's way round with [`orient::toward_sample`]. [`grid::step`] finds a
//! deflection written on a grid coarser than the noise (an export that kept too few
//! decimals), which nothing downstream can undo.

pub mod clip;
mod csv;
mod error;
pub mod gaps;
pub mod glitch;
pub mod grid;
pub mod orient;
mod sidecar;

use std::io::{Read, Write};

pub use error::{ErrorKind, FileKind, Location, RecordingError};
pub use sidecar::{Cantilever, Piezo, Sample, Sidecar, Tip, DEFAULT_POISSON_RATIO, FORMAT};

/// Metres per nanometre.
const M_PER_NM: f64 = 1e-9;

/// The piezo drive column: exactly one of the two in a recording.
#[derive(Debug, Clone, PartialEq)]
pub enum Drive {
    /// `drive_v`: voltage commanded to the piezo actuator (DAC output), V.
    Volts(Vec<f64>),
    /// `drive_nm`: commanded actuator displacement, nm (calibrated closed-loop Z stages).
    Nanometres(Vec<f64>),
}

impl Drive {
    /// The column name in the samples file: `drive_v` or `drive_nm`.
    pub fn column_name(&self) -> &'static str {
        match self {
            Drive::Volts(_) => csv::DRIVE_V,
            Drive::Nanometres(_) => csv::DRIVE_NM,
        }
    }

    /// The column's unit: `V` or `nm`.
    pub fn unit(&self) -> &'static str {
        match self {
            Drive::Volts(_) => "V",
            Drive::Nanometres(_) => "nm",
        }
    }

    /// The values, in the column's own unit.
    pub fn values(&self) -> &[f64] {
        match self {
            Drive::Volts(v) | Drive::Nanometres(v) => v,
        }
    }
}

/// One recording: samples, metadata, and what the reader ignored or assumed.
///
/// All sample columns have the same length (checked by [`Recording::validate`], which
/// [`Recording::write`] calls). Values are in the file's units (the unit is in each name);
/// the conversion methods return SI.
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    /// Sampling rate, Hz; equal to `meta.sample_rate_hz`.
    pub sample_rate_hz: f64,
    /// Sample times, s, uniformly spaced at `1 / sample_rate_hz` (need not start at 0).
    pub time_s: Vec<f64>,
    /// The drive, in volts or nanometres.
    pub drive: Drive,
    /// Cantilever deflection on the sample under test, V (positive = repulsive).
    pub deflection_v: Vec<f64>,
    /// Deflection the same drive produced on a hard reference sample, V.
    pub reference_deflection_v: Option<Vec<f64>>,
    /// The actuator's own position sensor, nm.
    pub measured_height_nm: Option<Vec<f64>>,
    /// Columns not in recording/1, in file order: kept (and written back), otherwise ignored.
    pub extra_columns: Vec<(String, Vec<f64>)>,
    /// The sidecar.
    pub meta: Sidecar,
    /// Reader warnings: unknown sidecar keys (full path), ignored columns, defaults applied;
    /// one line each. Not written.
    pub warnings: Vec<String>,
}

/// What [`mended`] did to a recording before a fit reads it, each for a note.
#[derive(Debug, Clone, Default)]
pub struct Mending {
    /// Missing samples of the optional channels, filled or the channel removed.
    pub gaps: gaps::ChannelGaps,
    /// Single-sample glitches of the deflection, each replaced by its neighbours' mean.
    pub glitches: Vec<glitch::Glitch>,
    /// Base channels read with their sign reversed.
    pub reversals: Vec<orient::Reversal>,
}

/// `rec` as the offline fit and the diagnosis both read it: the optional channels' gaps
/// filled ([`gaps::with_gaps_filled`]), the deflection's glitches mended from their
/// neighbours ([`glitch::with_glitches_mended`]), then a base that falls toward the sample
/// read reversed ([`orient::toward_sample`]); borrowed where none of them changed
/// anything.
pub fn mended(rec: &Recording) -> (std::borrow::Cow<'_, Recording>, Mending) {
    let (filled, gaps) = gaps::with_gaps_filled(rec);
    let (glitch_free, glitches) = glitch::with_glitches_mended(&filled);
    let (oriented, reversals) = orient::toward_sample(&glitch_free);
    let untouched = matches!(filled, std::borrow::Cow::Borrowed(_))
        && matches!(glitch_free, std::borrow::Cow::Borrowed(_))
        && matches!(oriented, std::borrow::Cow::Borrowed(_));
    let out = if untouched {
        std::borrow::Cow::Borrowed(rec)
    } else {
        std::borrow::Cow::Owned(oriented.into_owned())
    };
    (
        out,
        Mending {
            gaps,
            glitches,
            reversals,
        },
    )
}

/// The most a deflection signal reaches, V: photodiode electronics and their converters
/// span ±10 V, some ±15 V. Past that, a column is in another unit.
const PHOTODIODE_LIMIT_V: f64 = 20.0;

/// A warning where a deflection column `column` reaches past [`PHOTODIODE_LIMIT_V`]: such a
/// column is most likely in nm (or another unit), and every force would scale with it. The
/// values are kept as written.
fn beyond_photodiode(column: &str, v: &[f64]) -> Option<String> {
    let (k, peak) = v
        .iter()
        .enumerate()
        .filter(|(_, x)| x.is_finite())
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))?;
    (peak.abs() > PHOTODIODE_LIMIT_V).then(|| {
        let peak = if peak.abs() < 1e6 {
            peak.to_string()
        } else {
            format!("{peak:.4e}")
        };
        format!(
            "samples column `{column}` reaches {peak} V (CSV row {}), past the ±{PHOTODIODE_LIMIT_V} V \
             a photodiode's electronics put out: is it in nm or another unit? Every force and \
             indentation scales with it",
            k + 2
        )
    })
}

/// Reads everything, strips a UTF-8 byte-order mark, checks UTF-8.
pub(crate) fn read_text(reader: &mut impl Read, file: FileKind) -> Result<String, RecordingError> {
    let mut bytes = Vec::new();
    reader
        .read_to_end(&mut bytes)
        .map_err(|e| RecordingError::io(file, e))?;
    const BOM: &[u8] = b"\xEF\xBB\xBF";
    let skip = if bytes.starts_with(BOM) { BOM.len() } else { 0 };
    bytes.drain(..skip);
    String::from_utf8(bytes).map_err(|e| {
        let valid = e.utf8_error().valid_up_to();
        let line = e.as_bytes()[..valid]
            .iter()
            .filter(|&&b| b == b'\n')
            .count()
            + 1;
        let location = match file {
            FileKind::Csv => Location::Row(line),
            FileKind::Sidecar => Location::Line { line, column: None },
        };
        RecordingError::new(
            file,
            location,
            ErrorKind::InvalidUtf8 {
                offset: valid + skip,
            },
        )
    })
}

impl Recording {
    /// Reads a recording from its samples (`csv`) and its sidecar. Both are read to the end
    /// and must be UTF-8 (a byte-order mark is accepted). See [`Recording::from_strs`].
    pub fn read(mut csv: impl Read, mut sidecar: impl Read) -> Result<Recording, RecordingError> {
        let sidecar_text = read_text(&mut sidecar, FileKind::Sidecar)?;
        let csv_text = read_text(&mut csv, FileKind::Csv)?;
        Self::from_strs(&csv_text, &sidecar_text)
    }

    /// Parses a recording from the text of its two files.
    ///
    /// The sidecar is parsed first (its sample rate is needed to check the time column), then
    /// the samples; then the two are checked against each other: the time step against
    /// `sample_rate_hz`, and `piezo.gain_nm_per_v` is required when the drive is `drive_v`.
    pub fn from_strs(csv: &str, sidecar: &str) -> Result<Recording, RecordingError> {
        let (meta, mut warnings) = Sidecar::from_toml_str(sidecar)?;
        let csv = csv.strip_prefix('\u{feff}').unwrap_or(csv);
        let samples = csv::parse(csv, &mut warnings)?;
        if matches!(samples.drive, Drive::Volts(_)) && meta.piezo.is_none() {
            return Err(RecordingError::key(
                "piezo.gain_nm_per_v",
                ErrorKind::MissingPiezoGain,
            ));
        }
        csv::check_time(&samples.time_s, meta.sample_rate_hz)?;
        for (column, values) in [
            (csv::DEFLECTION, Some(&samples.deflection_v)),
            (csv::REFERENCE, samples.reference_deflection_v.as_ref()),
        ] {
            warnings.extend(values.and_then(|v| beyond_photodiode(column, v)));
        }
        Ok(Recording {
            sample_rate_hz: meta.sample_rate_hz,
            time_s: samples.time_s,
            drive: samples.drive,
            deflection_v: samples.deflection_v,
            reference_deflection_v: samples.reference_deflection_v,
            measured_height_nm: samples.measured_height_nm,
            extra_columns: samples.extra_columns,
            meta,
            warnings,
        })
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.time_s.len()
    }

    /// True when there are no samples (never for a recording that was read).
    pub fn is_empty(&self) -> bool {
        self.time_s.is_empty()
    }

    /// The sample columns in file order, as `(name, values)`.
    fn columns(&self) -> Vec<(&str, &[f64])> {
        let mut columns: Vec<(&str, &[f64])> = vec![
            (csv::TIME, &self.time_s),
            (self.drive.column_name(), self.drive.values()),
            (csv::DEFLECTION, &self.deflection_v),
        ];
        if let Some(r) = &self.reference_deflection_v {
            columns.push((csv::REFERENCE, r));
        }
        if let Some(h) = &self.measured_height_nm {
            columns.push((csv::HEIGHT, h));
        }
        for (name, values) in &self.extra_columns {
            columns.push((name, values));
        }
        columns
    }

    /// Checks everything the reader would check, on the in-memory recording: the sidecar's
    /// values, equal column lengths, at least two samples, finite required columns, uniform
    /// time at `sample_rate_hz`, writable extra column names, a piezo gain with `drive_v`.
    /// A recording that validates reads back from what [`Recording::write`] writes.
    pub fn validate(&self) -> Result<(), RecordingError> {
        self.meta.validate()?;
        if self.sample_rate_hz != self.meta.sample_rate_hz {
            return Err(RecordingError::key(
                "sample_rate_hz",
                ErrorKind::InconsistentSampleRate {
                    recording: self.sample_rate_hz,
                    sidecar: self.meta.sample_rate_hz,
                },
            ));
        }
        if matches!(self.drive, Drive::Volts(_)) && self.meta.piezo.is_none() {
            return Err(RecordingError::key(
                "piezo.gain_nm_per_v",
                ErrorKind::MissingPiezoGain,
            ));
        }
        for (i, (name, _)) in self.extra_columns.iter().enumerate() {
            let why = csv::bad_column_name(name).or_else(|| {
                self.extra_columns[..i]
                    .iter()
                    .any(|(other, _)| other == name)
                    .then_some("it appears more than once")
            });
            if let Some(why) = why {
                return Err(RecordingError::csv(
                    Location::Header,
                    ErrorKind::BadColumnName {
                        name: name.clone(),
                        why,
                    },
                ));
            }
        }
        let n = self.len();
        for (i, (name, values)) in self.columns().into_iter().enumerate() {
            if values.len() != n {
                return Err(RecordingError::csv(
                    Location::Column(name.to_owned()),
                    ErrorKind::LengthMismatch {
                        expected: n,
                        found: values.len(),
                    },
                ));
            }
            // The first three columns are the required ones: they must be finite.
            if i < 3 {
                if let Some(k) = values.iter().position(|v| !v.is_finite()) {
                    return Err(RecordingError::csv(
                        Location::Cell {
                            row: csv::row_of_sample(k),
                            column: name.to_owned(),
                        },
                        ErrorKind::NotFinite {
                            text: values[k].to_string(),
                        },
                    ));
                }
            }
        }
        csv::check_time(&self.time_s, self.sample_rate_hz)
    }

    /// Writes the samples to `csv` and the sidecar to `sidecar`, after [`validate`]
    /// (nothing is written if it fails).
    ///
    /// The CSV has the spec's column names (`time_s`, the drive, `deflection_v`, then the
    /// optional and extra columns present), `\n` line endings, and every value with the
    /// shortest digits that parse back to the same `f64`, so a write–read round trip is exact.
    /// Writes are buffered internally; both writers are flushed.
    ///
    /// [`validate`]: Recording::validate
    pub fn write(&self, csv: impl Write, sidecar: impl Write) -> Result<(), RecordingError> {
        self.validate()?;
        let sidecar_text = self.meta.to_toml_string()?;
        let mut w = std::io::BufWriter::new(csv);
        csv::write(&mut w, &self.columns())
            .and_then(|()| w.flush())
            .map_err(|e| RecordingError::io(FileKind::Csv, e))?;
        let mut sidecar = sidecar;
        sidecar
            .write_all(sidecar_text.as_bytes())
            .and_then(|()| sidecar.flush())
            .map_err(|e| RecordingError::io(FileKind::Sidecar, e))
    }

    /// Force on the sample per sample, N: `F = K_t · C_t · deflection_v`, with K_t in N/m and
    /// C_t in nm/V converted to m/V. Positive deflection (tip pushed away from the sample) is a
    /// positive, repulsive force.
    pub fn force_n(&self) -> Vec<f64> {
        let c = &self.meta.cantilever;
        let n_per_v = c.spring_constant_n_per_m * c.deflection_sensitivity_nm_per_v * M_PER_NM;
        self.deflection_v.iter().map(|&d| n_per_v * d).collect()
    }

    /// Indentation per sample, m: `h = C_t · (reference_deflection_v − deflection_v)`, with
    /// C_t converted to m/V; positive when the soft sample lets the tip in. `None` without the
    /// reference channel (then the hard-sample deflection must be predicted from the drive
    /// through the calibrated piezo/cantilever model, which is not this module's business).
    /// Not clamped: before contact both channels read the same and `h` is zero up to noise.
    pub fn indentation_m(&self) -> Option<Vec<f64>> {
        let m_per_v = self.meta.cantilever.deflection_sensitivity_nm_per_v * M_PER_NM;
        let reference = self.reference_deflection_v.as_ref()?;
        Some(
            reference
                .iter()
                .zip(&self.deflection_v)
                .map(|(&r, &d)| m_per_v * (r - d))
                .collect(),
        )
    }

    /// Commanded actuator displacement per sample, nm: `drive_v × piezo.gain_nm_per_v`, or
    /// `drive_nm` as is. `None` only for a `drive_v` recording without a piezo gain, which the
    /// reader never returns.
    pub fn drive_nm(&self) -> Option<Vec<f64>> {
        match &self.drive {
            Drive::Nanometres(nm) => Some(nm.clone()),
            Drive::Volts(v) => {
                let gain = self.meta.piezo?.gain_nm_per_v;
                Some(v.iter().map(|&x| gain * x).collect())
            }
        }
    }

    /// [`drive_nm`](Recording::drive_nm) in SI units, m.
    pub fn drive_m(&self) -> Option<Vec<f64>> {
        let mut d = self.drive_nm()?;
        d.iter_mut().for_each(|x| *x *= M_PER_NM);
        Some(d)
    }
}
