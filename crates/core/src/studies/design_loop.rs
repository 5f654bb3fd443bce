//! The paper's Sec. II-B iteration closed on a simulated, instrument-free measurement: start
//! from the initial design F0, then design → measure → estimate → redesign until the
//! parameters stop moving. Table I Case 3 is the outcome of this loop.

use super::table1::{self, Experiment};
use super::{rms, steady_state_response, white_noise};
use crate::design::{
    DesignConfig, DesignError, DesignLine, DesignLoop, Level, LoopConfig, LoopStep, SynthConfig,
};
use crate::discrete::Sampling;
use crate::estimate::frequency::{
    fit_spectra, periodic_spectra, pool_spectra, FrequencyFitOptions, PeriodicSpectra,
};
use crate::estimate::{Estimate, EstimateError};
use crate::fisher::{fisher_multisine, relative_crlb, Line, NoiseSpectrum};
use crate::prony::PronySeries;
use thiserror::Error;

/// One completed iteration.
#[derive(Debug, Clone)]
pub struct LoopIteration {
    /// The excitation's lines (Hz, power fraction).
    pub lines: Vec<(f64, f64)>,
    pub estimate: Estimate,
    /// The simulated measurement of this iteration.
    pub experiment: Experiment,
    /// Relative parameter change from the model the excitation was designed for (the first
    /// iteration, measured with F0, has none).
    pub rel_change: Option<f64>,
}

/// The whole loop.
#[derive(Debug, Clone)]
pub struct LoopStudy {
    pub iterations: Vec<LoopIteration>,
    pub converged: bool,
}

impl LoopStudy {
    pub fn final_estimate(&self) -> &Estimate {
        &self
            .iterations
            .last()
            .expect("a study has at least one iteration")
            .estimate
    }

    /// Relative CRLB at `truth` of the pooled estimate: the Fisher information of every
    /// measurement, with its true noise, summed.
    pub fn pooled_crlb(&self, truth: &PronySeries) -> Option<Vec<f64>> {
        let p = truth.n_params();
        let mut fim = nalgebra::DMatrix::<f64>::zeros(p, p);
        for it in &self.iterations {
            let e = &it.experiment;
            let lines: Vec<Line> = e
                .lines
                .iter()
                .map(|&(f, a)| Line {
                    freq_hz: f,
                    amplitude: a,
                })
                .collect();
            fim += fisher_multisine(
                truth,
                &Sampling::Tustin {
                    fs_hz: table1::FS_HZ,
                },
                &lines,
                e.u.len(),
                &NoiseSpectrum::White { std: e.noise_std },
            );
        }
        relative_crlb(&fim)
    }
}

/// Why the loop stopped early.
#[derive(Debug, Error)]
pub enum LoopStudyError {
    #[error("design: {0}")]
    Design(#[from] DesignError),
    #[error("estimation in iteration {iteration}: {error}")]
    Estimate {
        iteration: usize,
        error: EstimateError,
    },
}

/// Settings of the study.
#[derive(Debug, Clone)]
pub struct LoopStudySettings {
    /// Search band, Hz.
    pub band_hz: (f64, f64),
    /// Output SNR, rms(y)/rms(noise).
    pub snr: f64,
    /// Iteration limit (F0 measurement included).
    pub max_iterations: usize,
    /// Convergence threshold on the relative parameter change.
    pub rel_change_tol: f64,
}

impl Default for LoopStudySettings {
    fn default() -> Self {
        Self {
            band_hz: (0.5, 2000.0),
            snr: table1::SNR_CASE2,
            max_iterations: 8,
            rel_change_tol: 0.005,
        }
    }
}

/// The initial design F0 = {1, 10, 30, 60} Hz at equal power.
pub fn initial_design() -> Vec<(f64, f64)> {
    vec![(1.0, 0.25), (10.0, 0.25), (30.0, 0.25), (60.0, 0.25)]
}

fn measure(
    truth: &PronySeries,
    u: &[f64],
    lines: Vec<(f64, f64)>,
    snr: f64,
    seed: u64,
) -> Experiment {
    let np = u.len() / table1::PERIODS;
    let y_clean = steady_state_response(truth, &u[..np], table1::PERIODS, table1::FS_HZ);
    let std = rms(&y_clean) / snr;
    let y = y_clean
        .iter()
        .zip(white_noise(y_clean.len(), std, seed))
        .map(|(a, b)| a + b)
        .collect();
    Experiment {
        u: u.to_vec(),
        y,
        noise_std: std,
        lines,
    }
}

/// Runs the loop on `truth` with seeds `seed`, `seed + 1`, … for the successive measurements.
/// The total input power is that of the paper's Case 1 input throughout. Each iteration's
/// estimate uses the lines of every measurement so far ([`pool_spectra`]): information
/// accumulates, so the estimates settle instead of jittering at one record's CRLB.
pub fn run(
    truth: &PronySeries,
    settings: &LoopStudySettings,
    seed: u64,
) -> Result<LoopStudy, LoopStudyError> {
    let order = truth.order();
    let opts = FrequencyFitOptions::new(order, table1::FS_HZ, table1::PERIODS);
    let mut pooled: Vec<PeriodicSpectra> = Vec::new();
    let mut fit = |exp: &Experiment, iteration: usize| {
        let err = |error| LoopStudyError::Estimate { iteration, error };
        let spectra = periodic_spectra(
            &exp.u,
            &exp.y,
            table1::FS_HZ,
            table1::PERIODS,
            &opts.lines,
            opts.noise_smoothing_bins,
        )
        .map_err(err)?;
        pooled.push(spectra);
        let all = pool_spectra(&pooled).expect("same sample rate throughout");
        fit_spectra(&all, &opts).map_err(err)
    };
    // Iteration 1: the initial design F0, nothing known about the material.
    let f0 = table1::amplitudes_at_case1_power(&initial_design());
    let np = (table1::FS_HZ * table1::DURATION_S) as usize / table1::PERIODS;
    let u_period = super::sum_of_sines(&f0, table1::FS_HZ, 0, np);
    let u0: Vec<f64> = u_period
        .iter()
        .copied()
        .cycle()
        .take(np * table1::PERIODS)
        .collect();
    let exp0 = measure(truth, &u0, f0, settings.snr, seed);
    let first = fit(&exp0, 1)?;
    let power: f64 = table1::amplitudes_at_case1_power(&initial_design())
        .iter()
        .map(|(_, a)| a * a / 2.0)
        .sum();
    let mut design = DesignConfig::new(settings.band_hz);
    design.initial = initial_design()
        .iter()
        .map(|&(f, p)| DesignLine {
            freq_hz: f,
            power_frac: p,
        })
        .collect();
    let synth = SynthConfig {
        level: Level::Rms(power.sqrt()),
        ..SynthConfig::default()
    };
    let mut cfg = LoopConfig::new(design, synth);
    cfg.rel_change_tol = settings.rel_change_tol;
    cfg.max_iterations = settings.max_iterations.saturating_sub(1).max(1);
    let mut iterations = vec![LoopIteration {
        lines: initial_design(),
        estimate: first.clone(),
        experiment: exp0,
        rel_change: None,
    }];
    let mut lp = DesignLoop::new(first.model.clone(), cfg)?;
    let mut converged = false;
    loop {
        let exc = lp.next_excitation()?.clone();
        let lines: Vec<(f64, f64)> = exc
            .design
            .lines
            .iter()
            .map(|l| (l.freq_hz, l.power_frac))
            .collect();
        let sig_lines = exc
            .signal
            .lines
            .iter()
            .map(|l| (l.freq_hz, l.amplitude))
            .collect();
        let iteration = iterations.len() + 1;
        let exp = measure(
            truth,
            &exc.signal.samples,
            sig_lines,
            settings.snr,
            seed + iteration as u64,
        );
        let est = fit(&exp, iteration)?;
        let step = lp.feed(est.model.clone())?;
        iterations.push(LoopIteration {
            lines,
            estimate: est,
            experiment: exp,
            rel_change: Some(step.rel_change()),
        });
        match step {
            LoopStep::Continue { .. } => continue,
            LoopStep::Converged { .. } => {
                converged = true;
                break;
            }
            LoopStep::IterationLimit { .. } => break,
        }
    }
    Ok(LoopStudy {
        iterations,
        converged,
    })
}
