//! The polar-angle test of section `sec:fors1` (lower panels of fig:radprofB): the angle `phi`
//! of the instrumental polarization against the polar angle `alpha` of the bin about the
//! centre. A radial pattern lies on `phi = alpha` (slope 1, intercept 0, modulo 180 deg).

use crate::bins::Bin;
use crate::radial::ErrorScaling;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// The fitted line `phi = slope * alpha + intercept` (degrees) and the points it was fitted to.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolarAngleTest {
    pub slope: f64,
    pub slope_err: f64,
    pub intercept_deg: f64,
    pub intercept_err_deg: f64,
    /// Per used bin: `alpha` in (-180, 180] deg and `phi` unwrapped onto the fitted line (deg).
    pub alpha_deg: Vec<f64>,
    pub phi_deg: Vec<f64>,
    pub sigma_phi_deg: Vec<f64>,
}

/// `a` wrapped into (-90, 90]: differences of polarization angles are taken modulo 180 deg.
pub fn wrap_half_turn_deg(a: f64) -> f64 {
    let w = (a + 90.0).rem_euclid(180.0) - 90.0;
    if w <= -90.0 {
        w + 180.0
    } else {
        w
    }
}

/// Fit `phi` against `alpha` for the bins (about `centre`, arcmin) by weighted least squares
/// with weights `1 / sigma_phi^2`, unwrapping each `phi` onto the current line (modulo 180
/// deg) and iterating. Bins closer than `r_min` arcmin to the centre are left out (their
/// polar angle is ill defined). The errors are scaled by `max(1, chi2_red)`
/// ([`ErrorScaling::Conservative`]; [`polar_angle_test_with`] chooses).
pub fn polar_angle_test(bins: &[Bin], centre: [f64; 2], r_min: f64) -> Result<PolarAngleTest> {
    polar_angle_test_with(bins, centre, r_min, ErrorScaling::Conservative, 1.0)
}

/// [`polar_angle_test`] with the errors scaled as `scaling` says and the variances multiplied
/// by `inflation` (the correlated-errors factor of the radial fit on the same bins, or 1).
pub fn polar_angle_test_with(
    bins: &[Bin],
    centre: [f64; 2],
    r_min: f64,
    scaling: ErrorScaling,
    inflation: f64,
) -> Result<PolarAngleTest> {
    let mut alpha = vec![];
    let mut phi = vec![];
    let mut sig = vec![];
    for b in bins.iter().filter(|b| b.used && b.is_valid()) {
        let (dx, dy) = (b.x - centre[0], b.y - centre[1]);
        if dx.hypot(dy) < r_min {
            continue;
        }
        let (p, ph) = b.p_phi();
        if p <= 0.0 {
            continue;
        }
        // sigma_phi = sqrt(u^2 sq^2 + q^2 su^2) / (2 p^2) (rad), from phi = atan2(u, q) / 2.
        let s = (b.u * b.u * b.sigma_q * b.sigma_q + b.q * b.q * b.sigma_u * b.sigma_u).sqrt() / (2.0 * p * p);
        alpha.push(crate::region::polar_angle(dx, dy).to_degrees());
        phi.push(ph.to_degrees());
        // Floor at 1e-3 deg: maps given without noise must not get infinite weights.
        sig.push(s.to_degrees().clamp(1e-3, 90.0));
    }
    if alpha.len() < 3 {
        return Err(Error::TooFewBins { used: alpha.len(), total: bins.len(), needed: 3 });
    }
    // Start from slope 1 and the circular mean offset of phi - alpha (period 180 deg), so that
    // a tangential pattern (offset 90) is not torn apart at the +-90 wrap.
    let (mut ss, mut cc) = (0.0, 0.0);
    for k in 0..alpha.len() {
        let d = 2.0 * (phi[k] - alpha[k]).to_radians();
        let w = 1.0 / (sig[k] * sig[k]);
        ss += w * d.sin();
        cc += w * d.cos();
    }
    let (mut a, mut b) = (1.0, 0.5 * ss.atan2(cc).to_degrees());
    let mut unwrapped = phi.clone();
    let mut cov = [[0.0; 2]; 2];
    for _ in 0..8 {
        for k in 0..alpha.len() {
            let line = a * alpha[k] + b;
            unwrapped[k] = line + wrap_half_turn_deg(phi[k] - line);
        }
        // Weighted linear regression.
        let (mut s, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for k in 0..alpha.len() {
            let w = 1.0 / (sig[k] * sig[k]);
            s += w;
            sx += w * alpha[k];
            sy += w * unwrapped[k];
            sxx += w * alpha[k] * alpha[k];
            sxy += w * alpha[k] * unwrapped[k];
        }
        let det = s * sxx - sx * sx;
        if !(det > 0.0) {
            return Err(Error::Degenerate("the bins do not span a range of polar angles".into()));
        }
        let (na, nb) = ((s * sxy - sx * sy) / det, (sxx * sy - sx * sxy) / det);
        cov = [[s / det, -sx / det], [-sx / det, sxx / det]];
        let done = (na - a).abs() < 1e-10 && (nb - b).abs() < 1e-8;
        a = na;
        b = nb;
        if done {
            break;
        }
    }
    let chi2: f64 = (0..alpha.len()).map(|k| ((unwrapped[k] - a * alpha[k] - b) / sig[k]).powi(2)).sum();
    let scale = scaling.factor(chi2 / (alpha.len() as f64 - 2.0).max(1.0)) * inflation;
    Ok(PolarAngleTest {
        slope: a,
        slope_err: (cov[0][0] * scale).sqrt(),
        intercept_deg: wrap_half_turn_deg(b),
        intercept_err_deg: (cov[1][1] * scale).sqrt(),
        alpha_deg: alpha,
        phi_deg: unwrapped,
        sigma_phi_deg: sig,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radial_and_tangential_patterns() {
        // A radial pattern (phi = alpha) has slope 1, intercept 0; a tangential one
        // (phi = alpha + 90) slope 1, intercept 90 == -90 modulo 180.
        for (offset, want) in [(0.0, 0.0), (90.0f64, 90.0)] {
            let mut bins = vec![];
            for k in 0..72 {
                let a = (k as f64 * 5.0 + 1.0).to_radians();
                let (x, y) = (2.0 * a.cos(), 2.0 * a.sin());
                let ph = a + offset.to_radians();
                bins.push(Bin::new(x, y, 0.01 * (2.0 * ph).cos(), 0.01 * (2.0 * ph).sin(), 1e-4, 1e-4));
            }
            let t = polar_angle_test(&bins, [0.0, 0.0], 0.1).unwrap();
            assert!((t.slope - 1.0).abs() < 1e-9, "{}", t.slope);
            assert!(wrap_half_turn_deg(t.intercept_deg - want).abs() < 1e-6, "{}", t.intercept_deg);
        }
    }

    #[test]
    fn wrap_edges() {
        assert_eq!(wrap_half_turn_deg(90.0), 90.0);
        assert_eq!(wrap_half_turn_deg(-90.0), 90.0);
        assert!((wrap_half_turn_deg(179.0) + 1.0).abs() < 1e-12);
        assert!((wrap_half_turn_deg(-181.0) + 1.0).abs() < 1e-12);
    }
}
