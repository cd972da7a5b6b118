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
}
