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

    /// `d mueller_at / d q` and `d mueller_at / d u` at `(x, y)` arcmin, the derivatives of
    /// the element's matrix with respect to its own `(q, u)` ([`eval`](Self::eval)), for an
    /// element whose matrix is a function of them: the chain then carries the element's
    /// covariance into its forward model's (`InstrumentChain::forward`). `None` (the default):
    /// the element's own errors are not the chain's.
    fn qu_derivatives(&self, _x_arcmin: f64, _y_arcmin: f64) -> Option<[mueller::Mueller; 2]> {
        None
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

/// A partial polarizer `M_I(p, phi)` of `eq:instpol` the same over the field, given by its
/// `(q, u)` with their covariance (a calibration's instrumental polarization at one position):
/// an element whose errors the chain carries ([`FieldModel::qu_derivatives`]).
#[derive(Clone, Copy, Debug)]
pub struct PartialPolarizer(pub InstPol);

impl FieldModel for PartialPolarizer {
    fn eval(&self, _: f64, _: f64) -> InstPol {
        self.0
    }
    fn contains(&self, _: f64, _: f64) -> bool {
        true
    }
    /// `M_I = N / (1 + p)` with (rows and columns `I, Q, U, V`, `p = hypot(q, u)`)
    /// `N = [[1, q, u, 0], [q, 1 - u^2/p, q u/p, 0], [u, q u/p, 1 - q^2/p, 0], [0, 0, 0, 1 - p]]`
    /// (`mueller::partial_polarizer` with `p cos 2phi = q`, `p sin 2phi = u`), differentiated
    /// term by term. At `p = 0`, where the terms in `1/p` have a direction, the symmetric limit
    /// (that of central differences): `N' = [[0, 1, 0, 0], [1, 0, 0, 0], 0, 0]` for `q` and
    /// its companion for `u`.
    fn qu_derivatives(&self, _: f64, _: f64) -> Option<[mueller::Mueller; 2]> {
        let (q, u) = (self.0.q, self.0.u);
        let p = mueller::hypot(q, u);
        if !p.is_finite() {
            return None;
        }
        let mut dq = mueller::Mueller::zeros();
        let mut du = mueller::Mueller::zeros();
        (dq[(0, 1)], dq[(1, 0)], du[(0, 2)], du[(2, 0)]) = (1.0, 1.0, 1.0, 1.0);
        if p == 0.0 {
            return Some([dq, du]);
        }
        let (p3, k) = (p * p * p, 1.0 / (1.0 + p));
        dq[(1, 1)] = u * u * q / p3;
        dq[(1, 2)] = u / p - q * q * u / p3;
        dq[(2, 1)] = dq[(1, 2)];
        dq[(2, 2)] = -2.0 * q / p + q * q * q / p3;
        dq[(3, 3)] = -q / p;
        du[(1, 1)] = -2.0 * u / p + u * u * u / p3;
        du[(1, 2)] = q / p - q * u * u / p3;
        du[(2, 1)] = du[(1, 2)];
        du[(2, 2)] = q * q * u / p3;
        du[(3, 3)] = -u / p;
        // M = k N with dk/dp = -k^2 and dp/dq = q/p, dp/du = u/p.
        let n = mueller::partial_polarizer(p, 0.5 * u.atan2(q)) / k;
        Some([dq * k - n * (k * k * q / p), du * k - n * (k * k * u / p)])
    }
    fn describe(&self) -> String {
        format!("a partial polarizer q = {}, u = {}", self.0.q, self.0.u)
    }
}
