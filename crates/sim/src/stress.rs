//! A stressed collimator lens as an effect a scene can call for (`[effects.stressed_lens]`):
//! stress birefringence whose retardance grows as the square of the distance from
//! a stress centre, `delta(r) = delta_edge (r / R)^2`, with the fast axis radial about that
//! centre (a lens squeezed by its mount) or tangential (a lens under hoop tension), turned by
//! `axis_offset_deg`. A centre away from the optical axis makes the field asymmetric.
//!
//! It acts on linear polarization only through `1 - cos delta` (see `mueller::linear`): on an
//! unpolarized sky it does nothing, on the paper's 6.45 % B-band sky a `delta_edge` of about
//! 18 degrees gives about 0.3 % at the field edge. The block is applied after the diattenuation
//! field of `[effects.instpol]`, as in the physical form of `mueller::linear`.

use mueller::linear::LinearBlock;
use serde::{Deserialize, Serialize};

/// `[effects.stressed_lens]` of a scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StressedLensSpec {
    /// Retardance (deg) at `radius_arcmin` from the stress centre.
    pub retardance_edge_deg: f64,
    /// Radius (arcmin) at which the retardance is `retardance_edge_deg`.
    pub radius_arcmin: f64,
    /// Stress centre (arcmin, field coordinates).
    #[serde(default)]
    pub centre_arcmin: [f64; 2],
    /// Fast axis tangential instead of radial.
    #[serde(default)]
    pub tangential: bool,
    /// Added to the axis (deg).
    #[serde(default)]
    pub axis_offset_deg: f64,
    /// The lens before the instrumental field (`[effects.instpol]`) instead of after it: light
    /// meets the lens first.
    #[serde(default)]
    pub before_instpol: bool,
}

impl StressedLensSpec {
    /// A clear error naming the key when the values are not usable.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.radius_arcmin > 0.0 && self.radius_arcmin.is_finite()) {
            return Err(format!("effects.stressed_lens.radius_arcmin = {} must be positive", self.radius_arcmin));
        }
        if !self.retardance_edge_deg.is_finite() || !self.axis_offset_deg.is_finite() {
            return Err("effects.stressed_lens: retardance_edge_deg and axis_offset_deg must be finite".into());
        }
        if !self.centre_arcmin.iter().all(|v| v.is_finite()) {
            return Err("effects.stressed_lens.centre_arcmin must be finite".into());
        }
        Ok(())
    }

    /// The lens as an element of the chain ([`field::StressedLens`]): angles in radians, a
    /// tangential axis as an offset of `pi / 2`.
    pub fn element(&self) -> field::StressedLens {
        let tangential = if self.tangential { std::f64::consts::FRAC_PI_2 } else { 0.0 };
        field::StressedLens {
            retardance_edge: self.retardance_edge_deg.to_radians(),
            radius_arcmin: self.radius_arcmin,
            centre_arcmin: self.centre_arcmin,
            axis_offset: self.axis_offset_deg.to_radians() + tangential,
        }
    }

    /// Retardance (rad) and fast-axis angle (rad) at `(x, y)` arcmin.
    pub fn retardance_at(&self, x: f64, y: f64) -> (f64, f64) {
        self.element().retardance_at(x, y)
    }

    /// The linear block of the lens at `(x, y)` arcmin.
    pub fn block_at(&self, x: f64, y: f64) -> LinearBlock {
        field::FieldModel::block_at(&self.element(), x, y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On the paper's B sky (6.45 %, chi 68.4 deg) an 18 deg edge retardance shifts the measured
    /// polarization by 0.3 % or so at the edge, nothing on the axis, and nothing for an
    /// unpolarized sky; checked against the crate's separate 4 x 4 retarder matrix.
    #[test]
    fn b_sky_asymmetry_is_a_few_tenths_of_a_percent() {
        let s = StressedLensSpec {
            retardance_edge_deg: 18.0,
            radius_arcmin: 3.4,
            centre_arcmin: [0.0, 0.0],
            tangential: false,
            axis_offset_deg: 0.0,
            before_instpol: false,
        };
        let chi = 68.4f64.to_radians();
        let (q0, u0) = (0.0645 * (2.0 * chi).cos(), 0.0645 * (2.0 * chi).sin());
        let (q, u) = s.block_at(0.0, 0.0).forward(q0, u0).unwrap();
        assert!((q - q0).abs() < 1e-15 && (u - u0).abs() < 1e-15);
        let mut worst: f64 = 0.0;
        for k in 0..72 {
            let a = k as f64 * 5f64.to_radians();
            let (x, y) = (3.4 * a.cos(), 3.4 * a.sin());
            let (q, u) = s.block_at(x, y).forward(q0, u0).unwrap();
            let m = mueller::retarder(18f64.to_radians(), a) * mueller::stokes_qu(1.0, q0, u0);
            assert!((q - m[1] / m[0]).abs() < 1e-14 && (u - m[2] / m[0]).abs() < 1e-14);
            worst = worst.max(mueller::hypot(q - q0, u - u0));
            assert_eq!(s.block_at(x, y).forward(0.0, 0.0), Some((0.0, 0.0)));
        }
        assert!(worst > 0.002 && worst < 0.0045, "largest shift {worst}");
    }
}
