//! Intervals on the true polarization degree `P0` from one measured `P` and `sigma`.
//!
//! - **Neyman central intervals** (classical): the set of `P0` whose central `cl` acceptance
//!   region of the Rice distribution contains the measured `P`. The Rice cdf `F(P | P0)`
//!   decreases with `P0`, so the limits solve `F(P | lo) = (1 + cl)/2` and
//!   `F(P | hi) = (1 - cl)/2`. When `F(P | 0) <= (1 + cl)/2` the lower limit is 0 and the
//!   interval is an upper limit only; when `F(P | 0) <= (1 - cl)/2` (P below the lower
//!   acceptance edge even of `P0 = 0`) no `P0` accepts the measurement: the classical
//!   central interval is empty, reported as `lo = 0`, `hi = None` with `empty = true`.
//! - **Bayesian HPD intervals**: flat prior on `P0 >= 0`, Rice likelihood; the interval of
//!   highest posterior density holding `cl` of the posterior. When the posterior peaks at 0
//!   (`P <= sqrt(2) sigma`) the interval starts at 0 (an upper limit).

use super::estimators::{ln_likelihood_n, ml_n, posterior_support};
use super::rice::cdf_n;
use super::special::{brent, brent_expand, integrate_panels};
use super::{check, Error};
use std::fmt;
use std::str::FromStr;

/// Which interval.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IntervalKind {
    Neyman,
    Hpd,
}

impl FromStr for IntervalKind {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        match s.trim().to_ascii_lowercase().as_str() {
            "neyman" => Ok(IntervalKind::Neyman),
            "hpd" => Ok(IntervalKind::Hpd),
            _ => Err(Error::Model(format!("unknown interval kind '{s}' (known: neyman, hpd)"))),
        }
    }
}

impl fmt::Display for IntervalKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            IntervalKind::Neyman => "neyman",
            IntervalKind::Hpd => "hpd",
        })
    }
}

/// An interval on `P0` (same units as `P`). `lo`/`hi` are `None` where that limit does not
/// exist.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Interval {
    pub lo: Option<f64>,
    pub hi: Option<f64>,
    /// The lower limit is 0: the measurement gives an upper limit on `P0` only.
    pub upper_limit_only: bool,
    /// The classical construction accepts no `P0` at all (very small measured `P`).
    pub empty: bool,
    pub cl: f64,
}

fn check_cl(cl: f64) -> Result<f64, Error> {
    if !(cl > 0.0 && cl < 1.0) {
        return Err(Error::Invalid { name: "confidence level", value: cl, why: "must be in (0, 1)" });
    }
    Ok(cl)
}

/// Neyman central interval on `P0` at confidence `cl` for measured `p` with error `sigma`.
///
/// ```
/// use stokes::stats::neyman_interval;
/// // At high S/N the 68.27 % interval on P0 is P +- sigma, shifted down by the bias of P
/// // (about sigma^2 / (2 P)): P = 1 %, sigma = 0.05 %.
/// let i = neyman_interval(0.01, 0.0005, 0.6827).unwrap();
/// let (lo, hi) = (i.lo.unwrap(), i.hi.unwrap());
/// assert!((lo - (0.0095 - 0.0005 * 0.0005 / 0.02)).abs() < 2e-6);
/// assert!((hi - (0.0105 - 0.0005 * 0.0005 / 0.02)).abs() < 2e-6);
/// assert!(!i.upper_limit_only);
/// ```
pub fn neyman_interval(p: f64, sigma: f64, cl: f64) -> Result<Interval, Error> {
    let p = check("P", p, false)?;
    let sigma = check("sigma", sigma, true)?;
    let cl = check_cl(cl)?;
    let x = p / sigma;
    let (x_lo, x_hi) = neyman_n(x, cl);
    let empty = x_hi.is_none();
    Ok(Interval { lo: Some(x_lo * sigma), hi: x_hi.map(|h| h * sigma), upper_limit_only: x_lo == 0.0, empty, cl })
}

/// Normalized Neyman limits `(lo, hi)` for `x = P / sigma`.
pub fn neyman_n(x: f64, cl: f64) -> (f64, Option<f64>) {
    let up = 0.5 * (1.0 + cl);
    let down = 0.5 * (1.0 - cl);
    let f0 = cdf_n(x, 0.0);
    let tol = 1e-12 * x.max(1.0);
    let lo = if f0 <= up { 0.0 } else { brent_expand(|a| cdf_n(x, a) - up, 0.0, x.max(1.0), tol).unwrap_or(0.0) };
    let hi = if f0 <= down { None } else { brent_expand(|a| cdf_n(x, a) - down, 0.0, x + 2.0, tol) };
    (lo, hi)
}

/// Bayesian highest-posterior-density interval on `P0` (flat prior on `P0 >= 0`) holding
/// `cl` of the posterior, for measured `p` with error `sigma`.
pub fn hpd_interval(p: f64, sigma: f64, cl: f64) -> Result<Interval, Error> {
    let p = check("P", p, false)?;
    let sigma = check("sigma", sigma, true)?;
    let cl = check_cl(cl)?;
    let (lo, hi) = hpd_n(p / sigma, cl);
    Ok(Interval { lo: Some(lo * sigma), hi: Some(hi * sigma), upper_limit_only: lo == 0.0, empty: false, cl })
}

/// Normalized HPD limits for `x = P / sigma`.
pub fn hpd_n(x: f64, cl: f64) -> (f64, f64) {
    let (s_lo, s_hi) = posterior_support(x);
    let mode = ml_n(x); // the posterior mode under a flat prior is the ML estimate
    let peak = ln_likelihood_n(x, mode);
    let lw = move |a: f64| ln_likelihood_n(x, a) - peak; // <= 0
    let w = move |a: f64| lw(a).exp();
    let n = ((s_hi - s_lo) / 0.25).ceil() as usize;
    let z = integrate_panels(w, s_lo, s_hi, n);
    let lw0 = if s_lo == 0.0 { lw(0.0) } else { f64::NEG_INFINITY };
    // For a level t = ln(density / peak) in (-60, 0): the interval [l(t), u(t)].
    let limits = move |t: f64| -> (f64, f64) {
        let l = if lw0 >= t { 0.0 } else { brent(|a| lw(a) - t, s_lo, mode, 1e-13).unwrap_or(s_lo) };
        let u = brent(|a| lw(a) - t, mode, s_hi, 1e-13).unwrap_or(s_hi);
        (l, u)
    };
    let mass = |t: f64| {
        let (l, u) = limits(t);
        let k = ((u - l) / 0.25).ceil().max(1.0) as usize;
        integrate_panels(w, l, u, k) / z
    };
    // mass(t) decreases from ~1 at t = -60 to 0 at t = 0.
    let t = brent(|t| mass(t) - cl, -60.0, -1e-300, 1e-13).unwrap_or(-60.0);
    limits(t)
}
