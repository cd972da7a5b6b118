//! The one value of normalized linear polarization that flows between stages: `q = Q/I`,
//! `u = U/I` with their covariance.
//!
//! A measurement of a star or a bin, the instrumental polarization a field model predicts at a
//! position, a standard's expected polarization and a corrected result are all this value (with
//! a position beside it where one is needed). Its operations are the ones every stage needs and
//! that were once written in each: the polarization degree and angle with their errors
//! (`eq:poldeg`, `eq:polang`, `eq:sigp`, `eq:sigchi`), a turn of the angle with the covariance
//! (`R C R^T`), and the covariance through any linear map (`J C J^T`).
//!
//! Conventions: fractions, not percent; angles in radians; `chi` in [0, pi) measured as
//! `eq:polang` (`tan 2 chi = u / q`).

use serde::{Deserialize, Serialize};

/// The standard deviation of an angle that is not constrained at all (uniform over a range of
/// `pi`): `pi / sqrt(12)`. The cap of [`Qu::p_chi_with_errors`]'s angle error.
pub const SIGMA_CHI_UNCONSTRAINED: f64 = 0.906_899_682_117_108_9;

/// Normalized Stokes `q = Q/I`, `u = U/I` (fractions) with their covariance
/// `[[var_q, cov_qu], [cov_qu, var_u]]`.
///
/// ```
/// use mueller::Qu;
/// // 1 % at chi = 30 deg, sigma 0.1 % on each of q and u.
/// let chi = 30f64.to_radians();
/// let m = Qu::from_sigmas(0.01 * (2.0 * chi).cos(), 0.01 * (2.0 * chi).sin(), 1e-3, 1e-3, 0.0);
/// let e = m.p_chi_with_errors();
/// assert!((e.p - 0.01).abs() < 1e-15 && (e.chi - chi).abs() < 1e-12);
/// // eq:sigp: sigma_P = sigma for equal, independent errors; eq:sigchi: sigma_chi = sigma / (2 P).
/// assert!((e.sigma_p - 1e-3).abs() < 1e-15 && (e.sigma_chi - 0.05).abs() < 1e-12);
/// // Turning the angle by the HWP zero angle keeps P and the error ellipse's trace.
/// let r = m.rotated(2f64.to_radians());
/// assert!((r.p_chi().1 - 32f64.to_radians()).abs() < 1e-12);
/// assert!((r.var_q + r.var_u - 2e-6).abs() < 1e-20);
/// ```
/// How far above `P = 1` a measured `P` may lie, in units of its error, and still be taken as
/// light measured with noise ([`Qu::unphysical`]; the dual-beam reduction uses the same rule).
pub const P_ABOVE_ONE_SIGMAS: f64 = 3.0;

/// Why a `(q, u)` with its covariance cannot be a measurement of light ([`Qu::unphysical`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Unphysical {
    /// `cov_qu^2 > var_q var_u`: not a covariance.
    Covariance,
    /// `P > 1 + 3 sigma_P`.
    AboveOne { p: f64, sigma_p: f64 },
}

#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Qu {
    pub q: f64,
    pub u: f64,
    pub var_q: f64,
    pub var_u: f64,
    pub cov_qu: f64,
}

/// The frame a `(q, u)`'s angle is measured in. A dual-beam reduction measures `chi` from the
/// plate's zero; standards, catalogs and the models of a calibration give it in the sky's
/// frame. The two differ by the plate's zero angle: the angle (deg, as instrument files,
/// catalogs and calibration files tabulate it, `hwp_chi_offset_deg`) added to a `chi` measured
/// at the plate ([`crate::Hwp`]'s `chi_offset`). A value that goes from a reduction to a
/// correction says which frame it is in, and [`Frame::turn_to`] is the one conversion: a value
/// in the sky frame already is not turned again, and one at the plate is not taken as the sky's.
///
/// ```
/// use mueller::{Frame, Qu};
/// // A catalog of FORS2 v_HIGH (zero angle -1.8 deg) is in the sky frame; a calibration of
/// // that filter recording the same zero angle does not turn it, one recording 0 (the plate
/// // as measured) turns it back by 1.8 deg.
/// let row = Frame::Sky { zero_angle_deg: -1.8 };
/// assert_eq!(row.turn_to(-1.8), 0.0);
/// assert_eq!(row.turn_to(0.0), 1.8);
/// let qu = Qu::new(0.02, 0.0, 1e-6, 1e-6, 0.0);
/// assert_eq!(row.to_sky(&qu, -1.8), qu);
/// let plate = row.at_plate(&qu);
/// assert!((plate.p_chi().1.to_degrees() - 1.8).abs() < 1e-12);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Frame {
    /// As the plate measured it: `chi` from the plate's zero, which these values do not place
    /// on the sky.
    Plate,
    /// The sky's as the instrument sees it: the plate's zero angle `zero_angle_deg` (deg) added
    /// to the `chi` measured at the plate (`instpol catalog`'s rows, with their
    /// `hwp_chi_offset_deg` column). On an instrument whose angle zero points north this is the
    /// celestial frame; on a rotator it turns with the instrument. The models of a calibration
    /// live here.
    Sky { zero_angle_deg: f64 },
    /// The celestial frame, north through east, of an instrument a rotator turns: the plate's
    /// zero angle `zero_angle_deg`, then the instrument's position angle on the sky
    /// `position_angle_deg` (deg), added to the `chi` measured at the plate (`instpol
    /// catalog`'s rows of an instrument with `[polarimetry.sky_angle]`, with their
    /// `hwp_chi_offset_deg` and `sky_pa_deg` columns).
    Celestial { zero_angle_deg: f64, position_angle_deg: f64 },
}

impl Frame {
    /// The frame of rows that carry the zero angle `carried` (deg): the sky's, or the plate's
    /// when they carry none (a table without the zero-angle column).
    pub fn carrying(carried: Option<f64>) -> Self {
        carried.map_or(Frame::Plate, |zero_angle_deg| Frame::Sky { zero_angle_deg })
    }

    /// The frame of values that carry the zero angle `carried` (deg) and, on a rotator, were
    /// then turned onto the sky by the instrument's position angle `position_angle` (deg):
    /// [`Frame::carrying`] without one, [`Frame::Celestial`] with both; `None` for a position
    /// angle without the zero angle under it (the frame is not whole).
    pub fn carrying_on_sky(carried: Option<f64>, position_angle: Option<f64>) -> Option<Self> {
        match (carried, position_angle) {
            (Some(zero_angle_deg), Some(position_angle_deg)) => {
                Some(Frame::Celestial { zero_angle_deg, position_angle_deg })
            }
            (None, Some(_)) => None,
            (c, None) => Some(Frame::carrying(c)),
        }
    }

    /// The zero angle (deg) a value in this frame has been turned by: 0 at the plate.
    #[inline]
    pub fn carried_deg(self) -> f64 {
        match self {
            Frame::Plate => 0.0,
            Frame::Sky { zero_angle_deg } => zero_angle_deg,
            Frame::Celestial { zero_angle_deg, position_angle_deg } => zero_angle_deg + position_angle_deg,
        }
    }

    /// The plate's zero angle (deg) this frame says, when it says one.
    pub fn zero_angle_deg(self) -> Option<f64> {
        match self {
            Frame::Plate => None,
            Frame::Sky { zero_angle_deg } | Frame::Celestial { zero_angle_deg, .. } => Some(zero_angle_deg),
        }
    }

    /// The instrument's position angle on the sky (deg) this frame has been turned by, when it
    /// is the celestial frame.
    pub fn position_angle_deg(self) -> Option<f64> {
        match self {
            Frame::Celestial { position_angle_deg, .. } => Some(position_angle_deg),
            _ => None,
        }
    }

    /// The frame as the instrument sees it: the celestial frame without its position angle (the
    /// sky frame of its zero angle), any other frame itself. A calibration's models live there.
    pub fn in_instrument(self) -> Frame {
        match self {
            Frame::Celestial { zero_angle_deg, .. } => Frame::Sky { zero_angle_deg },
            f => f,
        }
    }

    /// `qu`, given in the instrument's frame (after a correction in a model's sky frame), turned
    /// onto the sky by this frame's position angle: itself, bit for bit, for any frame but the
    /// celestial one.
    #[inline]
    pub fn onto_sky(self, qu: &Qu) -> Qu {
        match self {
            Frame::Celestial { position_angle_deg, .. } => qu.rotated(position_angle_deg.to_radians()),
            _ => *qu,
        }
    }

    /// The turn (deg, added to `chi`, `eq:polang`) that takes a value in this frame into the
    /// sky frame of a plate of zero angle `zero_angle_deg`: that angle less the one the value
    /// carries. Exactly 0 for a value in that frame already.
    #[inline]
    pub fn turn_to(self, zero_angle_deg: f64) -> f64 {
        zero_angle_deg - self.carried_deg()
    }

    /// `qu`, given in this frame, in the sky frame of a plate of zero angle `zero_angle_deg`
    /// ([`turn_to`](Self::turn_to), [`Qu::rotated`]): `qu` itself, bit for bit, when it is in
    /// that frame already.
    #[inline]
    pub fn to_sky(self, qu: &Qu, zero_angle_deg: f64) -> Qu {
        qu.rotated(self.turn_to(zero_angle_deg).to_radians())
    }

    /// `qu`, given in this frame, as the plate measured it (the sky frame of a zero angle of 0).
    #[inline]
    pub fn at_plate(self, qu: &Qu) -> Qu {
        self.to_sky(qu, 0.0)
    }
}

/// `P`, `chi` and their linearized errors (fractions and radians), from
/// [`Qu::p_chi_with_errors`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolErrors {
    pub p: f64,
    pub sigma_p: f64,
    pub chi: f64,
    pub sigma_chi: f64,
}

impl Qu {
    /// No polarization, known exactly (an unpolarized standard).
    pub const ZERO: Qu = Qu { q: 0.0, u: 0.0, var_q: 0.0, var_u: 0.0, cov_qu: 0.0 };

    /// `(q, u)` with its covariance.
    pub const fn new(q: f64, u: f64, var_q: f64, var_u: f64, cov_qu: f64) -> Self {
        Self { q, u, var_q, var_u, cov_qu }
    }

    /// `(q, u)` with 1-sigma errors and a covariance, as tables give them. A negative error is
    /// not an error: it is kept as a negative variance (`sigma |sigma|`), so that a check of the
    /// variances refuses it rather than taking its square as valid.
    pub fn from_sigmas(q: f64, u: f64, sigma_q: f64, sigma_u: f64, cov_qu: f64) -> Self {
        Self { q, u, var_q: sigma_q * sigma_q.abs(), var_u: sigma_u * sigma_u.abs(), cov_qu }
    }

    /// The 1-sigma error of `q` (a negative variance, from rounding, counts as 0; an unknown
    /// one, NaN, stays unknown).
    #[inline]
    pub fn sigma_q(&self) -> f64 {
        sigma_of(self.var_q)
    }

    /// The 1-sigma error of `u` (as [`sigma_q`](Self::sigma_q)).
    #[inline]
    pub fn sigma_u(&self) -> f64 {
        sigma_of(self.var_u)
    }

    /// Polarization degree and angle (`eq:poldeg`, `eq:polang`): `P = hypot(q, u)`,
    /// `chi = atan2(u, q) / 2` folded into [0, pi).
    #[inline]
    pub fn p_chi(&self) -> (f64, f64) {
        (crate::hypot(self.q, self.u), crate::fold_pi(0.5 * self.u.atan2(self.q)))
    }

    /// `P`, `chi` with their linearized errors (`eq:sigp`, `eq:sigchi`, generalized to a full
    /// covariance). At `P = 0` the error of `P` is `sqrt((var_q + var_u) / 2)` and the angle is
    /// unconstrained; the angle error is capped at [`SIGMA_CHI_UNCONSTRAINED`].
    #[inline]
    pub fn p_chi_with_errors(&self) -> PolErrors {
        let Qu { q, u, var_q: vq, var_u: vu, cov_qu: c } = *self;
        let (p, chi) = self.p_chi();
        if p > 0.0 {
            let p2 = p * p;
            let sigma_p = ((q * q * vq + u * u * vu + 2.0 * q * u * c).max(0.0) / p2).sqrt();
            let sc = 0.5 * ((u * u * vq + q * q * vu - 2.0 * q * u * c).max(0.0)).sqrt() / p2;
            PolErrors { p, sigma_p, chi, sigma_chi: sc.min(SIGMA_CHI_UNCONSTRAINED) }
        } else {
            PolErrors { p, sigma_p: (0.5 * (vq + vu)).max(0.0).sqrt(), chi, sigma_chi: SIGMA_CHI_UNCONSTRAINED }
        }
    }

    /// What makes this value not a measurement of light, given finite values and variances
    /// `>= 0`: a covariance that is not positive semidefinite (`cov_qu^2 > var_q var_u`,
    /// beyond rounding: no error ellipse has it), or more than full polarization (`P > 1`,
    /// `eq:poldeg`) by more than [`P_ABOVE_ONE_SIGMAS`] of its error. `None` when neither.
    pub fn unphysical(&self) -> Option<Unphysical> {
        if self.cov_qu * self.cov_qu > self.var_q * self.var_u * (1.0 + 1e-9) {
            return Some(Unphysical::Covariance);
        }
        let e = self.p_chi_with_errors();
        (e.p > 1.0 + P_ABOVE_ONE_SIGMAS * e.sigma_p).then_some(Unphysical::AboveOne { p: e.p, sigma_p: e.sigma_p })
    }

    /// The same polarization with its angle turned by `dchi` (rad): `(q, u)` rotated by
    /// `2 dchi` (`eq:polang`), the covariance by `R C R^T` with
    /// `R = [[cos 2dchi, -sin 2dchi], [sin 2dchi, cos 2dchi]]`. How a `chi` measured at the
    /// plate becomes the sky's when the HWP zero angle `dchi` is added. A zero turn returns the
    /// value itself, bit for bit.
    #[inline]
    pub fn rotated(&self, dchi: f64) -> Self {
        if dchi == 0.0 {
            return *self;
        }
        let (s, c) = (2.0 * dchi).sin_cos();
        self.rotated_cos_sin(c, s)
    }

    /// [`rotated`](Self::rotated) with `cos 2dchi`, `sin 2dchi` given: for a loop that turns
    /// many values by one angle and computes the sine and cosine once.
    #[inline]
    pub fn rotated_cos_sin(&self, c: f64, s: f64) -> Self {
        let (var_q, var_u, cov_qu) = sandwich(&[[c, -s], [s, c]], self.var_q, self.var_u, self.cov_qu);
        Self { q: c * self.q - s * self.u, u: s * self.q + c * self.u, var_q, var_u, cov_qu }
    }

    /// The covariance carried through the linear map `j` (row-major 2 x 2, the Jacobian of a
    /// new `(q, u)` with respect to this one): `J C J^T` as `(var_q, var_u, cov_qu)`.
    #[inline]
    pub fn covariance_through(&self, j: &[[f64; 2]; 2]) -> (f64, f64, f64) {
        sandwich(j, self.var_q, self.var_u, self.cov_qu)
    }
}

/// `sqrt(v)`, 0 for a negative `v` (rounding), NaN for NaN (`f64::max` would make it 0: a
/// wrong error rather than an unknown one).
#[inline]
fn sigma_of(v: f64) -> f64 {
    if v < 0.0 {
        0.0
    } else {
        v.sqrt()
    }
}

/// `J C J^T` for the symmetric `C = [[a, c], [c, b]]` and a row-major 2 x 2 `J`, returned as
/// `(var_q, var_u, cov)`: how a covariance of `(q, u)` is carried through a linear map.
#[inline]
pub fn sandwich(j: &[[f64; 2]; 2], a: f64, b: f64, c: f64) -> (f64, f64, f64) {
    let r0 = [j[0][0] * a + j[0][1] * c, j[0][0] * c + j[0][1] * b];
    let r1 = [j[1][0] * a + j[1][1] * c, j[1][0] * c + j[1][1] * b];
    (r0[0] * j[0][0] + r0[1] * j[0][1], r1[0] * j[1][0] + r1[1] * j[1][1], r0[0] * j[1][0] + r0[1] * j[1][1])
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix2, Vector2};
    use std::f64::consts::{FRAC_PI_2, PI};

    /// The frames against rotations written here with nalgebra: a value in the sky frame of
    /// `z` is not turned into that frame again (bit for bit); one carrying `c` goes into the
    /// frame of `z` by `R(2 (z - c))` and back to the plate by `R(-2 c)`; a value at the plate
    /// goes into the frame of `z` by `R(2 z)`; going through a third frame on the way changes
    /// nothing but rounding.
    #[test]
    fn frames_turn_by_the_zero_angle_they_lack() {
        let e = Qu::new(0.03, -0.01, 4e-6, 9e-6, 1e-6);
        let by_hand = |v: &Qu, deg: f64| {
            let a = 2.0 * deg.to_radians();
            let m = Matrix2::new(a.cos(), -a.sin(), a.sin(), a.cos());
            let x = m * Vector2::new(v.q, v.u);
            let c = m * Matrix2::new(v.var_q, v.cov_qu, v.cov_qu, v.var_u) * m.transpose();
            Qu::new(x[0], x[1], c[(0, 0)], c[(1, 1)], c[(0, 1)])
        };
        let close = |a: &Qu, b: &Qu| {
            (a.q - b.q).abs() < 5e-17
                && (a.u - b.u).abs() < 5e-17
                && (a.var_q - b.var_q).abs() < 1e-20
                && (a.var_u - b.var_u).abs() < 1e-20
                && (a.cov_qu - b.cov_qu).abs() < 1e-20
        };
        for (c, z) in [(-1.8, -1.8), (-1.8, 0.0), (1.2, 2.9), (0.0, 45.0), (170.0, -10.0)] {
            let sky = Frame::Sky { zero_angle_deg: c };
            assert_eq!(sky.to_sky(&e, c), e);
            assert_eq!(sky.turn_to(c), 0.0);
            assert!(close(&sky.to_sky(&e, z), &by_hand(&e, z - c)), "{c} -> {z}");
            assert!(close(&sky.at_plate(&e), &by_hand(&e, -c)), "{c} -> plate");
            assert!(close(&Frame::Plate.to_sky(&e, z), &by_hand(&e, z)), "plate -> {z}");
            let via = Frame::Sky { zero_angle_deg: 7.0 }.to_sky(&sky.to_sky(&e, 7.0), z);
            assert!(close(&via, &sky.to_sky(&e, z)), "{c} -> 7 -> {z}");
            assert_eq!(sky.zero_angle_deg(), Some(c));
        }
        assert_eq!(Frame::Plate.at_plate(&e), e);
        assert_eq!(Frame::Plate.zero_angle_deg(), None);
        assert_eq!(Frame::carrying(None), Frame::Plate);
        assert_eq!(Frame::carrying(Some(2.89)), Frame::Sky { zero_angle_deg: 2.89 });
        // The celestial frame: the position angle on top of the zero angle, each undone by hand.
        for (z, pa) in [(2.89, -142.0), (0.0, 30.0), (-1.8, 181.5)] {
            let cel = Frame::Celestial { zero_angle_deg: z, position_angle_deg: pa };
            assert!(close(&cel.at_plate(&e), &by_hand(&e, -z - pa)), "{z}, {pa} -> plate");
            assert!(close(&cel.to_sky(&e, z), &by_hand(&e, -pa)), "{z}, {pa} -> instrument");
            assert!(close(&cel.onto_sky(&cel.to_sky(&e, z)), &e), "{z}, {pa} back onto the sky");
            assert_eq!(cel.in_instrument(), Frame::Sky { zero_angle_deg: z });
            assert_eq!((cel.zero_angle_deg(), cel.position_angle_deg()), (Some(z), Some(pa)));
            assert_eq!(Frame::Sky { zero_angle_deg: z }.onto_sky(&e), e);
        }
    }

    /// The rotation against nalgebra's `R v` and `R C R^T`: the invariants (trace,
    /// determinant, P) hold, a 90 deg turn of chi negates (q, u), and chi moves by the turn.
    #[test]
    fn rotation_is_r_c_rt() {
        let e = Qu::new(0.03, -0.01, 4e-6, 9e-6, 1e-6);
        for dchi in [0.3, -1.1, 2.0, FRAC_PI_2] {
            let r = e.rotated(dchi);
            let m = Matrix2::new((2.0 * dchi).cos(), -(2.0 * dchi).sin(), (2.0 * dchi).sin(), (2.0 * dchi).cos());
            let v = m * Vector2::new(e.q, e.u);
            let c = m * Matrix2::new(e.var_q, e.cov_qu, e.cov_qu, e.var_u) * m.transpose();
            assert!((r.q - v[0]).abs() < 1e-17 && (r.u - v[1]).abs() < 1e-17);
            assert!((r.var_q - c[(0, 0)]).abs() < 1e-21 && (r.var_u - c[(1, 1)]).abs() < 1e-21);
            assert!((r.cov_qu - c[(0, 1)]).abs() < 1e-21);
            let (p0, c0) = e.p_chi();
            let (p1, c1) = r.p_chi();
            assert!((p1 - p0).abs() < 1e-15);
            let d = (c1 - c0 - dchi).rem_euclid(PI);
            assert!(d.min(PI - d) < 1e-12, "{dchi}");
        }
        let h = e.rotated(FRAC_PI_2);
        assert!((h.q + e.q).abs() < 1e-17 && (h.u + e.u).abs() < 1e-17 && (h.cov_qu - e.cov_qu).abs() < 1e-21);
        assert_eq!(e.rotated(0.0), e);
    }

    /// eq:sigp and eq:sigchi against a numerical propagation (central differences of P and chi
    /// through the covariance), and the limits: P -> 0 (the angle unconstrained, sigma_P from the
    /// mean variance) and the angle wrap (chi near 0 and near pi give the same errors).
    #[test]
    fn errors_against_numerical_propagation_and_limits() {
        let e = Qu::new(0.012, 0.005, 2.5e-7, 1.6e-7, 4e-8);
        let got = e.p_chi_with_errors();
        let h = 1e-7;
        let f = |q: f64, u: f64| Qu::new(q, u, 0.0, 0.0, 0.0).p_chi();
        let dp =
            [(f(e.q + h, e.u).0 - f(e.q - h, e.u).0) / (2.0 * h), (f(e.q, e.u + h).0 - f(e.q, e.u - h).0) / (2.0 * h)];
        let dc =
            [(f(e.q + h, e.u).1 - f(e.q - h, e.u).1) / (2.0 * h), (f(e.q, e.u + h).1 - f(e.q, e.u - h).1) / (2.0 * h)];
        let var = |d: [f64; 2]| d[0] * d[0] * e.var_q + d[1] * d[1] * e.var_u + 2.0 * d[0] * d[1] * e.cov_qu;
        assert!((got.sigma_p / var(dp).sqrt() - 1.0).abs() < 1e-6, "{got:?}");
        assert!((got.sigma_chi / var(dc).sqrt() - 1.0).abs() < 1e-6, "{got:?}");

        let z = Qu::new(0.0, 0.0, 1e-6, 3e-6, 0.0).p_chi_with_errors();
        assert_eq!((z.p, z.chi), (0.0, 0.0));
        assert!((z.sigma_p - 2e-6f64.sqrt()).abs() < 1e-18);
        assert_eq!(z.sigma_chi, SIGMA_CHI_UNCONSTRAINED);
        assert!((SIGMA_CHI_UNCONSTRAINED - PI / 12f64.sqrt()).abs() < 1e-16);

        let near0 = Qu::new(0.01, 1e-9, 1e-6, 1e-6, 0.0).p_chi_with_errors();
        let nearpi = Qu::new(0.01, -1e-9, 1e-6, 1e-6, 0.0).p_chi_with_errors();
        assert!(near0.chi < 1e-6 && PI - nearpi.chi < 1e-6);
        assert!((near0.sigma_chi - nearpi.sigma_chi).abs() < 1e-15);
        // SNR -> infinity: the errors vanish with the covariance.
        // An unknown variance stays unknown; a rounding-negative one is no error.
        assert!(Qu::new(0.0, 0.0, f64::NAN, -1e-30, 0.0).sigma_q().is_nan());
        assert_eq!(Qu::new(0.0, 0.0, f64::NAN, -1e-30, 0.0).sigma_u(), 0.0);
        assert_eq!(Qu::from_sigmas(0.0, 0.0, 3e-3, 4e-3, 0.0).sigma_u(), 4e-3);
        let exact = Qu::new(0.01, 0.02, 0.0, 0.0, 0.0).p_chi_with_errors();
        assert_eq!((exact.sigma_p, exact.sigma_chi), (0.0, 0.0));
    }

    /// `J C J^T` against nalgebra for a general (non-orthogonal) map.
    #[test]
    fn sandwich_is_j_c_jt() {
        let j = [[1.3, -0.2], [0.7, 0.9]];
        let (a, b, c) = (4e-6, 9e-6, -2e-6);
        let (vq, vu, cv) = sandwich(&j, a, b, c);
        let jm = Matrix2::new(j[0][0], j[0][1], j[1][0], j[1][1]);
        let cm = jm * Matrix2::new(a, c, c, b) * jm.transpose();
        assert!((vq - cm[(0, 0)]).abs() < 1e-20 && (vu - cm[(1, 1)]).abs() < 1e-20 && (cv - cm[(0, 1)]).abs() < 1e-20);
    }
}
