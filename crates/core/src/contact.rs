//! Contact transforms: from force P and indentation h to the linear pair (u, y).
//!
//! Lee–Radok's extension of Hertz contact makes the map `u → y` linear and time invariant,
//! with the creep compliance as its impulse-response kernel (the paper's eq. 3):
//!
//! * sphere of radius R: `h^{3/2} = 3(1−ν²)/(4√R) · ∫ J(t−τ) dP(τ)`, so
//!   `u = 3(1−ν²)P/(4√R)` (= `9P/(16√R)` at ν = 0.5) and `y = h^{3/2}`;
//! * cone of half-angle α (Sneddon): `h² = π(1−ν²)/(2 tan α) · ∫ J dP`, so
//!   `u = π(1−ν²)P/(2 tan α)` and `y = h²`.
//!
//! With these, `J` is the Young's creep compliance of the material (1/Pa). Units: P in N,
//! h in m, R in m; u comes out in N/√m (sphere) or N (cone), y in m^{3/2} or m².

use serde::{Deserialize, Serialize};

/// Tip geometry for the contact transform.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "lowercase")]
pub enum TipGeometry {
    /// Spherical tip (Hertz), radius in metres.
    Sphere { radius_m: f64 },
    /// Conical tip (Sneddon), half-opening angle in radians.
    Cone { half_angle_rad: f64 },
}

/// A contact transform: tip geometry plus the sample's Poisson ratio.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Contact {
    pub tip: TipGeometry,
    pub poisson_ratio: f64,
}

impl Contact {
    /// Sphere with the paper's incompressible sample (ν = 0.5).
    pub fn sphere(radius_m: f64) -> Self {
        Self {
            tip: TipGeometry::Sphere { radius_m },
            poisson_ratio: 0.5,
        }
    }

    /// Cone with an incompressible sample (ν = 0.5).
    pub fn cone(half_angle_rad: f64) -> Self {
        Self {
            tip: TipGeometry::Cone { half_angle_rad },
            poisson_ratio: 0.5,
        }
    }

    /// Factor `c` with `u = c·P`.
    pub fn force_factor(&self) -> f64 {
        let nu = 1.0 - self.poisson_ratio * self.poisson_ratio;
        match self.tip {
            TipGeometry::Sphere { radius_m } => 3.0 * nu / (4.0 * radius_m.sqrt()),
            TipGeometry::Cone { half_angle_rad } => {
                std::f64::consts::PI * nu / (2.0 * half_angle_rad.tan())
            }
        }
    }

    /// Exponent of the indentation in `y = h^k`: 3/2 for a sphere, 2 for a cone.
    pub fn indentation_exponent(&self) -> f64 {
        match self.tip {
            TipGeometry::Sphere { .. } => 1.5,
            TipGeometry::Cone { .. } => 2.0,
        }
    }

    /// `u` from a force in newtons.
    pub fn u_from_force(&self, force_n: f64) -> f64 {
        self.force_factor() * force_n
    }

    /// Force in newtons from `u`.
    pub fn force_from_u(&self, u: f64) -> f64 {
        u / self.force_factor()
    }

    /// `y` from an indentation in metres; no contact (h ≤ 0) gives 0.
    pub fn y_from_indentation(&self, h_m: f64) -> f64 {
        if h_m <= 0.0 {
            0.0
        } else {
            h_m.powf(self.indentation_exponent())
        }
    }

    /// Indentation in metres from `y` (negative y clamps to 0: no contact).
    pub fn indentation_from_y(&self, y: f64) -> f64 {
        if y <= 0.0 {
            0.0
        } else {
            y.powf(1.0 / self.indentation_exponent())
        }
    }

    /// Static (elastic) indentation under force `force_n` on a material of compliance
    /// `compliance_per_pa`: the classic Hertz / Sneddon result.
    pub fn elastic_indentation(&self, force_n: f64, compliance_per_pa: f64) -> f64 {
        self.indentation_from_y(compliance_per_pa * self.u_from_force(force_n))
    }
}

/// The root of a contact equation `g(d) = 0` in the lever's deflection `d`: `g` decreasing
/// on the bracket `[lo, hi]` (`g(lo) ≥ 0 ≥ g(hi)`), `slope` its derivative (or a close
/// enough one). Newton steps from `x0`, the previous sample's root, which a slowly moving base
/// leaves two or three steps away; a step that leaves the shrinking bracket is replaced by
/// bisection, so it converges whatever the slope. Stops when a step or the bracket falls
/// below `tol`, or after `max_iter` steps. The twin and the fit's deflection refinement both
/// solve their contacts with it.
pub fn decreasing_root(
    g: impl Fn(f64) -> f64,
    slope: impl Fn(f64) -> f64,
    (mut lo, mut hi): (f64, f64),
    x0: f64,
    tol: f64,
    max_iter: usize,
) -> f64 {
    let mut d = x0.clamp(lo, hi);
    for _ in 0..max_iter {
        let gd = g(d);
        if gd > 0.0 {
            lo = d;
        } else {
            hi = d;
        }
        let mut next = d - gd / slope(d);
        if !(next > lo && next < hi) {
            next = 0.5 * (lo + hi);
        }
        let step = (next - d).abs();
        d = next;
        if step <= tol || hi - lo <= tol {
            break;
        }
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Hertz: P = (4/3)·E/(1−ν²)·√R·h^{3/2}. Check the transform reproduces it.
    #[test]
    fn sphere_matches_hertz() {
        let (r, e, nu) = (20e-9, 1.0e6, 0.3);
        let c = Contact {
            tip: TipGeometry::Sphere { radius_m: r },
            poisson_ratio: nu,
        };
        let h: f64 = 15e-9;
        let p = 4.0 / 3.0 * e / (1.0 - nu * nu) * r.sqrt() * h.powf(1.5);
        let h_back = c.elastic_indentation(p, 1.0 / e);
        assert!((h_back - h).abs() / h < 1e-12);
        // The paper's factor 9/(16√R) at ν = 0.5.
        let paper = Contact::sphere(r);
        assert!((paper.force_factor() - 9.0 / (16.0 * r.sqrt())).abs() < 1e-9);
    }

    /// Sneddon: P = (2/π)·E/(1−ν²)·tan α·h².
    #[test]
    fn cone_matches_sneddon() {
        let (a, e) = (18f64.to_radians(), 2.0e5);
        let c = Contact::cone(a);
        let h = 100e-9;
        let p = 2.0 / std::f64::consts::PI * e / 0.75 * a.tan() * h * h;
        assert!((c.elastic_indentation(p, 1.0 / e) - h).abs() / h < 1e-12);
        assert_eq!(c.y_from_indentation(-1e-9), 0.0);
    }
}
