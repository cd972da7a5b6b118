//! One binned measurement of the instrumental polarization: the rows of the calibration
//! file's binary table and the input of every fit.

use serde::{Deserialize, Serialize};

/// The instrumental polarization measured in one bin of the field.
///
/// `q = p cos 2phi`, `u = p sin 2phi` are the normalized Stokes parameters of the partial
/// polarizer `M_I(p, phi)` (`eq:instpol`) found in this bin (fractions); positions are the
/// bin's centre in arcmin from the detector centre.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Bin {
    pub x: f64,
    pub y: f64,
    pub q: f64,
    pub u: f64,
    pub sigma_q: f64,
    pub sigma_u: f64,
    /// `p`, `phi` (rad) of the paper's approximate solution (`eq:approx`), NaN when the bin
    /// did not come from a sky-field solution (e.g. an imported map).
    pub p_approx: f64,
    pub phi_approx: f64,
    /// Whether the last fit used this bin (inside the region, not excluded, finite).
    pub used: bool,
}

impl Bin {
    /// A bin with no approximate solution attached.
    pub fn new(x: f64, y: f64, q: f64, u: f64, sigma_q: f64, sigma_u: f64) -> Self {
        Bin { x, y, q, u, sigma_q, sigma_u, p_approx: f64::NAN, phi_approx: f64::NAN, used: true }
    }

    /// Whether every number a fit needs is finite and the errors are positive.
    pub fn is_valid(&self) -> bool {
        [self.x, self.y, self.q, self.u].iter().all(|v| v.is_finite())
            && self.sigma_q.is_finite()
            && self.sigma_u.is_finite()
            && self.sigma_q > 0.0
            && self.sigma_u > 0.0
    }

    /// `(p, phi)` of the bin, phi in [0, pi).
    pub fn p_phi(&self) -> (f64, f64) {
        stokes::polarization(self.q, self.u)
    }
}
