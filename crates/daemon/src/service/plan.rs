//! Submitted plans. A plan is TOML text:
//!
//! ```toml
//! name = "pdms-a"          # optional: a label in the run directory's name
//! seed = 7                 # optional: the twin's seed (simulated backend)
//! [run]                    # optional: keys of the configured [run] to override
//! max_iterations = 4
//! ```
//!
//! It is checked like a configuration file: syntax and types with line, column and key path,
//! unknown keys refused, then the merged plan's values with [`RunPlan::validate`].

use super::protocol::ApiError;
use crate::config::{parse_toml, ConfigError, ConfigErrorKind, RunPlan, SimConfigFile};
use serde::Deserialize;
use std::path::Path;

/// A checked plan.
#[derive(Debug, Clone)]
pub struct Plan {
    pub name: Option<String>,
    pub seed: Option<u64>,
    /// The configured `[run]` with the plan's keys over it.
    pub run: RunPlan,
    /// The text as submitted (kept in the run directory as `plan.toml`).
    pub text: String,
}

/// Type check of the plan alone (every `[run]` key has a default, so partial tables pass).
#[derive(Debug, Deserialize)]
struct PlanTypes {
    #[serde(default)]
    #[allow(dead_code)]
    run: RunPlan,
    name: Option<String>,
    seed: Option<u64>,
}

/// Largest plan accepted, bytes.
pub const MAX_PLAN: usize = 64 * 1024;

fn invalid(e: impl std::fmt::Display) -> ApiError {
    ApiError::new("invalid_plan", e.to_string())
}

/// Parses and checks `text` against the configured measurement `base`.
pub fn parse_plan(text: &str, base: &SimConfigFile) -> Result<Plan, ApiError> {
    if text.len() > MAX_PLAN {
        return Err(invalid(format!(
            "plan is {} bytes; at most {MAX_PLAN}",
            text.len()
        )));
    }
    let file = Path::new("plan");
    let loaded = parse_toml::<PlanTypes>(text, file).map_err(invalid)?;
    if !loaded.unknown_keys.is_empty() {
        return Err(invalid(format!(
            "plan: unknown key(s) {} (a plan has `name`, `seed` and a `[run]` table)",
            loaded
                .unknown_keys
                .iter()
                .map(|k| format!("`{k}`"))
                .collect::<Vec<_>>()
                .join(", ")
        )));
    }
    let PlanTypes { name, seed, .. } = loaded.value;
    if let Some(n) = &name {
        let ok = !n.is_empty()
            && n.len() <= 64
            && n.chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
            && !n.starts_with('.');
        if !ok {
            return Err(invalid(
                "plan: key `name`: must be 1 to 64 characters of A-Z a-z 0-9 . _ - (not starting with a dot)",
            ));
        }
    }
    // Merge the plan's [run] keys over the configured plan, table by table.
    let doc: toml::Table = text.parse().map_err(invalid)?;
    let mut merged = toml::Value::try_from(&base.run).map_err(invalid)?;
    if let Some(over) = doc.get("run") {
        merge(&mut merged, over);
    }
    let run: RunPlan = serde_path_to_error::deserialize(merged).map_err(|e| {
        invalid(format!(
            "plan: key `run.{}`: {}",
            e.path(),
            e.inner().message().trim()
        ))
    })?;
    let problems = run.validate();
    if !problems.is_empty() {
        return Err(invalid(ConfigError {
            file: file.to_path_buf(),
            kind: ConfigErrorKind::Invalid(problems),
        }));
    }
    Ok(Plan {
        name,
        seed,
        run,
        text: text.to_string(),
    })
}

fn merge(into: &mut toml::Value, over: &toml::Value) {
    match (into, over) {
        (toml::Value::Table(a), toml::Value::Table(b)) => {
            for (k, v) in b {
                match a.get_mut(k) {
                    Some(slot) => merge(slot, v),
                    None => {
                        a.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        (slot, v) => *slot = v.clone(),
    }
}

impl Plan {
    /// The run's configuration: the daemon's with this plan applied.
    pub fn apply(&self, base: &SimConfigFile) -> SimConfigFile {
        let mut cfg = base.clone();
        cfg.run = self.run.clone();
        if let Some(seed) = self.seed {
            cfg.twin.seed = seed;
        }
        cfg
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn base() -> SimConfigFile {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/sim-pdms.toml");
        SimConfigFile::load(&path).unwrap().0
    }

    #[test]
    fn overrides_only_the_given_keys() {
        let b = base();
        let p = parse_plan(
            "name = \"a-1\"\nseed = 9\n[run]\nmax_iterations = 3\n[run.miic]\nrelaxation = 0.5\n",
            &b,
        )
        .unwrap();
        assert_eq!(p.run.max_iterations, 3);
        assert_eq!(p.run.miic.relaxation, 0.5);
        assert_eq!(p.run.miic.max_iterations, b.run.miic.max_iterations);
        assert_eq!(p.run.preload_nn, b.run.preload_nn);
        assert_eq!(p.apply(&b).twin.seed, 9);
        assert!(parse_plan("", &b).is_ok());
    }

    #[test]
    fn errors_name_the_key() {
        let b = base();
        let msg = |t: &str| parse_plan(t, &b).unwrap_err().message;
        assert!(msg("[run]\nband_hz = \"wide\"\n").contains("run.band_hz"));
        assert!(msg("[run]\nperiods = 0\n").contains("run.periods"));
        assert!(msg("[run]\nforce_rms_nn = 10.0\n").contains("run.force_rms_nn"));
        assert!(msg("[run]\nbogus = 1\n").contains("run.bogus"));
        assert!(msg("[twin]\nseed = 1\n").contains("twin"));
        assert!(msg("name = \"../x\"\n").contains("name"));
        assert!(msg("[run\n").contains("plan:1"));
    }
}
