//! The daemon's configuration file: the sections `viscoprobe run` reads (`[instrument]`,
//! `[twin]`, `[run]`, `[safety]`, loaded and validated by [`SimConfigFile::load`]) plus
//! `[service]`, parsed here from the same text.

use crate::config::{parse_toml, ConfigError, ConfigErrorKind, SimConfigFile};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Default control socket (systemd's `RuntimeDirectory=viscoprobe`).
pub const DEFAULT_SOCKET: &str = "/run/viscoprobe/control.sock";
/// Default state directory (systemd's `StateDirectory=viscoprobe`).
pub const DEFAULT_STATE_DIR: &str = "/var/lib/viscoprobe";
/// Installed configuration (systemd's `ConfigurationDirectory=viscoprobe`).
pub const INSTALLED_CONFIG: &str = "/etc/viscoprobe/viscoprobe.toml";

/// `[service]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServiceSection {
    /// Unix control socket; created with mode 0660.
    pub socket_path: PathBuf,
    /// Run directories go to `<state_dir>/runs/`.
    pub state_dir: PathBuf,
    /// Group whose members may use the socket (root and the daemon's own user always may);
    /// also given the socket file when the daemon may chown it. None: root and self only.
    pub allowed_group: Option<String>,
    /// Send WATCHDOG=1 when systemd asks for it (`WATCHDOG_USEC`).
    pub watchdog: bool,
    /// A run that reports no progress for this long is considered hung: the watchdog pings
    /// stop and systemd restarts the service (the run is then marked interrupted), s.
    pub run_stall_timeout_s: f64,
    /// Queued runs at most (the running one not counted).
    pub max_queue: usize,
}

impl Default for ServiceSection {
    fn default() -> Self {
        Self {
            socket_path: DEFAULT_SOCKET.into(),
            state_dir: DEFAULT_STATE_DIR.into(),
            allowed_group: None,
            watchdog: true,
            run_stall_timeout_s: 120.0,
            max_queue: 16,
        }
    }
}

#[derive(Debug, Deserialize)]
struct ServiceOnly {
    #[serde(default)]
    service: ServiceSection,
}

/// Everything the daemon reads from its configuration file.
#[derive(Debug, Clone)]
pub struct DaemonConfig {
    pub file: PathBuf,
    /// The file's text (the base of every run's configuration snapshot).
    pub text: String,
    pub sim: SimConfigFile,
    pub service: ServiceSection,
    pub warnings: Vec<String>,
}

impl DaemonConfig {
    /// Loads and validates the whole file: the measurement sections with
    /// [`SimConfigFile::load`] (key paths in every error), then `[service]`.
    pub fn load(file: &Path) -> Result<Self, ConfigError> {
        let (sim, warnings) = SimConfigFile::load(file)?;
        let text = std::fs::read_to_string(file).map_err(|e| ConfigError {
            file: file.to_path_buf(),
            kind: ConfigErrorKind::Read(e),
        })?;
        let mut problems = sim.run.validate();
        let service = parse_toml::<ServiceOnly>(&text, file)?.value.service;
        problems.extend(service.validate());
        if !problems.is_empty() {
            return Err(ConfigError {
                file: file.to_path_buf(),
                kind: ConfigErrorKind::Invalid(problems),
            });
        }
        // `[service]` is ours: SimConfigFile does not know it and warns about it.
        let warnings = warnings
            .into_iter()
            .filter(|w| !w.contains("unknown key `service"))
            .collect();
        Ok(Self {
            file: file.to_path_buf(),
            text,
            sim,
            service,
            warnings,
        })
    }
}

impl ServiceSection {
    /// Value checks, with key paths.
    pub fn validate(&self) -> Vec<(String, String)> {
        let mut v = Vec::new();
        if self.socket_path.as_os_str().is_empty() {
            v.push(("service.socket_path".into(), "must not be empty".into()));
        }
        // sun_path holds 108 bytes with its terminating NUL.
        if self.socket_path.as_os_str().len() > 107 {
            v.push((
                "service.socket_path".into(),
                format!(
                    "too long for a Unix socket ({} bytes, at most 107)",
                    self.socket_path.as_os_str().len()
                ),
            ));
        }
        if self.state_dir.as_os_str().is_empty() {
            v.push(("service.state_dir".into(), "must not be empty".into()));
        }
        if !(self.run_stall_timeout_s.is_finite() && self.run_stall_timeout_s > 0.0) {
            v.push((
                "service.run_stall_timeout_s".into(),
                format!("must be positive (got {})", self.run_stall_timeout_s),
            ));
        }
        if let Some(g) = &self.allowed_group {
            match nix::unistd::Group::from_name(g) {
                Ok(Some(_)) => {}
                Ok(None) => v.push((
                    "service.allowed_group".into(),
                    format!("no group named `{g}` on this system"),
                )),
                Err(e) => v.push((
                    "service.allowed_group".into(),
                    format!("cannot look up group `{g}`: {e}"),
                )),
            }
        }
        v
    }
}

/// The socket the client uses when none is given: `$VISCOPROBE_SOCKET`, then `[service]
/// socket_path` of the installed configuration or `config/viscoprobe.toml`, then
/// [`DEFAULT_SOCKET`].
pub fn default_client_socket() -> PathBuf {
    if let Some(p) = std::env::var_os("VISCOPROBE_SOCKET").filter(|p| !p.is_empty()) {
        return p.into();
    }
    for file in [INSTALLED_CONFIG, "config/viscoprobe.toml"] {
        let path = Path::new(file);
        if let Ok(text) = std::fs::read_to_string(path) {
            if let Ok(l) = parse_toml::<ServiceOnly>(&text, path) {
                return l.value.service.socket_path;
            }
        }
    }
    DEFAULT_SOCKET.into()
}
