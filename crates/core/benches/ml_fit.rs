//! Benchmark of the frequency-domain ML fit on the paper's record: 2 s at 8 kHz
//! (16 000 samples, two periods), Table I Case 2 input and noise, three Prony terms.
//! Also the ARX fit on the same data, for the ratio.

use criterion::{criterion_group, criterion_main, Criterion};
use std::hint::black_box;
use viscoprobe_core::prony::PronySeries;
use viscoprobe_core::studies::table1::{self, amplitudes_at_case1_power, case1_design, SNR_CASE2};

fn bench_fits(c: &mut Criterion) {
    let truth = PronySeries::paper_pdms();
    let exp = table1::simulate(
        &truth,
        &amplitudes_at_case1_power(&case1_design()),
        Some(SNR_CASE2),
        1,
    );
    c.bench_function("ml_fit_2s_8kHz_3terms", |b| {
        b.iter(|| table1::fit_ml(black_box(&exp), 3).unwrap())
    });
    c.bench_function("arx_fit_2s_8kHz_3terms", |b| {
        b.iter(|| table1::fit_paper_arx(black_box(&exp), 3))
    });
}

criterion_group!(benches, bench_fits);
criterion_main!(benches);
