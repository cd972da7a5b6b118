//! The radial field model of section `sec:fors1`: `p(r) = sum_k c_k r^k` about an optical-axis
//! centre, with the polarization angle along the radius (`phi = alpha`), fitted by robust
//! weighted least squares to the `(q, u)` of each bin.
//!
//! Fitting `q = p(r) cos 2 alpha`, `u = p(r) sin 2 alpha` rather than `p` keeps the fit free of
//! the positive bias of `p` at low signal-to-noise (section `sec:bias`), lets `p(r)` change
//! sign (a tangential pattern is a negative `p`), and constrains the centre through the angles.

use crate::conditioning::{self, Words};
use crate::lsq::{self, Linear, LsqError};
use crate::models::bins::Bin;
use crate::models::model::{FieldModel, InstPol};
use crate::models::region::Exclusion;
use crate::{Error, Result};
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};
use stokes::stats::robust::{median, Middle, MAD_TO_SIGMA};

/// The radial polynomial model `p(r) = sum_{k = first_power}^{degree} c_k r^k` (r in arcmin,
/// `p` a fraction), the angle `phi = alpha` (the polar angle about `centre`).
///
/// The paper's V- and I-band fits (section `sec:fors1`) have `first_power = 1`: `p` vanishes on
/// the axis. Parameter order everywhere (covariance, errors): `c_first..c_degree, x0, y0`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RadialModel {
    pub first_power: usize,
    pub coeffs: Vec<f64>,
    /// Optical-axis centre, arcmin from the detector centre.
    pub centre: [f64; 2],
    pub centre_free: bool,
    /// Covariance of `(c..., x0, y0)`, row-major, `n_params()^2` values; the centre rows are
    /// zero when the centre was fixed.
    pub cov: Vec<f64>,
    /// How `cov` was scaled from the per-bin errors (None for a model that was not fitted, or
    /// read from a file written before this was recorded: those used [`ErrorScaling::Scaled`]).
    #[serde(default)]
    pub scaling: Option<CovarianceScaling>,
}

impl RadialModel {
    /// A model with no covariance (e.g. a simulation's input pattern).
    pub fn new(first_power: usize, coeffs: Vec<f64>, centre: [f64; 2]) -> Self {
        let n = coeffs.len() + 2;
        RadialModel { first_power, coeffs, centre, centre_free: false, cov: vec![0.0; n * n], scaling: None }
    }

    /// Highest power of r.
    pub fn degree(&self) -> usize {
        self.first_power + self.coeffs.len().saturating_sub(1)
    }

    /// Number of parameters in the covariance: the coefficients and the two centre coordinates.
    pub fn n_params(&self) -> usize {
        self.coeffs.len() + 2
    }

    /// `cov[i][j]`.
    pub fn cov_at(&self, i: usize, j: usize) -> f64 {
        self.cov[i * self.n_params() + j]
    }

    /// One-sigma errors of the coefficients.
    pub fn coefficient_errors(&self) -> Vec<f64> {
        (0..self.coeffs.len()).map(|i| self.cov_at(i, i).max(0.0).sqrt()).collect()
    }

    /// One-sigma errors of the centre (0 when fixed).
    pub fn centre_errors(&self) -> [f64; 2] {
        let n = self.coeffs.len();
        [self.cov_at(n, n).max(0.0).sqrt(), self.cov_at(n + 1, n + 1).max(0.0).sqrt()]
    }

    /// `p(r)`, the paper's radial polynomial (section `sec:fors1`).
    pub fn p_of_r(&self, r: f64) -> f64 {
        field::radial::poly(self.first_power, &self.coeffs, r)
    }

    /// One-sigma error of `p(r)` from the coefficient covariance.
    pub fn p_of_r_sigma(&self, r: f64) -> f64 {
        let g: Vec<f64> = (0..self.coeffs.len()).map(|i| r.powi((self.first_power + i) as i32)).collect();
        let mut v = 0.0;
        for i in 0..g.len() {
            for j in 0..g.len() {
                v += g[i] * g[j] * self.cov_at(i, j);
            }
        }
        v.max(0.0).sqrt()
    }

    /// `(q, u)` at `(x, y)` arcmin.
    #[inline]
    pub fn qu(&self, x: f64, y: f64) -> (f64, f64) {
        let (q, u, ..) = self.eval_core(x, y, false);
        (q, u)
    }

    /// The hot path of [`FieldModel::eval`] and [`qu`](Self::qu): no allocation, Horner in `r`.
    /// Returns `(q, u, c2, s2, p, dp/dr, r)` (`c2 = cos 2 alpha`, `s2 = sin 2 alpha`); `dp/dr` only
    /// when `want_dp` (the centre gradient needs it), else 0. On the axis (`r < 1e-12`) `c2 = 1`,
    /// `s2 = 0` (alpha = 0, as in [`radial_eval`]).
    #[inline]
    fn eval_core(&self, x: f64, y: f64, want_dp: bool) -> (f64, f64, f64, f64, f64, f64, f64) {
        let (dx, dy) = (x - self.centre[0], y - self.centre[1]);
        let r2 = dx * dx + dy * dy;
        let r = r2.sqrt();
        if r < 1e-12 {
            let p = if self.first_power == 0 { self.coeffs.first().copied().unwrap_or(0.0) } else { 0.0 };
            return (p, 0.0, 1.0, 0.0, p, 0.0, r);
        }
        let inv = 1.0 / r2;
        let (c2, s2) = ((dx * dx - dy * dy) * inv, 2.0 * dx * dy * inv);
        // The one evaluation of p(r) (and dp/dr when the centre gradient needs it).
        let (p, dp) = if want_dp {
            field::radial::poly_and_derivative(self.first_power, &self.coeffs, r)
        } else {
            (field::radial::poly(self.first_power, &self.coeffs, r), 0.0)
        };
        (p * c2, p * s2, c2, s2, p, dp, r)
    }

    /// `sum_j cov[row][j] r^j` over the coefficient columns (Horner).
    #[inline]
    fn cov_row_poly(&self, row: usize, r: f64) -> f64 {
        let np = self.n_params();
        let base = row * np;
        let mut t = 0.0;
        for j in (0..self.coeffs.len()).rev() {
            t = t * r + self.cov[base + j];
        }
        t
    }

    /// `sum_i cov[i][col] r^i` over the coefficient rows (Horner).
    #[inline]
    fn cov_col_poly(&self, col: usize, r: f64) -> f64 {
        let np = self.n_params();
        let mut t = 0.0;
        for i in (0..self.coeffs.len()).rev() {
            t = t * r + self.cov[i * np + col];
        }
        t
    }
}

/// `r^k` for the small powers of the model (k = 0, 1 in practice) without `powi`'s call.
#[inline]
fn pow_small(r: f64, k: usize) -> f64 {
    let mut v = 1.0;
    for _ in 0..k {
        v *= r;
    }
    v
}

/// `q = p(r) cos 2 alpha = g(r) (dx^2 - dy^2)`, `u = p(r) sin 2 alpha = 2 g(r) dx dy` with
/// `g = p / r^2`: the form without angles, smooth wherever `p(r) / r^2` is. Fills the gradient
/// with respect to `(c..., x0, y0)`.
fn radial_eval(
    first_power: usize,
    coeffs: &[f64],
    centre: [f64; 2],
    x: f64,
    y: f64,
    gq: &mut [f64],
    gu: &mut [f64],
) -> (f64, f64) {
    let (dx, dy) = (x - centre[0], y - centre[1]);
    let r = mueller::hypot(dx, dy);
    gq.iter_mut().chain(gu.iter_mut()).for_each(|g| *g = 0.0);
    let nc = coeffs.len();
    if r < 1e-12 {
        // On the axis the angle is undefined; only a c_0 term would be non-zero there, and its
        // direction is arbitrary: take alpha = 0.
        if first_power == 0 {
            gq[0] = 1.0;
            return (coeffs[0], 0.0);
        }
        return (0.0, 0.0);
    }
    let (c2, s2) = ((dx * dx - dy * dy) / (r * r), 2.0 * dx * dy / (r * r));
    let (p, dp) = field::radial::poly_and_derivative(first_power, coeffs, r);
    for i in 0..coeffs.len() {
        let rk = r.powi((first_power + i) as i32);
        gq[i] = rk * c2;
        gu[i] = rk * s2;
    }
    // d/dx0 = -d/ddx. q = p c2: dq/ddx = p' dx/r c2 + p dc2/ddx; dc2/ddx = 2 dx/r^2 (1 - c2)... use
    // c2 = cos 2a, s2 = sin 2a with da/ddx = -dy/r^2, da/ddy = dx/r^2.
    let (drdx, drdy) = (dx / r, dy / r);
    let (dadx, dady) = (-dy / (r * r), dx / (r * r));
    let dq_ddx = dp * drdx * c2 - 2.0 * p * s2 * dadx;
    let dq_ddy = dp * drdy * c2 - 2.0 * p * s2 * dady;
    let du_ddx = dp * drdx * s2 + 2.0 * p * c2 * dadx;
    let du_ddy = dp * drdy * s2 + 2.0 * p * c2 * dady;
    gq[nc] = -dq_ddx;
    gq[nc + 1] = -dq_ddy;
    gu[nc] = -du_ddx;
    gu[nc + 1] = -du_ddy;
    (p * c2, p * s2)
}

/// The variance of `(q, u)` is `g^T C g` with the gradient `g` of `radial_eval`. Its
/// coefficient part is `g_i = r^(f+i) (cos 2a, sin 2a)`, so the coefficient block reduces to
/// `V = sum_ij r^(f+i) C_ij r^(f+j)` (the variance of `p(r)`, nested Horner) times `cos^2`,
/// `sin^2`, `cos sin`; the centre enters only when it was fitted (a fixed centre is not a
/// parameter and its covariance rows are zero), through the two mixed sums and the 2 x 2 block.
/// No allocation, `O(n^2)` multiply-adds for `V` and `O(n)` for the centre terms.
impl FieldModel for RadialModel {
    #[inline]
    fn eval(&self, x: f64, y: f64) -> InstPol {
        let nc = self.coeffs.len();
        let free = self.centre_free;
        let (q, u, c2, s2, p, dp, r) = self.eval_core(x, y, free);
        if r < 1e-12 {
            // On the axis only c_0 has a gradient (dq/dc_0 = 1, alpha = 0), as radial_eval.
            let vq = if self.first_power == 0 && nc > 0 { self.cov_at(0, 0) } else { 0.0 };
            return InstPol { q, u, var_q: vq.max(0.0), var_u: 0.0, cov_qu: 0.0 };
        }
        // Coefficient block: V = r^(2f) sum_i r^i (sum_j C_ij r^j).
        let rf = pow_small(r, self.first_power);
        let mut v = 0.0;
        for i in (0..nc).rev() {
            v = v * r + self.cov_row_poly(i, r);
        }
        v *= rf * rf;
        let (mut vq, mut vu, mut cqu) = (c2 * c2 * v, s2 * s2 * v, c2 * s2 * v);
        if free {
            // Gradient with respect to (x0, y0): minus that with respect to (dx, dy).
            let (dx, dy) = (x - self.centre[0], y - self.centre[1]);
            let inv_r2 = 1.0 / (r * r);
            let (drdx, drdy) = (dx / r, dy / r);
            let (dadx, dady) = (-dy * inv_r2, dx * inv_r2);
            let gqx = -(dp * drdx * c2 - 2.0 * p * s2 * dadx);
            let gqy = -(dp * drdy * c2 - 2.0 * p * s2 * dady);
            let gux = -(dp * drdx * s2 + 2.0 * p * c2 * dadx);
            let guy = -(dp * drdy * s2 + 2.0 * p * c2 * dady);
            let (ix, iy) = (nc, nc + 1);
            // sum_i r^(f+i) C_(i, centre) and sum_j C_(centre, j) r^(f+j).
            let (colx, coly) = (rf * self.cov_col_poly(ix, r), rf * self.cov_col_poly(iy, r));
            let (rowx, rowy) = (rf * self.cov_row_poly(ix, r), rf * self.cov_row_poly(iy, r));
            let (cxx, cxy, cyx, cyy) =
                (self.cov_at(ix, ix), self.cov_at(ix, iy), self.cov_at(iy, ix), self.cov_at(iy, iy));
            let quad = |ax: f64, ay: f64, bx: f64, by: f64| ax * (cxx * bx + cxy * by) + ay * (cyx * bx + cyy * by);
            vq += c2 * (gqx * colx + gqy * coly) + c2 * (gqx * rowx + gqy * rowy) + quad(gqx, gqy, gqx, gqy);
            vu += s2 * (gux * colx + guy * coly) + s2 * (gux * rowx + guy * rowy) + quad(gux, guy, gux, guy);
            cqu += c2 * (gux * colx + guy * coly) + s2 * (gqx * rowx + gqy * rowy) + quad(gqx, gqy, gux, guy);
        }
        InstPol { q, u, var_q: vq.max(0.0), var_u: vu.max(0.0), cov_qu: cqu }
    }

    fn contains(&self, _x: f64, _y: f64) -> bool {
        true
    }

    /// `(c_first..c_degree, x0, y0)`.
    fn params(&self) -> Vec<f64> {
        let mut v = self.coeffs.clone();
        v.extend_from_slice(&self.centre);
        v
    }

    fn covariance(&self) -> Option<Vec<f64>> {
        Some(self.cov.clone())
    }

    /// The gradient the fit uses (`radial_eval`): coefficients, then the centre.
    fn jacobian(&self, x: f64, y: f64) -> Option<(Vec<f64>, Vec<f64>)> {
        let n = self.n_params();
        let (mut gq, mut gu) = (vec![0.0; n], vec![0.0; n]);
        radial_eval(self.first_power, &self.coeffs, self.centre, x, y, &mut gq, &mut gu);
        Some((gq, gu))
    }

    fn describe(&self) -> String {
        format!(
            "radial polynomial of degree {} (from r^{}), centre ({:.4}, {:.4}) arcmin{}",
            self.degree(),
            self.first_power,
            self.centre[0],
            self.centre[1],
            if self.centre_free { " (fitted)" } else { "" }
        )
    }
}

/// Down-weighting of outlying bins in the fit (iteratively reweighted least squares on the
/// bin's standardized residual `t`, scaled by a robust estimate of its spread when that
/// exceeds 1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Robust {
    /// Plain weighted least squares.
    None,
    /// Huber: weight 1 for `|t| <= k`, `k / |t|` beyond (k = 1.345: 95% efficiency).
    Huber(f64),
    /// Cauchy: weight `1 / (1 + (t / k)^2)` (k = 2.385).
    Cauchy(f64),
}

impl Robust {
    fn weight(&self, t: f64) -> f64 {
        match *self {
            Robust::None => 1.0,
            Robust::Huber(k) => {
                if t.abs() <= k {
                    1.0
                } else {
                    k / t.abs()
                }
            }
            Robust::Cauchy(k) => 1.0 / (1.0 + (t / k).powi(2)),
        }
    }

    /// Name for files and reports.
    pub fn name(&self) -> String {
        match self {
            Robust::None => "none".into(),
            Robust::Huber(k) => format!("huber:{k}"),
            Robust::Cauchy(k) => format!("cauchy:{k}"),
        }
    }
}

/// How the parameter covariance `(J^T W J)^-1` of a fit (`W` from the per-bin errors, `J` the
/// Jacobian at the solution) is scaled by the fit's reduced chi^2.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum ErrorScaling {
    /// By `max(1, chi2_red)` (the default): errors grow when the bins scatter more than their
    /// errors say (a model that does not fit, errors understated), but never shrink below what
    /// the stated per-bin errors allow. A chi^2 below 1 usually means the errors are correlated
    /// (smoothed maps) or overstated, not that the data are better than stated.
    #[default]
    Conservative,
    /// Always by `chi2_red`, as scipy's `curve_fit(absolute_sigma=False)`: the per-bin errors
    /// are right only up to a common factor, which the scatter about the model sets.
    Scaled,
    /// Not at all: the per-bin errors are trusted as they are (`absolute_sigma=True`).
    Absolute,
}

impl ErrorScaling {
    /// The factor applied to `(J^T W J)^-1` for a fit of reduced chi^2 `chi2_reduced`.
    pub fn factor(self, chi2_reduced: f64) -> f64 {
        match self {
            ErrorScaling::Conservative => chi2_reduced.max(1.0),
            ErrorScaling::Scaled => chi2_reduced,
            ErrorScaling::Absolute => 1.0,
        }
    }

    /// Name for files, JSON and the CLI.
    pub fn name(self) -> &'static str {
        match self {
            ErrorScaling::Conservative => "conservative",
            ErrorScaling::Scaled => "scaled",
            ErrorScaling::Absolute => "absolute",
        }
    }
}

impl std::str::FromStr for Robust {
    type Err = Error;

    /// `huber` (k = 1.345), `cauchy` (k = 2.385) or `none`, ignoring case.
    fn from_str(s: &str) -> Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "huber" => Ok(Robust::Huber(1.345)),
            "cauchy" => Ok(Robust::Cauchy(2.385)),
            "none" => Ok(Robust::None),
            other => Err(Error::Input(format!("unknown robust loss '{other}': use huber, cauchy or none"))),
        }
    }
}

impl std::str::FromStr for ErrorScaling {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s.trim().to_ascii_lowercase().as_str() {
            "conservative" => Ok(ErrorScaling::Conservative),
            "scaled" => Ok(ErrorScaling::Scaled),
            "absolute" => Ok(ErrorScaling::Absolute),
            other => Err(Error::Input(format!(
                "unknown error scaling '{other}': use conservative (max(1, chi2_red), the default), scaled (chi2_red) \
                 or absolute (the per-bin errors as given)"
            ))),
        }
    }
}

/// How a fitted covariance was scaled: `cov = (J^T W J)^-1 * chi2_factor * inflation`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CovarianceScaling {
    pub mode: ErrorScaling,
    /// Reduced chi^2 of the fit (robust weights included).
    pub chi2_reduced: f64,
    /// `mode.factor(chi2_reduced)`.
    pub chi2_factor: f64,
    /// The correlated-errors inflation `tau` ([`crate::models::correlation`]) when it was estimated.
    pub correlation_inflation: Option<f64>,
}

impl CovarianceScaling {
    /// The whole factor applied to `(J^T W J)^-1`.
    pub fn total(&self) -> f64 {
        self.chi2_factor * self.correlation_inflation.unwrap_or(1.0)
    }
}

/// How to fit a [`RadialModel`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RadialFitOptions {
    /// Highest power of r (default 3, as the paper).
    pub degree: usize,
    /// Fit a constant `c_0` too (default false: `p` vanishes on the axis, as the paper assumes).
    pub include_c0: bool,
    /// Fit the optical-axis centre (default false: fixed at `centre`).
    pub free_centre: bool,
    /// The fixed centre, or the starting point of a free one (arcmin; default the detector centre).
    pub centre: [f64; 2],
    /// Parts of the field left out. Sectors and rings are about the model's centre: with a free
    /// centre, membership is recomputed about the fitted centre and the model refitted.
    pub exclusions: Vec<Exclusion>,
    pub robust: Robust,
    /// How the covariance uses the reduced chi^2 (default [`ErrorScaling::Conservative`]).
    #[serde(default)]
    pub error_scaling: ErrorScaling,
    /// Inflate the covariance for correlated bin errors, estimated from the residuals'
    /// autocorrelation on the bins' grid ([`crate::models::correlation`]; default false).
    #[serde(default)]
    pub correlated_errors: bool,
}

impl Default for RadialFitOptions {
    fn default() -> Self {
        RadialFitOptions {
            degree: 3,
            include_c0: false,
            free_centre: false,
            centre: [0.0, 0.0],
            exclusions: vec![],
            robust: Robust::Huber(1.345),
            error_scaling: ErrorScaling::Conservative,
            correlated_errors: false,
        }
    }
}

impl RadialFitOptions {
    /// Parse a model name `radialN` (N = degree, e.g. `radial3`), optionally `radial0N` to
    /// include `c_0`.
    pub fn set_model_name(&mut self, name: &str) -> Result<()> {
        let bad = || Error::Input(format!("unknown model '{name}': expected radialN (N = degree 1..8, e.g. radial3)"));
        let digits = name.strip_prefix("radial").ok_or_else(bad)?;
        let d: usize = digits.parse().map_err(|_| bad())?;
        if !(1..=8).contains(&d) {
            return Err(bad());
        }
        self.degree = d;
        Ok(())
    }
}

/// The result of a radial fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RadialFit {
    pub model: RadialModel,
    /// Reduced chi^2 of the (robustly weighted) fit; how it scales the covariance is
    /// `model.scaling` (and [`RadialFitOptions::error_scaling`]).
    pub chi2_reduced: f64,
    /// The correlated-errors estimate, when asked for.
    pub correlation: Option<crate::models::correlation::CorrelationInflation>,
    /// The centre (arcmin) about which sector and ring exclusions were measured: the fitted
    /// centre of the previous pass when the centre is free (equal to the final one when the
    /// membership settled), else the fixed centre.
    pub exclusion_centre: [f64; 2],
    /// Fits run to settle the exclusion membership (1 without polar exclusions or a free centre).
    pub passes: usize,
    /// RMS per component of the residuals `q - q_model`, `u - u_model` over the used bins.
    pub rms_residual: f64,
    pub n_used: usize,
    /// Per input bin: used by the fit (valid and not excluded).
    pub used: Vec<bool>,
    /// Per input bin: final robust weight (0 for unused bins).
    pub weights: Vec<f64>,
}

/// The least-squares problem of the fit: standardized, weighted residuals of the used bins.
struct Problem<'a> {
    bins: Vec<&'a Bin>,
    /// sqrt(robust weight) / sigma for q and u.
    wq: Vec<f64>,
    wu: Vec<f64>,
    first_power: usize,
    nc: usize,
    free_centre: bool,
    fixed_centre: [f64; 2],
}

impl Problem<'_> {
    fn split(&self, p: &[f64]) -> (Vec<f64>, [f64; 2]) {
        let c = p[..self.nc].to_vec();
        let centre = if self.free_centre { [p[self.nc], p[self.nc + 1]] } else { self.fixed_centre };
        (c, centre)
    }
    fn n_free(&self) -> usize {
        self.nc + if self.free_centre { 2 } else { 0 }
    }
    fn residuals(&self, p: &[f64]) -> DVector<f64> {
        let (c, centre) = self.split(p);
        let n = self.bins.len();
        let mut r = DVector::zeros(2 * n);
        let (mut gq, mut gu) = (vec![0.0; self.nc + 2], vec![0.0; self.nc + 2]);
        for (i, b) in self.bins.iter().enumerate() {
            let (q, u) = radial_eval(self.first_power, &c, centre, b.x, b.y, &mut gq, &mut gu);
            r[2 * i] = (q - b.qu.q) * self.wq[i];
            r[2 * i + 1] = (u - b.qu.u) * self.wu[i];
        }
        r
    }
    fn jacobian(&self, p: &[f64]) -> DMatrix<f64> {
        let (c, centre) = self.split(p);
        let n = self.bins.len();
        let m = self.n_free();
        let mut j = DMatrix::zeros(2 * n, m);
        let (mut gq, mut gu) = (vec![0.0; self.nc + 2], vec![0.0; self.nc + 2]);
        for (i, b) in self.bins.iter().enumerate() {
            radial_eval(self.first_power, &c, centre, b.x, b.y, &mut gq, &mut gu);
            for k in 0..m {
                j[(2 * i, k)] = gq[k] * self.wq[i];
                j[(2 * i + 1, k)] = gu[k] * self.wu[i];
            }
        }
        j
    }
}

impl lsq::Problem for Problem<'_> {
    type Eval = DVector<f64>;
    type Lin = DMatrix<f64>;
    fn evaluate(&self, x: &[f64]) -> std::result::Result<DVector<f64>, LsqError> {
        Ok(self.residuals(x))
    }
    fn chi2(&self, r: &DVector<f64>) -> f64 {
        r.norm_squared()
    }
    fn linearize(&self, x: &[f64], r: &DVector<f64>) -> std::result::Result<Linear<DMatrix<f64>>, LsqError> {
        Ok(Linear::of_jacobian(self.jacobian(x), r))
    }
    fn words(&self, _n: usize) -> Words {
        self.words()
    }
}

impl Problem<'_> {
    /// The conditioning judge's words: the coefficients by their power of r, the centre, and
    /// the layout that determines them (the radii present, and a pattern to centre on).
    fn words(&self) -> Words {
        let mut names: Vec<String> =
            (0..self.nc).map(|k| format!("the r^{} coefficient", k + self.first_power)).collect();
        if self.free_centre {
            names.extend(["the centre's x".to_string(), "the centre's y".to_string()]);
        }
        let (lo, hi) = self.bins.iter().fold((f64::INFINITY, 0.0f64), |(l, h), b| {
            let r = (b.x - self.fixed_centre[0]).hypot(b.y - self.fixed_centre[1]);
            (l.min(r), h.max(r))
        });
        let mut remedy = format!(
            "the bins' radii span only {lo:.4}..{hi:.4} arcmin from the centre; a radial profile of {} powers of r \
             needs bins at several distances from the centre",
            self.nc
        );
        if self.free_centre {
            remedy.push_str(", and a free centre a polarization that changes with radius to centre on");
        }
        Words::new(names, remedy)
    }
}

/// Gauss-Newton from `start` under [`lsq::RADIAL`] (full steps; if they do not lower the cost,
/// a free centre far from the start, damped ones).
fn gauss_newton(problem: &Problem, start: Vec<f64>) -> Result<Vec<f64>> {
    lsq::ladder(problem, start, &lsq::RADIAL).map(|s| s.x).map_err(|e| {
        // The fit's words for its failures, as when argmin's solver ran it (its own for a
        // singular normal matrix).
        let why = match e {
            LsqError::Undetermined(u) => return Error::Undetermined(u),
            LsqError::Singular => "Non-invertible matrix".to_string(),
            LsqError::NoDecrease { from, to } => format!("cost rose from {from} to {to}"),
            LsqError::Evaluation(w) => w,
        };
        Error::FitFailed(format!("Gauss-Newton did not converge: {why}"))
    })
}

/// Fit the radial model (section `sec:fors1`) to the bins by robust weighted least squares on
/// `(q, u)` (Gauss-Newton, [`lsq::RADIAL`], inside iteratively reweighted least squares). The
/// covariance is `(J^T W J)^-1` from the Jacobian at the solution, scaled as
/// [`RadialFitOptions::error_scaling`] says (default `max(1, chi2_red)`) and, when asked,
/// inflated for correlated bin errors ([`crate::models::correlation`]).
///
/// Sector and ring exclusions are measured about the model's centre. With a free centre the
/// first pass takes them about the starting centre; the membership is then recomputed about the
/// fitted centre and the model refitted from there, until the membership no longer changes (at
/// most three passes).
pub fn fit_radial(bins: &[Bin], opts: &RadialFitOptions) -> Result<RadialFit> {
    let membership = |c: [f64; 2]| -> Vec<bool> {
        bins.iter().map(|b| b.is_valid() && !opts.exclusions.iter().any(|e| e.excludes_about(b.x, b.y, c))).collect()
    };
    let mut centre = opts.centre;
    let mut used = membership(centre);
    let mut fit = match fit_pass(bins, opts, opts.centre, used.clone()) {
        Ok(f) => f,
        // With no radial pattern there is no optical axis to find: say so, rather than
        // "did not converge" (the free centre's Jacobian vanishes when p(r) = 0).
        Err(e) if opts.free_centre => {
            let fixed = RadialFitOptions { free_centre: false, ..opts.clone() };
            match fit_pass(bins, &fixed, opts.centre, used.clone()) {
                Ok(f) if f.model.coeffs.iter().enumerate().all(|(k, c)| c.abs() <= 3.0 * f.model.cov_at(k, k).sqrt()) => {
                    return Err(Error::Input(format!(
                        "no radial pattern to centre: with the centre fixed at ({}, {}) arcmin every coefficient is within 3 sigma of zero ({:?}), so the optical-axis centre is undefined; fit with a fixed centre",
                        opts.centre[0], opts.centre[1], f.model.coeffs
                    )))
                }
                _ => return Err(e),
            }
        }
        Err(e) => return Err(e),
    };
    let mut passes = 1;
    if opts.free_centre && opts.exclusions.iter().any(|e| e.is_polar()) {
        while passes < 3 {
            let next = membership(fit.model.centre);
            if next == used {
                break;
            }
            centre = fit.model.centre;
            used = next;
            // Start the refit from the fitted centre (a fixed-centre stage there, then free).
            fit = fit_pass(bins, opts, centre, used.clone())?;
            passes += 1;
        }
    }
    fit.exclusion_centre = centre;
    fit.passes = passes;
    if opts.correlated_errors {
        let (mut gq, mut gu) = (vec![0.0; fit.model.n_params()], vec![0.0; fit.model.n_params()]);
        let z: Vec<(f64, f64, f64, f64)> = bins
            .iter()
            .zip(&fit.used)
            .filter(|(_, u)| **u)
            .map(|(b, _)| {
                let m = &fit.model;
                let (q, u) = radial_eval(m.first_power, &m.coeffs, m.centre, b.x, b.y, &mut gq, &mut gu);
                (b.x, b.y, (b.qu.q - q) / b.sigma_q(), (b.qu.u - u) / b.sigma_u())
            })
            .collect();
        let c = crate::models::correlation::residual_inflation(&z)?;
        for v in fit.model.cov.iter_mut() {
            *v *= c.factor;
        }
        if let Some(sc) = fit.model.scaling.as_mut() {
            sc.correlation_inflation = Some(c.factor);
        }
        fit.correlation = Some(c);
    }
    Ok(fit)
}

/// The weights of the robust loss for standardized residuals `t`, each first divided by their
/// spread (the MAD as a sigma) where that exceeds 1: the reweighting of every field fit.
pub(crate) fn robust_weights(t: &[f64], robust: Robust) -> Vec<f64> {
    let mut a = t.to_vec();
    let scale = (MAD_TO_SIGMA * median(&mut a, Middle::Mean)).max(1.0);
    t.iter().map(|ti| robust.weight(ti / scale)).collect()
}

/// One fit with a given bin membership, from `start_centre` (the fixed centre, or the start of
/// a free one).
fn fit_pass(bins: &[Bin], opts: &RadialFitOptions, start_centre: [f64; 2], used: Vec<bool>) -> Result<RadialFit> {
    let first_power = if opts.include_c0 { 0 } else { 1 };
    if opts.degree < first_power.max(1) {
        return Err(Error::Input(format!("degree {} is too low for the radial model", opts.degree)));
    }
    let nc = opts.degree - first_power + 1;
    let n_free = nc + if opts.free_centre { 2 } else { 0 };
    let sel: Vec<&Bin> = bins.iter().zip(&used).filter(|(_, u)| **u).map(|(b, _)| b).collect();
    // Two numbers per bin; ask for a few bins per parameter so the covariance means something.
    let needed = (2 * n_free).max(n_free + 3);
    if sel.len() < needed {
        return Err(Error::TooFewBins { used: sel.len(), total: bins.len(), needed });
    }
    let mut problem = Problem {
        wq: sel.iter().map(|b| 1.0 / b.sigma_q()).collect(),
        wu: sel.iter().map(|b| 1.0 / b.sigma_u()).collect(),
        bins: sel,
        first_power,
        nc,
        free_centre: false,
        fixed_centre: start_centre,
    };
    // The coefficients must be constrained by the radii present (all bins at one radius make
    // every r^k column the same shape).
    conditioning::judge(&problem.jacobian(&vec![0.0; nc]), &problem.words())?;

    // Robust weights from the standardized residuals of each bin (without the weights).
    let robust_weights = |problem: &Problem, params: &[f64]| -> Vec<f64> {
        let (c, centre) = problem.split(params);
        let (mut gq, mut gu) = (vec![0.0; nc + 2], vec![0.0; nc + 2]);
        let t: Vec<f64> = problem
            .bins
            .iter()
            .map(|b| {
                let (q, u) = radial_eval(first_power, &c, centre, b.x, b.y, &mut gq, &mut gu);
                let (tq, tu) = ((q - b.qu.q) / b.sigma_q(), (u - b.qu.u) / b.sigma_u());
                (0.5 * (tq * tq + tu * tu)).sqrt()
            })
            .collect();
        robust_weights(&t, opts.robust)
    };

    let mut params = gauss_newton(&problem, vec![0.0; nc])?;
    let mut weights = vec![1.0; problem.bins.len()];
    let sigmas: Vec<(f64, f64)> = problem.bins.iter().map(|b| (b.sigma_q(), b.sigma_u())).collect();
    let set_weights = |problem: &mut Problem, w: &[f64]| {
        for i in 0..w.len() {
            problem.wq[i] = w[i].sqrt() / sigmas[i].0;
            problem.wu[i] = w[i].sqrt() / sigmas[i].1;
        }
    };
    for stage in 0..2 {
        if stage == 1 {
            if !opts.free_centre {
                break;
            }
            problem.free_centre = true;
            params.extend_from_slice(&start_centre);
        }
        for _ in 0..30 {
            if opts.robust == Robust::None {
                params = gauss_newton(&problem, params)?;
                break;
            }
            let w_new = robust_weights(&problem, &params);
            let change = w_new.iter().zip(&weights).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            weights = w_new;
            set_weights(&mut problem, &weights);
            params = gauss_newton(&problem, params)?;
            if change < 1e-4 {
                break;
            }
        }
    }

    // Covariance from the Jacobian at the solution, scaled as the options say.
    let j = problem.jacobian(&params);
    conditioning::judge(&j, &problem.words())?;
    let r = problem.residuals(&params);
    let dof = (2 * problem.bins.len()).saturating_sub(n_free).max(1);
    let chi2_reduced = r.norm_squared() / dof as f64;
    let jtj = j.transpose() * &j;
    let chi2_factor = opts.error_scaling.factor(chi2_reduced);
    let inv = jtj.try_inverse().ok_or_else(|| Error::Degenerate("the normal matrix of the fit is singular".into()))?
        * chi2_factor;
    let np = nc + 2;
    let mut cov = vec![0.0; np * np];
    for a in 0..n_free {
        for b in 0..n_free {
            // Symmetrize: the numerical inverse is symmetric only to rounding.
            cov[a * np + b] = 0.5 * (inv[(a, b)] + inv[(b, a)]);
        }
    }
    let (coeffs, centre) = problem.split(&params);
    let scaling =
        CovarianceScaling { mode: opts.error_scaling, chi2_reduced, chi2_factor, correlation_inflation: None };
    let model = RadialModel { first_power, coeffs, centre, centre_free: opts.free_centre, cov, scaling: Some(scaling) };
    let mut ss = 0.0;
    for b in &problem.bins {
        let (q, u) = model.qu(b.x, b.y);
        ss += (b.qu.q - q).powi(2) + (b.qu.u - u).powi(2);
    }
    let n_used = problem.bins.len();
    let rms_residual = (ss / (2 * n_used) as f64).sqrt();
    let mut all_w = vec![0.0; bins.len()];
    let mut k = 0;
    for (i, u) in used.iter().enumerate() {
        if *u {
            all_w[i] = weights[k];
            k += 1;
        }
    }
    Ok(RadialFit {
        model,
        chi2_reduced,
        correlation: None,
        exclusion_centre: start_centre,
        passes: 1,
        rms_residual,
        n_used,
        used,
        weights: all_w,
    })
}
