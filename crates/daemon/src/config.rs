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
    /// `simulated` (the twin in this file) or `serial` (a DAQ board at `port`).
    #[serde(default)]
    pub backend: BackendName,
    /// Serial port of the DAQ board, e.g. `/dev/ttyACM0` (with `backend = "serial"`).
    #[serde(default)]
    pub port: Option<String>,
}

/// Which instrument backend a run uses.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BackendName {
    #[default]
    Simulated,
    Serial,
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

/// A simulated-instrument configuration (`config/sim-*.toml`): the instrument, the twin
/// behind it, and the measurement plan and safety limits of `viscoprobe run`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SimConfigFile {
    pub instrument: InstrumentSection,
    pub twin: TwinConfig,
    #[serde(default)]
    pub run: RunPlan,
    #[serde(default)]
    pub safety: SafetySection,
}

/// `[run]`: the closed-loop measurement plan.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default)]
pub struct RunPlan {
    /// Mean force in contact, nN.
    pub preload_nn: f64,
    /// RMS of the force excitation, nN.
    pub force_rms_nn: f64,
    /// Design band, Hz.
    pub band_hz: [f64; 2],
    /// Length of one acquisition, s (whole periods).
    pub duration_s: f64,
    /// Periods per acquisition (≥ 2 lets the estimator measure the noise).
    pub periods: usize,
    /// Prony terms to estimate.
    pub order: usize,
    /// Design iterations at most.
    pub max_iterations: usize,
    /// Stop when the relative parameter change falls below this.
    pub rel_change_tol: f64,
    /// Mains frequency to keep dark (with harmonics), Hz; 0 = none.
    pub exclude_mains_hz: f64,
    /// `measured` (run each drive on the hard reference too) or `predicted` (from calibration).
    pub reference: ReferenceMode,
    /// Where run directories go.
    pub out_dir: String,
    pub miic: MiicPlan,
    /// Approach speed, nm/s of actuator travel.
    pub approach_speed_nm_per_s: f64,
    /// Play each final drive once more with the tip out of contact and subtract the lever's
    /// response there (hydrodynamic drag, optical cross-talk) from the force.
    pub free_space_correction: bool,
}

impl Default for RunPlan {
    fn default() -> Self {
        Self {
            preload_nn: 5.0,
            force_rms_nn: 1.0,
            band_hz: [0.5, 2000.0],
            duration_s: 2.0,
            periods: 2,
            order: 3,
            max_iterations: 8,
            rel_change_tol: 0.005,
            exclude_mains_hz: 0.0,
            reference: ReferenceMode::Measured,
            out_dir: "runs".into(),
            miic: MiicPlan::default(),
            approach_speed_nm_per_s: 1000.0,
            free_space_correction: true,
        }
    }
}

impl RunPlan {
    /// Value checks, with key paths.
    pub fn validate(&self) -> Vec<(String, String)> {
        let mut v = Vec::new();
        let mut pos = |k: &str, x: f64| {
            if !(x.is_finite() && x > 0.0) {
                v.push((format!("run.{k}"), format!("must be positive (got {x})")));
            }
        };
        pos("preload_nn", self.preload_nn);
        pos("force_rms_nn", self.force_rms_nn);
        pos("duration_s", self.duration_s);
        pos("rel_change_tol", self.rel_change_tol);
        pos("approach_speed_nm_per_s", self.approach_speed_nm_per_s);
        pos("miic.target_err2_pct", self.miic.target_err2_pct);
        pos("miic.target_errinf_pct", self.miic.target_errinf_pct);
        if !(self.band_hz[0] > 0.0 && self.band_hz[1] > self.band_hz[0]) {
            v.push((
                "run.band_hz".into(),
                format!(
                    "must be [low, high] with 0 < low < high (got {:?})",
                    self.band_hz
                ),
            ));
        }
        if self.periods < 1 {
            v.push(("run.periods".into(), "must be at least 1".into()));
        }
        if self.order < 1 || self.order > 6 {
            v.push((
                "run.order".into(),
                format!("must be 1 to 6 Prony terms (got {})", self.order),
            ));
        }
        if self.max_iterations < 1 {
            v.push(("run.max_iterations".into(), "must be at least 1".into()));
        }
        if !(self.miic.relaxation > 0.0 && self.miic.relaxation <= 1.0) {
            v.push((
                "run.miic.relaxation".into(),
                format!("must lie in (0, 1] (got {})", self.miic.relaxation),
            ));
        }
        if self.force_rms_nn * 3.0 >= self.preload_nn {
            v.push((
                "run.force_rms_nn".into(),
                format!(
                    "3×force_rms ({:.2} nN) must stay below the preload ({} nN) or the tip loses contact",
                    3.0 * self.force_rms_nn,
                    self.preload_nn
                ),
            ));
        }
        v
    }
}

/// How the hard-sample deflection is obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ReferenceMode {
    Measured,
    Predicted,
}

/// `[run.miic]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default)]
pub struct MiicPlan {
    pub max_iterations: usize,
    pub target_err2_pct: f64,
    pub target_errinf_pct: f64,
    pub relaxation: f64,
    /// Cancel output lines the desired force does not have (contact and hysteresis harmonics).
    pub cancel_harmonics: bool,
}

impl Default for MiicPlan {
    fn default() -> Self {
        Self {
            max_iterations: 8,
            target_err2_pct: 1.0,
            target_errinf_pct: 3.0,
            relaxation: 1.0,
            cancel_harmonics: true,
        }
    }
}

/// `[safety]`: limits enforced below every controller.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default)]
pub struct SafetySection {
    pub min_drive_v: f64,
    pub max_drive_v: f64,
    pub max_slew_v_per_s: f64,
    pub max_force_nn: f64,
    pub retract_drive_v: f64,
}

impl Default for SafetySection {
    fn default() -> Self {
        Self {
            min_drive_v: -10.0,
            max_drive_v: 10.0,
            max_slew_v_per_s: 2.0e4,
            max_force_nn: 40.0,
            retract_drive_v: 0.0,
        }
    }
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
