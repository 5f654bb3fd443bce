//! Shared formatting for terminal tables and JSON output.

use std::io::Write;

/// Writes `value` as pretty JSON followed by a newline to stdout.
pub fn print_json<T: serde::Serialize>(value: &T) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    serde_json::to_writer_pretty(&mut out, value)?;
    writeln!(out)?;
    Ok(())
}

/// An error and its causes as one line, `outer: cause: root`, as anyhow's `{:#}` prints it,
/// except that a cause whose text the line already ends with is not repeated. The core's
/// errors say their cause in their own message as well as exposing it as their source
/// (`FitError::Estimate` prints "estimation: {cause}"), so that a plain `{}` reads whole;
/// `{:#}` then printed "estimation: data contain a non-finite value at sample 3154: data
/// contain a non-finite value at sample 3154".
pub fn error_text(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if line.ends_with(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

/// Human units for a Prony parameter given its canonical name (`J0`, `J2`, `tau1`, …):
/// compliances in µPa⁻¹, times in ms — the units of the paper's tables.
pub fn human_param(name: &str, si: f64) -> (f64, &'static str) {
    let (scale, unit) = param_unit(name);
    (si * scale, unit)
}

/// The factor from SI to [`human_param`]'s unit, and the unit, for a parameter name.
pub fn param_unit(name: &str) -> (f64, &'static str) {
    if name.starts_with("tau") {
        (1e3, "ms")
    } else {
        (1e6, "µPa⁻¹")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cause that the message above it already ends with is said once; other causes are
    /// chained as anyhow chains them.
    #[test]
    fn an_error_says_each_cause_once() {
        #[derive(Debug)]
        struct Root;
        impl std::fmt::Display for Root {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "root cause at sample 7")
            }
        }
        impl std::error::Error for Root {}
        // As the core's `#[error("estimation: {0}")] Estimate(#[from] EstimateError)`.
        #[derive(Debug)]
        struct Outer(Root);
        impl std::fmt::Display for Outer {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "estimation: {}", self.0)
            }
        }
        impl std::error::Error for Outer {
            fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
                Some(&self.0)
            }
        }
        let e = anyhow::Error::new(Outer(Root)).context("fitting run.csv");
        assert_eq!(
            format!("{e:#}"),
            "fitting run.csv: estimation: root cause at sample 7: root cause at sample 7"
        );
        assert_eq!(
            error_text(&e),
            "fitting run.csv: estimation: root cause at sample 7"
        );
        let plain = anyhow::anyhow!("no file").context("reading run.toml");
        assert_eq!(error_text(&plain), "reading run.toml: no file");
    }
}
