//! Smooth forms of the Mueller field other than the 2-D polynomial: the
//! paper's radial family and the natural-neighbour interpolant, each built from the per-bin
//! fits ([`crate::mueller_field::fit_per_bin`]) through the models the `p, phi` calibrations
//! already use ([`RadialModel`](crate::models::radial::RadialModel) fitted by [`fit_radial`], [`ResidualMap`](crate::models::residual::ResidualMap)): no second radial
//! model or interpolant.
//!
//! # The radial family
//!
//! The diattenuation `(q_d, u_d) = p (cos 2phi, sin 2phi)` is a spin-2 field like the `(q, u)`
//! of the paper's radial model (section `sec:fors1`): a partial polarizer whose axis is radial
//! about the optical axis is `p(r) (cos 2 alpha, sin 2 alpha)`, fitted as such. The retardance
//! vector `g = m (cos 4 theta, sin 4 theta)` (`m = (1 - cos delta) / 2`,
//! [`mueller::linear::retardance_of_vector`]) turns with four times its axis `theta`: a
//! retardance whose axis is radial (or tangential: the same block for linear polarimetry) is
//! `m(r) (cos 4 alpha, sin 4 alpha)`, the same radial model evaluated at the position whose
//! polar angle is doubled (`r` kept). Rotation, depolarization and the general block have no
//! such pattern: the radial form refuses them. The centre is the field origin (the optical
//! axis of the maps' coordinates), `p` vanishes on the axis (powers `1..=deg` of `r`).
//!
//! Each pair is fitted to the per-bin values with their marginal covariance (the diagonal:
//! [`Bin`] carries no `q, u` covariance); the pairs' coefficients are independent in the
//! form's covariance. The form's `chi2_dof` is the per-bin values' full chi^2 (each bin's own
//! covariance of all its parameters) about the radial form: far above 1 says the field is not
//! radial, and the fit says so in a warning.
//!
//! # The interpolant
//!
//! Natural-neighbour interpolation of every per-bin parameter on the Delaunay triangulation of
//! the bin centres ([`ResidualMap`](crate::models::residual::ResidualMap), two channels per map). It passes through the per-bin
//! values at the bin centres and is continuous; its covariance is the interpolated per-bin
//! covariance (an upper bound of the variance of a weighted mean of independent bins, equal to
//! the bin's at its centre). Outside the convex hull of the bins it has no value
//! ([`MuellerField::contains`](field::FieldModel::contains) is false there).

use crate::models::bins::Bin;
use crate::models::radial::{fit_radial, ErrorScaling, RadialFitOptions, Robust};
use crate::mueller_field::forms::double_angle;
pub use crate::mueller_field::forms::{
    radial_form_of, radial_pairs, radial_rows, InterpForm, InterpPoint, RadialForm, RadialPair, Smooth,
};
use crate::mueller_field::{BinFit, Kind, MuellerField};
use crate::{Error, Result};
use nalgebra::{DMatrix, DVector};

/// Totals of the per-bin fits a smooth form is built from (`n_obs`, `chi2_dof` pooled).
fn pooled(bins: &[BinFit]) -> (usize, f64) {
    let n_obs = bins.iter().map(|b| b.field.n_obs).sum();
    let (mut c2, mut dof) = (0.0, 0.0);
    for b in bins {
        let d = (2 * b.field.n_obs).saturating_sub(b.field.free.len()) as f64;
        if b.field.chi2_dof.is_finite() && d > 0.0 {
            c2 += b.field.chi2_dof * d;
            dof += d;
        }
    }
    (n_obs, if dof > 0.0 { c2 / dof } else { f64::NAN })
}

fn check_bins(bins: &[BinFit]) -> Result<(Kind, Vec<usize>)> {
    let first = bins.first().ok_or_else(|| Error::Input("no per-bin fit to build a smooth form from".into()))?;
    let (kind, free) = (first.field.kind, first.field.free.clone());
    if bins.iter().any(|b| b.field.kind != kind || b.field.free != free || b.field.coeffs.len() != free.len()) {
        return Err(Error::Input("per-bin fits of different models".into()));
    }
    Ok((kind, free))
}

fn bounds_of(bins: &[BinFit]) -> [f64; 4] {
    bins.iter().fold([f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY], |b, f| {
        [b[0].min(f.x_arcmin), b[1].max(f.x_arcmin), b[2].min(f.y_arcmin), b[3].max(f.y_arcmin)]
    })
}

/// The interpolant form of the per-bin fits (module docs).
pub fn interp_field(bins: &[BinFit]) -> Result<MuellerField> {
    let (kind, free) = check_bins(bins)?;
    let points = bins
        .iter()
        .map(|b| InterpPoint { x: b.x_arcmin, y: b.y_arcmin, vals: b.field.coeffs.clone(), cov: b.field.cov.clone() })
        .collect();
    let form = InterpForm::new(points)?;
    let (n_obs, chi2_dof) = pooled(bins);
    let warnings = bins_warnings(bins);
    Ok(MuellerField {
        kind,
        deg: 0,
        scale_arcmin: 1.0,
        free,
        coeffs: vec![],
        cov: vec![],
        chi2_dof,
        n_obs,
        condition: bins.iter().map(|b| b.field.condition).filter(|c| c.is_finite()).fold(f64::NAN, f64::max),
        bounds: bounds_of(bins),
        warnings,
        smooth: Smooth::Interp(form),
    })
}

/// Realizability findings of the bins, summed (the smooth forms built from them carry them).
fn bins_warnings(bins: &[BinFit]) -> Vec<String> {
    let n = bins.iter().filter(|b| !b.field.warnings.is_empty()).count();
    if n == 0 {
        vec![]
    } else {
        vec![format!(
            "{n} of {} per-bin fits have realizability warnings (not physical Mueller matrices within 3 sigma)",
            bins.len()
        )]
    }
}

/// The radial form of the per-bin fits, `p(r)` and `m(r)` of powers `1..=deg` (module docs).
/// Refuses a kind with parameters that have no radial pattern.
pub fn radial_field(bins: &[BinFit], deg: usize) -> Result<MuellerField> {
    let (kind, free) = check_bins(bins)?;
    let pairs = radial_pairs(kind).map_err(Error::Input)?;
    if !(1..=8).contains(&deg) {
        return Err(Error::Input(format!("radial degree {deg}: must be 1..8")));
    }
    let opts = RadialFitOptions {
        degree: deg,
        include_c0: false,
        free_centre: false,
        centre: [0.0, 0.0],
        exclusions: vec![],
        robust: Robust::None,
        error_scaling: ErrorScaling::Conservative,
        correlated_errors: false,
    };
    let nf = free.len();
    let mut out = Vec::new();
    for &param in &pairs {
        let k = free.iter().position(|&i| i == param).expect("pairs are free parameters");
        let spin4 = param == 2;
        let data: Vec<Bin> = bins
            .iter()
            .map(|b| {
                let (x, y) = if spin4 { double_angle(b.x_arcmin, b.y_arcmin) } else { (b.x_arcmin, b.y_arcmin) };
                let c = &b.field.cov;
                Bin::new(
                    x,
                    y,
                    b.field.coeffs[k],
                    b.field.coeffs[k + 1],
                    c[k * nf + k].max(0.0).sqrt(),
                    c[(k + 1) * nf + k + 1].max(0.0).sqrt(),
                )
            })
            .collect();
        let fit = fit_radial(&data, &opts).map_err(|e| match e {
            Error::TooFewBins { used, needed, .. } => Error::Input(format!(
                "the radial form of {} needs >= {needed} fitted bins, {used} were fitted",
                kind.name(param)
            )),
            e => e,
        })?;
        out.push(RadialPair { param, model: fit.model });
    }
    let form = RadialForm { pairs: out };
    // The full chi^2 of the per-bin values about the form, each bin with its own covariance.
    let (mut chi2, mut used) = (0.0, 0usize);
    for b in bins {
        let (v, _) = form.params_at(b.x_arcmin, b.y_arcmin);
        let c = DMatrix::from_row_slice(nf, nf, &b.field.cov);
        let d = DVector::from_iterator(nf, (0..nf).map(|k| b.field.coeffs[k] - v[k]));
        if let Some(ch) = c.cholesky() {
            chi2 += d.dot(&ch.solve(&d));
            used += 1;
        }
    }
    let n_par: usize = form.pairs.iter().map(|p| p.model.coeffs.len()).sum();
    let dof = (used * nf).saturating_sub(n_par) as f64;
    let chi2_dof = if dof > 0.0 { chi2 / dof } else { f64::NAN };
    let mut warnings = bins_warnings(bins);
    // 5 sigma of chi^2's own scatter (sqrt(2 / dof)) above 1.
    if dof > 0.0 && !(chi2_dof <= 1.0 + 5.0 * (2.0 / dof).sqrt()) {
        warnings.push(format!(
            "the radial form does not describe the per-bin field: reduced chi^2 {chi2_dof:.3} over {dof} degrees of freedom (1 +- {:.3} expected); the field is not radial about the origin: use the poly or interp form",
            (2.0 / dof).sqrt()
        ));
    }
    let (n_obs, _) = pooled(bins);
    let coeffs: Vec<f64> = form.pairs.iter().flat_map(|p| p.model.coeffs.clone()).collect();
    let n = coeffs.len();
    let mut cov = vec![0.0; n * n];
    let mut o = 0;
    for p in &form.pairs {
        let m = p.model.coeffs.len();
        for i in 0..m {
            for j in 0..m {
                cov[(o + i) * n + o + j] = p.model.cov_at(i, j);
            }
        }
        o += m;
    }
    Ok(MuellerField {
        kind,
        deg,
        scale_arcmin: 1.0,
        free,
        coeffs,
        cov,
        chi2_dof,
        n_obs,
        condition: f64::NAN,
        bounds: bounds_of(bins),
        warnings,
        smooth: Smooth::Radial(form),
    })
}
