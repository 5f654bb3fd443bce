//! The HAL's error: what went wrong, and whether trying again can help.

use thiserror::Error;

/// What kind of fault a backend met.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HalErrorKind {
    /// A read or write did not complete in time (transient).
    Timeout,
    /// The drive queue ran dry before the next block (transient: write further ahead).
    Underrun,
    /// A frame or block arrived damaged and was dropped (transient).
    Corrupted,
    /// Samples were lost (a sequence gap) (transient for the link, but data are missing).
    Lost,
    /// The device went away (unplugged, hang-up) (fatal until reconnected).
    Disconnected,
    /// The device speaks another protocol version or firmware (fatal).
    VersionMismatch,
    /// The device broke the protocol (fatal).
    Protocol,
    /// The request is outside what the device can do (fatal for this request).
    Unsupported,
    /// A configuration value is invalid (fatal for this request).
    InvalidConfig,
    /// A safety limit tripped; the actuator has been retracted (fatal for the run).
    SafetyLimit,
    /// The call came in the wrong state (e.g. read before start).
    State,
    /// The caller cancelled the operation (Ctrl-C, abort request).
    Cancelled,
}

impl HalErrorKind {
    /// True when the same operation may succeed if retried.
    pub fn is_transient(self) -> bool {
        matches!(
            self,
            Self::Timeout | Self::Underrun | Self::Corrupted | Self::Lost
        )
    }
}

/// A HAL error: its kind and a sentence of context.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("{kind:?}: {detail}")]
pub struct HalError {
    pub kind: HalErrorKind,
    pub detail: String,
}

impl HalError {
    pub fn new(kind: HalErrorKind, detail: impl Into<String>) -> Self {
        Self {
            kind,
            detail: detail.into(),
        }
    }

    pub fn is_transient(&self) -> bool {
        self.kind.is_transient()
    }
}
