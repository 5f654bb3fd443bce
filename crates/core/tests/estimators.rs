//! Estimator behaviour on analytic and simulated cases.

use viscoprobe_core::discrete::simulate_tustin;
use viscoprobe_core::estimate::arx::fit_arx;
use viscoprobe_core::estimate::frequency::{fit_periodic, FrequencyFitOptions};
use viscoprobe_core::estimate::time_domain::{fit_time_domain, TimeFitOptions};
use viscoprobe_core::estimate::EstimateError;
use viscoprobe_core::prony::{PronySeries, PronyTerm};
use viscoprobe_core::studies::{rms, steady_state_response, sum_of_sines, white_noise};

const FS: f64 = 8000.0;

/// A ramp to `peak` over `ramp_s`, then a hold: a creep test.
fn ramp_hold(peak: f64, ramp_s: f64, total_s: f64) -> Vec<f64> {
    let n = (total_s * FS) as usize;
    (0..n)
        .map(|i| (i as f64 / FS / ramp_s).min(1.0) * peak)
        .collect()
}

/// Three lines cannot identify seven parameters: the ML estimator says so.
#[test]
fn ml_refuses_under_determined_data() {
    let truth = PronySeries::paper_pdms();
    let np = 8000;
    let u = sum_of_sines(&[(1.0, 1.0), (10.0, 1.0), (100.0, 1.0)], FS, 0, np);
    let y = steady_state_response(&truth, &u, 2, FS);
    let u2: Vec<f64> = u.iter().copied().cycle().take(2 * np).collect();
    let err = fit_periodic(&u2, &y, FS, &FrequencyFitOptions::new(3, FS, 2)).unwrap_err();
    match err {
        EstimateError::UnderDetermined {
            lines,
            params,
            needed,
            ..
        } => {
            assert_eq!((lines, params, needed), (3, 7, 4));
        }
        other => panic!("expected UnderDetermined, got {other}"),
    }
    assert!(err.to_string().contains("needs at least 4 lines"), "{err}");
}

/// Bad input is refused with a reason, never a panic.
#[test]
fn estimators_refuse_bad_input() {
    let u = vec![1.0; 1000];
    let mut y = vec![0.0; 1000];
    assert!(matches!(
        fit_time_domain(&u, &y, FS, &TimeFitOptions::new(1)),
        Err(EstimateError::NoExcitation(_))
    ));
    assert!(matches!(
        fit_arx(&u[..10], &y, FS, 1),
        Err(EstimateError::LengthMismatch { .. })
    ));
    y[17] = f64::NAN;
    let u2: Vec<f64> = (0..1000).map(|i| (i as f64).sin()).collect();
    assert!(matches!(
        fit_arx(&u2, &y, FS, 1),
        Err(EstimateError::NonFinite(17))
    ));
    let y2 = u2.clone();
    assert!(matches!(
        fit_periodic(
            &u2[..999],
            &y2[..999],
            FS,
            &FrequencyFitOptions::new(1, FS, 2)
        ),
        Err(EstimateError::NotWholePeriods {
            samples: 999,
            periods: 2
        })
    ));
    assert!(matches!(
        fit_periodic(&u2, &y2, FS, &FrequencyFitOptions::new(0, FS, 2)),
        Err(EstimateError::Order(0))
    ));
    let zeros = vec![0.0; 1000];
    assert!(matches!(
        fit_periodic(&zeros, &y2, FS, &FrequencyFitOptions::new(1, FS, 2)),
        Err(EstimateError::NoExcitation(_))
    ));
}

/// Time-domain output error on a fast ramp-and-hold creep test recovers a two-term
/// material, and its 95 % intervals cover the truth.
#[test]
fn output_error_fits_ramp_and_hold() {
    let truth = PronySeries::new(
        5e-6,
        vec![
            PronyTerm {
                j_per_pa: 1.5e-6,
                tau_s: 0.2,
            },
            PronyTerm {
                j_per_pa: 1.0e-6,
                tau_s: 0.01,
            },
        ],
    );
    let u = ramp_hold(1e-3, 0.002, 2.0);
    let y_clean = simulate_tustin(&truth, &u, FS);
    let noise = white_noise(u.len(), rms(&y_clean) / 500.0, 7);
    let y: Vec<f64> = y_clean.iter().zip(&noise).map(|(a, b)| a + b).collect();
    let est = fit_time_domain(&u, &y, FS, &TimeFitOptions::new(2)).expect("OE fit");
    for (i, (t, e)) in truth.to_vec().iter().zip(est.values()).enumerate() {
        let rel = (e - t) / t;
        assert!(rel.abs() < 0.02, "param {i}: truth {t}, estimate {e}");
        let [lo, hi] = est.ci95[i];
        assert!(lo <= *t && *t <= hi, "param {i}: {t} outside [{lo}, {hi}]");
    }
    assert!(
        (est.diagnostics.cost_per_dof.sqrt() * rms(&y) - rms(&y_clean) / 500.0).abs()
            < 0.05 * rms(&y_clean) / 500.0
    );
}

/// On noise-free data ARX recovers a one-term material exactly, from a step.
#[test]
fn arx_is_exact_without_noise() {
    let truth = PronySeries::new(
        4e-6,
        vec![PronyTerm {
            j_per_pa: 1e-6,
            tau_s: 5e-3,
        }],
    );
    let u: Vec<f64> = (0..4000)
        .map(|i| if i < 100 { 0.0 } else { 1.0 } + 0.1 * ((i as f64) * 0.05).sin())
        .collect();
    let y = simulate_tustin(&truth, &u, FS);
    let est = fit_arx(&u, &y, FS, 1).unwrap();
    for (t, e) in truth.to_vec().iter().zip(est.values()) {
        assert!(((e - t) / t).abs() < 1e-8, "{t} vs {e}");
    }
}

/// A linear drift added to periodic data is removed exactly; the periodic part is untouched.
#[test]
fn linear_drift_is_removed() {
    use viscoprobe_core::estimate::frequency::remove_linear_drift;
    let np = 400;
    let periodic: Vec<f64> = (0..3 * np)
        .map(|i| (2.0 * std::f64::consts::PI * (i % np) as f64 / np as f64 * 3.0).sin())
        .collect();
    let drifted: Vec<f64> = periodic
        .iter()
        .enumerate()
        .map(|(i, v)| v + 1e-3 * i as f64 + 0.5)
        .collect();
    let back = remove_linear_drift(&drifted, 3);
    let mean_p = periodic.iter().sum::<f64>() / periodic.len() as f64;
    let mean_b = back.iter().sum::<f64>() / back.len() as f64;
    for (a, b) in periodic.iter().zip(&back) {
        assert!(((a - mean_p) - (b - mean_b)).abs() < 1e-9, "{a} vs {b}");
    }
}
