//! Every paired star of a frame set (`instpol.catalog`, as `instpol catalog`), corrected in
//! the same run when a calibration is given.

use crate::convert::*;
use crate::errors::*;
use numpy::PyArray1;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

/// Every paired star of a frame set (`instpol catalog`): one entry per column, one value per
/// star, plus the catalog's metadata.
#[pyfunction]
#[pyo3(signature = (frames, instrument, fwhm, threshold, aperture, annulus, bias, flat, hwp_angles, assembled, kappa, kappa_from_data, pair_tol, cal, allow_extrapolation, force, correct_again=false))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn _catalog<'py>(
    py: Python<'py>,
    frames: Vec<PathBuf>,
    instrument: Option<&str>,
    fwhm: f64,
    threshold: f64,
    aperture: &str,
    annulus: (f64, f64),
    bias: Option<PathBuf>,
    flat: Option<PathBuf>,
    hwp_angles: Option<Vec<f64>>,
    assembled: bool,
    kappa: Option<f64>,
    kappa_from_data: bool,
    pair_tol: f64,
    cal: Option<PathBuf>,
    allow_extrapolation: bool,
    force: bool,
    correct_again: bool,
) -> PyResult<Bound<'py, PyDict>> {
    use skyfield::catalog::CatalogConfig;
    let radius = skyfield::photometry::ApertureRadius::parse(aperture).ok_or_else(|| {
        InputError::new_err(format!(
            "aperture '{aperture}': expected a radius in px (8), a multiple of the FWHM ('2.5fwhm') or 'best'"
        ))
    })?;
    let kappa = match (kappa, kappa_from_data) {
        (Some(_), true) => return Err(InputError::new_err("give kappa or kappa_from_data, not both")),
        (Some(k), false) => stokes::KappaCorrection::known(k).map_err(|e| input_err(format!("kappa {k}: {e}")))?,
        (None, true) => stokes::KappaCorrection::FromData,
        (None, false) => stokes::KappaCorrection::None,
    };
    let inst = instrument::Instrument::load(&frames_instrument(instrument, &frames)?).map_err(inst_err)?;
    let cfg = CatalogConfig {
        detect: skyfield::detect::DetectConfig {
            fwhm_px: fwhm,
            threshold_sigma: threshold,
            pair_tol_px: pair_tol,
            ..Default::default()
        },
        radius,
        annulus: Some(annulus),
        weighting: skyfield::aperture::Weighting::Exact,
        kappa,
        force,
    };
    cfg.check().map_err(sky_err)?;
    let read = read_options(bias, flat, hwp_angles, assembled, correct_again)?;
    refuse_same_data(&frames, skyfield::same::By::Content)?;
    refuse_same_data(frames.iter().chain(&read.bias).chain(&read.flat).chain(&cal), skyfield::same::By::Identity)?;
    let loaded = match &cal {
        Some(p) => Some(py.detach(|| fit::files::calibration::load(p)).map_err(|e| load_err(p, e))?),
        None => None,
    };
    // The one step `instpol catalog` makes (workflow::steps::catalog), corrected in the same
    // run as `instpol catalog --cal`.
    let opts = fit::correction::correct::CorrectOptions { allow_extrapolation, ..Default::default() };
    let run = py.detach(|| {
        workflow::steps::catalog(&frames, &inst, &read, &cfg, loaded.as_ref().map(|l| (l, opts)), None, Box::new(|| {}))
    });
    let workflow::steps::CatalogRun { catalog: cat, warnings, corrected } = run.map_err(|e| match (e, &cal) {
        (workflow::steps::CatalogError::Correction(e), Some(p)) => input_err(format!("cal {}: {e}", p.display())),
        (workflow::steps::CatalogError::Frames(e) | workflow::steps::CatalogError::Output(e), _) => sky_err(e),
        (e, None) => input_err(e),
    })?;
    let warnings: Vec<String> = warnings.iter().map(|w| w.to_string()).collect();
    let d = catalog_dict(py, &cat)?;
    d.set_item("recorded_angles", recorded_angles_dict(py, &cat, &frames, &inst)?)?;
    if let Some((c, used)) = &corrected {
        set_corrected(&d, c, used.as_ref())?;
    }
    d.set_item("warnings", warnings)?;
    Ok(d)
}

/// A catalog's rows as Python columns (one value per star), with its metadata.
pub(crate) fn catalog_dict<'py>(py: Python<'py>, cat: &skyfield::catalog::Catalog) -> PyResult<Bound<'py, PyDict>> {
    let rows = &cat.rows;
    let n = cat.hwp_deg.len();
    let d = PyDict::new(py);
    let col = |f: fn(&skyfield::catalog::Row) -> f64| arr1(py, rows.iter().map(f).collect());
    d.set_item("id", PyArray1::from_vec(py, rows.iter().map(|r| r.id as u64).collect()))?;
    d.set_item("x", col(|r| r.x))?;
    d.set_item("y", col(|r| r.y))?;
    d.set_item("x_e", col(|r| r.x_e))?;
    d.set_item("y_e", col(|r| r.y_e))?;
    d.set_item("x_arcmin", col(|r| r.x_arcmin))?;
    d.set_item("y_arcmin", col(|r| r.y_arcmin))?;
    d.set_item("fwhm_px", col(|r| r.fwhm_px))?;
    d.set_item("aperture_px", col(|r| r.aperture_px))?;
    d.set_item("flux_e", col(|r| r.flux_e))?;
    d.set_item("q", col(|r| r.q))?;
    d.set_item("u", col(|r| r.u))?;
    d.set_item("sigma_q", col(|r| r.sigma_q))?;
    d.set_item("sigma_u", col(|r| r.sigma_u))?;
    d.set_item("cov_qu", col(|r| r.cov_qu))?;
    d.set_item("p", col(|r| r.p))?;
    d.set_item("sigma_p", col(|r| r.sigma_p))?;
    d.set_item("chi_deg", col(|r| r.chi_deg))?;
    d.set_item("sigma_chi_deg", col(|r| r.sigma_chi_deg))?;
    d.set_item("a0", col(|r| r.a0))?;
    d.set_item("kappa", col(|r| opt(r.kappa)))?;
    d.set_item("kappa_applied", col(|r| opt(r.kappa_applied)))?;
    d.set_item("chi2_mod", col(|r| r.chi2_mod))?;
    d.set_item("dof_mod", PyArray1::from_vec(py, rows.iter().map(|r| r.dof_mod as u64).collect()))?;
    d.set_item("sigma_q_scatter", col(|r| r.sigma_q_scatter))?;
    d.set_item("sigma_u_scatter", col(|r| r.sigma_u_scatter))?;
    d.set_item("flags", PyArray1::from_vec(py, rows.iter().map(|r| r.flags).collect()))?;
    d.set_item("flag_names", rows.iter().map(|r| skyfield::catalog::flags::names(r.flags)).collect::<Vec<_>>())?;
    d.set_item("note", rows.iter().map(|r| r.note.clone()).collect::<Vec<_>>())?;
    // The frames' celestial WCS: each star's RA, Dec (deg), as the catalog's table has them.
    if rows.iter().any(|r| r.ra_deg.is_some()) {
        d.set_item("ra_deg", col(|r| opt(r.ra_deg)))?;
        d.set_item("dec_deg", col(|r| opt(r.dec_deg)))?;
    }
    // Through a quarter-wave plate: V/I of every star and the plate's zero angle (the linear
    // columns are NaN), as `instpol catalog` writes them.
    if let Some(z) = cat.qwp_zero_angle_deg {
        d.set_item("v", col(|r| opt(r.v)))?;
        d.set_item("sigma_v", col(|r| opt(r.sigma_v)))?;
        d.set_item("qwp_zero_angle_deg", z)?;
    }
    let f: Vec<f64> = rows.iter().flat_map(|r| (0..n).map(|i| r.f.get(i).copied().unwrap_or(f64::NAN))).collect();
    d.set_item("f", arr2(py, f, rows.len(), n)?)?;
    d.set_item("hwp_deg", cat.hwp_deg.clone())?;
    d.set_item("filter", &cat.filter)?;
    // What the catalog is (instrument, filter, plate, frame, detector), as its tables' keywords.
    if let Some(p) = &cat.product {
        d.set_item("product", product_dict(py, p)?)?;
    }
    d.set_item("chi_offset_deg", cat.chi_offset_deg)?;
    d.set_item("oe_offset_px", cat.oe_offset_px)?;
    d.set_item("unpaired", cat.unpaired.clone())?;
    d.set_item("unpaired_why", cat.unpaired_why.iter().map(|w| pythonize_why(*w)).collect::<Vec<_>>())?;
    d.set_item("unpaired_shift_px", cat.unpaired_shift_px)?;
    d.set_item("n_sources", cat.n_sources)?;
    Ok(d)
}

/// The exposures' telescope angles, as `instpol catalog` records them in its tables: what
/// `Calibration.correct(..., recorded=...)` takes; None when the frames record none.
pub(crate) fn recorded_angles_dict<'py>(
    py: Python<'py>,
    cat: &skyfield::catalog::Catalog,
    frames: &[PathBuf],
    inst: &instrument::Instrument,
) -> PyResult<Option<Bound<'py, PyDict>>> {
    let Some(r) = fit::telescope::cal::recorded_angles(&cat.frames, frames, inst) else { return Ok(None) };
    let rd = PyDict::new(py);
    let (s, e) = r.parallactic_rad.unwrap_or_default();
    rd.set_item("parang_deg", (s.to_degrees(), e.to_degrees()))?;
    rd.set_item("rotator_deg", r.rotator_rad.map(f64::to_degrees))?;
    let ex: Vec<(f64, f64, f64)> =
        r.exposure_tracks.iter().map(|x| (x.hwp_deg, x.start.to_degrees(), x.end.to_degrees())).collect();
    rd.set_item("exposures", ex)?;
    // What the q, u carry: correct(recorded=...) takes it as the CLI takes a table's
    // hwp_chi_offset_deg column.
    rd.set_item("hwp_chi_offset_deg", cat.chi_offset_deg)?;
    Ok(Some(rd))
}

/// The corrected columns of `instpol correct` (NaN for a star not measured), with what the
/// correction applied and the telescope model it used.
pub(crate) fn set_corrected(
    d: &Bound<'_, PyDict>,
    c: &fit::correction::catalog_correct::CorrectedCatalog,
    used: Option<&fit::correction::catalog_correct::TelescopeUsed>,
) -> PyResult<()> {
    let py = d.py();
    let out = fit::correction::columns::Outputs::of_rows(&c.rows);
    for (name, values) in out.names.iter().zip(out.values) {
        d.set_item(name, arr1(py, values))?;
    }
    d.set_item("extrapolated", PyArray1::from_vec(py, out.extrapolated))?;
    d.set_item("chi_offset_applied_deg", c.chi_offset_applied_deg)?;
    d.set_item("n_extrapolated", c.n_extrapolated)?;
    d.set_item("telescope_model", used.map(|t| t.model))?;
    d.set_item("telescope_band", used.map(|t| t.band.clone()))?;
    d.set_item("telescope_exposures", used.map(|t| t.exposures))?;
    Ok(())
}
