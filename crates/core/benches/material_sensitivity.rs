//! What the material's forward sensitivities (`twin::material::MaterialSensitivity`) cost and
//! how they compare with the finite differences the diagnosis's Jacobians take
//! (`docs/diagnosis-speed.md`). A sphere on a three-term Prony material under a quasi-static
//! lever, stepped with the twin's own pieces (`MaterialState`, `Contact::y_and_slope`,
//! `contact::decreasing_root_and_slope`) but without its actuator, adhesion or detector, so
//! that only the material and the contact root are measured. 20 000 samples at 4 kHz: an
//! approach to 300 nm past the contact point, then five lines of 20 nm from 3 to 800 Hz.
//! Run: `cargo bench --bench material_sensitivity`.

use std::time::Instant;
use viscoprobe_core::contact::{decreasing_root_and_slope, Contact};
use viscoprobe_core::prony::{PronySeries, PronyTerm};
use viscoprobe_core::twin::material::{MaterialSensitivity, MaterialState};

/// ln J0, ln J1..3, ln τ1..3 (slowest first, as `PronySeries` orders them), and the contact
/// point in units of 10 nm, as the diagnosis fits it.
const PARAMS: usize = 8;
const NAMES: [&str; PARAMS] = [
    "ln J0",
    "ln J1",
    "ln J2",
    "ln J3",
    "ln tau1 (80 ms)",
    "ln tau2 (5 ms)",
    "ln tau3 (0.3 ms)",
    "contact point",
];
const FS_HZ: f64 = 4000.0;
const K_N_PER_M: f64 = 0.1;

/// The lever's deflection (m) per sample, and with `sensitivities` its derivative in each
/// parameter. `tol_scale` scales the twin's root tolerance, `1e-14·(1 + gap)` m.
fn run(
    p: &[f64; PARAMS],
    base_nm: &[f64],
    tol_scale: f64,
    sensitivities: bool,
) -> Vec<[f64; PARAMS]> {
    let terms = (0..3)
        .map(|i| PronyTerm {
            j_per_pa: p[1 + i].exp(),
            tau_s: p[4 + i].exp(),
        })
        .collect();
    let mut material = MaterialState::new(&PronySeries::new(p[0].exp(), terms), FS_HZ);
    let mut sens = MaterialSensitivity::new(&material, 1);
    let contact = Contact::sphere(1e-6);
    let cf_k = contact.force_factor() * K_N_PER_M;
    let contact_m = 10e-9 * p[7];
    let (mut moved, mut du) = ([(0.0, 0.0); PARAMS], [0.0; PARAMS]);
    let mut last_d = 0.0;
    let mut out = Vec::with_capacity(base_nm.len());
    for &z in base_nm {
        let gap = z * 1e-9 - contact_m;
        let (alpha, beta) = material.affine();
        let touching = gap > 0.0 && contact.y_from_indentation(gap) > beta;
        // g(d) = y(gap − d) − α·cf·K·d − β, decreasing in d.
        let g = |d: f64| {
            let (y, dy) = contact.y_and_slope(gap - d);
            (y - alpha * cf_k * d - beta, -dy - alpha * cf_k)
        };
        let (d, slope) = if touching {
            let tol = tol_scale * 1e-14 * (1.0 + gap.abs());
            decreasing_root_and_slope(g, (0.0, gap), last_d, tol, 60)
        } else {
            (0.0, 1.0)
        };
        let mut row = [d; PARAMS];
        if sensitivities {
            // ∂d/∂θ = −g_θ/g_d, g_d the solve's last slope; out of contact d stays 0.
            sens.affine(&material, &mut moved);
            let dy_dh = contact.y_and_slope(gap - d).1;
            for q in 0..PARAMS {
                let dgap = if q == 7 { -10e-9 } else { 0.0 };
                let (dalpha, dbeta) = moved[q];
                let g_theta = dy_dh * dgap - dalpha * cf_k * d - dbeta;
                row[q] = if touching { -g_theta / slope } else { 0.0 };
                du[q] = cf_k * row[q];
            }
            sens.commit(&material, cf_k * d, &du);
        }
        material.commit(cf_k * d);
        last_d = d;
        out.push(row);
    }
    out
}

fn main() {
    let base_nm: Vec<f64> = (0..20_000)
        .map(|k| {
            let t = k as f64 / FS_HZ;
            if t < 1.0 {
                -100.0 + 400.0 * t
            } else {
                let lines = [3.0f64, 17.0, 61.0, 233.0, 800.0];
                300.0
                    + (lines.iter())
                        .map(|f| 20.0 * (2.0 * std::f64::consts::PI * f * t + f).sin())
                        .sum::<f64>()
            }
        })
        .collect();
    let p0 = [
        5e-4f64.ln(),
        1.5e-4f64.ln(),
        5e-5f64.ln(),
        2e-5f64.ln(),
        0.08f64.ln(),
        0.005f64.ln(),
        0.0003f64.ln(),
        0.0,
    ];
    let moved = |q: usize, h: f64| {
        let mut p = p0;
        p[q] += h;
        p
    };
    let deflection = |p: &[f64; PARAMS], tol_scale: f64| -> Vec<f64> {
        run(p, &base_nm, tol_scale, false)
            .iter()
            .map(|r| r[0])
            .collect()
    };
    let at = run(&p0, &base_nm, 1.0, true);
    let (d0, exact0) = (deflection(&p0, 1.0), deflection(&p0, 1e-16));
    // rms over samples of (column − sensitivity), over the rms of the column.
    let off = |col: &dyn Fn(usize) -> f64, q: usize| {
        let (mut num, mut den) = (0.0, 0.0);
        for (k, row) in at.iter().enumerate() {
            num += (col(k) - row[q]).powi(2);
            den += col(k).powi(2);
        }
        (num / den).sqrt()
    };
    println!("finite-difference columns against the forward sensitivities (rms of the difference / rms of the column):");
    println!(
        "{:18} {:>20} {:>20} {:>32}",
        "parameter", "forward, step 1e-4", "central, step 1e-3", "forward 1e-4, roots to the bit"
    );
    for (q, name) in NAMES.iter().enumerate() {
        let fwd = deflection(&moved(q, 1e-4), 1.0);
        let (plus, minus) = (
            deflection(&moved(q, 1e-3), 1.0),
            deflection(&moved(q, -1e-3), 1.0),
        );
        let exact = deflection(&moved(q, 1e-4), 1e-16);
        let forward = off(&|k| (fwd[k] - d0[k]) / 1e-4, q);
        let central = off(&|k| (plus[k] - minus[k]) / 2e-3, q);
        let to_the_bit = off(&|k| (exact[k] - exact0[k]) / 1e-4, q);
        println!("{name:18} {forward:>20.2e} {central:>20.2e} {to_the_bit:>32.2e}");
    }
    let (mut worst, mut sum, mut count) = (0.0f64, 0.0, 0.0);
    for (d, e) in d0.iter().zip(&exact0).filter(|(_, e)| **e != 0.0) {
        let r = ((d - e) / e).abs();
        worst = worst.max(r);
        sum += r * r;
        count += 1.0;
    }
    println!(
        "the root at the twin's tolerance against the root to the bit: worst {worst:.1e}, rms {:.1e} (relative)",
        (sum / count).sqrt()
    );
    let time = |sensitivities: bool| {
        let reps = 40;
        let t0 = Instant::now();
        for _ in 0..reps {
            std::hint::black_box(run(&p0, &base_nm, 1.0, sensitivities));
        }
        t0.elapsed().as_secs_f64() / reps as f64
    };
    let (plain, with) = (time(false), time(true));
    println!(
        "one run {:.2} ms; with the {PARAMS} sensitivities {:.2} ms: {:.2} runs' time, where finite differences take {PARAMS} more runs",
        plain * 1e3,
        with * 1e3,
        with / plain
    );
}
