//! Java `.properties` files, the text format of every JPK header.
//!
//! Written by hand: the Rust crates for Java properties are small, rarely maintained, and none
//! reports errors with the entry and line this reader needs; the grammar
//! (`java.util.Properties.load`) is short enough to follow exactly:
//!
//! - natural lines end at `\n`, `\r` or `\r\n`; a line ending in an odd number of backslashes
//!   continues on the next one, whose leading white space is dropped;
//! - blank lines and lines whose first non-blank character is `#` or `!` are skipped (comment
//!   lines never continue);
//! - the key ends at the first unescaped `=`, `:` or white space (space, tab, form feed); white
//!   space and one `=` or `:` around the separator are dropped, the rest is the value;
//! - escapes in keys and values: `\t`, `\n`, `\r`, `\f`, `\uXXXX` (UTF-16, surrogate pairs
//!   joined), and `\c` for any other character `c` (so `\:`, `\=`, `\\`, `\ `);
//! - a later duplicate key replaces an earlier one.
//!
//! Encoding: Java writes these files in ISO-8859-1 with everything else as `\uXXXX`. The reader
//! takes UTF-8 when the bytes are valid UTF-8 (a leading byte-order mark is dropped) and
//! ISO-8859-1 otherwise; in both cases control characters other than tab, line feed, form feed
//! and carriage return are refused, since no text header contains them and binary garbage
//! always does. Malformed `\u` escapes are refused too (Java throws on them).

use std::collections::BTreeMap;

use super::error::{short, JpkError};

/// One parsed `.properties` file: its key–value pairs and the archive entry it came from.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Properties {
    entry: String,
    map: BTreeMap<String, String>,
}

impl Properties {
    /// Parses the bytes of the archive entry `entry` (the name is only used in errors).
    pub fn parse(entry: &str, bytes: &[u8]) -> Result<Properties, JpkError> {
        let text = decode(entry, bytes)?;
        let chars: Vec<char> = text.chars().collect();
        let mut map = BTreeMap::new();
        let mut i = 0;
        let mut line = 1;
        let n = chars.len();
        let is_blank = |c: char| c == ' ' || c == '\t' || c == '\x0c';
        while i < n {
            // Leading white space of a natural line.
            while i < n && is_blank(chars[i]) {
                i += 1;
            }
            if i >= n {
                break;
            }
            match chars[i] {
                '\r' | '\n' => {
                    i = skip_newline(&chars, i);
                    line += 1;
                    continue;
                }
                '#' | '!' => {
                    while i < n && chars[i] != '\n' && chars[i] != '\r' {
                        i += 1;
                    }
                    continue;
                }
                _ => {}
            }
            let start_line = line;
            // Collect the logical line, keeping escapes as they are, dropping continuations.
            let mut logical = Vec::new();
            let mut backslashes = 0usize;
            while i < n {
                let c = chars[i];
                if c == '\n' || c == '\r' {
                    if backslashes % 2 == 1 {
                        logical.pop();
                        i = skip_newline(&chars, i);
                        line += 1;
                        while i < n && is_blank(chars[i]) {
                            i += 1;
                        }
                        backslashes = 0;
                        continue;
                    }
                    break;
                }
                backslashes = if c == '\\' { backslashes + 1 } else { 0 };
                logical.push(c);
                i += 1;
            }
            let (key, value) = split_key_value(&logical);
            let key = unescape(key, entry, start_line)?;
            let value = unescape(value, entry, start_line)?;
            map.insert(key, value);
        }
        Ok(Properties {
            entry: entry.to_owned(),
            map,
        })
    }

    /// The archive entry these properties were read from.
    pub fn entry(&self) -> &str {
        &self.entry
    }

    /// The value of `key`, if present.
    pub fn get(&self, key: &str) -> Option<&str> {
        self.map.get(key).map(String::as_str)
    }

    /// Number of keys.
    pub fn len(&self) -> usize {
        self.map.len()
    }

    /// True when the file held no key.
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }

    /// All pairs, sorted by key.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &str)> {
        self.map.iter().map(|(k, v)| (k.as_str(), v.as_str()))
    }

    /// The pairs whose key starts with `prefix`, with the prefix removed.
    pub fn with_prefix<'a>(&'a self, prefix: &'a str) -> impl Iterator<Item = (&'a str, &'a str)> {
        self.map
            .range(prefix.to_owned()..)
            .take_while(move |(k, _)| k.starts_with(prefix))
            .map(move |(k, v)| (&k[prefix.len()..], v.as_str()))
    }

    /// The value of a required key.
    pub(crate) fn require(&self, key: &str) -> Result<&str, JpkError> {
        self.get(key).ok_or_else(|| JpkError::MissingKey {
            entry: self.entry.clone(),
            key: key.to_owned(),
        })
    }

    /// A required number (Java `Double.toString` syntax; `NaN` and `Infinity` parse).
    pub(crate) fn f64(&self, key: &str) -> Result<f64, JpkError> {
        let text = self.require(key)?;
        self.parse_f64(key, text)
    }

    /// An optional number: `None` when the key is absent or its value is empty.
    pub(crate) fn opt_f64(&self, key: &str) -> Result<Option<f64>, JpkError> {
        match self.get(key) {
            None => Ok(None),
            Some(t) if t.trim().is_empty() => Ok(None),
            Some(t) => self.parse_f64(key, t).map(Some),
        }
    }

    /// A required, finite number.
    pub(crate) fn finite_f64(&self, key: &str) -> Result<f64, JpkError> {
        let v = self.f64(key)?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(self.bad_value(key, "a finite number"))
        }
    }

    /// A required non-negative integer.
    pub(crate) fn usize(&self, key: &str) -> Result<usize, JpkError> {
        let text = self.require(key)?;
        text.trim()
            .parse::<usize>()
            .map_err(|_| self.bad_value(key, "a non-negative integer"))
    }

    /// An optional non-negative integer.
    pub(crate) fn opt_usize(&self, key: &str) -> Result<Option<usize>, JpkError> {
        match self.get(key) {
            None => Ok(None),
            Some(_) => self.usize(key).map(Some),
        }
    }

    fn parse_f64(&self, key: &str, text: &str) -> Result<f64, JpkError> {
        let t = text.trim();
        // Rust also accepts "inf" and "infinity"; Java writes "Infinity" and "NaN".
        t.parse::<f64>()
            .map_err(|_| self.bad_value(key, "a number"))
    }

    /// The error for a value of the wrong form at `key`.
    pub(crate) fn bad_value(&self, key: &str, expected: &'static str) -> JpkError {
        JpkError::BadValue {
            entry: self.entry.clone(),
            key: key.to_owned(),
            value: short(self.get(key).unwrap_or("")),
            expected,
        }
    }
}

fn skip_newline(chars: &[char], i: usize) -> usize {
    if chars[i] == '\r' && chars.get(i + 1) == Some(&'\n') {
        i + 2
    } else {
        i + 1
    }
}

/// Splits a logical line (escapes still raw) into raw key and raw value.
fn split_key_value(chars: &[char]) -> (&[char], &[char]) {
    let is_blank = |c: char| c == ' ' || c == '\t' || c == '\x0c';
    let n = chars.len();
    let mut k = 0;
    let mut escaped = false;
    while k < n {
        let c = chars[k];
        if escaped {
            escaped = false;
        } else if c == '\\' {
            escaped = true;
        } else if c == '=' || c == ':' || is_blank(c) {
            break;
        }
        k += 1;
    }
    let key = &chars[..k];
    let mut v = k;
    while v < n && is_blank(chars[v]) {
        v += 1;
    }
    if v < n && (chars[v] == '=' || chars[v] == ':') {
        v += 1;
        while v < n && is_blank(chars[v]) {
            v += 1;
        }
    }
    (key, &chars[v..])
}

/// Resolves the escapes of a raw key or value.
fn unescape(raw: &[char], entry: &str, line: usize) -> Result<String, JpkError> {
    let err = |detail: String| JpkError::Text {
        entry: entry.to_owned(),
        line,
        detail,
    };
    let mut out = String::with_capacity(raw.len());
    let mut i = 0;
    while i < raw.len() {
        let c = raw[i];
        i += 1;
        if c != '\\' {
            out.push(c);
            continue;
        }
        let Some(&e) = raw.get(i) else {
            // A lone backslash at the very end of the file: Java drops it.
            break;
        };
        i += 1;
        match e {
            't' => out.push('\t'),
            'n' => out.push('\n'),
            'r' => out.push('\r'),
            'f' => out.push('\x0c'),
            'u' => {
                let unit = hex4(raw, i).ok_or_else(|| {
                    err("malformed \\uXXXX escape (four hex digits expected)".into())
                })?;
                i += 4;
                let ch = if (0xD800..0xDC00).contains(&unit) {
                    let low = (raw.get(i) == Some(&'\\') && raw.get(i + 1) == Some(&'u'))
                        .then(|| hex4(raw, i + 2))
                        .flatten()
                        .filter(|l| (0xDC00..0xE000).contains(l))
                        .ok_or_else(|| err(format!("unpaired surrogate \\u{unit:04X}")))?;
                    i += 6;
                    char::from_u32(0x10000 + ((unit - 0xD800) << 10) + (low - 0xDC00))
                } else {
                    char::from_u32(unit)
                };
                out.push(ch.ok_or_else(|| err(format!("unpaired surrogate \\u{unit:04X}")))?);
            }
            other => out.push(other),
        }
    }
    Ok(out)
}

fn hex4(raw: &[char], at: usize) -> Option<u32> {
    let digits = raw.get(at..at + 4)?;
    digits
        .iter()
        .try_fold(0u32, |acc, c| Some(acc * 16 + c.to_digit(16)?))
}

/// Bytes to text: UTF-8 when valid, ISO-8859-1 otherwise; control characters refused.
fn decode(entry: &str, bytes: &[u8]) -> Result<String, JpkError> {
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let (text, encoding) = match std::str::from_utf8(bytes) {
        Ok(s) => (s.to_owned(), "UTF-8"),
        Err(_) => (bytes.iter().map(|&b| b as char).collect(), "ISO-8859-1"),
    };
    let mut line = 1;
    for c in text.chars() {
        if c == '\n' {
            line += 1;
        }
        let control = matches!(c, '\0'..='\x08' | '\x0b' | '\x0e'..='\x1f' | '\x7f'..='\u{9f}');
        if control {
            return Err(JpkError::Text {
                entry: entry.to_owned(),
                line,
                detail: format!(
                    "not a text file: control character U+{:04X} (read as {encoding})",
                    c as u32
                ),
            });
        }
    }
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Properties {
        Properties::parse("t.properties", text.as_bytes()).unwrap()
    }

    #[test]
    fn java_grammar() {
        let p = parse(
            "#comment\n! also\n  a=1\nb : 2\nc 3\nd\\:e=\\u00B5m\nf=x\\\n    y\\\\\ng=\\\\\\\nh\r\ni=\r\nj\n\\ k=\\=",
        );
        assert_eq!(p.get("a"), Some("1"));
        assert_eq!(p.get("b"), Some("2"));
        assert_eq!(p.get("c"), Some("3"));
        assert_eq!(p.get("d:e"), Some("µm"));
        assert_eq!(p.get("f"), Some("xy\\"));
        assert_eq!(p.get("g"), Some("\\h"));
        assert_eq!(p.get("i"), Some(""));
        assert_eq!(p.get("j"), Some(""));
        assert_eq!(p.get(" k"), Some("="));
        assert_eq!(p.len(), 9);
    }

    #[test]
    fn timestamps_and_surrogates() {
        let p = parse("t=2021-06-30 13\\:48\\:08.425 +0100\ns=\\uD83D\\uDE00");
        assert_eq!(p.get("t"), Some("2021-06-30 13:48:08.425 +0100"));
        assert_eq!(p.get("s"), Some("😀"));
    }

    #[test]
    fn refusals_name_the_line() {
        let e = Properties::parse("x", b"a=1\nb=\\u12G4\n").unwrap_err();
        assert!(e.to_string().contains("x, line 2"), "{e}");
        let e = Properties::parse("x", b"a=1\nb=\\uD800\n").unwrap_err();
        assert!(e.to_string().contains("surrogate"), "{e}");
        let e = Properties::parse("x", b"a=1\n\nb=\x00\xff\n").unwrap_err();
        assert!(e.to_string().contains("line 3"), "{e}");
        // ISO-8859-1 text is fine.
        let p = Properties::parse("x", b"a=caf\xe9").unwrap();
        assert_eq!(p.get("a"), Some("café"));
    }
}
