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

#[cfg(test)]
mod tests {
    use super::*;

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
