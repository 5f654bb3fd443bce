//! The record of a run: per-iteration estimates, designs and tracking errors, the final
//! estimate with intervals and moduli, written as `report.json` and `report.md` (atomically).

use super::session::Approach;
use crate::config::SimConfigFile;
use serde::Serialize;
use serde_json::{json, Map, Value};
use std::path::Path;
use viscoprobe_core::design::DesignLine;
use viscoprobe_core::estimate::Estimate;
use viscoprobe_core::miic::TrackingError;
use viscoprobe_core::prony::PronySeries;
use viscoprobe_hal::SafetyStats;

/// One MIIC step.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct MiicRecord {
    pub step: usize,
    pub err2_pct: f64,
    pub errinf_pct: f64,
    /// Mean (preload) offset of the deflection from the desired, V.
    pub mean_error_v: f64,
}

/// One design iteration.
#[derive(Debug, Clone, Serialize)]
pub struct IterationRecord {
    pub iteration: usize,
    pub lines: Vec<DesignLineOut>,
    pub params: Vec<f64>,
    pub std: Vec<f64>,
    pub ci95: Vec<[f64; 2]>,
    pub rel_change: Option<f64>,
    pub tracking: TrackingError,
    pub miic: Vec<MiicRecord>,
    /// One period of desired and achieved force, nN (decimated), for the plots.
    #[serde(skip)]
    pub force_period: (Vec<f64>, Vec<f64>, Vec<f64>),
    #[serde(skip)]
    pub estimate: Option<Estimate>,
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct DesignLineOut {
    pub freq_hz: f64,
    pub power_frac: f64,
}

impl IterationRecord {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        iteration: usize,
        lines: &[DesignLine],
        est: &Estimate,
        rel_change: Option<f64>,
        last: MiicRecord,
        miic: Vec<MiicRecord>,
        desired_v: &[f64],
        played: &super::Played,
        np: usize,
        periods: usize,
    ) -> Self {
        // Achieved: the mean of the recorded periods; both in nN above the free baseline.
        let base = desired_v.iter().copied().fold(f64::INFINITY, f64::min);
        let _ = base;
        let mut achieved = vec![0.0; np];
        for p in 0..periods {
            let from = played.start + p * np;
            for (a, d) in achieved.iter_mut().zip(&played.deflection[from..from + np]) {
                *a += d / periods as f64;
            }
        }
        let step = (np / 2000).max(1);
        let idx: Vec<usize> = (0..np).step_by(step).collect();
        Self {
            iteration,
            lines: lines
                .iter()
                .map(|l| DesignLineOut {
                    freq_hz: l.freq_hz,
                    power_frac: l.power_frac,
                })
                .collect(),
            params: est.values(),
            std: est.std.clone(),
            ci95: est.ci95.clone(),
            rel_change,
            tracking: TrackingError {
                err2_pct: last.err2_pct,
                errinf_pct: last.errinf_pct,
                mean_error: last.mean_error_v,
            },
            miic,
            force_period: (
                idx.iter().map(|&i| i as f64).collect(),
                idx.iter().map(|&i| desired_v[i]).collect(),
                idx.iter().map(|&i| achieved[i]).collect(),
            ),
            estimate: Some(est.clone()),
        }
    }
}

/// Calibration results.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Calibration {
    pub reference: Option<Approach>,
    pub sample: Option<Approach>,
    /// Measured hard-reference slope over the nominal (piezo gain / sensitivity): ≈ 1.
    pub sensitivity_ratio: f64,
    /// Drive → deflection response in contact on the sample: (Hz, |G| V/V, phase rad).
    pub sample_response: Vec<(f64, f64, f64)>,
}

/// The whole run.
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    pub status: String,
    pub converged: bool,
    pub config: String,
    pub directory: String,
    pub calibration: Calibration,
    pub iterations: Vec<IterationRecord>,
    pub measurement_time_s: f64,
    pub wall_time_s: f64,
    pub retracted: bool,
    pub safety: SafetyStats,
    pub warnings: Vec<String>,
    pub error: Option<String>,
    /// The twin's material (simulated runs).
    pub truth: Option<PronySeries>,
    #[serde(skip)]
    pub sample_rate_hz: f64,
}

impl RunReport {
    pub fn new(cfg: &SimConfigFile, dir: &Path) -> Self {
        Self {
            status: "running".into(),
            converged: false,
            config: String::new(),
            directory: dir.display().to_string(),
            calibration: Calibration::default(),
            iterations: Vec::new(),
            measurement_time_s: 0.0,
            wall_time_s: 0.0,
            retracted: false,
            safety: SafetyStats::default(),
            warnings: Vec::new(),
            error: None,
            truth: Some(cfg.twin.sample.material.clone()),
            sample_rate_hz: cfg.instrument.sample_rate_hz,
        }
    }

    /// Marks a run that ended without error.
    pub fn finish(&mut self, cfg: &SimConfigFile) {
        if self.status == "running" {
            self.status = "completed".into();
        }
        if !self.converged && self.status == "completed" {
            self.warnings.push(format!(
                "not converged after {} iterations (run.max_iterations): the last estimate is reported",
                cfg.run.max_iterations
            ));
        }
    }

    pub fn last(&self) -> Option<&IterationRecord> {
        self.iterations.last()
    }

    /// The JSON of `report.json`.
    pub fn to_json(&self) -> Value {
        let names = |n: usize| PronySeries::param_names(n);
        let obj = |names: &[String], v: &[f64]| -> Value {
            Value::Object(
                names
                    .iter()
                    .cloned()
                    .zip(v.iter().map(|x| json!(x)))
                    .collect::<Map<_, _>>(),
            )
        };
        let mut out = json!({
            "status": self.status,
            "converged": self.converged,
            "iterations": self.iterations.len(),
            "measurement_time_s": self.measurement_time_s,
            "wall_time_s": self.wall_time_s,
            "retracted": self.retracted,
            "units": {"J": "1/Pa", "tau": "s", "moduli": "Pa", "freq": "Hz", "tracking": "percent of the desired force's AC part"},
            "calibration": self.calibration,
            "safety": self.safety,
            "warnings": self.warnings,
            "error": self.error,
            "history": self.iterations,
        });
        if let Some(last) = self.last() {
            let n = names((last.params.len() - 1) / 2);
            out["params"] = obj(&n, &last.params);
            out["std"] = obj(&n, &last.std);
            out["ci95"] = Value::Object(
                n.iter()
                    .cloned()
                    .zip(last.ci95.iter().map(|c| json!(c)))
                    .collect(),
            );
            out["tracking"] = json!(last.tracking);
            if let Some(est) = &last.estimate {
                out["moduli"] = moduli_json(est);
            }
            if let Some(truth) = &self.truth {
                if truth.order() * 2 + 1 == last.params.len() {
                    let tv = truth.to_vec();
                    let err: Vec<f64> = tv
                        .iter()
                        .zip(&last.params)
                        .map(|(t, e)| 100.0 * (e - t) / t)
                        .collect();
                    let covered: Vec<Value> = tv
                        .iter()
                        .zip(&last.ci95)
                        .map(|(t, c)| json!(c[0] <= *t && *t <= c[1]))
                        .collect();
                    out["truth"] = obj(&n, &tv);
                    out["error_pct"] = obj(&n, &err);
                    out["truth_in_ci95"] = Value::Object(n.iter().cloned().zip(covered).collect());
                }
            }
        }
        out
    }

    /// Writes `report.json` and `report.md` through temporary files.
    pub fn write(&self, dir: &Path) -> anyhow::Result<()> {
        write_atomic(
            &dir.join("report.json"),
            serde_json::to_string_pretty(&self.to_json())?.as_bytes(),
        )?;
        write_atomic(&dir.join("report.md"), self.markdown().as_bytes())?;
        Ok(())
    }

    fn markdown(&self) -> String {
        let mut m = String::new();
        m.push_str(&format!("# viscoprobe run — {}\n\n", self.status));
        m.push_str(&format!(
            "- converged: **{}** after {} design iteration(s)\n- measurement time: {:.2} s (simulated instrument time), wall time {:.2} s\n- actuator retracted at the end: {}\n",
            self.converged,
            self.iterations.len(),
            self.measurement_time_s,
            self.wall_time_s,
            self.retracted
        ));
        if let Some(e) = &self.error {
            m.push_str(&format!("- **error:** {e}\n"));
        }
        for w in &self.warnings {
            m.push_str(&format!("- warning: {w}\n"));
        }
        if let Some(last) = self.last() {
            let n = PronySeries::param_names((last.params.len() - 1) / 2);
            m.push_str("\n## Estimate (final iteration, all acquisitions pooled)\n\n| param | estimate | 95 % interval | truth | error % |\n|---|---|---|---|---|\n");
            let tv = self.truth.as_ref().map(|t| t.to_vec());
            for (i, name) in n.iter().enumerate() {
                let (scale, unit) = crate::output::param_unit(name);
                let truth = tv.as_ref().filter(|t| t.len() == n.len()).map(|t| t[i]);
                m.push_str(&format!(
                    "| {name} | {:.4} {unit} | [{:.4}, {:.4}] | {} | {} |\n",
                    last.params[i] * scale,
                    last.ci95[i][0] * scale,
                    last.ci95[i][1] * scale,
                    truth.map_or("—".into(), |t| format!("{:.4}", t * scale)),
                    truth.map_or("—".into(), |t| format!(
                        "{:+.2}",
                        100.0 * (last.params[i] - t) / t
                    )),
                ));
            }
            if let Some(est) = &last.estimate {
                m.push_str(&format!(
                    "\nInstantaneous modulus {:.3} MPa, relaxed modulus {:.3} MPa.\n",
                    est.model.instantaneous_modulus() / 1e6,
                    est.model.relaxed_modulus() / 1e6
                ));
            }
        }
        m.push_str("\n## Iterations\n\n| it | lines (Hz) | MIIC steps | err₂ % | err∞ % | change % |\n|---|---|---|---|---|---|\n");
        for it in &self.iterations {
            m.push_str(&format!(
                "| {} | {} | {} | {:.2} | {:.2} | {} |\n",
                it.iteration,
                it.lines
                    .iter()
                    .map(|l| format!("{}", l.freq_hz))
                    .collect::<Vec<_>>()
                    .join(", "),
                it.miic.len(),
                it.tracking.err2_pct,
                it.tracking.errinf_pct,
                it.rel_change
                    .map_or("—".into(), |r| format!("{:.3}", 100.0 * r))
            ));
        }
        m.push_str("\nPlots: `convergence.svg`, `moduli.svg`, `tracking.svg`, `design.svg`. Acquisitions: `iter-NN.csv` + `.toml` (recording/1).\n");
        m
    }
}

/// The band a run's report tabulates its moduli over, Hz.
pub const REPORT_BAND_HZ: (f64, f64) = (0.1, 1e4);

/// E′, E″ and tan δ on a 41-point log grid over `band_hz` with 95 % bands (delta method on the
/// estimate's covariance): rows `[f_Hz, E′, ±E′, E″, ±E″, tan δ, ±tan δ]`, Pa.
pub fn moduli_table(est: &Estimate, band_hz: (f64, f64)) -> Vec<[f64; 7]> {
    let v = est.values();
    let cov = &est.covariance;
    let (lo, hi) = band_hz;
    let grid: Vec<f64> = (0..=40)
        .map(|i| lo * (hi / lo).powf(i as f64 / 40.0))
        .collect();
    grid.iter()
        .map(|&f| {
            let w = 2.0 * std::f64::consts::PI * f;
            let eval = |p: &[f64]| {
                let m = PronySeries::from_vec(p);
                let e = m.complex_modulus(w);
                [e.re, e.im, e.im / e.re]
            };
            let base = eval(&v);
            let mut var = [0.0; 3];
            let grads: Vec<[f64; 3]> = (0..v.len())
                .map(|i| {
                    let h = 1e-6 * v[i].abs().max(1e-30);
                    let mut up = v.clone();
                    up[i] += h;
                    let e = eval(&up);
                    [
                        (e[0] - base[0]) / h,
                        (e[1] - base[1]) / h,
                        (e[2] - base[2]) / h,
                    ]
                })
                .collect();
            for (i, gi) in grads.iter().enumerate() {
                for (j, gj) in grads.iter().enumerate() {
                    for q in 0..3 {
                        var[q] += gi[q] * cov[(i, j)] * gj[q];
                    }
                }
            }
            let z = viscoprobe_core::estimate::Z95;
            [
                f,
                base[0],
                z * var[0].sqrt(),
                base[1],
                z * var[1].sqrt(),
                base[2],
                z * var[2].sqrt(),
            ]
        })
        .collect()
}

fn moduli_json(est: &Estimate) -> Value {
    let rows = moduli_table(est, REPORT_BAND_HZ);
    json!({
        "instantaneous_modulus_pa": est.model.instantaneous_modulus(),
        "relaxed_modulus_pa": est.model.relaxed_modulus(),
        "freq_hz": rows.iter().map(|r| r[0]).collect::<Vec<_>>(),
        "storage_pa": rows.iter().map(|r| r[1]).collect::<Vec<_>>(),
        "storage_ci95_halfwidth_pa": rows.iter().map(|r| r[2]).collect::<Vec<_>>(),
        "loss_pa": rows.iter().map(|r| r[3]).collect::<Vec<_>>(),
        "loss_ci95_halfwidth_pa": rows.iter().map(|r| r[4]).collect::<Vec<_>>(),
        "tan_delta": rows.iter().map(|r| r[5]).collect::<Vec<_>>(),
        "tan_delta_ci95_halfwidth": rows.iter().map(|r| r[6]).collect::<Vec<_>>(),
    })
}

/// Writes a file through a temporary name and a rename, so readers never see half of it.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let tmp = path.with_extension("partial");
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)?;
    Ok(())
}
