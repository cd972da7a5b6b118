//! The Rice distribution of the measured polarization degree (section `sec:bias`).
//!
//! With `Q`, `U` normal with means `Q0`, `U0` and equal errors `sigma`, the measured
//! `P = hypot(Q, U)` has the density
//! `f(P | P0, sigma) = P / sigma^2 exp(-(P^2 + P0^2) / (2 sigma^2)) I0(P P0 / sigma^2)`
//! (Rice 1944). In the normalized variables `x = P / sigma`, `a = P0 / sigma` this is written
//! `x exp(-(x - a)^2 / 2) i0e(x a)` with the exponentially scaled `i0e`, which is finite for
//! every `x a` (no overflow at `x a = 1e6` or `1e12`). `P0 = 0` is the Rayleigh distribution.

use super::special::{bessel_ratio, brent, integrate_panels};
use super::{check, Error};
use spec_math::cephes64::{i0e, i1e};
use std::f64::consts::{FRAC_PI_2, PI};

/// Normalized Rice density `f(x | a)` (`sigma = 1`).
///
/// ```
/// use stokes::stats::rice::pdf_n;
/// // With no true polarization (a = 0) the Rice density is Rayleigh's, x exp(-x^2/2).
/// assert!((pdf_n(1.5, 0.0) - 1.5 * (-1.125f64).exp()).abs() < 1e-15);
/// ```
#[inline]
pub fn pdf_n(x: f64, a: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    let d = x - a;
    x * (-0.5 * d * d).exp() * i0e(x * a)
}

/// Natural log of [`pdf_n`] (`-inf` at `x = 0`).
#[inline]
pub fn ln_pdf_n(x: f64, a: f64) -> f64 {
    if x <= 0.0 {
        return f64::NEG_INFINITY;
    }
    let d = x - a;
    x.ln() - 0.5 * d * d + i0e(x * a).ln()
}

/// Half-width (in units of sigma) beyond which the Rice tails are below `exp(-72)` of the
/// mass next to the integration end point: see [`cdf_n`].
const REACH: f64 = 12.0;

fn panels(len: f64) -> usize {
    // Panels of at most 0.75 sigma: 20-point Gauss-Legendre is then exact to rounding.
    ((len / 0.75).ceil() as usize).max(1)
}

/// Normalized Rice cdf `F(x | a) = 1 - Q1(a, x)` (Marcum Q), by Gauss-Legendre quadrature of
/// the density. Below the bulk (`x <= a`) the integral runs from `x - 12` to `x` (the density
/// further left is smaller by `exp(-12 (a - x) - 72)`), so small cdf values keep their
/// relative precision; above it the complement [`sf_n`] is integrated instead.
pub fn cdf_n(x: f64, a: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x <= a.max(1.0) {
        let lo = (x - REACH).max(0.0);
        integrate_panels(|t| pdf_n(t, a), lo, x, panels(x - lo)).min(1.0)
    } else {
        (1.0 - sf_n(x, a)).max(0.0)
    }
}

/// Normalized Rice survival function `1 - F(x | a) = Q1(a, x)`, accurate in the far upper
/// tail.
pub fn sf_n(x: f64, a: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    if x <= a.max(1.0) {
        return (1.0 - cdf_n(x, a)).max(0.0);
    }
    let hi = x + REACH;
    integrate_panels(|t| pdf_n(t, a), x, hi, panels(REACH)).min(1.0)
}

/// Closed-form mean of the normalized Rice distribution,
/// `sqrt(pi/2) L_{1/2}(-a^2/2) = sqrt(pi/2) [(1 + a^2/2) i0e(a^2/4) + (a^2/2) i1e(a^2/4)]`
/// (the Laguerre function written with scaled Bessel functions: the `exp(-a^2/4)` of
/// `L_{1/2}` cancels the growth of `I0`, `I1`).
///
/// ```
/// use stokes::stats::rice::mean_n;
/// // a = 0: the Rayleigh mean sqrt(pi/2); large a: a + 1/(2a) (the bias of P at high S/N).
/// assert!((mean_n(0.0) - std::f64::consts::FRAC_PI_2.sqrt()).abs() < 1e-15);
/// assert!((mean_n(50.0) - (50.0 + 1.0 / 100.0)).abs() < 1e-5);
/// ```
pub fn mean_n(a: f64) -> f64 {
    let h = 0.5 * a * a;
    let z = 0.5 * h;
    (FRAC_PI_2).sqrt() * ((1.0 + h) * i0e(z) + h * i1e(z))
}

/// `(E[x - a], E[(x - a)^2])` by quadrature: the bias and mean square error without the
/// cancellation of `mean - a` for large `a`.
pub fn central_moments_n(a: f64) -> (f64, f64) {
    let lo = (a - 1.5 * REACH).max(0.0);
    let hi = a.max(1.0) + 1.5 * REACH;
    let n = panels(hi - lo);
    let m1 = integrate_panels(|t| (t - a) * pdf_n(t, a), lo, hi, n);
    let m2 = integrate_panels(|t| (t - a) * (t - a) * pdf_n(t, a), lo, hi, n);
    (m1, m2)
}

/// Bias of the mean, `E[x] - a`: closed form for `a <= 4`, quadrature above (where the closed
/// form would subtract nearly equal numbers).
pub fn mean_bias_n(a: f64) -> f64 {
    if a <= 4.0 {
        mean_n(a) - a
    } else {
        central_moments_n(a).0
    }
}

/// Standard deviation of the normalized Rice distribution: `sqrt(2 + a^2 - mean^2)` for
/// `a <= 4`, `sqrt(E[(x-a)^2] - E[x-a]^2)` by quadrature above.
pub fn std_n(a: f64) -> f64 {
    if a <= 4.0 {
        let m = mean_n(a);
        (2.0 + a * a - m * m).max(0.0).sqrt()
    } else {
        let (m1, m2) = central_moments_n(a);
        (m2 - m1 * m1).max(0.0).sqrt()
    }
}

/// `d ln f / dx = 1/x - x + a I1(x a)/I0(x a)`: zero at the mode.
#[inline]
fn dlnpdf_dx(x: f64, a: f64) -> f64 {
    1.0 / x - x + a * bessel_ratio(x * a)
}

/// Mode of the normalized Rice distribution (Wardle & Kronberg 1974): the root of
/// `1/x - x + a I1(xa)/I0(xa) = 0`, bracketed in `[1, (a + sqrt(a^2 + 4)) / 2]` (the
/// derivative is `>= 0` at `x = 1` and `< 0` where `1/x - x + a = 0`, because `I1/I0 < 1`).
pub fn mode_n(a: f64) -> f64 {
    if a == 0.0 {
        return 1.0;
    }
    let hi = 0.5 * (a + (a * a + 4.0).sqrt());
    brent(|x| dlnpdf_dx(x, a), 1.0, hi, 1e-15 * hi.max(1.0)).unwrap_or(hi)
}

/// Quantile `q` in (0, 1) of the normalized Rice distribution (Brent on the cdf, or on the
/// survival function above the median so tail quantiles keep their precision).
pub fn quantile_n(q: f64, a: f64) -> f64 {
    let hi = a + 40.0;
    let f = |x: f64| if q <= 0.5 { cdf_n(x, a) - q } else { (1.0 - q) - sf_n(x, a) };
    brent(f, 0.0, hi, 1e-14 * hi).unwrap_or(f64::NAN)
}

/// The Rice distribution of the measured polarization degree `P` for true degree `p0` and
/// error `sigma` of each of `Q`, `U` (both fractions).
///
/// ```
/// use stokes::stats::Rice;
/// let r = Rice::new(0.0, 0.01).unwrap(); // Rayleigh
/// assert!((r.std() - 0.01 * (2.0 - std::f64::consts::PI / 2.0).sqrt()).abs() < 1e-15);
/// ```
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rice {
    p0: f64,
    sigma: f64,
}

impl Rice {
    /// `p0 >= 0`, `sigma > 0`, both finite.
    pub fn new(p0: f64, sigma: f64) -> Result<Self, Error> {
        Ok(Self { p0: check("P0", p0, false)?, sigma: check("sigma", sigma, true)? })
    }
    pub fn p0(&self) -> f64 {
        self.p0
    }
    pub fn sigma(&self) -> f64 {
        self.sigma
    }
    fn a(&self) -> f64 {
        self.p0 / self.sigma
    }
    /// Density of `P` (per unit `P`).
    pub fn pdf(&self, p: f64) -> f64 {
        pdf_n(p / self.sigma, self.a()) / self.sigma
    }
    /// Log density of `P`.
    pub fn ln_pdf(&self, p: f64) -> f64 {
        ln_pdf_n(p / self.sigma, self.a()) - self.sigma.ln()
    }
    /// `Pr(P_measured <= p)`.
    pub fn cdf(&self, p: f64) -> f64 {
        cdf_n(p / self.sigma, self.a())
    }
    /// `Pr(P_measured > p)`.
    pub fn sf(&self, p: f64) -> f64 {
        sf_n(p / self.sigma, self.a())
    }
    /// Mean `<P>`.
    pub fn mean(&self) -> f64 {
        self.sigma * mean_n(self.a())
    }
    /// Bias of the mean, `<P> - P0`, without cancellation at high signal-to-noise.
    pub fn mean_bias(&self) -> f64 {
        self.sigma * mean_bias_n(self.a())
    }
    /// Mode (most probable measured `P`), the estimator of the bias used in section `sec:bias`.
    pub fn mode(&self) -> f64 {
        self.sigma * mode_n(self.a())
    }
    /// Median.
    pub fn median(&self) -> f64 {
        self.sigma * quantile_n(0.5, self.a())
    }
    /// Quantile `q` in (0, 1).
    pub fn quantile(&self, q: f64) -> Result<f64, Error> {
        if !(q > 0.0 && q < 1.0) {
            return Err(Error::Invalid { name: "quantile", value: q, why: "must be in (0, 1)" });
        }
        Ok(self.sigma * quantile_n(q, self.a()))
    }
    /// Standard deviation of `P`: the "RMS error" `sigma_P` of the paper's Monte Carlo
    /// (fig:deltap, upper panel).
    pub fn std(&self) -> f64 {
        self.sigma * std_n(self.a())
    }
    /// Root mean square of `P`, `sqrt(<P^2>) = sqrt(P0^2 + 2 sigma^2)`.
    pub fn rms(&self) -> f64 {
        self.sigma.hypot(self.sigma).hypot(self.p0)
    }
    /// Root mean square error about the truth, `sqrt(<(P - P0)^2>)`.
    pub fn rms_error(&self) -> f64 {
        self.sigma * central_moments_n(self.a()).1.sqrt()
    }
}

/// Standard deviation of the Rayleigh distribution (`P0 = 0`): `sigma sqrt(2 - pi/2)`, the
/// dashed line of fig:deltap.
pub fn rayleigh_std(sigma: f64) -> f64 {
    sigma * (2.0 - PI / 2.0).sqrt()
}

/// Mean of the Rayleigh distribution: `sigma sqrt(pi/2)`.
pub fn rayleigh_mean(sigma: f64) -> f64 {
    sigma * FRAC_PI_2.sqrt()
}
