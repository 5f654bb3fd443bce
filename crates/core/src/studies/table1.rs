//! The paper's Table I (and the efficiency study at its Case 2 conditions).
//!
//! fs = 8 kHz, a 2 s record of two 1 s periods, the PDMS truth of Table I, and band-limited
//! white output noise (discrete white noise, band-limited by sampling — Simulink's
//! "Band-Limited White Noise") with SNR = rms(y)/rms(noise).

use super::{rms, steady_state_response, sum_of_sines, white_noise};
use crate::discrete::Sampling;
use crate::estimate::arx::fit_arx;
use crate::estimate::frequency::{fit_periodic, FrequencyFitOptions};
use crate::estimate::{Estimate, EstimateError};
use crate::fisher::{fisher_multisine, relative_crlb, Line, NoiseSpectrum};
use crate::prony::PronySeries;

/// Sample rate of the paper's simulations, Hz.
pub const FS_HZ: f64 = 8000.0;
/// Record length, s.
pub const DURATION_S: f64 = 2.0;
/// Whole periods in the record.
pub const PERIODS: usize = 2;
/// Force amplitude A of the paper's input `u = A Σ αi sin(2π fi t)`, N (10 nN).
pub const FORCE_AMPLITUDE_N: f64 = 10e-9;
/// Tip radius used to turn force into u, m.
pub const TIP_RADIUS_M: f64 = 20e-9;
/// SNR of Case 2 and Case 3.
pub const SNR_CASE2: f64 = 134.3;
pub const SNR_CASE3: f64 = 146.7;

/// The input of Cases 1 and 2: F0 = {(1, .25), (10, .25), (100, .25), (1000, .25)} Hz.
pub fn case1_design() -> Vec<(f64, f64)> {
    vec![(1.0, 0.25), (10.0, 0.25), (100.0, 0.25), (1000.0, 0.25)]
}

/// Sine amplitudes (units of u) for a design given as (Hz, power fraction), at the total
/// input power of the paper's Case 1 input (four sines of amplitude A/4).
pub fn amplitudes_at_case1_power(design: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let a = u_per_newton() * FORCE_AMPLITUDE_N * 0.25;
    let total_power = 4.0 * a * a / 2.0;
    let sum: f64 = design.iter().map(|d| d.1).sum();
    design
        .iter()
        .map(|&(f, p)| (f, (2.0 * total_power * p / sum).sqrt()))
        .collect()
}

/// `u = 9P/(16√R)` per newton of force.
pub fn u_per_newton() -> f64 {
    crate::contact::Contact::sphere(TIP_RADIUS_M).force_factor()
}

/// One simulated experiment.
#[derive(Debug, Clone)]
pub struct Experiment {
    pub u: Vec<f64>,
    pub y: Vec<f64>,
    /// Per-sample output noise standard deviation actually used (0 without noise).
    pub noise_std: f64,
    /// The sine lines (Hz, amplitude in u).
    pub lines: Vec<(f64, f64)>,
}

/// Simulates `truth` under the sine `lines` (Hz, amplitude) with the given SNR.
pub fn simulate(
    truth: &PronySeries,
    lines: &[(f64, f64)],
    snr: Option<f64>,
    seed: u64,
) -> Experiment {
    let np = (FS_HZ * DURATION_S) as usize / PERIODS;
    let u_period = sum_of_sines(lines, FS_HZ, 0, np);
    let y_clean = steady_state_response(truth, &u_period, PERIODS, FS_HZ);
    let u: Vec<f64> = u_period
        .iter()
        .copied()
        .cycle()
        .take(np * PERIODS)
        .collect();
    let (y, noise_std) = match snr {
        None => (y_clean, 0.0),
        Some(snr) => {
            let std = rms(&y_clean) / snr;
            let noise = white_noise(y_clean.len(), std, seed);
            (y_clean.iter().zip(noise).map(|(a, b)| a + b).collect(), std)
        }
    };
    Experiment {
        u,
        y,
        noise_std,
        lines: lines.to_vec(),
    }
}

/// Relative CRLB (fractions) of `truth` under an experiment's lines and noise.
pub fn crlb(truth: &PronySeries, exp: &Experiment) -> Option<Vec<f64>> {
    if exp.noise_std == 0.0 {
        return None;
    }
    let lines: Vec<Line> = exp
        .lines
        .iter()
        .map(|&(f, a)| Line {
            freq_hz: f,
            amplitude: a,
        })
        .collect();
    let fim = fisher_multisine(
        truth,
        &Sampling::Tustin { fs_hz: FS_HZ },
        &lines,
        exp.u.len(),
        &NoiseSpectrum::White { std: exp.noise_std },
    );
    relative_crlb(&fim)
}

/// The ML estimator as configured for these studies.
pub fn fit_ml(exp: &Experiment, order: usize) -> Result<Estimate, EstimateError> {
    fit_periodic(
        &exp.u,
        &exp.y,
        FS_HZ,
        &FrequencyFitOptions::new(order, FS_HZ, PERIODS),
    )
}

/// The paper's ARX estimator (na = n, nb = n + 1).
pub fn fit_paper_arx(exp: &Experiment, order: usize) -> Result<Estimate, EstimateError> {
    fit_arx(&exp.u, &exp.y, FS_HZ, order)
}

/// Signed percent errors of `est` (canonical order) against `truth`.
pub fn error_pct(truth: &PronySeries, est: &[f64]) -> Vec<f64> {
    truth
        .to_vec()
        .iter()
        .zip(est)
        .map(|(t, e)| 100.0 * (e - t) / t)
        .collect()
}

/// One case of Table I: its experiment and both estimators' results.
#[derive(Debug, Clone)]
pub struct CaseResult {
    pub name: &'static str,
    pub description: String,
    pub snr: Option<f64>,
    pub lines: Vec<(f64, f64)>,
    pub crlb_rel: Option<Vec<f64>>,
    pub arx: ArxOutcome,
    pub ml: Result<Estimate, EstimateError>,
}

/// What the paper's ARX procedure gives on one experiment.
#[derive(Debug, Clone)]
pub struct ArxOutcome {
    /// The ARX estimator proper: an estimate, or why there is none.
    pub estimate: Result<Estimate, EstimateError>,
    /// The values the paper's procedure prints (`d2c` + `residue` in complex arithmetic,
    /// real parts), canonical order — present even when the poles came out complex.
    pub paper_values: Option<Vec<f64>>,
    /// True when the least-squares model has complex poles.
    pub complex_poles: bool,
}

/// Runs the paper's ARX procedure on an experiment.
pub fn arx_outcome(exp: &Experiment, order: usize) -> ArxOutcome {
    let estimate = fit_paper_arx(exp, order);
    let (paper_values, complex_poles) =
        match crate::estimate::arx::arx_least_squares(&exp.u, &exp.y, FS_HZ, order) {
            Ok(fit) => match crate::discrete::d2c_complex(&fit.tf) {
                Ok((j0, terms)) => {
                    let complex = terms.iter().any(|t| t.tau.im.abs() > 1e-12 * t.tau.norm());
                    let mut v = vec![j0];
                    v.extend(terms.iter().map(|t| t.j.re));
                    v.extend(terms.iter().map(|t| t.tau.re));
                    (Some(v), complex)
                }
                Err(_) => (None, false),
            },
            Err(_) => (None, false),
        };
    ArxOutcome {
        estimate,
        paper_values,
        complex_poles,
    }
}

/// Runs one case.
pub fn run_case(
    name: &'static str,
    description: String,
    truth: &PronySeries,
    design: &[(f64, f64)],
    snr: Option<f64>,
    seed: u64,
) -> CaseResult {
    let lines = amplitudes_at_case1_power(design);
    let exp = simulate(truth, &lines, snr, seed);
    CaseResult {
        name,
        description,
        snr,
        crlb_rel: crlb(truth, &exp),
        arx: arx_outcome(&exp, truth.order()),
        ml: fit_ml(&exp, truth.order()),
        lines,
    }
}

/// Per-parameter result of the efficiency study.
#[derive(Debug, Clone)]
pub struct EfficiencyRow {
    pub name: String,
    /// Relative CRLB (fraction).
    pub crlb_rel: f64,
    /// Empirical relative standard deviation over the runs (fraction).
    pub std_rel: f64,
    /// Empirical mean relative error (fraction): the bias.
    pub mean_rel: f64,
}

/// Efficiency study: `runs` noise seeds at Case 2 conditions, ML estimator.
#[derive(Debug, Clone)]
pub struct Efficiency {
    pub runs: usize,
    pub failures: usize,
    pub rows: Vec<EfficiencyRow>,
}

/// Runs the ML fit on `runs` seeds (`seed0`, `seed0 + 1`, …); `progress` is called after each.
pub fn efficiency(runs: usize, seed0: u64, mut progress: impl FnMut(usize)) -> Efficiency {
    let truth = PronySeries::paper_pdms();
    let lines = amplitudes_at_case1_power(&case1_design());
    let names = PronySeries::param_names(truth.order());
    let tv = truth.to_vec();
    let mut errs: Vec<Vec<f64>> = vec![Vec::new(); tv.len()];
    let mut failures = 0;
    let mut crlb_rel = vec![f64::NAN; tv.len()];
    for r in 0..runs {
        let exp = simulate(&truth, &lines, Some(SNR_CASE2), seed0 + r as u64);
        if r == 0 {
            crlb_rel = crlb(&truth, &exp).unwrap_or(crlb_rel);
        }
        match fit_ml(&exp, truth.order()) {
            Ok(est) => {
                for (i, v) in est.values().iter().enumerate() {
                    errs[i].push((v - tv[i]) / tv[i]);
                }
            }
            Err(_) => failures += 1,
        }
        progress(r + 1);
    }
    let rows = names
        .into_iter()
        .enumerate()
        .map(|(i, name)| {
            let e = &errs[i];
            let k = e.len().max(1) as f64;
            let mean = e.iter().sum::<f64>() / k;
            let var = e.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (k - 1.0).max(1.0);
            EfficiencyRow {
                name,
                crlb_rel: crlb_rel[i],
                std_rel: var.sqrt(),
                mean_rel: mean,
            }
        })
        .collect();
    Efficiency {
        runs,
        failures,
        rows,
    }
}

/// Case 3: the D-optimal design loop over 0.5–2000 Hz from F0 = {1, 10, 30, 60} Hz, output SNR
/// 146.7. ML reports the loop's final (pooled) estimate, ARX its fit of the last record.
pub fn run_case3(truth: &PronySeries, seed: u64) -> CaseResult {
    use super::design_loop::{run, LoopStudySettings};
    let settings = LoopStudySettings {
        snr: SNR_CASE3,
        ..LoopStudySettings::default()
    };
    match run(truth, &settings, seed) {
        Ok(study) => {
            let last = study.iterations.last().expect("at least one iteration");
            let n = study.iterations.len();
            CaseResult {
                name: "case3",
                description: format!(
                    "D-optimal design loop over {}–{} Hz from F0 = {{1, 10, 30, 60}} Hz, output noise SNR {SNR_CASE3}: \
                     {} after {n} iterations ({} s of data in all); ML pools every record",
                    settings.band_hz.0,
                    settings.band_hz.1,
                    if study.converged { "converged" } else { "NOT converged" },
                    n as f64 * DURATION_S
                ),
                snr: Some(SNR_CASE3),
                lines: last.experiment.lines.clone(),
                crlb_rel: study.pooled_crlb(truth),
                arx: arx_outcome(&last.experiment, truth.order()),
                ml: Ok(study.final_estimate().clone()),
            }
        }
        Err(e) => CaseResult {
            name: "case3",
            description: format!("D-optimal design loop failed: {e}"),
            snr: Some(SNR_CASE3),
            lines: vec![],
            crlb_rel: None,
            arx: ArxOutcome {
                estimate: Err(EstimateError::NoExcitation("no record".into())),
                paper_values: None,
                complex_poles: false,
            },
            ml: Err(match e {
                super::design_loop::LoopStudyError::Estimate { error, .. } => error,
                other => EstimateError::NoExcitation(other.to_string()),
            }),
        },
    }
}

/// All three cases of Table I with one noise seed.
pub fn all_cases(truth: &PronySeries, seed: u64) -> Vec<CaseResult> {
    vec![
        run_case(
            "case1",
            "Case 1 input (1, 10, 100, 1000 Hz, equal amplitudes), no noise".into(),
            truth,
            &case1_design(),
            None,
            seed,
        ),
        run_case(
            "case2",
            format!("Case 1 input, band-limited white output noise, SNR {SNR_CASE2}"),
            truth,
            &case1_design(),
            Some(SNR_CASE2),
            seed,
        ),
        run_case3(truth, seed),
    ]
}
