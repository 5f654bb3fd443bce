//! The final refinement of a fit: output error on the deflection, with the drive as input.
//!
//! The linear pair of [`super::prepare`] takes both channels from the lever: the force
//! `u ∝ K·d` and the indentation `h = z − z_c − d` carry the same detector noise, so an
//! output-error fit of `u → y` has noise in its input (errors in variables) and biases the
//! fastest terms. And where the indentation comes from the drive, the contact position `z_c`
//! is read off at one sample, a constant error in `h` that scales every compliance.
//!
//! Here the input is the noise-free drive position `z` (the commanded drive in nm; with a
//! hard reference channel, the drive calibrated against it) and the output is the measured
//! deflection `d`. For parameters `θ = (J0, Ji, τi, z_c)` the deflection follows sample by
//! sample from the implicit Hertz/Sneddon–Lee–Radok equation
//!
//! ```text
//!   h = z − z_c − d,   h^k = α·c·K·d + β   (in contact, h > 0),   d = 0 otherwise,
//! ```
//!
//! where `y = α·u + β` is the Prony material's first-order-hold step
//! ([`crate::twin::material::MaterialState`]) and `u = c·K·d`: a scalar monotone equation,
//! solved by safeguarded Newton from the previous sample. The fit minimises
//! `Σ (d_meas − d_model)²` with the shared Levenberg–Marquardt; the noise is the detector's
//! alone, white, so the Gauss–Newton matrix at the optimum gives the covariance, and the
//! contact position's uncertainty is in the Prony parameters' marginal intervals.

use super::Prepared;
use crate::contact::decreasing_root;
use crate::estimate::lm::{solve_lazy, LmOptions, LmResult};
use crate::estimate::{Diagnostics, Estimate, EstimateError, Method};
use crate::linalg::spd_inverse;
use crate::prony::PronySeries;
use crate::recording::Recording;
use crate::twin::material::MaterialState;
use nalgebra::{DMatrix, DVector};

/// Free-lever samples before the detected contact that the refinement also fits, so that the
/// fitted contact may move earlier than the detected one.
const PRE_CONTACT: usize = 20;

/// The data of a refinement: drive position and measured deflection over the window.
#[derive(Debug, Clone)]
pub struct Problem {
    /// First sample (index into the recording) of the refined window; it ends where the
    /// prepared window ends.
    pub start: usize,
    /// Drive position, nm (calibrated: see `drive_scale`).
    pub z_nm: Vec<f64>,
    /// Measured deflection `C·(v − baseline)`, nm.
    pub d_nm: Vec<f64>,
    /// Detector noise, nm rms (from the free approach): the residuals' scale.
    pub sigma_nm: f64,
    /// Standard error of the baseline level, nm: a constant shift of `d_nm`.
    pub baseline_sigma_nm: f64,
    /// Drive nm per nm of actuator motion: 1, or the slope of the hard reference against the
    /// drive when there is a reference channel.
    pub drive_scale: f64,
    /// Standard error of that slope (0 without a reference): a calibration uncertainty the
    /// intervals carry.
    pub drive_scale_sigma: f64,
    /// Start value of the contact position, nm (in `z_nm`'s frame).
    pub z_contact_start_nm: f64,
    pub k_n_per_m: f64,
    pub force_factor: f64,
    pub exponent: f64,
    pub fs_hz: f64,
    /// Window samples (indices into `z_nm`, ascending) that are not residuals: spikes off a
    /// first refinement ([`super::spikes`]). Empty unless the caller sets them.
    pub left_out: Vec<usize>,
}

impl Problem {
    /// The refinement problem of a prepared recording, or why there is none.
    pub fn new(rec: &Recording, p: &Prepared) -> Result<Self, String> {
        let c_nm = rec.meta.cantilever.deflection_sensitivity_nm_per_v;
        let sigma_nm = c_nm * p.baseline_noise_v;
        if !(sigma_nm.is_finite() && sigma_nm > 0.0) {
            return Err("the free lever shows no noise to weight the deflection by".into());
        }
        let Some(drive_nm) = rec.drive_nm() else {
            return Err("the drive has no position in nm".into());
        };
        let start = p.contact_walkback_index.saturating_sub(PRE_CONTACT);
        let (c, end) = (p.contact_index, p.end_index);
        // The baseline of `prepare`, extended to the free samples before contact: its level at
        // the contact's drive plus the tilt (V per nm of drive).
        let d_nm: Vec<f64> = (start..end)
            .map(|i| {
                let bl = p.baseline_v + p.baseline_tilt_v_per_nm * (drive_nm[i] - drive_nm[c]);
                c_nm * (rec.deflection_v[i] - bl)
            })
            .collect();
        let (drive_scale, drive_scale_sigma) = match p.indentation_source {
            "drive" => (1.0, 0.0),
            "reference" => {
                let r = rec
                    .reference_deflection_v
                    .as_ref()
                    .ok_or("no reference channel")?;
                reference_scale(&drive_nm[c..end], &r[c..end], c_nm, sigma_nm)?
            }
            other => {
                return Err(format!(
                    "the indentation comes from the {other} channel, a noisy position the \
                     drive-to-deflection model does not use"
                ))
            }
        };
        let z_nm: Vec<f64> = drive_nm[start..end]
            .iter()
            .map(|x| drive_scale * x)
            .collect();
        // Contact position implied by the prepared indentation: h = z − z_c − d.
        let mut zc: Vec<f64> = (c..end)
            .map(|i| z_nm[i - start] - d_nm[i - start] - 1e9 * p.indentation_m[i - c])
            .collect();
        zc.sort_by(f64::total_cmp);
        let z_contact_start_nm = zc[zc.len() / 2];
        let contact = rec.meta.contact();
        Ok(Self {
            start,
            z_nm,
            d_nm,
            sigma_nm,
            baseline_sigma_nm: c_nm * p.baseline_level_sigma_v,
            drive_scale,
            drive_scale_sigma,
            z_contact_start_nm,
            k_n_per_m: rec.meta.cantilever.spring_constant_n_per_m,
            force_factor: contact.force_factor(),
            exponent: contact.indentation_exponent(),
            fs_hz: p.fs_hz,
            left_out: Vec::new(),
        })
    }

    /// Model deflection, nm, of `model` with the contact at `zc_nm`.
    pub fn simulate(&self, model: &PronySeries, zc_nm: f64) -> Vec<f64> {
        self.simulate_on(&self.z_nm, model, zc_nm)
    }

    /// [`Problem::simulate`] on other drive positions `z_nm`.
    fn simulate_on(&self, z_nm: &[f64], model: &PronySeries, zc_nm: f64) -> Vec<f64> {
        let kc = self.k_n_per_m * self.force_factor;
        simulate_deflection(model, zc_nm, z_nm, kc, self.exponent, self.fs_hz)
    }
}

/// The drive's scale against the hard reference: the reference deflection in contact is the
/// actuator's motion (`C·v_ref = a + s·z`). Refused when the reference is not a straight line
/// in the drive within its noise: then the actuator has dynamics of its own (hysteresis,
/// creep) and the drive is not the position. Returns the slope and its standard error.
fn reference_scale(
    z: &[f64],
    v_ref: &[f64],
    c_nm: f64,
    sigma_nm: f64,
) -> Result<(f64, f64), String> {
    let pts: Vec<(f64, f64)> = z
        .iter()
        .zip(v_ref)
        .map(|(&x, &v)| (x, c_nm * v))
        .filter(|(_, r)| *r > 5.0 * sigma_nm)
        .collect();
    if pts.len() < 20 {
        return Err("the hard reference is not in contact over the window".into());
    }
    let n = pts.len() as f64;
    let (xm, ym) = (
        pts.iter().map(|p| p.0).sum::<f64>() / n,
        pts.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let sxx: f64 = pts.iter().map(|p| (p.0 - xm).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| (p.0 - xm) * (p.1 - ym)).sum();
    if sxx <= 0.0 {
        return Err("the drive does not move while the reference is in contact".into());
    }
    let s = sxy / sxx;
    let rms = (pts
        .iter()
        .map(|p| (p.1 - ym - s * (p.0 - xm)).powi(2))
        .sum::<f64>()
        / (n - 2.0))
        .sqrt();
    if rms > 1.5 * sigma_nm {
        return Err(format!(
            "the hard reference is not a straight line in the drive ({rms:.3} nm rms about \
             it, detector noise {sigma_nm:.3} nm): the actuator has dynamics of its own"
        ));
    }
    Ok((s, rms / sxx.sqrt()))
}

/// Deflection (nm) of a lever of stiffness `k·c` (`u = kc·d`, N/m × the contact's force
/// factor) whose base moves by `z_nm` onto a Prony material in contact from `zc_nm`, with
/// indentation exponent `expo`: the implicit equation of the module documentation solved at
/// every sample, the material at rest before the first.
pub fn simulate_deflection(
    model: &PronySeries,
    zc_nm: f64,
    z_nm: &[f64],
    kc: f64,
    expo: f64,
    fs_hz: f64,
) -> Vec<f64> {
    let mut mat = MaterialState::new(model, fs_hz);
    let mut out = Vec::with_capacity(z_nm.len());
    // h^k for h ≥ 0 (0 below), without `powf` for the sphere and the cone.
    let pow = |h: f64| {
        let h = h.max(0.0);
        if expo == 1.5 {
            h * h.sqrt()
        } else if expo == 2.0 {
            h * h
        } else {
            h.powf(expo)
        }
    };
    let mut d = 0.0f64;
    for &z in z_nm {
        let g = (z - zc_nm) * 1e-9;
        let (alpha, beta) = mat.affine();
        let a = alpha * kc;
        // f(d) = (g − d)^k − a·d − β, decreasing on [0, g]; in contact when f(0) > 0.
        let f = |d: f64| pow(g - d) - a * d - beta;
        if g > 0.0 && f(0.0) > 0.0 {
            d = if f(g) >= 0.0 {
                g
            } else {
                let f_and_slope = |d: f64| {
                    let h = (g - d).max(1e-300);
                    (f(d), -expo * pow(h) / h - a)
                };
                decreasing_root(f_and_slope, (0.0, g), d, 1e-15 * g, 100)
            };
        } else {
            d = 0.0;
        }
        mat.commit(kc * d);
        out.push(d * 1e9);
    }
    out
}

/// A refined fit.
#[derive(Debug, Clone)]
pub struct Refined {
    /// The Prony estimate, intervals marginal over the contact position and including the
    /// calibration terms; or why the optimum has no intervals (an order too many).
    pub estimate: Result<Estimate, EstimateError>,
    pub model: PronySeries,
    /// Fitted contact position, nm of drive, and its standard error.
    pub contact_nm: f64,
    pub contact_sigma_nm: f64,
    /// Sum of squared deflection residuals, nm², over `samples`.
    pub rss_nm2: f64,
    /// Samples fitted: the window less [`Problem::left_out`].
    pub samples: usize,
    /// Deflection residuals over the whole window, nm; zero at [`Problem::left_out`].
    pub residuals_nm: Vec<f64>,
    pub iterations: usize,
}

impl Refined {
    /// `N·ln(RSS/N) + p·ln N` with `p = 2n + 2` (the contact position is a parameter).
    pub fn bic(&self) -> f64 {
        let n = self.samples as f64;
        let p = (2 * self.model.order() + 2) as f64;
        n * (self.rss_nm2 / n).max(1e-300).ln() + p * n.ln()
    }
}

/// Refines `start` (any order) on `prob`. An optimum whose parameters the data cannot
/// separate is still returned, with its cost, and the reason in place of the estimate.
pub fn refine(prob: &Problem, start: &PronySeries) -> Result<Refined, EstimateError> {
    let n = start.order();
    let np = 2 * n + 2;
    let len = prob.z_nm.len();
    let samples = len - prob.left_out.len().min(len);
    if samples < 4 * np {
        return Err(EstimateError::TooFewSamples {
            samples,
            params: np,
        });
    }
    let zc0 = prob.z_contact_start_nm;
    let unpack = |p: &[f64]| -> Option<(PronySeries, f64)> {
        if p.iter().any(|v| !v.is_finite()) || p[..np - 1].iter().any(|v| v.abs() > 700.0) {
            return None;
        }
        let m = PronySeries::from_vec(&p[..np - 1].iter().map(|v| v.exp()).collect::<Vec<_>>());
        m.is_physical().then_some((m, zc0 + p[np - 1]))
    };
    let residuals = |p: &[f64]| -> Option<DVector<f64>> {
        let (m, zc) = unpack(p)?;
        let d = prob.simulate(&m, zc);
        let mut r = DVector::from_fn(len, |k, _| (prob.d_nm[k] - d[k]) / prob.sigma_nm);
        for &k in prob.left_out.iter().filter(|&&k| k < len) {
            r[k] = 0.0;
        }
        Some(r)
    };
    // Central differences: ln-parameters by 1e-6, the contact by 1e-4 nm.
    let jacobian = |p: &[f64], _: &DVector<f64>| -> Option<DMatrix<f64>> {
        let mut jac = DMatrix::zeros(len, np);
        for i in 0..np {
            let h = if i == np - 1 { 1e-4 } else { 1e-6 };
            let mut q = p.to_vec();
            q[i] = p[i] + h;
            let up = residuals(&q)?;
            q[i] = p[i] - h;
            let dn = residuals(&q)?;
            for k in 0..len {
                jac[(k, i)] = (up[k] - dn[k]) / (2.0 * h);
            }
        }
        Some(jac)
    };
    let mut p0: Vec<f64> = start.to_vec().iter().map(|v| v.ln()).collect();
    p0.push(0.0);
    let opts = LmOptions {
        max_iterations: 200,
        cost_tolerance: 1e-12,
        // The cost is a χ² in units of the detector noise: 1e-4 of it is nothing.
        cost_tolerance_abs: 1e-4,
        ..LmOptions::default()
    };
    let res: LmResult = solve_lazy(&p0, residuals, jacobian, opts).ok_or(EstimateError::NoStart)?;
    // Terms slowest first: the parameters and the solver's Jacobian at the optimum permuted
    // alike, so the covariance needs no permutation and nothing is simulated again.
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| res.params[1 + n + b].total_cmp(&res.params[1 + n + a]));
    let perm: Vec<usize> = std::iter::once(0)
        .chain(order.iter().map(|&i| 1 + i))
        .chain(order.iter().map(|&i| 1 + n + i))
        .chain(std::iter::once(np - 1))
        .collect();
    let p: Vec<f64> = perm.iter().map(|&i| res.params[i]).collect();
    let jac = DMatrix::from_fn(len, np, |k, c| res.jacobian[(k, perm[c])]);
    let r = &res.residuals;
    let (model, contact_nm) = unpack(&p).ok_or(EstimateError::NoStart)?;
    let rss = res.cost * prob.sigma_nm.powi(2);
    let residuals_nm: Vec<f64> = res.residuals.iter().map(|r| r * prob.sigma_nm).collect();
    let mut out = Refined {
        estimate: Err(EstimateError::NoStart),
        model,
        contact_nm,
        contact_sigma_nm: f64::NAN,
        rss_nm2: rss,
        samples,
        residuals_nm,
        iterations: res.iterations,
    };
    let jtj = jac.transpose() * &jac;
    let rcond = crate::linalg::scaled_rcond(&jtj);
    let dof = samples - np;
    let s2 = res.cost / dof as f64;
    let Some(cov) = spd_inverse(&jtj) else {
        out.estimate = Err(EstimateError::IllConditioned { rcond });
        return Ok(out);
    };
    let cov = cov * s2;
    out.contact_sigma_nm = cov[(np - 1, np - 1)].max(0.0).sqrt();
    let block = cov.view((0, 0), (np - 1, np - 1)).into_owned();
    let lag1 = (1..len).map(|t| r[t] * r[t - 1]).sum::<f64>() / res.cost.max(1e-300);
    let mut warnings = Vec::new();
    if !res.converged {
        warnings.push(format!(
            "the refinement on the deflection stopped at its limit of {} iterations before \
             converging: the estimate is its last point",
            opts.max_iterations
        ));
    }
    if lag1.abs() > 3.0 / (samples as f64).sqrt() {
        warnings.push(format!(
            "deflection residuals are correlated (lag-1 correlation {lag1:.3}); intervals \
             assume white noise and may be too narrow"
        ));
    }
    let diagnostics = Diagnostics {
        cost: res.cost,
        dof,
        cost_per_dof: s2,
        iterations: res.iterations,
        observations: samples,
        noise_free: false,
        warnings,
    };
    let mut est = Estimate::from_log_fit(Method::TimeOutputError, &p[..np - 1], block, diagnostics);
    // A calibration error shifts the measured deflection by Δr (in units of the noise), which
    // the fit carries into its parameters by (JᵀJ)⁻¹Jᵀ·Δr.
    let chol = jtj.cholesky();
    let shift = |dr: DVector<f64>| -> Option<Vec<f64>> {
        let delta = chol.as_ref()?.solve(&(jac.transpose() * dr));
        Some(delta.as_slice()[..np - 1].to_vec())
    };
    // One standard error of the baseline level shifts every deflection by the same amount.
    if prob.baseline_sigma_nm > 0.0 {
        let dr = DVector::from_element(len, prob.baseline_sigma_nm / prob.sigma_nm);
        if let Some(delta) = shift(dr) {
            est = est.with_systematic(&delta, "the force baseline (free-lever level)");
        }
    }
    // The drive's calibration against the reference: the model run on drive positions scaled
    // by one standard error of the slope.
    if prob.drive_scale_sigma > 0.0 {
        let eps = prob.drive_scale_sigma / prob.drive_scale;
        let z: Vec<f64> = prob.z_nm.iter().map(|x| x * (1.0 + eps)).collect();
        let (base, scaled) = (
            prob.simulate(&out.model, contact_nm),
            prob.simulate_on(&z, &out.model, contact_nm),
        );
        let dr = DVector::from_fn(len, |k, _| (scaled[k] - base[k]) / prob.sigma_nm);
        if let Some(delta) = shift(dr) {
            est = est.with_systematic(&delta, "the drive's scale against the hard reference");
        }
    }
    out.estimate = Ok(est);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analysis::simulate_foh;
    use crate::contact::Contact;
    use crate::prony::PronyTerm;
    use rand::rngs::StdRng;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    fn gel() -> PronySeries {
        PronySeries::new(
            1.0e-4,
            vec![
                PronyTerm {
                    j_per_pa: 3.0e-5,
                    tau_s: 0.2,
                },
                PronyTerm {
                    j_per_pa: 2.5e-5,
                    tau_s: 0.02,
                },
            ],
        )
    }

    /// A ramp from above the contact into 300 nm past it in 5 ms, then held for 0.5 s.
    fn ramp_hold(fs: f64) -> Vec<f64> {
        let n_ramp = (0.005 * fs) as usize;
        (0..(0.505 * fs) as usize)
            .map(|k| 80.0 + 320.0 * (k as f64 / n_ramp as f64).min(1.0))
            .collect()
    }

    /// The deflection solves the Lee–Radok relation it was built from: with `u = K·c·d` and
    /// `h = z − z_c − d`, `h^{3/2}` is the first-order-hold response of the material to `u`
    /// (simulated by the estimators' own, separately written, filter bank).
    #[test]
    fn deflection_satisfies_lee_radok() {
        let fs = 4000.0;
        let contact = Contact::sphere(2.5e-6);
        let k = 0.065;
        let kc = k * contact.force_factor();
        let z = ramp_hold(fs);
        let zc = 100.0;
        let d = simulate_deflection(&gel(), zc, &z, kc, 1.5, fs);
        // In contact from the first sample past the contact position on.
        let first = z.iter().position(|&x| x > zc).unwrap();
        assert!(d[..first].iter().all(|&v| v == 0.0));
        let u: Vec<f64> = d[first - 1..].iter().map(|&v| kc * v * 1e-9).collect();
        let y = simulate_foh(&gel(), &u, fs);
        for (i, yi) in y.iter().enumerate().skip(1) {
            let h = (z[first - 1 + i] - zc - d[first - 1 + i]) * 1e-9;
            let want = h.powf(1.5);
            assert!(
                (yi - want).abs() <= 1e-9 * want,
                "sample {i}: {yi:e} vs {want:e}"
            );
        }
        // It creeps: the deflection (force) relaxes under the held base.
        let n = d.len();
        assert!(d[n - 1] < 0.9 * d[first + 20]);
    }

    /// White noise on the deflection only, a start 20 % off and the contact 3 nm off: the
    /// truth comes back within its intervals, and the contact within 4 standard errors.
    #[test]
    fn refine_recovers_material_and_contact() {
        let fs = 4000.0;
        let contact = Contact::sphere(2.5e-6);
        let k = 0.065;
        let z = ramp_hold(fs);
        let truth = gel();
        let zc = 100.0;
        let clean = simulate_deflection(&truth, zc, &z, k * contact.force_factor(), 1.5, fs);
        let sigma = 0.085;
        let mut rng = StdRng::seed_from_u64(7);
        let d_nm: Vec<f64> = clean
            .iter()
            .map(|c| {
                c + sigma * {
                    let z: f64 = StandardNormal.sample(&mut rng);
                    z
                }
            })
            .collect();
        let prob = Problem {
            start: 0,
            z_nm: z,
            d_nm,
            sigma_nm: sigma,
            baseline_sigma_nm: 0.0,
            drive_scale: 1.0,
            drive_scale_sigma: 0.0,
            z_contact_start_nm: zc + 3.0,
            k_n_per_m: k,
            force_factor: contact.force_factor(),
            exponent: 1.5,
            fs_hz: fs,
            left_out: vec![],
        };
        let start =
            PronySeries::from_vec(&truth.to_vec().iter().map(|v| v * 1.2).collect::<Vec<_>>());
        let r = refine(&prob, &start).unwrap();
        let est = r.estimate.as_ref().unwrap();
        for (i, (w, [lo, hi])) in truth.to_vec().iter().zip(&est.ci95).enumerate() {
            assert!(
                lo <= w && w <= hi,
                "parameter {i}: {w:e} outside [{lo:e}, {hi:e}]"
            );
        }
        assert!(
            (r.contact_nm - zc).abs() < 4.0 * r.contact_sigma_nm,
            "contact {} ± {}",
            r.contact_nm,
            r.contact_sigma_nm
        );
        let rms = (r.rss_nm2 / r.samples as f64).sqrt();
        assert!(
            (rms / sigma - 1.0).abs() < 0.05,
            "residual {rms} vs noise {sigma}"
        );
    }
}
