//! Forward sensitivities of an indentation twin's deflection to its material parameters,
//! against the finite differences the diagnosis's Jacobians use. A research sketch for issue 9
//! item 4 (see `docs/diagnosis-speed.md`), not the project's twin: a sphere on a Prony
//! material (the twin's first-order-hold recursion, `twin::material`), a quasi-static lever,
//! no adhesion, no actuator dynamics, no detector. It stands alone (std only) so that the
//! arithmetic can be read and rerun on its own:
//!
//!     rustc -O tools/sensitivity-prototype/main.rs -o /tmp/sens && /tmp/sens
//!
//! It prints, per parameter, how far the finite-difference column (forward, step 1e-4 as
//! `diagnose::fit::FD_STEP`; and central, step 1e-3) is from the forward sensitivity, the
//! root's error at the twin's tolerance against a root solved to the last bit, and the cost
//! of a run with the eight sensitivities against one without.
use std::time::Instant;

/// ln J0, ln J1..3, ln τ1..3 and the contact point (nm).
const P_N: usize = 8;

#[derive(Clone)]
struct Params {
    ln_j0: f64,
    ln_j: [f64; 3],
    ln_tau: [f64; 3],
    contact_nm: f64,
}

impl Params {
    fn moved(&self, q: usize, by: f64) -> Self {
        let mut p = self.clone();
        match q {
            0 => p.ln_j0 += by,
            1..=3 => p.ln_j[q - 1] += by,
            4..=6 => p.ln_tau[q - 4] += by,
            // The diagnosis's contact point is in units of 10 nm.
            _ => p.contact_nm += 10.0 * by,
        }
        p
    }
}

struct Run {
    deflection_m: Vec<f64>,
    /// ∂d/∂θ per sample (empty unless asked for).
    sensitivity: Vec<[f64; P_N]>,
}

/// The twin's contact solve: Newton from the last root inside a shrinking bracket, stopped
/// when a step or the bracket falls below `tol` (as `contact::decreasing_root_and_slope_from`).
fn root(
    g: impl Fn(f64) -> (f64, f64),
    (mut lo, mut hi): (f64, f64),
    start: f64,
    tol: f64,
) -> (f64, f64) {
    let mut d = start.clamp(lo, hi);
    let (mut gd, mut slope) = g(d);
    for _ in 0..60 {
        if gd > 0.0 {
            lo = d
        } else {
            hi = d
        }
        let mut next = d - gd / slope;
        if !(next > lo && next < hi) {
            next = 0.5 * (lo + hi)
        }
        let step = (next - d).abs();
        d = next;
        if step <= tol || hi - lo <= tol {
            break;
        }
        (gd, slope) = g(d);
    }
    (d, slope)
}

fn run(p: &Params, base_nm: &[f64], fs: f64, tol_scale: f64, with_sensitivity: bool) -> Run {
    let (k, radius) = (0.1_f64, 1e-6_f64);
    // y = h^{3/2} = J ∗ u with u = 9P/(16√R), P = K·d.
    let cf = 9.0 / (16.0 * radius.sqrt());
    let t = 1.0 / fs;
    let j0 = p.ln_j0.exp();
    let j = p.ln_j.map(f64::exp);
    let tau = p.ln_tau.map(f64::exp);
    // Each term: x[k] = a·x[k−1] + c·(u[k] − u[k−1]), a = e^{−T/τ}, c = τ(1 − a)/T,
    // and their derivatives in ln τ: a·T/τ and c − a.
    let a = tau.map(|tau| (-t / tau).exp());
    let c: [f64; 3] = std::array::from_fn(|i| tau[i] * (1.0 - a[i]) / t);
    let da: [f64; 3] = std::array::from_fn(|i| a[i] * t / tau[i]);
    let dc: [f64; 3] = std::array::from_fn(|i| c[i] - a[i]);
    let (mut x, mut u_prev, mut d_prev) = ([0.0; 3], 0.0, 0.0_f64);
    let (mut dx, mut du_prev) = ([[0.0; P_N]; 3], [0.0; P_N]);
    let mut out = Run {
        deflection_m: Vec::with_capacity(base_nm.len()),
        sensitivity: Vec::new(),
    };
    for &z in base_nm {
        let gap = (z - p.contact_nm) * 1e-9;
        // y = α·u + β for this sample's u (`MaterialState::affine`).
        let mut alpha = j0;
        let mut beta = 0.0;
        for i in 0..3 {
            alpha -= j[i] * c[i];
            beta += j[i] * (c[i] * u_prev - a[i] * x[i]);
        }
        let touching = gap > 0.0 && gap.powf(1.5) > beta;
        // g(d) = (gap − d)^{3/2} − α·cf·K·d − β, decreasing in d.
        let g = |d: f64| {
            let h = (gap - d).max(0.0);
            (
                h.powf(1.5) - alpha * cf * k * d - beta,
                -1.5 * h.sqrt() - alpha * cf * k,
            )
        };
        let (d, slope) = if touching {
            root(g, (0.0, gap), d_prev, tol_scale * 1e-14 * (1.0 + gap.abs()))
        } else {
            (0.0, 1.0)
        };
        let u = cf * k * d;
        if with_sensitivity {
            // The root moves as ∂d/∂θ = −g_θ/g_d; g_d is the solve's last slope.
            let mut s = [0.0; P_N];
            if touching {
                let dy_dh = 1.5 * (gap - d).sqrt();
                for (q, sq) in s.iter_mut().enumerate() {
                    let (mut dalpha, mut dgap) = (0.0, 0.0);
                    let mut dbeta: f64 = (0..3)
                        .map(|i| j[i] * (c[i] * du_prev[q] - a[i] * dx[i][q]))
                        .sum();
                    match q {
                        0 => dalpha = j0,
                        1..=3 => {
                            let i = q - 1;
                            dalpha = -j[i] * c[i];
                            dbeta += j[i] * (c[i] * u_prev - a[i] * x[i]);
                        }
                        4..=6 => {
                            let i = q - 4;
                            dalpha = -j[i] * dc[i];
                            dbeta += j[i] * (dc[i] * u_prev - da[i] * x[i]);
                        }
                        _ => dgap = -10e-9,
                    }
                    let g_theta = dy_dh * dgap - dalpha * cf * k * d - dbeta;
                    *sq = -g_theta / slope;
                }
            }
            for q in 0..P_N {
                let du = cf * k * s[q];
                for i in 0..3 {
                    let (dai, dci) = if q == 4 + i {
                        (da[i], dc[i])
                    } else {
                        (0.0, 0.0)
                    };
                    dx[i][q] = dai * x[i]
                        + a[i] * dx[i][q]
                        + dci * (u - u_prev)
                        + c[i] * (du - du_prev[q]);
                }
                du_prev[q] = du;
            }
            out.sensitivity.push(s);
        }
        for i in 0..3 {
            x[i] = a[i] * x[i] + c[i] * (u - u_prev);
        }
        u_prev = u;
        d_prev = d;
        out.deflection_m.push(d);
    }
    out
}

fn main() {
    let fs = 4000.0;
    let n = 20_000;
    // An approach to 300 nm past the contact point, then five lines of 20 nm from 3 to 800 Hz.
    let base_nm: Vec<f64> = (0..n)
        .map(|k| {
            let t = k as f64 / fs;
            if t < 1.0 {
                -100.0 + 400.0 * t
            } else {
                let lines = [3.0, 17.0, 61.0, 233.0, 800.0];
                300.0
                    + lines
                        .iter()
                        .map(|f| 20.0 * (2.0 * std::f64::consts::PI * f * t + f).sin())
                        .sum::<f64>()
            }
        })
        .collect();
    let p = Params {
        ln_j0: 5e-4f64.ln(),
        ln_j: [1.5e-4f64.ln(), 5e-5f64.ln(), 2e-5f64.ln()],
        ln_tau: [0.08f64.ln(), 0.005f64.ln(), 0.0003f64.ln()],
        contact_nm: 0.0,
    };
    let names = [
        "ln J0",
        "ln J1",
        "ln J2",
        "ln J3",
        "ln tau1 (80 ms)",
        "ln tau2 (5 ms)",
        "ln tau3 (0.3 ms)",
        "contact point",
    ];
    let at = run(&p, &base_nm, fs, 1.0, true);
    // rms over samples of (column − sensitivity), over the rms of the column.
    let off = |col: &dyn Fn(usize) -> f64, q: usize| {
        let (mut num, mut den) = (0.0, 0.0);
        for k in 0..n {
            num += (col(k) - at.sensitivity[k][q]).powi(2);
            den += col(k).powi(2);
        }
        (num / den).sqrt()
    };
    println!("finite-difference columns against the forward sensitivities (rms of the difference / rms of the column):");
    println!(
        "{:18} {:>22} {:>22} {:>30}",
        "parameter", "forward, step 1e-4", "central, step 1e-3", "forward 1e-4, roots to the bit"
    );
    let exact_at = run(&p, &base_nm, fs, 1e-16, false);
    for (q, name) in names.iter().enumerate() {
        let fwd = run(&p.moved(q, 1e-4), &base_nm, fs, 1.0, false);
        let (plus, minus) = (
            run(&p.moved(q, 1e-3), &base_nm, fs, 1.0, false),
            run(&p.moved(q, -1e-3), &base_nm, fs, 1.0, false),
        );
        let exact = run(&p.moved(q, 1e-4), &base_nm, fs, 1e-16, false);
        let forward = off(&|k| (fwd.deflection_m[k] - at.deflection_m[k]) / 1e-4, q);
        let central = off(
            &|k| (plus.deflection_m[k] - minus.deflection_m[k]) / 2e-3,
            q,
        );
        let to_the_bit = off(
            &|k| (exact.deflection_m[k] - exact_at.deflection_m[k]) / 1e-4,
            q,
        );
        println!("{name:18} {forward:>22.2e} {central:>22.2e} {to_the_bit:>30.2e}");
    }
    let (mut worst, mut sum, mut count) = (0.0_f64, 0.0, 0.0);
    for (d, e) in at.deflection_m.iter().zip(&exact_at.deflection_m) {
        if *e != 0.0 {
            let r = ((d - e) / e).abs();
            worst = worst.max(r);
            sum += r * r;
            count += 1.0;
        }
    }
    println!("the root at the twin's tolerance against the root to the bit: worst {worst:.1e}, rms {:.1e} (relative)", (sum / count).sqrt());
    let time = |with: bool| {
        let reps = 40;
        let t0 = Instant::now();
        for _ in 0..reps {
            std::hint::black_box(run(&p, &base_nm, fs, 1.0, with));
        }
        t0.elapsed().as_secs_f64() / reps as f64
    };
    let (plain, with) = (time(false), time(true));
    println!(
        "one run {:.2} ms; with the {P_N} sensitivities {:.2} ms: {:.2} runs' time, where finite differences take {P_N} more runs",
        plain * 1e3,
        with * 1e3,
        with / plain
    );
}
