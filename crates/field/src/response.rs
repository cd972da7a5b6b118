//! The instrument's constant response to linear polarization, as observatories calibrate it
//! on standard stars (the MOPTOP, RoboPol and SPARC4 reductions): a constant instrumental
//! polarization `(q0, u0)` that an unpolarized star shows, a polarimetric efficiency `eta`
//! (measured `p` over true `p`, a depolarization below 1) and an angle offset `k`:
//!
//! ```text
//! (q, u)_measured = (q0, u0) + eta R(-k) (q, u)_true
//! ```
//!
//! `R(a)` turns a polarization angle by `a` (`(q, u)` by `2 a`, [`mueller::Qu::rotated`]).
//! The offset `k` has the sign of the HWP zero angle (`fit::zeroangle`): the angle to *add* to
//! a measured `chi` to make it the true one, so a star's measured `chi` is its true one less
//! `k`. Both `(q, u)` are in one frame (the instrument's sky frame of the calibration, where
//! the models of every calibration live); the response is the same over the field.
//!
//! As a Mueller element it is the linear block `[[1, 0, 0], [q0, eta c, eta s], [u0, -eta s,
//! eta c]]` with `c = cos 2k`, `s = sin 2k` (intensity kept, no circular polarization passed),
//! so the simulator renders it through the chain like any element and the correction inverts
//! it exactly: `(q, u)_true = R(k) ((q, u)_measured - (q0, u0)) / eta`.

use mueller::linear::LinearBlock;

/// The constant response (module docs). `efficiency` is a fraction (1: none lost), `offset_deg`
/// in degrees as the instrument and scene files give angles.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConstantResponse {
    /// The instrumental `q` an unpolarized star shows (fraction).
    pub q0: f64,
    /// The instrumental `u` an unpolarized star shows (fraction).
    pub u0: f64,
    /// Measured `p` over true `p` (fraction, in (0, 1] for a physical instrument).
    pub efficiency: f64,
    /// The angle to add to a measured `chi` (deg): a star's measured `chi` is its true one
    /// less this.
    pub offset_deg: f64,
}

impl ConstantResponse {
    /// The response that changes nothing.
    pub const IDENTITY: Self = Self { q0: 0.0, u0: 0.0, efficiency: 1.0, offset_deg: 0.0 };

    /// `(cos 2k, sin 2k)` of the offset.
    fn cos_sin(&self) -> (f64, f64) {
        let (s, c) = (2.0 * self.offset_deg.to_radians()).sin_cos();
        (c, s)
    }

    /// The `(I, Q, U)` block (module docs).
    pub fn block(&self) -> LinearBlock {
        let (c, s) = self.cos_sin();
        let e = self.efficiency;
        let mut b = LinearBlock::identity();
        for (k, v) in [(self.q0, e * c, e * s), (self.u0, -e * s, e * c)].into_iter().enumerate() {
            (b.0[(k + 1, 0)], b.0[(k + 1, 1)], b.0[(k + 1, 2)]) = v;
        }
        b
    }

    /// The measured `(q, u)` of a star of true `(q, u)`.
    pub fn forward(&self, q: f64, u: f64) -> (f64, f64) {
        let (c, s) = self.cos_sin();
        let e = self.efficiency;
        (self.q0 + e * (c * q + s * u), self.u0 + e * (-s * q + c * u))
    }

    /// The true `(q, u)` of a star measured at `(q, u)`; `None` for an efficiency that is 0 or
    /// not a number (nothing of the star's polarization reached the analyser).
    pub fn invert(&self, q: f64, u: f64) -> Option<(f64, f64)> {
        let e = self.efficiency;
        if !(e.is_finite() && e != 0.0) {
            return None;
        }
        let (c, s) = self.cos_sin();
        let (dq, du) = (q - self.q0, u - self.u0);
        Some(((c * dq - s * du) / e, (s * dq + c * du) / e))
    }

    /// Why the response cannot be an instrument's, or `None`: every value finite, the
    /// efficiency in (0, 1] and `hypot(q0, u0) + efficiency <= 1` (no star of `p <= 1` is
    /// measured above 1).
    pub fn unphysical(&self) -> Option<String> {
        let ConstantResponse { q0, u0, efficiency: e, offset_deg } = *self;
        if ![q0, u0, e, offset_deg].iter().all(|v| v.is_finite()) {
            return Some(format!("q0 {q0}, u0 {u0}, efficiency {e} and offset_deg {offset_deg} must all be numbers"));
        }
        if !(e > 0.0 && e <= 1.0) {
            return Some(format!("efficiency {e} must lie in (0, 1]"));
        }
        if q0.hypot(u0) + e > 1.0 + 1e-12 {
            return Some(format!(
                "hypot(q0, u0) + efficiency = {:.4} exceeds 1: a fully polarized star would be measured above p = 1",
                q0.hypot(u0) + e
            ));
        }
        None
    }
}

impl crate::FieldModel for ConstantResponse {
    /// What an unpolarized star shows: `(q0, u0)`.
    fn eval(&self, _: f64, _: f64) -> crate::InstPol {
        crate::InstPol { q: self.q0, u: self.u0, ..crate::InstPol::ZERO }
    }
    fn contains(&self, _: f64, _: f64) -> bool {
        true
    }
    fn block_at(&self, _: f64, _: f64) -> LinearBlock {
        self.block()
    }
    fn mueller_at(&self, _: f64, _: f64) -> mueller::Mueller {
        self.block().to_mueller()
    }
    fn describe(&self) -> String {
        format!(
            "a constant response: (q0, u0) = ({:.5}, {:.5}), efficiency {:.4}, offset {:.3} deg",
            self.q0, self.u0, self.efficiency, self.offset_deg
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The forward map is the block applied to `(1, q, u)`, and its closed form: a star of
    /// p = 4 %, chi = 30 deg through eta = 0.9, k = 5 deg and no (q0, u0) is measured at
    /// p = 3.6 %, chi = 25 deg; the inverse gives the star back; efficiency 1 and offset 0
    /// with no (q0, u0) is the identity.
    #[test]
    fn forward_block_closed_form_and_inverse() {
        let r = ConstantResponse { q0: 0.0, u0: 0.0, efficiency: 0.9, offset_deg: 5.0 };
        let (q, u) = (0.04 * 60f64.to_radians().cos(), 0.04 * 60f64.to_radians().sin());
        let (mq, mu) = r.forward(q, u);
        assert!((mq.hypot(mu) - 0.036).abs() < 1e-15);
        assert!(((0.5 * mu.atan2(mq)).to_degrees() - 25.0).abs() < 1e-12);
        let r = ConstantResponse { q0: 0.003, u0: -0.002, ..r };
        let (mq, mu) = r.forward(q, u);
        let b = r.block().apply([1.0, q, u]);
        assert!((b[0] - 1.0).abs() < 1e-15 && (b[1] - mq).abs() < 1e-15 && (b[2] - mu).abs() < 1e-15);
        let (tq, tu) = r.invert(mq, mu).unwrap();
        assert!((tq - q).abs() < 1e-15 && (tu - u).abs() < 1e-15);
        assert_eq!(ConstantResponse::IDENTITY.forward(q, u), (q, u));
        assert!(ConstantResponse { efficiency: 0.0, ..r }.invert(mq, mu).is_none());
        assert!(ConstantResponse { efficiency: 1.2, ..r }.unphysical().is_some());
        assert!(r.unphysical().is_none());
    }
}
