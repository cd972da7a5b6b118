//! The field-dependent part of the instrument's optical chain: the elements between the
//! telescope and the analyser whose action depends on the position in the field (the
//! instrumental partial polarizer of `eq:instpol`, a stressed lens, the half-wave plate's
//! defects, a fitted Mueller field), each a [`FieldModel`] answering its linear Mueller block,
//! in the order light meets them.
//!
//! Order matters: the blocks do not commute (a retarder after a partial polarizer is not one
//! before it), and the telescope, whose matrix changes from exposure to exposure, acts before
//! all of them. The simulator renders through [`FieldChain::apply_at`] (each element in turn)
//! or, behind a telescope, through [`FieldChain::mueller_at`] (their product, kept per pixel
//! and applied after each exposure's telescope matrix, circular polarization included: M3
//! makes some, a retarder after it turns some back).
//!
//! [`InstrumentChain`] is the whole chain as one value, the one the simulator renders through
//! and the correction inverts: the telescope, these elements, the half-wave plate's zero angle
//! and, for rendering frames, the plate and the analyser ([`crate::analyser::Analyser`]). Its
//! forward models: to the two beams' fluxes of one exposure (`crate::render`, what every
//! simulated frame is made of), and to the `(q, u)` demodulated from one exposure or a set of
//! them, with their exact inverses, the covariance carried through both.

use crate::FieldModel;
use mueller::linear::LinearBlock;
use mueller::telescope::{BandModel, Demodulation, Exposure, Track};
use mueller::{Mueller, Qu};
use std::sync::Arc;

/// The field-dependent elements of the chain, first met first.
#[derive(Clone, Default)]
pub struct FieldChain {
    elements: Vec<(Arc<dyn FieldModel>, String)>,
}

impl FieldChain {
    /// No element: the identity.
    pub fn new() -> Self {
        Self::default()
    }

    /// Add `element` after the ones already in the chain (light meets it later), with a line
    /// saying what it is.
    pub fn then(mut self, element: Arc<dyn FieldModel>, what: impl Into<String>) -> Self {
        self.elements.push((element, what.into()));
        self
    }

    pub fn is_empty(&self) -> bool {
        self.elements.is_empty()
    }

    /// What each element is, in order.
    pub fn describe(&self) -> Vec<&str> {
        self.elements.iter().map(|(_, w)| w.as_str()).collect()
    }

    /// `(I, Q, U)` after the chain at `(x, y)` arcmin: each element's block applied in turn.
    #[inline]
    pub fn apply_at(&self, x_arcmin: f64, y_arcmin: f64, iqu: [f64; 3]) -> [f64; 3] {
        self.elements.iter().fold(iqu, |s, (e, _)| e.block_at(x_arcmin, y_arcmin).apply(s))
    }

    /// The chain's block at `(x, y)` arcmin: the product of its elements' blocks, the last
    /// met on the left.
    pub fn block_at(&self, x_arcmin: f64, y_arcmin: f64) -> LinearBlock {
        let mut it = self.elements.iter();
        let Some((first, _)) = it.next() else { return LinearBlock::identity() };
        it.fold(first.block_at(x_arcmin, y_arcmin), |b, (e, _)| LinearBlock(e.block_at(x_arcmin, y_arcmin).0 * b.0))
    }

    /// The chain's Mueller matrix at `(x, y)` arcmin: the product of its elements' matrices
    /// ([`FieldModel::mueller_at`]), the last met on the left.
    pub fn mueller_at(&self, x_arcmin: f64, y_arcmin: f64) -> Mueller {
        let mut it = self.elements.iter();
        let Some((first, _)) = it.next() else { return Mueller::identity() };
        it.fold(first.mueller_at(x_arcmin, y_arcmin), |m, (e, _)| e.mueller_at(x_arcmin, y_arcmin) * m)
    }
}

/// Why the chain could not be evaluated or inverted.
#[derive(Debug)]
pub enum ChainError {
    /// The telescope model could not be evaluated (its mirror), or the system is singular.
    Model(mueller::Error),
    /// A chain with a telescope asked for an exposure without a parallactic-angle track.
    NoTrack,
    /// No light passes the chain at this position, or the result is not finite.
    NoLight { x: f64, y: f64 },
    /// The fluxes were asked of a chain without a plate and analyser (one that starts from
    /// demodulated `(q, u)`).
    NoAnalyser,
}

impl std::fmt::Display for ChainError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ChainError::Model(e) => write!(f, "{e}"),
            ChainError::NoTrack => write!(f, "the chain has a telescope and the exposure no parallactic-angle track"),
            ChainError::NoLight { x, y } => {
                write!(f, "the chain passes no light or no finite polarization at ({x}, {y}) arcmin")
            }
            ChainError::NoAnalyser => write!(f, "the chain has no plate and analyser: it gives (q, u), not fluxes"),
        }
    }
}

impl std::error::Error for ChainError {}

impl From<mueller::Error> for ChainError {
    fn from(e: mueller::Error) -> Self {
        ChainError::Model(e)
    }
}

/// The instrument's optical chain from the sky to the analyser, in the order light meets it:
/// the telescope (a band model whose matrix is averaged over each exposure's
/// parallactic-angle track, `mueller::telescope`), the field-dependent elements
/// ([`FieldChain`]), and the half-wave plate, whose zero angle turns what the analyser sees.
///
/// Frames: the elements act in the sky frame; a measurement at the plate (demodulated with the
/// HWP angles as read) has its polarization angle smaller by [`zero_angle`](Self::zero_angle)
/// than the light reaching the plate, so [`forward`](Self::forward) turns by `-zero_angle` last
/// and [`invert`](Self::invert) by `+zero_angle` first (the plate of zero angle `z` read at
/// `theta` modulates as `cos, sin (4 theta + 2 z)`).
///
/// The telescope's matrix is divided by its `M_00` (fluxes kept, as the simulator renders) and
/// its band model's constant `q0, u0` is not used: the instrument's own polarization is the
/// elements'.
///
/// With an [`Analyser`](crate::analyser::Analyser) (the plate with its defects and motion, the
/// Wollaston, the post-analyser optics) the chain goes on to the detector's two beams:
/// [`fluxes`](Self::fluxes) and its pieces (`crate::render`), through which the simulator
/// renders every frame. A correction's chain has none: it starts from the `(q, u)` the
/// reduction demodulated, at the plate.
#[derive(Clone, Default)]
pub struct InstrumentChain {
    pub telescope: Option<BandModel>,
    pub elements: FieldChain,
    /// The HWP zero angle (rad); with an analyser, its plate's
    /// ([`with_analyser`](Self::with_analyser)).
    pub zero_angle: f64,
    /// The plate and the analyser, when the chain renders fluxes.
    pub analyser: Option<crate::analyser::Analyser>,
}

/// The telescope's matrix over `track` ([`BandModel::matrix_track`]) divided by its `M_00`,
/// so that an unpolarized source keeps its flux: the chain's telescope, as the simulator
/// renders it and the correction inverts it.
pub fn telescope_matrix(t: &BandModel, track: Track) -> Result<Mueller, mueller::Error> {
    let m = t.matrix_track(track)?;
    Ok(m / m[(0, 0)])
}

/// `d (q', u') / d (q, u)` of the normalized `M (1, q, u, 0)` at `v = M (1, q, u, 0)`.
fn normalized_jacobian(m: &Mueller, v: &mueller::Stokes) -> [[f64; 2]; 2] {
    let i2 = v[0] * v[0];
    let d = |k: usize, j: usize| (m[(k, j)] * v[0] - v[k] * m[(0, j)]) / i2;
    [[d(1, 1), d(1, 2)], [d(2, 1), d(2, 2)]]
}

/// The 2 x 2 inverse of a Jacobian; `None` when singular.
fn inverse2(j: &[[f64; 2]; 2]) -> Option<[[f64; 2]; 2]> {
    let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
    (det.is_finite() && det != 0.0).then(|| [[j[1][1] / det, -j[0][1] / det], [-j[1][0] / det, j[0][0] / det]])
}

impl InstrumentChain {
    /// The Mueller matrix from the sky to just before the plate at `(x, y)` arcmin for an
    /// exposure over `track` (needed when the chain has a telescope).
    pub fn matrix(&self, x: f64, y: f64, track: Option<Track>) -> Result<Mueller, ChainError> {
        let f = self.elements.mueller_at(x, y);
        match (&self.telescope, track) {
            (None, _) => Ok(f),
            (Some(_), None) => Err(ChainError::NoTrack),
            (Some(t), Some(track)) => Ok(f * telescope_matrix(t, track)?),
        }
    }

    /// The `(q, u)` one exposure over `track` measures at the plate at `(x, y)` arcmin for
    /// the sky's `sky` (without circular polarization), its covariance `J C J^T` through the
    /// chain's exact Jacobian.
    pub fn forward(&self, x: f64, y: f64, sky: &Qu, track: Option<Track>) -> Result<Qu, ChainError> {
        let m = self.matrix(x, y, track)?;
        let v = m * mueller::Stokes::new(1.0, sky.q, sky.u, 0.0);
        if !(v[0] > 0.0 && v[0].is_finite()) {
            return Err(ChainError::NoLight { x, y });
        }
        let j = normalized_jacobian(&m, &v);
        let (vq, vu, c) = sky.covariance_through(&j);
        Ok(Qu::new(v[1] / v[0], v[2] / v[0], vq, vu, c).rotated(-self.zero_angle))
    }

    /// The demodulation (`eq:Q`, `eq:U`) of `exposures` at `(x, y)` arcmin, each exposure
    /// through its own track, in the sky frame: the plate angle of each is shifted by half the
    /// zero angle ([`InstrumentChain`] docs), so that the result is the sky frame's.
    pub fn demodulation(&self, x: f64, y: f64, exposures: &[Exposure]) -> Result<Demodulation, ChainError> {
        let matrices = exposures
            .iter()
            .map(|e| Ok((e.hwp + 0.5 * self.zero_angle, self.matrix(x, y, Some(e.track))?)))
            .collect::<Result<Vec<_>, ChainError>>()?;
        Ok(Demodulation::of_matrices(matrices)?)
    }

    /// The `(q, u)` the dual-beam reduction demodulates at the plate from `exposures` (HWP
    /// angle as read, track each) at `(x, y)` arcmin for the sky's `sky`; the covariance
    /// through the Jacobian (central differences of the demodulation, which is smooth).
    pub fn forward_exposures(&self, x: f64, y: f64, sky: &Qu, exposures: &[Exposure]) -> Result<Qu, ChainError> {
        let d = self.demodulation(x, y, exposures)?;
        let (q, u) = d.forward(sky.q, sky.u);
        if !(q.is_finite() && u.is_finite()) {
            return Err(ChainError::NoLight { x, y });
        }
        let j = demodulation_jacobian(&d, sky.q, sky.u);
        let (vq, vu, c) = sky.covariance_through(&j);
        Ok(Qu::new(q, u, vq, vu, c).rotated(-self.zero_angle))
    }

    /// The sky's `(q, u)` of a measurement `measured` at the plate at `(x, y)` arcmin from one
    /// exposure over `track` (or a set that shares it): the zero angle turned back, then the
    /// chain's matrix inverted exactly ([`mueller::telescope::invert_normalized`]); the
    /// covariance through the inverse Jacobian, `J^-1 C J^-T`.
    pub fn invert(&self, x: f64, y: f64, measured: &Qu, track: Option<Track>) -> Result<Qu, ChainError> {
        let m = self.matrix(x, y, track)?;
        let at = measured.rotated(self.zero_angle);
        let (q, u) = mueller::telescope::invert_normalized(&m, [at.q, at.u])?;
        let v = m * mueller::Stokes::new(1.0, q, u, 0.0);
        let ji = inverse2(&normalized_jacobian(&m, &v)).ok_or(ChainError::NoLight { x, y })?;
        let (vq, vu, c) = at.covariance_through(&ji);
        Ok(Qu::new(q, u, vq, vu, c))
    }

    /// The sky's `(q, u)` of a measurement demodulated from `exposures` at `(x, y)` arcmin:
    /// the zero angle turned back, then [`Demodulation::solve`] from the inverse over the first
    /// exposure's track; the covariance through the inverse Jacobian.
    pub fn invert_exposures(&self, x: f64, y: f64, measured: &Qu, exposures: &[Exposure]) -> Result<Qu, ChainError> {
        let d = self.demodulation(x, y, exposures)?;
        let at = measured.rotated(self.zero_angle);
        let first = exposures.first().map(|e| e.track);
        let start = self.invert(x, y, &Qu::new(measured.q, measured.u, 0.0, 0.0, 0.0), first)?;
        let (q, u) = d.solve((at.q, at.u), (start.q, start.u))?;
        let ji = inverse2(&demodulation_jacobian(&d, q, u)).ok_or(ChainError::NoLight { x, y })?;
        let (vq, vu, c) = at.covariance_through(&ji);
        Ok(Qu::new(q, u, vq, vu, c))
    }
}

/// `d forward / d (q, u)` of a demodulation, by central differences (step 1e-6 on fractions:
/// the forward model is linear-fractional, its second derivative of order 1, so the error is
/// of order 1e-12).
fn demodulation_jacobian(d: &Demodulation, q: f64, u: f64) -> [[f64; 2]; 2] {
    let h = 1e-6;
    let (aq, au) = d.forward(q + h, u);
    let (bq, bu) = d.forward(q - h, u);
    let (cq, cu) = d.forward(q, u + h);
    let (dq, du) = d.forward(q, u - h);
    [[(aq - bq) / (2.0 * h), (cq - dq) / (2.0 * h)], [(au - bu) / (2.0 * h), (cu - du) / (2.0 * h)]]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::InstPol;

    /// A retarder of retardance `delta` at axis 0 (its `(I, Q, U)` block, written here).
    struct Retarder(f64);
    impl FieldModel for Retarder {
        fn eval(&self, _: f64, _: f64) -> InstPol {
            InstPol::default()
        }
        fn contains(&self, _: f64, _: f64) -> bool {
            true
        }
        fn mueller_at(&self, _: f64, _: f64) -> mueller::Mueller {
            let (s, c) = self.0.sin_cos();
            mueller::Mueller::new(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, c, -s, 0.0, 0.0, s, c)
        }
    }
    /// A uniform partial polarizer along 45 deg (`u = p`; the default block from `eval`).
    struct Polarizer(f64);
    impl FieldModel for Polarizer {
        fn eval(&self, _: f64, _: f64) -> InstPol {
            InstPol { u: self.0, ..Default::default() }
        }
        fn contains(&self, _: f64, _: f64) -> bool {
            true
        }
    }

    /// The order of the elements: unpolarized light through a partial polarizer at 45 deg
    /// comes out with `u = p` (eq:instpol); a half-wave retarder at 0 deg after it turns that
    /// into `u = -p`, while before it (on unpolarized light) it does nothing. The product of
    /// the blocks equals the elements applied in turn.
    #[test]
    fn elements_act_in_the_order_light_meets_them() {
        let p = 0.02;
        let half_wave = || Arc::new(Retarder(std::f64::consts::PI));
        let pol_then_ret = FieldChain::new().then(Arc::new(Polarizer(p)), "pol").then(half_wave(), "ret");
        let ret_then_pol = FieldChain::new().then(half_wave(), "ret").then(Arc::new(Polarizer(p)), "pol");
        let unpol = [1.0, 0.0, 0.0];
        let (a, b) = (pol_then_ret.apply_at(0.0, 0.0, unpol), ret_then_pol.apply_at(0.0, 0.0, unpol));
        assert!(a[1].abs() < 1e-15 && (a[2] / a[0] + p).abs() < 1e-15, "{a:?}");
        assert!(b[1].abs() < 1e-15 && (b[2] / b[0] - p).abs() < 1e-15, "{b:?}");
        let s = [1.0, 0.01, -0.03];
        for c in [&pol_then_ret, &ret_then_pol] {
            let b = c.block_at(0.3, -0.1).apply(s);
            let v = c.apply_at(0.3, -0.1, s);
            for k in 0..3 {
                assert!((b[k] - v[k]).abs() < 1e-15, "{b:?} vs {v:?}");
            }
        }
        assert_eq!(FieldChain::new().apply_at(1.0, 1.0, s), s);
        assert_eq!(pol_then_ret.describe(), vec!["pol", "ret"]);
    }
}
