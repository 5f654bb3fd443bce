//! Configuration files: TOML in, typed values out, with exact key paths in every error and a
//! warning for every unknown key.
//!
//! Loading is two steps, as in cargo-nextest: [`load_toml`] parses and type-checks (naming the
//! file, line, column and key path of the first error, and collecting unknown keys as
//! warnings), then the caller's `validate` checks values the types cannot (ranges, physics).

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::{Path, PathBuf};
use viscoprobe_core::twin::TwinConfig;

/// A configuration file that could not be used.
#[derive(Debug)]
pub struct ConfigError {
    pub file: PathBuf,
    pub kind: ConfigErrorKind,
}

/// What was wrong with it.
#[derive(Debug)]
pub enum ConfigErrorKind {
    Read(std::io::Error),
    /// TOML syntax or a value of the wrong type at a key path.
    Parse {
        line: Option<usize>,
        column: Option<usize>,
        path: String,
        message: String,
    },
    /// Values that parse but make no sense, each with its key path.
    Invalid(Vec<(String, String)>),
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let file = self.file.display();
        match &self.kind {
            ConfigErrorKind::Read(e) => write!(f, "cannot read {file}: {e}"),
            ConfigErrorKind::Parse {
                line,
                column,
                path,
                message,
            } => {
                write!(f, "{file}")?;
                if let (Some(l), Some(c)) = (line, column) {
                    write!(f, ":{l}:{c}")?;
                }
                if !path.is_empty() && path != "." {
                    write!(f, ": key `{path}`")?;
                }
                write!(f, ": {message}")
            }
            ConfigErrorKind::Invalid(issues) => {
                write!(f, "{file}: {} invalid value(s):", issues.len())?;
                for (path, msg) in issues {
                    write!(f, "\n  `{path}`: {msg}")?;
                }
                Ok(())
            }
        }
    }
}

impl std::error::Error for ConfigError {}

/// A parsed document and the unknown keys it contained (full key paths).
#[derive(Debug)]
pub struct Loaded<T> {
    pub value: T,
    pub unknown_keys: Vec<String>,
}

/// Parses TOML text into `T`; `file` is only used in messages.
pub fn parse_toml<T: DeserializeOwned>(text: &str, file: &Path) -> Result<Loaded<T>, ConfigError> {
    let err = |kind| ConfigError {
        file: file.to_path_buf(),
        kind,
    };
    let de = toml::de::Deserializer::parse(text).map_err(|e| err(parse_kind(text, "", &e)))?;
    let mut unknown_keys = Vec::new();
    let mut record = |path: serde_ignored::Path<'_>| unknown_keys.push(path.to_string());
    let ignored = serde_ignored::Deserializer::new(de, &mut record);
    let value: T = serde_path_to_error::deserialize(ignored).map_err(|e| {
        let path = e.path().to_string();
        err(parse_kind(text, &path, e.inner()))
    })?;
    Ok(Loaded {
        value,
        unknown_keys,
    })
}

fn parse_kind(text: &str, path: &str, e: &toml::de::Error) -> ConfigErrorKind {
    let (line, column) = match e.span() {
        Some(span) => {
            let before = &text[..span.start.min(text.len())];
            let line = before.matches('\n').count() + 1;
            let column = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
            (Some(line), Some(column))
        }
        None => (None, None),
    };
    ConfigErrorKind::Parse {
        line,
        column,
        path: path.to_string(),
        message: e.message().trim().to_string(),
    }
}

/// Reads and parses a TOML file.
pub fn load_toml<T: DeserializeOwned>(file: &Path) -> Result<Loaded<T>, ConfigError> {
    let text = std::fs::read_to_string(file).map_err(|e| ConfigError {
        file: file.to_path_buf(),
        kind: ConfigErrorKind::Read(e),
    })?;
    parse_toml(&text, file)
}

/// `[instrument]` of a simulation configuration.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct InstrumentSection {
    pub sample_rate_hz: f64,
    #[serde(default = "default_block")]
    pub block_len: usize,
    /// `simulated` (as fast as possible) or `wall_clock`.
    #[serde(default)]
    pub pacing: PacingName,
}

fn default_block() -> usize {
    800
}

/// Pacing of the simulated SPM.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PacingName {
    #[default]
    Simulated,
    WallClock,
}

/// A simulated-instrument configuration (`config/sim-*.toml`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SimConfigFile {
    pub instrument: InstrumentSection,
    pub twin: TwinConfig,
}

impl SimConfigFile {
    /// Loads, type-checks and validates a simulation configuration; unknown keys are returned
    /// as warnings.
    pub fn load(file: &Path) -> Result<(Self, Vec<String>), ConfigError> {
        let Loaded {
            value,
            unknown_keys,
        } = load_toml::<Self>(file)?;
        let mut issues: Vec<(String, String)> = value
            .twin
            .validate("twin")
            .into_iter()
            .map(|i| (i.path, i.message))
            .collect();
        if !(value.instrument.sample_rate_hz.is_finite() && value.instrument.sample_rate_hz > 0.0) {
            issues.push((
                "instrument.sample_rate_hz".into(),
                "must be a positive number of Hz".into(),
            ));
        }
        if value.instrument.block_len == 0 {
            issues.push((
                "instrument.block_len".into(),
                "must be at least 1 sample".into(),
            ));
        }
        if !issues.is_empty() {
            return Err(ConfigError {
                file: file.to_path_buf(),
                kind: ConfigErrorKind::Invalid(issues),
            });
        }
        let warnings = unknown_keys
            .into_iter()
            .map(|k| format!("{}: unknown key `{k}` ignored", file.display()))
            .collect();
        Ok((value, warnings))
    }
}
