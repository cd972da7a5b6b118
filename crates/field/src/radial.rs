//! The paper's radial polynomial (section `sec:fors1`): `p(r) = sum_k c_k r^k`, evaluated in
//! one place for the fitter, the simulator and the corrections, and the radial pattern
//! (`phi` = the polar angle about the optical axis) it describes.

use crate::model::{FieldModel, InstPol};
use std::f64::consts::PI;

/// `r^k` for the small powers of the models (k = 0, 1 in practice) without `powi`'s call.
#[inline]
fn pow_small(r: f64, k: usize) -> f64 {
    let mut v = 1.0;
    for _ in 0..k {
        v *= r;
    }
    v
}

/// `p(r) = sum_i coeffs[i] r^(first_power + i)` (section `sec:fors1`), by Horner in `r` then
/// the `r^first_power` factor.
///
/// ```
/// // The paper's V band, percent: p(4.1') = 0.012 4.1 + 0.046 4.1^2 + 0.002 4.1^3 = 0.9593 %.
/// let p = field::radial::poly(1, &[0.012, 0.046, 0.002], 4.1);
/// assert!((p - (0.012 * 4.1 + 0.046 * 4.1 * 4.1 + 0.002 * 4.1f64.powi(3))).abs() < 1e-15);
/// ```
#[inline]
pub fn poly(first_power: usize, coeffs: &[f64], r: f64) -> f64 {
    let mut s = 0.0;
    for c in coeffs.iter().rev() {
        s = s * r + c;
    }
    s * pow_small(r, first_power)
}

/// `(p(r), dp/dr)` of [`poly`] (section `sec:fors1`): Horner for the sum and its derivative
/// together, then the product rule for the `r^first_power` factor. `p` is bit-identical to
/// [`poly`].
#[inline]
pub fn poly_and_derivative(first_power: usize, coeffs: &[f64], r: f64) -> (f64, f64) {
    let (mut s, mut ds) = (0.0, 0.0);
    for c in coeffs.iter().rev() {
        ds = ds * r + s;
        s = s * r + c;
    }
    let rf = pow_small(r, first_power);
    let df = if first_power == 0 { 0.0 } else { first_power as f64 * pow_small(r, first_power - 1) };
    (s * rf, df * s + rf * ds)
}

/// A given radial pattern (a simulation's input, not a fit): `p(r) = sum_k c_k r^k` (`c_k` a
/// fraction, index = power of r, r in arcmin from `centre`) with `phi` = the polar angle of the
/// position about `centre` plus `phi_offset` (section `sec:fors1`: `phi_offset = 0`, the
/// radial pattern). A negative `p` is the same partial polarizer turned by 90 deg (a
/// tangential pattern). No covariance: the fitted model with errors is `fit::RadialModel`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RadialPattern {
    pub coeffs: Vec<f64>,
    /// Optical-axis centre, arcmin from the field origin.
    pub centre: [f64; 2],
    /// Added to the polar angle (rad).
    pub phi_offset: f64,
}

impl RadialPattern {
    /// The pattern of coefficients `c_0, c_1, ...` (fractions) about `centre`, radial.
    ///
    /// ```
    /// use field::{FieldModel, RadialPattern};
    /// // The paper's V pattern p(r) = 0.012 r + 0.046 r^2 + 0.002 r^3 % (sec:fors1) at the corner
    /// // star's position (2.53', -3.23'): r = 4.10', p = 0.960 %, radial (phi = the polar angle).
    /// let v = RadialPattern::new(vec![0.0, 0.012e-2, 0.046e-2, 0.002e-2], [0.0, 0.0]);
    /// let (x, y) = (2.53, -3.23);
    /// let r = f64::hypot(x, y);
    /// let inst = v.eval(x, y);
    /// let p = 1e-2 * (0.012 * r + 0.046 * r * r + 0.002 * r * r * r);
    /// assert!((f64::hypot(inst.q, inst.u) - p).abs() < 1e-15 && (p - 0.0096).abs() < 5e-5);
    /// assert!((0.5 * inst.u.atan2(inst.q) - y.atan2(x)).abs() < 1e-12);
    /// ```
    pub fn new(coeffs: Vec<f64>, centre: [f64; 2]) -> Self {
        Self { coeffs, centre, phi_offset: 0.0 }
    }
}

impl FieldModel for RadialPattern {
    fn eval(&self, x: f64, y: f64) -> InstPol {
        let (p, phi) = self.p_phi(x, y);
        InstPol { q: p * (2.0 * phi).cos(), u: p * (2.0 * phi).sin(), ..Default::default() }
    }

    fn contains(&self, _x: f64, _y: f64) -> bool {
        true
    }

    /// `p(r)` and the polar angle (+ offset), a negative `p` turned by 90 deg.
    fn p_phi(&self, x: f64, y: f64) -> (f64, f64) {
        let (dx, dy) = (x - self.centre[0], y - self.centre[1]);
        let p = poly(0, &self.coeffs, dx.hypot(dy));
        let phi = dy.atan2(dx) + self.phi_offset;
        if p >= 0.0 {
            (p, phi)
        } else {
            (-p, phi + 0.5 * PI)
        }
    }

    fn params(&self) -> Vec<f64> {
        self.coeffs.clone()
    }

    /// `dq/dc_k = r^k cos 2phi`, `du/dc_k = r^k sin 2phi` (the centre and offset are fixed).
    fn jacobian(&self, x: f64, y: f64) -> Option<(Vec<f64>, Vec<f64>)> {
        let (dx, dy) = (x - self.centre[0], y - self.centre[1]);
        let r = dx.hypot(dy);
        let a = 2.0 * (dy.atan2(dx) + self.phi_offset);
        let rk = (0..self.coeffs.len()).map(|k| r.powi(k as i32));
        Some((rk.clone().map(|v| v * a.cos()).collect(), rk.map(|v| v * a.sin()).collect()))
    }

    fn describe(&self) -> String {
        format!(
            "radial polynomial p(r) = sum c_k r^k, c = {:?} (fractions), centre {:?} arcmin, phi = polar angle + {} deg",
            self.coeffs,
            self.centre,
            self.phi_offset.to_degrees()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Against the sum written term by term, and the derivative against a central difference.
    #[test]
    fn poly_against_term_sum_and_derivative() {
        let c = [0.012, 0.046, 0.002, -0.0007];
        for f in 0..3 {
            for r in [0.0f64, 0.3, 1.0, 2.7, 4.83] {
                let direct: f64 = c.iter().enumerate().map(|(i, ck)| ck * r.powi((f + i) as i32)).sum();
                assert!((poly(f, &c, r) - direct).abs() < 1e-15, "f {f} r {r}");
                let (p, dp) = poly_and_derivative(f, &c, r);
                assert_eq!(p, poly(f, &c, r));
                let h = 1e-6;
                let num = (poly(f, &c, r + h) - poly(f, &c, (r - h).max(0.0))) / (r + h - (r - h).max(0.0));
                // One-sided at r = 0: its error is c_(k+1) h ~ 5e-8.
                assert!((dp - num).abs() < 1e-7, "f {f} r {r}: {dp} vs {num}");
            }
        }
    }

    /// The paper's V pattern at (3', 4') from the centre: r = 5', alpha = atan2(4, 3).
    #[test]
    fn pattern_by_hand() {
        let m = RadialPattern::new(vec![0.0, 0.012e-2, 0.046e-2, 0.002e-2], [0.0, 0.0]);
        let (p, phi) = m.p_phi(3.0, 4.0);
        assert!((p - (0.012e-2 * 5.0 + 0.046e-2 * 25.0 + 0.002e-2 * 125.0)).abs() < 1e-16);
        assert!((phi - 4f64.atan2(3.0)).abs() < 1e-15);
        // q = p cos 2a with cos 2a = (3^2 - 4^2)/25, sin 2a = 2 3 4 / 25.
        let v = m.eval(3.0, 4.0);
        assert!((v.q - p * (-7.0 / 25.0)).abs() < 1e-16 && (v.u - p * (24.0 / 25.0)).abs() < 1e-16);
        // A negative p is the tangential pattern: p > 0 at phi + 90 deg.
        let t = RadialPattern::new(vec![0.0, -0.01], [1.0, 0.0]);
        let (p, phi) = t.p_phi(1.0, 2.0);
        assert!((p - 0.02).abs() < 1e-16 && (phi - PI).abs() < 1e-15);
        // Jacobian: the model is linear in the coefficients.
        let (jq, ju) = m.jacobian(3.0, 4.0).unwrap();
        let q: f64 = jq.iter().zip(&m.coeffs).map(|(a, b)| a * b).sum();
        let u: f64 = ju.iter().zip(&m.coeffs).map(|(a, b)| a * b).sum();
        assert!((q - v.q).abs() < 1e-16 && (u - v.u).abs() < 1e-16);
    }
}
