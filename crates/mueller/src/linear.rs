//! The linear block of the pre-analyzer Mueller matrix: the 3 x 3 block (rows and columns
//! I, Q, U) that linear polarimetry sees, and its physical parameterization.
//!
//! A dual-beam polarimeter measures the normalized linear Stokes parameters at the half-wave
//! plate. Sky light is linearly polarized (`V = 0`) and the analyzer does not measure the `V`
//! that reaches the plate (to first order in the plate's retardance error), so of the
//! pre-analyzer matrix only the 3 x 3 block acting on `(I, Q, U)` matters. [`LinearBlock::forward`]
//! is the one forward model of the Mueller field: the measured `(q, u)` of a source of
//! normalized Stokes `(q_sky, u_sky)`; the simulator applies the same block to intensities with
//! [`LinearBlock::apply`].
//!
//! The physical form ([`Physical`]) is `B · M_I(p, phi)`: the paper's partial polarizer
//! `M_I(p, phi)` (`eq:instpol`: diattenuation, the whole of today's calibration) followed by a
//! `Q, U` block `B = (1 - depol) Rot(rotation) R_ret(delta, axis)`, with `R_ret` the linear
//! block of a linear retarder. The order does not matter to first order in the small effects;
//! it is fixed so that `delta = rotation = depol = 0` is exactly `M_I`.
//!
//! Linear polarimetry sees a retarder only through `1 - cos delta` (light along its axis passes
//! unchanged; the part at 45 degrees loses `1 - cos delta` of its linear polarization into `V`),
//! and cannot tell its fast from its slow axis: its natural linear parameters are the
//! *retardance vector* `g = (1 - cos delta) / 2 (cos 4 theta, sin 4 theta)`, with which
//! `R_ret = (1 - |g|) 1 + [[g1, g2], [g2, -g1]]`. A fit uses `g` (the measured q, u respond
//! linearly to it) and reports `delta = acos(1 - 2 |g|)` and `theta` modulo 90 degrees.

use crate::{analysis, Mueller};
use nalgebra::Matrix3;

/// The 3 x 3 block (I, Q, U) of a pre-analyzer Mueller matrix.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinearBlock(pub Matrix3<f64>);

impl LinearBlock {
    /// The identity (no instrumental effect).
    pub fn identity() -> Self {
        Self(Matrix3::identity())
    }

    /// The (I, Q, U) block of a 4 x 4 Mueller matrix.
    pub fn of_mueller(m: &Mueller) -> Self {
        Self(m.fixed_view::<3, 3>(0, 0).into_owned())
    }

    /// The 4 x 4 Mueller matrix of an element known only by its linear block: circular
    /// polarization arriving is not passed on and none is made (the `V` row and column are
    /// zero), which is what the block alone says about the linear part and no more.
    pub fn to_mueller(&self) -> Mueller {
        let mut m = Mueller::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&self.0);
        m
    }

    /// The block applied to a linear Stokes vector `(I, Q, U)` (intensities kept).
    #[inline]
    pub fn apply(&self, iqu: [f64; 3]) -> [f64; 3] {
        let m = &self.0;
        [
            m[(0, 0)] * iqu[0] + m[(0, 1)] * iqu[1] + m[(0, 2)] * iqu[2],
            m[(1, 0)] * iqu[0] + m[(1, 1)] * iqu[1] + m[(1, 2)] * iqu[2],
            m[(2, 0)] * iqu[0] + m[(2, 1)] * iqu[1] + m[(2, 2)] * iqu[2],
        ]
    }

    /// The forward model of the Mueller field: the normalized `(q, u)` measured for a source of
    /// normalized Stokes `(q_sky, u_sky)`, i.e. the normalized Stokes parameters of
    /// `M (1, q_sky, u_sky)`. `None` when no light gets through (`I' <= 0`).
    #[inline]
    pub fn forward(&self, q_sky: f64, u_sky: f64) -> Option<(f64, f64)> {
        let [i, q, u] = self.apply([1.0, q_sky, u_sky]);
        (i > 0.0 && i.is_finite()).then(|| (q / i, u / i))
    }

    /// The exact inverse of [`forward`](Self::forward): the source's `(q, u)` that the block
    /// turns into the measured `(q_meas, u_meas)`. `None` for a singular block (condition
    /// number above 1e12) or when the inverse has no positive intensity.
    pub fn invert(&self, q_meas: f64, u_meas: f64) -> Option<(f64, f64)> {
        let svd = self.0.svd(false, false);
        let (mx, mn) = (svd.singular_values.max(), svd.singular_values.min());
        if !(mn > 1e-12 * mx) {
            return None;
        }
        let inv = LinearBlock(self.0.try_inverse()?);
        inv.forward(q_meas, u_meas)
    }

    /// The block scaled to `m00 = 1` (the normalized q, u do not see the overall throughput).
    pub fn normalized(&self) -> Self {
        Self(self.0 / self.0[(0, 0)])
    }

    /// Stokes criterion on the linear subspace, a necessary condition for realizability: every
    /// fully linearly polarized input `(1, cos t, sin t)` must leave with `I' >= 0` and a
    /// degree of polarization `<= 1`. Returns the largest excess `sqrt(Q'^2 + U'^2) / I' - 1`
    /// over 720 input angles (`<= 0` for a realizable block; `inf` when some `I' <= 0`).
    pub fn max_polarization_excess(&self) -> f64 {
        let mut worst = f64::NEG_INFINITY;
        for k in 0..720 {
            let t = k as f64 * std::f64::consts::PI / 360.0;
            let [i, q, u] = self.apply([1.0, t.cos(), t.sin()]);
            if !(i > 0.0) {
                return f64::INFINITY;
            }
            worst = worst.max(crate::hypot(q, u) / i - 1.0);
        }
        worst
    }
}

/// The physical parameters of the linear block (see the module docs). Angles in radians.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Physical {
    /// Diattenuation `p` of the paper's `M_I(p, phi)` (fraction) and its angle `phi`.
    pub p: f64,
    pub phi: f64,
    /// Linear retardance `delta` (rad, `[0, pi]`) and its axis (rad, modulo pi/2).
    pub retardance: f64,
    pub retardance_axis: f64,
    /// Rotation of the polarization plane (rad): chi' = chi + rotation.
    pub rotation: f64,
    /// Depolarization fraction: the Q, U block is scaled by `1 - depolarization`.
    pub depolarization: f64,
}

/// The retardance vector `g` of a retarder (module docs).
pub fn retardance_vector(delta: f64, axis: f64) -> [f64; 2] {
    let e = 0.5 * (1.0 - delta.cos());
    let (s, c) = (4.0 * axis).sin_cos();
    [e * c, e * s]
}

/// `(delta, axis)` of a retardance vector `g` (inverse of [`retardance_vector`]); `delta` in
/// `[0, pi]` (`|g| > 1` is clamped to pi), axis in `[0, pi/2)`.
pub fn retardance_of_vector(g: [f64; 2]) -> (f64, f64) {
    let m = crate::hypot(g[0], g[1]);
    let delta = (1.0 - 2.0 * m).clamp(-1.0, 1.0).acos();
    let axis = (0.25 * g[1].atan2(g[0])).rem_euclid(0.5 * std::f64::consts::PI);
    (delta, axis)
}

/// The linear block of the physical form from the linear parameters of a fit:
/// `(q_d, u_d) = p (cos 2phi, sin 2phi)` of `M_I`, the retardance vector `g`, the rotation
/// (rad) and the depolarization fraction.
pub fn physical_block(qd: f64, ud: f64, g: [f64; 2], rotation: f64, depolarization: f64) -> LinearBlock {
    let p = crate::hypot(qd, ud);
    let (c2, s2) = if p > 0.0 { (qd / p, ud / p) } else { (1.0, 0.0) };
    // M_I(p, phi) restricted to (I, Q, U), with its 1 / (1 + p) normalization (eq:instpol).
    let k = 1.0 / (1.0 + p);
    #[rustfmt::skip]
    let mi = Matrix3::new(
        1.0,    p * c2,              p * s2,
        p * c2, 1.0 - p * s2 * s2,   p * c2 * s2,
        p * s2, p * c2 * s2,         1.0 - p * c2 * c2,
    ) * k;
    let gm = crate::hypot(g[0], g[1]);
    let (a, b, c, d) = (1.0 - gm + g[0], g[1], g[1], 1.0 - gm - g[0]);
    let (sr, cr) = (2.0 * rotation).sin_cos();
    let f = 1.0 - depolarization;
    // Rot(rotation) * R_ret, scaled by 1 - depolarization.
    let (b11, b12, b21, b22) =
        (f * (cr * a - sr * c), f * (cr * b - sr * d), f * (sr * a + cr * c), f * (sr * b + cr * d));
    #[rustfmt::skip]
    let bm = Matrix3::new(
        1.0, 0.0, 0.0,
        0.0, b11, b12,
        0.0, b21, b22,
    );
    LinearBlock(bm * mi)
}

impl Physical {
    /// The linear block of these parameters ([`physical_block`]).
    pub fn block(&self) -> LinearBlock {
        let (s, c) = (2.0 * self.phi).sin_cos();
        physical_block(
            self.p * c,
            self.p * s,
            retardance_vector(self.retardance, self.retardance_axis),
            self.rotation,
            self.depolarization,
        )
    }

    /// The full 4 x 4 Mueller matrix of the same elements (depolarizer x rotator x retarder x
    /// `M_I`), for the Cloude realizability test on the whole matrix.
    pub fn mueller(&self) -> Mueller {
        let mi = crate::partial_polarizer(self.p, self.phi);
        let ret = crate::retarder(self.retardance, self.retardance_axis);
        // A rotator of the polarization plane: the Stokes rotation R(-rotation) (chi grows).
        let rot = crate::rotation(-self.rotation);
        let f = 1.0 - self.depolarization;
        let dep = Mueller::from_diagonal(&nalgebra::Vector4::new(1.0, f, f, f));
        dep * rot * ret * mi
    }

    /// Whether the whole matrix is physically realizable (Cloude's coherency test,
    /// [`analysis::is_physical`]) and every parameter is in its range.
    pub fn is_realizable(&self, tol: f64) -> bool {
        (0.0..=1.0).contains(&self.p)
            && (0.0..=1.0).contains(&self.depolarization)
            && analysis::is_physical(&self.mueller(), tol)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// The physical block equals the (I, Q, U) block of the 4 x 4 product built from the
    /// crate's separate element matrices (retarder, rotation, partial polarizer).
    #[test]
    fn physical_block_is_the_block_of_the_element_product() {
        for &(p, phi, d, ax, rot, dep) in
            &[(0.0, 0.0, 0.0, 0.0, 0.0, 0.0), (0.03, 0.4, 0.35, 1.1, 0.02, 0.01), (0.2, 2.9, 2.5, 0.3, -0.4, 0.3)]
        {
            let ph = Physical { p, phi, retardance: d, retardance_axis: ax, rotation: rot, depolarization: dep };
            let want = LinearBlock::of_mueller(&ph.mueller());
            assert_relative_eq!(ph.block().0, want.0, epsilon = 1e-13);
            assert!(ph.is_realizable(1e-9));
        }
    }

    /// Pure retarder on linear light: light along the axis is untouched; light at 45 deg to it
    /// keeps `cos delta` of its polarization (the rest goes into V).
    #[test]
    fn retarder_keeps_axis_light_and_shrinks_45_deg_light_by_cos_delta() {
        let (d, ax) = (0.4f64, 0.3f64);
        let b = Physical { retardance: d, retardance_axis: ax, ..Default::default() }.block();
        let (q, u) = b.forward((2.0 * ax).cos(), (2.0 * ax).sin()).unwrap();
        assert_relative_eq!(q, (2.0 * ax).cos(), epsilon = 1e-14);
        assert_relative_eq!(u, (2.0 * ax).sin(), epsilon = 1e-14);
        let t = ax + std::f64::consts::FRAC_PI_4;
        let (q, u) = b.forward(0.05 * (2.0 * t).cos(), 0.05 * (2.0 * t).sin()).unwrap();
        assert_relative_eq!(crate::hypot(q, u), 0.05 * d.cos(), epsilon = 1e-14);
        let (d2, ax2) = retardance_of_vector(retardance_vector(d, ax));
        assert_relative_eq!(d2, d, epsilon = 1e-12);
        assert_relative_eq!(ax2, ax, epsilon = 1e-12);
    }

    /// Forward then inverse returns the source; an ideal polarizer (singular) is refused.
    #[test]
    fn invert_undoes_forward_and_refuses_a_singular_block() {
        let b =
            Physical { p: 0.01, phi: 0.7, retardance: 0.5, retardance_axis: 0.2, rotation: 0.03, depolarization: 0.02 }
                .block();
        let (q, u) = b.forward(0.0645, -0.02).unwrap();
        let (q0, u0) = b.invert(q, u).unwrap();
        assert_relative_eq!(q0, 0.0645, epsilon = 1e-14);
        assert_relative_eq!(u0, -0.02, epsilon = 1e-14);
        let pol = LinearBlock::of_mueller(&crate::polarizer(0.3));
        assert!(pol.invert(0.1, 0.0).is_none());
    }

    /// The Stokes criterion: realizable blocks have no excess, an over-polarizing block has.
    #[test]
    fn polarization_excess_flags_an_over_polarizing_block() {
        assert!(LinearBlock::identity().max_polarization_excess().abs() < 1e-14);
        let b = Physical { p: 0.05, phi: 0.2, retardance: 1.0, retardance_axis: 0.1, ..Default::default() }.block();
        assert!(b.max_polarization_excess() <= 1e-12);
        let mut m = Matrix3::identity();
        m[(1, 1)] = 1.02;
        assert_relative_eq!(LinearBlock(m).max_polarization_excess(), 0.02, epsilon = 1e-9);
    }
}
