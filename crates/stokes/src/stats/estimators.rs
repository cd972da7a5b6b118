//! Estimators of the true polarization degree `P0` from a measured `P` and its error
//! (section `sec:bias`), selectable by name.
//!
//! All work in `x = P / sigma`. Root finding is bracketed (Brent), never a bare Newton.
//!
//! | name | estimator | zero below | validity |
//! |---|---|---|---|
//! | `naive` | `P` | never | `P / sigma >~ 5` (bias `sigma^2 / (2 P)`) |
//! | `as` | `sqrt(P^2 - sigma^2)` (asymptotic; Wardle & Kronberg 1974) | `P <= sigma` | `P / sigma >~ 3` |
//! | `wk` | `P0` whose Rice mode is `P` (Wardle & Kronberg 1974, exact, not asymptotic) | `P <= sigma` | `P / sigma >~ 0.7` (Simmons & Stewart) |
//! | `ml` | maximum of the Rice likelihood in `P0` (Simmons & Stewart 1985) | `P <= sqrt(2) sigma` | best for `P0 / sigma <~ 0.7` |
//! | `mp2` | 2-D most probable, `P - sigma^2 / P` (Wang et al. 1997; Quinn 2012) | `P <= sigma` | `P / sigma >~ 2` |
//! | `mas` | modified asymptotic (Plaszczynski et al. 2014), unequal `sigma_Q`, `sigma_U` | never (`-> P/2` as `P -> 0`) | unbiased for `P0 / sigma >~ 2` |
//! | `mb` | posterior mean, flat prior on `P0 >= 0` (Vaillancourt 2006; Montier et al. 2015) | never (`-> sqrt(2/pi) sigma` at `P = 0`) | all `P`; biased high at low S/N |
//! | `pr06` | `P [1 - (0.62 sigma / P)^1.92]` (this paper, sec:bias) | `P <= 0.62 sigma` | `P / sigma > 4` |

use super::rice::pdf_n;
use super::special::{bessel_ratio, bessel_ratio_over_z, brent_expand, integrate_panels, ln_i0};
use super::{check, Error};
use std::fmt;
use std::str::FromStr;

/// A measured polarization: `Q/I`, `U/I` and their (independent) errors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolMeasurement {
    pub q: f64,
    pub u: f64,
    pub sigma_q: f64,
    pub sigma_u: f64,
}

impl PolMeasurement {
    /// A measurement known only by `P` and one `sigma` (equal errors on `Q` and `U`).
    pub fn from_p(p: f64, sigma: f64) -> Result<Self, Error> {
        let p = check("P", p, false)?;
        let sigma = check("sigma", sigma, true)?;
        Ok(Self { q: p, u: 0.0, sigma_q: sigma, sigma_u: sigma })
    }
    /// A measurement of `Q`, `U` with errors `sigma_q`, `sigma_u`.
    pub fn new(q: f64, u: f64, sigma_q: f64, sigma_u: f64) -> Result<Self, Error> {
        for (n, v) in [("Q", q), ("U", u)] {
            if !v.is_finite() {
                return Err(Error::Invalid { name: n, value: v, why: "must be finite" });
            }
        }
        Ok(Self { q, u, sigma_q: check("sigma_Q", sigma_q, true)?, sigma_u: check("sigma_U", sigma_u, true)? })
    }
    /// Measured `P = hypot(Q, U)`.
    pub fn p(&self) -> f64 {
        self.q.hypot(self.u)
    }
    /// The one `sigma` of the Rice-based estimators: `sqrt((sigma_Q^2 + sigma_U^2) / 2)`,
    /// exact when the errors are equal.
    pub fn sigma(&self) -> f64 {
        (0.5 * (self.sigma_q * self.sigma_q + self.sigma_u * self.sigma_u)).sqrt()
    }
    /// Plaszczynski et al.'s noise along the measured direction,
    /// `b^2 = (Q^2 sigma_U^2 + U^2 sigma_Q^2) / P^2` (= `sigma^2` at `P = 0`).
    pub fn b(&self) -> f64 {
        let p = self.p();
        if p == 0.0 {
            return self.sigma();
        }
        ((self.q * self.sigma_u).powi(2) + (self.u * self.sigma_q).powi(2)).sqrt() / p
    }
}

/// A named estimator of `P0`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Estimator {
    Naive,
    As,
    Wk,
    Ml,
    Mp2,
    Mas,
    Mb,
    Pr06,
}

/// The value of an estimator and whether the measurement is inside its documented validity
/// range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    pub value: f64,
    pub in_validity_range: bool,
}

impl Estimator {
    /// All estimators, in the order of the module table.
    pub const ALL: [Estimator; 8] = [
        Estimator::Naive,
        Estimator::As,
        Estimator::Wk,
        Estimator::Ml,
        Estimator::Mp2,
        Estimator::Mas,
        Estimator::Mb,
        Estimator::Pr06,
    ];

    /// The name used on the command line.
    pub fn name(&self) -> &'static str {
        match self {
            Estimator::Naive => "naive",
            Estimator::As => "as",
            Estimator::Wk => "wk",
            Estimator::Ml => "ml",
            Estimator::Mp2 => "mp2",
            Estimator::Mas => "mas",
            Estimator::Mb => "mb",
            Estimator::Pr06 => "pr06",
        }
    }

    /// Estimate `P0` from a measurement.
    pub fn estimate(&self, m: &PolMeasurement) -> Estimate {
        let p = m.p();
        let s = m.sigma();
        let x = p / s;
        if x > SNR_UNBIASED {
            // Every estimator is `P (1 - O(sigma^2 / P^2))`: beyond 1e8 the correction is
            // below the rounding of `P` itself. The formulas would overflow there (`x^2` at
            // `x > 1e154`, the Bessel ratios far sooner) and gave NaN, or 0 for ML.
            return Estimate { value: p, in_validity_range: true };
        }
        let (value, valid) = match self {
            Estimator::Naive => (p, x >= 5.0),
            Estimator::As => (s * as_n(x), x >= 3.0),
            Estimator::Wk => (s * wk_n(x), x >= 0.7),
            Estimator::Ml => (s * ml_n(x), true),
            Estimator::Mp2 => (s * mp2_n(x), x >= 2.0),
            Estimator::Mas => {
                let b = m.b();
                (b * mas_n(p / b), true)
            }
            Estimator::Mb => (s * mb_n(x), true),
            Estimator::Pr06 => (s * pr06_n(x), x > 4.0),
        };
        Estimate { value, in_validity_range: valid }
    }

    /// Estimate from `P` and `sigma` (equal errors on `Q`, `U`).
    pub fn estimate_p(&self, p: f64, sigma: f64) -> Result<Estimate, Error> {
        Ok(self.estimate(&PolMeasurement::from_p(p, sigma)?))
    }

    /// The estimator applied to a normalized measurement `x = P / sigma` (equal errors),
    /// returned in units of sigma.
    pub fn apply_n(&self, x: f64) -> f64 {
        match self {
            Estimator::Naive => x,
            Estimator::As => as_n(x),
            Estimator::Wk => wk_n(x),
            Estimator::Ml => ml_n(x),
            Estimator::Mp2 => mp2_n(x),
            Estimator::Mas => mas_n(x),
            Estimator::Mb => mb_n(x),
            Estimator::Pr06 => pr06_n(x),
        }
    }
}

impl fmt::Display for Estimator {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Estimator {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        let l = s.trim().to_ascii_lowercase();
        Estimator::ALL.into_iter().find(|e| e.name() == l).ok_or_else(|| Error::UnknownEstimator(s.to_string()))
    }
}

/// The signal-to-noise `P / sigma` beyond which every estimator returns `P`: the bias
/// corrections, of relative size `(sigma / P)^2 / 2`, are then below 1e-16.
pub const SNR_UNBIASED: f64 = 1e8;

/// Asymptotic estimator `sqrt(x^2 - 1)` for `x > 1`, else 0 (written `(x-1)(x+1)`: no
/// cancellation near the threshold).
///
/// ```
/// use stokes::stats::estimators::as_n;
/// // sec:bias: P measured at 1.25 sigma is P0 = sqrt(1.25^2 - 1) = 0.75 sigma; below 1 sigma, 0.
/// assert!((as_n(1.25) - 0.75).abs() < 1e-15);
/// assert_eq!(as_n(0.9), 0.0);
/// ```
pub fn as_n(x: f64) -> f64 {
    if x <= 1.0 {
        0.0
    } else {
        ((x - 1.0) * (x + 1.0)).sqrt()
    }
}

/// Wardle & Kronberg: the `a` whose Rice mode equals `x`, i.e. the root in `a` of
/// `1/x - x + a I1(a x)/I0(a x) = 0`. The Rice mode is 1 at `a = 0` and grows with `a`, so
/// `x <= 1` gives 0. `a I1(ax)/I0(ax)` increases with `a` and is below `a`, so the root lies
/// above `x - 1/x`; the bracket is expanded upward until it changes sign.
pub fn wk_n(x: f64) -> f64 {
    if !(x > 1.0) {
        return 0.0;
    }
    let target = x - 1.0 / x;
    let f = |a: f64| a * bessel_ratio(a * x) - target;
    brent_expand(f, target.max(0.0), target + 1.0, 1e-15 * x).unwrap_or(target)
}

/// Simmons & Stewart maximum likelihood: the root `a > 0` of `d ln f(x|a)/da = 0`, i.e.
/// `a = x I1(a x)/I0(a x)`. The right side has slope `x^2/2` at `a = 0`, so a positive root
/// exists only for `x > sqrt 2`; below, the likelihood is maximal at `a = 0`. The function is
/// solved as `x^2 I1(ax)/(ax I0(ax)) - 1 = 0`, which is `x^2/2 - 1 > 0` at `a = 0` and
/// negative at `a = x` (because `I1/I0 < 1`).
///
/// Note: the likelihood equation is `P0 = P I1/I0`, not `P = P0 I1/I0` as it is sometimes
/// quoted; only the former has the `sqrt(2) sigma` threshold.
pub fn ml_n(x: f64) -> f64 {
    if !(x > std::f64::consts::SQRT_2) {
        return 0.0;
    }
    let f = |a: f64| x * x * bessel_ratio_over_z(a * x) - 1.0;
    super::special::brent(f, 0.0, x, 1e-15 * x).unwrap_or(0.0)
}

/// The 2-D most probable estimator (Wang et al. 1997; Quinn 2012; Montier et al. 2015
/// "MP2"): the `P0` for which the measured `(Q, U)` is the mode of the 2-D density of
/// `(P, theta)`: `d/dP [P exp(-(P - P0)^2 / 2 sigma^2)] = 0` gives `P0 = P - sigma^2 / P`,
/// written `(x - 1)(x + 1)/x`; zero for `P <= sigma`.
pub fn mp2_n(x: f64) -> f64 {
    if x <= 1.0 {
        0.0
    } else {
        (x - 1.0) * (x + 1.0) / x
    }
}

/// Modified asymptotic estimator (Plaszczynski et al. 2014) in units of `b`:
/// `x - (1 - exp(-x^2)) / (2x)`. It is continuous, positive, and tends to `x/2` as
/// `x -> 0` (`1 - exp(-x^2) ~ x^2`), and to `x - 1/(2x)` (the AS expansion) at high S/N.
/// `1 - exp(-x^2)` is computed as `-expm1(-x^2)`.
pub fn mas_n(x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x < 1e-4 {
        // -expm1(-x^2)/(2x) = x/2 - x^3/4 + ...
        return x - (0.5 * x - 0.25 * x * x * x);
    }
    x + (-x * x).exp_m1() / (2.0 * x)
}

/// The paper's fitted correction (sec:bias): `P0 = P [1 - (0.62 / (sqrt(N/2) eta))^1.92]`
/// with `eta = P SNR`. With `sigma = sigma_P = 1 / (sqrt(N/2) SNR)` (`eq:sigp`) the
/// argument `sqrt(N/2) eta` is `P / sigma = x`, so the `N` dependence enters through `sigma`.
/// Valid for `x > 4`; clipped at 0 (for `x <= 0.62`).
pub fn pr06_n(x: f64) -> f64 {
    if x <= 0.62 {
        return 0.0;
    }
    x * (1.0 - (0.62 / x).powf(1.92))
}

/// Log of the Rice likelihood in `a` for fixed `x`, without the `a`-independent factors:
/// `-(x - a)^2 / 2 + ln i0e(x a)` (`= ln f(x|a) - ln x`).
#[inline]
pub fn ln_likelihood_n(x: f64, a: f64) -> f64 {
    let d = x - a;
    -0.5 * d * d + ln_i0(x * a) - x * a
}

/// Support of the posterior of `a` (flat prior, `a >= 0`) for data `x`: the likelihood is
/// below `exp(-100)` of its peak outside.
pub(crate) fn posterior_support(x: f64) -> (f64, f64) {
    ((x - 14.0).max(0.0), x + 14.0)
}

/// Posterior mean of `a` with a flat prior on `a >= 0` and the Rice likelihood
/// (Vaillancourt 2006; Montier et al. 2015 "MB"), by Gauss-Legendre quadrature. At `x = 0`
/// the posterior is a half-normal and the mean is `sqrt(2/pi)`.
pub fn mb_n(x: f64) -> f64 {
    let (lo, hi) = posterior_support(x);
    // Panels of one sigma: the posterior is smooth on that scale (20-point rule).
    let n = (hi - lo).ceil() as usize;
    // Scale by the likelihood at the ML point to keep exp() in range.
    let peak = ln_likelihood_n(x, ml_n(x));
    let w = |a: f64| (ln_likelihood_n(x, a) - peak).exp();
    let (z, m) = super::special::integrate_panels2(w, lo, hi, n);
    m / z
}

/// Expected value of an estimator over the Rice distribution of `x` for true `a` (both in
/// units of sigma), by quadrature: the bias curves of fig:bias.
pub fn expected_n(est: Estimator, a: f64) -> f64 {
    let lo = (a - 14.0).max(0.0);
    let hi = a.max(1.0) + 14.0;
    let n = ((hi - lo) / 0.5).ceil() as usize;
    integrate_panels(|x| est.apply_n(x) * pdf_n(x, a), lo, hi, n)
}
