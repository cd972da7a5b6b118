//! The sky-field solution (section `sec:instr`): from the measured normalized Stokes
//! parameters `(Q1/I1, U1/I1)` of an empty field whose sky polarization `(P_sky, chi_sky)` is
//! known, the instrumental polarization `p`, `phi` in every bin.
//!
//! Two solutions are given side by side:
//!
//! - **approximate** (`eq:approx`, for `p, P_sky << 1`): with `dQ = q1 - q0`, `dU = u1 - u0`,
//!   `tan 2phi = dU / dQ` and the paper's two estimates `p_1 = dQ / cos 2phi`,
//!   `p_2 = dU / sin 2phi`. Averaging them with weights `cos^2 2phi` and `sin^2 2phi` (which
//!   give each estimate the weight its own sensitivity deserves and remove the blow-ups at
//!   `cos 2phi ~ 0` and `sin 2phi ~ 0`) is exactly
//!   `(dQ cos 2phi + dU sin 2phi) = hypot(dQ, dU)`: the stable form used here, with
//!   `2phi = atan2(dU, dQ)`.
//! - **exact**: `eq:instpol` (the Mueller matrix `mueller::partial_polarizer`) inverted in closed
//!   form. In the frame of the polarizer's axis `a = (cos 2phi, sin 2phi)` the normalized
//!   output is `m_par = (v_par + p) / (1 + p v_par)`, `m_perp = (1 - p) v_perp / (1 + p v_par)`
//!   for sky `v = (q0, u0)`. Eliminating `p` leaves `a_perp . (m - v) = v x m`, i.e.
//!   `sin(psi - 2phi) = (v x d) / |d|` with `d = m - v`, `psi = atan2(dU, dQ)`; the root with
//!   `p >= 0` is `2phi = psi - asin((v x d) / |d|)`, and then
//!   `p = (m_par - v_par) / (1 - m_par v_par) = sqrt(|d|^2 - (v x d)^2) / (1 - m_par v_par)`.
//!   The approximation is the limit `v -> 0`; the two part at order `P_sky` in angle and
//!   `P_sky^2`, `p P_sky` in degree.
//!
//! Errors per bin are propagated from the map's `(sigma_q, sigma_u, cov_qu)` through the
//! Jacobian of the exact solution (central differences of the closed form).

use crate::{Error, StokesMap};
use serde::{Deserialize, Serialize};

/// The sky's own polarization over the field (constant, as the paper assumes).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SkyPolarization {
    /// Degree (fraction).
    pub p: f64,
    /// Angle (rad).
    pub chi: f64,
}

impl SkyPolarization {
    /// From the CLI's units: percent and degrees (any sign; taken modulo 180).
    pub fn from_percent_deg(p_percent: f64, chi_deg: f64) -> Result<Self, Error> {
        if !(p_percent.is_finite() && (0.0..100.0).contains(&p_percent)) {
            return Err(Error::Invalid(format!("sky polarization {p_percent}% is not in [0, 100)")));
        }
        if !chi_deg.is_finite() {
            return Err(Error::Invalid(format!("sky polarization angle {chi_deg} deg is not finite")));
        }
        Ok(SkyPolarization { p: p_percent / 100.0, chi: mueller::fold_pi(chi_deg.to_radians()) })
    }

    /// `(q0, u0) = P (cos 2chi, sin 2chi)` (`eq:QU`).
    pub fn qu(&self) -> (f64, f64) {
        let (s, c) = (2.0 * self.chi).sin_cos();
        (self.p * c, self.p * s)
    }
}

/// `eq:approx` solved for `(p, phi)` (phi in [0, pi)): the weighted mean of the paper's `p_1`
/// and `p_2` with weights `cos^2 2phi`, `sin^2 2phi`, i.e. `hypot(dQ, dU)`.
///
/// ```
/// use skyfield::solve::solve_approx;
/// // eq:approx: the sky's 1.74 % at -53.8 deg (V field) plus an instrument of 0.5 % at 10 deg
/// // measures their sum; the difference is the instrument again.
/// let qu = |p: f64, chi: f64| (p * (2.0 * chi).to_radians().cos(), p * (2.0 * chi).to_radians().sin());
/// let ((q0, u0), (qi, ui)) = (qu(0.0174, -53.8), qu(0.005, 10.0));
/// let (p, phi) = solve_approx(q0 + qi, u0 + ui, q0, u0);
/// assert!((p - 0.005).abs() < 1e-15 && (phi.to_degrees() - 10.0).abs() < 1e-10);
/// ```
pub fn solve_approx(q1: f64, u1: f64, q0: f64, u0: f64) -> (f64, f64) {
    let (dq, du) = (q1 - q0, u1 - u0);
    let p = dq.hypot(du);
    let phi = if p > 0.0 { mueller::fold_pi(0.5 * du.atan2(dq)) } else { 0.0 };
    (p, phi)
}

/// `eq:instpol` inverted exactly for `(p, phi)` (phi in [0, pi)) given the sky `(q0, u0)` and
/// the measured normalized `(q1, u1)`; closed form derived in the module docs. `None` when the
/// input is not physical (`|v| >= 1`, `|m| >= 1`) or the solution has `p >= 1`.
///
/// ```
/// use skyfield::solve::solve_exact;
/// // eq:instpol written out: unpolarized-normalized M_I(p, phi) acting on the sky (1, q0, u0),
/// // here p = 1 %, phi = 30 deg on the B field's 6.45 % at 68.4 deg.
/// let (p, phi) = (0.01f64, 30f64.to_radians());
/// let (c, s) = ((2.0 * phi).cos(), (2.0 * phi).sin());
/// let (q0, u0) = (0.0645 * (136.8f64).to_radians().cos(), 0.0645 * (136.8f64).to_radians().sin());
/// let i1 = 1.0 + p * c * q0 + p * s * u0;
/// let q1 = (p * c + (1.0 - p * s * s) * q0 + p * c * s * u0) / i1;
/// let u1 = (p * s + p * c * s * q0 + (1.0 - p * c * c) * u0) / i1;
/// let (pe, phie) = solve_exact(q1, u1, q0, u0).unwrap();
/// assert!((pe - p).abs() < 1e-14 && (phie - phi).abs() < 1e-10);
/// ```
pub fn solve_exact(q1: f64, u1: f64, q0: f64, u0: f64) -> Option<(f64, f64)> {
    let (dq, du) = (q1 - q0, u1 - u0);
    if !(q0.hypot(u0) < 1.0 && q1.hypot(u1) < 1.0) {
        return None;
    }
    let d = dq.hypot(du);
    if d == 0.0 {
        return Some((0.0, 0.0));
    }
    let k = q0 * du - u0 * dq; // v x d
    let delta = (k / d).clamp(-1.0, 1.0).asin();
    let two_phi = du.atan2(dq) - delta;
    let (s, c) = two_phi.sin_cos();
    let m_par = q1 * c + u1 * s;
    let v_par = q0 * c + u0 * s;
    let p = ((d - k) * (d + k)).max(0.0).sqrt() / (1.0 - m_par * v_par);
    if !(p < 1.0) {
        return None;
    }
    Some((p, mueller::fold_pi(0.5 * two_phi)))
}

/// The instrumental polarization found in one bin.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BinSolution {
    /// Bin centre, arcmin from the detector centre.
    pub x: f64,
    pub y: f64,
    /// Exact solution: degree (fraction) and angle (rad, [0, pi)).
    pub p: f64,
    pub phi: f64,
    /// `q = p cos 2phi`, `u = p sin 2phi` of the exact solution and their covariance
    /// (serialized as the fields `q`, `u`, `var_q`, `var_u`, `cov_qu`, as before).
    #[serde(flatten)]
    pub qu: mueller::Qu,
    pub sigma_p: f64,
    pub sigma_phi: f64,
    /// The approximate solution (`eq:approx`).
    pub p_approx: f64,
    pub phi_approx: f64,
}

impl BinSolution {
    /// `p_exact - p_approx` (fraction).
    pub fn dp(&self) -> f64 {
        self.p - self.p_approx
    }
    /// `phi_exact - phi_approx` wrapped into (-pi/2, pi/2].
    pub fn dphi(&self) -> f64 {
        let h = std::f64::consts::FRAC_PI_2;
        let w = (self.phi - self.phi_approx + h).rem_euclid(std::f64::consts::PI) - h;
        if w <= -h {
            w + std::f64::consts::PI
        } else {
            w
        }
    }
}

/// Solve one bin: exact and approximate `(p, phi)`, with the covariance of the instrumental
/// `(q, u)` propagated from the measured `(sigma_q, sigma_u, cov_qu)`. `None` when the exact
/// inversion has no physical solution.
#[allow(clippy::too_many_arguments)]
pub fn solve_bin(
    x: f64,
    y: f64,
    q1: f64,
    u1: f64,
    sigma_q: f64,
    sigma_u: f64,
    cov_qu: f64,
    sky: &SkyPolarization,
) -> Option<BinSolution> {
    let (q0, u0) = sky.qu();
    let (p, phi) = solve_exact(q1, u1, q0, u0)?;
    let (pa, phia) = solve_approx(q1, u1, q0, u0);
    let qu = |m1: f64, m2: f64| -> Option<(f64, f64)> {
        let (p, phi) = solve_exact(m1, m2, q0, u0)?;
        Some((p * (2.0 * phi).cos(), p * (2.0 * phi).sin()))
    };
    let (q, u) = (p * (2.0 * phi).cos(), p * (2.0 * phi).sin());
    // Jacobian of (q, u)_inst with respect to (q1, u1) by central differences; the closed form
    // is smooth away from p = 0, and exactly the identity when the sky is unpolarized.
    let h = 1e-6;
    let (a, b) = (qu(q1 + h, u1)?, qu(q1 - h, u1)?);
    let (c, d) = (qu(q1, u1 + h)?, qu(q1, u1 - h)?);
    let j = [[(a.0 - b.0) / (2.0 * h), (c.0 - d.0) / (2.0 * h)], [(a.1 - b.1) / (2.0 * h), (c.1 - d.1) / (2.0 * h)]];
    let cm = [[sigma_q * sigma_q, cov_qu], [cov_qu, sigma_u * sigma_u]];
    let mut ci = [[0.0; 2]; 2];
    for r in 0..2 {
        for s in 0..2 {
            for k in 0..2 {
                for l in 0..2 {
                    ci[r][s] += j[r][k] * cm[k][l] * j[s][l];
                }
            }
        }
    }
    let (vq, vu, cqu) = (ci[0][0], ci[1][1], ci[0][1]);
    let (sigma_p, sigma_phi) = if p > 0.0 {
        (
            ((q * q * vq + u * u * vu + 2.0 * q * u * cqu) / (p * p)).max(0.0).sqrt(),
            ((u * u * vq + q * q * vu - 2.0 * q * u * cqu) / (4.0 * p.powi(4))).max(0.0).sqrt(),
        )
    } else {
        (0.5 * (vq + vu).sqrt(), std::f64::consts::FRAC_PI_2)
    };
    Some(BinSolution {
        x,
        y,
        p,
        phi,
        qu: mueller::Qu::new(q, u, vq, vu, cqu),
        sigma_p,
        sigma_phi,
        p_approx: pa,
        phi_approx: phia,
    })
}

/// Solve every valid bin of a Stokes map for the instrumental polarization, given the sky's.
/// Bins whose exact inversion has no physical solution are skipped; the count is returned.
pub fn solve_map(map: &StokesMap, sky: &SkyPolarization) -> Result<(Vec<BinSolution>, usize), Error> {
    if !(sky.p.is_finite() && sky.p >= 0.0 && sky.p < 1.0 && sky.chi.is_finite()) {
        return Err(Error::Invalid(format!("sky polarization p = {}, chi = {} rad is not physical", sky.p, sky.chi)));
    }
    let mut out = vec![];
    let mut skipped = 0;
    for (k, i, j) in map.valid_bins() {
        let (x, y) = map.geometry.centre_arcmin(i, j);
        let cov = if map.cov_qu[k].is_finite() { map.cov_qu[k] } else { 0.0 };
        let (sq, su) = (map.sigma_q[k], map.sigma_u[k]);
        if !(map.q[k].is_finite() && map.u[k].is_finite() && sq.is_finite() && su.is_finite()) {
            skipped += 1;
            continue;
        }
        match solve_bin(x, y, map.q[k], map.u[k], sq, su, cov, sky) {
            Some(s) => out.push(s),
            None => skipped += 1,
        }
    }
    if out.is_empty() {
        return Err(Error::NoValidBins);
    }
    Ok((out, skipped))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Forward model: the sky through `M_I(p, phi)` (`eq:instpol`), normalized.
    fn forward(p: f64, phi: f64, q0: f64, u0: f64) -> (f64, f64) {
        let s1 = mueller::partial_polarizer(p, phi) * mueller::stokes_qu(1.0, q0, u0);
        (s1[1] / s1[0], s1[2] / s1[0])
    }

    #[test]
    fn exact_inverts_eq_instpol_to_machine_precision() {
        for &(p, phi, ps, chis) in &[
            (0.01, 0.3, 0.0645, 68.4f64.to_radians()),
            (0.3, 2.9, 0.5, 0.1),
            (1e-6, 1.0, 0.0174, (-53.8f64).to_radians()),
            (0.05, 0.0, 0.0, 0.0),
            (0.9, 1.2, 0.8, 2.0),
        ] {
            let (q0, u0) = (ps * (2.0 * chis).cos(), ps * (2.0 * chis).sin());
            let (q1, u1) = forward(p, phi, q0, u0);
            let (pe, phie) = solve_exact(q1, u1, q0, u0).unwrap();
            assert!((pe - p).abs() < 1e-12, "p {p}: {pe}");
            let dphi =
                (phie - phi + 0.5 * std::f64::consts::PI).rem_euclid(std::f64::consts::PI) - 0.5 * std::f64::consts::PI;
            assert!(dphi.abs() < 1e-9 / p.max(1e-3), "phi {phi}: {phie}");
        }
    }

    #[test]
    fn approx_is_the_weighted_mean_of_p1_and_p2() {
        // The paper's p_1 = dQ / cos 2phi, p_2 = dU / sin 2phi averaged with weights cos^2 and
        // sin^2 equals hypot(dQ, dU); checked where neither estimate blows up.
        let (q1, u1, q0, u0) = (0.013, -0.004, 0.002, 0.001);
        let (p, phi) = solve_approx(q1, u1, q0, u0);
        let (c, s) = ((2.0 * phi).cos(), (2.0 * phi).sin());
        let (p1, p2) = ((q1 - q0) / c, (u1 - u0) / s);
        let mean = (c * c * p1 + s * s * p2) / (c * c + s * s);
        assert!((mean - p).abs() < 1e-15 && (p1 - p2).abs() < 1e-15);
        // At cos 2phi = 0 (p_1 = 0/0) the stable form still holds.
        let (p, phi) = solve_approx(0.0, 0.01, 0.0, 0.0);
        assert!((p - 0.01).abs() < 1e-17 && (phi - std::f64::consts::FRAC_PI_4).abs() < 1e-15);
    }

    #[test]
    fn exact_and_approx_agree_for_small_p_and_part_for_large() {
        // eq:approx holds for p, P_sky << 1: the two agree to second order.
        let worst = |p: f64, ps: f64| {
            let mut dp: f64 = 0.0;
            let mut dphi: f64 = 0.0;
            for k in 0..36 {
                let phi = k as f64 * 5f64.to_radians();
                let (q0, u0) = (ps * 0.3f64.cos(), ps * 0.3f64.sin());
                let (q1, u1) = forward(p, phi, q0, u0);
                let (pe, _) = solve_exact(q1, u1, q0, u0).unwrap();
                let (pa, phia) = solve_approx(q1, u1, q0, u0);
                dp = dp.max(((pa - pe) / pe).abs());
                let d = (phia - phi + 0.5 * std::f64::consts::PI).rem_euclid(std::f64::consts::PI)
                    - 0.5 * std::f64::consts::PI;
                dphi = dphi.max(d.abs());
            }
            (dp, dphi.to_degrees())
        };
        // Paper's I band at the corner: p ~ 1.4%, P_sky 1.34%: within 0.1% relative, 0.5 deg.
        let (dp, dphi) = worst(0.014, 0.0134);
        assert!(dp < 1.5e-3 && dphi < 0.5, "{dp} {dphi}");
        // Tiny p and sky: p agrees to ~P^2; the angle offset is of order P_sky / 2 rad
        // whatever p is (0.03 deg for 0.1%).
        let (dp, dphi) = worst(1e-3, 1e-3);
        assert!(dp < 1e-5 && dphi < 0.035, "{dp} {dphi}");
        // They part at several percent: the B-band sky (6.45%) with p = 5% gives relative
        // differences of p of order p P_sky and angle offsets of order P_sky / 2 rad (degrees).
        let (dp, dphi) = worst(0.05, 0.0645);
        assert!(dp > 3e-3 && dphi > 1.0, "{dp} {dphi}");
        let (dp, dphi) = worst(0.2, 0.2);
        assert!(dp > 0.03 && dphi > 4.0, "{dp} {dphi}");
    }

    #[test]
    fn errors_propagate_as_identity_for_an_unpolarized_sky() {
        let sky = SkyPolarization { p: 0.0, chi: 0.0 };
        let s = solve_bin(1.0, 2.0, 0.01, 0.005, 1e-4, 2e-4, 0.0, &sky).unwrap();
        assert!((s.qu.var_q.sqrt() - 1e-4).abs() < 1e-9 && (s.qu.var_u.sqrt() - 2e-4).abs() < 1e-9);
        assert!((s.qu.q - 0.01).abs() < 1e-15 && (s.qu.u - 0.005).abs() < 1e-15);
        // sigma_p of eq:sigp-like propagation: (q^2 sq^2 + u^2 su^2) / p^2.
        let want = ((0.01f64 * 1e-4).powi(2) + (0.005f64 * 2e-4).powi(2)).sqrt() / 0.01f64.hypot(0.005);
        assert!((s.sigma_p - want).abs() < 1e-9, "{} {want}", s.sigma_p);
    }

    #[test]
    fn unphysical_input_has_no_solution() {
        assert!(solve_exact(1.2, 0.0, 0.0, 0.0).is_none());
        assert!(solve_exact(0.1, 0.0, 1.0, 0.0).is_none());
        assert!(SkyPolarization::from_percent_deg(-1.0, 0.0).is_err());
        assert!(SkyPolarization::from_percent_deg(1.74, f64::NAN).is_err());
        let s = SkyPolarization::from_percent_deg(1.74, -53.8).unwrap();
        assert!((s.chi.to_degrees() - 126.2).abs() < 1e-9);
    }
}
