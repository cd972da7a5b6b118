//! Which physics explains a fitted Mueller field: candidate causes, each a
//! field of linear blocks with a few parameters, fitted by least squares to a fitted Mueller
//! field ([`crate::mueller_field`]) with its covariance, and ranked.
//!
//! The candidates ([`Cause`]): the collimator's own polarization ray trace
//! (`mueller::raytrace`, amplitude free), a stressed lens, a tilted half-wave plate, a wedged
//! half-wave plate and a polarizing half-wave plate (`mueller::causes`), and the null
//! candidate "nothing beyond the diattenuation". The plate causes act on the modulation, so
//! each is turned into the block it is equivalent to after the demodulation
//! (`stokes::equivalent`, the one Stokes solver at the data's HWP angles).
//!
//! What is compared: the paper's diattenuation `M_I(p, phi)` (`eq:instpol`) is what one sky
//! field measures and every candidate may sit on top of some diattenuation field, so the
//! diattenuation is a nuisance: the comparison uses the parameters a diattenuation cannot make
//! (retardance vector, rotation, depolarization of the physical form; the `Q, U` block
//! `m11, m12, m21, m22` of the general form) and their covariance, which is the exact
//! marginalization over the diattenuation for Gaussian errors. A field fitted with the
//! diattenuation alone has nothing to compare and is refused.
//!
//! Two targets: the smooth field of a Mueller-field file (its polynomial coefficients and
//! their covariance; a candidate's field is projected onto the same polynomial basis by least
//! squares over a grid inside the file's bounds) or per-bin fits (each bin's parameters and
//! covariance). Each candidate is fitted by Levenberg-Marquardt from several starts on the
//! whitened residuals; the ranking uses chi^2 and the Bayesian information criterion
//! `BIC = chi^2 + k ln n` (Schwarz 1978); candidates within `DELTA_BIC` of the best are
//! reported as not told apart by the data, never silently dropped.

use crate::lsq::{self, Linear, LsqError};
use crate::mueller_field::{BinFit, Kind, MuellerField};
use crate::{Error, Result};
use mueller::causes::{self, UniaxialPlate};
use mueller::linear::{physical_block, retardance_vector, LinearBlock};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;
use stokes::StokesSolver;

/// Two candidates whose BIC differ by less than this are not told apart ("very strong"
/// evidence starts at 10: Kass & Raftery 1995, JASA 90, 773, sec. 3.2).
pub const DELTA_BIC: f64 = 10.0;

/// A candidate cause of the field.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Cause {
    /// Nothing beyond the diattenuation (no parameter).
    DiattenuationOnly,
    /// The polarization ray trace of the collimator, its deviation from the identity scaled.
    Raytrace,
    /// A stressed lens ([`causes::stressed_lens`]).
    StressedLens,
    /// A tilted half-wave plate ([`causes::tilted_hwp`]).
    TiltedHwp,
    /// A wedged half-wave plate ([`causes::wedged_hwp`]).
    WedgedHwp,
    /// A polarizing half-wave plate (`mueller::Hwp`'s pleochroism: a partial polarizer turning
    /// with the plate).
    PolarizingHwp,
}

impl Cause {
    pub const ALL: [Cause; 6] = [
        Cause::DiattenuationOnly,
        Cause::Raytrace,
        Cause::StressedLens,
        Cause::TiltedHwp,
        Cause::WedgedHwp,
        Cause::PolarizingHwp,
    ];

    pub fn name(&self) -> &'static str {
        match self {
            Cause::DiattenuationOnly => "diattenuation_only",
            Cause::Raytrace => "raytrace",
            Cause::StressedLens => "stressed_lens",
            Cause::TiltedHwp => "tilted_hwp",
            Cause::WedgedHwp => "wedged_hwp",
            Cause::PolarizingHwp => "polarizing_hwp",
        }
    }

    /// Names (with units) of the parameters.
    pub fn param_names(&self) -> &'static [&'static str] {
        match self {
            Cause::DiattenuationOnly => &[],
            Cause::Raytrace => &["amplitude"],
            Cause::StressedLens => &["retardance_edge_deg", "centre_x_arcmin", "centre_y_arcmin", "axis_offset_deg"],
            Cause::TiltedHwp => &["tilt_deg", "tilt_azimuth_deg"],
            Cause::WedgedHwp => &["retardance_error_deg", "gradient_x_deg_per_arcmin", "gradient_y_deg_per_arcmin"],
            Cause::PolarizingHwp => &["diattenuation", "angle_deg"],
        }
    }

    /// Typical size of each parameter (finite-difference steps and damping).
    fn scales(&self) -> &'static [f64] {
        match self {
            Cause::DiattenuationOnly => &[],
            Cause::Raytrace => &[1.0],
            Cause::StressedLens => &[10.0, 1.0, 1.0, 10.0],
            Cause::TiltedHwp => &[1.0, 30.0],
            Cause::WedgedHwp => &[1.0, 0.3, 0.3],
            Cause::PolarizingHwp => &[1e-3, 30.0],
        }
    }

    /// Start points of the fit (the problems are not convex: signs and axes are ambiguous).
    fn starts(&self, r: f64) -> Vec<Vec<f64>> {
        let mut v = Vec::new();
        match self {
            Cause::DiattenuationOnly => v.push(vec![]),
            Cause::Raytrace => v.push(vec![1.0]),
            Cause::StressedLens => {
                for a in [10.0, 30.0] {
                    for (x, y) in [(0.0, 0.0), (0.3 * r, 0.0), (-0.3 * r, 0.0), (0.0, 0.3 * r), (0.0, -0.3 * r)] {
                        for off in [0.0, 22.5, 45.0, 67.5] {
                            v.push(vec![a, x, y, off]);
                        }
                    }
                }
            }
            Cause::TiltedHwp => {
                for t in [2.0, 8.0, 20.0] {
                    for az in [0.0, 60.0, 120.0, 180.0, 240.0, 300.0] {
                        v.push(vec![t, az]);
                    }
                }
            }
            Cause::WedgedHwp => {
                for p in [[5.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 2.0], [10.0, 1.0, 1.0], [-10.0, -1.0, 1.0]] {
                    v.push(p.to_vec());
                }
            }
            Cause::PolarizingHwp => {
                for psi in [0.0, 45.0, 90.0, 135.0] {
                    v.push(vec![0.01, psi]);
                }
            }
        }
        v
    }

    /// Whether parameters are physical (a plate tilted by less than 60 deg, a retardance error
    /// of less than 180 deg, a diattenuation below 1): the fit does not leave this domain.
    fn valid(&self, t: &[f64]) -> bool {
        t.iter().all(|v| v.is_finite())
            && match self {
                Cause::TiltedHwp => t[0].abs() <= 60.0,
                Cause::WedgedHwp => t.iter().all(|v| v.abs() <= 180.0),
                Cause::PolarizingHwp => t[0].abs() < 1.0,
                Cause::StressedLens => t[0].abs() <= 360.0 && t[1].abs() <= 100.0 && t[2].abs() <= 100.0,
                _ => true,
            }
    }

    /// Parse a comma-separated list of cause names ("all" for every one).
    pub fn parse_list(s: &str) -> std::result::Result<Vec<Cause>, String> {
        let mut out = Vec::new();
        for w in s.split(',').map(str::trim).filter(|w| !w.is_empty()) {
            if w == "all" {
                return Ok(Cause::ALL.to_vec());
            }
            let c = Cause::ALL.iter().find(|c| c.name() == w).ok_or_else(|| {
                let names: Vec<&str> = Cause::ALL.iter().map(|c| c.name()).collect();
                format!("unknown cause '{w}' (one of {}, or all)", names.join(", "))
            })?;
            if !out.contains(c) {
                out.push(*c);
            }
        }
        if !out.contains(&Cause::DiattenuationOnly) {
            // The null candidate is always compared: no winner without it.
            out.insert(0, Cause::DiattenuationOnly);
        }
        Ok(out)
    }
}

/// What the candidates need besides their parameters.
pub struct Context {
    /// The HWP angles of the data (the plate causes go through this demodulation).
    pub solver: StokesSolver,
    /// The half-wave plate's crystal (tilted plate).
    pub plate: UniaxialPlate,
    /// Angular magnification at the plate: telescope aperture over collimated beam diameter.
    pub magnification: f64,
    /// Radius (arcmin) at which the stressed lens's `retardance_edge_deg` is given.
    pub radius_arcmin: f64,
    /// The ray trace's linear block at a field position (None: the cause is not offered).
    pub raytrace: Option<Box<dyn Fn(f64, f64) -> Option<LinearBlock> + Sync + Send>>,
}

impl Context {
    /// The 16 angles `i pi / 8` (a full turn), a zero-order quartz plate in B, magnification
    /// `magnification`, edge radius `radius_arcmin`, no ray trace.
    pub fn new(angles_rad: &[f64], magnification: f64, radius_arcmin: f64) -> Result<Self> {
        let solver = StokesSolver::new(angles_rad).map_err(|e| Error::Input(format!("HWP angles: {e}")))?;
        if !(magnification >= 0.0 && magnification.is_finite()) {
            return Err(Error::Input(format!("magnification = {magnification} must be >= 0")));
        }
        if !(radius_arcmin > 0.0 && radius_arcmin.is_finite()) {
            return Err(Error::Input(format!("radius_arcmin = {radius_arcmin} must be positive")));
        }
        Ok(Self { solver, plate: UniaxialPlate::quartz_half_wave_b(0), magnification, radius_arcmin, raytrace: None })
    }
}

/// The values a fit is compared against: stacked parameters with a whitening.
pub struct Target {
    kind: Kind,
    /// Full-vector indices compared (a subset of the fitted kind's free parameters).
    compared: Vec<usize>,
    positions: Vec<(f64, f64)>,
    y: DVector<f64>,
    mode: Mode,
}

enum Mode {
    /// Polynomial coefficients: model = `proj` (nm x npos) applied to each compared
    /// parameter's values at the grid positions; whitening by the lower Cholesky factor.
    Smooth { proj: DMatrix<f64>, chol: DMatrix<f64> },
    /// One block of compared parameters per position, each with its Cholesky factor.
    PerBin { chol: Vec<DMatrix<f64>> },
}

/// Full-vector indices a diattenuation cannot produce, for a kind.
fn comparable(kind: Kind) -> &'static [usize] {
    match kind {
        Kind::Physical { .. } => &[2, 3, 4, 5],
        Kind::General => &[3, 4, 6, 7],
    }
}

/// The full parameter vector of `kind` for a block.
fn full_of_block(kind: Kind, b: &LinearBlock) -> [f64; 8] {
    let mut out = [0.0; 8];
    match kind {
        Kind::Physical { .. } => out[..6].copy_from_slice(&causes::physical_of_block(b)),
        Kind::General => {
            let m = b.normalized().0;
            out = [m[(0, 1)], m[(0, 2)], m[(1, 0)], m[(1, 1)], m[(1, 2)], m[(2, 0)], m[(2, 1)], m[(2, 2)]];
        }
    }
    out
}

/// Lower Cholesky factor of a covariance, through its diagonal scaling (the correlation form
/// keeps the factorization accurate when the parameters differ by orders of magnitude).
fn cholesky_scaled(c: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = c.nrows();
    let d: Vec<f64> = (0..n).map(|i| c[(i, i)].max(0.0).sqrt()).collect();
    if d.iter().any(|v| !(*v > 0.0) || !v.is_finite()) {
        return None;
    }
    let s = DMatrix::from_fn(n, n, |i, j| c[(i, j)] / (d[i] * d[j]));
    let l = s.cholesky()?.l();
    Some(DMatrix::from_fn(n, n, |i, j| l[(i, j)] * d[i]))
}

fn compared_of(kind: Kind, free: &[usize], what: &str) -> Result<Vec<usize>> {
    let c: Vec<usize> = comparable(kind).iter().copied().filter(|i| free.contains(i)).collect();
    if c.is_empty() {
        return Err(Error::Input(format!(
            "{what}: the field was fitted with the diattenuation alone: nothing a cause other than a diattenuation makes was fitted, so there is nothing to compare (fit it with --free retardance[,rotation,depolarization] or --general from >= 2 sky fields)"
        )));
    }
    Ok(c)
}

impl Target {
    /// The smooth field of a Mueller-field file: its polynomial coefficients of the compared
    /// parameters and their covariance; candidates are projected onto the same basis by least
    /// squares on a `grid x grid` grid inside the file's bounds.
    pub fn smooth(mf: &MuellerField, grid: usize, what: &str) -> Result<Self> {
        let compared = compared_of(mf.kind, &mf.free, what)?;
        let nf = mf.free.len();
        let nm = mf.coeffs.len() / nf;
        let b = mf.bounds;
        if !b.iter().all(|v| v.is_finite()) {
            return Err(Error::Input(format!("{what}: the field's bounds are not finite")));
        }
        let g = grid.max(2 * (mf.deg + 1)).max(4);
        let mut positions = Vec::with_capacity(g * g);
        for j in 0..g {
            for i in 0..g {
                let fx = (i as f64 + 0.5) / g as f64;
                let fy = (j as f64 + 0.5) / g as f64;
                positions.push((b[0] + fx * (b[1] - b[0]), b[2] + fy * (b[3] - b[2])));
            }
        }
        // The file's own monomial basis, through its own evaluation with unit coefficients.
        let mut unit = mf.clone();
        let z = DMatrix::from_fn(positions.len(), nm, |p, m| {
            unit.coeffs.iter_mut().for_each(|c| *c = 0.0);
            unit.coeffs[m] = 1.0;
            unit.full_at(positions[p].0, positions[p].1)[mf.free[0]]
        });
        let ztz = z.transpose() * &z;
        let proj = ztz
            .cholesky()
            .ok_or_else(|| {
                Error::Degenerate(format!("{what}: the projection grid cannot carry the degree-{} basis", mf.deg))
            })?
            .solve(&z.transpose());
        let ks: Vec<usize> = compared.iter().map(|i| mf.free.iter().position(|f| f == i).unwrap()).collect();
        let idx: Vec<usize> = ks.iter().flat_map(|&k| k * nm..(k + 1) * nm).collect();
        let n = nf * nm;
        let y = DVector::from_iterator(idx.len(), idx.iter().map(|&i| mf.coeffs[i]));
        let cov = DMatrix::from_fn(idx.len(), idx.len(), |a, c| mf.cov[idx[a] * n + idx[c]]);
        let chol = cholesky_scaled(&cov).ok_or_else(|| {
            Error::Degenerate(format!("{what}: the covariance of the compared parameters is singular"))
        })?;
        Ok(Self { kind: mf.kind, compared, positions, y, mode: Mode::Smooth { proj, chol } })
    }

    /// Per-bin fits (each a degree-0 field at its position): the compared parameters of every
    /// bin with that bin's covariance. Bins whose covariance is singular are left out.
    pub fn per_bin(bins: &[BinFit], what: &str) -> Result<Self> {
        let first = bins.first().ok_or_else(|| Error::Input(format!("{what}: no bin fit")))?;
        let kind = first.field.kind;
        let compared = compared_of(kind, &first.field.free, what)?;
        let (mut positions, mut y, mut chol) = (Vec::new(), Vec::new(), Vec::new());
        for b in bins {
            let f = &b.field;
            if f.kind != kind || f.deg != 0 || f.free != first.field.free {
                return Err(Error::Input(format!("{what}: bin fits of different models")));
            }
            let nf = f.free.len();
            let ks: Vec<usize> = compared.iter().map(|i| f.free.iter().position(|v| v == i).unwrap()).collect();
            let cov = DMatrix::from_fn(ks.len(), ks.len(), |a, c| f.cov[ks[a] * nf + ks[c]]);
            let Some(l) = cholesky_scaled(&cov) else { continue };
            positions.push((b.x_arcmin, b.y_arcmin));
            y.extend(ks.iter().map(|&k| f.coeffs[k]));
            chol.push(l);
        }
        if positions.is_empty() {
            return Err(Error::Degenerate(format!("{what}: no bin has a usable covariance")));
        }
        Ok(Self { kind, compared, positions, y: DVector::from_vec(y), mode: Mode::PerBin { chol } })
    }

    /// Number of compared numbers.
    pub fn n_data(&self) -> usize {
        self.y.len()
    }

    /// Names of the compared parameters.
    pub fn compared_names(&self) -> Vec<&'static str> {
        self.compared.iter().map(|&i| self.kind.name(i)).collect()
    }

    /// Whitened residuals of model values `v[p][c]` (position p, compared parameter c).
    fn residuals(&self, v: &[Vec<f64>]) -> DVector<f64> {
        let nc = self.compared.len();
        match &self.mode {
            Mode::Smooth { proj, chol } => {
                let nm = proj.nrows();
                let mut d = self.y.clone();
                for c in 0..nc {
                    let vals = DVector::from_iterator(v.len(), v.iter().map(|r| r[c]));
                    let m = proj * vals;
                    for k in 0..nm {
                        d[c * nm + k] -= m[k];
                    }
                }
                chol.solve_lower_triangular(&d).unwrap_or_else(|| DVector::from_element(d.len(), f64::INFINITY))
            }
            Mode::PerBin { chol } => {
                let mut out = DVector::zeros(self.y.len());
                for (p, l) in chol.iter().enumerate() {
                    let d = DVector::from_iterator(nc, (0..nc).map(|c| self.y[p * nc + c] - v[p][c]));
                    let w = l.solve_lower_triangular(&d).unwrap_or_else(|| DVector::from_element(nc, f64::INFINITY));
                    out.rows_mut(p * nc, nc).copy_from(&w);
                }
                out
            }
        }
    }
}

/// One fitted parameter.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Param {
    pub name: &'static str,
    pub value: f64,
    /// 1-sigma error (scaled by sqrt(chi2_dof) when that exceeds 1); infinite when the data
    /// do not constrain the parameter.
    pub sigma: f64,
}

/// One candidate fitted to the target.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct CauseFit {
    pub cause: Cause,
    pub params: Vec<Param>,
    pub chi2: f64,
    pub dof: usize,
    pub chi2_dof: f64,
    pub bic: f64,
    /// BIC minus the best candidate's.
    pub delta_bic: f64,
    /// For the ray trace: chi^2 of the field as computed (amplitude 1).
    pub chi2_as_computed: Option<f64>,
    pub note: Option<String>,
}

/// The comparison of all candidates.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Explanation {
    /// Sorted by BIC, best first.
    pub fits: Vec<CauseFit>,
    pub n_data: usize,
    pub compared: Vec<&'static str>,
    pub best: Cause,
    /// Candidates within [`DELTA_BIC`] of the best (the data cannot tell them from it).
    pub not_told_apart: Vec<Cause>,
    /// True when the best candidate describes the field (its chi^2 within 5 sigma of dof).
    pub adequate: bool,
    pub verdict: String,
}

/// Model values at every position for a cause with parameters `t`; None when a block has
/// no light through (the cause is then impossible there).
fn model(cause: Cause, t: &[f64], target: &Target, ctx: &Context, rt: &[Option<[f64; 8]>]) -> Option<Vec<Vec<f64>>> {
    if !cause.valid(t) {
        return None;
    }
    let kind = target.kind;
    let ident = {
        let mut f = [0.0; 8];
        f[..kind.identity().len()].copy_from_slice(&kind.identity());
        f
    };
    let pick = |f: &[f64; 8]| -> Vec<f64> { target.compared.iter().map(|&i| f[i]).collect() };
    let hwp_block = |x: f64, y: f64| -> Option<LinearBlock> {
        match cause {
            Cause::TiltedHwp => {
                let (inc, alpha) = causes::hwp_incidence(x, y, t[0].to_radians(), t[1].to_radians(), ctx.magnification);
                stokes::equivalent::equivalent_block(&ctx.solver, |th| causes::tilted_hwp(&ctx.plate, th, inc, alpha))
            }
            Cause::WedgedHwp => stokes::equivalent::equivalent_block(&ctx.solver, |th| {
                causes::wedged_hwp(th, x, y, t[0].to_radians(), t[1].to_radians(), t[2].to_radians())
            }),
            Cause::PolarizingHwp => {
                let hwp = mueller::Hwp {
                    pleochroism: Some(mueller::Harmonic { amplitude: t[0], phase: t[1].to_radians() }),
                    ..Default::default()
                };
                stokes::equivalent::equivalent_block(&ctx.solver, |th| hwp.matrix(th))
            }
            _ => None,
        }
    };
    // The polarizing plate is the same everywhere: one block.
    let uniform =
        if cause == Cause::PolarizingHwp { Some(pick(&full_of_block(kind, &hwp_block(0.0, 0.0)?))) } else { None };
    target
        .positions
        .par_iter()
        .enumerate()
        .map(|(p, &(x, y))| -> Option<Vec<f64>> {
            Some(match cause {
                Cause::DiattenuationOnly => pick(&ident),
                Cause::Raytrace => {
                    let f = rt.get(p).copied().flatten()?;
                    let mut g = ident;
                    for &i in &target.compared {
                        g[i] = ident[i] + t[0] * (f[i] - ident[i]);
                    }
                    pick(&g)
                }
                Cause::StressedLens => {
                    let (d, ax) = causes::stressed_lens(
                        x,
                        y,
                        t[0].to_radians(),
                        ctx.radius_arcmin,
                        [t[1], t[2]],
                        t[3].to_radians(),
                    );
                    pick(&full_of_block(kind, &physical_block(0.0, 0.0, retardance_vector(d, ax), 0.0, 0.0)))
                }
                Cause::PolarizingHwp => uniform.clone()?,
                Cause::TiltedHwp | Cause::WedgedHwp => pick(&full_of_block(kind, &hwp_block(x, y)?)),
            })
        })
        .collect()
}

fn chi2_of(r: &DVector<f64>) -> f64 {
    let c = r.norm_squared();
    if c.is_finite() {
        c
    } else {
        f64::INFINITY
    }
}

/// One candidate's least-squares problem: the whitened residuals of its parameters.
struct CauseProblem<'a> {
    cause: Cause,
    target: &'a Target,
    ctx: &'a Context,
    rt: &'a [Option<[f64; 8]>],
}

impl CauseProblem<'_> {
    fn residuals(&self, t: &[f64]) -> Option<DVector<f64>> {
        model(self.cause, t, self.target, self.ctx, self.rt).map(|v| self.target.residuals(&v))
    }
    /// Central differences; one-sided at the edge of the physical domain, zero outside it.
    fn jacobian(&self, t: &[f64], r0: &DVector<f64>) -> DMatrix<f64> {
        let k = t.len();
        let scales = self.cause.scales();
        let mut j = DMatrix::zeros(r0.len(), k);
        for c in 0..k {
            let h = 1e-5 * scales[c].max(t[c].abs());
            let (mut a, mut b) = (t.to_vec(), t.to_vec());
            a[c] += h;
            b[c] -= h;
            let col = match (self.residuals(&a), self.residuals(&b)) {
                (Some(ra), Some(rb)) => (ra - rb) / (2.0 * h),
                (Some(ra), None) => (ra - r0) / h,
                (None, Some(rb)) => (r0 - rb) / h,
                (None, None) => continue,
            };
            j.set_column(c, &col);
        }
        j
    }
}

impl lsq::Problem for CauseProblem<'_> {
    type Eval = DVector<f64>;
    type Lin = DMatrix<f64>;
    fn evaluate(&self, t: &[f64]) -> std::result::Result<DVector<f64>, LsqError> {
        self.residuals(t)
            .ok_or_else(|| LsqError::Evaluation(format!("{} is outside its physical domain", self.cause.name())))
    }
    fn chi2(&self, r: &DVector<f64>) -> f64 {
        chi2_of(r)
    }
    fn linearize(&self, t: &[f64], r: &DVector<f64>) -> std::result::Result<Linear<DMatrix<f64>>, LsqError> {
        Ok(Linear::of_jacobian(self.jacobian(t, r), r))
    }
}

/// Levenberg-Marquardt ([`lsq::CAUSES`]) on the whitened residuals from one start; returns the
/// parameters, chi^2 and the Jacobian of the last iteration (at the solution, or at the point
/// before the last step when the decrease stopped the run).
fn lm(
    cause: Cause,
    start: &[f64],
    target: &Target,
    ctx: &Context,
    rt: &[Option<[f64; 8]>],
) -> Option<(Vec<f64>, f64, DMatrix<f64>)> {
    let problem = CauseProblem { cause, target, ctx, rt };
    let r = problem.residuals(start)?;
    let chi2 = chi2_of(&r);
    if !chi2.is_finite() {
        return None;
    }
    if start.is_empty() {
        return Some((start.to_vec(), chi2, DMatrix::zeros(r.len(), 0)));
    }
    let s = lsq::run(&problem, start.to_vec(), r, &lsq::CAUSES);
    let j = match (s.ending, s.lin) {
        // The loop takes each Jacobian before its step; the one at the point where the
        // iteration limit stopped it is taken here.
        (lsq::Ending::IterationLimit, _) => problem.jacobian(&s.x, &s.eval),
        (_, Some(j)) => j,
        (_, None) => return None,
    };
    Some((s.x, s.chi2, j))
}

/// Fit one candidate (best of its starts).
fn fit_cause(cause: Cause, target: &Target, ctx: &Context, rt: &[Option<[f64; 8]>], n: usize) -> CauseFit {
    let names = cause.param_names();
    let k = names.len();
    let mut best: Option<(Vec<f64>, f64, DMatrix<f64>)> = None;
    let mut note = None;
    if cause == Cause::Raytrace && rt.iter().any(|b| b.is_none()) {
        note = Some("the ray trace has no block at some field position (no [optics] or vignetted)".to_string());
    } else {
        for s in cause.starts(ctx.radius_arcmin) {
            if let Some(f) = lm(cause, &s, target, ctx, rt) {
                if best.as_ref().is_none_or(|b| f.1 < b.1) {
                    best = Some(f);
                }
            }
        }
    }
    let dof = n.saturating_sub(k);
    let Some((t, chi2, j)) = best else {
        return CauseFit {
            cause,
            params: names.iter().map(|&name| Param { name, value: f64::NAN, sigma: f64::NAN }).collect(),
            chi2: f64::INFINITY,
            dof,
            chi2_dof: f64::INFINITY,
            bic: f64::INFINITY,
            delta_bic: f64::INFINITY,
            chi2_as_computed: None,
            note: note.or_else(|| Some("no start point gave a finite chi^2".into())),
        };
    };
    let chi2_dof = if dof > 0 { chi2 / dof as f64 } else { f64::NAN };
    let scale = if dof >= 30 && chi2_dof > 1.0 { chi2_dof } else { 1.0 };
    // The covariance only where the data determine every parameter: the workspace's judge
    // (`crate::conditioning`) on the whitened Jacobian, not a failed inverse; its refusal,
    // naming the free parameter, is the cause's note.
    let words = crate::conditioning::Words::new(
        names.iter().map(|n| n.to_string()).collect(),
        "fields whose sky polarization or field positions tell this cause's parameters apart",
    );
    let judged = if k > 0 { crate::conditioning::judge(&j, &words) } else { Ok(()) };
    let cov = match &judged {
        Ok(()) if k > 0 => (j.transpose() * &j).try_inverse(),
        _ => None,
    };
    let params = names
        .iter()
        .enumerate()
        .map(|(i, &name)| {
            // An error far beyond the parameter's whole range is no constraint at all.
            let limit = 1e3 * cause.scales()[i].max(t[i].abs());
            let v = cov.as_ref().map(|c| c[(i, i)] * scale).filter(|v| *v >= 0.0 && v.sqrt() < limit);
            Param { name, value: t[i], sigma: v.map_or(f64::INFINITY, f64::sqrt) }
        })
        .collect::<Vec<_>>();
    if let Err(u) = judged {
        note = Some(u.to_string());
    } else if params.iter().any(|p| !p.sigma.is_finite()) {
        note = Some("some parameters are not constrained by the data (singular information matrix)".into());
    }
    let chi2_as_computed = if cause == Cause::Raytrace {
        model(cause, &[1.0], target, ctx, rt).map(|v| chi2_of(&target.residuals(&v)))
    } else {
        None
    };
    CauseFit {
        cause,
        params,
        chi2,
        dof,
        chi2_dof,
        bic: chi2 + k as f64 * (n as f64).ln(),
        delta_bic: 0.0,
        chi2_as_computed,
        note,
    }
}

/// Fit every candidate in `which` (the null candidate is always added) to the target and
/// rank them.
pub fn explain(target: &Target, ctx: &Context, which: &[Cause]) -> Result<Explanation> {
    let n = target.n_data();
    let mut list: Vec<Cause> = which.to_vec();
    if !list.contains(&Cause::DiattenuationOnly) {
        list.insert(0, Cause::DiattenuationOnly);
    }
    if ctx.raytrace.is_none() {
        list.retain(|c| *c != Cause::Raytrace);
    }
    // The ray trace's blocks at the positions, once.
    let rt: Vec<Option<[f64; 8]>> = match &ctx.raytrace {
        Some(f) if list.contains(&Cause::Raytrace) => {
            target.positions.par_iter().map(|&(x, y)| f(x, y).map(|b| full_of_block(target.kind, &b))).collect()
        }
        _ => Vec::new(),
    };
    let mut fits: Vec<CauseFit> = list.iter().map(|&c| fit_cause(c, target, ctx, &rt, n)).collect();
    fits.sort_by(|a, b| a.bic.total_cmp(&b.bic));
    let best_bic = fits[0].bic;
    if !best_bic.is_finite() {
        return Err(Error::Degenerate("no candidate gave a finite chi^2".into()));
    }
    for f in &mut fits {
        f.delta_bic = f.bic - best_bic;
    }
    let best = fits[0].cause;
    let not_told_apart: Vec<Cause> = fits[1..].iter().filter(|f| f.delta_bic < DELTA_BIC).map(|f| f.cause).collect();
    let b = &fits[0];
    let adequate = b.dof == 0 || (b.chi2 - b.dof as f64) < 5.0 * (2.0 * b.dof as f64).sqrt();
    let names = |v: &[Cause]| v.iter().map(|c| c.name()).collect::<Vec<_>>().join(", ");
    let mut verdict = if best == Cause::DiattenuationOnly {
        format!(
            "no evidence for any candidate beyond the diattenuation: the compared parameters ({}) are consistent with none of the effects (chi2/dof = {:.3})",
            target.compared_names().join(", "),
            b.chi2_dof
        )
    } else if not_told_apart.contains(&Cause::DiattenuationOnly) {
        format!(
            "the data cannot tell {} (best) from nothing beyond the diattenuation (delta BIC < {DELTA_BIC}): no cause is claimed",
            best.name()
        )
    } else if !not_told_apart.is_empty() {
        format!(
            "{} fits best but the data cannot tell it from {} (delta BIC < {DELTA_BIC}): no single cause is picked",
            best.name(),
            names(&not_told_apart)
        )
    } else {
        let next = fits
            .get(1)
            .map_or(String::new(), |f| format!(" (next: {}, delta BIC = {:.1})", f.cause.name(), f.delta_bic));
        format!("{} explains the field best{next}", best.name())
    };
    if !adequate {
        verdict.push_str(&format!(
            "; but even the best candidate leaves chi2/dof = {:.2} over {} dof: the field is not fully described by these candidates",
            b.chi2_dof, b.dof
        ));
    }
    Ok(Explanation { fits, n_data: n, compared: target.compared_names(), best, not_told_apart, adequate, verdict })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The polarizing plate over a full turn, derived: the partial polarizer turning with the
    /// plate passes the plate-rotated `(A, B)` as `A (1 - d sin^2 2a) + B d sin 2a cos 2a`
    /// with `2a = 2 theta + psi`; the `4 theta` part of that is `(1 - d/2) (q, u)` (the rest is
    /// at 0 and 8 theta), and the additive `d cos 2a` is at 2 theta: a uniform depolarization
    /// `d / 2` and no offset, to first order in `d`.
    #[test]
    fn polarizing_plate_is_a_uniform_depolarization_of_half_its_diattenuation() {
        let ctx = Context::new(&(0..16).map(|k| k as f64 * std::f64::consts::PI / 8.0).collect::<Vec<_>>(), 0.0, 3.4)
            .unwrap();
        for (d, psi) in [(0.01f64, 0.0f64), (0.003, 1.1)] {
            let hwp = mueller::Hwp {
                pleochroism: Some(mueller::Harmonic { amplitude: d, phase: psi }),
                ..Default::default()
            };
            let b = stokes::equivalent::equivalent_block(&ctx.solver, |th| hwp.matrix(th)).unwrap();
            let f = full_of_block(Kind::Physical { retardance: true, rotation: true, depolarization: true }, &b);
            assert!((f[5] - d / 2.0).abs() < d * d, "{f:?}");
            assert!(f[2].hypot(f[3]) < d * d && f[4].abs() < d * d && b.0[(1, 0)].abs() < 1e-15, "{f:?}");
        }
    }
}
