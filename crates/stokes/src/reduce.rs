//! Reduction of one source: from the two beam fluxes at `N` HWP angles to `Q/I`, `U/I`, `P`,
//! `chi` with errors, the Fourier harmonics, `a_0` and the Wollaston `kappa`.
//!
//! # Estimator
//!
//! - **Optimal set** (`theta_i = i pi/8`, `N` a multiple of 4): the Fourier sums `eq:Q`,
//!   `eq:U`, i.e. equal weights, *whatever the per-angle errors*. The exact cancellation of the
//!   Wollaston imbalance, of the post-analyzer term (both appear as an offset `a_0`) and of the
//!   harmonics `k != N/4` rests on the redundant positions entering with equal weights;
//!   weighting them by their (slightly unequal) errors would trade a small gain in variance for a
//!   systematic error of order `a_0` times the weight imbalance. Errors are still propagated
//!   exactly from the per-angle errors.
//! - **Any other set** (missing or uneven angles, `N = 2`): weighted least squares of
//!   `eq:system` with weights `1/sigma_F,i^2` when the `sigma_F,i` differ, plain least squares
//!   when they are equal (the two coincide then). For counts the weights depend on `F_i`
//!   only through `1 - F_i^2`, a negligible correlation for the small `P` of this use.
//!
//! The angles are taken in the order given: "optimal set" means the `i`-th angle is
//! `i pi/8`, and `kappa_j` uses positions `j - 1` and `j + 1`.
//!
//! # Errors
//!
//! `sigma_F,i` is propagated exactly from the per-beam errors
//! ([`crate::sigma_normalized_difference`]); without per-beam errors the fluxes are photon
//! counts (electrons) and `sigma = sqrt(f)`. From them: `sigma_Q`, `sigma_U`, their covariance,
//! and by linear propagation `sigma_P`, `sigma_chi` ([`Reduction::sigma_p`],
//! [`Reduction::sigma_chi`]).
//!
//! Beside them the analytic `eq:sigp` / `eq:sigchi` values use the SNR *of the intensity image
//! `f_O + f_E` of one exposure*, `SNR_i = (f_O + f_E)/sqrt(sigma_O^2 + sigma_E^2)` (for counts
//! `sqrt(f_O + f_E)`), combined over the exposures as `SNR = (mean_i SNR_i^-2)^(-1/2)`, the
//! value that makes `eq:sigp` exact for equal weights and small `P` ([`Reduction::snr`]).
//! The two agree to `O(P^2)` for counts on the optimal set.

use crate::fourier::{fourier_coefficients, Harmonic};
use crate::kappa::{correct_fluxes, kappa_estimates, KappaEstimate};
use crate::solver::{normalized_difference, polarization, sigma_normalized_difference, StokesSolver};
use crate::Error;
use mueller::Qu;
use std::fmt;

/// The fluxes of one source in the two beams at `N` HWP angles, validated.
#[derive(Debug, Clone, PartialEq)]
pub struct Measurement {
    theta: Vec<f64>,
    f_o: Vec<f64>,
    f_e: Vec<f64>,
    sigma_o: Vec<f64>,
    sigma_e: Vec<f64>,
    poisson: bool,
    /// Each exposure's plate sweep (rad) when the plate turned during it; empty: fixed.
    sweep: Vec<f64>,
}

/// Which estimator gave `Q/I`, `U/I`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Estimator {
    /// `eq:Q`, `eq:U` on the optimal set (equal weights).
    FourierSums,
    /// Unweighted least squares of `eq:system` (equal errors).
    LeastSquares,
    /// Least squares weighted by `1/sigma_F^2`.
    WeightedLeastSquares,
}

/// Something the caller should know about a reduction that still produced numbers.
#[derive(Debug, Clone, PartialEq)]
pub enum Warning {
    /// `N = 2`: nothing is redundant.
    TwoAngles,
    /// Not the optimal set: no Fourier analysis.
    FourierSkipped { n: usize },
    /// Fewer than 4 angles: no `kappa` from the data.
    KappaNeedsFour { n: usize },
    /// Angles present but no pair `pi/4` apart in consecutive-but-one positions.
    KappaNoPairs,
    /// `kappa_j` clamped: data inconsistent with `eq:kappa` (negative beam flux).
    KappaClamped { j: usize, g: f64 },
    /// `|F_i| > 1`: one beam flux is negative.
    NegativeBeam { index: usize, f: f64 },
    /// `P = 0` (to rounding): `chi` is reported but has no meaning.
    ChiUndefined,
    /// `P` below its error: `P` is biased high and `chi` poorly defined.
    LowSignificance { p: f64, sigma_p: f64 },
    /// Some `sigma_F` are zero and others are not: equal weights used.
    ZeroErrors,
}

impl fmt::Display for Warning {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Warning::TwoAngles => write!(
                f,
                "N = 2: the Wollaston imbalance (t, kappa) and the post-analyzer polarization are not cancelled \
                 (they need redundant positions, N >= 4); P and chi may be biased"
            ),
            Warning::FourierSkipped { n } => write!(
                f,
                "the {n} HWP angles are not the optimal set theta_i = i*22.5 deg with N a multiple of 4: \
                 Fourier analysis skipped"
            ),
            Warning::KappaNeedsFour { n } => {
                write!(f, "kappa from the data needs N >= 4 HWP angles (N = {n}); none estimated")
            }
            Warning::KappaNoPairs => {
                write!(f, "no HWP angles 45 deg apart two positions apart: kappa not estimated")
            }
            Warning::KappaClamped { j, g } => write!(
                f,
                "kappa_{j}: |g| = {:.4} < 1 is inconsistent with eq:kappa (a negative beam flux?); clamped",
                g.abs()
            ),
            Warning::NegativeBeam { index, f: v } => {
                write!(f, "|F| = {:.4} > 1 at HWP angle index {index}: one beam flux is negative", v.abs())
            }
            Warning::ChiUndefined => write!(f, "P = 0 (to rounding): the polarization angle is undefined"),
            Warning::LowSignificance { p, sigma_p } => write!(
                f,
                "P = {:.3e} is below its error {:.3e}: P is biased high and chi is poorly defined",
                p, sigma_p
            ),
            Warning::ZeroErrors => write!(f, "some flux errors are zero and others not: equal weights used"),
        }
    }
}

/// The result of [`reduce`].
#[derive(Debug, Clone, PartialEq)]
pub struct Reduction {
    /// Number of HWP angles.
    pub n: usize,
    /// HWP angles (rad).
    pub theta: Vec<f64>,
    /// `F_i` (`eq:F`).
    pub f: Vec<f64>,
    /// Errors of `F_i`, propagated from the per-beam errors.
    pub sigma_f: Vec<f64>,
    pub estimator: Estimator,
    /// `Q/I`, `U/I` with covariance.
    pub qu: Qu,
    /// `P` (`eq:poldeg`), fraction.
    pub p: f64,
    /// `chi` (`eq:polang`), rad in `[0, pi)`.
    pub chi: f64,
    /// False when `P = 0` to rounding (`P <= 4 N eps max|F_i|`): `chi` is then meaningless.
    pub chi_defined: bool,
    /// `sigma_P` propagated from the per-beam errors.
    pub sigma_p: f64,
    /// `sigma_chi` (rad) propagated from the per-beam errors; infinite when `P = 0`.
    pub sigma_chi: f64,
    /// Effective SNR of the intensity image `f_O + f_E` of one exposure (see module docs).
    pub snr: f64,
    /// `eq:sigp`: `1/(sqrt(N/2) SNR)`; for a plate turning through `d_i` during exposure `i`,
    /// `1/(sqrt(sum e_i^2 / 2) SNR)` with `e_i = sin(2 d_i)/(2 d_i)` the modulation each keeps
    /// ([`mueller::hwp_sweep_efficiency`]): the same form with each `F_i` carrying `e_i` of the
    /// signal (`N` when every `e_i = 1`).
    pub sigma_p_analytic: f64,
    /// `eq:sigchi`: `sigma_P/(2P)` (rad); infinite when `P = 0`.
    pub sigma_chi_analytic: f64,
    /// `a_0 = mean F_i` (`eq:a0`).
    pub a0: f64,
    /// Error of `a_0`.
    pub sigma_a0: f64,
    /// Harmonics `k = 0 ..= N/2` (`eq:fourcoeff`); empty unless the optimal set.
    pub fourier: Vec<Harmonic>,
    /// `kappa_j` (`eq:kappa2`); empty for `N < 4`.
    pub kappa: Vec<KappaEstimate>,
    /// Mean of the `kappa_j`.
    pub kappa_mean: Option<f64>,
    pub warnings: Vec<Warning>,
}

/// The largest `sigma_chi` (rad) worth reporting: the standard deviation of an angle uniform
/// over `[0, pi)`, `pi/sqrt(12)` (52 deg). A propagated error beyond it (a `P` far below its
/// error, where linear propagation gives e.g. 5e6 deg) says only that chi is undetermined.
pub const SIGMA_CHI_UNDETERMINED: f64 = std::f64::consts::PI / 3.464_101_615_137_754_5;

impl Reduction {
    /// `chi` (`eq:polang`) in degrees, in `[0, 180)` (a value that rounds to 180 at the wrap is
    /// folded to 0), as every command and the Python package report it.
    pub fn chi_deg(&self) -> f64 {
        let d = self.chi.to_degrees();
        if d >= 180.0 {
            d - 180.0
        } else {
            d
        }
    }

    /// `sigma_chi` in degrees as every command reports it (one rule for `stokes`,
    /// `photometry`, ...): `None` when chi is undetermined (`P = 0` to rounding, or an error
    /// above [`SIGMA_CHI_UNDETERMINED`]).
    pub fn sigma_chi_deg_reported(&self) -> Option<f64> {
        (self.chi_defined && self.sigma_chi.is_finite() && self.sigma_chi <= SIGMA_CHI_UNDETERMINED)
            .then(|| self.sigma_chi.to_degrees())
    }

    /// `(q, u)` with its covariance and `chi` (deg, in `[0, 180)`) in the sky's frame: the
    /// plate's zero angle `zero_angle_deg` (the angle instruments tabulate, added to a measured
    /// chi) added to chi and turning `q, u` with it (`Qu::rotated`); `P` and its error do not
    /// change. The one turn of a star's reduction into the frame of published standards, for
    /// `photometry` and `catalog` alike.
    ///
    /// ```
    /// // A star of P = 1 % at the plate at chi = 27.11 deg through FORS2's I_BESS (zero angle
    /// // 2.89 deg) is at 30 deg on the sky.
    /// let theta = mueller::optimal_angles(4);
    /// let f = |t: &f64, s: f64| 1e6 * (1.0 + s * 0.01 * (4.0 * t - 2.0 * 27.11f64.to_radians()).cos());
    /// let fo = theta.iter().map(|t| f(t, 1.0)).collect();
    /// let fe = theta.iter().map(|t| f(t, -1.0)).collect();
    /// let r = stokes::Measurement::poisson(theta, fo, fe).unwrap().reduce().unwrap();
    /// let (sky, chi_deg) = r.in_sky_frame(2.89);
    /// assert!((chi_deg - 30.0).abs() < 1e-9);
    /// assert!((sky.q - 0.01 * 60f64.to_radians().cos()).abs() < 1e-12);
    /// ```
    pub fn in_sky_frame(&self, zero_angle_deg: f64) -> (Qu, f64) {
        (self.qu.rotated(zero_angle_deg.to_radians()), (self.chi.to_degrees() + zero_angle_deg).rem_euclid(180.0))
    }
}

impl Measurement {
    /// Photon counts (electrons) in the two beams: Poisson errors `sqrt(f)`. Angles in rad.
    ///
    /// ```
    /// use stokes::Measurement;
    /// // An ideal dual beam: f_O,E = I/2 (1 +- P cos(4 theta - 2 chi)), P = 2 %, chi = 30 deg,
    /// // I = 2e6 e-. The reduction gives P and chi back, and sigma_P of eq:sigp:
    /// // 1 / (sqrt(N/2) SNR) with SNR = sqrt(I) for N = 4.
    /// let theta = mueller::optimal_angles(4);
    /// let f = |t: &f64, s: f64| 1e6 * (1.0 + s * 0.02 * (4.0 * t - 60f64.to_radians()).cos());
    /// let m = Measurement::poisson(
    ///     theta.clone(),
    ///     theta.iter().map(|t| f(t, 1.0)).collect(),
    ///     theta.iter().map(|t| f(t, -1.0)).collect(),
    /// )
    /// .unwrap();
    /// let r = m.reduce().unwrap();
    /// assert!((r.p - 0.02).abs() < 1e-14 && (r.chi_deg() - 30.0).abs() < 1e-9);
    /// assert!((r.sigma_p_analytic - 1.0 / (2f64.sqrt() * 2e6f64.sqrt())).abs() < 1e-8);
    /// ```
    pub fn poisson(theta: Vec<f64>, f_o: Vec<f64>, f_e: Vec<f64>) -> Result<Self, Error> {
        let n = theta.len();
        check_len("f_O", f_o.len(), n)?;
        check_len("f_E", f_e.len(), n)?;
        for (what, v) in [("f_O", &f_o), ("f_E", &f_e)] {
            if let Some((i, &x)) = v.iter().enumerate().find(|(_, x)| !x.is_finite()) {
                return Err(Error::NonFinite { what, index: i, value: x });
            }
        }
        check_total(&f_o, &f_e)?;
        for (what, v) in [("f_O", &f_o), ("f_E", &f_e)] {
            for (i, &x) in v.iter().enumerate() {
                if x < 0.0 {
                    return Err(Error::Invalid {
                        what,
                        index: i,
                        value: x,
                        why:
                            "photon counts cannot be negative (give sigma_o, sigma_e for background-subtracted fluxes)",
                    });
                }
            }
        }
        let sigma_o = f_o.iter().map(|x| x.sqrt()).collect();
        let sigma_e = f_e.iter().map(|x| x.sqrt()).collect();
        Self::build(theta, f_o, f_e, sigma_o, sigma_e, true)
    }

    /// Fluxes with their 1-sigma errors (any units, the same for both beams). Angles in rad.
    pub fn with_errors(
        theta: Vec<f64>,
        f_o: Vec<f64>,
        f_e: Vec<f64>,
        sigma_o: Vec<f64>,
        sigma_e: Vec<f64>,
    ) -> Result<Self, Error> {
        Self::build(theta, f_o, f_e, sigma_o, sigma_e, false)
    }

    fn build(
        theta: Vec<f64>,
        f_o: Vec<f64>,
        f_e: Vec<f64>,
        sigma_o: Vec<f64>,
        sigma_e: Vec<f64>,
        poisson: bool,
    ) -> Result<Self, Error> {
        let n = theta.len();
        if n < 2 {
            return Err(Error::TooFewAngles(n));
        }
        check_len("f_O", f_o.len(), n)?;
        check_len("f_E", f_e.len(), n)?;
        check_len("sigma_O", sigma_o.len(), n)?;
        check_len("sigma_E", sigma_e.len(), n)?;
        for (what, v) in
            [("HWP angle", &theta), ("f_O", &f_o), ("f_E", &f_e), ("sigma_O", &sigma_o), ("sigma_E", &sigma_e)]
        {
            if let Some((i, &x)) = v.iter().enumerate().find(|(_, x)| !x.is_finite()) {
                return Err(Error::NonFinite { what, index: i, value: x });
            }
        }
        for (what, v) in [("sigma_O", &sigma_o), ("sigma_E", &sigma_e)] {
            if let Some((i, &x)) = v.iter().enumerate().find(|(_, x)| **x < 0.0) {
                return Err(Error::Invalid { what, index: i, value: x, why: "an error cannot be negative" });
            }
        }
        check_total(&f_o, &f_e)?;
        // Duplicated, degenerate angle sets: the solver's checks are the one place for them.
        StokesSolver::new(&theta)?;
        Ok(Self { theta, f_o, f_e, sigma_o, sigma_e, poisson, sweep: Vec::new() })
    }

    /// The same fluxes taken while the plate turned uniformly: exposure `i` through
    /// `sweep[i]` rad about its angle in [`Self::theta`] (the middle angle). The reduction then
    /// solves `eq:system` with the averaged modulation ([`StokesSolver::with_sweeps`]).
    /// Errors: a sweep per angle is needed, finite, and not one that leaves nothing modulated.
    pub fn with_sweeps(mut self, sweep: Vec<f64>) -> Result<Self, Error> {
        StokesSolver::with_sweeps(&self.theta, &sweep)?;
        self.sweep = if sweep.iter().all(|&d| d == 0.0) { Vec::new() } else { sweep };
        Ok(self)
    }

    /// Each exposure's plate sweep (rad); empty for a fixed plate.
    pub fn sweeps(&self) -> &[f64] {
        &self.sweep
    }

    /// The one solver of this measurement's angles and sweeps.
    fn solver(&self) -> Result<StokesSolver, Error> {
        if self.sweep.is_empty() {
            StokesSolver::new(&self.theta)
        } else {
            StokesSolver::with_sweeps(&self.theta, &self.sweep)
        }
    }

    /// HWP angles (rad).
    pub fn theta(&self) -> &[f64] {
        &self.theta
    }
    /// Ordinary-beam fluxes.
    pub fn f_o(&self) -> &[f64] {
        &self.f_o
    }
    /// Extraordinary-beam fluxes.
    pub fn f_e(&self) -> &[f64] {
        &self.f_e
    }
    /// Per-beam errors `(sigma_O, sigma_E)` (Poisson `sqrt(f)` for counts).
    pub fn sigmas(&self) -> (&[f64], &[f64]) {
        (&self.sigma_o, &self.sigma_e)
    }
    /// True when the errors are Poisson errors of counts.
    pub fn is_poisson(&self) -> bool {
        self.poisson
    }

    /// The measurement with both beams corrected for a known Wollaston `kappa` (section
    /// `sec:wollaston`): `f_O/(1 + kappa)`, `f_E/(1 - kappa)`, errors scaled alike (the
    /// result carries explicit errors: the corrected fluxes are no longer counts).
    pub fn corrected_for_kappa(&self, kappa: f64) -> Result<Self, Error> {
        KappaCorrection::known(kappa)?;
        let n = self.theta.len();
        let mut m = self.clone();
        for i in 0..n {
            (m.f_o[i], m.f_e[i]) = correct_fluxes(self.f_o[i], self.f_e[i], kappa);
            (m.sigma_o[i], m.sigma_e[i]) = correct_fluxes(self.sigma_o[i], self.sigma_e[i], kappa);
        }
        m.poisson = false;
        Ok(m)
    }

    /// `F_i` (`eq:F`) and their errors.
    pub fn normalized_differences(&self) -> (Vec<f64>, Vec<f64>) {
        let f = (0..self.theta.len()).map(|i| normalized_difference(self.f_o[i], self.f_e[i])).collect();
        let s = (0..self.theta.len())
            .map(|i| sigma_normalized_difference(self.f_o[i], self.f_e[i], self.sigma_o[i], self.sigma_e[i]))
            .collect();
        (f, s)
    }

    /// See [`reduce`].
    pub fn reduce(&self) -> Result<Reduction, Error> {
        reduce(self)
    }

    /// [`reduce`] with the Wollaston imbalance handled as `k` says; returns the reduction and
    /// the `kappa` that was applied to the fluxes (`None` for [`KappaCorrection::None`]).
    ///
    /// [`KappaCorrection::FromData`] estimates `kappa` from these same data (the mean of the
    /// `kappa_j` of `eq:kappa2`, from positions 45 deg apart), corrects both beams with it
    /// ([`Self::corrected_for_kappa`]) and reduces again, in one call: `kappa` enters `F_i` in
    /// second order (`eq:F` cancels it to first order on a complete set), so the estimate from
    /// the uncorrected `F_i` is unbiased to that order. Refused when no `kappa_j` exists (fewer
    /// than 4 angles, or no pair 45 deg apart), with the reason.
    pub fn reduce_with(&self, k: KappaCorrection) -> Result<(Reduction, Option<f64>), Error> {
        match k {
            KappaCorrection::None => Ok((self.reduce()?, None)),
            KappaCorrection::Known(kappa) => Ok((self.corrected_for_kappa(kappa)?.reduce()?, Some(kappa))),
            KappaCorrection::FromData => {
                let first = self.reduce()?;
                let Some(kappa) = first.kappa_mean else {
                    let why = first
                        .warnings
                        .iter()
                        .find(|w| matches!(w, Warning::KappaNeedsFour { .. } | Warning::KappaNoPairs))
                        .map_or("no kappa_j".to_string(), |w| w.to_string());
                    return Err(Error::KappaNotEstimable(why));
                };
                Ok((self.corrected_for_kappa(kappa)?.reduce()?, Some(kappa)))
            }
        }
    }
}

/// How a reduction treats the Wollaston imbalance `kappa = (t - s)/(t + s)` (section
/// `sec:wollaston`).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub enum KappaCorrection {
    /// The fluxes as measured (`eq:F` cancels `kappa` to first order on a complete set).
    #[default]
    None,
    /// A known `kappa` (e.g. from flats), applied to both beams.
    Known(f64),
    /// `kappa` estimated from the data themselves (`eq:kappa2`) and applied in the same run.
    FromData,
}

impl KappaCorrection {
    /// A known `kappa`: `kappa = (t - s)/(t + s)` lies in the open interval (-1, 1) (a beam of
    /// no light at the ends), the one rule every face and step takes it by
    /// ([`Error::KappaOutOfRange`] names the value).
    pub fn known(kappa: f64) -> Result<Self, Error> {
        if kappa.is_finite() && kappa.abs() < 1.0 {
            Ok(KappaCorrection::Known(kappa))
        } else {
            Err(Error::KappaOutOfRange(kappa))
        }
    }
}

/// True when HWP angles given "in degrees" all lie within `[-2pi, 2pi]`: radians by mistake
/// (the optimal set 0, 22.5, 45, 67.5 deg is 0, 0.39, 0.79, 1.18 rad). No useful degree set
/// spans less than 6.3 deg: HWP sets step by 22.5 deg or so. Callers refuse such input.
pub fn looks_like_radians(deg: &[f64]) -> bool {
    deg.len() >= 2 && deg.iter().all(|d| d.abs() <= std::f64::consts::TAU + 1e-9)
}

/// HWP angles given in degrees that look like radians ([`looks_like_radians`]); its text says
/// what they were, and the caller adds how to give them (its option or argument).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{shown}, all within 0..2pi: these look like radians (in degrees the angles would span only {span:.2} deg)")]
pub struct LooksLikeRadians {
    shown: String,
    span: f64,
}

/// The one check of HWP angles a user gives in degrees (a table's column, an option, a scene,
/// a Python argument): refused when they look like radians.
pub fn check_degrees(deg: &[f64]) -> Result<(), LooksLikeRadians> {
    if !looks_like_radians(deg) {
        return Ok(());
    }
    let lo = deg.iter().cloned().fold(f64::MAX, f64::min);
    let hi = deg.iter().cloned().fold(f64::MIN, f64::max);
    let shown = format!("{:?}{}", &deg[..deg.len().min(8)], if deg.len() > 8 { " ..." } else { "" });
    Err(LooksLikeRadians { shown, span: hi - lo })
}

fn check_total(f_o: &[f64], f_e: &[f64]) -> Result<(), Error> {
    for (i, (o, e)) in f_o.iter().zip(f_e).enumerate() {
        let total = o + e;
        if !(total > 0.0) {
            return Err(Error::NonPositiveFlux { index: i, total });
        }
    }
    Ok(())
}

fn check_len(what: &'static str, got: usize, expected: usize) -> Result<(), Error> {
    if got != expected {
        return Err(Error::LengthMismatch { what, got, expected });
    }
    Ok(())
}

/// Reduce one source: `F_i` (`eq:F`), `Q/I`, `U/I` (`eq:Q`, `eq:U` or least squares of
/// `eq:system`), `P`, `chi` (`eq:poldeg`, `eq:polang`), errors (`eq:sigp`, `eq:sigchi` and
/// propagated), harmonics (`eq:fourcoeff`), `a_0` (`eq:a0`) and `kappa_j` (`eq:g`,
/// `eq:kappa2`). See the module docs for the choice of estimator and SNR.
///
/// ```
/// use stokes::{Measurement, reduce};
/// let theta: Vec<f64> = (0..4).map(|i| i as f64 * std::f64::consts::PI / 8.0).collect();
/// // Q/I = 0.02, U/I = 0: F = 0.02, 0, -0.02, 0 with 1e6 counts per exposure.
/// let m = Measurement::poisson(theta, vec![5.1e5, 5e5, 4.9e5, 5e5], vec![4.9e5, 5e5, 5.1e5, 5e5]).unwrap();
/// let r = reduce(&m).unwrap();
/// assert!((r.p - 0.02).abs() < 1e-15 && r.chi.abs() < 1e-15);
/// assert!((r.sigma_p_analytic - 1e-3 / 2f64.sqrt()).abs() < 1e-15);
/// ```
pub fn reduce(m: &Measurement) -> Result<Reduction, Error> {
    let n = m.theta.len();
    let solver = m.solver()?;
    let (f, sigma_f) = m.normalized_differences();
    // F is in [-1, 1] for counts; an error of 1e150 (errors 1e150 times the fluxes) says that
    // nothing was measured, and its square (the variances below) would overflow to inf.
    for (i, &s) in sigma_f.iter().enumerate() {
        if !(s.is_finite() && s <= 1e150) {
            return Err(Error::Undetermined { index: i, sigma_f: s });
        }
    }
    let mut warnings = Vec::new();
    if n == 2 {
        warnings.push(Warning::TwoAngles);
    }
    for (i, &x) in f.iter().enumerate() {
        if x.abs() > 1.0 {
            warnings.push(Warning::NegativeBeam { index: i, f: x });
        }
    }

    let all_equal = sigma_f.iter().all(|&s| s == sigma_f[0]);
    let any_zero = sigma_f.contains(&0.0);
    let (estimator, qu) = if solver.is_optimal() {
        (Estimator::FourierSums, solver.solve_with_errors(&f, &sigma_f)?)
    } else if all_equal {
        (Estimator::LeastSquares, solver.solve_with_errors(&f, &sigma_f)?)
    } else if any_zero {
        warnings.push(Warning::ZeroErrors);
        (Estimator::LeastSquares, solver.solve_with_errors(&f, &sigma_f)?)
    } else {
        (Estimator::WeightedLeastSquares, solver.solve_weighted(&f, &sigma_f)?)
    };

    let (p, chi) = polarization(qu.q, qu.u);
    // P = 0 to rounding: the Fourier sums of F_i carry ~N eps max|F| of rounding, which is
    // all a P of that size is (e.g. unpolarized light through an imbalanced prism).
    let fmax = f.iter().fold(0.0f64, |a, x| a.max(x.abs()));
    let chi_defined = p > 4.0 * n as f64 * f64::EPSILON * fmax;
    let (sigma_p, sigma_chi) = if chi_defined {
        // Unit vector (cos 2chi, sin 2chi): no p^4 that could underflow.
        let (c, s) = (qu.q / p, qu.u / p);
        let vp = c * c * qu.var_q + s * s * qu.var_u + 2.0 * c * s * qu.cov_qu;
        let vchi = (s * s * qu.var_q + c * c * qu.var_u - 2.0 * c * s * qu.cov_qu) / (4.0 * p * p);
        (vp.max(0.0).sqrt(), vchi.max(0.0).sqrt())
    } else {
        warnings.push(Warning::ChiUndefined);
        (((qu.var_q + qu.var_u) / 2.0).sqrt(), f64::INFINITY)
    };
    if chi_defined && p < sigma_p {
        warnings.push(Warning::LowSignificance { p, sigma_p });
    }
    // P <= 1 for any light (eq:poldeg); beyond it by more than the errors, the data are not a
    // measurement of light (typically one beam that received nothing: F_i = +-1 exactly, with
    // a zero Poisson error).
    if !(p <= 1.0 + mueller::qu::P_ABOVE_ONE_SIGMAS * sigma_p) {
        let dark_beam = (0..n).find(|&i| m.f_o[i] == 0.0 || m.f_e[i] == 0.0);
        return Err(Error::MoreThanFullyPolarized { p, sigma_p, dark_beam });
    }

    // SNR of the intensity image of one exposure, combined so that eq:sigp holds.
    // Scale-free ratios sigma/t: sigma^2 and t^2 over- or underflow at extreme scales.
    let inv_snr2: f64 = (0..n)
        .map(|i| {
            let tot = m.f_o[i] + m.f_e[i];
            let (a, b) = (m.sigma_o[i] / tot, m.sigma_e[i] / tot);
            a * a + b * b
        })
        .sum::<f64>()
        / n as f64;
    let snr = 1.0 / inv_snr2.sqrt();
    // (Summing 1.0 N times is N exactly: a fixed plate's value is the plain form's, bit for bit.)
    let kept: f64 = if m.sweep.is_empty() {
        n as f64
    } else {
        m.sweep.iter().map(|&d| mueller::hwp_sweep_efficiency(d).powi(2)).sum()
    };
    let sigma_p_analytic = 1.0 / ((kept / 2.0).sqrt() * snr);
    let sigma_chi_analytic = if chi_defined { sigma_p_analytic / (2.0 * p) } else { f64::INFINITY };

    let a0 = crate::kappa::a0(&f);
    let sigma_a0 = sigma_f.iter().map(|s| s * s).sum::<f64>().sqrt() / n as f64;

    let fourier = if solver.is_optimal() {
        fourier_coefficients(&f, &sigma_f)?
    } else {
        warnings.push(Warning::FourierSkipped { n });
        Vec::new()
    };

    let kappa = if n >= 4 {
        let k = kappa_estimates(&m.theta, &f);
        if k.is_empty() {
            warnings.push(Warning::KappaNoPairs);
        }
        for e in k.iter().filter(|e| e.clamped) {
            warnings.push(Warning::KappaClamped { j: e.j, g: e.g });
        }
        k
    } else {
        warnings.push(Warning::KappaNeedsFour { n });
        Vec::new()
    };
    let kappa_mean =
        if kappa.is_empty() { None } else { Some(kappa.iter().map(|e| e.kappa).sum::<f64>() / kappa.len() as f64) };

    Ok(Reduction {
        n,
        theta: m.theta.clone(),
        f,
        sigma_f,
        estimator,
        qu,
        p,
        chi,
        chi_defined,
        sigma_p,
        sigma_chi,
        snr,
        sigma_p_analytic,
        sigma_chi_analytic,
        a0,
        sigma_a0,
        fourier,
        kappa,
        kappa_mean,
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn opt(n: usize) -> Vec<f64> {
        (0..n).map(|i| i as f64 * PI / 8.0).collect()
    }

    #[test]
    fn validation_names_the_input() {
        let e = Measurement::poisson(opt(4), vec![1.0, 2.0, 3.0], vec![1.0; 4]).unwrap_err();
        assert_eq!(e, Error::LengthMismatch { what: "f_O", got: 3, expected: 4 });
        let e = Measurement::poisson(opt(4), vec![1.0, 2.0, -0.5, 1.0], vec![1.0; 4]).unwrap_err();
        assert!(matches!(e, Error::Invalid { what: "f_O", index: 2, .. }));
        let e = Measurement::poisson(opt(4), vec![1.0, 2.0, -3.0, 1.0], vec![1.0; 4]).unwrap_err();
        assert_eq!(e, Error::NonPositiveFlux { index: 2, total: -2.0 });
        let e = Measurement::with_errors(opt(4), vec![1.0, 2.0, -3.0, 1.0], vec![1.0; 4], vec![1.0; 4], vec![1.0; 4])
            .unwrap_err();
        assert_eq!(e, Error::NonPositiveFlux { index: 2, total: -2.0 });
        let e = Measurement::poisson(opt(1), vec![1.0], vec![1.0]).unwrap_err();
        assert_eq!(e, Error::TooFewAngles(1));
        let e = Measurement::poisson(vec![0.0, 0.3, 2.0 * PI], vec![1.0; 3], vec![1.0; 3]).unwrap_err();
        assert!(matches!(e, Error::DuplicateAngle { first: 0, second: 2, .. }));
        let e =
            Measurement::with_errors(opt(4), vec![1.0; 4], vec![1.0; 4], vec![1.0, f64::NAN, 1.0, 1.0], vec![1.0; 4])
                .unwrap_err();
        assert!(matches!(e, Error::NonFinite { what: "sigma_O", index: 1, .. }));
        let m = Measurement::poisson(opt(4), vec![1.0; 4], vec![1.0; 4]).unwrap();
        assert_eq!(m.corrected_for_kappa(1.0).unwrap_err(), Error::KappaOutOfRange(1.0));
    }
}
