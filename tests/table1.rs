//! Acceptance of the estimation core against the paper's Table I and the Cramér–Rao bound.

use viscoprobe_core::prony::PronySeries;
use viscoprobe_core::studies::table1::{self, error_pct};

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |a, b| a.max(b.abs()))
}

/// Case 1 (no noise): the paper's ARX is exact, and so is ML.
#[test]
fn case1_arx_and_ml_are_exact() {
    let truth = PronySeries::paper_pdms();
    let cases = table1::all_cases(&truth, 1);
    let c1 = &cases[0];
    let arx = c1.arx.estimate.as_ref().expect("ARX on noise-free data");
    let e = error_pct(&truth, &arx.values());
    assert!(max_abs(&e) < 1.0, "ARX errors {e:?}");
    assert!(
        max_abs(&e) < 1e-6,
        "noise-free ARX should be exact to rounding: {e:?}"
    );
    let ml = c1.ml.as_ref().expect("ML on noise-free data");
    assert!(max_abs(&error_pct(&truth, &ml.values())) < 1e-6);
}

/// Case 2: ARX shows the paper's failure; ML is within 1 % and its intervals cover the truth.
#[test]
fn case2_arx_fails_and_ml_does_not() {
    let truth = PronySeries::paper_pdms();
    for seed in [1, 2, 3] {
        let cases = table1::all_cases(&truth, seed);
        let c2 = &cases[1];
        let arx_vals = match &c2.arx.estimate {
            Ok(e) => e.values(),
            Err(_) => c2
                .arx
                .paper_values
                .clone()
                .expect("the paper's procedure always prints numbers"),
        };
        let arx_err = error_pct(&truth, &arx_vals);
        assert!(
            max_abs(&arx_err) > 20.0,
            "seed {seed}: ARX should fail under noise, errors {arx_err:?}"
        );
        let ml = c2.ml.as_ref().expect("ML fit");
        let ml_err = error_pct(&truth, &ml.values());
        assert!(max_abs(&ml_err) < 1.0, "seed {seed}: ML errors {ml_err:?}");
        let crlb = c2.crlb_rel.as_ref().unwrap();
        for (i, t) in truth.to_vec().iter().enumerate() {
            // The fit's own standard deviation is the CRLB evaluated at the estimate.
            let rel_std = ml.std[i] / ml.values()[i];
            assert!(
                (rel_std / crlb[i] - 1.0).abs() < 0.25,
                "seed {seed} param {i}: std {rel_std} vs CRLB {}",
                crlb[i]
            );
            let [lo, hi] = ml.ci95[i];
            // 7 params × 3 seeds at 95 %: allow none to miss by more than a whisker.
            assert!(
                *t > lo - 0.5 * (hi - lo) && *t < hi + 0.5 * (hi - lo),
                "seed {seed} param {i}: {t} vs [{lo}, {hi}]"
            );
        }
    }
}

/// Case 3: ML within 1 % on all seven parameters.
#[test]
fn case3_ml_within_one_percent() {
    let truth = PronySeries::paper_pdms();
    let cases = table1::all_cases(&truth, 1);
    let ml = cases[2].ml.as_ref().expect("ML fit");
    let e = error_pct(&truth, &ml.values());
    assert!(
        max_abs(&e) < 1.0,
        "Case 3 ML errors {e:?} with design {:?}",
        cases[2].lines
    );
}

/// Efficiency over 200 seeds: empirical std ≤ 1.3 × CRLB for every parameter, no failures,
/// and no bias beyond what 200 seeds can resolve.
#[test]
fn ml_is_efficient_over_200_seeds() {
    let eff = table1::efficiency(200, 1000, |_| {});
    assert_eq!(eff.failures, 0);
    for r in &eff.rows {
        let ratio = r.std_rel / r.crlb_rel;
        eprintln!(
            "{:<5} CRLB {:.4} %  std {:.4} %  ratio {:.3}  bias {:+.4} %",
            r.name,
            100.0 * r.crlb_rel,
            100.0 * r.std_rel,
            ratio,
            100.0 * r.mean_rel
        );
        assert!(ratio <= 1.3, "{}: std/CRLB = {ratio}", r.name);
        assert!(
            ratio >= 0.7,
            "{}: std/CRLB = {ratio} is below the bound: the CRLB or the scatter is wrong",
            r.name
        );
        // Bias must be small against the scatter: |mean| < 4 standard errors of the mean.
        assert!(
            r.mean_rel.abs() < 4.0 * r.std_rel / (200f64).sqrt(),
            "{}: bias {}",
            r.name,
            r.mean_rel
        );
    }
}

/// The closed design loop (no instrument, SNR 134) from F0 = {1, 10, 30, 60} Hz converges
/// (parameter change < 0.5 %) within 5 iterations, with all seven parameters within 1 %.
#[test]
fn closed_design_loop_converges_within_five_iterations() {
    use viscoprobe_core::studies::design_loop::{run, LoopStudySettings};
    let truth = PronySeries::paper_pdms();
    for seed in [11, 12] {
        let study = run(
            &truth,
            &LoopStudySettings {
                max_iterations: 5,
                ..Default::default()
            },
            seed,
        )
        .expect("loop runs");
        for (i, it) in study.iterations.iter().enumerate() {
            eprintln!(
                "seed {seed} it {}: change {:?}, errors {:?}, lines {:?}",
                i + 1,
                it.rel_change,
                error_pct(&truth, &it.estimate.values())
                    .iter()
                    .map(|e| format!("{e:.2}"))
                    .collect::<Vec<_>>(),
                it.lines.iter().map(|l| l.0).collect::<Vec<_>>()
            );
        }
        assert!(
            study.converged,
            "seed {seed}: not converged in 5 iterations"
        );
        assert!(study.iterations.len() <= 5);
        let e = error_pct(&truth, &study.final_estimate().values());
        assert!(max_abs(&e) < 1.0, "seed {seed}: final errors {e:?}");
        // The design must have reached past 200 Hz to see tau3.
        assert!(study
            .iterations
            .last()
            .unwrap()
            .lines
            .iter()
            .any(|l| l.0 > 200.0));
    }
}
