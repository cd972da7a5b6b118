//! The one normalized flux difference and the one Stokes solver of the workspace.

use crate::Error;
use mueller::Qu;
use std::f64::consts::PI;

/// Normalized flux difference `F = (f_O - f_E) / (f_O + f_E)` (`eq:F`).
///
/// ```
/// // eq:F: 300 e- in the ordinary beam, 100 e- in the extraordinary: F = 200 / 400.
/// assert_eq!(stokes::normalized_difference(300.0, 100.0), 0.5);
/// ```
#[inline]
pub fn normalized_difference(f_o: f64, f_e: f64) -> f64 {
    let t = f_o + f_e;
    if t.is_finite() {
        (f_o - f_e) / t
    } else {
        // Both near f64::MAX: the sum overflowed, the halves do not (F is scale-free).
        (0.5 * f_o - 0.5 * f_e) / (0.5 * f_o + 0.5 * f_e)
    }
}

/// Error of `F` (`eq:F`) propagated exactly from independent per-beam errors:
/// `sigma_F = 2 sqrt(f_E^2 sigma_O^2 + f_O^2 sigma_E^2) / (f_O + f_E)^2`.
/// For Poisson counts (`sigma^2 = f`) this is `sqrt((1 - F^2) / (f_O + f_E))`.
///
/// ```
/// // Poisson counts of N = 5000 e- in each beam: sigma_F = 1 / sqrt(2N) = 0.01.
/// let s = stokes::sigma_normalized_difference(5000.0, 5000.0, 5000f64.sqrt(), 5000f64.sqrt());
/// assert!((s - 0.01).abs() < 1e-15);
/// ```
#[inline]
pub fn sigma_normalized_difference(f_o: f64, f_e: f64, sigma_o: f64, sigma_e: f64) -> f64 {
    let mut tot = f_o + f_e;
    let (mut f_o, mut f_e, mut sigma_o, mut sigma_e) = (f_o, f_e, sigma_o, sigma_e);
    if !tot.is_finite() {
        // Both fluxes near f64::MAX: halve everything (the result is scale-free).
        (f_o, f_e, sigma_o, sigma_e) = (0.5 * f_o, 0.5 * f_e, 0.5 * sigma_o, 0.5 * sigma_e);
        tot = f_o + f_e;
    }
    // Scale-free factors (f_E/t)(sigma_O/t): f_E sigma_O and t^2 over- or underflow for fluxes
    // near 1e+-160 (1e-200 fluxes gave 0/0 = NaN), their ratios do not.
    2.0 * mueller::hypot((f_e / tot) * (sigma_o / tot), (f_o / tot) * (sigma_e / tot))
}

/// Variance of `F` (`eq:F`) from independent per-beam variances: `sigma_F^2` of
/// [`sigma_normalized_difference`] without its square roots, for callers that add variances
/// (frame reduction, per pixel and angle). Evaluated as
/// `4 ((f_E/t)^2 var_O + (f_O/t)^2 var_E) / t^2` with `t = f_O + f_E`, so that no fourth power
/// of `t` over- or underflows; where this form would (`|t|` beyond about `1e+-150`, or a
/// variance near the f64 limit), the square of the scaled `sigma_normalized_difference`.
/// For Poisson counts (`var = f`) this is `(1 - F^2) / (f_O + f_E)`.
#[inline]
pub fn variance_normalized_difference(f_o: f64, f_e: f64, var_o: f64, var_e: f64) -> f64 {
    let v = variance_normalized_difference_fast(f_o, f_e, var_o, var_e);
    if fast_variance_in_range(v) {
        v
    } else {
        sigma_normalized_difference(f_o, f_e, var_o.sqrt(), var_e.sqrt()).powi(2)
    }
}

/// The fast form of [`variance_normalized_difference`] without its range fallback: equal to it
/// wherever [`fast_variance_in_range`] holds for the result (elsewhere it may have over- or
/// underflowed). For vectorized loops, which treat such values as masked (frame reduction:
/// a pixel whose `f_O + f_E` is beyond about `1e+-140` e- has no usable flux anyway).
#[inline(always)]
pub fn variance_normalized_difference_fast(f_o: f64, f_e: f64, var_o: f64, var_e: f64) -> f64 {
    let inv = 1.0 / (f_o + f_e);
    let (a, b) = (f_e * inv, f_o * inv);
    4.0 * (a * a * var_o + b * b * var_e) * (inv * inv)
}

/// Whether a value of [`variance_normalized_difference_fast`] is exact to rounding: finite
/// and clear of the underflow zone.
#[inline(always)]
pub fn fast_variance_in_range(v: f64) -> bool {
    v.is_finite() & (v > 1e-290)
}

/// Polarization degree and angle from normalized Stokes parameters (`eq:poldeg`,
/// `eq:polang`): `P = hypot(q, u)`, `chi = atan2(u, q) / 2` folded into [0, pi)
/// ([`Qu::p_chi`] of an exact value).
///
/// ```
/// // A 3-4-5 triangle: q = 0.03, u = 0.04 is P = 5 % at chi = atan(4/3)/2 = 26.565 deg; u < 0
/// // folds chi into [0, 180): -26.565 deg is 153.435 deg.
/// let (p, chi) = stokes::polarization(0.03, 0.04);
/// assert!((p - 0.05).abs() < 1e-16 && (chi.to_degrees() - 26.565051177077990).abs() < 1e-12);
/// let (_, chi) = stokes::polarization(0.03, -0.04);
/// assert!((chi.to_degrees() - 153.43494882292201).abs() < 1e-12);
/// ```
#[inline]
pub fn polarization(q: f64, u: f64) -> (f64, f64) {
    Qu::new(q, u, 0.0, 0.0, 0.0).p_chi()
}

/// Linear solver of `eq:system`, `F_i = Q cos 4theta_i + U sin 4theta_i`, for a fixed set of
/// HWP angles.
///
/// Built once per angle set, it holds the weights `c_q,i`, `c_u,i` with
/// `Q = sum c_q,i F_i`, `U = sum c_u,i F_i`: the unweighted least-squares solution, which for
/// the optimal set `theta_i = i pi/8` with `N` a multiple of 4 is exactly the Fourier sums of
/// `eq:Q` and `eq:U` (`2/N cos(pi i / 2)` and `2/N sin(pi i / 2)`). Solving is then two dot
/// products: no allocation, cheap enough for Monte Carlo inner loops.
#[derive(Debug, Clone, PartialEq)]
pub struct StokesSolver {
    theta: Vec<f64>,
    c4: Vec<f64>,
    s4: Vec<f64>,
    cq: Vec<f64>,
    cu: Vec<f64>,
    /// `(A^T A)^-1` for the design `A = [cos 4theta, sin 4theta]`.
    inv: [[f64; 2]; 2],
    optimal: bool,
}

impl StokesSolver {
    /// Prepare the solver for HWP angles `theta` (rad). Errors: fewer than 2 angles,
    /// the same plate position twice (angles equal modulo 2 pi), angles that cannot
    /// separate Q from U. Redundant positions (theta and theta + pi/4, + pi/2, ...) are
    /// welcome: they are what cancels the Wollaston and flat-field terms.
    ///
    /// ```
    /// use stokes::StokesSolver;
    /// // eq:Q, eq:U on the optimal four angles give back q, u from F_i = q cos 4t + u sin 4t.
    /// let theta = mueller::optimal_angles(4);
    /// let f: Vec<f64> = theta.iter().map(|t| 0.012 * (4.0 * t).cos() - 0.005 * (4.0 * t).sin()).collect();
    /// let (q, u) = StokesSolver::new(&theta).unwrap().solve(&f);
    /// assert!((q - 0.012).abs() < 1e-16 && (u + 0.005).abs() < 1e-16);
    /// // The same plate position twice cannot be solved.
    /// assert!(StokesSolver::new(&[0.0, 2.0 * std::f64::consts::PI]).is_err());
    /// ```
    pub fn new(theta: &[f64]) -> Result<Self, Error> {
        Self::build(theta, None)
    }

    /// Prepare the solver for exposures during which the plate turned uniformly: exposure `i`
    /// from `theta_i - sweep_i / 2` to `theta_i + sweep_i / 2` (rad; `theta` the middle
    /// angles). Each exposure's `F_i` is then `e_i (Q cos 4theta_i + U sin 4theta_i)` with the
    /// modulation efficiency `e_i = sin(2 sweep_i) / (2 sweep_i)`
    /// ([`mueller::hwp_sweep_efficiency`]: the mean of `cos 4theta`, `sin 4theta` over the
    /// motion), so the design matrix of `eq:system` is `[e cos 4theta, e sin 4theta]` and its
    /// least-squares solution replaces `eq:Q`, `eq:U`. With equal sweeps on the optimal set
    /// that is the Fourier sums divided by `e`. All sweeps zero is [`Self::new`], bit for bit.
    ///
    /// Errors as [`Self::new`], and [`Error::NoModulation`] when the design is singular because
    /// the plate turned through a whole modulation period (90 deg: `e = 0`) in the exposures
    /// that would have constrained `Q` or `U`.
    ///
    /// ```
    /// use stokes::StokesSolver;
    /// // 16 exposures of 22.5 deg each (two turns of 8): F_i carries 0.9003 of the modulation,
    /// // and the swept design gives q, u back; the fixed plate's solution is 0.9003 of them.
    /// let sweep = 22.5f64.to_radians();
    /// let theta: Vec<f64> = (0..16).map(|k| (11.25 + 22.5 * k as f64).to_radians()).collect();
    /// let e = (2.0 * sweep).sin() / (2.0 * sweep);
    /// let f: Vec<f64> = theta.iter().map(|t| e * (0.01 * (4.0 * t).cos() + 0.02 * (4.0 * t).sin())).collect();
    /// let (q, u) = StokesSolver::with_sweeps(&theta, &[sweep; 16]).unwrap().solve(&f);
    /// assert!((q - 0.01).abs() < 1e-15 && (u - 0.02).abs() < 1e-15);
    /// let (q, _) = StokesSolver::new(&theta).unwrap().solve(&f);
    /// assert!((q / 0.01 - 0.9003163161571061).abs() < 1e-12);
    /// // A plate that turns 90 deg in every exposure modulates nothing.
    /// assert!(StokesSolver::with_sweeps(&theta, &[90f64.to_radians(); 16]).is_err());
    /// ```
    pub fn with_sweeps(theta: &[f64], sweep: &[f64]) -> Result<Self, Error> {
        if sweep.len() != theta.len() {
            return Err(Error::LengthMismatch { what: "HWP sweep", got: sweep.len(), expected: theta.len() });
        }
        for (i, &d) in sweep.iter().enumerate() {
            if !d.is_finite() {
                return Err(Error::NonFinite { what: "HWP sweep", index: i, value: d });
            }
        }
        if sweep.iter().all(|&d| d == 0.0) {
            return Self::build(theta, None);
        }
        Self::build(theta, Some(sweep))
    }

    fn build(theta: &[f64], sweep: Option<&[f64]>) -> Result<Self, Error> {
        let n = theta.len();
        if n < 2 {
            return Err(Error::TooFewAngles(n));
        }
        for (i, &t) in theta.iter().enumerate() {
            if !t.is_finite() {
                return Err(Error::NonFinite { what: "HWP angle", index: i, value: t });
            }
        }
        // The same plate position twice (modulo a full turn) is a bookkeeping error. Sorted
        // positions on the circle: a duplicate is a pair of neighbours (or the last and the
        // first, across 2 pi), so the check is n log n, not the n^2 of all pairs (1e5 rows).
        let red: Vec<f64> = theta.iter().map(|t| t.rem_euclid(2.0 * PI)).collect();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&i, &j| red[i].total_cmp(&red[j]).then(i.cmp(&j)));
        let mut worst: Option<(usize, usize)> = None;
        for k in 0..n {
            let (i, j) = (order[k], order[(k + 1) % n]);
            let d = (red[i] - red[j]).abs();
            if d.min(2.0 * PI - d) < 1e-9 {
                // Report the pair that comes first in the input, as the rows were read.
                let pair = (i.min(j), i.max(j));
                if worst.is_none_or(|w| (pair.1, pair.0) < (w.1, w.0)) {
                    worst = Some(pair);
                }
            }
        }
        if let Some((i, j)) = worst {
            return Err(Error::DuplicateAngle { deg: theta[j].to_degrees(), first: i, second: j });
        }
        let mut c4: Vec<f64> = theta.iter().map(|t| (4.0 * t).cos()).collect();
        let mut s4: Vec<f64> = theta.iter().map(|t| (4.0 * t).sin()).collect();
        if let Some(sweep) = sweep {
            for i in 0..n {
                let e = mueller::hwp_sweep_efficiency(sweep[i]);
                c4[i] *= e;
                s4[i] *= e;
            }
        }
        let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
        for i in 0..n {
            a += c4[i] * c4[i];
            b += c4[i] * s4[i];
            c += s4[i] * s4[i];
        }
        let det = a * c - b * b;
        if sweep.is_some() {
            // The fixed plate's design at the same angles: if it is regular, a singular swept
            // one lost its modulation to the motion.
            let (mut a0, mut b0, mut c0) = (0.0, 0.0, 0.0);
            for t in theta {
                let (s, c) = (4.0 * t).sin_cos();
                a0 += c * c;
                b0 += c * s;
                c0 += s * s;
            }
            let fixed_regular = a0 * c0 - b0 * b0 > 1e-12 * (a0 + c0) * (a0 + c0);
            if fixed_regular && !(det > 1e-12 * (a0 + c0) * (a0 + c0)) {
                let sweep = sweep.unwrap_or_default();
                let (i, d) = sweep
                    .iter()
                    .enumerate()
                    .min_by(|x, y| {
                        mueller::hwp_sweep_efficiency(*x.1).abs().total_cmp(&mueller::hwp_sweep_efficiency(*y.1).abs())
                    })
                    .map(|(i, d)| (i, *d))
                    .unwrap_or((0, 0.0));
                return Err(Error::NoModulation { index: i, sweep_deg: d.to_degrees() });
            }
        }
        if det <= 1e-12 * (a + c) * (a + c) {
            return Err(Error::Degenerate);
        }
        let inv = [[c / det, -b / det], [-b / det, a / det]];
        let cq: Vec<f64> = (0..n).map(|i| inv[0][0] * c4[i] + inv[0][1] * s4[i]).collect();
        let cu: Vec<f64> = (0..n).map(|i| inv[1][0] * c4[i] + inv[1][1] * s4[i]).collect();
        // The Fourier sums are the solution only with equal efficiencies (a common sweep).
        let common_sweep = sweep.is_none_or(|d| d.iter().all(|&x| x == d[0]));
        let optimal = common_sweep
            && n.is_multiple_of(4)
            && theta.iter().enumerate().all(|(i, &t)| ((t - i as f64 * PI / 8.0).abs()) < 1e-9);
        Ok(Self { theta: theta.to_vec(), c4, s4, cq, cu, inv, optimal })
    }

    /// Number of HWP angles.
    pub fn n(&self) -> usize {
        self.theta.len()
    }

    /// The HWP angles (rad).
    pub fn angles(&self) -> &[f64] {
        &self.theta
    }

    /// `cos 4theta_i` and `sin 4theta_i`, each times the exposure's modulation efficiency
    /// when the plate turned during it ([`Self::with_sweeps`]).
    pub fn modulation(&self) -> (&[f64], &[f64]) {
        (&self.c4, &self.s4)
    }

    /// The weights `c_q,i`, `c_u,i` of the linear solution.
    pub fn weights(&self) -> (&[f64], &[f64]) {
        (&self.cq, &self.cu)
    }

    /// True for the optimal set `theta_i = i pi/8`, `N` a multiple of 4, where the solution is
    /// the Fourier sums `eq:Q`, `eq:U`.
    pub fn is_optimal(&self) -> bool {
        self.optimal
    }

    /// `(Q/I, U/I)` from the `F_i` (equal weights). `f.len()` must equal [`Self::n`]; the hot
    /// path does not check beyond a debug assertion.
    #[inline]
    pub fn solve(&self, f: &[f64]) -> (f64, f64) {
        debug_assert_eq!(f.len(), self.cq.len());
        let mut q = 0.0;
        let mut u = 0.0;
        for i in 0..f.len() {
            q += self.cq[i] * f[i];
            u += self.cu[i] * f[i];
        }
        (q, u)
    }

    /// Solve with the covariance propagated from per-angle errors `sigma_f` of the `F_i`
    /// (equal-weight estimator, exact propagation). With all `sigma_f` equal to
    /// `1/SNR` on the optimal set this gives `var(Q) = var(U) = 2 / (N SNR^2)`, i.e. `eq:sigp`.
    ///
    /// ```
    /// use stokes::StokesSolver;
    /// // eq:sigp: with sigma_F = 1/SNR at each of N = 16 optimal angles, sigma_Q = sigma_U =
    /// // sqrt(2/N) / SNR; at SNR = 1000 that is 3.536e-4.
    /// let theta = mueller::optimal_angles(16);
    /// let qu = StokesSolver::new(&theta).unwrap().solve_with_errors(&[0.0; 16], &[1e-3; 16]).unwrap();
    /// assert!((qu.sigma_q() - (2.0f64 / 16.0).sqrt() * 1e-3).abs() < 1e-15);
    /// assert!((qu.sigma_u() - qu.sigma_q()).abs() < 1e-18 && qu.cov_qu.abs() < 1e-20);
    /// ```
    pub fn solve_with_errors(&self, f: &[f64], sigma_f: &[f64]) -> Result<Qu, Error> {
        self.check_len("F", f.len())?;
        self.check_len("sigma_F", sigma_f.len())?;
        let (q, u) = self.solve(f);
        let (mut vq, mut vu, mut cqu) = (0.0, 0.0, 0.0);
        for i in 0..f.len() {
            let v = sigma_f[i] * sigma_f[i];
            vq += self.cq[i] * self.cq[i] * v;
            vu += self.cu[i] * self.cu[i] * v;
            cqu += self.cq[i] * self.cu[i] * v;
        }
        Ok(Qu { q, u, var_q: vq, var_u: vu, cov_qu: cqu })
    }

    /// Weighted least squares with weights `1 / sigma_f^2`: the minimum-variance solution when
    /// the `F_i` have unequal errors (e.g. uneven exposures).
    pub fn solve_weighted(&self, f: &[f64], sigma_f: &[f64]) -> Result<Qu, Error> {
        self.check_len("F", f.len())?;
        self.check_len("sigma_F", sigma_f.len())?;
        // Modified Gram-Schmidt on the weighted design sqrt(w) [cos 4theta, sin 4theta | F]:
        // the normal equations would square the condition, which extreme weights (F ~ +-1,
        // sigma_F ~ 0) make large; here the second pivot is a sum of squared residuals, not
        // the cancelling c - b^2 / a.
        // Weights relative to the smallest error, (s_min/s)^2 in (0, 1]: 1/s^2 itself overflows
        // for s below 1e-154. The variances are scaled back by s_min^2 at the end.
        let mut s_min = f64::INFINITY;
        for (i, &s) in sigma_f.iter().enumerate() {
            if !(s.is_finite() && s > 0.0) {
                return Err(Error::NonFinite { what: "sigma_F", index: i, value: s });
            }
            s_min = s_min.min(s);
        }
        let (mut a, mut b, mut rq) = (0.0, 0.0, 0.0);
        for i in 0..f.len() {
            let r = s_min / sigma_f[i];
            let w = r * r;
            a += w * self.c4[i] * self.c4[i];
            b += w * self.c4[i] * self.s4[i];
            rq += w * self.c4[i] * f[i];
        }
        if !(a > 0.0) {
            return Err(Error::Degenerate);
        }
        let (mu, nu) = (b / a, rq / a);
        let (mut r22, mut y2) = (0.0, 0.0);
        for i in 0..f.len() {
            let r = s_min / sigma_f[i];
            let w = r * r;
            let s_res = self.s4[i] - mu * self.c4[i];
            r22 += w * s_res * s_res;
            y2 += w * s_res * (f[i] - nu * self.c4[i]);
        }
        if !(r22 > 0.0) {
            return Err(Error::Degenerate);
        }
        let u = y2 / r22;
        let v = s_min * s_min;
        Ok(Qu { q: nu - mu * u, u, var_q: (1.0 / a + mu * mu / r22) * v, var_u: v / r22, cov_qu: -mu / r22 * v })
    }

    /// `(A^T A)^-1`: the covariance of `(Q, U)` in units of a common variance of the `F_i`.
    pub fn unit_covariance(&self) -> [[f64; 2]; 2] {
        self.inv
    }

    fn check_len(&self, what: &'static str, got: usize) -> Result<(), Error> {
        if got != self.n() {
            return Err(Error::LengthMismatch { what, got, expected: self.n() });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// The variance form is the square of `sigma_normalized_difference` (a few ulp), on both
    /// sides of its fallback, and Poisson counts give `(1 - F^2) / (f_O + f_E)` (`eq:F`).
    #[test]
    fn variance_is_sigma_squared() {
        for &(fo, fe, vo, ve) in &[
            (1000.0, 800.0, 1000.0, 800.0),
            (3.0, 1e-3, 3.0 + 25.0, 25.0),
            (1e-160, 2e-160, 1e-160, 2e-160),
            (1e170, 3e170, 1e170, 3e170),
            (5.0, 5.0, 1e305, 1e300),
        ] {
            let v = variance_normalized_difference(fo, fe, vo, ve);
            let s = sigma_normalized_difference(fo, fe, f64::sqrt(vo), f64::sqrt(ve));
            assert_relative_eq!(v, s * s, max_relative = 1e-14);
        }
        let (fo, fe) = (12345.0, 9876.0);
        let f = normalized_difference(fo, fe);
        assert_relative_eq!(
            variance_normalized_difference(fo, fe, fo, fe),
            (1.0 - f * f) / (fo + fe),
            max_relative = 1e-14
        );
    }

    fn optimal(n: usize) -> Vec<f64> {
        (0..n).map(|i| i as f64 * PI / 8.0).collect()
    }

    /// eq:Q / eq:U: for the optimal set the least-squares weights are the Fourier sums.
    #[test]
    fn eq_q_eq_u_are_least_squares_for_optimal_set() {
        for n in [4, 8, 12, 16] {
            let s = StokesSolver::new(&optimal(n)).unwrap();
            assert!(s.is_optimal());
            let (cq, cu) = s.weights();
            for i in 0..n {
                let a = PI / 2.0 * i as f64;
                assert_relative_eq!(cq[i], 2.0 / n as f64 * a.cos(), epsilon = 1e-14);
                assert_relative_eq!(cu[i], 2.0 / n as f64 * a.sin(), epsilon = 1e-14);
            }
        }
    }

    #[test]
    fn any_angle_set_recovers_noiseless_qu() {
        let th: [f64; 5] = [0.1, 0.5, 0.77, 1.3, 2.9];
        let (q0, u0) = (0.013, -0.042);
        let f: Vec<f64> = th.iter().map(|t| q0 * (4.0 * t).cos() + u0 * (4.0 * t).sin()).collect();
        let (q, u) = StokesSolver::new(&th).unwrap().solve(&f);
        assert_relative_eq!(q, q0, epsilon = 1e-15);
        assert_relative_eq!(u, u0, epsilon = 1e-15);
    }

    #[test]
    fn eq_sigp_from_propagation() {
        let snr = 250.0;
        for n in [4, 8, 16] {
            let s = StokesSolver::new(&optimal(n)).unwrap();
            let e = s.solve_with_errors(&vec![0.0; n], &vec![1.0 / snr; n]).unwrap();
            let sigp = 1.0 / ((n as f64 / 2.0).sqrt() * snr);
            assert_relative_eq!(e.var_q.sqrt(), sigp, max_relative = 1e-12);
            assert_relative_eq!(e.var_u.sqrt(), sigp, max_relative = 1e-12);
        }
    }

    /// Extreme weights (F ~ -1 with a Poisson sigma_F 270x smaller than the others, from the
    /// forward model at P = 1, kappa = 0.92 on an uneven 3-angle set, found by the stability
    /// suite): the weighted solution of noiseless data must stay at rounding. The normal
    /// equations lost three digits here (1.7e-13); Gram-Schmidt keeps them.
    #[test]
    fn weighted_solution_stays_at_rounding_with_extreme_weights() {
        let theta = [4.524500752026731, 0.0, 1.9221326456935723];
        let (p, chi, k) = (1.0f64, 2.2716649610191713f64, 0.9193479355902536f64);
        let train = mueller::DualBeam { wollaston: mueller::Wollaston::with_t(0.5 * (1.0 + k)), ..Default::default() };
        let fl = train.fluxes(&mueller::stokes_p_chi(1.0, p, chi), &theta);
        let (mut f, mut sig) = (vec![], vec![]);
        for b in &fl {
            let (fo, fe) = (b.f_o / (1.0 + k), b.f_e / (1.0 - k));
            f.push(normalized_difference(fo, fe));
            sig.push(sigma_normalized_difference(fo, fe, fo.sqrt(), fe.sqrt()));
        }
        let e = StokesSolver::new(&theta).unwrap().solve_weighted(&f, &sig).unwrap();
        let (q0, u0) = (p * (2.0 * chi).cos(), p * (2.0 * chi).sin());
        assert!((e.q - q0).abs() < 4.0 * f64::EPSILON && (e.u - u0).abs() < 4.0 * f64::EPSILON, "{e:?} vs {q0} {u0}");
    }

    #[test]
    fn rejects_bad_sets() {
        assert_eq!(StokesSolver::new(&[0.0]).unwrap_err(), Error::TooFewAngles(1));
        assert!(matches!(StokesSolver::new(&[0.0, 2.0 * PI]), Err(Error::DuplicateAngle { .. })));
        assert!(matches!(StokesSolver::new(&[0.0, PI / 2.0]), Err(Error::Degenerate)));
        assert!(matches!(StokesSolver::new(&[0.0, PI / 4.0]), Err(Error::Degenerate)));
    }

    /// A plate turning through 22.5 deg per exposure, 16 exposures over two turns of 8
    /// positions: F_i from the fixed plate's fluxes averaged over 4000 sub-steps of each
    /// exposure's motion (midpoint rule, written here) solve to the star's q, u with the swept
    /// design (to the sub-steps' error), while the fixed plate's design gives them times
    /// sin(2d)/(2d) = 0.9003; with a sweep of 90 deg in every exposure nothing is modulated and
    /// the solver says so, where the fixed design at the same angles is regular.
    #[test]
    fn swept_design_recovers_qu_and_the_fixed_one_is_low_by_sinc() {
        let (q0, u0) = (0.021, -0.013);
        let d = 22.5f64.to_radians();
        let theta: Vec<f64> = (0..16).map(|k| (11.25 + 22.5 * k as f64).to_radians()).collect();
        let train = mueller::DualBeam::ideal();
        let s = mueller::stokes_qu(1.0, q0, u0);
        let f: Vec<f64> = theta
            .iter()
            .map(|&t| {
                let n = 4000;
                let (mut fo, mut fe) = (0.0, 0.0);
                for k in 0..n {
                    let a = t - 0.5 * d + (k as f64 + 0.5) * d / n as f64;
                    let b = train.fluxes(&s, &[a])[0];
                    fo += b.f_o;
                    fe += b.f_e;
                }
                normalized_difference(fo, fe)
            })
            .collect();
        let (q, u) = StokesSolver::with_sweeps(&theta, &[d; 16]).unwrap().solve(&f);
        assert_relative_eq!(q, q0, epsilon = 1e-8);
        assert_relative_eq!(u, u0, epsilon = 1e-8);
        let (qf, uf) = StokesSolver::new(&theta).unwrap().solve(&f);
        let e = (2.0 * d).sin() / (2.0 * d);
        assert_relative_eq!(qf, e * q0, epsilon = 1e-8);
        assert_relative_eq!(uf, e * u0, epsilon = 1e-8);
        assert_relative_eq!(e, 0.9003163161571061, epsilon = 1e-15);
        // No motion is the fixed solver, bit for bit.
        assert_eq!(StokesSolver::with_sweeps(&theta, &[0.0; 16]).unwrap(), StokesSolver::new(&theta).unwrap());
        let quarter = 90f64.to_radians();
        assert!(StokesSolver::new(&theta).is_ok());
        match StokesSolver::with_sweeps(&theta, &[quarter; 16]) {
            Err(Error::NoModulation { sweep_deg, .. }) => assert!((sweep_deg - 90.0).abs() < 1e-9),
            other => panic!("{other:?}"),
        }
        assert!(matches!(StokesSolver::with_sweeps(&theta, &[d; 3]), Err(Error::LengthMismatch { .. })));
        assert!(matches!(StokesSolver::with_sweeps(&theta, &[f64::NAN; 16]), Err(Error::NonFinite { .. })));
    }

    #[test]
    fn chi_at_the_wrap() {
        let (_, chi) = polarization(1.0, -1e-300);
        assert!((0.0..PI).contains(&chi));
        let (p, chi) = polarization(0.0, 0.0);
        assert_eq!(p, 0.0);
        assert!(chi.is_finite());
    }

    /// The n log n duplicate check finds a duplicate exactly when the all-pairs rule (angles equal
    /// modulo 2 pi to 1e-9 rad) does, and names the same rows when there is one pair; checked
    /// against a brute-force loop on random sets with planted duplicates, also across 2 pi.
    #[test]
    fn duplicate_check_matches_all_pairs() {
        let brute = |t: &[f64]| -> Option<(usize, usize)> {
            for i in 0..t.len() {
                for j in i + 1..t.len() {
                    let d = (t[i].rem_euclid(2.0 * PI) - t[j].rem_euclid(2.0 * PI)).abs();
                    if d.min(2.0 * PI - d) < 1e-9 {
                        return Some((i, j));
                    }
                }
            }
            None
        };
        let mut x = 12345u64;
        let mut rnd = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64
        };
        for trial in 0..400 {
            let n = 2 + (rnd() * 30.0) as usize;
            let mut t: Vec<f64> = (0..n).map(|_| (rnd() - 0.5) * 40.0).collect();
            if trial % 2 == 0 {
                let (i, j) = ((rnd() * n as f64) as usize % n, (rnd() * n as f64) as usize % n);
                if i != j {
                    // A full turn (or two) apart, or one rounding step apart across 0.
                    t[j] = t[i] + 2.0 * PI * ((rnd() * 3.0) as i32 - 1) as f64;
                }
            }
            if trial % 7 == 0 {
                t[0] = 2.0 * PI - 1e-12;
                t[n - 1] = 1e-12;
            }
            let got = match StokesSolver::new(&t) {
                Err(Error::DuplicateAngle { first, second, .. }) => Some((first, second)),
                _ => None,
            };
            let want = brute(&t);
            assert_eq!(got.is_some(), want.is_some(), "{t:?}");
            if let (Some(g), Some(w)) = (got, want) {
                // Both name a duplicated pair; with one planted pair it is the same pair.
                let d = |p: (usize, usize)| {
                    let e = (t[p.0].rem_euclid(2.0 * PI) - t[p.1].rem_euclid(2.0 * PI)).abs();
                    e.min(2.0 * PI - e)
                };
                assert!(d(g) < 1e-9 && g.0 < g.1, "{t:?}: {g:?} vs {w:?}");
            }
        }
    }
}
