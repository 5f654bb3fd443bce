//! The piezo actuator: static gain, hysteresis (Bouc–Wen, or play operators), creep and
//! resonant modes.
//!
//! Drive voltage `v` → quasi-static displacement `x_qs = g·v_p − h + c` (nm), where `v_p` is
//! the drive through the play operators (`v` without them), `h` the Bouc–Wen hysteretic
//! state and `c` the creep state → resonant modes in series → position.
//! Positive displacement moves the cantilever base toward the sample.

use super::dynamics::{FirstOrder, InputHold, SecondOrder};
use serde::{Deserialize, Serialize};

/// Actuator parameters, as in the twin's TOML `[actuator]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActuatorConfig {
    /// Static gain, nm/V.
    pub gain_nm_per_v: f64,
    /// Resonant modes, applied in series (empty: an ideal, infinitely fast actuator).
    #[serde(default)]
    pub modes: Vec<ResonantMode>,
    /// Bouc–Wen rate-independent hysteresis (absent: none).
    #[serde(default)]
    pub hysteresis: Option<BoucWen>,
    /// Creep toward a slightly larger static gain (absent: none).
    #[serde(default)]
    pub creep: Option<Creep>,
    /// Prandtl–Ishlinskii hysteresis: the drive through weighted play operators (absent:
    /// none). Beside `hysteresis` both act.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub play: Option<PlayHysteresis>,
}

/// One resonance of the scanner.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ResonantMode {
    pub freq_hz: f64,
    pub q: f64,
    /// How the mode's input moves between samples (`input = "ramped"`; default `"held"`).
    /// The diagnosis's nominal actuator roll-off is ramped, so that its lag shows below a
    /// sample ([`InputHold`]).
    #[serde(default, skip_serializing_if = "InputHold::is_held")]
    pub input: InputHold,
    /// A mode of part of the frame or stage rather than of the whole scanner: the motion
    /// passes through it above the resonance as below, and is amplified by this factor at
    /// it — `(s² + (ω0·g/Q)s + ω0²)/(s² + (ω0/Q)s + ω0²)` with `g = peak_gain`. Absent: the
    /// scanner's own mode, which rolls off above the resonance.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub peak_gain: Option<f64>,
    /// A mode carrying only part of the motion (a compliant mount under part of a stage):
    /// this fraction κ rides on it, the rest passes straight through —
    /// `(1 − κ) + κ·ω0²/(s² + (ω0/Q)s + ω0²)`, unit gain below the resonance and `1 − κ`
    /// above. Absent: the whole motion (κ = 1). Ignored beside `peak_gain`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fraction: Option<f64>,
}

impl ResonantMode {
    /// A mode with its input held over each sample, as every configured mode is by default.
    pub fn held(freq_hz: f64, q: f64) -> Self {
        Self {
            freq_hz,
            q,
            input: InputHold::Held,
            peak_gain: None,
            fraction: None,
        }
    }

    /// A held mode that carries a `fraction` of the motion ([`Self::fraction`]).
    pub fn partial(freq_hz: f64, q: f64, fraction: f64) -> Self {
        Self {
            fraction: Some(fraction),
            ..Self::held(freq_hz, q)
        }
    }

    /// A held mode that passes the motion through above the resonance, `peak_gain` at it.
    pub fn peaking(freq_hz: f64, q: f64, peak_gain: f64) -> Self {
        Self {
            peak_gain: Some(peak_gain),
            ..Self::held(freq_hz, q)
        }
    }
}

/// Bouc–Wen model in its piezo form: `dh = α·g·dv − β·|dv|·h − γ·dv·|h|` (h in nm).
/// It depends on increments of `v` only, so its loops are rate independent.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BoucWen {
    /// Dimensionless; loop width scales with it (0.1–0.2 typical of PZT).
    pub alpha: f64,
    /// 1/V.
    pub beta: f64,
    /// 1/V.
    pub gamma: f64,
}

/// Prandtl–Ishlinskii hysteresis in the form `v_p = v + a·(Σᵢ wᵢ·Pᵢ(v) − v)`: [`PLAY_OPERATORS`]
/// play (backlash) operators `Pᵢ` of radii `rᵢ = radius_v·i/n` (i = 1…n), their weights
/// `wᵢ ∝ exp(−shape·(i − 1)/(n − 1))` summing to one. A play operator's output follows the
/// drive only once it has moved `rᵢ` away, so `v_p` lags each reversal of the drive and its
/// loop is wide by `a` times the radii. Unlike Bouc–Wen's, the loop's branches are made of
/// straight pieces and it closes exactly on every reversal: a stage with dry friction or
/// domain-wall pinning in steps. Rate independent, as every play operator is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PlayHysteresis {
    /// Share of the drive that goes through the operators, dimensionless (0 none, 1 all).
    pub amplitude: f64,
    /// The widest operator's radius, V.
    pub radius_v: f64,
    /// How the weights fall from the narrowest operator to the widest (0: equal weights;
    /// positive: the narrow ones weigh more).
    pub shape: f64,
}

/// Play operators of [`PlayHysteresis`].
pub const PLAY_OPERATORS: usize = 8;

impl PlayHysteresis {
    /// `(radius_v, weight)` of each operator.
    pub fn operators(&self) -> [(f64, f64); PLAY_OPERATORS] {
        let n = PLAY_OPERATORS as f64;
        let raw = |i: usize| (-self.shape * i as f64 / (n - 1.0)).exp();
        let total: f64 = (0..PLAY_OPERATORS).map(raw).sum();
        std::array::from_fn(|i| (self.radius_v * (i + 1) as f64 / n, raw(i) / total))
    }

    /// Area (V², per unit gain) of the loop the drive through the operators draws against
    /// the drive over a swing of ±`amplitude_v`: each operator's parallelogram `4r(A − r)`
    /// (none for an operator wider than the swing), weighted, times `amplitude`.
    pub fn loop_area(&self, amplitude_v: f64) -> f64 {
        let parallelogram = |r: f64| 4.0 * r.min(amplitude_v) * (amplitude_v - r).max(0.0);
        (self.operators().iter())
            .map(|&(r, w)| w * parallelogram(r))
            .sum::<f64>()
            * self.amplitude
    }
}

/// Linear creep: an extra `fraction·g·v` approached with time constant `tau_s`; or, with
/// `decades`, the logarithmic creep of a real piezo (`x(t) ≈ g·v·(1 + γ·log10(t/t0))` after a
/// step): `fraction` per decade of time, one first-order term per decade at `tau_s`,
/// `10·tau_s`, … (`decades` terms, so `decades·fraction` in all).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Creep {
    pub fraction: f64,
    pub tau_s: f64,
    /// Decades of a logarithmic creep (absent: a single time constant).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub decades: Option<u32>,
}

/// The most decades a logarithmic creep spans.
pub const MAX_CREEP_DECADES: u32 = 12;

impl Creep {
    /// `(fraction, tau_s)` of each first-order term.
    pub fn terms(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        (0..self.decades.unwrap_or(1)).map(|k| (self.fraction, self.tau_s * 10f64.powi(k as i32)))
    }
}

/// Actuator state.
#[derive(Debug, Clone)]
pub struct Actuator {
    cfg: ActuatorConfig,
    modes: Vec<SecondOrder>,
    /// One first-order lag per creep term, each with its share of `g·v`.
    creep: Vec<(f64, FirstOrder)>,
    h_nm: f64,
    /// Each play operator's output, V ([`PlayHysteresis`]).
    play_v: [f64; PLAY_OPERATORS],
    last_v: f64,
    position_nm: f64,
}

impl Actuator {
    pub fn new(cfg: &ActuatorConfig, fs_hz: f64) -> Self {
        Self {
            modes: cfg
                .modes
                .iter()
                .map(|m| {
                    let mode = SecondOrder::with_hold(m.freq_hz, m.q, fs_hz, m.input);
                    match (m.peak_gain, m.fraction) {
                        (Some(g), _) => mode.peaking(g),
                        (None, Some(k)) => mode.partial(k),
                        (None, None) => mode,
                    }
                })
                .collect(),
            creep: cfg
                .creep
                .iter()
                .flat_map(|c| c.terms())
                .map(|(f, tau)| (f, FirstOrder::new(tau, fs_hz)))
                .collect(),
            cfg: cfg.clone(),
            h_nm: 0.0,
            play_v: [0.0; PLAY_OPERATORS],
            last_v: 0.0,
            position_nm: 0.0,
        }
    }

    /// Puts the actuator at rest at voltage `v` (hysteresis state cleared).
    pub fn settle(&mut self, v: f64) {
        self.last_v = v;
        self.h_nm = 0.0;
        self.play_v = [v; PLAY_OPERATORS];
        let gv = self.cfg.gain_nm_per_v * v;
        let mut creep = 0.0;
        for (share, f) in &mut self.creep {
            f.settle(*share * gv);
            creep += *share * gv;
        }
        let x = gv + creep;
        for m in &mut self.modes {
            m.settle(x);
        }
        self.position_nm = x;
    }

    /// Quasi-static displacement after the hysteresis and creep update for voltage `v`.
    fn quasi_static(&mut self, v: f64) -> f64 {
        let g = self.cfg.gain_nm_per_v;
        if let Some(bw) = self.cfg.hysteresis {
            let dv = v - self.last_v;
            // Split large increments so the explicit update stays accurate (rate independence
            // holds for any split: only the path in v matters).
            let n = ((dv.abs() / 0.01).ceil() as usize).clamp(1, 64);
            let step = dv / n as f64;
            for _ in 0..n {
                self.h_nm += bw.alpha * g * step
                    - bw.beta * step.abs() * self.h_nm
                    - bw.gamma * step * self.h_nm.abs();
            }
        }
        self.last_v = v;
        let v = match self.cfg.play {
            Some(p) => {
                let mut through = 0.0;
                for (y, (r, w)) in self.play_v.iter_mut().zip(p.operators()) {
                    *y = y.max(v - r).min(v + r);
                    through += w * *y;
                }
                v + p.amplitude * (through - v)
            }
            None => v,
        };
        let creep: f64 = self
            .creep
            .iter_mut()
            .map(|(share, f)| f.step(*share * g * v))
            .sum();
        g * v - self.h_nm + creep
    }

    /// The base positions (nm) over `drive` (V), from rest at its first sample, as the twin
    /// starts ([`crate::twin::Twin`] settles there): from rest at zero, the first sample
    /// would be a step of the whole offset, which rings every mode and creep term and
    /// strokes the hysteresis.
    pub fn path(cfg: &ActuatorConfig, fs_hz: f64, drive: &[f64]) -> Vec<f64> {
        let mut actuator = Self::new(cfg, fs_hz);
        actuator.settle(drive.first().copied().unwrap_or(0.0));
        drive.iter().map(|&v| actuator.step(v)).collect()
    }

    /// Advances one sample with drive `v` volts; returns the base position, nm.
    pub fn step(&mut self, v: f64) -> f64 {
        let mut x = self.quasi_static(v);
        for m in &mut self.modes {
            x = m.step(x);
        }
        self.position_nm = x;
        x
    }

    pub fn position_nm(&self) -> f64 {
        self.position_nm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hysteretic() -> ActuatorConfig {
        ActuatorConfig {
            gain_nm_per_v: 100.0,
            modes: vec![],
            hysteresis: Some(BoucWen {
                alpha: 0.15,
                beta: 0.05,
                gamma: 0.02,
            }),
            creep: None,
            play: None,
        }
    }

    /// Area of the (v, x) loop over the last period of a sine sweep.
    fn loop_area(cfg: &ActuatorConfig, freq_hz: f64, fs_hz: f64) -> f64 {
        let mut a = Actuator::new(cfg, fs_hz);
        a.settle(0.0);
        let per = (fs_hz / freq_hz) as usize;
        let mut pts = Vec::new();
        for k in 0..3 * per {
            let v = 5.0 * (2.0 * std::f64::consts::PI * freq_hz * k as f64 / fs_hz).sin();
            let x = a.step(v);
            if k >= 2 * per {
                pts.push((v, x));
            }
        }
        // Shoelace formula.
        let n = pts.len();
        (0..n)
            .map(|i| pts[i].0 * pts[(i + 1) % n].1 - pts[(i + 1) % n].0 * pts[i].1)
            .sum::<f64>()
            .abs()
            / 2.0
    }

    /// A Bouc–Wen loop has non-zero area and the same area at 1 Hz and 100 Hz, sampled
    /// differently: rate independence.
    #[test]
    fn bouc_wen_loop_is_rate_independent() {
        let cfg = hysteretic();
        let slow = loop_area(&cfg, 1.0, 4000.0);
        let fast = loop_area(&cfg, 100.0, 8000.0);
        let full = 2.0 * 5.0 * 2.0 * 5.0 * 100.0; // bounding box of the loop, V·nm
        assert!(slow > 0.01 * full, "loop area {slow} V·nm is too small");
        assert!(
            (slow - fast).abs() / slow < 0.02,
            "slow {slow} vs fast {fast}"
        );
        let linear = ActuatorConfig {
            hysteresis: None,
            ..cfg
        };
        assert!(loop_area(&linear, 1.0, 4000.0) < 1e-6 * full);
    }

    /// A play operator of radius r under a sine of amplitude A draws a parallelogram of
    /// area 4·r·(A − r) in (v, output); the actuator's loop is that, weighted, times g·a —
    /// at 1 Hz and at 100 Hz alike (rate independence). Without the operators: no loop.
    #[test]
    fn play_operators_draw_their_parallelograms() {
        let play = PlayHysteresis {
            amplitude: 0.1,
            radius_v: 2.0,
            shape: 0.0,
        };
        let cfg = ActuatorConfig {
            gain_nm_per_v: 100.0,
            modes: vec![],
            hysteresis: None,
            creep: None,
            play: Some(play),
        };
        // Every operator is narrower than the swing here (2 V of 5).
        let expected = play.loop_area(5.0) * 100.0;
        for (freq_hz, fs_hz) in [(1.0, 4000.0), (100.0, 8000.0)] {
            let area = loop_area(&cfg, freq_hz, fs_hz);
            assert!(
                (area / expected - 1.0).abs() < 0.01,
                "{area} V·nm at {freq_hz} Hz against {expected}"
            );
        }
        let linear = ActuatorConfig { play: None, ..cfg };
        assert!(loop_area(&linear, 1.0, 4000.0) < 1e-6 * expected);
    }

    /// A voltage step creeps toward (1 + fraction)·g·v with the configured time constant.
    #[test]
    fn creep_follows_first_order() {
        let cfg = ActuatorConfig {
            gain_nm_per_v: 50.0,
            modes: vec![],
            hysteresis: None,
            creep: Some(Creep {
                decades: None,
                fraction: 0.1,
                tau_s: 0.5,
            }),
            play: None,
        };
        let fs = 1000.0;
        let mut a = Actuator::new(&cfg, fs);
        a.settle(0.0);
        let mut x = 0.0;
        for _ in 0..500 {
            x = a.step(2.0);
        }
        let expected = 100.0 + 10.0 * (1.0 - (-1.0f64).exp());
        assert!((x - expected).abs() < 1e-9, "{x} vs {expected}");
    }

    /// A logarithmic creep over five decades: the step response is the sum of its five
    /// first-order terms, and inside their span it grows by about `fraction·g·v` per decade
    /// of time, as a real piezo's does.
    #[test]
    fn logarithmic_creep_grows_per_decade() {
        let creep = Creep {
            fraction: 0.02,
            tau_s: 0.01,
            decades: Some(5),
        };
        let cfg = ActuatorConfig {
            gain_nm_per_v: 50.0,
            modes: vec![],
            hysteresis: None,
            creep: Some(creep),
            play: None,
        };
        let fs = 1000.0;
        let mut a = Actuator::new(&cfg, fs);
        a.settle(0.0);
        let gv = 100.0;
        let mut at = std::collections::BTreeMap::new();
        for k in 1..=10_000 {
            let x = a.step(2.0);
            if [100, 1000, 10_000].contains(&k) {
                at.insert(k, x);
            }
        }
        for (&k, &x) in &at {
            let t = k as f64 / fs;
            let expected = gv
                * (1.0
                    + (0..5)
                        .map(|j| 0.02 * (1.0 - (-t / (0.01 * 10f64.powi(j))).exp()))
                        .sum::<f64>());
            assert!((x - expected).abs() < 1e-9, "t {t}: {x} vs {expected}");
        }
        for (lo, hi) in [(100, 1000), (1000, 10_000)] {
            let per_decade = (at[&hi] - at[&lo]) / gv;
            assert!((per_decade - 0.02).abs() < 0.2 * 0.02, "{per_decade}");
        }
    }
}
