//! One bias correction of a measured `P` as `instpol bias` and the Python `instpol.bias` report
//! it: an estimator of `P0` (section `sec:bias`) and an interval on `P0`.

use super::estimators::{Estimate, Estimator, PolMeasurement};
use super::intervals::{hpd_interval, neyman_interval, Interval, IntervalKind};
use super::{check, Error};

/// A bias-corrected polarization degree: the chosen estimate, the interval, and every
/// estimator's value (in the order of [`Estimator::ALL`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Debiased {
    pub estimate: Estimate,
    pub interval: Interval,
    pub all: [f64; 8],
}

/// Correct a measured `p` with error `sigma` (each of `Q`, `U`, `eq:sigp`) for the
/// polarization bias with `est`, and give the `kind` interval at confidence `cl`.
///
/// MAS (Plaszczynski et al. 2014) takes unequal errors `sigma_q`, `sigma_u` (default `sigma`)
/// and the measured angle `chi` (rad, which matters only when they differ); the Rice-based
/// estimators and both intervals use the one `sigma`.
#[allow(clippy::too_many_arguments)]
pub fn debias(
    p: f64,
    sigma: f64,
    est: Estimator,
    kind: IntervalKind,
    cl: f64,
    sigma_q: Option<f64>,
    sigma_u: Option<f64>,
    chi: f64,
) -> Result<Debiased, Error> {
    check("P", p, false)?;
    check("sigma", sigma, true)?;
    if !chi.is_finite() {
        return Err(Error::Invalid { name: "chi", value: chi, why: "must be finite" });
    }
    let (s2, c2) = (2.0 * chi).sin_cos();
    let m = PolMeasurement::new(p * c2, p * s2, sigma_q.unwrap_or(sigma), sigma_u.unwrap_or(sigma))?;
    let m_eq = PolMeasurement::from_p(p, sigma)?;
    let pick = |e: Estimator| if e == Estimator::Mas { e.estimate(&m) } else { e.estimate(&m_eq) };
    let interval = match kind {
        IntervalKind::Neyman => neyman_interval(p, sigma, cl)?,
        IntervalKind::Hpd => hpd_interval(p, sigma, cl)?,
    };
    Ok(Debiased { estimate: pick(est), interval, all: Estimator::ALL.map(|e| pick(e).value) })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Closed forms: AS is sqrt(P^2 - sigma^2), MP2 is P - sigma^2 / P, naive is P; with
    /// equal errors MAS does not depend on the angle.
    #[test]
    fn closed_forms_and_angle_independence() {
        let d = debias(0.05, 0.01, Estimator::As, IntervalKind::Neyman, 0.6827, None, None, 0.3).unwrap();
        assert!((d.estimate.value - (0.05f64 * 0.05 - 1e-4).sqrt()).abs() < 1e-15);
        assert_eq!(d.all[0], 0.05);
        assert!((d.all[4] - (0.05 - 1e-4 / 0.05)).abs() < 1e-15);
        let a = debias(0.03, 0.01, Estimator::Mas, IntervalKind::Hpd, 0.9, None, None, 0.0).unwrap();
        let b = debias(0.03, 0.01, Estimator::Mas, IntervalKind::Hpd, 0.9, None, None, 1.1).unwrap();
        assert!((a.estimate.value - b.estimate.value).abs() < 1e-15);
        assert!(debias(-0.1, 0.01, Estimator::As, IntervalKind::Hpd, 0.9, None, None, 0.0).is_err());
        assert!(debias(0.1, 0.0, Estimator::As, IntervalKind::Hpd, 0.9, None, None, 0.0).is_err());
    }
}
