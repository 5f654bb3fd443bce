//! Channels beside the deflection as witnesses of a model's instrument chain.
//!
//! [`HeightWitness`]: the stage's position sensor as a second witness of the piezo's path.
//!
//! Where a recording drives the piezo in volts and also has `measured_height_nm`, the
//! sensor reads the piezo's own extension: its creep and its hysteresis show there directly,
//! while a thermal drift of the frame or the sample, a retardation of the material or
//! anything in the detector does not. From the deflection alone a slow creep and a slow
//! drift look alike (both bend the in-contact deflection along a settling curve); the sensor
//! tells them apart at once.
//!
//! The witness judges without fitting. Every model the diagnosis fits to the deflection has
//! a piezo path (the actuator of its twin: gain, creep and hysteresis at the fitted
//! parameters); the witness scores that path against the sensor. The sensor's χ² is thus
//! one more term of the same likelihood, evaluated at parameters the deflection chose: a
//! creep fitted to what was really a drift puts a creep into the sensor's path that the
//! sensor never saw, and loses there. One measurement is the sensor's own: a creep the
//! deflection barely shows strays in its fit there, so [`HeightWitness::creep_fit`] measures
//! it on the sensor for the diagnosis to hold while it refits the rest (a second model,
//! judged like the first).
//!
//! Beside the path, the regression has free nuisance terms that say nothing about the
//! catalog: the sensor's own scale and zero, a slow parabola of its own drift (capacitive
//! sensors warm too), and the first two derivatives of the drive for what the path's linear
//! dynamics miss. Its noise is the residual of the nominal path (the drive's own, or the
//! nominal model's stage path where that reads better: [`HeightWitness::read_along`]), so
//! structure the witness does not model only widens the scale and weakens its evidence.
//! Those derivative columns absorb a small lag; [`HeightWitness::dynamics_rss`] scores a
//! path that carries the actuator's lag itself without them, for where the sensor's lag
//! says something the deflection cannot (a delay after the stage: `SensorLag` in the
//! diagnosis).

//!
//! [`ReferenceWitness`]: a `reference_deflection_v` column, the same drive on a hard reference
//! sample. It reads the whole chain from drive to detector — the actuator's gain, dynamics,
//! modes, creep and hysteresis, the detector's delay and nonlinearity (over the wider range a
//! hard sample deflects through), the drag off the surface — and nothing of the sample under
//! test:
//! an actuator mode or a delay fitted to the deflection shows there as well, a retardation of
//! the material, a drag in contact, an adhesion or a change of tip does not. Each model's
//! reference deflection ([`super::model::Problem::simulate_reference`]) is scored against the
//! column with a free scale (the gain), a free in-contact step (a contact point a little off:
//! a soft sample's first touch is hard to place), and a slow parabola of the detector's zero.
//! As for the sensor, the noise is the nominal model's residual there. Where it is correlated
//! off the surface (1/f noise), every fit is made on the whitened channel
//! (`Regression::whitening_filter`: generalised least squares), so that each model's path is
//! weighed against the noise at its own frequencies and a slow path cannot take up the
//! noise's wander. The sensor's noise is taken as white: it has no stretch where no model's
//! path could misfit to measure it on.

use super::noise::{ar_by_aic, detrend, whiten};
use crate::twin::dynamics::FirstOrder;
use nalgebra::{DMatrix, DVector};

/// Columns of the height witness's regression besides the path: zero, t, t², v̇, v̈.
const NUISANCE: usize = 5;

/// A recorded channel, regressed on a model's path columns beside fixed nuisance columns,
/// fitted on the train samples.
#[derive(Debug, Clone)]
struct Regression {
    target: Vec<f64>,
    /// n × (nuisance count), each column scaled to unit RMS.
    nuisance: DMatrix<f64>,
    train: Vec<usize>,
    held: Vec<usize>,
    /// The channel whitened ([`Self::whitening_filter`]), set once the nominal path is known;
    /// `None`: fitted as recorded.
    whitened: Option<Whitened>,
}

/// A channel's target and nuisance columns through its noise's whitening filter.
#[derive(Debug, Clone)]
struct Whitened {
    /// `[1, a1, …, ap]`: `e[i] = Σ_j a_j·x[i−j]` is white ([`whiten`]).
    filter: Vec<f64>,
    target: Vec<f64>,
    nuisance: DMatrix<f64>,
}

impl Regression {
    /// `None` for indices outside the record or too few train samples.
    fn new(target: &[f64], cols: &[Vec<f64>], train: &[usize], held: &[usize]) -> Option<Self> {
        let n = target.len();
        if train.len() < 4 * (cols.len() + 2) || train.iter().chain(held).any(|&i| i >= n) {
            return None;
        }
        let mut nuisance = DMatrix::zeros(n, cols.len());
        for (j, c) in cols.iter().enumerate() {
            for (i, x) in unit_rms(c).into_iter().enumerate() {
                nuisance[(i, j)] = x;
            }
        }
        Some(Self {
            target: target.to_vec(),
            nuisance,
            train: train.to_vec(),
            held: held.to_vec(),
            whitened: None,
        })
    }

    /// Parameters of a fit with `paths` path columns.
    fn parameters(&self, paths: usize) -> usize {
        self.nuisance.ncols() + paths
    }

    /// Residuals, on every sample, of the target against `paths` (each with a free
    /// coefficient) beside the nuisance columns, fitted on the train samples. `None` for a
    /// path of the wrong length or one that is not finite.
    fn residuals(&self, paths: &[&[f64]]) -> Option<Vec<f64>> {
        self.fit(paths).map(|f| f.residuals)
    }

    /// [`Self::residuals`], with the coefficients of `paths` and their errors.
    fn fit(&self, paths: &[&[f64]]) -> Option<Solved> {
        let n = self.target.len();
        if paths
            .iter()
            .any(|p| p.len() != n || p.iter().any(|v| !v.is_finite()))
        {
            return None;
        }
        let scales: Vec<f64> = paths.iter().map(|p| unit_rms_scale(p)).collect();
        let q = self.nuisance.ncols();
        let p = paths.len() + q;
        // Whitened, the paths go through the same filter as the target and the nuisance.
        let filtered: Vec<Vec<f64>>;
        let (paths, nuisance, target): (Vec<&[f64]>, &DMatrix<f64>, &[f64]) = match &self.whitened {
            Some(w) => {
                filtered = paths.iter().map(|p| whiten(&w.filter, p)).collect();
                (
                    filtered.iter().map(|v| &v[..]).collect(),
                    &w.nuisance,
                    &w.target,
                )
            }
            None => (paths.to_vec(), &self.nuisance, &self.target),
        };
        let row = |i: usize, r: &mut [f64]| {
            for (k, path) in paths.iter().enumerate() {
                r[k] = path[i] * scales[k];
            }
            for j in 0..q {
                r[paths.len() + j] = nuisance[(i, j)];
            }
        };
        // Normal equations on unit-RMS columns, solved by SVD so that a column the record
        // does not excite (v̈ of a drive of ramps) drops out instead of blowing up.
        let mut ata = DMatrix::<f64>::zeros(p, p);
        let mut atb = DVector::<f64>::zeros(p);
        let mut r = vec![0.0; p];
        for &i in &self.train {
            row(i, &mut r);
            for a in 0..p {
                atb[a] += r[a] * target[i];
                for b in 0..p {
                    ata[(a, b)] += r[a] * r[b];
                }
            }
        }
        let svd = ata.svd(true, true);
        let coef = svd.solve(&atb, 1e-10).ok()?;
        let inverse = svd.pseudo_inverse(1e-10).ok()?;
        let out: Vec<f64> = (0..n)
            .map(|i| {
                row(i, &mut r);
                let fit: f64 = (0..p).map(|a| r[a] * coef[a]).sum();
                target[i] - fit
            })
            .collect();
        let path_coefs = (0..paths.len()).map(|k| coef[k] * scales[k]).collect();
        let path_sd_per_sigma = (0..paths.len())
            .map(|k| inverse[(k, k)].max(0.0).sqrt() * scales[k])
            .collect();
        out.iter().all(|v| v.is_finite()).then_some(Solved {
            path_coefs,
            path_sd_per_sigma,
            residuals: out,
        })
    }

    /// Residual sums of squares (train, held-out) of the fit with `paths` ([`Self::residuals`]).
    fn residual_sums(&self, paths: &[&[f64]]) -> Option<(f64, f64)> {
        Some(self.sums(&self.residuals(paths)?))
    }

    /// Sums of squares (train, held-out) of residuals `r` on every sample.
    fn sums(&self, r: &[f64]) -> (f64, f64) {
        let sum = |idx: &[usize]| idx.iter().map(|&i| r[i] * r[i]).sum::<f64>();
        (sum(&self.train), sum(&self.held))
    }

    /// Degrees of freedom of a fit with `paths` path columns on the train samples (at least 1).
    fn dof(&self, paths: usize) -> f64 {
        self.train
            .len()
            .saturating_sub(self.parameters(paths))
            .max(1) as f64
    }

    /// Whitens the channel against the noise of the fit with `paths` over the samples `quiet`
    /// marks, where no model's path can misfit (the reference off its surface): an AR
    /// filter of that residual, its order by AIC (at most `noise::MAX_ORDER`, as
    /// `noise::measure` picks the deflection's), through which every later fit passes the
    /// target, the nuisance and its paths. Nothing changes where the residual is white (order
    /// 0) or where fewer than 500 quiet samples lie in runs of at least 256.
    ///
    /// Each quiet run is taken less its own straight line: an offset or a slope that a run
    /// keeps from the fit over the whole record is misfit, not noise. Taken whole, the
    /// residual of an independent simulator's hysteresis record with white noise off the
    /// surface (fresh rec07) gave an order of 27, and the filter took the hysteresis's slow
    /// evidence on the reference down with it (a creep was named instead); per run, order 0.
    ///
    /// A channel whose noise wanders (1/f) has far fewer independent samples than it has
    /// samples, and a slow model path took up its wander at the full sample count. An AR(1)
    /// variance inflation, `(1 + ρ)/(1 − ρ)` of the lag-one correlation, was the first
    /// correction (it took an independent simulator's 1/f null from a piezo creep's evidence
    /// of 190, all the reference's, to 43.0 under a bar of 43.9, fresh rec12); whitened, 7.7.
    fn whiten(&mut self, paths: &[&[f64]], quiet: &[bool]) {
        self.whitened = None;
        let Some(filter) = self.whitening_filter(paths, quiet) else {
            return;
        };
        if filter.len() == 1 {
            return;
        }
        let mut nuisance = DMatrix::zeros(self.nuisance.nrows(), self.nuisance.ncols());
        for (j, column) in self.nuisance.column_iter().enumerate() {
            let column: Vec<f64> = column.iter().copied().collect();
            nuisance.set_column(j, &DVector::from_vec(whiten(&filter, &column)));
        }
        self.whitened = Some(Whitened {
            target: whiten(&filter, &self.target),
            nuisance,
            filter,
        });
    }

    /// The filter of [`Self::whiten`]; `None` where it has too little to go on.
    fn whitening_filter(&self, paths: &[&[f64]], quiet: &[bool]) -> Option<Vec<f64>> {
        let r = self.residuals(paths)?;
        let max = super::noise::MAX_ORDER;
        let mut runs: Vec<Vec<f64>> = vec![];
        let mut i = 0;
        while i < r.len() {
            let start = i;
            while i < r.len() && quiet.get(i) == Some(&true) {
                i += 1;
            }
            if i - start >= 8 * max {
                let run = &r[start..i];
                let line = [
                    vec![1.0; run.len()],
                    (0..run.len()).map(|k| k as f64).collect(),
                ];
                runs.push(detrend(run, &line));
            }
            i += 1;
        }
        let samples: usize = runs.iter().map(Vec::len).sum();
        if samples < 500 {
            return None;
        }
        let autocovariance: Vec<f64> = (0..=max)
            .map(|k| {
                let sum: f64 = runs
                    .iter()
                    .map(|x| (k..x.len()).map(|i| x[i] * x[i - k]).sum::<f64>())
                    .sum();
                sum / samples as f64
            })
            .collect();
        ar_by_aic(&autocovariance, samples).map(|(filter, _)| filter)
    }

    /// χ² (train, held-out) of the fit with `paths`, in units of the noise scale `sigma`
    /// (of the whitened channel, where it is whitened).
    fn chi2(&self, paths: &[&[f64]], sigma: f64) -> Option<(f64, f64)> {
        let (train, held) = self.residual_sums(paths)?;
        let s2 = sigma * sigma;
        Some((train / s2, held / s2))
    }

    /// The noise scale of a fit with `paths` path columns: its train RMS residual; `None`
    /// where it is not finite, or is nothing against the target (a target that is a path
    /// to rounding has no noise to scale by, and witnesses nothing).
    fn noise_scale(&self, paths: &[&[f64]]) -> Option<f64> {
        let (rss_train, _) = self.residual_sums(paths)?;
        let sigma = (rss_train / self.dof(paths.len())).sqrt();
        let n = self.target.len() as f64;
        let rms = (self.target.iter().map(|x| x * x).sum::<f64>() / n).sqrt();
        (sigma.is_finite() && sigma > 1e-9 * rms).then_some(sigma)
    }
}

/// A single-term creep measured on the height sensor ([`HeightWitness::creep_fit`]).
#[derive(Debug, Clone, Copy)]
pub struct SensorCreep {
    pub fraction: f64,
    pub tau_s: f64,
    /// Standard deviations of ln fraction and ln τ (NaN where the sensor does not bound
    /// them: a best τ at the end of the grid).
    pub ln_fraction_sd: f64,
    pub ln_tau_sd: f64,
}

/// A [`Regression`]'s fit.
struct Solved {
    /// The coefficient of each path as given (not scaled).
    path_coefs: Vec<f64>,
    /// Their standard deviations for a noise of unit variance.
    path_sd_per_sigma: Vec<f64>,
    /// Residuals on every sample.
    residuals: Vec<f64>,
}

/// The sensor, its nuisance columns and its noise scale.
#[derive(Debug, Clone)]
pub struct HeightWitness {
    fit: Regression,
    /// The sensor against a path that carries the actuator's linear dynamics itself: its
    /// scale and slow zero only, no derivative columns to absorb a lag
    /// ([`Self::dynamics_rss`]).
    dynamics: Regression,
    /// The sensor's noise, nm: the RMS residual of the nominal (linear) path on the train
    /// samples.
    pub sigma_nm: f64,
    /// χ² (train, held-out) of the nominal path.
    pub nominal: (f64, f64),
}

impl HeightWitness {
    /// The witness of `sensor_nm` beside `drive_v`, both sampled at `fs_hz`; `None` when the
    /// sensor is too short, not finite, or explains nothing (a flat column).
    pub fn new(
        drive_v: &[f64],
        sensor_nm: &[f64],
        fs_hz: f64,
        train: &[usize],
        held: &[usize],
    ) -> Option<Self> {
        let n = drive_v.len();
        if n < 8 * NUISANCE || sensor_nm.len() != n || !finite(drive_v) || !finite(sensor_nm) {
            return None;
        }
        let d1 = central_difference(drive_v, fs_hz);
        let d2 = central_difference(&d1, fs_hz);
        let mut cols = slow_zero(n).to_vec();
        let dynamics = Regression::new(sensor_nm, &cols, train, held)?;
        cols.extend([d1, d2]);
        let fit = Regression::new(sensor_nm, &cols, train, held)?;
        let sigma_nm = fit.noise_scale(&[drive_v])?;
        let nominal = fit.chi2(&[drive_v], sigma_nm)?;
        Some(Self {
            fit,
            dynamics,
            sigma_nm,
            nominal,
        })
    }

    /// This witness with its noise scale and nominal χ² read off `path_nm` (the nominal
    /// model's stage path, its linear dynamics carried) where that fits the sensor better than
    /// the drive does: beside a stage slow against the excitation, the drive's two derivative
    /// columns do not follow its dynamics, and the residual they leave is the stage's, not the
    /// sensor's noise. Itself otherwise.
    pub fn read_along(&self, path_nm: &[f64]) -> Self {
        let better = self
            .fit
            .noise_scale(&[path_nm])
            .filter(|&sigma| sigma < self.sigma_nm)
            .and_then(|sigma| Some((sigma, self.fit.chi2(&[path_nm], sigma)?)));
        match better {
            Some((sigma_nm, nominal)) => Self {
                sigma_nm,
                nominal,
                ..self.clone()
            },
            None => self.clone(),
        }
    }

    /// Residual sums of squares (train, held-out; nm²) of the sensor against `path_nm`, a
    /// path through the model's own actuator dynamics, with a free scale and slow zero but
    /// no derivative columns: what the model says of the actuator's lag shows here. `None`
    /// for a path of the wrong length or one that is not finite.
    pub fn dynamics_rss(&self, path_nm: &[f64]) -> Option<(f64, f64)> {
        self.dynamics.residual_sums(&[path_nm])
    }

    /// The single-term creep that fits the sensor best on `path_nm`, a piezo path without
    /// creep (the drive through the nominal gain), its τ from `taus_s`. A creep adds
    /// `fraction·(path through a first-order lag of τ)`, linear in the fraction: for each τ the
    /// fraction is the ratio of the two paths' coefficients in one regression (beside the
    /// nuisance columns), and the τ with the least train residual is taken.
    /// Not a judgement (that is [`Self::chi2`] on a model the deflection fitted): where the
    /// deflection barely shows a creep, its own fit strays, and this is where its refit can
    /// start instead. `None` without a positive fraction.
    pub fn creep_fit(&self, path_nm: &[f64], fs_hz: f64, taus_s: &[f64]) -> Option<SensorCreep> {
        let first = *path_nm.first()?;
        let sigma2 = |rss: f64| rss / self.fit.dof(2);
        // (fraction, train RSS, sd of ln fraction) per τ; the sd from the creep column's
        // coefficient error, the gain's neglected.
        let fits: Vec<Option<(f64, f64, f64)>> = taus_s
            .iter()
            .map(|&tau| {
                let mut lag = FirstOrder::new(tau, fs_hz);
                lag.settle(first);
                let creep: Vec<f64> = path_nm.iter().map(|&x| lag.step(x)).collect();
                let f = self.fit.fit(&[path_nm, &creep])?;
                let rss = self.fit.sums(&f.residuals).0;
                let fraction = f.path_coefs[1] / f.path_coefs[0];
                let sd = sigma2(rss).sqrt() * f.path_sd_per_sigma[1] / f.path_coefs[1].abs();
                Some((fraction, rss, sd))
            })
            .collect();
        let rss = |k: usize| fits[k].map_or(f64::INFINITY, |x| x.1);
        let k = (0..fits.len())
            .filter(|&k| fits[k].is_some_and(|(f, _, _)| f > 0.0 && f.is_finite()))
            .min_by(|&a, &b| rss(a).total_cmp(&rss(b)))?;
        let (fraction, best, ln_fraction_sd) = fits[k]?;
        // ln τ: the curvature of the profile residual (the fraction refitted at each τ) about
        // the best grid point, χ² = RSS/σ² rising by one at one standard deviation.
        let neighbours = (
            k.checked_sub(1).and_then(|b| fits[b]),
            fits.get(k + 1).copied().flatten(),
        );
        let ln_tau_sd = match neighbours {
            (Some((_, below, _)), Some((_, above, _))) => {
                let h = (taus_s[k + 1] / taus_s[k]).ln();
                let curvature = (below + above - 2.0 * best) / (h * h);
                (2.0 * sigma2(best) / curvature).sqrt()
            }
            _ => f64::NAN,
        };
        Some(SensorCreep {
            fraction,
            tau_s: taus_s[k],
            ln_fraction_sd,
            ln_tau_sd,
        })
    }

    /// Degrees of freedom of the sensor's fit against one path with its lag
    /// ([`Self::dynamics_rss`]).
    pub fn dynamics_dof(&self) -> f64 {
        self.dynamics.dof(1)
    }

    /// χ² (train, held-out) of the sensor against `path_nm` with a free scale, beside the
    /// nuisance columns fitted on the train samples. `None` for a path of the wrong length
    /// or one that is not finite.
    pub fn chi2(&self, path_nm: &[f64]) -> Option<(f64, f64)> {
        self.fit.chi2(&[path_nm], self.sigma_nm)
    }
}

/// A model's reading of the hard reference: deflection (V) and whether the tip touches the
/// reference, per sample ([`super::model::Problem::simulate_reference`]).
pub type ReferencePath = (Vec<f64>, Vec<bool>);

/// The reference column, its nuisance columns and its noise scale.
#[derive(Debug, Clone)]
pub struct ReferenceWitness {
    fit: Regression,
    /// The reference channel's noise, V: the RMS residual of the nominal model's reference
    /// path on the train samples (of the whitened channel, where its noise is correlated).
    pub sigma_v: f64,
    /// χ² (train, held-out) of the nominal model's path.
    pub nominal: (f64, f64),
    /// How far beyond the sample's contact point the reference run touched its sample, nm,
    /// as every model's reading of the reference assumes it
    /// ([`super::model::Problem::simulate_reference`]): 0 as built, and the nominal model's
    /// best reading where the diagnosis finds the reference off the sample's contact point.
    pub contact_offset_nm: f64,
}

impl ReferenceWitness {
    /// The witness of `reference_v` for the nominal model's reference path `nominal`;
    /// `None` when the column is too short, not finite, never touched, or is the nominal
    /// path to rounding.
    pub fn new(
        reference_v: &[f64],
        nominal: &ReferencePath,
        train: &[usize],
        held: &[usize],
    ) -> Option<Self> {
        let n = reference_v.len();
        if n < 64 || !finite(reference_v) || !nominal.1.iter().any(|&c| c) {
            return None;
        }
        let mut fit = Regression::new(reference_v, &slow_zero(n), train, held)?;
        let touching = indicator(&nominal.1);
        let off_surface: Vec<bool> = nominal.1.iter().map(|&c| !c).collect();
        fit.whiten(&[&nominal.0, &touching], &off_surface);
        let sigma_v = fit.noise_scale(&[&nominal.0, &touching])?;
        let nominal = fit.chi2(&[&nominal.0, &touching], sigma_v)?;
        Some(Self {
            fit,
            sigma_v,
            nominal,
            contact_offset_nm: 0.0,
        })
    }

    /// χ² (train, held-out) of the reference column against `path` (free scale, free
    /// in-contact step) beside the nuisance columns. `None` for a path of the wrong length,
    /// one that is not finite, or one that never touches.
    pub fn chi2(&self, path: &ReferencePath) -> Option<(f64, f64)> {
        if !path.1.iter().any(|&c| c) {
            return None;
        }
        self.fit.chi2(&[&path.0, &indicator(&path.1)], self.sigma_v)
    }
}

fn finite(x: &[f64]) -> bool {
    x.iter().all(|v| v.is_finite())
}

/// The nuisance columns of a channel's slowly wandering zero: 1, t and t² (less its mean),
/// with t from −1 to 1 across the record.
fn slow_zero(n: usize) -> [Vec<f64>; 3] {
    let mid = 0.5 * (n.max(1) - 1) as f64;
    let t: Vec<f64> = (0..n).map(|i| (i as f64 - mid) / mid.max(1.0)).collect();
    let t2 = t.iter().map(|x| x * x - 1.0 / 3.0).collect();
    [vec![1.0; n], t, t2]
}

fn indicator(flags: &[bool]) -> Vec<f64> {
    flags.iter().map(|&c| if c { 1.0 } else { 0.0 }).collect()
}

/// 1 / RMS of `x`, or 0 for a column of zeros.
fn unit_rms_scale(x: &[f64]) -> f64 {
    let rms = (x.iter().map(|v| v * v).sum::<f64>() / x.len().max(1) as f64).sqrt();
    if rms > 0.0 {
        1.0 / rms
    } else {
        0.0
    }
}

fn unit_rms(x: &[f64]) -> Vec<f64> {
    let s = unit_rms_scale(x);
    x.iter().map(|v| v * s).collect()
}

/// Central difference per second (one-sided at the ends).
fn central_difference(x: &[f64], fs_hz: f64) -> Vec<f64> {
    let n = x.len();
    (0..n)
        .map(|i| {
            let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
            if b > a {
                (x[b] - x[a]) * fs_hz / (b - a) as f64
            } else {
                0.0
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;

    /// A drive of ramps and holds, a sensor that reads `40·v` plus `extra` plus 0.2 nm of
    /// white noise; alternate blocks of 500 samples train and hold out.
    fn case(extra: impl Fn(usize, f64) -> f64) -> (Vec<f64>, Vec<f64>, Vec<usize>, Vec<usize>) {
        let n = 20_000;
        let drive: Vec<f64> = (0..n)
            .map(|i| {
                let t = i as f64 / n as f64;
                10.0 * (t * 4.0).min(1.0) * (1.0 - ((t - 0.75) * 4.0).clamp(0.0, 1.0))
            })
            .collect();
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let sensor: Vec<f64> = drive
            .iter()
            .enumerate()
            .map(|(i, v)| 40.0 * v + extra(i, *v) + 0.2 * rng.sample::<f64, _>(StandardNormal))
            .collect();
        let (train, held): (Vec<usize>, Vec<usize>) = (0..n).partition(|i| (i / 500) % 2 == 0);
        (drive, sensor, train, held)
    }

    #[test]
    fn the_nominal_path_leaves_the_sensor_noise_and_a_creep_path_explains_a_creep() {
        let fs: f64 = 10_000.0;
        // A creep of 0.5 % of the position, settling with τ = 0.3 s.
        let creep = |drive: &[f64]| -> Vec<f64> {
            let a = (-1.0 / (fs * 0.3)).exp();
            let mut s = 0.0;
            drive
                .iter()
                .map(|v| {
                    s = a * s + (1.0 - a) * 0.005 * 40.0 * v;
                    s
                })
                .collect()
        };
        let (drive, _, train, held) = case(|_, _| 0.0);
        let c = creep(&drive);
        let (_, sensor, _, _) = case(|i, _| c[i]);
        let w = HeightWitness::new(&drive, &sensor, fs, &train, &held).unwrap();
        let with: Vec<f64> = drive.iter().zip(&c).map(|(v, c)| 40.0 * v + c).collect();
        let (tr, ho) = w.chi2(&with).unwrap();
        // The creep's 2 nm is ten times the noise, but at a free scale only its settling
        // after each ramp is left (during a ramp it is a lag, which v̇ takes): the nominal
        // path leaves 0.09 nm RMS of it.
        assert!(w.sigma_nm > 0.21, "σ {}", w.sigma_nm);
        // The right path leaves only the noise: its χ² per sample, against the nominal
        // residual's scale, is (0.2/σ)².
        let floor = (0.2 / w.sigma_nm).powi(2);
        assert!(
            (tr / train.len() as f64 - floor).abs() < 0.1 * floor,
            "{tr}"
        );
        assert!(
            (ho / held.len() as f64 - floor).abs() < 0.15 * floor,
            "{ho}"
        );
        assert!(w.nominal.1 - ho > 1000.0, "{:?} → {ho}", w.nominal);
    }

    #[test]
    fn a_drift_of_the_sensor_alone_is_no_evidence_for_a_creep() {
        let fs: f64 = 10_000.0;
        // The sensor drifts along a parabola of 3 nm: the nuisance absorbs it.
        let (drive, sensor, train, held) = case(|i, _| 3.0 * (i as f64 / 20_000.0).powi(2));
        let w = HeightWitness::new(&drive, &sensor, fs, &train, &held).unwrap();
        assert!((w.sigma_nm - 0.2).abs() < 0.01, "σ {}", w.sigma_nm);
        let per = w.nominal.1 / held.len() as f64;
        assert!((per - 1.0).abs() < 0.05, "held χ²/sample {per}");
        // A creep path fitted where there is none scores worse than the plain one.
        let a = (-1.0 / (fs * 0.3)).exp();
        let mut s = 0.0;
        let path: Vec<f64> = drive
            .iter()
            .map(|v| {
                s = a * s + (1.0 - a) * 0.005 * 40.0 * v;
                40.0 * v + s
            })
            .collect();
        let (_, ho) = w.chi2(&path).unwrap();
        assert!(ho - w.nominal.1 > 100.0, "{} → {ho}", w.nominal.1);
    }

    /// A hard reference read through a first-order stage (lag 40 µs at 8 kHz) with 2 mV of
    /// noise: the path with the lag leaves the noise alone, a nominal path without it leaves
    /// the lag's misfit (which sets the witness's scale); a contact point 0.5 nm off costs
    /// nothing (the in-contact step is free), and a path that never touches is no reading.
    #[test]
    fn the_reference_reads_the_chain_and_forgives_the_contact_point() {
        let fs: f64 = 8000.0;
        let n = 16_000;
        // Base position, nm: rest, approach, a 300 Hz and a 900 Hz line in contact, retract.
        let base: Vec<f64> = (0..n)
            .map(|i| {
                let t = i as f64 / fs;
                let ramp = 150.0 * (t / 0.5).min(1.0) * (1.0 - ((t - 1.5) / 0.5).clamp(0.0, 1.0));
                let tone = if (0.5..1.5).contains(&t) {
                    let w = 2.0 * std::f64::consts::PI;
                    10.0 * (w * 300.0 * t).sin() + 5.0 * (w * 900.0 * t).sin()
                } else {
                    0.0
                };
                ramp + tone - 50.0
            })
            .collect();
        let lagged = {
            let a = (-1.0 / (fs * 40e-6)).exp();
            let mut s = base[0];
            base.iter()
                .map(|&b| {
                    s = a * s + (1.0 - a) * b;
                    s
                })
                .collect::<Vec<f64>>()
        };
        let path = |z: &[f64], zc: f64| -> ReferencePath {
            let d = z.iter().map(|&z| (z - zc).max(0.0) / 60.0).collect();
            (d, z.iter().map(|&z| z > zc).collect())
        };
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let recorded: Vec<f64> = path(&lagged, 0.0)
            .0
            .iter()
            .map(|d| 0.3 + d + 2e-3 * rng.sample::<f64, _>(StandardNormal))
            .collect();
        let (train, held): (Vec<usize>, Vec<usize>) = (0..n).partition(|i| (i / 300) % 3 != 2);
        let nominal = path(&base, 0.0);
        let w = ReferenceWitness::new(&recorded, &nominal, &train, &held).unwrap();
        assert!(w.sigma_v > 2.5e-3, "σ {} V", w.sigma_v);
        let right = w.chi2(&path(&lagged, 0.0)).unwrap();
        let floor = (2e-3 / w.sigma_v).powi(2);
        let per = right.1 / held.len() as f64;
        assert!((per - floor).abs() < 0.1 * floor, "{per} vs {floor}");
        assert!(
            w.nominal.1 - right.1 > 1000.0,
            "{:?} → {right:?}",
            w.nominal
        );
        let off = w.chi2(&path(&lagged, 0.5)).unwrap();
        assert!(
            (off.1 - right.1).abs() < 0.02 * right.1,
            "{off:?} vs {right:?}"
        );
        let never = path(&lagged, 1e6);
        assert!(w.chi2(&never).is_none());
        assert!(ReferenceWitness::new(&recorded, &never, &train, &held).is_none());
        let mut bad = recorded.clone();
        bad[3] = f64::NAN;
        assert!(ReferenceWitness::new(&bad, &nominal, &train, &held).is_none());
    }

    /// A reference whose noise wanders (AR(1), ρ = 0.9) is whitened: its filter is that
    /// process's, and the nominal path leaves a held-out χ² of about one per sample against the
    /// whitened σ. A white one is fitted as recorded, also where the zero rises along each
    /// stretch off the surface and not in contact, which the record's slow parabola cannot
    /// follow (a misfit, not noise: each stretch is taken less its own line).
    #[test]
    fn a_wandering_reference_noise_is_whitened() {
        let n = 12_000;
        let nominal: ReferencePath = (0..n)
            .map(|i| {
                let z = 300.0 * (1.0 - (2.0 * i as f64 / n as f64 - 1.0).abs()) - 100.0;
                ((z.max(0.0)) / 60.0, z > 0.0)
            })
            .unzip();
        let (train, held): (Vec<usize>, Vec<usize>) = (0..n).partition(|i| (i / 300) % 3 != 2);
        // Off the surface for the first and the last sixth of the record.
        let stretch = n / 6;
        let witness = |rho: f64, rise: f64| {
            let mut rng = rand::rngs::StdRng::seed_from_u64(5);
            let mut e = 0.0;
            let recorded: Vec<f64> = nominal
                .0
                .iter()
                .enumerate()
                .map(|(i, d)| {
                    e = rho * e + 2e-3 * rng.sample::<f64, _>(StandardNormal);
                    let along = i.min(stretch) + i.saturating_sub(n - stretch);
                    0.3 + d + e + rise * along as f64 / stretch as f64
                })
                .collect();
            let w = ReferenceWitness::new(&recorded, &nominal, &train, &held).unwrap();
            let filter = w.fit.whitened.as_ref().map(|x| x.filter.clone());
            (filter, w.nominal.1 / held.len() as f64)
        };
        let (filter, per) = witness(0.9, 0.0);
        let filter = filter.expect("a wandering noise is whitened");
        assert!((filter[1] + 0.9).abs() < 0.05, "{filter:?}");
        assert!((per - 1.0).abs() < 0.1, "{per}");
        for rise in [0.0, 4e-3] {
            let (filter, per) = witness(0.0, rise);
            assert_eq!(filter, None, "rise {rise}");
            assert!((per - 1.0).abs() < 0.1, "{per}");
        }
    }

    #[test]
    fn bad_columns_give_no_witness() {
        let (drive, mut sensor, train, held) = case(|_, _| 0.0);
        assert!(HeightWitness::new(&drive, &sensor[..100], 1e4, &train, &held).is_none());
        sensor[7] = f64::NAN;
        assert!(HeightWitness::new(&drive, &sensor, 1e4, &train, &held).is_none());
        let w = HeightWitness::new(&drive, &drive, 1e4, &train, &held);
        // A sensor that is exactly the drive has no noise to scale by.
        assert!(w.is_none());
        let scaled: Vec<f64> = drive.iter().map(|v| 40.0 * v).collect();
        assert!(HeightWitness::new(&drive, &scaled, 1e4, &train, &held).is_none());
    }
}
