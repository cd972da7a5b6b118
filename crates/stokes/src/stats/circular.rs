//! Circular statistics: angles averaged, compared and tested as angles, each with its period.
//! A polarization angle and an HWP zero angle repeat every half turn (pi: 179 deg and 1 deg are
//! 2 deg apart), a position angle every turn (2 pi). The linear mean of 179 and 1 deg is 90 deg,
//! the worst answer there is; the circular mean is 0 deg. The workspace's averages of angles go
//! through this module (the zero angle from several standards, a trend's series of zero angles
//! and telescope offsets); no angle is averaged as a line.
//!
//! An angle `a` of period `P` is the point `(cos k a, sin k a)` of the unit circle, `k = 2 pi /
//! P`. The weighted mean is the direction of the weighted sum of those points (the mean
//! resultant); it is undefined when the sum vanishes (angles spread evenly round the circle),
//! and [`weighted_mean`] says so rather than return a direction of rounding noise. Differences
//! are wrapped into `(-P/2, P/2]` ([`difference`]); the scatter about a mean, the chi^2 and the
//! step test are taken on those differences, which for data spread much less than a period are
//! the linear ones. The circular median is the sample angle that minimizes the sum of absolute
//! differences to the others (Mardia & Jupp 2000, Directional Statistics, section 2.2.2).
//!
//! Everything is in radians.

use std::f64::consts::PI;

/// The period of an angle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Period {
    /// pi: polarization angles, HWP zero angles, the telescope's angle offsets.
    HalfTurn,
    /// 2 pi: position angles (parallactic, rotator, position angle on the sky).
    Turn,
}

impl Period {
    /// The period (rad).
    pub fn rad(self) -> f64 {
        match self {
            Period::HalfTurn => PI,
            Period::Turn => 2.0 * PI,
        }
    }
}

/// `a - b` wrapped into `(-P/2, P/2]`: the difference of two angles of period `P`.
pub fn difference(a: f64, b: f64, period: Period) -> f64 {
    wrap(a - b, period)
}

/// `a` wrapped into `(-P/2, P/2]`. For a half turn this is the workspace's
/// `mueller::wrap_half_pi`, to the bit.
pub fn wrap(a: f64, period: Period) -> f64 {
    match period {
        Period::HalfTurn => mueller::wrap_half_pi(a),
        Period::Turn => {
            let r = (a + PI).rem_euclid(2.0 * PI) - PI;
            if r <= -PI {
                r + 2.0 * PI
            } else {
                r
            }
        }
    }
}

/// The weighted circular mean of a sample ([`weighted_mean`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mean {
    /// The mean direction (rad), in `(-P/2, P/2]`.
    pub mean: f64,
    /// `sum w d^2` of the differences `d` from the mean (with `w = 1 / sigma^2`, the chi^2).
    pub chi2: f64,
    /// The mean resultant length `|sum w e^{i k a}| / sum w`, in `[0, 1]`: 1 for equal angles,
    /// near 0 for angles spread round the circle.
    pub resultant: f64,
}

/// Below this mean resultant length the mean direction is not defined: the sum of the unit
/// vectors is rounding noise (angles spread evenly round the circle).
pub const UNDEFINED_RESULTANT: f64 = 1e-12;

/// The weighted circular mean of `angles` (rad) with weights `w` (`1 / sigma^2` for a chi^2),
/// of period `period`; `None` for an empty sample, weights that are not finite and positive,
/// or a mean resultant below [`UNDEFINED_RESULTANT`].
pub fn weighted_mean(angles: &[f64], w: &[f64], period: Period) -> Option<Mean> {
    direction(angles, w, period).filter(|m| m.resultant >= UNDEFINED_RESULTANT)
}

/// [`weighted_mean`] whatever the mean resultant: the direction of the weighted sum of the
/// unit vectors even where it is rounding noise (0 where the sum is exactly zero), with the
/// resultant that says how much it means. For a caller that judges the spread itself (by the
/// chi^2 about the direction); `None` only for an empty sample or weights that are not finite
/// and positive.
pub fn direction(angles: &[f64], w: &[f64], period: Period) -> Option<Mean> {
    if angles.is_empty() || angles.len() != w.len() || w.iter().any(|x| !(x.is_finite() && *x > 0.0)) {
        return None;
    }
    let k = 2.0 * PI / period.rad();
    let (s, c) =
        angles.iter().zip(w).fold((0.0, 0.0), |(s, c), (&a, &wi)| (s + wi * (k * a).sin(), c + wi * (k * a).cos()));
    let resultant = s.hypot(c) / w.iter().sum::<f64>();
    let mean = wrap(s.atan2(c) / k, period);
    let chi2 = angles.iter().zip(w).map(|(&a, &wi)| wi * difference(a, mean, period).powi(2)).sum();
    Some(Mean { mean, chi2, resultant })
}

/// The circular mean of `angles` (equal weights).
pub fn mean(angles: &[f64], period: Period) -> Option<f64> {
    weighted_mean(angles, &vec![1.0; angles.len()], period).map(|m| m.mean)
}

/// The circular median (module docs): the sample angle with the least sum of absolute
/// differences to the others (of two such, the first); `None` for an empty sample.
pub fn median(angles: &[f64], period: Period) -> Option<f64> {
    let cost = |m: f64| angles.iter().map(|&a| difference(a, m, period).abs()).sum::<f64>();
    let mut best: Option<(f64, f64)> = None;
    for &m in angles {
        let c = cost(m);
        if best.is_none_or(|(_, bc)| c < bc) {
            best = Some((m, c));
        }
    }
    best.map(|(m, _)| wrap(m, period))
}

/// The circular standard deviation `sqrt(-2 ln R) / k` (rad) of `angles` (Mardia & Jupp 2000,
/// eq. 2.3.11): for angles spread by `s` much less than a period it is `s`; infinite for
/// angles spread evenly round the circle.
pub fn scatter(angles: &[f64], period: Period) -> f64 {
    let k = 2.0 * PI / period.rad();
    match weighted_mean(angles, &vec![1.0; angles.len()], period) {
        Some(m) => (-2.0 * m.resultant.min(1.0).ln()).max(0.0).sqrt() / k,
        None => f64::INFINITY,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn deg(v: &[f64]) -> Vec<f64> {
        v.iter().map(|d| d.to_radians()).collect()
    }

    #[test]
    fn angles_across_the_wrap_average_to_the_wrap() {
        // 179 and 1 deg as polarization angles: 0 deg (the linear mean, 90 deg, is the
        // orthogonal angle). As position angles, 359 and 1 deg: 0 deg.
        let m = mean(&deg(&[179.0, 1.0]), Period::HalfTurn).unwrap();
        assert!(m.to_degrees().abs() < 1e-12, "{}", m.to_degrees());
        let m = mean(&deg(&[359.0, 1.0]), Period::Turn).unwrap();
        assert!(m.to_degrees().abs() < 1e-12, "{}", m.to_degrees());
        // 179 and 1 deg as position angles: 90 deg.
        let m = mean(&deg(&[179.0, 1.0]), Period::Turn).unwrap();
        assert!((m.to_degrees() - 90.0).abs() < 1e-12);
    }

    #[test]
    fn the_mean_is_the_linear_one_for_a_tight_sample_and_turns_with_it() {
        // Closed form: for a sample spread much less than a period, the weighted circular mean
        // is the weighted linear mean to second order in the spread; turning every angle by
        // t turns the mean by t (equivariance), whatever t.
        let a = deg(&[30.0, 30.2, 29.9, 30.4]);
        let w = [1.0, 2.0, 1.0, 0.5];
        let lin = a.iter().zip(&w).map(|(x, y)| x * y).sum::<f64>() / w.iter().sum::<f64>();
        let m = weighted_mean(&a, &w, Period::HalfTurn).unwrap();
        assert!((m.mean - lin).abs() < 1e-6, "{} vs {}", m.mean, lin);
        for t in [-200.0f64, -91.0, 89.5, 150.0, 720.0] {
            let turned: Vec<f64> = a.iter().map(|x| x + t.to_radians()).collect();
            let mt = weighted_mean(&turned, &w, Period::HalfTurn).unwrap();
            assert!(difference(mt.mean, m.mean + t.to_radians(), Period::HalfTurn).abs() < 1e-12, "turn {t}");
            assert!((mt.chi2 - m.chi2).abs() < 1e-12);
        }
    }

    #[test]
    fn the_half_turn_wrap_is_the_workspaces() {
        for a in [-7.0, -3.2, -1.6, 0.0, std::f64::consts::FRAC_PI_2, 2.0, 9.9] {
            assert_eq!(wrap(a, Period::HalfTurn).to_bits(), mueller::wrap_half_pi(a).to_bits());
            let w = wrap(a, Period::Turn);
            assert!(w > -PI && w <= PI && ((a - w) / (2.0 * PI)).fract().abs() < 1e-12);
        }
    }

    #[test]
    fn an_even_spread_has_no_mean_and_infinite_scatter() {
        // Four angles a quarter period apart: the unit vectors cancel.
        assert!(mean(&deg(&[0.0, 45.0, 90.0, 135.0]), Period::HalfTurn).is_none());
        assert!(scatter(&deg(&[0.0, 90.0, 180.0, 270.0]), Period::Turn).is_infinite());
        assert!(weighted_mean(&[], &[], Period::Turn).is_none());
        assert!(weighted_mean(&[0.1], &[f64::NAN], Period::Turn).is_none());
        // The direction is still given (of the sums' rounding noise), with a resultant that
        // says it means nothing and a finite chi^2 about it.
        let d = direction(&[0.0, PI / 2.0], &[1.0, 1.0], Period::HalfTurn).unwrap();
        assert!(d.resultant < 1e-15 && d.chi2.is_finite(), "{d:?}");
    }

    #[test]
    fn scatter_and_median_against_closed_forms() {
        // Two angles +-d about 0: R = cos(k d), so sqrt(-2 ln cos(k d)) / k, which tends to d
        // for small d (the linear standard deviation of +-d).
        let d = 3f64.to_radians();
        let s = scatter(&[d, -d], Period::HalfTurn);
        assert!((s - (-2.0 * (2.0 * d).cos().ln()).sqrt() / 2.0).abs() < 1e-15);
        assert!((s - d).abs() < 1e-3 * d);
        // The median of 170, 175, 2, 8, 100 deg (period 180): 175 deg lies among the cluster
        // about 0 (sum of distances 5 + 7 + 13 + 75 = 100, against 102 for 170 and 2).
        let m = median(&deg(&[170.0, 175.0, 2.0, 8.0, 100.0]), Period::HalfTurn).unwrap();
        assert!((m.to_degrees() + 5.0).abs() < 1e-9, "{}", m.to_degrees());
    }
}
