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

    /// For each element whose own `(q, u)` has known derivatives
    /// ([`FieldModel::qu_derivatives`]): `d v / d q_e` and `d v / d u_e` of the Stokes vector
    /// `v` that leaves the chain for `s` entering it at `(x, y)` arcmin (the elements before
    /// it, the derivative, the elements after it), with the element's `(q, u)` and covariance.
    pub fn qu_sensitivities(
        &self,
        x_arcmin: f64,
        y_arcmin: f64,
        s: &mueller::Stokes,
    ) -> Vec<([mueller::Stokes; 2], Qu)> {
        let ms: Vec<Mueller> = self.elements.iter().map(|(e, _)| e.mueller_at(x_arcmin, y_arcmin)).collect();
        let mut out = Vec::new();
        for (k, (e, _)) in self.elements.iter().enumerate() {
            let Some([dq, du]) = e.qu_derivatives(x_arcmin, y_arcmin) else { continue };
            let before = ms[..k].iter().fold(*s, |v, m| m * v);
            let after = |v: mueller::Stokes| ms[k + 1..].iter().fold(v, |v, m| m * v);
            out.push(([after(dq * before), after(du * before)], e.eval(x_arcmin, y_arcmin)));
        }
        out
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
    /// the sky's `sky` (without circular polarization), its covariance through the chain's
    /// analytic Jacobians: `J C J^T` of the sky's, plus `J_e C_e J_e^T` of every element whose
    /// own `(q, u)` carries a covariance and has derivatives ([`FieldChain::qu_sensitivities`]:
    /// a calibration's partial polarizer with its errors).
    pub fn forward(&self, x: f64, y: f64, sky: &Qu, track: Option<Track>) -> Result<Qu, ChainError> {
        let m = self.matrix(x, y, track)?;
        let s = mueller::Stokes::new(1.0, sky.q, sky.u, 0.0);
        let v = m * s;
        if !(v[0] > 0.0 && v[0].is_finite()) {
            return Err(ChainError::NoLight { x, y });
        }
        let j = normalized_jacobian(&m, &v);
        let (vq, vu, c) = sky.covariance_through(&j);
        let (eq, eu, ec) = self.elements_covariance(x, y, &s, &v, track)?;
        Ok(Qu::new(v[1] / v[0], v[2] / v[0], vq + eq, vu + eu, c + ec).rotated(-self.zero_angle))
    }

    /// The covariance the elements' own errors give the normalized output `v` of the sky's
    /// `s` at `(x, y)` arcmin: `sum J_e C_e J_e^T` over the elements with derivatives
    /// ([`FieldChain::qu_sensitivities`]), `J_e = d (v1/v0, v2/v0) / d (q_e, u_e)`; zero when
    /// no element has them.
    fn elements_covariance(
        &self,
        x: f64,
        y: f64,
        s: &mueller::Stokes,
        v: &mueller::Stokes,
        track: Option<Track>,
    ) -> Result<(f64, f64, f64), ChainError> {
        let entering = match (&self.telescope, track) {
            (Some(t), Some(track)) => telescope_matrix(t, track)? * s,
            _ => *s,
        };
        let mut out = (0.0, 0.0, 0.0);
        for ([dq, du], e) in self.elements.qu_sensitivities(x, y, &entering) {
            // d (v1 / v0) = (dv1 v0 - v1 dv0) / v0^2, and alike for v2.
            let d = |dv: &mueller::Stokes, k: usize| (dv[k] * v[0] - v[k] * dv[0]) / (v[0] * v[0]);
            let (a, b, c) = e.covariance_through(&[[d(&dq, 1), d(&du, 1)], [d(&dq, 2), d(&du, 2)]]);
            out = (out.0 + a, out.1 + b, out.2 + c);
        }
        Ok(out)
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
    /// through the demodulation's analytic Jacobian ([`Demodulation::jacobian`]).
    pub fn forward_exposures(&self, x: f64, y: f64, sky: &Qu, exposures: &[Exposure]) -> Result<Qu, ChainError> {
        let d = self.demodulation(x, y, exposures)?;
        let (q, u) = d.forward(sky.q, sky.u);
        if !(q.is_finite() && u.is_finite()) {
            return Err(ChainError::NoLight { x, y });
        }
        let j = d.jacobian(sky.q, sky.u);
        let (vq, vu, c) = sky.covariance_through(&j);
        Ok(Qu::new(q, u, vq, vu, c).rotated(-self.zero_angle))
    }

    /// The sky's `(q, u)` of a measurement `measured` at the plate at `(x, y)` arcmin from one
    /// exposure over `track` (or a set that shares it): the zero angle turned back, then the
    /// chain's matrix inverted exactly ([`mueller::telescope::invert_normalized`]); the
    /// covariance through the same Jacobians as [`forward`](Self::forward)'s, inverted (the
    /// measurement is `f(sky, elements)`, so `d sky = J^-1 (d measured - J_e d e)`):
    /// `J^-1 (C + sum J_e C_e J_e^T) J^-T`.
    pub fn invert(&self, x: f64, y: f64, measured: &Qu, track: Option<Track>) -> Result<Qu, ChainError> {
        let m = self.matrix(x, y, track)?;
        let at = measured.rotated(self.zero_angle);
        let (q, u) = mueller::telescope::invert_normalized(&m, [at.q, at.u])?;
        let s = mueller::Stokes::new(1.0, q, u, 0.0);
        let v = m * s;
        let ji = inverse2(&normalized_jacobian(&m, &v)).ok_or(ChainError::NoLight { x, y })?;
        let (eq, eu, ec) = self.elements_covariance(x, y, &s, &v, track)?;
        let with_elements = Qu { var_q: at.var_q + eq, var_u: at.var_u + eu, cov_qu: at.cov_qu + ec, ..at };
        let (vq, vu, c) = with_elements.covariance_through(&ji);
        Ok(Qu::new(q, u, vq, vu, c))
    }

    /// The first-order inverse (`eq:approx` for any chain): the `(q, u)` the chain gives
    /// unpolarized light at `(x, y)` arcmin over `track` ([`forward`](Self::forward) of a zero
    /// sky, with the elements' own covariance) subtracted from the measurement, the zero angle
    /// turned back first; the covariances add. For one partial polarizer `M_I` this is
    /// `q0 = q1 - p cos 2phi`, `u0 = u1 - p sin 2phi`.
    pub fn invert_first_order(&self, x: f64, y: f64, measured: &Qu, track: Option<Track>) -> Result<Qu, ChainError> {
        let at = measured.rotated(self.zero_angle);
        let own = Self { zero_angle: 0.0, ..self.clone() }.forward(x, y, &Qu::ZERO, track)?;
        Ok(Qu::new(at.q - own.q, at.u - own.u, at.var_q + own.var_q, at.var_u + own.var_u, at.cov_qu + own.cov_qu))
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
        let ji = inverse2(&d.jacobian(q, u)).ok_or(ChainError::NoLight { x, y })?;
        let (vq, vu, c) = at.covariance_through(&ji);
        Ok(Qu::new(q, u, vq, vu, c))
    }
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

    /// An element's own errors through the chain, against the closed form of `eq:instpol`
    /// for a polarizer along `Q` of degree `p` (`q' = (q + p) / (1 + p q)`,
    /// `u' = u (1 - p) / (1 + p q)`, and for unpolarized light `(q', u') = (q_e, u_e)`):
    /// `forward` gives an unpolarized sky the element's covariance itself, a sky `(q, 0)` the
    /// variance of `q_e` times `((1 - q^2) / (1 + p q)^2)^2`; `invert` of an exact measurement
    /// of an unpolarized sky gives `var_qe / (1 - p^2)^2` and `var_ue / (1 - p)^2`.
    #[test]
    fn an_elements_errors_go_through_the_chains_jacobians() {
        let p = 0.03;
        let e = Qu::new(p, 0.0, 4e-6, 9e-6, 1e-6);
        let chain = InstrumentChain {
            elements: FieldChain::new().then(Arc::new(crate::PartialPolarizer(e)), "pol"),
            ..Default::default()
        };
        let zero = Qu::new(0.0, 0.0, 0.0, 0.0, 0.0);
        let f = chain.forward(0.2, 0.1, &zero, None).unwrap();
        assert!((f.q - p).abs() < 1e-15 && f.u.abs() < 1e-15, "{f:?}");
        for (a, b) in [(f.var_q, e.var_q), (f.var_u, e.var_u), (f.cov_qu, e.cov_qu)] {
            assert!((a - b).abs() < 1e-15 * b.abs().max(1e-6), "{f:?} vs {e:?}");
        }
        let qs = 0.05;
        let f = chain.forward(0.0, 0.0, &Qu::new(qs, 0.0, 0.0, 0.0, 0.0), None).unwrap();
        let want = ((1.0 - qs * qs) / (1.0 + p * qs).powi(2)).powi(2) * e.var_q;
        assert!((f.var_q - want).abs() < 1e-12 * want, "{} vs {want}", f.var_q);
        let back = chain.invert(0.0, 0.0, &Qu::new(p, 0.0, 0.0, 0.0, 0.0), None).unwrap();
        assert!(back.q.abs() < 1e-15 && back.u.abs() < 1e-15, "{back:?}");
        let (wq, wu) = (e.var_q / (1.0 - p * p).powi(2), e.var_u / (1.0 - p).powi(2));
        assert!((back.var_q - wq).abs() < 1e-12 * wq && (back.var_u - wu).abs() < 1e-12 * wu, "{back:?}");
        // Near zero polarization the derivatives take their symmetric limit: no NaN.
        let at_zero = InstrumentChain {
            elements: FieldChain::new()
                .then(Arc::new(crate::PartialPolarizer(Qu::new(0.0, 0.0, 1e-6, 1e-6, 0.0))), "0"),
            ..Default::default()
        };
        let f = at_zero.forward(0.0, 0.0, &zero, None).unwrap();
        assert!((f.var_q - 1e-6).abs() < 1e-18 && (f.var_u - 1e-6).abs() < 1e-18, "{f:?}");
        // First order (eq:approx): the element's (q, u) subtracted, the covariances added.
        let m = Qu::new(0.05, -0.01, 1e-6, 2e-6, 0.0);
        let fo = chain.invert_first_order(0.0, 0.0, &m, None).unwrap();
        assert!((fo.q - (m.q - p)).abs() < 1e-17 && (fo.u - m.u).abs() < 1e-17, "{fo:?}");
        for (a, b) in [(fo.var_q, m.var_q + e.var_q), (fo.var_u, m.var_u + e.var_u), (fo.cov_qu, e.cov_qu)] {
            assert!((a - b).abs() < 1e-15 * b.abs(), "{fo:?}");
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
