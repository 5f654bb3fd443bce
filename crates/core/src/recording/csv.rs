//! The samples file: a strict numeric CSV, parsed and written by hand.
//!
//! Why no CSV crate: recording/1 has no quoting, no embedded separators or line breaks and no
//! text cells; every cell is a decimal number in a column named by an identifier. What the
//! format does need is exact error locations (line number, column name, offending text) and
//! per-column rules (required columns must be finite, optional ones may hold `NaN`), which a
//! ~150-line parser over `str::split` gives directly; a general CSV reader would add quoting
//! rules the format forbids and still need this layer on top.
//!
//! Accepted leniencies (all lossless): a UTF-8 byte-order mark (stripped before this module
//! sees the text), CRLF line endings, spaces or tabs around cells, and any number of blank lines
//! at the end of the file. Cells are parsed with `f64::from_str`, so `1e-3`, `+2`, `.5` are
//! numbers; `inf`, `-inf` and `NaN` are numbers but not finite.

use std::io::Write;

use super::error::{ErrorKind, Location, RecordingError};
use super::Drive;

/// Column names of recording/1.
pub(crate) const TIME: &str = "time_s";
pub(crate) const DRIVE_V: &str = "drive_v";
pub(crate) const DRIVE_NM: &str = "drive_nm";
pub(crate) const DEFLECTION: &str = "deflection_v";
pub(crate) const REFERENCE: &str = "reference_deflection_v";
pub(crate) const HEIGHT: &str = "measured_height_nm";
const KNOWN: [&str; 6] = [TIME, DRIVE_V, DRIVE_NM, DEFLECTION, REFERENCE, HEIGHT];

/// Relative tolerance on time steps, from the spec.
pub(crate) const TIME_TOLERANCE: f64 = 1e-6;

/// The columns of a samples file, sorted by role.
#[derive(Debug)]
pub(crate) struct Samples {
    pub time_s: Vec<f64>,
    pub drive: Drive,
    pub deflection_v: Vec<f64>,
    pub reference_deflection_v: Option<Vec<f64>>,
    pub measured_height_nm: Option<Vec<f64>>,
    pub extra_columns: Vec<(String, Vec<f64>)>,
}

fn trim_cell(s: &str) -> &str {
    s.trim_matches([' ', '\t'])
}

fn is_blank(line: &str) -> bool {
    line.trim_matches([' ', '\t', '\r']).is_empty()
}

/// Line number (1-based) of the `index`-th sample (0-based): the header is line 1.
pub(crate) fn row_of_sample(index: usize) -> usize {
    index + 2
}

/// Parses the text of a samples file (BOM already stripped). Returns the columns and one
/// warning per ignored column.
pub(crate) fn parse(text: &str, warnings: &mut Vec<String>) -> Result<Samples, RecordingError> {
    // Lines, with a CR before the LF removed (CRLF files).
    let mut lines = text
        .split('\n')
        .map(|l| l.strip_suffix('\r').unwrap_or(l))
        .enumerate()
        .map(|(i, l)| (i + 1, l));

    if text.split('\n').all(is_blank) {
        return Err(RecordingError::csv(Location::File, ErrorKind::Empty));
    }
    let (_, header_line) = lines.next().unwrap_or((1, ""));
    if is_blank(header_line) {
        return Err(RecordingError::csv(
            Location::Header,
            ErrorKind::BlankHeader,
        ));
    }
    let header: Vec<String> = header_line
        .split(',')
        .map(|c| trim_cell(c).to_owned())
        .collect();
    for (i, name) in header.iter().enumerate() {
        if name.is_empty() {
            return Err(RecordingError::csv(
                Location::Header,
                ErrorKind::EmptyColumnName {
                    position: i + 1,
                    last: i + 1 == header.len(),
                },
            ));
        }
        // Control characters (a stray CR, a tab inside a name) are refused here as the writer
        // refuses them, so that every name read can be written back as itself.
        if name.contains(char::is_control) {
            return Err(RecordingError::csv(
                Location::Header,
                ErrorKind::BadColumnName {
                    name: name.clone(),
                    why: if header.len() == 1 && name.contains('\t') {
                        TABS
                    } else {
                        CONTROL
                    },
                },
            ));
        }
        if header[..i].contains(name) {
            return Err(RecordingError::csv(
                Location::Header,
                ErrorKind::DuplicateColumn { name: name.clone() },
            ));
        }
    }
    let position = |name: &str| header.iter().position(|h| h == name);
    let missing = |name: &str| {
        RecordingError::csv(
            Location::Header,
            ErrorKind::MissingColumn {
                name: name.to_owned(),
                header: header.clone(),
            },
        )
    };
    let time_col = position(TIME).ok_or_else(|| missing(TIME))?;
    let drive_col = match (position(DRIVE_V), position(DRIVE_NM)) {
        (Some(_), Some(_)) => {
            return Err(RecordingError::csv(Location::Header, ErrorKind::BothDrives))
        }
        (None, None) => {
            return Err(RecordingError::csv(
                Location::Header,
                ErrorKind::NoDrive {
                    header: header.clone(),
                },
            ))
        }
        (Some(c), None) | (None, Some(c)) => c,
    };
    let deflection_col = position(DEFLECTION).ok_or_else(|| missing(DEFLECTION))?;
    let required: Vec<bool> = (0..header.len())
        .map(|c| c == time_col || c == drive_col || c == deflection_col)
        .collect();

    let ncols = header.len();
    let mut columns: Vec<Vec<f64>> = vec![Vec::new(); ncols];
    let mut first_blank: Option<usize> = None;
    for (row, line) in lines {
        if is_blank(line) {
            first_blank.get_or_insert(row);
            continue;
        }
        if let Some(blank) = first_blank {
            return Err(RecordingError::csv(
                Location::Row(blank),
                ErrorKind::BlankLine,
            ));
        }
        let found = line.bytes().filter(|&b| b == b',').count() + 1;
        if found != ncols {
            return Err(RecordingError::csv(
                Location::Row(row),
                ErrorKind::RaggedRow {
                    expected: ncols,
                    found,
                },
            ));
        }
        for (c, cell) in line.split(',').enumerate() {
            let cell = trim_cell(cell);
            let at = || Location::Cell {
                row,
                column: header[c].clone(),
            };
            let value = if cell.is_empty() {
                if required[c] {
                    return Err(RecordingError::csv(at(), ErrorKind::EmptyValue));
                }
                // An empty cell in an optional column is a missing value.
                f64::NAN
            } else {
                let v: f64 = cell.parse().map_err(|_| {
                    RecordingError::csv(
                        at(),
                        ErrorKind::NotNumeric {
                            text: cell.to_owned(),
                        },
                    )
                })?;
                if required[c] && !v.is_finite() {
                    return Err(RecordingError::csv(
                        at(),
                        ErrorKind::NotFinite {
                            text: cell.to_owned(),
                        },
                    ));
                }
                v
            };
            columns[c].push(value);
        }
    }
    let n = columns[time_col].len();
    if n < 2 {
        return Err(RecordingError::csv(
            Location::File,
            ErrorKind::TooFewSamples { found: n },
        ));
    }

    let mut take = |c: usize| std::mem::take(&mut columns[c]);
    let time_s = take(time_col);
    let drive = if header[drive_col] == DRIVE_V {
        Drive::Volts(take(drive_col))
    } else {
        Drive::Nanometres(take(drive_col))
    };
    let deflection_v = take(deflection_col);
    let reference_deflection_v = position(REFERENCE).map(&mut take);
    let measured_height_nm = position(HEIGHT).map(&mut take);
    let mut extra_columns = Vec::new();
    for (c, name) in header.iter().enumerate() {
        if !KNOWN.contains(&name.as_str()) {
            warnings.push(format!(
                "samples column `{name}` is not part of recording/1; kept but ignored"
            ));
            extra_columns.push((name.clone(), take(c)));
        }
    }
    Ok(Samples {
        time_s,
        drive,
        deflection_v,
        reference_deflection_v,
        measured_height_nm,
        extra_columns,
    })
}

/// Checks that `time_s` is uniformly spaced at `1 / sample_rate_hz` within the spec's relative
/// tolerance of 1e-6.
///
/// Two checks, so that the message names the actual problem: first the median step against the
/// sidecar's rate (a wrong rate offends on every row, and should be reported as such, not as
/// "uneven at row 3"); then every step against `1 / sample_rate_hz`, naming the first row
/// whose step from the previous row is off (a dropped or repeated sample, a clock glitch).
pub(crate) fn check_time(time_s: &[f64], sample_rate_hz: f64) -> Result<(), RecordingError> {
    if time_s.len() < 2 {
        return Err(RecordingError::csv(
            Location::File,
            ErrorKind::TooFewSamples {
                found: time_s.len(),
            },
        ));
    }
    let steps: Vec<f64> = time_s.windows(2).map(|w| w[1] - w[0]).collect();
    let mut sorted = steps.clone();
    let mid = sorted.len() / 2;
    let (_, &mut median, _) = sorted.select_nth_unstable_by(mid, f64::total_cmp);
    let relative = (median * sample_rate_hz - 1.0).abs();
    // A NaN (from an overflowing step) fails the check explicitly.
    if relative.is_nan() || relative > TIME_TOLERANCE {
        return Err(RecordingError::csv(
            Location::Column(TIME.to_owned()),
            ErrorKind::SampleRateMismatch {
                step_s: median,
                sample_rate_hz,
                relative,
            },
        ));
    }
    for (i, &step) in steps.iter().enumerate() {
        let relative = (step * sample_rate_hz - 1.0).abs();
        if relative.is_nan() || relative > TIME_TOLERANCE {
            return Err(RecordingError::csv(
                Location::Cell {
                    row: row_of_sample(i + 1),
                    column: TIME.to_owned(),
                },
                ErrorKind::UnevenTimeStep {
                    step_s: step,
                    expected_s: 1.0 / sample_rate_hz,
                    relative,
                },
            ));
        }
    }
    Ok(())
}

/// Why an extra column's name could not be written so that it reads back as itself, if so.
pub(crate) fn bad_column_name(name: &str) -> Option<&'static str> {
    if name.is_empty() {
        Some("it is empty")
    } else if name.contains(',') {
        Some("it contains a comma")
    } else if name.contains(char::is_control) {
        Some(CONTROL)
    } else if trim_cell(name) != name {
        Some("it starts or ends with a space or tab")
    } else if KNOWN.contains(&name) {
        Some("it is a recording/1 column name")
    } else {
        None
    }
}

const CONTROL: &str = "it contains a control character";
const TABS: &str = "it contains tabs: the columns seem separated by tabs, and the format \
                    separates them by ','";

/// Writes one value so that it parses back to the same bits: Rust's `{}` and `{:e}` both print
/// the shortest digits that round-trip; `{}` is more readable in the usual range, `{:e}` keeps
/// very large or very small values short.
fn write_value(w: &mut impl Write, x: f64) -> std::io::Result<()> {
    let a = x.abs();
    if a == 0.0 || (1e-5..1e16).contains(&a) || !x.is_finite() {
        write!(w, "{x}")
    } else {
        write!(w, "{x:e}")
    }
}

/// Writes the header and the rows. The caller has checked that all columns have the same
/// length and that the names are writable.
pub(crate) fn write(w: &mut impl Write, columns: &[(&str, &[f64])]) -> std::io::Result<()> {
    for (i, (name, _)) in columns.iter().enumerate() {
        if i > 0 {
            w.write_all(b",")?;
        }
        w.write_all(name.as_bytes())?;
    }
    w.write_all(b"\n")?;
    let n = columns.first().map_or(0, |(_, v)| v.len());
    for k in 0..n {
        for (i, (_, values)) in columns.iter().enumerate() {
            if i > 0 {
                w.write_all(b",")?;
            }
            // Lengths are checked by the caller; a short column would write `NaN`, never panic.
            write_value(w, values.get(k).copied().unwrap_or(f64::NAN))?;
        }
        w.write_all(b"\n")?;
    }
    Ok(())
}
