//! The field-dependent part of the instrument's optical chain: the elements between the
//! telescope and the analyser whose action depends on the position in the field (the
//! instrumental partial polarizer of `eq:instpol`, a stressed lens, the half-wave plate's
//! defects, a fitted Mueller field), each a [`FieldModel`] answering its linear Mueller block,
//! in the order light meets them.
//!
//! Order matters: the blocks do not commute (a retarder after a partial polarizer is not one
//! before it), and the telescope, whose matrix changes from exposure to exposure, acts before
//! all of them. The simulator renders through [`FieldChain::apply_at`] (each element in turn)
//! or, behind a telescope, through [`FieldChain::block_at`] (their product, kept per pixel and
//! applied after each exposure's telescope matrix).

use crate::FieldModel;
use mueller::linear::LinearBlock;
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
        fn block_at(&self, _: f64, _: f64) -> LinearBlock {
            let c = self.0.cos();
            LinearBlock(nalgebra::Matrix3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, c))
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
