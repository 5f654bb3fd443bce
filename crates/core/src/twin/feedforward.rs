//! A nominal open-loop inverse of the twin: the drive that makes a periodic force, to first
//! order, on an ideal actuator.
//!
//! Around the preload `P0` the Hertz–Lee–Radok contact is linearised: `h0^k = J0·c·P0` and a
//! force line `F(ω)` indents by `dh(ω) = J*(ω)·c·F(ω) / (k·h0^{k−1})`. The base must move by the
//! lever's share `F/K` plus that indentation. Actuator dynamics, hysteresis and adhesion are
//! ignored: this is a starting point (the drive `U_0` of an iterative controller, or an
//! open-loop simulation), not a tracker.

use super::TwinConfig;
use rustfft::num_complex::Complex64;
use rustfft::FftPlanner;

/// Drive voltages for one period of the force `force_n` (N, sampled at `fs_hz`).
pub fn drive_for_force(cfg: &TwinConfig, force_n: &[f64], fs_hz: f64) -> Vec<f64> {
    let n = force_n.len();
    if n == 0 {
        return Vec::new();
    }
    let contact = cfg.contact();
    let k = cfg.cantilever.spring_constant_n_per_m;
    let c = contact.force_factor();
    let m = &cfg.sample.material;
    let p0 = force_n.iter().sum::<f64>() / n as f64;
    let y0 = m.j0_per_pa * c * p0.max(0.0);
    let h0 = contact.indentation_from_y(y0);
    let mut planner = FftPlanner::<f64>::new();
    let mut spec: Vec<Complex64> = force_n
        .iter()
        .map(|&f| Complex64::new(f - p0, 0.0))
        .collect();
    planner.plan_fft_forward(n).process(&mut spec);
    for (i, x) in spec.iter_mut().enumerate() {
        let f = crate::miic::bin_frequency_hz(i, n, fs_hz);
        let jstar = if f >= 0.0 {
            m.complex_compliance(2.0 * std::f64::consts::PI * f)
        } else {
            m.complex_compliance(-2.0 * std::f64::consts::PI * f).conj()
        };
        let dh_per_n = if h0 > 0.0 {
            jstar * c / contact.shape_slope(h0)
        } else {
            Complex64::new(0.0, 0.0)
        };
        *x *= dh_per_n + 1.0 / k;
    }
    planner.plan_fft_inverse(n).process(&mut spec);
    let base0_m = cfg.sample.contact_point_nm * 1e-9 + p0 / k + h0;
    spec.iter()
        .map(|z| (base0_m + z.re / n as f64) * 1e9 / cfg.actuator.gain_nm_per_v)
        .collect()
}
