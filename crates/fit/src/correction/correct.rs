//! Applying a calibration: from a measured `(Q/I, U/I)` at a field position to the intrinsic
//! `(Q0/I0, U0/I0)` of the source, with the measurement's and the calibration's uncertainties
//! propagated.
//!
//! # What is inverted
//!
//! The pre-analyzer optics act on the sky's Stokes vector as the partial polarizer
//! `M_I(p, phi)` (`eq:instpol`, [`mueller::partial_polarizer`]): `S1 = M_I S0`. The measurement
//! gives the normalized `m = (q1, u1) = (Q1/I1, U1/I1)`; the instrumental polarization at the
//! position comes from a [`FieldModel`] as `a = (qi, ui) = p (cos 2phi, sin 2phi)`. The exact
//! correction is `S0 ∝ M_I^-1 (1, q1, u1)`, renormalized by `I0` (the `1 / (1 + p)` factor and
//! the unknown `I1` cancel). [`invert_exact_matrix`] does exactly that with nalgebra; the hot
//! path ([`invert_exact`]) uses its closed form, obtained by turning to the frame of `phi`, where
//! `M_I ∝ [[1, p, 0], [p, 1, 0], [0, 0, 1 - p]]`:
//!
//! ```text
//! v0 = [ (1 + p) m - a - (n·m) a ] / (1 - a·m),      n = a / p,
//! ```
//!
//! (the component of `m` along `n` transforms as `(m∥ - p) / (1 - p m∥)`, the perpendicular one
//! as `(1 + p) m⊥ / (1 - p m∥)`). The two are checked against each other in the tests. The
//! first-order form `eq:approx` is `v0 = m - a` ([`invert_first_order`]); the two differ at
//! second order, by terms of size `p P0` and `p^2`.
//!
//! # Uncertainties
//!
//! The corrected covariance is the linear propagation, by the analytic Jacobian of the exact map
//! ([`exact_jacobian`], checked against finite differences in the tests), of two independent
//! covariances: the measurement's `(sigma_q, sigma_u, cov)` and the calibration's own
//! `(var_q, var_u, cov_qu)` of the instrumental `(qi, ui)` at that position (the fit's coefficient
//! covariance or the map's interpolation error, as the model reports it):
//! `C0 = Jm Cm Jm^T + Ja Ca Ja^T`. For `eq:approx`, `Jm = I`, `Ja = -I`.
//! `M_I` depends on `p = |a|`, which is not differentiable at `a = 0`; there the terms that carry
//! the direction `n` (of size `|m|`) are left out, which is their average over directions.
//!
//! # Outside the calibrated field
//!
//! A position where [`FieldModel::contains`] is false is an error ([`Error::OutsideField`]),
//! unless extrapolation is allowed; then the model is still evaluated, the result is flagged
//! `extrapolated`, and the calibration covariance is inflated by adding `(f p)^2` to both
//! `var_q` and `var_u`, where `f` = [`CorrectOptions::extrapolation_rel_error`] (default 0.5):
//! an extrapolated polynomial (its `r^3` term grows fastest exactly there) or a map beyond its
//! hull is trusted to half its own size, in amplitude and (through `f / 2` rad) in angle.
//!
//! # The HWP chromatic zero angle, and the order of the two corrections
//!
//! A plate whose zero sits off by `chi_offset / 2` makes every measured chi smaller by
//! `chi_offset` (see [`mueller::Hwp`]): the reduction sees the light *at the plate*, rotated.
//! The light at the plate is `M_I S0`, and `M_I` acts in the sky frame. So the zero angle is
//! undone first (`chi -> chi + chi_offset`, i.e. `(q1, u1)` rotated by `2 chi_offset`), giving
//! `S1` in the frame where `M_I` and the calibration live, and `M_I` is inverted second. The
//! other order would amount to using `phi - chi_offset` for the instrumental angle. This
//! presumes the calibration's `(p, phi)` were measured in the sky frame too, i.e. from data that
//! had their zero angle corrected before the sky-field solution. The test
//! `forward_model_with_hwp_offset_round_trip` runs the full dual-beam forward model
//! (`M_I`, then a plate with a zero-angle offset) and recovers the sky exactly.

use crate::models::model::{FieldModel, InstPol};
use mueller::{Frame, Qu};

/// Errors of the correction; each names the position or the input that was wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    #[error("position ({x}, {y}) arcmin is outside the calibrated field (allow extrapolation to correct it with an inflated error)")]
    OutsideField { x: f64, y: f64 },
    #[error("{what} = {value} is not a finite number")]
    NonFinite { what: &'static str, value: f64 },
    #[error("{what} is too large: its square overflows (errors of q, u are fractions, below 1)")]
    TooLarge { what: &'static str },
    #[error("{what} = {value} is negative")]
    Negative { what: &'static str, value: f64 },
    #[error("cov_qu = {cov_qu} is larger than sigma_q sigma_u = {sigma_q} x {sigma_u}: not a covariance (|cov_qu| <= sigma_q sigma_u; cov_qu is a covariance, not a correlation coefficient)")]
    NotACovariance { cov_qu: f64, sigma_q: f64, sigma_u: f64 },
    #[error("P = hypot(q, u) = {p} +- {sigma_p} is more than fully polarized (P <= 1, eq:poldeg): are q, u in percent? they are fractions")]
    AboveOne { p: f64, sigma_p: f64 },
    #[error(
        "the calibration gives an unphysical instrumental polarization p = {p} (must be < 1) at ({x}, {y}) arcmin"
    )]
    Unphysical { p: f64, x: f64, y: f64 },
    #[error("measured (q, u) = ({q}, {u}) cannot come through the instrumental polarization (qi, ui) = ({qi}, {ui}): 1 - qi q - ui u = {d} <= 0")]
    Singular { q: f64, u: f64, qi: f64, ui: f64, d: f64 },
    #[error("the calibration has no value at ({x}, {y}) arcmin (outside its map or hull)")]
    NoModelValue { x: f64, y: f64 },
    /// A Mueller-field calibration ([`crate::mueller_field::cal`]) has no exact inverse here.
    #[error("{0}")]
    Mueller(String),
    /// The whole chain of a file's several field elements could not be inverted here
    /// ([`crate::correction::chain::Chain::with_elements`]).
    #[error("the chain of the file's field elements: {0}")]
    Chain(String),
    /// The telescope step of the chain failed here ([`crate::telescope::cal::correct_chain`]).
    #[error("telescope: {0}")]
    Telescope(String),
    #[error("row {row}: {source}")]
    Row { row: usize, source: Box<Error> },
    #[error("batch lengths differ: {inputs} inputs, {outputs} output slots")]
    Length { inputs: usize, outputs: usize },
}

/// Which inversion of `eq:instpol` to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Exact inversion of `M_I` (`eq:instpol`).
    #[default]
    Exact,
    /// The first-order form `eq:approx`: `q0 = q1 - p cos 2phi`, `u0 = u1 - p sin 2phi`.
    FirstOrder,
}

/// Options of a [`Corrector`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CorrectOptions {
    pub method: Method,
    /// Correct positions outside the calibrated field (flagged, with inflated errors) instead
    /// of failing.
    pub allow_extrapolation: bool,
    /// `f` of the inflation rule: outside the field, `(f p)^2` is added to the calibration's
    /// `var_q` and `var_u` (fraction; default 0.5).
    pub extrapolation_rel_error: f64,
    /// The HWP zero angle (deg) of the sky frame the model lives in (its calibration's
    /// `hwp_chi_offset_deg`): each measurement is turned into that frame from its own
    /// ([`mueller::Frame::turn_to`]).
    pub zero_angle_deg: f64,
}

impl Default for CorrectOptions {
    fn default() -> Self {
        Self { method: Method::Exact, allow_extrapolation: false, extrapolation_rel_error: 0.5, zero_angle_deg: 0.0 }
    }
}

impl CorrectOptions {
    /// The defaults with the HWP zero angle of a calibration file (its filter's offset).
    pub fn for_calibration(cal: &crate::Calibration) -> Self {
        Self { zero_angle_deg: cal.hwp_chi_offset_deg, ..Self::default() }
    }
}

/// A field model with an extra, position-independent model error: `sigma^2` added to
/// `var_q` and `var_u`. Use it to count the scatter of the data about a smooth fit (the
/// calibration's RMS residual, ~0.05% for FORS1 V and I in section `sec:fors1`) when the
/// question is how well the model predicts one new position (validation), not only how well
/// its coefficients are known.
pub struct WithModelError<'a, M: FieldModel + ?Sized> {
    pub model: &'a M,
    pub sigma: f64,
}

impl<M: FieldModel + ?Sized> FieldModel for WithModelError<'_, M> {
    #[inline]
    fn eval(&self, x: f64, y: f64) -> InstPol {
        let mut a = self.model.eval(x, y);
        let v = self.sigma * self.sigma;
        a.var_q += v;
        a.var_u += v;
        a
    }
    #[inline]
    fn contains(&self, x: f64, y: f64) -> bool {
        self.model.contains(x, y)
    }
}

/// A measurement to correct: position in arcmin from the detector centre, the measured
/// normalized Stokes parameters with their covariance (fractions), and the frame they are in
/// (at the plate, or in the sky's with the zero angle they carry): a correction turns it into
/// its model's frame from there, so that no value is taken in the wrong frame or turned twice.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Measurement {
    pub x: f64,
    pub y: f64,
    #[serde(flatten)]
    pub qu: Qu,
    pub frame: Frame,
}

impl Measurement {
    /// `(q, u)` as the plate measured them, at `(x, y)` arcmin, with 1-sigma errors and a
    /// covariance as tables give them.
    pub fn at_plate(x: f64, y: f64, q: f64, u: f64, sigma_q: f64, sigma_u: f64, cov_qu: f64) -> Self {
        Self { x, y, qu: Qu::from_sigmas(q, u, sigma_q, sigma_u, cov_qu), frame: Frame::Plate }
    }

    /// `qu`, in `frame`, at `(x, y)` arcmin.
    pub fn at(x: f64, y: f64, qu: Qu, frame: Frame) -> Self {
        Self { x, y, qu, frame }
    }

    /// This measurement in the sky frame of a plate of zero angle `zero_angle_deg`
    /// ([`Frame::to_sky`]): itself, bit for bit, when it is in that frame already.
    pub fn in_sky(&self, zero_angle_deg: f64) -> Self {
        Self { qu: self.frame.to_sky(&self.qu, zero_angle_deg), frame: Frame::Sky { zero_angle_deg }, ..*self }
    }

    /// This measurement as the instrument sees it: one in the celestial frame turned back by
    /// its position angle into the sky frame of its zero angle ([`Frame::in_instrument`]), any
    /// other itself.
    pub fn in_instrument(&self) -> Self {
        match self.frame.zero_angle_deg().filter(|_| self.frame.position_angle_deg().is_some()) {
            Some(z) => self.in_sky(z),
            None => *self,
        }
    }
}

/// The intrinsic polarization of a source after correction.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Corrected {
    /// `Q0/I0`, `U0/I0` (fractions) and their covariance.
    pub q0: f64,
    pub u0: f64,
    pub var_q0: f64,
    pub var_u0: f64,
    pub cov_qu0: f64,
    /// `P0 = hypot(q0, u0)` (fraction, not bias-corrected) and its linearized error.
    pub p0: f64,
    pub sigma_p0: f64,
    /// `chi0` in [0, pi) (rad) and its linearized error (rad), capped at `pi / sqrt(12)`, the
    /// standard deviation of an angle that is not constrained at all.
    pub chi0: f64,
    pub sigma_chi0: f64,
    /// The instrumental polarization that was removed, with the covariance used (inflated when
    /// extrapolated).
    pub inst: InstPol,
    /// True when the position lay outside the calibrated field.
    pub extrapolated: bool,
}

/// The names of [`Corrected::output_values`], in order. Angles in degrees, the rest fractions.
/// The columns a correction writes are [`output_columns`]: these with the estimator's.
pub const OUTPUT_NAMES: [&str; 11] =
    ["q0", "u0", "sigma_q0", "sigma_u0", "cov_qu0", "p0", "sigma_p0", "chi0_deg", "sigma_chi0_deg", "q_inst", "u_inst"];

/// Where the estimator's `p0_<name>` goes among [`OUTPUT_NAMES`]: after `sigma_chi0_deg`,
/// beside the other values of `P0`, before the instrumental `q_inst, u_inst`.
pub(crate) const ESTIMATE_AT: usize = 9;

/// The flag column that follows the [`output_columns`]: 1 where the position lay outside the
/// calibrated field.
pub const EXTRAPOLATED_COLUMN: &str = "extrapolated";

/// The one list of the numeric columns a correction of rows writes, in order: the columns
/// `instpol correct` appends to a table (then [`EXTRAPOLATED_COLUMN`]) and the keys of the
/// Python `Calibration.correct`. [`OUTPUT_NAMES`] with, when `est` is given, the
/// bias-corrected `p0_<name>` ([`Corrected::p0_estimate`]) after `sigma_chi0_deg`; the
/// values of a row are [`Corrected::output_row`].
pub fn output_columns(est: Option<stokes::stats::Estimator>) -> Vec<String> {
    let mut v: Vec<String> = OUTPUT_NAMES.iter().map(|s| s.to_string()).collect();
    if let Some(e) = est {
        v.insert(ESTIMATE_AT, format!("p0_{}", e.name()));
    }
    v
}

/// Whether a table's column `name` (any case) would be overwritten by the columns a
/// correction appends (with any estimator's).
pub fn is_output_column(name: &str) -> bool {
    let l = name.trim().to_ascii_lowercase();
    OUTPUT_NAMES.contains(&l.as_str()) || l.starts_with("p0_") || l == EXTRAPOLATED_COLUMN
}

impl Corrected {
    /// A correction from its `(q0, u0)` and their covariance (`qu`), with `P`, `chi` and their
    /// errors derived from them ([`p_chi_with_errors`]), the instrumental `inst` it removed and
    /// whether the position was `extrapolated`: what every correction path ends in.
    pub fn of(qu: Qu, inst: Qu, extrapolated: bool) -> Self {
        let (p0, sigma_p0, chi0, sigma_chi0) = p_chi_with_errors(qu.q, qu.u, qu.var_q, qu.var_u, qu.cov_qu);
        Corrected {
            q0: qu.q,
            u0: qu.u,
            var_q0: qu.var_q,
            var_u0: qu.var_u,
            cov_qu0: qu.cov_qu,
            p0,
            sigma_p0,
            chi0,
            sigma_chi0,
            inst,
            extrapolated,
        }
    }

    /// This correction turned by `deg` (added to `chi0`, `eq:polang`): `q0, u0` with their
    /// covariance, `chi0` and the instrumental `q, u` removed ([`Qu::rotated`]). Itself, bit
    /// for bit, for a turn of 0.
    pub fn turned(&self, deg: f64) -> Self {
        if deg == 0.0 {
            return *self;
        }
        let t = Qu::new(self.q0, self.u0, self.var_q0, self.var_u0, self.cov_qu0).rotated(deg.to_radians());
        Corrected {
            q0: t.q,
            u0: t.u,
            var_q0: t.var_q,
            var_u0: t.var_u,
            cov_qu0: t.cov_qu,
            chi0: mueller::fold_pi(self.chi0 + deg.to_radians()),
            inst: self.inst.rotated(deg.to_radians()),
            ..*self
        }
    }

    /// The values written for a corrected row, named by [`OUTPUT_NAMES`]: errors as standard
    /// deviations, angles in degrees, the instrumental `q, u` that was removed.
    #[inline]
    pub fn output_values(&self) -> [f64; 11] {
        [
            self.q0,
            self.u0,
            self.var_q0.sqrt(),
            self.var_u0.sqrt(),
            self.cov_qu0,
            self.p0,
            self.sigma_p0,
            self.chi0.to_degrees(),
            self.sigma_chi0.to_degrees(),
            self.inst.q,
            self.inst.u,
        ]
    }

    /// The values of one row under the names of [`output_columns`] with the same `est`.
    pub fn output_row(&self, est: Option<stokes::stats::Estimator>) -> Vec<f64> {
        let mut v = self.output_values().to_vec();
        if let Some(e) = est {
            v.insert(ESTIMATE_AT, self.p0_estimate(e));
        }
        v
    }

    /// The bias-corrected `P0` with `est` (section `sec:bias`) from the corrected `(q0, u0)`
    /// and their errors; NaN when the errors are not usable (e.g. zero). The `p0_<name>` column
    /// of `instpol correct` and of the Python `Calibration.correct`.
    pub fn p0_estimate(&self, est: stokes::stats::Estimator) -> f64 {
        match stokes::stats::PolMeasurement::new(self.q0, self.u0, self.var_q0.sqrt(), self.var_u0.sqrt()) {
            Ok(m) => est.estimate(&m).value,
            Err(_) => f64::NAN,
        }
    }
}

/// Rotate normalized Stokes parameters for a polarization-angle change of `+offset` (rad):
/// `chi -> chi + offset` ([`Qu::rotated`] of an exact value).
#[inline]
pub fn rotate_chi(q: f64, u: f64, offset: f64) -> (f64, f64) {
    let r = Qu::new(q, u, 0.0, 0.0, 0.0).rotated(offset);
    (r.q, r.u)
}

/// Exact inversion of `eq:instpol` by nalgebra: `S0 ∝ M_I(p, phi)^-1 (1, q1, u1, 0)`,
/// renormalized by `I0`. The reference for [`invert_exact`]; slower (a 4x4 inverse per call).
pub fn invert_exact_matrix(p: f64, phi: f64, q1: f64, u1: f64) -> Result<(f64, f64), Error> {
    if !(p < 1.0) {
        return Err(Error::Unphysical { p, x: f64::NAN, y: f64::NAN });
    }
    let m = mueller::partial_polarizer(p, phi);
    let inv = m.try_inverse().ok_or(Error::Unphysical { p, x: f64::NAN, y: f64::NAN })?;
    let s0 = inv * mueller::stokes_qu(1.0, q1, u1);
    if !(s0[0] > 0.0) {
        let (qi, ui) = (p * (2.0 * phi).cos(), p * (2.0 * phi).sin());
        return Err(Error::Singular { q: q1, u: u1, qi, ui, d: 1.0 - qi * q1 - ui * u1 });
    }
    Ok((s0[1] / s0[0], s0[2] / s0[0]))
}

/// The shared start of [`invert_exact`] and [`exact_jacobian`]: `p = |(qi, ui)|`,
/// `am = qi q1 + ui u1` and the denominator `d = 1 - am` of the inverse, refused when `M_I` is
/// not physical (`p >= 1`) or the measurement cannot come from it (`d <= 0`).
#[inline]
fn p_and_denominator(qi: f64, ui: f64, q1: f64, u1: f64) -> Result<(f64, f64, f64), Error> {
    let p = (qi * qi + ui * ui).sqrt();
    if !(p < 1.0) {
        return Err(Error::Unphysical { p, x: f64::NAN, y: f64::NAN });
    }
    let am = qi * q1 + ui * u1;
    let d = 1.0 - am;
    if !(d > 0.0) {
        return Err(Error::Singular { q: q1, u: u1, qi, ui, d });
    }
    Ok((p, am, d))
}

/// Exact inversion of `eq:instpol` in closed form: intrinsic `(q0, u0)` from measured
/// `(q1, u1)` and the instrumental `(qi, ui) = p (cos 2phi, sin 2phi)`.
///
/// ```
/// use fit::correction::correct::invert_exact;
/// // Along the instrument's axis eq:instpol gives m = (P0 + p)/(1 + p P0); inverted:
/// // P0 = (m - p)/(1 - p m). p = 1 %, measured 3 %: P0 = 0.02 / 0.9997.
/// let (q0, u0) = invert_exact(0.01, 0.0, 0.03, 0.0).unwrap();
/// assert!((q0 - 0.02 / 0.9997).abs() < 1e-15 && u0.abs() < 1e-18);
/// ```
#[inline]
pub fn invert_exact(qi: f64, ui: f64, q1: f64, u1: f64) -> Result<(f64, f64), Error> {
    let (p, am, d) = p_and_denominator(qi, ui, q1, u1)?;
    // (n·m) a = (a·m) a / p; zero when p = 0.
    let k = if p > 0.0 { am / p } else { 0.0 };
    let inv_d = 1.0 / d;
    Ok((((1.0 + p) * q1 - qi - k * qi) * inv_d, ((1.0 + p) * u1 - ui - k * ui) * inv_d))
}

/// The first-order correction `eq:approx`: `q0 = q1 - p cos 2phi`, `u0 = u1 - p sin 2phi`.
///
/// ```
/// // eq:approx: the instrumental (q, u) subtracted.
/// let (q0, u0) = fit::correction::correct::invert_first_order(0.01, 0.002, 0.03, -0.004);
/// assert!((q0 - 0.02).abs() < 1e-17 && (u0 + 0.006).abs() < 1e-17);
/// ```
#[inline]
pub fn invert_first_order(qi: f64, ui: f64, q1: f64, u1: f64) -> (f64, f64) {
    (q1 - qi, u1 - ui)
}

/// The exact correction with its Jacobians: returns `(q0, u0)`, `Jm = d(q0, u0)/d(q1, u1)` and
/// `Ja = d(q0, u0)/d(qi, ui)` (row-major 2x2). See the module docs for the formulas.
#[inline]
pub fn exact_jacobian(qi: f64, ui: f64, q1: f64, u1: f64) -> Result<((f64, f64), [[f64; 2]; 2], [[f64; 2]; 2]), Error> {
    let (p, _, d) = p_and_denominator(qi, ui, q1, u1)?;
    let (nq, nu) = if p > 0.0 { (qi / p, ui / p) } else { (0.0, 0.0) };
    let nm = nq * q1 + nu * u1;
    let inv_d = 1.0 / d;
    let q0 = ((1.0 + p) * q1 - qi - nm * qi) * inv_d;
    let u0 = ((1.0 + p) * u1 - ui - nm * ui) * inv_d;
    // Jm = [(1 + p) I - p n n^T + v0 a^T] / d
    let jm = [
        [((1.0 + p) - p * nq * nq + q0 * qi) * inv_d, (-p * nq * nu + q0 * ui) * inv_d],
        [(-p * nu * nq + u0 * qi) * inv_d, ((1.0 + p) - p * nu * nu + u0 * ui) * inv_d],
    ];
    // Ja = [m n^T - n m^T - I - (n·m)(I - n n^T) + v0 m^T] / d
    let ja = [
        [(-1.0 - nm * (1.0 - nq * nq) + q0 * q1) * inv_d, (q1 * nu - nq * u1 + nm * nq * nu + q0 * u1) * inv_d],
        [(u1 * nq - nu * q1 + nm * nu * nq + u0 * q1) * inv_d, (-1.0 - nm * (1.0 - nu * nu) + u0 * u1) * inv_d],
    ];
    Ok(((q0, u0), jm, ja))
}

/// `P`, `chi` of `(q, u)` with their linearized errors (`eq:sigp`, `eq:sigchi` generalized to a
/// full covariance): [`Qu::p_chi_with_errors`], as a tuple `(P, sigma_P, chi, sigma_chi)`.
#[inline]
pub fn p_chi_with_errors(q: f64, u: f64, vq: f64, vu: f64, c: f64) -> (f64, f64, f64, f64) {
    let e = Qu::new(q, u, vq, vu, c).p_chi_with_errors();
    (e.p, e.sigma_p, e.chi, e.sigma_chi)
}

/// Refuse a measurement with a non-finite position or value, or a non-finite or negative
/// error, naming the input.
#[inline]
pub(crate) fn check_measurement(m: &Measurement) -> Result<(), Error> {
    for (what, v) in [("x", m.x), ("y", m.y), ("q", m.qu.q), ("u", m.qu.u), ("cov_qu", m.qu.cov_qu)] {
        if !v.is_finite() {
            return Err(Error::NonFinite { what, value: v });
        }
    }
    // The errors are held as variances; a negative error is held as a negative variance
    // (`Qu::from_sigmas`) and a square that overflowed as infinity: both refused here, with the
    // error's own value where it is known.
    for (what, v) in [("sigma_q", m.qu.var_q), ("sigma_u", m.qu.var_u)] {
        if !v.is_finite() {
            if v.is_nan() {
                return Err(Error::NonFinite { what, value: v });
            }
            return Err(Error::TooLarge { what });
        }
        if v < 0.0 {
            return Err(Error::Negative { what, value: -(-v).sqrt() });
        }
    }
    match m.qu.unphysical() {
        None => Ok(()),
        Some(mueller::qu::Unphysical::Covariance) => {
            Err(Error::NotACovariance { cov_qu: m.qu.cov_qu, sigma_q: m.qu.sigma_q(), sigma_u: m.qu.sigma_u() })
        }
        Some(mueller::qu::Unphysical::AboveOne { p, sigma_p }) => Err(Error::AboveOne { p, sigma_p }),
    }
}

/// Applies one calibration to many measurements: build it once, then call
/// [`correct`](Self::correct) or [`correct_batch`](Self::correct_batch) as often as needed;
/// nothing is re-read and nothing is allocated per call.
///
/// `M` is any [`FieldModel`] (a concrete type for static dispatch in hot loops, or
/// `dyn FieldModel`).
///
/// ```
/// use fit::correction::correct::{CorrectOptions, Corrector, Measurement};
/// use fit::models::model::{FieldModel, InstPol};
///
/// /// A uniform 1% instrumental polarization along 0 deg over a 4' x 4' field.
/// struct Flat;
/// impl FieldModel for Flat {
///     fn eval(&self, _x: f64, _y: f64) -> InstPol {
///         InstPol { q: 0.01, u: 0.0, var_q: 1e-8, var_u: 1e-8, cov_qu: 0.0 }
///     }
///     fn contains(&self, x: f64, y: f64) -> bool { x.abs() <= 2.0 && y.abs() <= 2.0 }
/// }
///
/// let c = Corrector::new(&Flat, CorrectOptions::default());
/// let m = Measurement::at_plate(1.0, -0.5, 0.01, 0.0, 1e-4, 1e-4, 0.0);
/// let r = c.correct(&m).unwrap();
/// assert!(r.p0 < 1e-12); // an unpolarized star seen through the instrument
/// assert!(c.correct(&Measurement { x: 3.0, ..m }).is_err()); // outside the field
/// ```
pub struct Corrector<'a, M: FieldModel + ?Sized> {
    model: &'a M,
    opts: CorrectOptions,
    /// `cos, sin` of twice the turn of a measurement at the plate into the model's frame,
    /// computed once: most rows of a batch share that frame.
    plate_turn: (f64, f64),
}

impl<'a, M: FieldModel + ?Sized> Corrector<'a, M> {
    /// Prepare a corrector for `model` (precomputes the zero-angle rotation of values at the
    /// plate).
    pub fn new(model: &'a M, opts: CorrectOptions) -> Self {
        let (s, c) = (2.0 * opts.zero_angle_deg.to_radians()).sin_cos();
        Self { model, opts, plate_turn: (c, s) }
    }

    /// `m`'s `(q, u)` in the model's frame ([`Frame::to_sky`]; the rotation of a value at the
    /// plate computed once).
    #[inline]
    fn in_model_frame(&self, m: &Measurement) -> Qu {
        match m.frame {
            Frame::Plate => m.qu.rotated_cos_sin(self.plate_turn.0, self.plate_turn.1),
            f => f.to_sky(&m.qu, self.opts.zero_angle_deg),
        }
    }

    /// The options in use.
    pub fn options(&self) -> &CorrectOptions {
        &self.opts
    }

    /// The field model it corrects with.
    pub fn model(&self) -> &'a M {
        self.model
    }

    /// The instrumental polarization that would be removed at `(x, y)` arcmin, with the
    /// covariance as used (inflated outside the field) and the extrapolation flag.
    #[inline]
    pub fn instrumental(&self, x: f64, y: f64) -> Result<(InstPol, bool), Error> {
        let inside = self.model.contains(x, y);
        if !inside && !self.opts.allow_extrapolation {
            return Err(Error::OutsideField { x, y });
        }
        let mut a = self.model.eval(x, y);
        if !(a.q.is_finite() && a.u.is_finite() && a.var_q.is_finite() && a.var_u.is_finite()) {
            // A map cannot be extrapolated beyond its data: nothing to inflate.
            return Err(Error::NoModelValue { x, y });
        }
        if !inside {
            let f = self.opts.extrapolation_rel_error;
            let add = f * f * (a.q * a.q + a.u * a.u);
            a.var_q += add;
            a.var_u += add;
        }
        Ok((a, !inside))
    }

    /// Correct one measurement (`eq:instpol` inverted, or `eq:approx`), zero angle first.
    #[inline]
    pub fn correct(&self, m: &Measurement) -> Result<Corrected, Error> {
        check_measurement(m)?;
        let (a, extrapolated) = self.instrumental(m.x, m.y)?;
        // Zero angle first: M_I lives in the sky frame; the measurement says its own.
        let Qu { q: q1, u: u1, var_q: vq1, var_u: vu1, cov_qu: cv1 } = self.in_model_frame(m);
        let (q0, u0, vq0, vu0, cv0) = match self.opts.method {
            Method::Exact => {
                let ((q0, u0), jm, ja) = exact_jacobian(a.q, a.u, q1, u1).map_err(|e| match e {
                    Error::Unphysical { p, .. } => Error::Unphysical { p, x: m.x, y: m.y },
                    e => e,
                })?;
                let (aq, au, ac) = mueller::sandwich(&jm, vq1, vu1, cv1);
                let (bq, bu, bc) = mueller::sandwich(&ja, a.var_q, a.var_u, a.cov_qu);
                (q0, u0, aq + bq, au + bu, ac + bc)
            }
            Method::FirstOrder => {
                let (q0, u0) = invert_first_order(a.q, a.u, q1, u1);
                (q0, u0, vq1 + a.var_q, vu1 + a.var_u, cv1 + a.cov_qu)
            }
        };
        Ok(Corrected::of(Qu::new(q0, u0, vq0, vu0, cv0), a, extrapolated))
    }

    /// Correct a batch into `out` (same length). Stops at the first bad row with an error that
    /// names the row (0-based). Returns the number of extrapolated rows.
    pub fn correct_batch(&self, inputs: &[Measurement], out: &mut [Corrected]) -> Result<usize, Error> {
        if inputs.len() != out.len() {
            return Err(Error::Length { inputs: inputs.len(), outputs: out.len() });
        }
        let mut n_extra = 0;
        for (row, (m, o)) in inputs.iter().zip(out.iter_mut()).enumerate() {
            *o = self.correct(m).map_err(|e| Error::Row { row, source: Box::new(e) })?;
            n_extra += o.extrapolated as usize;
        }
        Ok(n_extra)
    }

    /// [`correct_batch`](Self::correct_batch) on all cores (rayon); the same results in the same
    /// order. On errors, the one of the lowest row is returned.
    pub fn par_correct_batch(&self, inputs: &[Measurement], out: &mut [Corrected]) -> Result<usize, Error> {
        use rayon::prelude::*;
        if inputs.len() != out.len() {
            return Err(Error::Length { inputs: inputs.len(), outputs: out.len() });
        }
        const CHUNK: usize = 4096;
        inputs
            .par_chunks(CHUNK)
            .zip(out.par_chunks_mut(CHUNK))
            .enumerate()
            .map(|(k, (i, o))| {
                self.correct_batch(i, o).map_err(|e| match e {
                    Error::Row { row, source } => Error::Row { row: row + k * CHUNK, source },
                    e => e,
                })
            })
            .collect::<Vec<_>>()
            .into_iter()
            .try_fold(0, |acc, r| r.map(|n| acc + n))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn closed_form_is_the_matrix_inverse() {
        for &(p, phi, q1, u1) in
            &[(0.0f64, 0.3f64, 0.01, -0.02), (0.05, 0.3, 0.04, 0.02), (0.3, 2.0, -0.2, 0.25), (0.9, -1.0, 0.5, 0.1)]
        {
            let (qi, ui) = (p * (2.0 * phi).cos(), p * (2.0 * phi).sin());
            let a = invert_exact(qi, ui, q1, u1).unwrap();
            let b = invert_exact_matrix(p, phi, q1, u1).unwrap();
            assert_relative_eq!(a.0, b.0, epsilon = 1e-14);
            assert_relative_eq!(a.1, b.1, epsilon = 1e-14);
        }
    }

    #[test]
    fn ideal_polarizer_is_singular() {
        assert!(matches!(invert_exact(1.0, 0.0, 0.5, 0.0), Err(Error::Unphysical { .. })));
        assert!(invert_exact_matrix(1.0, 0.0, 0.5, 0.0).is_err());
    }

    /// A measurement that no star can produce through `M_I` (1 - a.m <= 0) is an error that
    /// names the numbers, not a division by zero.
    #[test]
    fn impossible_measurement_is_singular() {
        let e = invert_exact(0.6, 0.0, 2.0, 0.0).unwrap_err();
        assert!(matches!(e, Error::Singular { .. }), "{e}");
        assert!(e.to_string().contains("(2, 0)"));
        assert!(exact_jacobian(0.6, 0.0, 2.0, 0.0).is_err());
        // P -> 1 of the instrument with a measurement along it: still finite below the limit.
        let (q0, u0) = invert_exact(0.999, 0.0, 0.9995, 0.0).unwrap();
        assert!(q0.is_finite() && u0 == 0.0 && q0 <= 1.0);
    }

    #[test]
    fn rotate_chi_adds_to_angle() {
        let (q, u) = rotate_chi(0.02 * (0.6f64).cos(), 0.02 * (0.6f64).sin(), 0.1);
        let (p, chi) = stokes::polarization(q, u);
        assert_relative_eq!(p, 0.02, epsilon = 1e-15);
        assert_relative_eq!(chi, 0.4, epsilon = 1e-14);
    }
}

/// A corrected Stokes map ([`correct_map`]) and what was done.
#[derive(Debug, Clone)]
pub struct CorrectedMap {
    /// The map with `q`, `u`, `p`, `chi` corrected and `sigma_q/u`, `cov_qu`,
    /// `sigma_q/u_phot` propagated (same layout; invalid bins untouched).
    pub map: skyfield::StokesMap,
    /// Bins corrected.
    pub n_bins: usize,
    /// Of those, bins outside the calibrated field (corrected by extrapolation, flagged).
    pub n_extrapolated: usize,
    /// Per corrected bin, in bin order: `P0` and the instrumental `p` removed.
    pub p0: Vec<f64>,
    pub p_inst: Vec<f64>,
}

/// The bin of a Stokes map that could not be corrected, and why.
#[derive(Debug, thiserror::Error)]
pub enum MapError {
    #[error("bin ({i}, {j}) at ({x:.3}, {y:.3}) arcmin: {source}")]
    Bin { i: usize, j: usize, x: f64, y: f64, source: Error },
    #[error("the Stokes map has no valid bins")]
    NoValidBins,
    /// The telescope model could not be set up for the map's exposures (before any bin).
    #[error("the exposures' telescope chain: {0}")]
    Exposures(Error),
}

/// Correct every valid bin of a Stokes map at its centre (`eq:instpol` inverted, or
/// `eq:approx`, as `opts` says): the scatter errors (`sigma_q/u`, `cov_qu`) and the
/// photon-noise errors (`sigma_q/u_phot`) are each propagated with the calibration's own
/// error. The map's instrument and filter are not checked here: the caller does (`instpol
/// correct` refuses a map of another instrument or filter, [`crate::correction::setup::same_filter`]). A
/// map that records its instrument's position angle on the sky (`SKYPA`) is corrected as the
/// instrument saw it and then turned onto the sky by that angle ([`Corrected::turned`]).
pub fn correct_map<M: FieldModel + ?Sized>(
    model: &M,
    map: &skyfield::StokesMap,
    opts: CorrectOptions,
) -> Result<CorrectedMap, MapError> {
    let cor = Corrector::new(model, opts);
    // On a rotator the corrected bin goes onto the sky by the map's position angle.
    let pa = map.sky_pa_deg.unwrap_or(0.0);
    correct_map_with(map, |m| cor.correct(m).map(|r| r.turned(pa)))
}

/// [`correct_map`] with any correction of one measurement (`correct`, e.g. the Mueller
/// field's [`crate::mueller_field::cal::MuellerCal::correct`]): every valid bin at its centre, the
/// scatter and the photon-noise errors each propagated.
pub fn correct_map_with(
    map: &skyfield::StokesMap,
    correct: impl Fn(&Measurement) -> Result<Corrected, Error> + Sync,
) -> Result<CorrectedMap, MapError> {
    use rayon::prelude::*;
    let g = &map.geometry;
    // The bins are independent: corrected in parallel (a telescope chain undone exposure by
    // exposure is a Newton solve per model and bin), then assembled in bin order, the first
    // failing bin in that order being the error, as a serial loop gives.
    let valid: Vec<usize> = (0..g.len()).filter(|&k| map.valid[k]).collect();
    let results: Vec<Result<(Corrected, Corrected), MapError>> = valid
        .par_iter()
        .map(|&k| {
            let (i, j) = (k % g.nx, k / g.nx);
            let (x, y) = g.centre_arcmin(i, j);
            let meas = Measurement::at_plate(x, y, map.q[k], map.u[k], map.sigma_q[k], map.sigma_u[k], map.cov_qu[k]);
            let bin_err = |source| MapError::Bin { i, j, x, y, source };
            let r = correct(&meas).map_err(bin_err)?;
            let rp = correct(&Measurement::at_plate(
                x,
                y,
                map.q[k],
                map.u[k],
                map.sigma_q_phot[k],
                map.sigma_u_phot[k],
                0.0,
            ))
            .map_err(bin_err)?;
            Ok((r, rp))
        })
        .collect();
    let mut m = map.clone();
    let (mut n, mut n_extra) = (0usize, 0usize);
    let mut p0s = Vec::with_capacity(valid.len());
    let mut pis = Vec::with_capacity(valid.len());
    for (&k, res) in valid.iter().zip(results) {
        let (r, rp) = res?;
        m.q[k] = r.q0;
        m.u[k] = r.u0;
        m.sigma_q[k] = r.var_q0.sqrt();
        m.sigma_u[k] = r.var_u0.sqrt();
        m.cov_qu[k] = r.cov_qu0;
        m.sigma_q_phot[k] = rp.var_q0.sqrt();
        m.sigma_u_phot[k] = rp.var_u0.sqrt();
        m.p[k] = r.p0;
        m.chi[k] = r.chi0;
        n += 1;
        n_extra += r.extrapolated as usize;
        p0s.push(r.p0);
        pis.push(r.inst.q.hypot(r.inst.u));
    }
    if n == 0 {
        return Err(MapError::NoValidBins);
    }
    Ok(CorrectedMap { map: m, n_bins: n, n_extrapolated: n_extra, p0: p0s, p_inst: pis })
}
