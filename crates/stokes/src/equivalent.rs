//! The linear block a half-wave-plate defect is equivalent to after the demodulation (what
//! `fit::mueller_field::explain` compares a fitted Mueller field with).
//!
//! A defect of the modulator (a tilted, wedged or polarizing plate) is not a pre-analyzer
//! element: it changes each `F_i` (`eq:F`), and the Stokes solver turns the changed `F_i` into
//! a measured `(q, u)`. For the linear polarimetry of a weakly polarized sky that map from
//! the sky's `(q, u)` to the measured one is affine, `(q, u) -> a + B (q, u)`, i.e. a linear
//! block `[[1, 0, 0], [a, B]]` that `mueller::linear::LinearBlock::forward` applies like any
//! pre-analyzer block. Terms of the defect that repeat at `2 theta` or `6 theta` vanish in the
//! demodulation for angle sets sampling the whole turn and leak for others (e.g. the four
//! angles 0 ... 67.5 deg): this function finds out by running the one solver.

use crate::StokesSolver;
use mueller::linear::LinearBlock;
use mueller::{Mueller, Stokes};

/// The equivalent linear block of a plate whose Mueller matrix at commanded angle `theta` is
/// `hwp(theta)`, followed by an ideal Wollaston (`F = Q / I` of the light leaving the plate),
/// demodulated by `solver`: offset from an unpolarized sky, columns by central differences
/// over sky polarization `+-h` (`h = 0.05`, where the map's curvature is `O(defect * h)`).
/// `None` when no light leaves the plate at some angle.
pub fn equivalent_block(solver: &StokesSolver, hwp: impl Fn(f64) -> Mueller) -> Option<LinearBlock> {
    let mats: Vec<Mueller> = solver.angles().iter().map(|&t| hwp(t)).collect();
    let mut f = vec![0.0; mats.len()];
    let mut meas = |q: f64, u: f64| -> Option<(f64, f64)> {
        let s = Stokes::new(1.0, q, u, 0.0);
        for (fk, m) in f.iter_mut().zip(&mats) {
            let o = m * s;
            if !(o[0] > 0.0) {
                return None;
            }
            *fk = o[1] / o[0];
        }
        Some(solver.solve(&f))
    };
    let h = 0.05;
    let a = meas(0.0, 0.0)?;
    let (qp, qm) = (meas(h, 0.0)?, meas(-h, 0.0)?);
    let (up, um) = (meas(0.0, h)?, meas(0.0, -h)?);
    let mut b = LinearBlock::identity();
    let m = &mut b.0;
    (m[(1, 0)], m[(1, 1)], m[(1, 2)]) = (a.0, (qp.0 - qm.0) / (2.0 * h), (up.0 - um.0) / (2.0 * h));
    (m[(2, 0)], m[(2, 1)], m[(2, 2)]) = (a.1, (qp.1 - qm.1) / (2.0 * h), (up.1 - um.1) / (2.0 * h));
    Some(b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn full_turn() -> StokesSolver {
        StokesSolver::new(&(0..16).map(|k| k as f64 * PI / 8.0).collect::<Vec<_>>()).unwrap()
    }

    /// An ideal plate is the identity; a plate whose axis sits at `theta + c/2` rotates the
    /// measured chi by `-c`, i.e. `(q, u)` by `-2c` (the chromatic zero angle,
    /// `mueller::Hwp::chi_offset`).
    #[test]
    fn ideal_plate_is_identity_and_axis_offset_is_a_rotation() {
        let s = full_turn();
        let b = equivalent_block(&s, |t| mueller::retarder(PI, t)).unwrap();
        assert!((b.0 - LinearBlock::identity().0).abs().max() < 1e-12);
        let c = 0.1f64;
        let b = equivalent_block(&s, |t| mueller::retarder(PI, t + 0.5 * c)).unwrap();
        let (q, u) = b.forward(0.05, 0.0).unwrap();
        assert!((q - 0.05 * (2.0 * c).cos()).abs() < 1e-12 && (u + 0.05 * (2.0 * c).sin()).abs() < 1e-12, "{q} {u}");
    }

    /// A retardance error eps leaves `cos^2(eps / 2)` of the polarization (the `(1 - cos
    /// delta) / 2` part of the plate's modulation) and no offset.
    #[test]
    fn retardance_error_scales_by_cos_squared_half() {
        let eps = 0.3f64;
        let b = equivalent_block(&full_turn(), |t| mueller::retarder(PI + eps, t)).unwrap();
        let k = (0.5 * eps).cos().powi(2);
        assert!((b.0[(1, 1)] - k).abs() < 1e-12 && (b.0[(2, 2)] - k).abs() < 1e-12);
        assert!(b.0[(1, 0)].abs() < 1e-15 && b.0[(2, 1)].abs() < 1e-12);
    }
}
