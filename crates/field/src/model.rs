//! The interface every instrumental-polarization field model offers.

/// The instrumental polarization at one field position: the normalized Stokes parameters
/// `q = p cos 2phi`, `u = p sin 2phi` of the partial polarizer `M_I(p, phi)` (`eq:instpol`)
/// with the model's own uncertainty (covariance of q, u from the fit or the interpolation).
/// It is the one `(q, u)` value of the workspace, [`mueller::Qu`]: `p_chi()` gives `(p, phi)`.
pub type InstPol = mueller::Qu;

/// A model of the instrumental polarization over the field: a value that says what `M_I`
/// is at a position. Positions are in arcminutes about the field origin of
/// [`FieldCoords`](crate::FieldCoords) (the detector centre unless stated; `docs/architecture.md`,
/// Conventions).
///
/// The simulator puts any model into frames (`sim::Plan::build_with_field`), the fitter fits
/// and stores models (`fit`), the correction inverts them (`fit::correction::correct`): none of them asks
/// which model it has. A new model (elliptical paraboloid, a telescope term that depends on the
/// parallactic angle, a full Mueller field) implements this trait; only `eval` and `contains`
/// are required.
pub trait FieldModel: Send + Sync {
    /// The instrumental polarization at `(x, y)` arcmin. Outside the model's field the value
    /// may be NaN (a gridded map) or an extrapolation (a polynomial): ask [`contains`](Self::contains).
    fn eval(&self, x_arcmin: f64, y_arcmin: f64) -> InstPol;

    /// Whether `(x, y)` lies inside the field where the model was calibrated.
    fn contains(&self, x_arcmin: f64, y_arcmin: f64) -> bool;

    /// `(p, phi)` of `M_I(p, phi)` at `(x, y)` arcmin (`eq:instpol`), phi in radians. The
    /// default takes them from [`eval`](Self::eval); a model whose natural parameters are `p`
    /// and `phi` (a radial pattern) returns them directly, without the round trip through
    /// `(q, u)`.
    fn p_phi(&self, x_arcmin: f64, y_arcmin: f64) -> (f64, f64) {
        self.eval(x_arcmin, y_arcmin).p_chi()
    }

    /// The model's free parameters, in the order of [`covariance`](Self::covariance) and
    /// [`jacobian`](Self::jacobian); empty for a model that has none (a gridded map).
    fn params(&self) -> Vec<f64> {
        Vec::new()
    }

    /// Covariance of [`params`](Self::params), row-major `n x n`; `None` when unknown.
    fn covariance(&self) -> Option<Vec<f64>> {
        None
    }

    /// `(dq/dparams, du/dparams)` at `(x, y)` arcmin; `None` for a model without parameters.
    /// The variance of `(q, u)` from the parameters is `J C J^T` with `C` the covariance.
    fn jacobian(&self, _x_arcmin: f64, _y_arcmin: f64) -> Option<(Vec<f64>, Vec<f64>)> {
        None
    }

    /// The element's Mueller matrix at `(x, y)` arcmin: what it does to the light there,
    /// circular polarization included (the telescope's M3 turns linear into circular
    /// polarization, and a retarder after it turns some back). The default is the partial
    /// polarizer `M_I(p, phi)` of `eq:instpol` from [`p_phi`](Self::p_phi) (its `V` row
    /// included, [`mueller::partial_polarizer`]), and the identity where the model gives no
    /// polarization or no finite value. An element that is not a partial polarizer (a
    /// stressed lens, a tilted plate, a Mueller field) returns its own matrix, and overrides
    /// [`block_at`](Self::block_at) with the same linear part when it computes that more
    /// directly.
    fn mueller_at(&self, x_arcmin: f64, y_arcmin: f64) -> mueller::Mueller {
        let (p, phi) = self.p_phi(x_arcmin, y_arcmin);
        if p != 0.0 && p.is_finite() && phi.is_finite() {
            mueller::partial_polarizer(p, phi)
        } else {
            mueller::Mueller::identity()
        }
    }

    /// The element's linear Mueller block (the `(I, Q, U)` part of
    /// [`mueller_at`](Self::mueller_at)) at `(x, y)` arcmin: all a chain needs where the light
    /// reaching the element carries no circular polarization.
    fn block_at(&self, x_arcmin: f64, y_arcmin: f64) -> mueller::linear::LinearBlock {
        mueller::linear::LinearBlock::of_mueller(&self.mueller_at(x_arcmin, y_arcmin))
    }

    /// One line saying what the model is (for `--explain` and provenance).
    fn describe(&self) -> String {
        "a field model".into()
    }
}

/// An element known by its linear Mueller block alone, as a function of the field position
/// (arcmin): a fitted or simulated block, a plate's equivalent block. It is defined
/// everywhere; its [`eval`](FieldModel::eval) is the polarization it gives unpolarized light,
/// and it passes no circular polarization ([`mueller::linear::LinearBlock::to_mueller`]).
pub struct LinearElement<F>(pub F);

impl<F: Fn(f64, f64) -> mueller::linear::LinearBlock + Send + Sync> FieldModel for LinearElement<F> {
    fn eval(&self, x_arcmin: f64, y_arcmin: f64) -> InstPol {
        let o = (self.0)(x_arcmin, y_arcmin).apply([1.0, 0.0, 0.0]);
        InstPol { q: o[1] / o[0], u: o[2] / o[0], ..InstPol::ZERO }
    }
    fn contains(&self, _: f64, _: f64) -> bool {
        true
    }
    fn block_at(&self, x_arcmin: f64, y_arcmin: f64) -> mueller::linear::LinearBlock {
        (self.0)(x_arcmin, y_arcmin)
    }
    fn mueller_at(&self, x_arcmin: f64, y_arcmin: f64) -> mueller::Mueller {
        (self.0)(x_arcmin, y_arcmin).to_mueller()
    }
    fn describe(&self) -> String {
        "a linear Mueller block".into()
    }
}
