//! The one error type of the recording reader and writer.
//!
//! Modelled on cargo-nextest's errors: a [`RecordingError`] is a [`ErrorKind`] (what is wrong)
//! plus where it is: which of the two files ([`FileKind`]), an optional file name the caller
//! supplied, and a [`Location`] inside that file (header, row and column, a sidecar key path, a
//! line and column of TOML text). Its `Display` reads as one sentence, e.g.
//! `samples row 1042, column deflection_v: value "NaN" is not finite`.

use std::fmt;

/// Which of the two files of a recording an error is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FileKind {
    /// The samples, `<stem>.csv`.
    Csv,
    /// The metadata, `<stem>.toml`.
    Sidecar,
}

impl FileKind {
    fn default_name(self) -> &'static str {
        match self {
            FileKind::Csv => "samples",
            FileKind::Sidecar => "sidecar",
        }
    }
}

/// Where in the file the problem is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Location {
    /// The file as a whole.
    File,
    /// The CSV header row (row 1).
    Header,
    /// A whole CSV row; rows count lines of the file, 1 = header, so the first sample is row 2.
    Row(usize),
    /// A whole CSV column, by name.
    Column(String),
    /// One CSV cell: row (as in [`Location::Row`]) and column name.
    Cell {
        /// Line number in the file, 1 = header.
        row: usize,
        /// Column name from the header.
        column: String,
    },
    /// A position in the sidecar's text (1-based line; 1-based column in characters if known).
    Line {
        /// 1-based line number.
        line: usize,
        /// 1-based column, counted in characters.
        column: Option<usize>,
    },
    /// A sidecar key, by its full dotted path, e.g. `cantilever.spring_constant_n_per_m`.
    Key(String),
}

/// What is wrong.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ErrorKind {
    /// Reading from the `Read` or writing to the `Write` failed.
    #[error("I/O error: {0}")]
    Io(std::io::Error),
    /// The bytes are not UTF-8 (a leading UTF-8 byte-order mark is accepted).
    #[error("invalid UTF-8 at byte offset {offset}")]
    InvalidUtf8 {
        /// Offset from the first byte of the file, byte-order mark included.
        offset: usize,
    },
    /// The samples file has no header row.
    #[error("the file is empty (expected a header row)")]
    Empty,
    /// The first line, which must be the header, is blank.
    #[error("the first line is blank (expected the header)")]
    BlankHeader,
    /// A header field is empty.
    #[error("column {position} has an empty name{}", if *last { " (a ',' at the end of the line? the format has none)" } else { "" })]
    EmptyColumnName {
        /// 1-based position in the header.
        position: usize,
        /// Whether it is the header's last field: a separator ending the line.
        last: bool,
    },
    /// Two columns have the same name.
    #[error("column name `{name}` appears more than once")]
    DuplicateColumn {
        /// The repeated name.
        name: String,
    },
    /// A required column is not in the header.
    #[error("missing required column `{name}` (header has: {}){}", header.join(", "), separator_hint(header))]
    MissingColumn {
        /// The missing column.
        name: String,
        /// The header as found.
        header: Vec<String>,
    },
    /// Both `drive_v` and `drive_nm` are present.
    #[error("exactly one of `drive_v` and `drive_nm` is allowed, found both")]
    BothDrives,
    /// Neither `drive_v` nor `drive_nm` is present.
    #[error("missing the drive: exactly one of `drive_v` or `drive_nm` is required (header has: {})", header.join(", "))]
    NoDrive {
        /// The header as found.
        header: Vec<String>,
    },
    /// A row has a different number of fields than the header.
    #[error("expected {expected} fields (as in the header), found {found}")]
    RaggedRow {
        /// Number of header fields.
        expected: usize,
        /// Number of fields in this row.
        found: usize,
    },
    /// A blank line between samples (blank lines are accepted only at the end).
    #[error("blank line between samples")]
    BlankLine,
    /// An empty cell in a required column.
    #[error("value is empty")]
    EmptyValue,
    /// A cell that is not a decimal number.
    #[error("value {text:?} is not a number")]
    NotNumeric {
        /// The cell as found (trimmed).
        text: String,
    },
    /// `NaN` or an infinity in a required column.
    #[error("value {text:?} is not finite")]
    NotFinite {
        /// The cell as found (trimmed), or the value as written.
        text: String,
    },
    /// Fewer than two samples.
    #[error("need at least 2 samples, found {found}")]
    TooFewSamples {
        /// Number of samples found.
        found: usize,
    },
    /// The typical (median) time step does not match the sidecar's sample rate.
    #[error(
        "time step {step_s:e} s ({:.3} Hz) does not match sample_rate_hz = {sample_rate_hz} \
         from the sidecar (relative difference {relative:.3e}, limit 1e-6)",
        1.0 / step_s
    )]
    SampleRateMismatch {
        /// Median time step found in `time_s`.
        step_s: f64,
        /// The sidecar's rate.
        sample_rate_hz: f64,
        /// `|step_s · sample_rate_hz − 1|`.
        relative: f64,
    },
    /// One time step deviates from `1 / sample_rate_hz` by more than 1e-6 relative.
    #[error(
        "time step {step_s:e} s (from the previous row) deviates from 1/sample_rate_hz = \
         {expected_s:e} s by a relative {relative:.3e} (limit 1e-6)"
    )]
    UnevenTimeStep {
        /// `time_s[row] − time_s[row − 1]`.
        step_s: f64,
        /// `1 / sample_rate_hz`.
        expected_s: f64,
        /// `|step_s / expected_s − 1|`.
        relative: f64,
    },
    /// Two columns of an in-memory [`Recording`](super::Recording) differ in length (writing).
    #[error("has {found} values, but time_s has {expected}")]
    LengthMismatch {
        /// Length of `time_s`.
        expected: usize,
        /// Length of this column.
        found: usize,
    },
    /// A column name with a control character (reading), or an extra column's name that
    /// cannot be written so that it reads back as itself (writing).
    #[error("column name {name:?} is not usable: {why}")]
    BadColumnName {
        /// The name.
        name: String,
        /// Why not.
        why: &'static str,
    },
    /// The sidecar is not valid TOML.
    #[error("TOML syntax error: {message}")]
    TomlSyntax {
        /// The toml crate's message (without its source excerpt).
        message: String,
    },
    /// A `[notes]` or `[truth]` table could not be written as TOML.
    #[error("cannot be written as TOML: {message}")]
    TomlWrite {
        /// The toml crate's message.
        message: String,
    },
    /// `format` is not `"recording/1"`.
    #[error("expected \"{expected}\", found {found}")]
    WrongFormat {
        /// The only supported format, `recording/1`.
        expected: &'static str,
        /// What the file says (TOML-quoted if it is a string).
        found: String,
    },
    /// A required sidecar key is absent.
    #[error("required key is missing")]
    MissingKey,
    /// `piezo.gain_nm_per_v` is absent although the drive is given in volts.
    #[error("required key is missing (the samples give the drive in volts, column drive_v)")]
    MissingPiezoGain,
    /// A sidecar key has the wrong TOML type.
    #[error("expected {expected}, found {found}")]
    WrongType {
        /// Expected type, e.g. "a number".
        expected: &'static str,
        /// Found type, e.g. "a string".
        found: &'static str,
    },
    /// A physical quantity that must be positive (and finite) is not.
    #[error("must be a positive finite number, found {value}")]
    NotPositive {
        /// The value found.
        value: f64,
    },
    /// A value outside its physical range.
    #[error("must be {range}, found {value}")]
    OutOfRange {
        /// The value found.
        value: f64,
        /// The allowed range in words.
        range: &'static str,
    },
    /// `tip.shape` is neither "sphere" nor "cone".
    #[error("expected \"sphere\" or \"cone\", found {found:?}")]
    UnknownTipShape {
        /// The shape as found.
        found: String,
    },
    /// `sample_rate_hz` differs between the [`Recording`](super::Recording) and its
    /// [`Sidecar`](super::Sidecar) (writing).
    #[error("Recording::sample_rate_hz = {recording} but Sidecar::sample_rate_hz = {sidecar}")]
    InconsistentSampleRate {
        /// `Recording::sample_rate_hz`.
        recording: f64,
        /// `Sidecar::sample_rate_hz`.
        sidecar: f64,
    },
}

/// An error reading or writing a recording: what is wrong ([`ErrorKind`]) and where.
#[derive(Debug)]
pub struct RecordingError {
    /// Which of the two files.
    pub file: FileKind,
    /// The file's name, if the caller supplied one (see
    /// [`with_file_names`](RecordingError::with_file_names)); otherwise the messages say
    /// "samples" or "sidecar".
    pub file_name: Option<String>,
    /// Where in the file.
    pub location: Location,
    /// What is wrong.
    pub kind: ErrorKind,
}

impl RecordingError {
    /// An error in `file` at `location`.
    pub fn new(file: FileKind, location: Location, kind: ErrorKind) -> Self {
        RecordingError {
            file,
            file_name: None,
            location,
            kind,
        }
    }

    pub(crate) fn csv(location: Location, kind: ErrorKind) -> Self {
        Self::new(FileKind::Csv, location, kind)
    }

    pub(crate) fn sidecar(location: Location, kind: ErrorKind) -> Self {
        Self::new(FileKind::Sidecar, location, kind)
    }

    pub(crate) fn key(path: &str, kind: ErrorKind) -> Self {
        Self::sidecar(Location::Key(path.to_owned()), kind)
    }

    pub(crate) fn io(file: FileKind, e: std::io::Error) -> Self {
        Self::new(file, Location::File, ErrorKind::Io(e))
    }

    /// Names the files in the message: `csv` if the error is about the samples, `sidecar` if it
    /// is about the metadata. The binary calls this with the paths it opened.
    pub fn with_file_names(mut self, csv: &str, sidecar: &str) -> Self {
        self.file_name = Some(
            match self.file {
                FileKind::Csv => csv,
                FileKind::Sidecar => sidecar,
            }
            .to_owned(),
        );
        self
    }
}

impl fmt::Display for RecordingError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.file_name {
            Some(name) => f.write_str(name)?,
            None => f.write_str(self.file.default_name())?,
        }
        match &self.location {
            Location::File => {}
            Location::Header => f.write_str(" header")?,
            Location::Row(row) => write!(f, " row {row}")?,
            Location::Column(column) => write!(f, " column {column}")?,
            Location::Cell { row, column } => write!(f, " row {row}, column {column}")?,
            Location::Line { line, column } => {
                write!(f, " line {line}")?;
                if let Some(column) = column {
                    write!(f, ", column {column}")?;
                }
            }
            Location::Key(path) => write!(f, " key {path}")?,
        }
        write!(f, ": {}", self.kind)
    }
}

// The kind's message (I/O errors included) is part of `Display`, so there is no `source()`:
// error-chain printers would otherwise repeat it.
impl std::error::Error for RecordingError {}

/// What a header that lacks a required column most likely holds instead, for the error's
/// end: the columns separated by ';' (a spreadsheet's export where ',' is the decimal
/// mark), or names in double quotes; nothing otherwise. (Tabs are a control character,
/// which the header check names first.)
fn separator_hint(header: &[String]) -> &'static str {
    let only = match header {
        [only] => Some(only.as_str()),
        _ => None,
    };
    if only.is_some_and(|h| h.contains(';')) {
        "; its columns seem separated by ';': the format separates them by ',' and writes '.' \
         as the decimal point"
    } else if header
        .iter()
        .any(|h| h.len() >= 2 && h.starts_with('"') && h.ends_with('"'))
    {
        "; its names are in double quotes: the format's names are bare (time_s, not \"time_s\")"
    } else {
        ""
    }
}
