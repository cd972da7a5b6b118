//! From binned measurements to a calibration: fit the radial model, run the polar-angle test,
//! optionally interpolate the residuals, and gather the numbers a person or a script reads.
//! `instpol calibrate`, `instpol fit` and `instpol demo` all go through [`calibrate_bins`].

use crate::bins::Bin;
use crate::calfile::{
    residual_from_bins, Calibration, Model, PixelGrid, PolarAngleSummary, Provenance, FORMAT_VERSION,
};
use crate::polar::{polar_angle_test, PolarAngleTest};
use crate::radial::{fit_radial, RadialFit, RadialFitOptions};
use crate::region::FieldRegion;
use crate::{Error, Result};
use serde::Serialize;

/// What a calibration is of.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationMeta {
    pub instrument: String,
    pub filter: String,
    pub lambda_nm: f64,
    pub hwp_chi_offset_deg: f64,
    pub pixel: Option<PixelGrid>,
    pub provenance: Provenance,
}

/// How to calibrate.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrateOptions {
    pub fit: RadialFitOptions,
    /// Keep the natural-neighbour interpolant of the residuals in the model.
    pub residual_map: bool,
    /// Bins closer than this (arcmin) to the centre are left out of the polar-angle test
    /// (their angle is noise); default 0.5.
    pub polar_r_min: f64,
    /// Margin (arcmin) added around the bins to make the valid region: half a bin.
    pub region_margin: f64,
}

impl Default for CalibrateOptions {
    fn default() -> Self {
        CalibrateOptions {
            fit: RadialFitOptions::default(),
            residual_map: false,
            polar_r_min: 0.5,
            region_margin: 0.05,
        }
    }
}

/// Everything a calibration run found.
#[derive(Debug, Clone)]
pub struct CalibrationRun {
    pub calibration: Calibration,
    pub fit: RadialFit,
    pub polar: PolarAngleTest,
}

/// Calibrate from bins of instrumental `(q, u)`: the radial fit (section `sec:fors1`), the
/// polar-angle test about the fitted centre, and optionally the residual interpolant.
pub fn calibrate_bins(mut bins: Vec<Bin>, meta: CalibrationMeta, opts: &CalibrateOptions) -> Result<CalibrationRun> {
    let valid = bins.iter().filter(|b| b.is_valid()).count();
    if valid == 0 {
        return Err(Error::TooFewBins { used: 0, total: bins.len(), needed: 1 });
    }
    let fit = fit_radial(&bins, &opts.fit)?;
    for (b, u) in bins.iter_mut().zip(&fit.used) {
        b.used = *u;
    }
    let polar = polar_angle_test(&bins, fit.model.centre, opts.polar_r_min)?;
    let region = FieldRegion::bounding(bins.iter().filter(|b| b.is_valid()).map(|b| (b.x, b.y)), opts.region_margin)
        .ok_or_else(|| Error::Input("no valid bin positions".into()))?;
    let model = if opts.residual_map {
        let residual = residual_from_bins(&fit.model, &bins)?;
        Model::RadialResidual { radial: fit.model.clone(), residual }
    } else {
        Model::Radial(fit.model.clone())
    };
    let calibration = Calibration {
        format_version: FORMAT_VERSION,
        instrument: meta.instrument,
        filter: meta.filter,
        lambda_nm: meta.lambda_nm,
        hwp_chi_offset_deg: meta.hwp_chi_offset_deg,
        model,
        region,
        rms_residual: fit.rms_residual,
        n_bins_used: fit.n_used,
        polar_angle: Some(PolarAngleSummary::from(&polar)),
        exclusions: opts.fit.exclusions.clone(),
        robust: opts.fit.robust.name(),
        pixel: meta.pixel,
        provenance: meta.provenance,
        bins,
        grid: None,
    };
    Ok(CalibrationRun { calibration, fit, polar })
}

/// Refit a calibration (native or imported) from its binned measurements.
pub fn refit(cal: &Calibration, opts: &CalibrateOptions) -> Result<CalibrationRun> {
    let bins: Vec<Bin> = cal.bins.iter().map(|b| Bin { used: true, ..*b }).collect();
    let mut provenance = cal.provenance.clone();
    provenance.tool_version = format!("instpol {}", env!("CARGO_PKG_VERSION"));
    provenance.date = crate::calfile::utc_now_iso();
    if !provenance.source.contains("refit") {
        provenance.source = format!("{} (refit)", provenance.source);
    }
    let meta = CalibrationMeta {
        instrument: cal.instrument.clone(),
        filter: cal.filter.clone(),
        lambda_nm: cal.lambda_nm,
        hwp_chi_offset_deg: cal.hwp_chi_offset_deg,
        pixel: cal.pixel,
        provenance,
    };
    calibrate_bins(bins, meta, opts)
}

/// How far the approximate (`eq:approx`) and exact (`eq:instpol`) sky-field solutions are
/// apart over the bins.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ApproxVsExact {
    /// Largest `|p_exact - p_approx|` (fraction) and RMS.
    pub max_dp: f64,
    pub rms_dp: f64,
    /// Largest `|phi_exact - phi_approx|` (deg, modulo 180).
    pub max_dphi_deg: f64,
}

/// Compare the approximate and exact solutions kept in the bins; `None` when the bins carry
/// no approximate solution.
pub fn approx_vs_exact(bins: &[Bin]) -> Option<ApproxVsExact> {
    let mut n = 0;
    let (mut max_dp, mut ss, mut max_dphi) = (0.0f64, 0.0, 0.0f64);
    for b in bins.iter().filter(|b| b.is_valid() && b.p_approx.is_finite()) {
        let (p, phi) = b.p_phi();
        let dp = p - b.p_approx;
        let dphi = crate::polar::wrap_half_turn_deg((phi - b.phi_approx).to_degrees());
        max_dp = max_dp.max(dp.abs());
        ss += dp * dp;
        // Angles of bins with p at the noise say nothing; weigh only bins with a clear p.
        if p > 5.0 * b.sigma_q.max(b.sigma_u) {
            max_dphi = max_dphi.max(dphi.abs());
        }
        n += 1;
    }
    (n > 0).then(|| ApproxVsExact { max_dp, rms_dp: (ss / n as f64).sqrt(), max_dphi_deg: max_dphi })
}

/// The JSON of `instpol calibrate` and `instpol fit` (field names are a contract).
#[derive(Debug, Clone, Serialize)]
pub struct FitSummary {
    pub filter: String,
    pub model: String,
    pub centre_arcmin: [f64; 2],
    #[serde(skip_serializing_if = "Option::is_none")]
    pub centre_px: Option<[f64; 2]>,
    pub centre_errors_arcmin: [f64; 2],
    pub centre_free: bool,
    /// Powers of r of the coefficients.
    pub powers: Vec<usize>,
    /// Coefficients (fraction per arcmin^k).
    pub coefficients: Vec<f64>,
    pub coefficient_errors: Vec<f64>,
    pub rms_residual: f64,
    pub chi2_reduced: f64,
    pub polar_angle_slope: f64,
    pub polar_angle_slope_err: f64,
    pub polar_angle_intercept_deg: f64,
    pub polar_angle_intercept_err_deg: f64,
    pub n_bins_used: usize,
    pub n_bins: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub residual_loo_rms: Option<[f64; 2]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub approx_vs_exact: Option<ApproxVsExact>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration_file: Option<String>,
}

impl FitSummary {
    pub fn new(run: &CalibrationRun) -> Self {
        let cal = &run.calibration;
        let m = &run.fit.model;
        FitSummary {
            filter: cal.filter.clone(),
            model: cal.model.kind().to_string(),
            centre_arcmin: m.centre,
            centre_px: cal.centre_px(),
            centre_errors_arcmin: m.centre_errors(),
            centre_free: m.centre_free,
            powers: (0..m.coeffs.len()).map(|i| m.first_power + i).collect(),
            coefficients: m.coeffs.clone(),
            coefficient_errors: m.coefficient_errors(),
            rms_residual: run.fit.rms_residual,
            chi2_reduced: run.fit.chi2_reduced,
            polar_angle_slope: run.polar.slope,
            polar_angle_slope_err: run.polar.slope_err,
            polar_angle_intercept_deg: run.polar.intercept_deg,
            polar_angle_intercept_err_deg: run.polar.intercept_err_deg,
            n_bins_used: run.fit.n_used,
            n_bins: cal.bins.len(),
            residual_loo_rms: match &cal.model {
                Model::RadialResidual { residual, .. } => Some([residual.loo_rms_q, residual.loo_rms_u]),
                _ => None,
            },
            approx_vs_exact: approx_vs_exact(&cal.bins),
            calibration_file: None,
        }
    }
}

/// The bins of a sky-field solution (`skyfield::solve`): the exact instrumental `(q, u)` with
/// their propagated errors, the approximate solution kept beside them.
pub fn bins_from_solutions(sol: &[skyfield::solve::BinSolution]) -> Vec<Bin> {
    sol.iter()
        .map(|s| Bin {
            x: s.x,
            y: s.y,
            q: s.q,
            u: s.u,
            sigma_q: s.var_q.max(0.0).sqrt(),
            sigma_u: s.var_u.max(0.0).sqrt(),
            p_approx: s.p_approx,
            phi_approx: s.phi_approx,
            used: true,
        })
        .collect()
}
