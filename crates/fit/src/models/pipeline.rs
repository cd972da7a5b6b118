//! From binned measurements to a calibration: fit the radial model, run the polar-angle test,
//! optionally interpolate the residuals, and gather the numbers a person or a script reads.
//! `instpol calibrate`, `instpol fit` and `instpol demo` all go through [`calibrate_bins`];
//! `calibrate` and `demo` reach it from a Stokes map through [`calibrate_map`].
//!
//! # The HWP zero angle: which frame the calibration is in
//!
//! A plate whose zero sits off by `chi_offset / 2` makes every measured angle smaller by
//! `chi_offset` ([`mueller::Hwp`], the filter's `hwp_chi_offset_deg`, the angle to *add* to a
//! measured chi). The reduction (`skyfield::reduce`) does not add it: a Stokes map made by
//! instpol is in the *plate* frame, `chi_meas = chi_sky - chi_offset`. The sky's `(P, chi)` of
//! the sky-field solution and the instrumental `M_I(p, phi)` (`eq:instpol`) live in the *sky*
//! frame, and [`crate::correction::correct`] assumes the calibration's field does too (it rotates a
//! measurement into the sky frame first, then inverts `M_I`). So [`calibrate_map`] rotates the
//! map's `(q, u)` and their covariance by `+chi_offset` ([`map_to_sky_frame`]) before the
//! solution, with the same offset it records in the calibration: applied exactly once, here.
//!
//! What is assumed of the other ways in:
//! - a map read from FITS (`instpol calibrate --map`) is an *uncorrected* instpol map, in the
//!   plate frame, like one fresh from the reduction (a map already corrected by
//!   `instpol correct` carries `INSTCORR`/`CORRHWP`, and `StokesMap::read_uncorrected`, which
//!   the commands read such inputs with, refuses it);
//! - [`refit`] starts from a calibration's bins, which are already solved instrumental `(q, u)`
//!   in that calibration's frame: nothing is rotated again;
//! - an imported third-party map (`crate::files::import`) is taken as is, in its producer's frame, and
//!   records a zero offset, so correcting with it rotates nothing either: it is consistent when
//!   the map and the measurements to correct share that frame (to first order the order of the
//!   two corrections does not matter, see [`crate::correction::correct`]).

use crate::files::calfile::{
    residual_from_bins, Calibration, Model, PixelGrid, PolarAngleSummary, Provenance, FORMAT_VERSION,
};
use crate::models::bins::Bin;
use crate::models::polar::{polar_angle_test_with, PolarAngleTest};
use crate::models::radial::{fit_radial, RadialFit, RadialFitOptions};
use crate::models::region::FieldRegion;
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

impl CalibrationMeta {
    /// A sky-field calibration of `inst` from a map in filter `map_filter` (canonical filter
    /// name, effective wavelength and HWP zero angle from the instrument's filter table when it
    /// knows the filter; else the map's name, no wavelength, no offset), pixel grid about the
    /// detector centre, provenance stamped now with the sky values and the input files.
    pub fn sky_field(
        inst: &instrument::Instrument,
        map_filter: &str,
        sky: &skyfield::solve::SkyPolarization,
        inputs: Vec<String>,
    ) -> Self {
        let filter = inst.filter(map_filter).ok();
        let mut provenance = Provenance::of_instrument("sky-field", inputs, inst, map_filter);
        provenance.sky_p = Some(sky.p);
        provenance.sky_chi_deg = Some(sky.chi.to_degrees());
        CalibrationMeta {
            instrument: inst.name.clone(),
            filter: filter.map(|f| f.name.clone()).unwrap_or_else(|| map_filter.to_string()),
            lambda_nm: filter.map(|f| f.lambda_eff_nm).unwrap_or(f64::NAN),
            hwp_chi_offset_deg: filter.map(|f| f.chi_offset_deg()).unwrap_or(0.0),
            pixel: Some(PixelGrid::of_instrument(inst)),
            provenance,
        }
    }
}

/// How to calibrate.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrateOptions {
    pub fit: RadialFitOptions,
    /// Keep the natural-neighbour interpolant of the residuals in the model.
    pub residual_map: bool,
    /// Store a polynomial field of this total degree (1: a plane, to
    /// [`crate::models::poly::MAX_DEGREE`]) instead of the radial model, for a field without an
    /// optical axis ([`crate::models::poly`]). The radial fit still runs: its centre is the polar-angle
    /// test's, and its profile says how far from radial the field is.
    pub poly_degree: Option<usize>,
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
            poly_degree: None,
            polar_r_min: 0.5,
            region_margin: 0.05,
        }
    }
}

impl CalibrateOptions {
    /// Read a model name: `radialN` (a polynomial of degree N in r about the optical axis,
    /// [`RadialFitOptions::set_model_name`]), `polyN` (a polynomial of total degree N in x, y,
    /// [`crate::models::poly`]) or `plane` (`poly1`).
    pub fn set_model_name(&mut self, name: &str) -> Result<()> {
        let lower = name.to_ascii_lowercase();
        let degree = match lower.as_str() {
            "plane" => Some(Ok(1)),
            n => n.strip_prefix("poly").map(|d| {
                d.parse::<usize>().ok().filter(|d| (1..=crate::models::poly::MAX_DEGREE).contains(d)).ok_or_else(|| {
                    Error::Input(format!(
                        "unknown model '{name}': polyN takes N = 1 (a plane) to {}",
                        crate::models::poly::MAX_DEGREE
                    ))
                })
            }),
        };
        match degree {
            Some(d) => self.poly_degree = Some(d?),
            None => {
                self.fit.set_model_name(&lower).map_err(|_| {
                    Error::Input(format!(
                        "unknown model '{name}': expected radialN (N = degree 1..8, e.g. radial3), polyN (N = 1..{}) or plane",
                        crate::models::poly::MAX_DEGREE
                    ))
                })?;
                self.poly_degree = None;
            }
        }
        Ok(())
    }
}

/// Everything a calibration run found.
#[derive(Debug, Clone)]
pub struct CalibrationRun {
    pub calibration: Calibration,
    /// The radial fit (the stored model unless a polynomial was asked for).
    pub fit: RadialFit,
    /// The polynomial fit, when it is the stored model ([`CalibrateOptions::poly_degree`]).
    pub poly: Option<crate::models::poly::PolyFit>,
    pub polar: PolarAngleTest,
}

impl CalibrationRun {
    /// The stored field model's `(q, u)` at `(x, y)` arcmin, without a residual interpolant.
    pub fn field_qu(&self, x: f64, y: f64) -> (f64, f64) {
        match &self.poly {
            Some(p) => p.model.qu(x, y),
            None => self.fit.model.qu(x, y),
        }
    }

    /// The stored model's fit's robust weight of each bin (0 for bins not used).
    pub fn weights(&self) -> &[f64] {
        self.poly.as_ref().map_or(&self.fit.weights, |p| &p.weights)
    }

    /// The stored model's free parameters: how many, and the size of its covariance's layout
    /// (a radial model lays out its centre after its coefficients, fixed or not).
    pub fn field_params(&self) -> (usize, usize) {
        match &self.poly {
            Some(p) => (2 * p.model.q.len(), 2 * p.model.q.len()),
            None => {
                let m = &self.fit.model;
                (m.coeffs.len() + if m.centre_free { 2 } else { 0 }, m.n_params())
            }
        }
    }

    /// The stored model's `(dq/dparams, du/dparams)` at `(x, y)`, in its layout.
    pub fn field_jacobian(&self, x: f64, y: f64) -> Option<(Vec<f64>, Vec<f64>)> {
        use crate::models::model::FieldModel;
        match &self.poly {
            Some(p) => p.model.jacobian(x, y),
            None => self.fit.model.jacobian(x, y),
        }
    }

    /// The factor the stored model's fit applied to `(J^T W J)^-1`.
    pub fn covariance_scale(&self) -> f64 {
        match &self.poly {
            Some(p) => p.model.scaling.map_or(p.chi2_reduced, |s| s.total()),
            None => self.fit.model.scaling.map_or(self.fit.chi2_reduced, |s| s.total()),
        }
    }

    /// The factor of the reduced chi^2 alone in [`Self::covariance_scale`] (1 when unknown).
    pub fn chi2_factor(&self) -> f64 {
        let s = match &self.poly {
            Some(p) => p.model.scaling,
            None => self.fit.model.scaling,
        };
        s.map_or(1.0, |s| s.chi2_factor)
    }

    /// The stored model's covariance, row-major in its layout ([`Self::field_params`]).
    pub fn field_covariance(&self) -> &[f64] {
        self.poly.as_ref().map_or(&self.fit.model.cov, |p| &p.model.cov)
    }

    /// Put a covariance (the stored model's layout) into the fit and the calibration.
    pub fn set_field_covariance(&mut self, cov: &[f64]) {
        match &mut self.poly {
            Some(p) => p.model.cov = cov.to_vec(),
            None => self.fit.model.cov = cov.to_vec(),
        }
        match &mut self.calibration.model {
            Model::Radial(r) | Model::RadialResidual { radial: r, .. } => r.cov = cov.to_vec(),
            Model::Poly(p) => p.cov = cov.to_vec(),
            Model::Map(_) => {}
        }
    }
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
    // The polar-angle test's errors follow the fit's choices (scaling, correlated errors).
    let inflation = fit.correlation.map_or(1.0, |c| c.factor);
    let polar = polar_angle_test_with(&bins, fit.model.centre, opts.polar_r_min, opts.fit.error_scaling, inflation)?;
    let region = FieldRegion::bounding(bins.iter().filter(|b| b.is_valid()).map(|b| (b.x, b.y)), opts.region_margin)
        .ok_or_else(|| Error::Input("no valid bin positions".into()))?;
    let poly = match opts.poly_degree {
        Some(_) if opts.residual_map => {
            return Err(Error::Input(
                "a residual interpolant is kept beside the radial model, not a polynomial: choose one".into(),
            ))
        }
        Some(d) => Some(crate::models::poly::fit_poly(&bins, d, &opts.fit)?),
        None => None,
    };
    let model = match (&poly, opts.residual_map) {
        (Some(p), _) => Model::Poly(p.model.clone()),
        (None, true) => {
            Model::RadialResidual { radial: fit.model.clone(), residual: residual_from_bins(&fit.model, &bins)? }
        }
        (None, false) => Model::Radial(fit.model.clone()),
    };
    if let Some(p) = &poly {
        for (b, u) in bins.iter_mut().zip(&p.used) {
            b.used = *u;
        }
    }
    let (rms_residual, n_used) = poly.as_ref().map_or((fit.rms_residual, fit.n_used), |p| (p.rms_residual, p.n_used));
    let calibration = Calibration {
        format_version: FORMAT_VERSION,
        instrument: meta.instrument,
        filter: meta.filter,
        lambda_nm: meta.lambda_nm,
        hwp_chi_offset_deg: meta.hwp_chi_offset_deg,
        model,
        region,
        rms_residual,
        n_bins_used: n_used,
        polar_angle: polar.angles_defined().then(|| PolarAngleSummary::from(&polar)),
        exclusions: opts.fit.exclusions.clone(),
        robust: opts.fit.robust.name(),
        pixel: meta.pixel,
        provenance: meta.provenance,
        bins,
        grid: None,
    };
    Ok(CalibrationRun { calibration, fit, poly, polar })
}

/// Refit a calibration (native or imported) from its binned measurements.
pub fn refit(cal: &Calibration, opts: &CalibrateOptions) -> Result<CalibrationRun> {
    let bins: Vec<Bin> = cal.bins.iter().map(|b| Bin { used: true, ..*b }).collect();
    let mut provenance = cal.provenance.clone();
    provenance.tool_version = format!("instpol {}", env!("CARGO_PKG_VERSION"));
    provenance.date = crate::files::keys::utc_now_iso();
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
        let dphi = crate::models::polar::wrap_half_turn_deg((phi - b.phi_approx).to_degrees());
        max_dp = max_dp.max(dp.abs());
        ss += dp * dp;
        // Angles of bins with p at the noise say nothing; weigh only bins with a clear p.
        if p > 5.0 * b.sigma_q().max(b.sigma_u()) {
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
    #[serde(rename = "sigma_centre_arcmin")]
    pub centre_errors_arcmin: [f64; 2],
    pub centre_free: bool,
    /// Powers of r of the coefficients.
    pub powers: Vec<usize>,
    /// Coefficients (fraction per arcmin^k).
    pub coefficients: Vec<f64>,
    #[serde(rename = "sigma_coefficients")]
    pub coefficient_errors: Vec<f64>,
    pub rms_residual: f64,
    #[serde(rename = "chi2_dof")]
    pub chi2_reduced: f64,
    /// How the errors use chi2_red: "conservative" (max(1, chi2_red)), "scaled" or "absolute".
    pub error_scaling: String,
    /// The whole factor applied to (J^T W J)^-1: the chi^2 factor times the correlation inflation.
    pub covariance_scale: f64,
    /// The correlated-errors estimate, when asked for (`--correlated-errors`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub correlation: Option<crate::models::correlation::CorrelationInflation>,
    pub polar_angle_slope: f64,
    #[serde(rename = "sigma_polar_angle_slope")]
    pub polar_angle_slope_err: f64,
    pub polar_angle_intercept_deg: f64,
    #[serde(rename = "sigma_polar_angle_intercept_deg")]
    pub polar_angle_intercept_err_deg: f64,
    /// The polar-angle test against noise (see `polar::PolarAngleTest::noise_p_value`): the
    /// slope and intercept mean something only when this is below 0.01.
    #[serde(rename = "polar_angle_noise_pvalue")]
    pub polar_angle_noise_p: f64,
    /// False: "no radial pattern", the bins are consistent with noise.
    pub polar_angle_pattern: bool,
    pub polar_angle_radial_z: f64,
    pub n_bins_used: usize,
    pub n_bins: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    #[serde(rename = "rms_residual_loo")]
    pub residual_loo_rms: Option<[f64; 2]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub approx_vs_exact: Option<ApproxVsExact>,
    #[serde(skip_serializing_if = "Option::is_none")]
    #[serde(rename = "output")]
    pub calibration_file: Option<String>,
    /// The plots drawn (`--plots`), PNG and SVG; omitted when none.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub plot_outputs: Vec<String>,
    /// The polynomial field when it is the stored model (`model` "POLY"); the radial fields
    /// above are then the radial fit of the same bins (the polar-angle test's centre), and
    /// `rms_residual`, `chi2_dof`, `n_bins_used` the polynomial's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub poly: Option<PolySummary>,
    /// What the calibration is (its product keywords, the inputs the run's); omitted for a
    /// calibration that does not say (refitted from a file written before products were).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub product: Option<skyfield::provenance::Product>,
}

/// A polynomial field in [`FitSummary`]: its terms `x^i y^j` (`powers`, `[i, j]`) and the
/// coefficients of `q` and `u` (fractions per arcmin^(i+j)) with their errors.
#[derive(Debug, Clone, Serialize)]
pub struct PolySummary {
    pub degree: usize,
    pub powers: Vec<[usize; 2]>,
    pub q: Vec<f64>,
    pub sigma_q: Vec<f64>,
    pub u: Vec<f64>,
    pub sigma_u: Vec<f64>,
}

impl FitSummary {
    pub fn new(run: &CalibrationRun) -> Self {
        let cal = &run.calibration;
        let m = &run.fit.model;
        let mut s = FitSummary {
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
            error_scaling: m.scaling.map_or("scaled", |s| s.mode.name()).to_string(),
            covariance_scale: m.scaling.map_or(run.fit.chi2_reduced, |s| s.total()),
            correlation: run.fit.correlation,
            polar_angle_slope: run.polar.slope,
            polar_angle_slope_err: run.polar.slope_err,
            polar_angle_intercept_deg: run.polar.intercept_deg,
            polar_angle_intercept_err_deg: run.polar.intercept_err_deg,
            polar_angle_noise_p: run.polar.noise_p_value,
            polar_angle_pattern: run.polar.pattern_detected(),
            polar_angle_radial_z: run.polar.radial_z,
            n_bins_used: run.fit.n_used,
            n_bins: cal.bins.len(),
            residual_loo_rms: match &cal.model {
                Model::RadialResidual { residual, .. } => Some([residual.loo_rms_q, residual.loo_rms_u]),
                _ => None,
            },
            approx_vs_exact: approx_vs_exact(&cal.bins),
            calibration_file: None,
            plot_outputs: Vec::new(),
            poly: None,
            product: cal.provenance.product.as_ref().map(|p| p.with_run_inputs()),
        };
        if let Some(p) = &run.poly {
            let m = &p.model;
            let e = m.coefficient_errors();
            let nt = m.q.len();
            s.rms_residual = p.rms_residual;
            s.chi2_reduced = p.chi2_reduced;
            s.n_bins_used = p.n_used;
            s.error_scaling = m.scaling.map_or("scaled", |s| s.mode.name()).to_string();
            s.covariance_scale = m.scaling.map_or(p.chi2_reduced, |s| s.total());
            s.poly = Some(PolySummary {
                degree: m.degree,
                powers: crate::models::poly::PolyModel::powers(m.degree).into_iter().map(|(i, j)| [i, j]).collect(),
                q: m.q.clone(),
                sigma_q: e[..nt].to_vec(),
                u: m.u.clone(),
                sigma_u: e[nt..].to_vec(),
            });
        }
        s
    }
}

/// A plate-frame Stokes map turned into the sky frame: every `(q, u)` rotated by `+chi_offset`
/// (rad; `chi -> chi + chi_offset`, i.e. by `2 chi_offset` in the `(q, u)` plane), their
/// covariance as `R C R^T`, the photon-noise errors as a diagonal covariance, `chi` shifted
/// (kept in [0, pi)); `p`, coverage and intensities unchanged. A zero offset returns an exact copy.
pub fn map_to_sky_frame(map: &skyfield::StokesMap, chi_offset: f64) -> skyfield::StokesMap {
    let mut out = map.clone();
    if chi_offset == 0.0 {
        return out;
    }
    let (s, c) = (2.0 * chi_offset).sin_cos();
    for k in 0..out.q.len() {
        // An unknown covariance (NaN, a map that records none) is turned as 0 and stays unknown.
        let cv = map.cov_qu[k];
        let qu = mueller::Qu::new(map.q[k], map.u[k], map.sigma_q[k].powi(2), map.sigma_u[k].powi(2), cv);
        let r = mueller::Qu { cov_qu: if cv.is_finite() { cv } else { 0.0 }, ..qu }.rotated_cos_sin(c, s);
        out.q[k] = r.q;
        out.u[k] = r.u;
        out.sigma_q[k] = r.sigma_q();
        out.sigma_u[k] = r.sigma_u();
        out.cov_qu[k] = if cv.is_finite() { r.cov_qu } else { cv };
        // The photon-noise errors: a diagonal covariance.
        let phot = mueller::Qu::new(0.0, 0.0, map.sigma_q_phot[k].powi(2), map.sigma_u_phot[k].powi(2), 0.0);
        let rp = phot.rotated_cos_sin(c, s);
        out.sigma_q_phot[k] = rp.sigma_q();
        out.sigma_u_phot[k] = rp.sigma_u();
        out.chi[k] = mueller::fold_pi(map.chi[k] + chi_offset);
    }
    out
}

/// The sky-field solution (`skyfield::solve`, section `sec:instr`) of a plate-frame map taken
/// through a plate of zero angle `hwp_chi_offset_deg`: the map is first turned into the sky
/// frame ([`map_to_sky_frame`]), so the bins are the instrumental `(q, u)` in the sky frame.
/// Returns the bins and the number of bins without a physical solution.
pub fn solve_sky_field(
    map: &skyfield::StokesMap,
    sky: &skyfield::solve::SkyPolarization,
    hwp_chi_offset_deg: f64,
) -> std::result::Result<(Vec<Bin>, usize), skyfield::Error> {
    let sky_frame = map_to_sky_frame(map, hwp_chi_offset_deg.to_radians());
    let (sol, skipped) = skyfield::solve::solve_map(&sky_frame, sky)?;
    Ok((bins_from_solutions(&sol), skipped))
}

/// The fit options that reproduce a calibration's own fit (for its profile and polar-angle
/// panels, or to refit its bins the same way): its exclusions, and for a radial model its
/// centre (free or fixed), constant term, degree and error treatment. A calibration without a
/// radial model (an imported map) is fitted with a free centre.
pub fn refit_options(cal: &Calibration) -> RadialFitOptions {
    let mut fo = RadialFitOptions { exclusions: cal.exclusions.clone(), ..Default::default() };
    match cal.model.radial() {
        Some(r) => {
            fo.free_centre = r.centre_free;
            fo.centre = r.centre;
            fo.include_c0 = r.first_power == 0;
            fo.degree = r.degree();
            // The file's own error treatment, so error bars drawn from the refit are the file's.
            if let Some(sc) = r.scaling {
                fo.error_scaling = sc.mode;
                fo.correlated_errors = sc.correlation_inflation.is_some();
            }
        }
        None => fo.free_centre = true,
    }
    fo
}

/// The radial model of a calibration: its own, or for a calibration without one (an imported
/// map) a free-centre radial fit of its bins (as `instpol wavelength-law` needs).
pub fn radial_model_of(cal: &Calibration) -> Result<crate::RadialModel> {
    match cal.model.radial() {
        Some(r) => Ok(r.clone()),
        None => {
            let opts = CalibrateOptions {
                fit: RadialFitOptions { free_centre: true, ..Default::default() },
                ..Default::default()
            };
            Ok(refit(cal, &opts)?.fit.model)
        }
    }
}

/// [`calibrate_map`] for a map of instrument `inst` with [`CalibrationMeta::sky_field`]: what
/// `instpol calibrate` and `instpol demo` run.
pub fn calibrate_sky_field(
    map: &skyfield::StokesMap,
    sky: &skyfield::solve::SkyPolarization,
    inst: &instrument::Instrument,
    inputs: Vec<String>,
    opts: &CalibrateOptions,
) -> Result<CalibrationRun> {
    let meta = CalibrationMeta::sky_field(inst, &map.filter, sky, inputs);
    // The map is in the plate frame: calibrate_map turns it into the sky frame with the
    // filter's HWP zero angle (the one recorded in the calibration) before solving.
    calibrate_map(map, sky, meta, opts)
}

/// Calibrate from a Stokes map of an empty field of known sky polarization (a map made by the
/// reduction, in the plate frame): the sky-field solution in the sky frame with the zero angle
/// `meta.hwp_chi_offset_deg` (the same number the calibration records), then
/// [`calibrate_bins`] with the valid region widened by half a map bin.
pub fn calibrate_map(
    map: &skyfield::StokesMap,
    sky: &skyfield::solve::SkyPolarization,
    meta: CalibrationMeta,
    opts: &CalibrateOptions,
) -> Result<CalibrationRun> {
    let (bins, _skipped) = solve_sky_field(map, sky, meta.hwp_chi_offset_deg)
        .map_err(|e| Error::Input(format!("sky-field solution of the {} map: {e}", map.filter)))?;
    let mut o = opts.clone();
    o.region_margin = 0.5 * map.geometry.bin_px as f64 * map.geometry.pixel_scale_arcsec / 60.0;
    calibrate_bins(bins, meta, &o)
}

/// The bins of a sky-field solution (`skyfield::solve`): the exact instrumental `(q, u)` with
/// their propagated errors, the approximate solution kept beside them.
pub fn bins_from_solutions(sol: &[skyfield::solve::BinSolution]) -> Vec<Bin> {
    sol.iter()
        .map(|s| Bin {
            p_approx: s.p_approx,
            phi_approx: s.phi_approx,
            ..Bin::new(s.x, s.y, s.qu.q, s.qu.u, s.qu.var_q.max(0.0).sqrt(), s.qu.var_u.max(0.0).sqrt())
        })
        .collect()
}
