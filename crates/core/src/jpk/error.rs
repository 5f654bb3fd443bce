//! Errors of the JPK reader: each names the archive entry, property key, segment or channel.

use crate::recording::RecordingError;

/// Why a `.jpk-force` file could not be read or converted.
#[derive(Debug, thiserror::Error)]
pub enum JpkError {
    /// The bytes are not a readable ZIP archive (truncated, not a ZIP, corrupt directory).
    #[error("not a readable .jpk-force (ZIP) archive: {detail}")]
    Archive {
        /// What the ZIP reader said.
        detail: String,
    },
    /// A required entry is absent from the archive.
    #[error("entry `{entry}` is missing from the archive")]
    MissingEntry {
        /// The entry's path inside the archive.
        entry: String,
    },
    /// An entry exists but cannot be read (corrupt or truncated data, bad checksum, too large).
    #[error("entry `{entry}` cannot be read: {detail}")]
    Entry {
        /// The entry's path inside the archive.
        entry: String,
        /// What went wrong.
        detail: String,
    },
    /// A properties file is not valid text or has a malformed escape.
    #[error("{entry}, line {line}: {detail}")]
    Text {
        /// The entry's path inside the archive.
        entry: String,
        /// 1-based line (the first line of a continued logical line).
        line: usize,
        /// What is wrong.
        detail: String,
    },
    /// A required property is absent.
    #[error("{entry}: missing property `{key}`")]
    MissingKey {
        /// The entry's path inside the archive.
        entry: String,
        /// The property key.
        key: String,
    },
    /// A property has a value of the wrong form or out of range.
    #[error("{entry}: property `{key}` = `{value}` is not {expected}")]
    BadValue {
        /// The entry's path inside the archive.
        entry: String,
        /// The property key.
        key: String,
        /// The value found (shortened when long).
        value: String,
        /// What was expected.
        expected: &'static str,
    },
    /// A channel's data do not match its headers.
    #[error("segment {segment}, channel `{channel}` (`{entry}`): {detail}")]
    Channel {
        /// Segment number (the `N` of `segments/N/`).
        segment: usize,
        /// Channel name.
        channel: String,
        /// The data entry's path inside the archive.
        entry: String,
        /// What is wrong.
        detail: String,
    },
    /// The file cannot become a recording (missing channel, non-uniform rate, no data).
    #[error("cannot convert to a recording: {detail}")]
    Conversion {
        /// What is missing or inconsistent.
        detail: String,
    },
    /// The converted recording failed [`Recording::validate`](crate::recording::Recording::validate).
    #[error("the converted recording is not valid: {0}")]
    Recording(#[from] RecordingError),
}

/// A value shortened for an error message (absurd inputs can be megabytes long).
pub(crate) fn short(value: &str) -> String {
    const MAX: usize = 80;
    match value.char_indices().nth(MAX) {
        None => value.to_owned(),
        Some((cut, _)) => format!("{}…", &value[..cut]),
    }
}
