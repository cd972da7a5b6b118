//! The interface every instrumental-polarization field model offers.

/// The instrumental polarization at one field position: the normalized Stokes parameters
/// `q = p cos 2phi`, `u = p sin 2phi` of the partial polarizer `M_I(p, phi)` (`eq:instpol`)
/// with the model's own uncertainty (covariance of q, u from the fit or the interpolation).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct InstPol {
    pub q: f64,
    pub u: f64,
    pub var_q: f64,
    pub var_u: f64,
    pub cov_qu: f64,
}

impl InstPol {
    /// `(p, phi)` with phi in [0, pi).
    pub fn p_phi(&self) -> (f64, f64) {
        stokes::polarization(self.q, self.u)
    }
}

/// A model of the instrumental polarization over the field. Positions are in arcminutes from
/// the detector centre (DESIGN.md conventions).
pub trait FieldModel: Send + Sync {
    /// The instrumental polarization at `(x, y)` arcmin.
    fn eval(&self, x_arcmin: f64, y_arcmin: f64) -> InstPol;
    /// Whether `(x, y)` lies inside the field where the model was calibrated.
    fn contains(&self, x_arcmin: f64, y_arcmin: f64) -> bool;
}
