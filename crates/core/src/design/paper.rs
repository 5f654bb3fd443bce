//! The paper's Table II design next to the same search and a wide-band design.
//!
//! Every row is evaluated for the same experiment: the true model, Tustin at 8 kHz, 2 s
//! (16 000 samples), the same total input power `P = 1` (unit rms of u's AC part), and the same
//! white output noise: the paper's Case 2 level, `σ = rms(y)/134.3` with `y` the output of the
//! Case 1/2 input (1, 10, 100, 1000 Hz at 25 % each) at that power. Relative bounds scale as
//! `σ/sqrt(P·N)`, so the ratios between rows do not depend on these choices.

use super::optimal::{d_max_over_p, d_optimal, predicted_crlb};
use super::{DesignConfig, DesignError, DesignLine};
use crate::fisher::NoiseSpectrum;
use crate::prony::PronySeries;
use serde::Serialize;

/// The paper's Table II: 1, 10, 30, 60, 83, 92, 79, 93 Hz at 25, 25, 10.7, 10.7, 7.15 ×4 %.
pub fn paper_table2_design() -> Vec<DesignLine> {
    [
        (1.0, 25.0),
        (10.0, 25.0),
        (30.0, 10.7),
        (60.0, 10.7),
        (83.0, 7.15),
        (92.0, 7.15),
        (79.0, 7.15),
        (93.0, 7.15),
    ]
    .iter()
    .map(|&(f, pct)| DesignLine {
        freq_hz: f,
        power_frac: pct / 100.0,
    })
    .collect()
}

/// The paper's Case 1/2 input: 1, 10, 100, 1000 Hz, equal power.
pub fn paper_case1_design() -> Vec<DesignLine> {
    [1.0, 10.0, 100.0, 1000.0]
        .iter()
        .map(|&f| DesignLine {
            freq_hz: f,
            power_frac: 0.25,
        })
        .collect()
}

/// One design of the comparison.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Table2Row {
    pub label: String,
    /// The band whose candidate grid `d_max_over_p` refers to, Hz.
    pub band_hz: (f64, f64),
    /// Lines in the order given (the paper's own order for Table II).
    pub lines: Vec<DesignLine>,
    /// `max d(f)/p` over the band's grid (1 = D-optimal there).
    pub d_max_over_p: f64,
    /// Search iterations, for the rows computed here.
    pub iterations: Option<usize>,
    /// Relative Cramér–Rao bounds, canonical order (fractions; `None` if not identifiable).
    pub crlb_rel: Option<Vec<f64>>,
}

/// The full comparison.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Table2Comparison {
    /// Canonical parameter names (`J0 … tau3`).
    pub param_names: Vec<String>,
    pub fs_hz: f64,
    pub duration_s: f64,
    pub n_samples: usize,
    /// Total AC input power, units of u² (rms of u = 1).
    pub total_power: f64,
    /// White output noise std, units of y.
    pub noise_std: f64,
    /// `rms(y)/σ` of the reference (Case 1/2) input.
    pub snr: f64,
    /// Case 1/2 input, Table II, the [1, 100] Hz search, the [0.5, 2000] Hz search.
    pub rows: Vec<Table2Row>,
}

/// Runs the paper's [1, 100] Hz search from F0 = {1, 10, 30, 60} Hz (α_k = 1/(k+3), Tustin
/// 8 kHz, 2 s) and the wide-band 0.5–2000 Hz search on `truth`, and evaluates both next to
/// the paper's Table II and Case 1/2 inputs at equal power and noise.
pub fn table2_comparison(truth: &PronySeries) -> Result<Table2Comparison, DesignError> {
    let narrow = DesignConfig::new((1.0, 100.0));
    let wide = DesignConfig::new((0.5, 2000.0));
    let sampling = narrow.sampling();
    let n = narrow.n_samples();
    let total_power = 1.0;
    let snr = 134.3;
    // Output rms of the Case 1/2 input at power P: sqrt(Σ A²|G|²/2) = sqrt(Σ P p |G|²).
    let y_rms = paper_case1_design()
        .iter()
        .map(|l| total_power * l.power_frac * sampling.response(truth, l.freq_hz).norm_sqr())
        .sum::<f64>()
        .sqrt();
    let noise_std = y_rms / snr;
    let noise = NoiseSpectrum::White { std: noise_std };
    let crlb =
        |lines: &[DesignLine]| predicted_crlb(truth, &sampling, lines, total_power, n, &noise);

    let mut rows = Vec::new();
    let case1 = paper_case1_design();
    rows.push(Table2Row {
        label: "Case 1/2 input (paper F0)".into(),
        band_hz: wide.band_hz,
        d_max_over_p: d_max_over_p(truth, &wide, &case1)?,
        iterations: None,
        crlb_rel: crlb(&case1),
        lines: case1,
    });
    let t2 = paper_table2_design();
    rows.push(Table2Row {
        label: "Table II (paper)".into(),
        band_hz: narrow.band_hz,
        d_max_over_p: d_max_over_p(truth, &narrow, &t2)?,
        iterations: None,
        crlb_rel: crlb(&t2),
        lines: t2,
    });
    for (label, cfg) in [
        ("D-optimal, paper's search [1, 100] Hz", &narrow),
        ("D-optimal, wide band [0.5, 2000] Hz", &wide),
    ] {
        let d = d_optimal(truth, cfg)?;
        rows.push(Table2Row {
            label: label.into(),
            band_hz: cfg.band_hz,
            d_max_over_p: d.d_max_over_p,
            iterations: Some(d.iterations),
            crlb_rel: crlb(&d.lines),
            lines: d.lines,
        });
    }
    Ok(Table2Comparison {
        param_names: PronySeries::param_names(truth.order()),
        fs_hz: narrow.fs_hz,
        duration_s: narrow.duration_s,
        n_samples: n,
        total_power,
        noise_std,
        snr,
        rows,
    })
}
