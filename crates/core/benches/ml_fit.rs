//! Benchmark of the frequency-domain ML fit on the paper's record: 2 s at 8 kHz
//! (16 000 samples, two periods), Table I Case 2 input and noise, three Prony terms.
//! Also the ARX fit on the same data, and the ratio of the two.
//! Run: `cargo bench -p viscoprobe-core --bench ml_fit`.
//!
//! A plain timing loop rather than criterion: two numbers and their ratio need no
//! statistics engine, and criterion's dependency tree cost every `cargo test` build (which
//! compiles dev-dependencies) about 40 CPU-seconds.

use std::hint::black_box;
use std::time::Instant;
use viscoprobe_core::prony::PronySeries;
use viscoprobe_core::studies::table1::{self, amplitudes_at_case1_power, case1_design, SNR_CASE2};

/// Rounds of timing per fit; the median of the rounds is reported.
const ROUNDS: usize = 15;
/// Wall time each round aims at, s: long enough that the clock's resolution does not matter.
const ROUND_S: f64 = 0.1;

/// Median seconds per call of `f`, over [`ROUNDS`] rounds of about [`ROUND_S`] each.
fn seconds_per_call(mut f: impl FnMut()) -> f64 {
    let t0 = Instant::now();
    f();
    let once = t0.elapsed().as_secs_f64().max(1e-9);
    let calls = ((ROUND_S / once).ceil() as usize).max(1);
    let mut rounds: Vec<f64> = (0..ROUNDS)
        .map(|_| {
            let t = Instant::now();
            for _ in 0..calls {
                f();
            }
            t.elapsed().as_secs_f64() / calls as f64
        })
        .collect();
    rounds.sort_by(f64::total_cmp);
    rounds[ROUNDS / 2]
}

fn main() {
    let truth = PronySeries::paper_pdms();
    let exp = table1::simulate(
        &truth,
        &amplitudes_at_case1_power(&case1_design()),
        Some(SNR_CASE2),
        1,
    );
    let ml = seconds_per_call(|| {
        black_box(table1::fit_ml(black_box(&exp), 3).expect("the ML fit converges"));
    });
    // Timed whether or not it returns an estimate: under Case 2's noise the paper's
    // estimator may not (see the paper notes), and the time to find that out is its cost.
    let arx_outcome = match table1::fit_paper_arx(&exp, 3) {
        Ok(_) => "an estimate".to_string(),
        Err(e) => format!("no estimate: {e}"),
    };
    let arx = seconds_per_call(|| {
        let _ = black_box(table1::fit_paper_arx(black_box(&exp), 3));
    });
    println!(
        "ML fit, 2 s at 8 kHz, 3 terms:  {:.3} ms (median of {ROUNDS} rounds)",
        ml * 1e3
    );
    println!(
        "ARX fit, same data:             {:.3} ms (median of {ROUNDS} rounds; it gives {arx_outcome})",
        arx * 1e3
    );
    println!("ARX / ML time:                  {:.2}", arx / ml);
}
