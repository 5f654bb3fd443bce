//! Shared formatting for terminal tables and JSON output.

use std::io::Write;

/// Writes `value` as pretty JSON followed by a newline to stdout.
pub fn print_json<T: serde::Serialize>(value: &T) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    serde_json::to_writer_pretty(&mut out, value)?;
    writeln!(out)?;
    Ok(())
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
