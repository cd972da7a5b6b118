//! A stressed lens as an element of the field chain: stress birefringence whose retardance
//! grows as the square of the distance from a stress centre, `delta(r) = delta_edge (r / R)^2`,
//! its fast axis radial about that centre turned by an offset (`pi / 2`: tangential), the
//! physics of `mueller::causes::stressed_lens`. The simulator's `[effects.stressed_lens]`
//! renders it and a calibration file stores it (`docs/calibration-file.md`, "Several field
//! elements"), so that a lens measured on its own is corrected with the rest of the chain.

use crate::{FieldModel, InstPol};
use mueller::linear::{physical_block, retardance_vector, LinearBlock};

/// A stressed lens (module docs); angles in radians, distances in arcmin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StressedLens {
    /// Retardance (rad) at `radius_arcmin` from the stress centre.
    pub retardance_edge: f64,
    /// Radius (arcmin) at which the retardance is `retardance_edge`; > 0.
    pub radius_arcmin: f64,
    /// Stress centre (arcmin, field coordinates).
    pub centre_arcmin: [f64; 2],
    /// Added to the radial fast axis (rad; `pi / 2` for a tangential axis).
    pub axis_offset: f64,
}

impl StressedLens {
    /// Retardance (rad) and fast-axis angle (rad) at `(x, y)` arcmin.
    pub fn retardance_at(&self, x: f64, y: f64) -> (f64, f64) {
        mueller::causes::stressed_lens(
            x,
            y,
            self.retardance_edge,
            self.radius_arcmin,
            self.centre_arcmin,
            self.axis_offset,
        )
    }
}

/// Its own block; its `eval` is the polarization it gives unpolarized light (none).
impl FieldModel for StressedLens {
    fn eval(&self, x: f64, y: f64) -> InstPol {
        let o = FieldModel::block_at(self, x, y).apply([1.0, 0.0, 0.0]);
        InstPol { q: o[1] / o[0], u: o[2] / o[0], ..Default::default() }
    }
    fn contains(&self, _x: f64, _y: f64) -> bool {
        true
    }
    fn block_at(&self, x: f64, y: f64) -> LinearBlock {
        let (delta, axis) = self.retardance_at(x, y);
        physical_block(0.0, 0.0, retardance_vector(delta, axis), 0.0, 0.0)
    }
    /// The whole retarder, so that circular polarization made before the lens (by the
    /// telescope's M3) is turned back into linear polarization as it is in the glass.
    fn mueller_at(&self, x: f64, y: f64) -> mueller::Mueller {
        let (delta, axis) = self.retardance_at(x, y);
        mueller::retarder(delta, axis)
    }
    fn describe(&self) -> String {
        "a stressed lens".into()
    }
}
