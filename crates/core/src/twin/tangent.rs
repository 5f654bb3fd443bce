//! Forward sensitivities of a twin's deflection: how every sample of the detector's reading
//! moves with the material's parameters, the contact point and the actuator's gain, carried
//! along one run ([`super::Twin::step_with_tangent`]) instead of one run per parameter.
//!
//! A fit's Jacobian by finite differences costs one simulation per parameter, and the
//! Jacobians are 80–85 % of a slow diagnosis's simulations (`docs/diagnosis-speed.md`). The
//! nominal material, the contact point and the gain are in every fit; their columns come
//! from one run carrying them. The math:
//!
//! - the material's state steps linearly, and so do its derivatives
//!   ([`MaterialSensitivity`]), which give `∂α` and `∂β` of this sample's `y = α·u + β`;
//! - the contact root of `g(d) = f(h) − α·cf·(K·d + F) − β` (`f` the filmed shape function,
//!   `h = gap − d`) moves as `∂d = −g_θ/g_d`, where `g_d` is the slope the Newton solve
//!   holds and `g_θ = f′(h)·∂gap − ∂α·cf·(K·d + F) − ∂β`;
//! - the gap moves with the contact point (−1 nm per nm) and with the gain (the base is
//!   homogeneous of degree one in the gain: Bouc–Wen, creep and the modes all scale with it,
//!   so `∂base/∂ln g = base`);
//! - the contact's input `u = cf·(K·d + F)` moves as `cf·K·∂d`, and feeds the state's
//!   derivatives for the next sample; out of contact `u = 0` and the free lever's deflection
//!   (`F_ext/K`) does not move;
//! - off the surface, an adhesive neck holds the tip by a spring from its foot (where the
//!   contact let go, which moves as the gap and the pull-off did then), and a long-range
//!   pull balances the lever at the root of `K·(gap − depth + x) + F·e^(−x/λ)`, the depth
//!   where the recovering surface stands (`f(depth) = β`): each moves as its root does;
//! - the detector's delay is linear: each derivative goes through a delay line of its own;
//! - a parameter that moves the drive itself (the diagnosis's nominal actuator dynamics act
//!   on the drive before the twin) moves the base through the actuator, which is linear
//!   without hysteresis: its derivative goes through an actuator of its own, at rest at
//!   zero, as the caller hands it in ([`super::Twin::step_with_tangent_and_drive`]).
//!
//! A contact gained or lost between samples is a jump no derivative sees, and so are a
//! neck breaking and a tip snapping onto or off the surface. The lever's mode, a detector
//! with noise, nonlinearity or quantisation, and a hysteretic actuator under a drive
//! parameter are not followed: [`super::Twin::tangent_of`] gives no tangent for a twin with
//! any of them, and its caller takes finite differences there.

use super::actuator::{Actuator, ActuatorConfig};
use super::detector::{Detector, DetectorConfig};
use super::material::{MaterialSensitivity, MaterialState, OwnParam};

/// One parameter a [`Tangent`] carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TangentParam {
    /// ln J0, the material's long-time compliance, its terms' J held.
    LnLongTimeCompliance,
    /// ln J of the material's term `i` (slowest first, as [`crate::prony::PronySeries`]
    /// orders them), J0 held.
    LnTermCompliance(usize),
    /// ln τ of the material's term `i`.
    LnTermTau(usize),
    /// The sample's contact point, nm.
    ContactPoint,
    /// ln of the actuator's gain.
    LnGain,
    /// A parameter of the drive `j` ([`super::Twin::step_with_tangent_and_drive`]).
    Drive(usize),
    /// ln of the DMT adhesion's pull-off force (`sample.adhesion_nn`).
    LnAdhesion,
    /// The surface drift's rate, nm/s (`sample.surface_drift_nm_per_s`).
    DriftRate,
    /// The surface drift's curvature, nm/s² (`sample.surface_drift_curvature_nm_per_s2`).
    DriftCurvature,
    /// ln of the film's thickness (`sample.thickness_nm`).
    LnFilmThickness,
    /// ln of an adhesive neck's stiffness (`sample.neck.stiffness_n_per_m`).
    LnNeckStiffness,
    /// ln of the long-range adhesion's decay length (`sample.adhesion_range_nm`).
    LnAdhesionRange,
    /// A parameter `j` that moves the base by what the caller hands in
    /// ([`super::Twin::step_with_tangent_moved`]): the actuator's own (its modes, creep and
    /// hysteresis), whose derivative the caller takes on the actuator alone.
    Base(usize),
}

/// The sensitivities of a running twin; see the module's docs.
#[derive(Debug, Clone)]
pub struct Tangent {
    pub(super) material: MaterialSensitivity,
    /// Every parameter, in order: the material's, then the others.
    params: Vec<TangentParam>,
    /// `(∂α, ∂β)` of this sample, per parameter (scratch).
    pub(super) affine: Vec<(f64, f64)>,
    /// `∂u` of this sample, per parameter (scratch).
    pub(super) du: Vec<f64>,
    /// `∂d/∂θ` of this sample's static deflection, m.
    pub(super) deflection_m: Vec<f64>,
    /// `∂(deflection reading)/∂θ` of this sample, V.
    deflection_v: Vec<f64>,
    /// One delay line per parameter, where the detector delays.
    delays: Vec<Detector>,
    /// One actuator per drive parameter, stepping the drive's derivative.
    drive_actuators: Vec<Actuator>,
    /// The base's derivatives in the drive parameters this sample, nm.
    drive_base_nm: Vec<f64>,
    /// The base's derivatives in the `Base` parameters this sample, nm.
    base_given_nm: Vec<f64>,
    /// While a neck holds the tip: its foot's derivatives, m, per parameter.
    pub(super) neck_foot_m: Vec<f64>,
    /// Whether a sample has been read out: the delay lines settle at the first.
    started: bool,
}

impl Tangent {
    /// All derivatives zero, for a twin at rest whose material is `material`, whose detector
    /// is `detector` (only its delay is read) and that runs at `fs_hz`. It carries the
    /// parameters `carried` (the material's own first, in the order given, then the others
    /// in theirs), or where `None` every material parameter and then `others`; `others` (none
    /// of the material's) are the parameters the caller may ask of this twin, `carried` a
    /// choice among them and the material's.
    ///
    /// The drive's parameters among `others` (`Drive(0)`, `Drive(1)`, … in order) go through
    /// copies of `actuator` (which must have no hysteresis: its response is then linear in
    /// the drive), carried or not: each takes the drive's derivative by its index.
    pub(super) fn new(
        material: &MaterialState,
        detector: &DetectorConfig,
        actuator: &ActuatorConfig,
        others: &[TangentParam],
        carried: Option<&[TangentParam]>,
        fs_hz: f64,
    ) -> Self {
        let drive_params = (others.iter())
            .filter(|p| matches!(p, TangentParam::Drive(_)))
            .count();
        debug_assert!(
            drive_params == 0 || (actuator.hysteresis.is_none() && actuator.play.is_none())
        );
        let terms = material.terms();
        // The material's own parameter a carried one is, if it is one.
        let own = |p: TangentParam| match p {
            TangentParam::LnLongTimeCompliance => Some(OwnParam::LongTime),
            TangentParam::LnTermCompliance(i) => Some(OwnParam::Compliance(i)),
            TangentParam::LnTermTau(i) => Some(OwnParam::Tau(i)),
            _ => None,
        };
        let all: Vec<TangentParam> = match carried {
            Some(carried) => (carried.iter())
                .filter(|&&p| own(p).is_some())
                .chain(carried.iter().filter(|&&p| own(p).is_none()))
                .copied()
                .collect(),
            None => std::iter::once(TangentParam::LnLongTimeCompliance)
                .chain((0..terms).map(TangentParam::LnTermCompliance))
                .chain((0..terms).map(TangentParam::LnTermTau))
                .chain(others.iter().copied())
                .collect(),
        };
        let material_params: Vec<OwnParam> = all.iter().filter_map(|&p| own(p)).collect();
        let extra = all.len() - material_params.len();
        let sens = MaterialSensitivity::carrying(material, &material_params, extra);
        let params = sens.params();
        let delay = DetectorConfig {
            delay_s: detector.delay_s,
            ..DetectorConfig::default()
        };
        let mut at_rest = Actuator::new(actuator, fs_hz);
        at_rest.settle(0.0);
        Self {
            params: all,
            neck_foot_m: vec![0.0; params],
            base_given_nm: vec![
                0.0;
                others
                    .iter()
                    .filter(|p| matches!(p, TangentParam::Base(_)))
                    .count()
            ],
            started: false,
            drive_actuators: vec![at_rest; drive_params],
            drive_base_nm: vec![0.0; drive_params],
            affine: vec![(0.0, 0.0); params],
            du: vec![0.0; params],
            deflection_m: vec![0.0; params],
            deflection_v: vec![0.0; params],
            delays: if detector.delay_s > 0.0 {
                (0..params)
                    .map(|_| Detector::new(&delay, fs_hz, 0))
                    .collect()
            } else {
                Vec::new()
            },
            material: sens,
        }
    }

    /// How many parameters are carried.
    pub fn params(&self) -> usize {
        self.du.len()
    }

    /// The parameters, in the order [`Self::deflection_v`] gives them.
    pub fn param(&self, q: usize) -> TangentParam {
        self.params[q]
    }

    /// The index of `p`, if carried.
    pub fn index(&self, p: TangentParam) -> Option<usize> {
        self.params.iter().position(|&q| q == p)
    }

    /// Puts the drive's derivatives at rest at `dv` (one per drive parameter), as the twin
    /// settles at the drive's first sample.
    pub(super) fn settle_drive(&mut self, dv: &[f64]) {
        for (a, &d) in self.drive_actuators.iter_mut().zip(dv) {
            a.settle(d);
        }
    }

    /// Takes this sample's base derivatives in the `Base` parameters, nm.
    pub(super) fn set_base(&mut self, dbase_nm: &[f64]) {
        for (out, &d) in self.base_given_nm.iter_mut().zip(dbase_nm) {
            *out = d;
        }
    }

    /// Steps the drive's derivatives `dv` (one per drive parameter) through the actuators.
    pub(super) fn step_drive(&mut self, dv: &[f64]) {
        for ((a, &d), out) in (self.drive_actuators.iter_mut())
            .zip(dv)
            .zip(&mut self.drive_base_nm)
        {
            *out = a.step(d);
        }
    }

    /// How the gap (m) moves with parameter `q` at base position `base_nm`, `t_s` after the
    /// twin settled.
    pub(super) fn gap_derivative_m(&self, q: usize, base_nm: f64, t_s: f64) -> f64 {
        match self.params[q] {
            TangentParam::ContactPoint => -1e-9,
            TangentParam::LnGain => base_nm * 1e-9,
            TangentParam::Drive(j) => self.drive_base_nm[j] * 1e-9,
            TangentParam::Base(j) => self.base_given_nm[j] * 1e-9,
            // The surface moves toward the tip by `v·t + c·t²`.
            TangentParam::DriftRate => t_s * 1e-9,
            TangentParam::DriftCurvature => t_s * t_s * 1e-9,
            _ => 0.0,
        }
    }

    /// Whether a parameter moves the film's factor (the caller then works out its slope).
    pub(super) fn has_film(&self) -> bool {
        self.params.contains(&TangentParam::LnFilmThickness)
    }

    /// The last sample's derivatives of the detector's reading, V, one per parameter.
    pub fn deflection_v(&self) -> &[f64] {
        &self.deflection_v
    }

    /// Takes this sample's static deflection derivatives (in `deflection_m`) to the reading:
    /// nm over the sensitivity (nm/V), then the detector's delay.
    pub(super) fn read_out(&mut self, sensitivity_nm_per_v: f64) {
        for (q, (out, &dd)) in (self.deflection_v.iter_mut())
            .zip(&self.deflection_m)
            .enumerate()
        {
            let v = dd * 1e9 / sensitivity_nm_per_v;
            *out = match self.delays.get_mut(q) {
                Some(line) => {
                    // The twin settled its delay line at its deflection at rest, which its
                    // first sample repeats (the drive starts where it settled): so do these.
                    if !self.started {
                        line.settle(v);
                    }
                    line.step(v)
                }
                None => v,
            };
        }
        self.started = true;
    }
}
