//! Statistics of a measured polarization degree: the Rice distribution of `P` and the
//! distribution of the measured angle, estimators of the true `P0` that correct the
//! polarization bias (section `sec:bias`), and confidence / credible intervals on `P0`.
//!
//! Everything assumes normally distributed `Q`, `U` with (by default) equal errors `sigma`:
//! the measured `P = hypot(Q, U)` then follows the Rice distribution of `P0 = hypot(Q0, U0)`
//! and `sigma` (`sigma` is `sigma_P` of `eq:sigp`). Functions are written in the normalized
//! variables `x = P / sigma`, `a = P0 / sigma` with exponentially scaled Bessel functions, so
//! nothing overflows up to `x a = 1e8` and beyond.
//!
//! - [`rice`]: pdf, cdf (Marcum Q by quadrature of the pdf), mean, mode, median, RMS, the
//!   Rayleigh limit;
//! - [`angle`]: the pdf of the measured angle (Naghizadeh-Khouei & Clarke 1993) and its
//!   68.27 % half-width;
//! - [`estimators`]: naive, AS, WK, ML, MP2, MAS, MB and the paper's PR06 law, by name;
//! - [`intervals`]: Neyman central intervals and Bayesian HPD intervals on `P0`;
//! - [`robust`]: the workspace's one median, the MAD-to-sigma factor and the clipped mean;
//! - [`circular`]: angles averaged as angles (mean, weighted mean, median, difference, scatter),
//!   each with its period.

pub mod angle;
pub mod circular;
pub mod debias;
pub mod estimators;
pub mod intervals;
pub mod rice;
pub mod robust;
pub mod special;

pub use angle::AngleDist;
pub use debias::{debias, Debiased};
pub use estimators::{Estimate, Estimator, PolMeasurement};
pub use intervals::{hpd_interval, neyman_interval, Interval, IntervalKind};
pub use rice::Rice;

/// The Gaussian one-sigma probability, `erf(1/sqrt 2) = 0.682689...`: the default confidence
/// level.
pub const ONE_SIGMA: f64 = 0.682_689_492_137_085_9;

/// Errors of the statistics and of the Monte Carlo engine: each names the offending input.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum Error {
    #[error("{name} = {value} is invalid: {why}")]
    Invalid { name: &'static str, value: f64, why: &'static str },
    #[error("unknown estimator '{0}' (known: naive, as, wk, ml, mp2, mas, mb, pr06)")]
    UnknownEstimator(String),
    #[error("{0}")]
    Model(String),
}

/// Check that `value` is finite and `> 0` (`positive`) or `>= 0`.
pub(crate) fn check(name: &'static str, value: f64, positive: bool) -> Result<f64, Error> {
    if !value.is_finite() {
        return Err(Error::Invalid { name, value, why: "must be finite" });
    }
    if positive && value <= 0.0 {
        return Err(Error::Invalid { name, value, why: "must be > 0" });
    }
    if value < 0.0 {
        return Err(Error::Invalid { name, value, why: "must be >= 0" });
    }
    Ok(value)
}
