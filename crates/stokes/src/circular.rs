//! Circular polarization with a quarter-wave plate: `V/I` of one source from the normalized
//! flux differences `F_i` (`eq:F`) at `N` plate angles, with its error.
//!
//! # The modulation
//!
//! A quarter-wave plate (retardance `pi/2`, `mueller::Hwp::quarter_wave`) with its fast axis
//! at `theta` before an analyser whose ordinary beam transmits light polarized along 0 (the
//! Wollaston of `eq:WP`) gives
//!
//! `F(theta) = q cos^2 2theta + u sin 2theta cos 2theta + v sin 2theta`,
//!
//! the `Q` row of the retarder's Mueller matrix (`Q' = c^2 Q + c s U + s V`, `c = cos 2theta`,
//! `s = sin 2theta`). The sign of `v` is `+` in the workspace's IAU convention (`V > 0` for
//! counter-clockwise rotation of the electric vector as seen by the observer;
//! `mueller::retarder` turns +45 deg linear light into `V > 0` with its fast axis at 0), so
//! `F(+45 deg) = v`, `F(-45 deg) = -v` for any linear polarization.
//! `crates/mueller/tests/it/quarter_wave.rs` checks this form against a Jones calculation.
//!
//! # The estimator
//!
//! Write the model as `F_i = a_0 + (q/2) cos 4theta_i + (u/2) sin 4theta_i + v sin 2theta_i`,
//! with `cos^2 2theta = (1 + cos 4theta)/2`, and `a_0` the offset that the beams' throughput
//! ratio (the Wollaston's `kappa`, a flat-field or gain ratio between the beams) adds to every
//! `F_i` (`F = (kappa + x) / (1 + kappa x)`: `a_0 = kappa` and `v` scaled by `1 - kappa^2`, a
//! second-order effect). `V` is the coefficient of `sin 2theta` once the other columns are
//! projected out: with `r` the part of the column `sin 2theta_i` orthogonal to the columns
//! `1`, `cos 4theta_i`, `sin 4theta_i`, `v = sum r_i F_i / sum r_i^2`. It is unbiased whatever
//! `a_0`, `q` and `u` are, needs no fit of them (the set may not determine them), and is the
//! equal-weight estimator, as the Fourier sums `eq:Q`, `eq:U` are for the linear case:
//!
//! - `theta = -45, +45 deg`: `v = (F(+45) - F(-45)) / 2`: the offset cancels, and so do the
//!   linear terms, exactly at the nominal angles and to first order in a zero-angle error
//!   `e` (`F(+-45 + e) = q sin^2 2e - u sin 2e cos 2e +- v cos 2e`: the difference is
//!   `2 v cos 2e`, biased by `-2 e^2 v` only);
//! - `theta = -45, 45, 135, 225 deg`: the mean of `+-F_i`; the redundant positions (the same
//!   axis on the plate's other side, 180 deg on) also cancel a plate defect that repeats
//!   once per turn (dust, the `k = 1` harmonic of `sec:HWP`).
//!
//! A set whose `sin 2theta` column lies in the span of the others (one position, or angles
//! all with `sin 2theta = 0`) does not determine `V` and is refused, naming the angles.
//!
//! # Errors
//!
//! As for the linear case: each `sigma_F,i` propagated exactly from the per-beam errors
//! (photon and read noise; [`crate::sigma_normalized_difference`]), and
//! `var(v) = sum (r_i / sum r_j^2)^2 sigma_F,i^2`; with equal `sigma_F = 1/SNR` at `N`
//! positions where `sin 2theta = +-1` that is `sigma_v = 1 / (sqrt(N) SNR)`, the analogue of
//! `eq:sigp` (`sigma_Q = sqrt(2/N) / SNR`: a half-wave plate spreads its `N` exposures over
//! two parameters).
//!
//! # The zero angle
//!
//! The plate's fast axis sits at the commanded angle plus its zero angle (an instrument's
//! `qwp_zero_angle_deg`); [`CircularSolver::with_zero_angle`] demodulates at the axis angles.

use crate::solver::{normalized_difference, sigma_normalized_difference};
use crate::Error;

/// A measured or expected `V/I` with its variance: the one circular-polarization value.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Circular {
    /// `V/I` (fraction, IAU sign).
    pub v: f64,
    /// Variance of `v`.
    pub var_v: f64,
}

impl Circular {
    /// An exact value (no error).
    pub fn exact(v: f64) -> Self {
        Self { v, var_v: 0.0 }
    }

    /// The error of `v`.
    pub fn sigma_v(&self) -> f64 {
        self.var_v.max(0.0).sqrt()
    }
}

/// The demodulation of `V/I` for a fixed set of quarter-wave-plate angles: the weights
/// `w_i` with `v = sum w_i F_i` (see the module documentation), built once per set.
#[derive(Debug, Clone, PartialEq)]
pub struct CircularSolver {
    /// The plate's axis angles (rad): commanded angle plus the zero angle.
    axis: Vec<f64>,
    w: Vec<f64>,
}

impl CircularSolver {
    /// Prepare the solver for plate angles `theta` (rad, the fast axis's). Errors: fewer than
    /// 2 angles, a non-finite angle, the same plate position twice (angles equal modulo
    /// 360 deg), and sets that do not determine `V` ([`Error::CircularUndetermined`], naming
    /// the angles).
    ///
    /// ```
    /// use stokes::circular::CircularSolver;
    /// // +-45 deg: v = (F(45) - F(-45)) / 2, whatever q, u and the beams' offset.
    /// let theta = [-45f64.to_radians(), 45f64.to_radians()];
    /// let s = CircularSolver::new(&theta).unwrap();
    /// let (q, u, v, a0) = (0.03, -0.02, 0.01, 0.004);
    /// let f: Vec<f64> = theta
    ///     .iter()
    ///     .map(|t: &f64| a0 + q * (2.0 * t).cos().powi(2) + u * (2.0 * t).sin() * (2.0 * t).cos() + v * (2.0 * t).sin())
    ///     .collect();
    /// assert!((s.solve(&f) - v).abs() < 1e-16);
    /// // One position, or 0 and 90 deg (sin 2theta = 0 at both), cannot give V.
    /// assert!(CircularSolver::new(&[45f64.to_radians()]).is_err());
    /// assert!(CircularSolver::new(&[0.0, 90f64.to_radians()]).is_err());
    /// ```
    pub fn new(theta: &[f64]) -> Result<Self, Error> {
        Self::with_zero_angle(theta, 0.0)
    }

    /// [`Self::new`] for commanded angles `theta` (rad) of a plate whose fast axis sits at
    /// `theta + zero_angle` (rad): the demodulation at the axis angles.
    pub fn with_zero_angle(theta: &[f64], zero_angle: f64) -> Result<Self, Error> {
        let n = theta.len();
        if n < 2 {
            return Err(Error::TooFewAngles(n));
        }
        if !zero_angle.is_finite() {
            return Err(Error::NonFinite { what: "QWP zero angle", index: 0, value: zero_angle });
        }
        for (i, &t) in theta.iter().enumerate() {
            if !t.is_finite() {
                return Err(Error::NonFinite { what: "QWP angle", index: i, value: t });
            }
        }
        let two_pi = 2.0 * std::f64::consts::PI;
        for j in 1..n {
            for i in 0..j {
                let d = (theta[i] - theta[j]).rem_euclid(two_pi);
                if d.min(two_pi - d) < 1e-9 {
                    return Err(Error::DuplicateAngle { deg: theta[j].to_degrees(), first: i, second: j });
                }
            }
        }
        let axis: Vec<f64> = theta.iter().map(|t| t + zero_angle).collect();
        // Orthonormal basis of the nuisance columns (offset, cos 4theta, sin 4theta) by
        // modified Gram-Schmidt; a column that the set leaves dependent (at +-45 deg cos 4theta
        // is the offset's column, sin 4theta vanishes) is dropped.
        let cols: [Vec<f64>; 3] = [
            vec![1.0; n],
            axis.iter().map(|t| (4.0 * t).cos()).collect(),
            axis.iter().map(|t| (4.0 * t).sin()).collect(),
        ];
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        let mut basis: Vec<Vec<f64>> = Vec::new();
        // Entries are at most 1 in size: a column whose remainder is below 1e-9 of a column of
        // ones is rounding (sin 4theta at +-45 deg is 1e-16, not 0) and is dropped.
        let tiny = 1e-9 * n as f64;
        for c in cols {
            let mut c = c;
            for b in &basis {
                let k = dot(&c, b);
                c.iter_mut().zip(b).for_each(|(x, y)| *x -= k * y);
            }
            let norm = dot(&c, &c);
            if norm > tiny {
                let s = norm.sqrt();
                c.iter_mut().for_each(|x| *x /= s);
                basis.push(c);
            }
        }
        let s2: Vec<f64> = axis.iter().map(|t| (2.0 * t).sin()).collect();
        let mut r = s2.clone();
        for b in &basis {
            let k = dot(&r, b);
            r.iter_mut().zip(b).for_each(|(x, y)| *x -= k * y);
        }
        let rr = dot(&r, &r);
        if !(rr > tiny) {
            let deg: Vec<String> = theta.iter().map(|t| format!("{}", t.to_degrees())).collect();
            return Err(Error::CircularUndetermined { angles_deg: format!("[{}]", deg.join(", ")) });
        }
        let w = r.iter().map(|x| x / rr).collect();
        Ok(Self { axis, w })
    }

    /// Number of plate angles.
    pub fn n(&self) -> usize {
        self.w.len()
    }

    /// The plate's axis angles (rad) the solver demodulates at.
    pub fn axis_angles(&self) -> &[f64] {
        &self.axis
    }

    /// The weights `w_i` of `v = sum w_i F_i`.
    pub fn weights(&self) -> &[f64] {
        &self.w
    }

    /// `V/I` from the `F_i`. `f.len()` must equal [`Self::n`] (a debug assertion).
    pub fn solve(&self, f: &[f64]) -> f64 {
        debug_assert_eq!(f.len(), self.w.len());
        self.w.iter().zip(f).map(|(w, f)| w * f).sum()
    }

    /// `V/I` with its variance propagated from the errors `sigma_f` of the `F_i`.
    ///
    /// ```
    /// use stokes::circular::CircularSolver;
    /// // Four positions with sigma_F = 1/SNR each: sigma_v = 1 / (sqrt(4) SNR) = 5e-4 at SNR 1000.
    /// let theta: Vec<f64> = [-45.0f64, 45.0, 135.0, 225.0].iter().map(|d| d.to_radians()).collect();
    /// let c = CircularSolver::new(&theta).unwrap().solve_with_errors(&[-0.01, 0.01, -0.01, 0.01], &[1e-3; 4]).unwrap();
    /// assert!((c.v - 0.01).abs() < 1e-16 && (c.sigma_v() - 5e-4).abs() < 1e-16);
    /// ```
    pub fn solve_with_errors(&self, f: &[f64], sigma_f: &[f64]) -> Result<Circular, Error> {
        for (what, len) in [("F", f.len()), ("sigma_F", sigma_f.len())] {
            if len != self.n() {
                return Err(Error::LengthMismatch { what, got: len, expected: self.n() });
            }
        }
        let var_v = self.w.iter().zip(sigma_f).map(|(w, s)| w * w * s * s).sum();
        Ok(Circular { v: self.solve(f), var_v })
    }

    /// `V/I` of one source from its beams' fluxes and their errors at each plate angle (photon
    /// and read noise, as photometry measures them): `F_i` and `sigma_F,i` by the crate's one
    /// `eq:F` ([`normalized_difference`], [`sigma_normalized_difference`]). Errors name the
    /// plate position whose flux is not finite or whose `f_O + f_E` is not positive.
    pub fn solve_fluxes(&self, f_o: &[f64], f_e: &[f64], sigma_o: &[f64], sigma_e: &[f64]) -> Result<Circular, Error> {
        for (what, v) in [("f_o", f_o), ("f_e", f_e), ("sigma_o", sigma_o), ("sigma_e", sigma_e)] {
            if v.len() != self.n() {
                return Err(Error::LengthMismatch { what, got: v.len(), expected: self.n() });
            }
            if let Some((index, &value)) = v.iter().enumerate().find(|(_, x)| !x.is_finite()) {
                return Err(Error::NonFinite { what, index, value });
            }
        }
        let mut f = Vec::with_capacity(self.n());
        let mut sigma_f = Vec::with_capacity(self.n());
        for i in 0..self.n() {
            let total = f_o[i] + f_e[i];
            if !(total > 0.0) {
                return Err(Error::NonPositiveFlux { index: i, total });
            }
            f.push(normalized_difference(f_o[i], f_e[i]));
            sigma_f.push(sigma_normalized_difference(f_o[i], f_e[i], sigma_o[i], sigma_e[i]));
        }
        self.solve_with_errors(&f, &sigma_f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn deg(a: &[f64]) -> Vec<f64> {
        a.iter().map(|d| d.to_radians()).collect()
    }

    /// The model F = a0 + q cos^2 2t + u sin 2t cos 2t + v sin 2t, written here.
    fn model(t: f64, a0: f64, q: f64, u: f64, v: f64) -> f64 {
        let (s, c) = (2.0 * t).sin_cos();
        a0 + q * c * c + u * s * c + v * s
    }

    /// Exact recovery of v on the 2- and 4-position sets and on 16 positions 22.5 deg apart,
    /// whatever the offset and the linear polarization; the weights of the +-45 pair are the
    /// closed form +-1/2, of the 4-position set +-1/4.
    #[test]
    fn v_exact_and_free_of_the_linear_terms() {
        let sets = [
            deg(&[-45.0, 45.0]),
            deg(&[-45.0, 45.0, 135.0, 225.0]),
            (0..16).map(|k| k as f64 * std::f64::consts::FRAC_PI_8).collect(),
        ];
        for th in &sets {
            let s = CircularSolver::new(th).unwrap();
            for &(a0, q, u, v) in &[(0.0, 0.0, 0.0, 0.02), (0.01, 0.05, -0.03, -0.01), (-0.02, -0.04, 0.06, 0.0)] {
                let f: Vec<f64> = th.iter().map(|&t| model(t, a0, q, u, v)).collect();
                assert!((s.solve(&f) - v).abs() < 1e-15, "{th:?}: {} vs {v}", s.solve(&f));
            }
        }
        let w2 = CircularSolver::new(&sets[0]).unwrap();
        assert!((w2.weights()[0] + 0.5).abs() < 1e-15 && (w2.weights()[1] - 0.5).abs() < 1e-15);
        let w4 = CircularSolver::new(&sets[1]).unwrap();
        for (w, want) in w4.weights().iter().zip([-0.25, 0.25, -0.25, 0.25]) {
            assert!((w - want).abs() < 1e-15);
        }
    }

    /// A zero-angle error e: the +-45 pair gives v cos 2e (second order, however large q, u),
    /// while one position alone (F(45 + e), v taken as F) is off by -u sin 2e cos 2e (first
    /// order); demodulating at the known axis angles removes even the second-order term.
    #[test]
    fn zero_angle_error_is_second_order_for_the_pair() {
        let (q, u, v) = (0.03, 0.04, 0.01);
        let e = 3f64.to_radians();
        let th = deg(&[-45.0, 45.0]);
        let f: Vec<f64> = th.iter().map(|&t| model(t + e, 0.0, q, u, v)).collect();
        let ignoring = CircularSolver::new(&th).unwrap().solve(&f);
        assert!((ignoring - v * (2.0 * e).cos()).abs() < 1e-15);
        assert!((ignoring - v).abs() < 2.0 * e * e * v * 1.01);
        let single = f[1];
        assert!(
            (single - v * (2.0 * e).cos() - (q * (2.0 * e).sin().powi(2) - u * (2.0 * e).sin() * (2.0 * e).cos()))
                .abs()
                < 1e-15
        );
        assert!((single - v).abs() > 0.5 * 2.0 * e * u);
        let known = CircularSolver::with_zero_angle(&th, e).unwrap().solve(&f);
        assert!((known - v).abs() < 1e-15);
    }

    /// Errors: exact propagation against the closed form sum w_i^2 sigma_i^2 with unequal
    /// errors; refusals name what is wrong.
    #[test]
    fn errors_and_refusals() {
        let th = deg(&[-45.0, 45.0, 135.0, 225.0]);
        let s = CircularSolver::new(&th).unwrap();
        let c = s.solve_with_errors(&[0.0; 4], &[1e-3, 2e-3, 3e-3, 4e-3]).unwrap();
        assert!((c.var_v - (1e-6 + 4e-6 + 9e-6 + 16e-6) / 16.0).abs() < 1e-20);
        // Poisson counts of N e- in each beam: sigma_F = 1/sqrt(2N), sigma_v = sigma_F / 2.
        let n = 5000.0;
        let c = s.solve_fluxes(&[n; 4], &[n; 4], &[n.sqrt(); 4], &[n.sqrt(); 4]).unwrap();
        assert!((c.sigma_v() - 0.5 / (2.0 * n).sqrt()).abs() < 1e-15 && c.v == 0.0);
        let e = CircularSolver::new(&deg(&[0.0, 90.0, 180.0])).unwrap_err();
        assert!(e.to_string().contains("[0, 90, 180]"), "{e}");
        assert!(matches!(CircularSolver::new(&deg(&[45.0, 405.0])), Err(Error::DuplicateAngle { .. })));
        assert!(matches!(CircularSolver::new(&[0.3]), Err(Error::TooFewAngles(1))));
        assert!(matches!(
            s.solve_fluxes(&[1.0, 1.0, -5.0, 1.0], &[1.0; 4], &[1.0; 4], &[1.0; 4]),
            Err(Error::NonPositiveFlux { index: 2, .. })
        ));
        assert!(s.solve_with_errors(&[0.0; 3], &[1.0; 4]).is_err());
    }
}
