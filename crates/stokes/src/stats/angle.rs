//! Distribution of the measured polarization angle (Naghizadeh-Khouei & Clarke 1993).
//!
//! For normal `Q`, `U` with equal errors `sigma` and true `P0`, `theta0`, the measured angle
//! `theta` (period pi) has the density
//! `G(theta) = (1/sqrt pi) [1/sqrt pi + eta exp(eta^2) (1 + erf eta)] exp(-eta0^2 / 2)`,
//! `eta0 = P0 / sigma`, `eta = eta0 cos 2(theta - theta0) / sqrt 2`
//! (per radian, on an interval of length pi). It follows from integrating the 2-D normal
//! density over the radius at fixed angle.
//!
//! Stable form: `exp(eta^2) (1 + erf eta) = erfcx(-eta)`. For `eta >= 0` we use
//! `erfcx(-eta) = 2 exp(eta^2) - erfcx(eta)` and fold `exp(-eta0^2/2)` into the exponent,
//! `eta^2 - eta0^2/2 = -eta0^2 sin^2 2(theta - theta0) / 2 <= 0`, so nothing overflows at any
//! `eta0`. Normalization: at `eta0 = 0`, `G = 1/pi`; for large `eta0`, `G` tends to a normal
//! density of width `sigma / (2 P0)` (`eq:sigchi`); in general `int G = 1` is verified by
//! quadrature in the tests to 1e-12.

use super::special::{brent, erfcx, integrate_adaptive};
use super::{check, Error};
use std::f64::consts::{FRAC_1_SQRT_2, FRAC_PI_2, PI};

/// The angle density for the deviation `d = theta - theta0` (rad, any value: period pi) and
/// `eta0 = P0 / sigma`.
pub fn pdf_dev(d: f64, eta0: f64) -> f64 {
    let inv_sqrt_pi = 1.0 / PI.sqrt();
    let (s2, c2) = (2.0 * d).sin_cos();
    let eta = eta0 * c2 * FRAC_1_SQRT_2;
    let g0 = (-0.5 * eta0 * eta0).exp();
    let bracket = if eta >= 0.0 {
        // eta erfcx(-eta) exp(-eta0^2/2) = 2 eta exp(-eta0^2 sin^2/2) - eta erfcx(eta) exp(-eta0^2/2)
        inv_sqrt_pi * g0 + 2.0 * eta * (-0.5 * eta0 * eta0 * s2 * s2).exp() - eta * erfcx(eta) * g0
    } else {
        g0 * (inv_sqrt_pi + eta * erfcx(-eta))
    };
    (inv_sqrt_pi * bracket).max(0.0)
}

/// Probability that the measured angle lies within `h` (rad, `0 <= h <= pi/2`) of the truth.
pub fn mass_within(h: f64, eta0: f64) -> f64 {
    let h = h.clamp(0.0, FRAC_PI_2);
    // The peak has width ~ 1/(2 eta0): split there so the quadrature sees it.
    let w = (3.0 / (eta0 + 1e-300)).min(FRAC_PI_2);
    let f = |t: f64| pdf_dev(t, eta0);
    let mut m = integrate_adaptive(f, 0.0, h.min(w), 1e-15, 1e-17);
    if h > w {
        m += integrate_adaptive(f, w, h, 1e-15, 1e-17);
    }
    (2.0 * m).min(1.0)
}

/// Half-width `h` with `Pr(|theta - theta0| <= h) = cl` (rad). At `eta0 = 0` the angle is
/// uniform and `h = cl pi / 2`.
pub fn half_width(cl: f64, eta0: f64) -> f64 {
    brent(|h| mass_within(h, eta0) - cl, 0.0, FRAC_PI_2, 1e-15).unwrap_or(FRAC_PI_2)
}

/// The distribution of the measured polarization angle for true `p0`, `sigma`, `theta0` (rad).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AngleDist {
    eta0: f64,
    theta0: f64,
}

impl AngleDist {
    /// `p0 >= 0`, `sigma > 0`, `theta0` any finite angle (rad).
    pub fn new(p0: f64, sigma: f64, theta0: f64) -> Result<Self, Error> {
        let p0 = check("P0", p0, false)?;
        let sigma = check("sigma", sigma, true)?;
        if !theta0.is_finite() {
            return Err(Error::Invalid { name: "theta0", value: theta0, why: "must be finite" });
        }
        Ok(Self { eta0: p0 / sigma, theta0 })
    }
    /// `eta0 = P0 / sigma`.
    pub fn eta0(&self) -> f64 {
        self.eta0
    }
    /// Density of the measured angle `theta` (rad, per radian, period pi).
    pub fn pdf(&self, theta: f64) -> f64 {
        pdf_dev(theta - self.theta0, self.eta0)
    }
    /// `Pr(|theta - theta0| <= h)`, angles folded modulo pi.
    pub fn mass_within(&self, h: f64) -> f64 {
        mass_within(h, self.eta0)
    }
    /// Half-width of the central interval holding `cl` of the probability (rad); with
    /// `cl = 0.6827` this is the honest "1 sigma" error of the angle, which tends to
    /// `sigma / (2 P0)` (`eq:sigchi`) at high signal-to-noise.
    pub fn half_width(&self, cl: f64) -> Result<f64, Error> {
        if !(cl > 0.0 && cl < 1.0) {
            return Err(Error::Invalid { name: "confidence level", value: cl, why: "must be in (0, 1)" });
        }
        Ok(half_width(cl, self.eta0))
    }
}
