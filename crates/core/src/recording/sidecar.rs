//! The metadata file (the "sidecar"): calibration, tip, sample, free-form notes and truth.
//!
//! Parsed into a `toml::Table` first and then walked by hand rather than through
//! `#[derive(Deserialize)]`: that is what lets the reader report every unknown key once with its
//! full path, name a missing key by its full path, and say which type was expected where.

use std::fmt::Write as _;

use toml::{Table, Value};

use super::error::{ErrorKind, Location, RecordingError};
use crate::contact::{Contact, TipGeometry};

/// The only format this module reads and writes.
pub const FORMAT: &str = "recording/1";

/// Poisson ratio assumed when `sample.poisson_ratio` is absent (incompressible, as in the paper).
pub const DEFAULT_POISSON_RATIO: f64 = 0.5;

/// The contents of a recording's `.toml` file.
#[derive(Debug, Clone, PartialEq)]
pub struct Sidecar {
    /// Always [`FORMAT`] (`"recording/1"`) once read; checked again when writing.
    pub format: String,
    /// Sampling rate of the samples file, Hz (> 0).
    pub sample_rate_hz: f64,
    /// `[cantilever]` calibration (required).
    pub cantilever: Cantilever,
    /// `[tip]` geometry (required).
    pub tip: Tip,
    /// `[piezo]` (optional, but required when the samples give the drive in volts).
    pub piezo: Option<Piezo>,
    /// `[sample]` (optional table; see [`Sample`] for the defaults).
    pub sample: Sample,
    /// `[notes]`: free-form, kept verbatim and written back, otherwise ignored.
    pub notes: Option<Table>,
    /// `[truth]`: the ground truth a simulator wrote, kept verbatim and written back.
    pub truth: Option<Table>,
}

/// `[cantilever]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cantilever {
    /// K_t, N/m (> 0).
    pub spring_constant_n_per_m: f64,
    /// C_t, nm of tip displacement per volt of deflection signal (> 0).
    pub deflection_sensitivity_nm_per_v: f64,
}

/// `[tip]`: `shape = "sphere"` with `radius_nm`, or `shape = "cone"` with `half_angle_deg`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Tip {
    /// Spherical tip (Hertz); radius in nm (> 0).
    Sphere {
        /// Radius, nm.
        radius_nm: f64,
    },
    /// Conical tip (Sneddon); half-opening angle in degrees (strictly between 0 and 90).
    Cone {
        /// Half-opening angle, degrees.
        half_angle_deg: f64,
    },
}

/// `[piezo]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Piezo {
    /// Nominal static gain of the actuator, nm/V (finite, non-zero; may be negative for an
    /// actuator wired to extend on negative voltage).
    pub gain_nm_per_v: f64,
}

/// `[sample]`. The whole table is optional.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// Free text, optional.
    pub name: Option<String>,
    /// Poisson ratio ν, −1 < ν ≤ 0.5. The spec does not mark it required, so an absent
    /// `sample.poisson_ratio` reads as [`DEFAULT_POISSON_RATIO`] (with a warning).
    pub poisson_ratio: f64,
}

impl Default for Sample {
    fn default() -> Self {
        Sample {
            name: None,
            poisson_ratio: DEFAULT_POISSON_RATIO,
        }
    }
}

impl Sidecar {
    /// Parses a sidecar from TOML text (a leading byte-order mark is accepted). Returns the
    /// sidecar and the warnings (unknown keys, defaults applied), one per key.
    ///
    /// `piezo` is left optional here; whether it is required depends on the samples, which
    /// [`Recording::read`](super::Recording::read) checks.
    pub fn from_toml_str(text: &str) -> Result<(Sidecar, Vec<String>), RecordingError> {
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        let mut warnings = Vec::new();
        let sidecar = parse(text, &mut warnings)?;
        Ok((sidecar, warnings))
    }

    /// Reads and parses a sidecar from any reader (UTF-8, optional byte-order mark).
    pub fn read(mut reader: impl std::io::Read) -> Result<(Sidecar, Vec<String>), RecordingError> {
        let text = super::read_text(&mut reader, super::FileKind::Sidecar)?;
        Self::from_toml_str(&text)
    }

    /// Checks the values: format, positive physical quantities, ranges. Errors name the key.
    pub fn validate(&self) -> Result<(), RecordingError> {
        if self.format != FORMAT {
            return Err(RecordingError::key(
                "format",
                ErrorKind::WrongFormat {
                    expected: FORMAT,
                    found: Value::String(self.format.clone()).to_string(),
                },
            ));
        }
        positive("sample_rate_hz", self.sample_rate_hz)?;
        positive(
            "cantilever.spring_constant_n_per_m",
            self.cantilever.spring_constant_n_per_m,
        )?;
        positive(
            "cantilever.deflection_sensitivity_nm_per_v",
            self.cantilever.deflection_sensitivity_nm_per_v,
        )?;
        match self.tip {
            Tip::Sphere { radius_nm } => positive("tip.radius_nm", radius_nm)?,
            Tip::Cone { half_angle_deg } => {
                if !(half_angle_deg > 0.0 && half_angle_deg < 90.0) {
                    return Err(RecordingError::key(
                        "tip.half_angle_deg",
                        ErrorKind::OutOfRange {
                            value: half_angle_deg,
                            range: "strictly between 0 and 90 degrees",
                        },
                    ));
                }
            }
        }
        if let Some(piezo) = self.piezo {
            let g = piezo.gain_nm_per_v;
            if !(g.is_finite() && g != 0.0) {
                return Err(RecordingError::key(
                    "piezo.gain_nm_per_v",
                    ErrorKind::OutOfRange {
                        value: g,
                        range: "finite and non-zero",
                    },
                ));
            }
        }
        let nu = self.sample.poisson_ratio;
        if !(nu > -1.0 && nu <= 0.5) {
            return Err(RecordingError::key(
                "sample.poisson_ratio",
                ErrorKind::OutOfRange {
                    value: nu,
                    range: "greater than -1 and at most 0.5",
                },
            ));
        }
        Ok(())
    }

    /// The sidecar as TOML text: `format`, `sample_rate_hz`, then `[cantilever]`, `[tip]`,
    /// `[piezo]`, `[sample]`, `[notes]` and `[truth]` (the last three only when present).
    /// Floats are written with the shortest digits that round-trip. Does not validate.
    pub fn to_toml_string(&self) -> Result<String, RecordingError> {
        let v = |x: f64| Value::Float(x).to_string();
        let mut s = String::new();
        // `fmt::Write` for `String` never fails.
        let _ = writeln!(s, "format = {}", Value::String(self.format.clone()));
        let _ = writeln!(s, "sample_rate_hz = {}", v(self.sample_rate_hz));
        let c = &self.cantilever;
        let _ = writeln!(s, "\n[cantilever]");
        let _ = writeln!(
            s,
            "spring_constant_n_per_m = {}",
            v(c.spring_constant_n_per_m)
        );
        let _ = writeln!(
            s,
            "deflection_sensitivity_nm_per_v = {}",
            v(c.deflection_sensitivity_nm_per_v)
        );
        let _ = writeln!(s, "\n[tip]");
        match self.tip {
            Tip::Sphere { radius_nm } => {
                let _ = writeln!(s, "shape = \"sphere\"\nradius_nm = {}", v(radius_nm));
            }
            Tip::Cone { half_angle_deg } => {
                let _ = writeln!(
                    s,
                    "shape = \"cone\"\nhalf_angle_deg = {}",
                    v(half_angle_deg)
                );
            }
        }
        if let Some(p) = self.piezo {
            let _ = writeln!(s, "\n[piezo]\ngain_nm_per_v = {}", v(p.gain_nm_per_v));
        }
        let _ = writeln!(s, "\n[sample]");
        if let Some(name) = &self.sample.name {
            let _ = writeln!(s, "name = {}", Value::String(name.clone()));
        }
        let _ = writeln!(s, "poisson_ratio = {}", v(self.sample.poisson_ratio));
        for (name, table) in [("notes", &self.notes), ("truth", &self.truth)] {
            if let Some(table) = table {
                let mut wrapper = Table::new();
                wrapper.insert(name.to_owned(), Value::Table(table.clone()));
                let text = toml::to_string(&wrapper).map_err(|e| {
                    RecordingError::key(
                        name,
                        ErrorKind::TomlWrite {
                            message: e.to_string(),
                        },
                    )
                })?;
                s.push('\n');
                s.push_str(&text);
                if !text.ends_with('\n') {
                    s.push('\n');
                }
            }
        }
        Ok(s)
    }

    /// The contact transform for this tip and sample, in SI units (radius in m, angle in rad).
    pub fn contact(&self) -> Contact {
        let tip = match self.tip {
            Tip::Sphere { radius_nm } => TipGeometry::Sphere {
                radius_m: radius_nm * 1e-9,
            },
            Tip::Cone { half_angle_deg } => TipGeometry::Cone {
                half_angle_rad: half_angle_deg.to_radians(),
            },
        };
        Contact {
            tip,
            poisson_ratio: self.sample.poisson_ratio,
        }
    }
}

fn positive(path: &str, value: f64) -> Result<(), RecordingError> {
    if value > 0.0 && value.is_finite() {
        Ok(())
    } else {
        Err(RecordingError::key(path, ErrorKind::NotPositive { value }))
    }
}

/// `prefix.key`, with the key quoted as TOML would if it is not a bare key.
fn key_path(prefix: &str, key: &str) -> String {
    let bare = !key.is_empty()
        && key
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    let key = if bare {
        key.to_owned()
    } else {
        Value::String(key.to_owned()).to_string()
    };
    if prefix.is_empty() {
        key
    } else {
        format!("{prefix}.{key}")
    }
}

fn type_name(v: &Value) -> &'static str {
    match v {
        Value::String(_) => "a string",
        Value::Integer(_) => "an integer",
        Value::Float(_) => "a float",
        Value::Boolean(_) => "a boolean",
        Value::Datetime(_) => "a date-time",
        Value::Array(_) => "an array",
        Value::Table(_) => "a table",
    }
}

fn wrong_type(path: &str, expected: &'static str, found: &Value) -> RecordingError {
    RecordingError::key(
        path,
        ErrorKind::WrongType {
            expected,
            found: type_name(found),
        },
    )
}

/// A table with its dotted path, for key lookups whose errors name the full path.
struct Section<'a> {
    path: &'a str,
    table: &'a Table,
}

impl<'a> Section<'a> {
    fn path(&self, key: &str) -> String {
        key_path(self.path, key)
    }

    /// A number; TOML integers are accepted where a float is expected (`8000` for `8000.0`).
    fn number(&self, key: &str) -> Result<Option<f64>, RecordingError> {
        match self.table.get(key) {
            None => Ok(None),
            Some(Value::Float(x)) => Ok(Some(*x)),
            Some(Value::Integer(i)) => Ok(Some(*i as f64)),
            Some(other) => Err(wrong_type(&self.path(key), "a number", other)),
        }
    }

    fn required_number(&self, key: &str) -> Result<f64, RecordingError> {
        self.number(key)?
            .ok_or_else(|| RecordingError::key(&self.path(key), ErrorKind::MissingKey))
    }

    fn string(&self, key: &str) -> Result<Option<&'a str>, RecordingError> {
        match self.table.get(key) {
            None => Ok(None),
            Some(Value::String(s)) => Ok(Some(s)),
            Some(other) => Err(wrong_type(&self.path(key), "a string", other)),
        }
    }

    fn table(&self, key: &str) -> Result<Option<&'a Table>, RecordingError> {
        match self.table.get(key) {
            None => Ok(None),
            Some(Value::Table(t)) => Ok(Some(t)),
            Some(other) => Err(wrong_type(&self.path(key), "a table", other)),
        }
    }

    /// One warning per key not in `known`.
    fn warn_unknown(&self, known: &[&str], warnings: &mut Vec<String>) {
        for key in self.table.keys() {
            if !known.contains(&key.as_str()) {
                warnings.push(format!(
                    "sidecar key `{}` is not part of recording/1; ignored",
                    self.path(key)
                ));
            }
        }
    }
}

fn syntax_error(text: &str, e: &toml::de::Error) -> RecordingError {
    let location = match e.span() {
        Some(span) => {
            let start = span.start.min(text.len());
            // Back off to a character boundary so that slicing cannot panic.
            let start = (0..=start)
                .rev()
                .find(|&i| text.is_char_boundary(i))
                .unwrap_or(0);
            let before = &text[..start];
            let line = before.matches('\n').count() + 1;
            let line_start = before.rfind('\n').map_or(0, |i| i + 1);
            let column = before[line_start..].chars().count() + 1;
            Location::Line {
                line,
                column: Some(column),
            }
        }
        None => Location::File,
    };
    RecordingError::sidecar(
        location,
        ErrorKind::TomlSyntax {
            message: e.message().trim().to_owned(),
        },
    )
}

fn parse(text: &str, warnings: &mut Vec<String>) -> Result<Sidecar, RecordingError> {
    let root: Table = toml::from_str(text).map_err(|e| syntax_error(text, &e))?;
    let empty = Table::new();
    let top = Section {
        path: "",
        table: &root,
    };

    // The format first: a different format explains every other difference.
    let format = top
        .string("format")?
        .ok_or_else(|| RecordingError::key("format", ErrorKind::MissingKey))?;
    if format != FORMAT {
        return Err(RecordingError::key(
            "format",
            ErrorKind::WrongFormat {
                expected: FORMAT,
                found: Value::String(format.to_owned()).to_string(),
            },
        ));
    }
    top.warn_unknown(
        &[
            "format",
            "sample_rate_hz",
            "cantilever",
            "tip",
            "piezo",
            "sample",
            "notes",
            "truth",
        ],
        warnings,
    );
    let sample_rate_hz = top.required_number("sample_rate_hz")?;

    // A missing required table reads as an empty one, so that the error names the first
    // missing key in it by its full path (`cantilever.spring_constant_n_per_m`).
    let cantilever = Section {
        path: "cantilever",
        table: top.table("cantilever")?.unwrap_or(&empty),
    };
    cantilever.warn_unknown(
        &["spring_constant_n_per_m", "deflection_sensitivity_nm_per_v"],
        warnings,
    );
    let cantilever = Cantilever {
        spring_constant_n_per_m: cantilever.required_number("spring_constant_n_per_m")?,
        deflection_sensitivity_nm_per_v: cantilever
            .required_number("deflection_sensitivity_nm_per_v")?,
    };

    let tip_section = Section {
        path: "tip",
        table: top.table("tip")?.unwrap_or(&empty),
    };
    let shape = tip_section
        .string("shape")?
        .ok_or_else(|| RecordingError::key("tip.shape", ErrorKind::MissingKey))?;
    let (tip, own, other) = match shape {
        "sphere" => (
            Tip::Sphere {
                radius_nm: tip_section.required_number("radius_nm")?,
            },
            "radius_nm",
            "half_angle_deg",
        ),
        "cone" => (
            Tip::Cone {
                half_angle_deg: tip_section.required_number("half_angle_deg")?,
            },
            "half_angle_deg",
            "radius_nm",
        ),
        _ => {
            return Err(RecordingError::key(
                "tip.shape",
                ErrorKind::UnknownTipShape {
                    found: shape.to_owned(),
                },
            ))
        }
    };
    if tip_section.table.contains_key(other) {
        warnings.push(format!(
            "sidecar key `tip.{other}` does not apply to shape = \"{shape}\"; ignored"
        ));
    }
    tip_section.warn_unknown(&["shape", own, other], warnings);

    let piezo = match top.table("piezo")? {
        None => None,
        Some(table) => {
            let section = Section {
                path: "piezo",
                table,
            };
            section.warn_unknown(&["gain_nm_per_v"], warnings);
            // An empty `[piezo]` is as good as none; with drive_v the recording reader then
            // reports `piezo.gain_nm_per_v` as missing.
            section
                .number("gain_nm_per_v")?
                .map(|gain_nm_per_v| Piezo { gain_nm_per_v })
        }
    };

    let sample_section = Section {
        path: "sample",
        table: top.table("sample")?.unwrap_or(&empty),
    };
    sample_section.warn_unknown(&["name", "poisson_ratio"], warnings);
    let poisson_ratio = match sample_section.number("poisson_ratio")? {
        Some(nu) => nu,
        None => {
            warnings.push(format!(
                "sidecar key `sample.poisson_ratio` is missing; assuming {DEFAULT_POISSON_RATIO} \
                 (incompressible)"
            ));
            DEFAULT_POISSON_RATIO
        }
    };
    let sample = Sample {
        name: sample_section.string("name")?.map(str::to_owned),
        poisson_ratio,
    };

    let sidecar = Sidecar {
        format: format.to_owned(),
        sample_rate_hz,
        cantilever,
        tip,
        piezo,
        sample,
        notes: top.table("notes")?.cloned(),
        truth: top.table("truth")?.cloned(),
    };
    sidecar.validate()?;
    sidecar.warn_implausible(warnings);
    Ok(sidecar)
}

impl Sidecar {
    /// One warning per calibration value a person types by hand that lies outside the range
    /// AFM work keeps it in, naming the key, the range and the unit slip it most likely is.
    /// A value outside is valid and kept; the warning is there because a sensitivity typed
    /// in µm/V reads as 1000 times too small, and everything downstream runs on without
    /// complaint: a fit of a corpus record whose sensitivity was typed 0.05 (for 51.7 nm/V)
    /// gave a modulus of 0.065 kPa against 150 kPa, and its note read a detector noise of
    /// 0.0001 nm as if that were possible (2026-11-30).
    fn warn_implausible(&self, warnings: &mut Vec<String>) {
        let radius_nm = match self.tip {
            Tip::Sphere { radius_nm } => Some(radius_nm),
            Tip::Cone { .. } => None,
        };
        let checks = [
            (
                "cantilever.spring_constant_n_per_m",
                Some(self.cantilever.spring_constant_n_per_m),
                "N/m",
                (1e-3, 500.0),
                "a value in mN/m is 1000 times one in N/m",
            ),
            (
                "cantilever.deflection_sensitivity_nm_per_v",
                Some(self.cantilever.deflection_sensitivity_nm_per_v),
                "nm/V",
                (1.0, 1e4),
                "a value in µm/V is 1/1000 of one in nm/V, one in pm/V 1000 times",
            ),
            (
                "tip.radius_nm",
                radius_nm,
                "nm",
                (0.5, 1e5),
                "a value in µm is 1/1000 of one in nm",
            ),
            (
                "piezo.gain_nm_per_v",
                self.piezo.map(|p| p.gain_nm_per_v),
                "nm/V",
                (0.1, 1e5),
                "a value in µm/V is 1/1000 of one in nm/V",
            ),
        ];
        for (key, value, unit, (lo, hi), slip) in checks {
            let Some(v) = value else { continue };
            if !(lo..=hi).contains(&v.abs()) {
                warnings.push(format!(
                    "{key} = {v} {unit} is outside the {lo}–{hi} {unit} of AFM work: check its \
                     unit ({slip}); every force and indentation scales with it"
                ));
            }
        }
    }
}
