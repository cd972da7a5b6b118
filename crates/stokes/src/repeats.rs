//! Repeated exposures at one HWP position: several exposures at the same
//! plate position (`theta`, or `theta + 360 deg`, the same position of a half-wave plate) are
//! combined, not refused, and an exposure that disagrees with its repeats is flagged by its
//! residual.
//!
//! Combining sums the beams' fluxes and adds their variances, as co-adding the frames would
//! (`skyfield` sums repeated frames the same way), so a sum of photon counts stays a count.
//! The check uses each exposure's own `F_j` (`eq:F`): the normalized difference is immune to
//! what changes between exposures in both beams alike (transparency, exposure time), so a
//! residual beyond its error says the exposure itself is wrong (a cosmic ray in one beam, a
//! plate not in position). The residual of `F_j` about the group's weighted mean `F` has
//! variance `sigma_j^2 - 1 / sum_k w_k` (`w_k = 1/sigma_k^2`), because the mean contains `F_j`.

use crate::solver::{normalized_difference, sigma_normalized_difference};
use serde::Serialize;
use std::f64::consts::TAU;

/// Angles (rad) equal modulo a full turn to within this are one plate position.
const SAME_POSITION_RAD: f64 = 1e-9;

/// One exposure's agreement with its repeats.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ExposureCheck {
    /// Index of the exposure in the input (0-based).
    pub index: usize,
    /// Index of the combined HWP position it went into.
    pub position: usize,
    /// Its own `F_j` (`eq:F`).
    pub f: f64,
    /// `(F_j - mean F) / sigma` of the residual (0 for a position with one exposure).
    pub pull: f64,
    /// `|pull|` above the threshold.
    pub outlier: bool,
}

/// Exposures combined per plate position.
#[derive(Debug, Clone, PartialEq)]
pub struct Combined {
    /// One entry per plate position, in order of first appearance (rad, as first given).
    pub theta: Vec<f64>,
    pub f_o: Vec<f64>,
    pub f_e: Vec<f64>,
    pub sigma_o: Vec<f64>,
    pub sigma_e: Vec<f64>,
    /// The exposures of each position (input indices).
    pub groups: Vec<Vec<usize>>,
    /// Every exposure's check, in input order.
    pub checks: Vec<ExposureCheck>,
}

impl Combined {
    /// True when some position had more than one exposure.
    pub fn any_repeats(&self) -> bool {
        self.groups.iter().any(|g| g.len() > 1)
    }
}

/// Plate positions (angles in rad, as [`combine_repeats`] groups them): the input order
/// sorted by the angle modulo a full turn, and the groups of equal positions, wrap included.
fn positions(theta: &[f64]) -> Vec<Vec<usize>> {
    let key = |i: usize| theta[i].rem_euclid(TAU);
    let mut order: Vec<usize> = (0..theta.len()).collect();
    order.sort_by(|&a, &b| key(a).total_cmp(&key(b)).then(a.cmp(&b)));
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for &i in &order {
        match groups.last_mut() {
            Some(g)
                if {
                    let d = (key(i) - key(g[0])).abs();
                    d < SAME_POSITION_RAD || (TAU - d) < SAME_POSITION_RAD
                } =>
            {
                g.push(i)
            }
            _ => groups.push(vec![i]),
        }
    }
    // The wrap: a group just below 2 pi and one at 0 are the same position.
    if groups.len() > 1 {
        let (a, b) = (key(groups[0][0]), key(groups[groups.len() - 1][0]));
        if TAU - (b - a) < SAME_POSITION_RAD {
            let last = groups.pop().unwrap();
            groups[0].extend(last);
        }
    }
    groups
}

/// True when two angles (rad) are the same plate position (equal modulo a full turn).
pub fn has_repeats(theta: &[f64]) -> bool {
    positions(theta).len() < theta.len()
}

/// Combine exposures at the same plate position (angles in rad, equal modulo 2 pi) and flag
/// exposures whose `F_j` lies more than `threshold` sigma from their position's mean.
/// The inputs are taken as they are (their validity is [`crate::Measurement`]'s to check).
pub fn combine_repeats(
    theta: &[f64],
    f_o: &[f64],
    f_e: &[f64],
    sigma_o: &[f64],
    sigma_e: &[f64],
    threshold: f64,
) -> Combined {
    let n = theta.len();
    // Sorted by the position modulo a full turn, then grouped: n log n.
    let mut groups = positions(theta);
    // Positions in the order of their first exposure; exposures in input order.
    groups.iter_mut().for_each(|g| g.sort_unstable());
    groups.sort_by_key(|g| g[0]);
    let mut out = Combined {
        theta: Vec::with_capacity(groups.len()),
        f_o: Vec::with_capacity(groups.len()),
        f_e: Vec::with_capacity(groups.len()),
        sigma_o: Vec::with_capacity(groups.len()),
        sigma_e: Vec::with_capacity(groups.len()),
        groups: vec![],
        checks: vec![ExposureCheck { index: 0, position: 0, f: f64::NAN, pull: 0.0, outlier: false }; n],
    };
    for (k, g) in groups.iter().enumerate() {
        out.theta.push(theta[g[0]]);
        out.f_o.push(g.iter().map(|&i| f_o[i]).sum());
        out.f_e.push(g.iter().map(|&i| f_e[i]).sum());
        out.sigma_o.push(g.iter().fold(0.0, |a, &i| mueller::hypot(a, sigma_o[i])));
        out.sigma_e.push(g.iter().fold(0.0, |a, &i| mueller::hypot(a, sigma_e[i])));
        let fs: Vec<(f64, f64)> = g
            .iter()
            .map(|&i| {
                (
                    normalized_difference(f_o[i], f_e[i]),
                    sigma_normalized_difference(f_o[i], f_e[i], sigma_o[i], sigma_e[i]),
                )
            })
            .collect();
        let sw: f64 = fs.iter().map(|(_, s)| 1.0 / (s * s)).sum();
        let mean = fs.iter().map(|(f, s)| f / (s * s)).sum::<f64>() / sw;
        for (&i, &(f, s)) in g.iter().zip(&fs) {
            let pull = if g.len() > 1 {
                let var = (s * s - 1.0 / sw).max(0.0);
                if var > 0.0 {
                    (f - mean) / var.sqrt()
                } else {
                    0.0
                }
            } else {
                0.0
            };
            out.checks[i] = ExposureCheck { index: i, position: k, f, pull, outlier: pull.abs() > threshold };
        }
    }
    out.groups = groups;
    out
}

/// An exposure whose `F` lies further than this (in sigma of its residual) from its repeats'
/// mean is flagged: beyond 4 sigma, one in 16 000 honest exposures.
pub const OUTLIER_SIGMA: f64 = 4.0;

/// One source's exposures as measured (angles in rad, the fluxes of both beams, their 1-sigma
/// errors or none for photon counts), combined per plate position when a position repeats:
/// `None` when none does (the exposures are reduced as they are). Photon counts (no errors)
/// take their Poisson errors `sqrt(f)` for the check and stay counts in the sums (the
/// combined errors are then the counts' own); a negative count is refused, naming its index,
/// before it can hide in a sum. Exposures beyond [`OUTLIER_SIGMA`] are flagged, not dropped.
pub fn combine_exposures(
    theta: &[f64],
    f_o: &[f64],
    f_e: &[f64],
    sigma: Option<(&[f64], &[f64])>,
) -> Result<Option<Combined>, crate::Error> {
    if !has_repeats(theta) {
        return Ok(None);
    }
    let poisson: (Vec<f64>, Vec<f64>);
    let (so, se) = match sigma {
        Some(s) => s,
        None => {
            if let Some(index) = f_o.iter().zip(f_e).position(|(o, e)| *o < 0.0 || *e < 0.0) {
                return Err(crate::Error::NegativeCount { index });
            }
            poisson = (f_o.iter().map(|v| v.sqrt()).collect(), f_e.iter().map(|v| v.sqrt()).collect());
            (&poisson.0[..], &poisson.1[..])
        }
    };
    Ok(Some(combine_repeats(theta, f_o, f_e, so, se, OUTLIER_SIGMA)))
}

/// One source reduced as `instpol stokes` and `instpol.stokes` reduce it: what
/// [`reduce_repeated`] returns.
#[derive(Debug, Clone)]
pub struct RepeatedReduction {
    pub reduction: crate::Reduction,
    /// The kappa applied (known, or estimated from the data), if any.
    pub kappa_applied: Option<f64>,
    /// The exposures combined per plate position; `None` when no position repeats.
    pub combined: Option<Combined>,
}

/// Why [`reduce_repeated`] failed: combining the exposures (indices are the exposures'), or
/// reducing them (indices are the combined positions', with the combination to name them by).
#[derive(Debug, Clone)]
pub enum RepeatedError {
    Combine(crate::Error),
    Reduce { error: crate::Error, combined: Option<Combined> },
}

/// One source's fluxes at plate angles `theta` (rad) reduced, the one composition of both
/// faces: exposures at one plate position combined ([`combine_exposures`]), the measurement
/// (Poisson counts, or with the errors `sigma` given), the Wollaston imbalance treated as
/// `kappa` says (`crate::Measurement::reduce_with`, `sec:wollaston`), the reduction.
pub fn reduce_repeated(
    theta: &[f64],
    f_o: &[f64],
    f_e: &[f64],
    sigma: Option<(&[f64], &[f64])>,
    kappa: crate::KappaCorrection,
) -> Result<RepeatedReduction, RepeatedError> {
    let combined = combine_exposures(theta, f_o, f_e, sigma).map_err(RepeatedError::Combine)?;
    let (th, o, e, errs) = match &combined {
        Some(c) => {
            (c.theta.clone(), c.f_o.clone(), c.f_e.clone(), sigma.map(|_| (c.sigma_o.clone(), c.sigma_e.clone())))
        }
        None => (theta.to_vec(), f_o.to_vec(), f_e.to_vec(), sigma.map(|(a, b)| (a.to_vec(), b.to_vec()))),
    };
    let reduced = match errs {
        Some((so, se)) => crate::Measurement::with_errors(th, o, e, so, se),
        None => crate::Measurement::poisson(th, o, e),
    }
    .and_then(|m| m.reduce_with(kappa));
    match reduced {
        Ok((reduction, kappa_applied)) => Ok(RepeatedReduction { reduction, kappa_applied, combined }),
        Err(error) => Err(RepeatedError::Reduce { error, combined }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two cycles of four plate positions: the one composition gives the polarization of the
    /// counts summed per position by hand, which for a noiseless source of `q`, `u` written in
    /// the test is exactly that source (`F_i = q cos 4 theta + u sin 4 theta`, eq:F, eq:Q,
    /// eq:U); a known kappa scales the beams before it, and its range is refused.
    #[test]
    fn repeats_summed_by_hand_give_the_source() {
        let (q, u) = (0.03, -0.02);
        let deg = [0.0, 22.5, 45.0, 67.5, 0.0, 22.5, 45.0, 67.5];
        let theta: Vec<f64> = deg.iter().map(|d: &f64| d.to_radians()).collect();
        let total = [1000.0, 1000.0, 1000.0, 1000.0, 3000.0, 3000.0, 3000.0, 3000.0];
        let f = |t: f64| q * (4.0 * t).cos() + u * (4.0 * t).sin();
        let f_o: Vec<f64> = theta.iter().zip(total).map(|(&t, n)| n * (1.0 + f(t)) / 2.0).collect();
        let f_e: Vec<f64> = theta.iter().zip(total).map(|(&t, n)| n * (1.0 - f(t)) / 2.0).collect();
        let r = reduce_repeated(&theta, &f_o, &f_e, None, crate::KappaCorrection::None).unwrap();
        let c = r.combined.as_ref().expect("positions repeat");
        for k in 0..4 {
            assert!((c.f_o[k] - (f_o[k] + f_o[k + 4])).abs() < 1e-9 && (c.f_e[k] - (f_e[k] + f_e[k + 4])).abs() < 1e-9);
        }
        assert!((r.reduction.qu.q - q).abs() < 1e-12 && (r.reduction.qu.u - u).abs() < 1e-12);
        assert_eq!(r.kappa_applied, None);
        let k = reduce_repeated(&theta, &f_o, &f_e, None, crate::KappaCorrection::Known(0.01)).unwrap();
        assert_eq!(k.kappa_applied, Some(0.01));
        let bad = reduce_repeated(&theta, &f_o, &f_e, None, crate::KappaCorrection::Known(1.0));
        assert!(matches!(
            bad,
            Err(RepeatedError::Reduce { error: crate::Error::KappaOutOfRange(_), combined: Some(_) })
        ));
    }

    /// Plate positions equal modulo a full turn are one, across the wrap too (-1e-12 rad and
    /// 720 deg go with 0); positions keep the order of their first exposure; sums and
    /// variances add.
    #[test]
    fn groups_by_position_modulo_a_turn() {
        let th = [0.5, 0.0, TAU - 1e-12, 4.0 * std::f64::consts::PI, 0.5 + TAU];
        let ones = [1.0; 5];
        let c = combine_repeats(&th, &[10.0, 1.0, 2.0, 3.0, 20.0], &ones, &ones, &ones, 4.0);
        assert_eq!(c.groups, vec![vec![0, 4], vec![1, 2, 3]]);
        assert_eq!(c.f_o, vec![30.0, 6.0]);
        assert_eq!(c.f_e, vec![2.0, 3.0]);
        assert!((c.sigma_o[1] - 3f64.sqrt()).abs() < 1e-15);
        assert_eq!(c.theta, vec![0.5, 0.0]);
        assert!(c.any_repeats());
        assert!(has_repeats(&th) && has_repeats(&[0.0, TAU - 1e-12]));
        assert!(!has_repeats(&[0.0, 0.5, 1.0, TAU - 1e-3]));
    }

    /// Photon counts are checked with sqrt(f) and summed as counts; a negative count is
    /// refused by its index; no repeat, nothing combined; an exposure 7.6 sigma off is flagged.
    #[test]
    fn exposures_combined_with_the_poisson_fallback() {
        let th = [0.0, 0.5, 0.0, 1.0];
        let (fo, fe) = ([100.0, 50.0, 400.0, 60.0], [100.0, 70.0, 100.0, 40.0]);
        let c = combine_exposures(&th, &fo, &fe, None).unwrap().unwrap();
        assert_eq!((c.f_o[0], c.f_e[0]), (500.0, 200.0));
        // F = 0 and 0.6 with sigma_F = 2 sqrt(f_o f_e / (f_o + f_e)^3) (eq:F, Poisson errors).
        let sf = |o: f64, e: f64| 2.0 * (o * e / (o + e).powi(3)).sqrt();
        let (s1, s2) = (sf(100.0, 100.0), sf(400.0, 100.0));
        let sw = 1.0 / (s1 * s1) + 1.0 / (s2 * s2);
        let mean = (0.0 / (s1 * s1) + 0.6 / (s2 * s2)) / sw;
        let pull = (0.0 - mean) / (s1 * s1 - 1.0 / sw).sqrt();
        assert!((c.checks[0].pull - pull).abs() < 1e-12 && pull.abs() > OUTLIER_SIGMA && c.checks[0].outlier);
        assert_eq!(combine_exposures(&[0.0, 0.5], &[1.0, 2.0], &[1.0, 2.0], None).unwrap(), None);
        let neg = combine_exposures(&th, &[1.0, 1.0, -1.0, 1.0], &fe, None).unwrap_err();
        assert_eq!(neg, crate::Error::NegativeCount { index: 2 });
        let ones = [1.0; 4];
        let given = combine_exposures(&th, &[1.0, 1.0, -1.0, 1.0], &fe, Some((&ones, &ones))).unwrap().unwrap();
        assert_eq!(given.f_o[0], 0.0);
    }
}
