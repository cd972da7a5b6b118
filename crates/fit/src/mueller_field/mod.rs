//! The instrument's Mueller field, fitted jointly to several calibration fields of known sky
//! polarization, and its exact inversion for polarized targets.
//!
//! One sky field of known `(q_sky, u_sky)` gives two numbers per position: enough for the
//! paper's partial polarizer `M_I(p, phi)` (`eq:instpol`), not for a retardance, a rotation of
//! the polarization plane or a depolarization, which all shift the measured `(q, u)` of a
//! polarized sky by an amount proportional to it. Fields with different sky polarization
//! separate them. The model here is the linear block of the pre-analyzer Mueller matrix
//! ([`mueller::linear`]), either in its physical form (diattenuation; retardance vector,
//! rotation and depolarization each optional) or as the general 3 x 3 block (8 parameters with
//! `m00 = 1`); each free parameter is a 2-D polynomial of degree `deg` in the field position
//! (`deg = 0` and the observations of one position: the per-bin fit).
//!
//! The fit is Gauss-Newton on the one forward model [`LinearBlock::forward`], weighted by the
//! measured covariances plus the sky polarization's own uncertainty. Before fitting it asks
//! the Fisher matrix at the start point which parameter combinations the inputs constrain, and
//! refuses, naming the parameters and the reason, when any is unconstrained (e.g. a retardance
//! from one sky field) instead of returning numbers. Every fitted matrix is checked for
//! physical realizability.
//!
//! Around the fit: the block a field fits ([`block`]), its forms over the field ([`forms`],
//! [`smooth`]), the steps of a calibration ([`stars`]), the field in a calibration file with its
//! exact correction ([`cal`]), the physics that explains it ([`explain`]) and what a calibration
//! costs ([`plan`]).

pub mod block;
pub mod cal;
pub mod explain;
pub mod forms;
pub mod maps;
pub mod plan;
pub mod smooth;
pub mod stars;

use crate::lsq::{self, Linear, LsqError};
pub use crate::mueller_field::block::Kind;
pub use crate::mueller_field::forms::Smooth;
use crate::{Error, Result};
use field::{FieldModel, InstPol};
use mueller::linear::{self, LinearBlock};
use nalgebra::{DMatrix, DVector};

/// One measured position of one calibration field: normalized `(q, u)` and their covariance.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Observation {
    pub x_arcmin: f64,
    pub y_arcmin: f64,
    #[serde(flatten)]
    pub qu: mueller::Qu,
}

impl Observation {
    /// `(q, u)` with its covariance at `(x, y)` arcmin.
    pub fn new(x_arcmin: f64, y_arcmin: f64, q: f64, u: f64, var_q: f64, var_u: f64, cov_qu: f64) -> Self {
        Self { x_arcmin, y_arcmin, qu: mueller::Qu::new(q, u, var_q, var_u, cov_qu) }
    }
}

/// A calibration field: its known sky polarization (with a 1-sigma uncertainty on each of
/// `q_sky`, `u_sky`) and its measured positions.
#[derive(Debug, Clone, PartialEq)]
pub struct CalField {
    pub name: String,
    pub sky_q: f64,
    pub sky_u: f64,
    pub sigma_sky: f64,
    pub obs: Vec<Observation>,
}

impl CalField {
    /// A field whose sky has degree `p` (fraction) and angle `chi` (rad, `eq:polang`).
    pub fn from_p_chi(name: &str, p: f64, chi: f64, sigma_sky: f64, obs: Vec<Observation>) -> Self {
        let (s, c) = (2.0 * chi).sin_cos();
        Self { name: name.into(), sky_q: p * c, sky_u: p * s, sigma_sky, obs }
    }
}

/// Options of [`fit_mueller_field`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MuellerFitOptions {
    pub kind: Kind,
    /// Polynomial degree of every free parameter over the field (0: constant).
    pub deg: usize,
    /// Positions are divided by this (arcmin) before the polynomial: keeps the normal
    /// equations well conditioned (the field radius).
    pub scale_arcmin: f64,
    /// Smallest accepted ratio of the smallest to the largest eigenvalue of the scaled Fisher
    /// matrix; below it the parameters along the weak direction are called unconstrained.
    pub min_eigen_ratio: f64,
    pub max_iter: usize,
}

impl Default for MuellerFitOptions {
    fn default() -> Self {
        Self { kind: Kind::diattenuation_retardance(), deg: 2, scale_arcmin: 4.0, min_eigen_ratio: 1e-9, max_iter: 30 }
    }
}

/// Monomials `x^i y^j`, `i + j <= deg`, in a fixed order.
fn monomials(deg: usize, x: f64, y: f64, out: &mut Vec<f64>) {
    out.clear();
    for tot in 0..=deg {
        for j in 0..=tot {
            out.push(x.powi((tot - j) as i32) * y.powi(j as i32));
        }
    }
}

pub(crate) fn n_monomials(deg: usize) -> usize {
    (deg + 1) * (deg + 2) / 2
}

/// The powers `(i, j)` of the monomials `x^i y^j` in the order of the coefficients (what the
/// calibration file's `PX`, `PY` columns record).
pub(crate) fn monomial_powers(deg: usize) -> Vec<(usize, usize)> {
    let mut v = Vec::with_capacity(n_monomials(deg));
    for tot in 0..=deg {
        for j in 0..=tot {
            v.push((tot - j, j));
        }
    }
    v
}

/// A fitted Mueller field: every free parameter a polynomial over the field.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MuellerField {
    pub kind: Kind,
    pub deg: usize,
    pub scale_arcmin: f64,
    /// Free parameter indices (into the kind's full vector).
    pub free: Vec<usize>,
    /// Coefficients, parameter-major: `coeffs[k * n_mono + m]`.
    pub coeffs: Vec<f64>,
    /// Covariance of `coeffs` (row-major), already scaled by `chi2_dof` when it exceeds 1.
    pub cov: Vec<f64>,
    pub chi2_dof: f64,
    pub n_obs: usize,
    /// Condition number of the (diagonally scaled) Fisher matrix at the solution.
    pub condition: f64,
    /// Positions inside this box (arcmin, `[xmin, xmax, ymin, ymax]`) are inside the model.
    pub bounds: [f64; 4],
    /// Realizability findings (empty when every checked matrix is realizable within 3 sigma).
    pub warnings: Vec<String>,
    /// How the parameters vary over the field: the polynomial of `coeffs` (the joint fit), or
    /// a form built from the per-bin fits ([`crate::mueller_field::smooth`]; `coeffs`, `cov` then
    /// hold the radial form's coefficients, or nothing for the interpolant).
    #[serde(default)]
    pub smooth: Smooth,
}

impl MuellerField {
    /// The free parameters at a position and the matrix `A` (`n_free x n_coeffs`) that maps
    /// coefficient changes onto them.
    fn local(&self, x: f64, y: f64) -> (Vec<f64>, Vec<f64>) {
        let mut mono = Vec::new();
        monomials(self.deg, x / self.scale_arcmin, y / self.scale_arcmin, &mut mono);
        let nm = mono.len();
        let nf = self.free.len();
        let vals = (0..nf).map(|k| (0..nm).map(|m| self.coeffs[k * nm + m] * mono[m]).sum()).collect();
        let mut a = vec![0.0; nf * nf * nm];
        for k in 0..nf {
            for m in 0..nm {
                a[k * nf * nm + k * nm + m] = mono[m];
            }
        }
        (vals, a)
    }

    /// The full parameter vector at a position (NaN where the form has no value: outside
    /// the interpolant's hull).
    pub fn full_at(&self, x: f64, y: f64) -> Vec<f64> {
        let vals = match &self.smooth {
            Smooth::Poly => self.local(x, y).0,
            _ => self.params_at(x, y).0,
        };
        let mut full = self.kind.identity();
        for (k, &i) in self.free.iter().enumerate() {
            full[i] = vals[k];
        }
        full
    }

    /// The free parameters at a position with their covariance (`n_free x n_free`).
    pub fn params_at(&self, x: f64, y: f64) -> (Vec<f64>, Vec<f64>) {
        match &self.smooth {
            Smooth::Poly => {}
            Smooth::Radial(r) => return r.params_at(x, y),
            Smooth::Interp(i) => {
                let nf = self.free.len();
                return i.params_at(x, y).unwrap_or_else(|| (vec![f64::NAN; nf], vec![f64::NAN; nf * nf]));
            }
        }
        let (vals, a) = self.local(x, y);
        let (nf, nc) = (self.free.len(), self.coeffs.len());
        let a = DMatrix::from_row_slice(nf, nc, &a);
        let c = DMatrix::from_row_slice(nc, nc, &self.cov);
        let v = &a * c * a.transpose();
        (vals, v.as_slice().to_vec())
    }

    /// The linear block at a position.
    pub fn block_at(&self, x: f64, y: f64) -> LinearBlock {
        self.kind.block(&self.full_at(x, y))
    }

    /// The physical parameters at a position (physical kind only).
    pub fn physical_at(&self, x: f64, y: f64) -> Option<linear::Physical> {
        let f = self.full_at(x, y);
        match self.kind {
            Kind::Physical { .. } => {
                let (p, phi) = stokes::polarization(f[0], f[1]);
                let (retardance, retardance_axis) = linear::retardance_of_vector([f[2], f[3]]);
                Some(linear::Physical { p, phi, retardance, retardance_axis, rotation: f[4], depolarization: f[5] })
            }
            Kind::General => None,
        }
    }

    /// The measured `(q, u)` of a source `(q_sky, u_sky)` at a position: the forward model.
    pub fn forward_at(&self, x: f64, y: f64, q_sky: f64, u_sky: f64) -> Option<(f64, f64)> {
        self.block_at(x, y).forward(q_sky, u_sky)
    }

    /// `[var_q, cov_qu, var_u]` of `g(params)` at a position from the parameter covariance
    /// there (`J C J^T`, `J` by central differences in the free parameters); `None` when `g`
    /// has no value next to `full`.
    fn model_covariance(
        &self,
        x: f64,
        y: f64,
        full: &[f64],
        g: &dyn Fn(&[f64]) -> Option<(f64, f64)>,
    ) -> Option<[f64; 3]> {
        let (_, pc) = self.params_at(x, y);
        let nf = self.free.len();
        let h = 1e-7;
        let mut jp = vec![[0.0; 2]; nf];
        let (mut a, mut b) = (full.to_vec(), full.to_vec());
        for (k, &i) in self.free.iter().enumerate() {
            a[i] = full[i] + h;
            b[i] = full[i] - h;
            let (ra, rb) = (g(&a)?, g(&b)?);
            a[i] = full[i];
            b[i] = full[i];
            jp[k] = [(ra.0 - rb.0) / (2.0 * h), (ra.1 - rb.1) / (2.0 * h)];
        }
        let mut v = [0.0; 3];
        for k in 0..nf {
            for l in 0..nf {
                let c = pc[k * nf + l];
                v[0] += jp[k][0] * c * jp[l][0];
                v[1] += jp[k][0] * c * jp[l][1];
                v[2] += jp[k][1] * c * jp[l][1];
            }
        }
        Some(v)
    }

    /// The exact correction of a measured `(q, u)` (covariance `[var_q, cov_qu, var_u]`) at a
    /// position: the source's `(q, u)` and its covariance, propagated from the measurement and
    /// from the model's parameter covariance (Jacobians by central differences of the one
    /// inverse [`LinearBlock::invert`]).
    pub fn correct(&self, x: f64, y: f64, q: f64, u: f64, var: [f64; 3]) -> Result<((f64, f64), [f64; 3])> {
        let full = self.full_at(x, y);
        let inv = |full: &[f64], q: f64, u: f64| self.kind.block(full).invert(q, u);
        let (q0, u0) = inv(&full, q, u).ok_or_else(|| {
            Error::Degenerate(format!("the Mueller field at ({x:.3}, {y:.3}) arcmin is singular: no exact inverse"))
        })?;
        let h = 1e-7;
        let d = |dq: f64, du: f64| -> Option<[f64; 2]> {
            let a = inv(&full, q + dq, u + du)?;
            let b = inv(&full, q - dq, u - du)?;
            Some([(a.0 - b.0) / (2.0 * h), (a.1 - b.1) / (2.0 * h)])
        };
        let sing =
            || Error::Degenerate(format!("the Mueller field at ({x:.3}, {y:.3}) arcmin is singular near ({q}, {u})"));
        let jq = d(h, 0.0).ok_or_else(sing)?;
        let ju = d(0.0, h).ok_or_else(sing)?;
        // Measurement part: J S J^T with J = [[jq0, ju0], [jq1, ju1]].
        let (vq, c, vu) = (var[0], var[1], var[2]);
        let mut out = [
            jq[0] * jq[0] * vq + 2.0 * jq[0] * ju[0] * c + ju[0] * ju[0] * vu,
            jq[0] * jq[1] * vq + (jq[0] * ju[1] + ju[0] * jq[1]) * c + ju[0] * ju[1] * vu,
            jq[1] * jq[1] * vq + 2.0 * jq[1] * ju[1] * c + ju[1] * ju[1] * vu,
        ];
        // Model part: over the free parameters at this position.
        let m = self.model_covariance(x, y, &full, &|f| inv(f, q, u)).ok_or_else(sing)?;
        for (o, v) in out.iter_mut().zip(m) {
            *o += v;
        }
        Ok(((q0, u0), out))
    }
}

/// The instrumental polarization of unpolarized light (`M (1, 0, 0)` normalized) is what
/// every existing consumer of a [`FieldModel`] asks for: the Mueller field is one.
impl FieldModel for MuellerField {
    fn eval(&self, x: f64, y: f64) -> InstPol {
        let full = self.full_at(x, y);
        let Some((q, u)) = self.kind.block(&full).forward(0.0, 0.0) else {
            return InstPol { q: f64::NAN, u: f64::NAN, ..Default::default() };
        };
        let v = self.model_covariance(x, y, &full, &|f| self.kind.block(f).forward(0.0, 0.0)).unwrap_or([f64::NAN; 3]);
        InstPol { q, u, var_q: v[0], var_u: v[2], cov_qu: v[1] }
    }

    fn contains(&self, x: f64, y: f64) -> bool {
        // 1e-9 arcmin of slack: a box read back from FITS keywords (16 significant digits)
        // must still hold the bin centres it was fitted on.
        let (b, t) = (self.bounds, 1e-9);
        let in_box = x >= b[0] - t && x <= b[1] + t && y >= b[2] - t && y <= b[3] + t;
        match &self.smooth {
            Smooth::Interp(i) => in_box && i.params_at(x, y).is_some(),
            _ => in_box,
        }
    }

    fn params(&self) -> Vec<f64> {
        self.coeffs.clone()
    }

    fn covariance(&self) -> Option<Vec<f64>> {
        Some(self.cov.clone())
    }

    /// The fitted block itself (the field is not a partial polarizer alone).
    fn block_at(&self, x: f64, y: f64) -> LinearBlock {
        MuellerField::block_at(self, x, y)
    }

    /// The fitted block says nothing of circular polarization: none is passed on
    /// ([`LinearBlock::to_mueller`]).
    fn mueller_at(&self, x: f64, y: f64) -> mueller::Mueller {
        MuellerField::block_at(self, x, y).to_mueller()
    }

    fn describe(&self) -> String {
        let names: Vec<&str> = self.free.iter().map(|&i| self.kind.name(i)).collect();
        let form = match &self.smooth {
            Smooth::Poly => format!("degree-{} polynomials", self.deg),
            Smooth::Radial(_) => format!("radial patterns about the origin, powers 1..{} of r", self.deg),
            Smooth::Interp(i) => format!("natural-neighbour interpolants of {} per-bin fits", i.points().len()),
        };
        format!(
            "Mueller field ({}: {}), parameters [{}] as {form}",
            self.kind.model_name(),
            self.kind.free_words().join(", "),
            names.join(", "),
        )
    }
}

/// The observations grouped by position (the fields share positions): each position's
/// monomials once, its rows contiguous.
struct Data {
    nm: usize,
    /// `npos x nm`, row-major.
    mono: Vec<f64>,
    /// Rows of position `p` are `rows[start[p]..start[p + 1]]`.
    start: Vec<usize>,
    rows: Vec<Row>,
}

impl Data {
    fn n_pos(&self) -> usize {
        self.start.len() - 1
    }
    fn mono(&self, p: usize) -> &[f64] {
        &self.mono[p * self.nm..(p + 1) * self.nm]
    }
    fn rows(&self, p: usize) -> &[Row] {
        &self.rows[self.start[p]..self.start[p + 1]]
    }
    /// The full parameter vector at position `p`.
    fn full(&self, p: usize, free: &[usize], coef: &[f64], full: &mut [f64]) {
        let m = self.mono(p);
        let nm = self.nm;
        for (k, &i) in free.iter().enumerate() {
            full[i] = coef[k * nm..(k + 1) * nm].iter().zip(m).map(|(c, x)| c * x).sum();
        }
    }
}

/// One observation with everything the fit needs, flattened.
#[derive(Clone, Copy)]
struct Row {
    sky: (f64, f64),
    meas: (f64, f64),
    /// Inverse covariance `[w_qq, w_qu, w_uu]`.
    w: [f64; 3],
}

/// Distinct sky polarization states among the fields (states closer than 3 sigma of the sky
/// or 1e-4 are one).
fn distinct_skies(fields: &[CalField]) -> Vec<(f64, f64)> {
    let mut out: Vec<(f64, f64, f64)> = Vec::new();
    for f in fields {
        let tol = (3.0 * f.sigma_sky).max(1e-4);
        if !out.iter().any(|&(q, u, t)| mueller::hypot(q - f.sky_q, u - f.sky_u) < tol.max(t)) {
            out.push((f.sky_q, f.sky_u, tol));
        }
    }
    out.into_iter().map(|(q, u, _)| (q, u)).collect()
}

/// Fit the Mueller field jointly to several calibration fields.
///
/// Refuses ([`Error::Degenerate`], with the parameters and the reason) when the inputs cannot
/// separate the free parameters; refuses a field with no usable observation or a bad sky.
pub fn fit_mueller_field(fields: &[CalField], opts: &MuellerFitOptions) -> Result<MuellerField> {
    if fields.is_empty() {
        return Err(Error::Input("no calibration field given".into()));
    }
    let deg = opts.deg;
    let nm = n_monomials(deg);
    let free = opts.kind.free();
    let nf = free.len();
    let n = nf * nm;
    if !(opts.scale_arcmin > 0.0 && opts.scale_arcmin.is_finite()) {
        return Err(Error::Input(format!("scale_arcmin = {} must be positive", opts.scale_arcmin)));
    }
    // (position key, row) pairs; grouped by position below.
    let mut keyed: Vec<((u64, u64), Row)> = Vec::new();
    let mut bounds = [f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY];
    for f in fields {
        if !(mueller::hypot(f.sky_q, f.sky_u) < 1.0) || !(f.sigma_sky >= 0.0) {
            return Err(Error::Input(format!(
                "field '{}': sky (q, u) = ({}, {}) +- {} is not a physical polarization",
                f.name, f.sky_q, f.sky_u, f.sigma_sky
            )));
        }
        let before = keyed.len();
        let s2 = f.sigma_sky * f.sigma_sky;
        for o in &f.obs {
            let (a, b, c) = (o.qu.var_q + s2, o.qu.cov_qu, o.qu.var_u + s2);
            let det = a * c - b * b;
            let ok = [o.x_arcmin, o.y_arcmin, o.qu.q, o.qu.u].iter().all(|v| v.is_finite())
                && a > 0.0
                && c > 0.0
                && det > 0.0;
            if !ok {
                continue;
            }
            keyed.push((
                (o.x_arcmin.to_bits(), o.y_arcmin.to_bits()),
                Row { sky: (f.sky_q, f.sky_u), meas: (o.qu.q, o.qu.u), w: [c / det, -b / det, a / det] },
            ));
            bounds = [
                bounds[0].min(o.x_arcmin),
                bounds[1].max(o.x_arcmin),
                bounds[2].min(o.y_arcmin),
                bounds[3].max(o.y_arcmin),
            ];
        }
        if keyed.len() == before {
            return Err(Error::Input(format!(
                "field '{}': no usable observation (finite q, u with positive variances)",
                f.name
            )));
        }
    }
    let n_rows = keyed.len();
    let data = {
        let mut order: Vec<usize> = (0..n_rows).collect();
        order.sort_by_key(|&i| keyed[i].0);
        let (mut mono, mut start, mut rows) = (Vec::new(), Vec::new(), Vec::with_capacity(n_rows));
        let mut m = Vec::with_capacity(nm);
        let mut last = None;
        for i in order {
            let (key, row) = &keyed[i];
            if last != Some(*key) {
                last = Some(*key);
                start.push(rows.len());
                let (x, y) = (f64::from_bits(key.0), f64::from_bits(key.1));
                monomials(deg, x / opts.scale_arcmin, y / opts.scale_arcmin, &mut m);
                mono.extend_from_slice(&m);
            }
            rows.push(*row);
        }
        start.push(rows.len());
        Data { nm, mono, start, rows }
    };
    if 2 * n_rows < n {
        return Err(Error::TooFewBins { used: n_rows, total: n_rows, needed: n.div_ceil(2) });
    }

    // Start: no instrumental effect except a first-order diattenuation, the mean of
    // (measured - sky) as the constant term (first-order eq:approx).
    let mut coef = vec![0.0; n];
    let kind = opts.kind;
    let ident = kind.identity();
    for (k, &i) in free.iter().enumerate() {
        coef[k * nm] = ident[i];
    }
    if let Kind::Physical { .. } = kind {
        let m = n_rows as f64;
        coef[0] = data.rows.iter().map(|r| r.meas.0 - r.sky.0).sum::<f64>() / m;
        coef[nm] = data.rows.iter().map(|r| r.meas.1 - r.sky.1).sum::<f64>() / m;
    }

    // Identifiability, from the Fisher matrix at the start (and, for the retardance, a probe
    // with a small retardance along each axis, because |g| has no derivative at g = 0).
    let (fisher, _, chi2) = normal_equations(&data, kind, &free, &coef);
    check_constrained(&fisher, kind, &free, nm, fields, opts.min_eigen_ratio)?;

    // Levenberg-Marquardt from the start, whose chi^2 is the normal equations' (which leave
    // out a row whose forward model fails, where `chi2_of` counts it infinite).
    let policy = lsq::Policy { max_iter: opts.max_iter, ..lsq::MUELLER_FIELD };
    let coef = lsq::run(&Fit { data: &data, kind, free: &free }, coef, chi2, &policy).x;
    let (fisher, _, chi2) = normal_equations(&data, kind, &free, &coef);
    let dof = (2 * n_rows - n) as f64;
    let chi2_dof = chi2 / dof;
    let (cov, condition) = invert_scaled(&fisher)
        .ok_or_else(|| Error::Degenerate("the Fisher matrix at the solution is singular".into()))?;
    // Inflate by chi2_dof when it exceeds 1 and has enough degrees of freedom to mean it (a
    // per-bin fit with 2 dof would otherwise scale its errors by noise).
    let scale = if dof >= 30.0 { chi2_dof.max(1.0) } else { 1.0 };
    let cov: Vec<f64> = cov.iter().map(|c| c * scale).collect();
    let mut mf = MuellerField {
        kind,
        deg,
        scale_arcmin: opts.scale_arcmin,
        free,
        coeffs: coef,
        cov,
        chi2_dof,
        n_obs: n_rows,
        condition,
        bounds,
        warnings: Vec::new(),
        smooth: Smooth::Poly,
    };
    mf.warnings = realizability(&mf, fields);
    // Residuals far above their errors: a wrong model, wrong errors or a sky declared wrongly
    // (the radial fit's bound); the numbers still come, with the warning. Far below 1: the
    // maps' errors are larger than their scatter about the model (over-estimated errors, or
    // noiseless simulated maps), and the coefficient errors, not scaled down, are too large by
    // about 1 / sqrt(chi2_dof). Only with the degrees of freedom to mean it, as the error
    // scaling above (a per-bin fit has 2).
    if dof >= 30.0 && !(mf.chi2_dof <= 10.0) {
        mf.warnings.push(format!(
            "reduced chi^2 of the joint fit is {:.3e}, far from 1: the model or the errors do not describe the fields (check each field's declared sky P and chi, and the maps' errors)",
            mf.chi2_dof
        ));
    }
    if dof >= 30.0 && mf.chi2_dof < 0.1 {
        mf.warnings.push(format!(
            "reduced chi^2 of the joint fit is {:.3e} with {dof} degrees of freedom: the maps' errors look over-estimated by ~{:.1}x (1/sqrt(chi2_dof)); the coefficient errors are not scaled down and are as conservative",
            mf.chi2_dof,
            1.0 / mf.chi2_dof.max(1e-300).sqrt()
        ));
    }
    Ok(mf)
}

/// The joint fit as a least-squares problem: its chi^2 at a point, its normal equations.
struct Fit<'a> {
    data: &'a Data,
    kind: Kind,
    free: &'a [usize],
}

impl lsq::Problem for Fit<'_> {
    type Eval = f64;
    type Lin = ();
    fn evaluate(&self, coef: &[f64]) -> std::result::Result<f64, LsqError> {
        Ok(chi2_of(self.data, self.kind, self.free, coef))
    }
    fn chi2(&self, chi2: &f64) -> f64 {
        *chi2
    }
    fn linearize(&self, coef: &[f64], _: &f64) -> std::result::Result<Linear<()>, LsqError> {
        // Its vector is `J^T W (measured - model)`: the right-hand side of the step.
        let (normal, rhs, _) = normal_equations(self.data, self.kind, self.free, coef);
        Ok(Linear { normal, rhs, kept: (), design: None })
    }
}

/// `(J^T W J, J^T W r, chi2)` over all rows at coefficients `coef`. The Jacobian of the
/// forward model is taken per position in the `n_free` block parameters (central differences
/// of the one forward model), so the normal matrix is `sum_p K_p (x) m_p m_p^T` over positions
/// with `K_p` the `n_free x n_free` information of position `p` and `m_p` its monomials:
/// computed as `Z^T diag(K_kl) Z` for each parameter pair (matrix products, not a rank-one
/// update per observation).
fn normal_equations(d: &Data, kind: Kind, free: &[usize], coef: &[f64]) -> (DMatrix<f64>, DVector<f64>, f64) {
    let nf = free.len();
    let nm = d.nm;
    let np = d.n_pos();
    let n = nf * nm;
    let mut kp = vec![0.0; np * nf * nf];
    let mut bp = vec![0.0; np * nf];
    let mut chi2 = 0.0;
    let mut full = kind.identity();
    let h = 1e-7;
    let mut plus = Vec::with_capacity(nf);
    let mut dv = vec![[0.0f64; 2]; nf];
    for p in 0..np {
        d.full(p, free, coef, &mut full);
        let b0 = kind.block(&full);
        plus.clear();
        for &i in free {
            let v = full[i];
            full[i] = v + h;
            let a = kind.block(&full);
            full[i] = v - h;
            let b = kind.block(&full);
            full[i] = v;
            plus.push((a, b));
        }
        let k = &mut kp[p * nf * nf..(p + 1) * nf * nf];
        let bb = &mut bp[p * nf..(p + 1) * nf];
        for r in d.rows(p) {
            let Some(pred) = b0.forward(r.sky.0, r.sky.1) else { continue };
            let res = (r.meas.0 - pred.0, r.meas.1 - pred.1);
            chi2 += r.w[0] * res.0 * res.0 + 2.0 * r.w[1] * res.0 * res.1 + r.w[2] * res.1 * res.1;
            for (j, (a, b)) in plus.iter().enumerate() {
                let pa = a.forward(r.sky.0, r.sky.1).unwrap_or(pred);
                let pb = b.forward(r.sky.0, r.sky.1).unwrap_or(pred);
                dv[j] = [(pa.0 - pb.0) / (2.0 * h), (pa.1 - pb.1) / (2.0 * h)];
            }
            for j in 0..nf {
                let wq = r.w[0] * dv[j][0] + r.w[1] * dv[j][1];
                let wu = r.w[1] * dv[j][0] + r.w[2] * dv[j][1];
                bb[j] += wq * res.0 + wu * res.1;
                for l in j..nf {
                    k[j * nf + l] += wq * dv[l][0] + wu * dv[l][1];
                }
            }
        }
    }
    let z = DMatrix::from_row_slice(np, nm, &d.mono);
    let mut a = DMatrix::zeros(n, n);
    let mut b = DVector::zeros(n);
    let mut wz = z.clone();
    for j in 0..nf {
        let bj = DVector::from_iterator(np, (0..np).map(|p| bp[p * nf + j]));
        b.rows_mut(j * nm, nm).copy_from(&(z.transpose() * bj));
        for l in j..nf {
            for p in 0..np {
                let w = kp[p * nf * nf + j * nf + l];
                for m in 0..nm {
                    wz[(p, m)] = w * z[(p, m)];
                }
            }
            let blk = z.transpose() * &wz;
            a.view_mut((j * nm, l * nm), (nm, nm)).copy_from(&blk);
            if l != j {
                a.view_mut((l * nm, j * nm), (nm, nm)).copy_from(&blk.transpose());
            }
        }
    }
    (a, b, chi2)
}

fn chi2_of(d: &Data, kind: Kind, free: &[usize], coef: &[f64]) -> f64 {
    let mut full = kind.identity();
    let mut chi2 = 0.0;
    for p in 0..d.n_pos() {
        d.full(p, free, coef, &mut full);
        let blk = kind.block(&full);
        for r in d.rows(p) {
            let Some(pred) = blk.forward(r.sky.0, r.sky.1) else { return f64::INFINITY };
            let res = (r.meas.0 - pred.0, r.meas.1 - pred.1);
            chi2 += r.w[0] * res.0 * res.0 + 2.0 * r.w[1] * res.0 * res.1 + r.w[2] * res.1 * res.1;
        }
    }
    chi2
}

/// Inverse of a symmetric positive definite matrix through its diagonal scaling (the
/// correlation form), and the condition number of that scaled matrix.
fn invert_scaled(a: &DMatrix<f64>) -> Option<(Vec<f64>, f64)> {
    let n = a.nrows();
    let d: Vec<f64> = (0..n).map(|i| a[(i, i)].max(0.0).sqrt()).collect();
    if d.iter().any(|&v| !(v > 0.0)) {
        return None;
    }
    let s = DMatrix::from_fn(n, n, |i, j| a[(i, j)] / (d[i] * d[j]));
    let eig = s.clone().symmetric_eigen();
    let (mx, mn) = (eig.eigenvalues.max(), eig.eigenvalues.min());
    if !(mn > 0.0) {
        return None;
    }
    let inv = s.cholesky()?.inverse();
    let cov = DMatrix::from_fn(n, n, |i, j| inv[(i, j)] / (d[i] * d[j]));
    Some((cov.as_slice().to_vec(), mx / mn))
}

/// Refuse, naming the parameters and the reason, when the scaled Fisher matrix has a
/// direction with (almost) no information.
fn check_constrained(
    fisher: &DMatrix<f64>,
    kind: Kind,
    free: &[usize],
    nm: usize,
    fields: &[CalField],
    min_ratio: f64,
) -> Result<()> {
    let n = fisher.nrows();
    let diag: Vec<f64> = (0..n).map(|i| fisher[(i, i)]).collect();
    let dmax = diag.iter().cloned().fold(0.0, f64::max);
    // A parameter the data do not touch at all has a zero diagonal.
    let mut weak = vec![false; free.len()];
    for (p, &d) in diag.iter().enumerate() {
        if !(d > min_ratio * dmax) {
            weak[p / nm] = true;
        }
    }
    if !weak.iter().any(|&w| w) {
        // The judge's scaled spectrum (the field has its normal matrix only, accumulated
        // from each datum's 2 x 2 weight), with the fit's own tolerance on eigenvalues.
        for v in crate::conditioning::weak_directions(fisher, min_ratio) {
            for (p, c) in v.iter().enumerate() {
                if c.abs() > 0.2 {
                    weak[p / nm] = true;
                }
            }
        }
    }
    if !weak.iter().any(|&w| w) {
        return Ok(());
    }
    let mut groups: Vec<&str> = Vec::new();
    for (k, &i) in free.iter().enumerate() {
        if weak[k] && !groups.contains(&kind.group(i)) {
            groups.push(kind.group(i));
        }
    }
    // The diattenuation is today's model and what one field determines: when it shares a weak
    // direction with another effect, the other effect is the one the inputs cannot give.
    let told_apart = if groups.len() > 1 && groups.contains(&"diattenuation") {
        groups.retain(|g| *g != "diattenuation");
        " (cannot be told from the diattenuation)"
    } else {
        ""
    };
    let skies = distinct_skies(fields);
    let n_per = free.len();
    let reason = if skies.len() == 1 {
        let (p, chi) = stokes::polarization(skies[0].0, skies[0].1);
        format!(
            "one sky polarization state (P_sky = {:.3} %, chi_sky = {:.1} deg) gives 2 numbers per position for {n_per} parameters; need >= 2 fields with different sky polarization (chi_sky, or P_sky){}",
            100.0 * p,
            chi.to_degrees(),
            if n_per > 4 { ", >= 3 not on one line in (q, u) for rotation or depolarization too" } else { "" }
        )
    } else {
        format!(
            "{} distinct sky polarization states give {} numbers per position for {n_per} parameters; need more fields whose sky (q, u) are not on one line (or fewer free parameters)",
            skies.len(),
            2 * skies.len()
        )
    };
    Err(Error::Degenerate(format!("{} unconstrained{told_apart}: {reason}", groups.join(", "))))
}

/// Realizability of the fitted matrices at every observed position: the Stokes criterion on
/// the block and, for the physical form, Cloude's test on the whole matrix and the parameter
/// ranges, each judged against 3 sigma of the model there.
fn realizability(mf: &MuellerField, fields: &[CalField]) -> Vec<String> {
    let mut bad_excess = 0usize;
    let mut bad_depol = 0usize;
    let mut checked = 0usize;
    let mut seen = std::collections::HashSet::new();
    for o in fields.iter().flat_map(|f| f.obs.iter()) {
        if !seen.insert((o.x_arcmin.to_bits(), o.y_arcmin.to_bits())) {
            continue;
        }
        checked += 1;
        let (_, pc) = mf.params_at(o.x_arcmin, o.y_arcmin);
        let nf = mf.free.len();
        let sig = (0..nf).map(|k| pc[k * nf + k].max(0.0).sqrt()).fold(0.0, f64::max);
        let block = mf.block_at(o.x_arcmin, o.y_arcmin).normalized();
        if block.max_polarization_excess() > 3.0 * sig {
            bad_excess += 1;
        }
        if let Some(ph) = mf.physical_at(o.x_arcmin, o.y_arcmin) {
            if let Some(k) = mf.free.iter().position(|&i| i == 5) {
                if ph.depolarization < -3.0 * pc[k * nf + k].max(0.0).sqrt() {
                    bad_depol += 1;
                }
            }
        }
    }
    let mut w = Vec::new();
    if bad_excess > 0 {
        w.push(format!(
            "{bad_excess} of {checked} positions: the fitted block polarizes beyond 100 % for some input (Stokes criterion) by more than 3 sigma: not a physical Mueller matrix"
        ));
    }
    if bad_depol > 0 {
        w.push(format!("{bad_depol} of {checked} positions: negative depolarization beyond 3 sigma (the block amplifies polarization)"));
    }
    w
}

/// A per-position fit (degree 0 at each distinct position present in every field).
#[derive(Debug, Clone, PartialEq)]
pub struct BinFit {
    pub x_arcmin: f64,
    pub y_arcmin: f64,
    pub field: MuellerField,
}

/// Fit every distinct position on its own (the per-bin Mueller matrices). Positions are
/// matched across fields by identical coordinates (the same binning); a position missing from
/// a field uses the fields it has, and is skipped when those cannot constrain the model.
/// Returns the fits and the number of positions skipped.
pub fn fit_per_bin(fields: &[CalField], opts: &MuellerFitOptions) -> Result<(Vec<BinFit>, usize)> {
    use rayon::prelude::*;
    let mut keys: Vec<(u64, u64)> = Vec::new();
    let mut index = std::collections::HashMap::new();
    let mut per: Vec<Vec<Vec<Observation>>> = Vec::new();
    for (fi, f) in fields.iter().enumerate() {
        for o in &f.obs {
            let key = (o.x_arcmin.to_bits(), o.y_arcmin.to_bits());
            let k = *index.entry(key).or_insert_with(|| {
                keys.push(key);
                per.push(vec![Vec::new(); fields.len()]);
                keys.len() - 1
            });
            per[k][fi].push(*o);
        }
    }
    let o = MuellerFitOptions { deg: 0, ..*opts };
    let res: Vec<Option<BinFit>> = per
        .par_iter()
        .zip(keys.par_iter())
        .map(|(obs, key)| {
            let sub: Vec<CalField> = fields
                .iter()
                .zip(obs)
                .filter(|(_, o)| !o.is_empty())
                .map(|(f, o)| CalField { obs: o.clone(), ..f.clone() })
                .collect();
            fit_mueller_field(&sub, &o).ok().map(|field| BinFit {
                x_arcmin: f64::from_bits(key.0),
                y_arcmin: f64::from_bits(key.1),
                field,
            })
        })
        .collect();
    let skipped = res.iter().filter(|r| r.is_none()).count();
    let fits: Vec<BinFit> = res.into_iter().flatten().collect();
    if fits.is_empty() {
        // Say why, from the whole set.
        fit_mueller_field(fields, &o)?;
        return Err(Error::Degenerate("no position could be fitted on its own".into()));
    }
    Ok((fits, skipped))
}

/// The format tag of a Mueller-field file ([`MuellerField::to_json`]).
pub const FORMAT: &str = "instpol-mueller-field-v1";

#[derive(serde::Serialize, serde::Deserialize)]
struct FileForm {
    format: String,
    field: MuellerField,
}

impl MuellerField {
    /// The field as a JSON document tagged [`FORMAT`].
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(&FileForm { format: FORMAT.into(), field: self.clone() }).expect("plain data")
    }

    /// Read a field written by [`to_json`](Self::to_json); `what` names the input in errors.
    /// Refuses another format, inconsistent lengths and non-finite coefficients.
    pub fn from_json(text: &str, what: &str) -> Result<Self> {
        let f: FileForm =
            serde_json::from_str(text).map_err(|e| Error::Input(format!("{what}: not a Mueller-field file: {e}")))?;
        if f.format != FORMAT {
            return Err(Error::Input(format!("{what}: format '{}' is not {FORMAT}", f.format)));
        }
        let m = f.field;
        let n = match &m.smooth {
            Smooth::Poly => m.free.len() * n_monomials(m.deg),
            Smooth::Radial(_) => crate::mueller_field::forms::radial_rows(m.kind, m.deg)
                .map_err(|e| Error::Input(format!("{what}: {e}")))?
                .len(),
            Smooth::Interp(_) => 0,
        };
        let full = m.kind.identity().len();
        if m.deg > 12
            || m.coeffs.len() != n
            || m.cov.len() != n * n
            || m.free.iter().any(|&i| i >= full)
            || m.free != m.kind.free()
        {
            return Err(Error::Input(format!("{what}: coefficient or covariance lengths do not match the model")));
        }
        if !m.coeffs.iter().chain(&m.cov).all(|v| v.is_finite()) || !(m.scale_arcmin > 0.0) {
            return Err(Error::Input(format!("{what}: non-finite coefficient or covariance, or bad scale")));
        }
        Ok(m)
    }
}

/// The valid bins of a Stokes map as observations (bin centres in arcmin, the scatter errors
/// of the bin means).
pub fn observations_of_map(map: &skyfield::maps::StokesMap) -> Vec<Observation> {
    map.valid_bins()
        .map(|(k, i, j)| {
            let (x, y) = map.geometry.centre_arcmin(i, j);
            Observation::new(
                x,
                y,
                map.q[k],
                map.u[k],
                map.sigma_q[k] * map.sigma_q[k],
                map.sigma_u[k] * map.sigma_u[k],
                map.cov_qu[k],
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn obs(q: f64, u: f64) -> Vec<Observation> {
        (0..25).map(|k| Observation::new((k % 5) as f64 - 2.0, (k / 5) as f64 - 2.0, q, u, 1e-8, 1e-8, 0.0)).collect()
    }

    /// With the diattenuation alone, the Mueller correction is the paper's exact inversion of
    /// `eq:instpol` (`correct::invert_exact_matrix`, a separate 4 x 4 implementation): today's
    /// calibrations are the special case.
    #[test]
    fn diattenuation_only_correction_is_the_exact_eq_instpol_inverse() {
        let (p, phi) = (0.004f64, 0.6f64);
        let blk = linear::Physical { p, phi, ..Default::default() }.block();
        let (q1, u1) = blk.forward(0.0645 * 0.3, 0.0645 * 0.95).unwrap();
        let f =
            CalField { name: "b".into(), sky_q: 0.0645 * 0.3, sky_u: 0.0645 * 0.95, sigma_sky: 0.0, obs: obs(q1, u1) };
        let kind = Kind::Physical { retardance: false, rotation: false, depolarization: false };
        let mf = fit_mueller_field(&[f], &MuellerFitOptions { kind, deg: 0, ..Default::default() }).unwrap();
        let ph = mf.physical_at(0.0, 0.0).unwrap();
        assert!((ph.p - p).abs() < 1e-12 && (ph.phi - phi).abs() < 1e-9, "{ph:?}");
        let ((q0, u0), _) = mf.correct(0.5, -0.5, 0.03, -0.01, [1e-8, 0.0, 1e-8]).unwrap();
        let (qw, uw) = crate::correction::correct::invert_exact_matrix(p, phi, 0.03, -0.01).unwrap();
        assert!((q0 - qw).abs() < 1e-11 && (u0 - uw).abs() < 1e-11);
        // serde_json parses floats to within an ulp (no float_roundtrip feature).
        let back = MuellerField::from_json(&mf.to_json(), "test").unwrap();
        assert_eq!((back.kind, back.deg, &back.free), (mf.kind, mf.deg, &mf.free));
        for (a, b) in back.coeffs.iter().chain(&back.cov).zip(mf.coeffs.iter().chain(&mf.cov)) {
            assert!((a - b).abs() <= 4.0 * f64::EPSILON * b.abs());
        }
        assert!(MuellerField::from_json("{\"format\": \"x\"}", "bad.json")
            .unwrap_err()
            .to_string()
            .contains("bad.json"));
    }

    /// Error propagation of the correction: the propagated measurement part equals the
    /// closed form for an identity block (the Jacobian is the identity).
    #[test]
    fn identity_block_passes_errors_through() {
        let f1 = CalField { name: "a".into(), sky_q: 0.05, sky_u: 0.0, sigma_sky: 0.0, obs: obs(0.05, 0.0) };
        let f2 = CalField { name: "b".into(), sky_q: 0.0, sky_u: 0.05, sigma_sky: 0.0, obs: obs(0.0, 0.05) };
        let mf = fit_mueller_field(&[f1, f2], &MuellerFitOptions { deg: 0, ..Default::default() }).unwrap();
        let ((q, u), c) = mf.correct(0.0, 0.0, 0.01, 0.02, [4e-8, 1e-8, 9e-8]).unwrap();
        assert!((q - 0.01).abs() < 1e-9 && (u - 0.02).abs() < 1e-9);
        // Model variance is tiny (1e-8 data over 25 positions): within 5 %.
        assert!(
            (c[0] / 4e-8 - 1.0).abs() < 0.05 && (c[2] / 9e-8 - 1.0).abs() < 0.05 && (c[1] / 1e-8 - 1.0).abs() < 0.1,
            "{c:?}"
        );
    }
}
