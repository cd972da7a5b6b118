//! The instrumental field measured on an empty sky field or from field stars
//! (`instpol.calibrate`, `instpol.calibrate_stars`, as `instpol calibrate` and
//! `calibrate-stars`).

use crate::convert::*;
use crate::errors::*;
use pyo3::prelude::*;
use std::path::PathBuf;

/// The instrumental field from a Stokes map of an empty field whose sky polarization is known
/// (`workflow::steps::calibrate_map`, what `instpol calibrate --map` runs): the fit's
/// summary as JSON text (`instpol calibrate --json`'s keys, no plots); the calibration written
/// to `out` when given. `sky`: (P percent, chi deg); `model`, `exclude` as the CLI's options.
#[pyfunction]
#[pyo3(signature = (map, instrument, sky, model, include_c0, free_centre, exclude, residual_map, out))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn _calibrate(
    py: Python<'_>,
    map: PathBuf,
    instrument: Option<&str>,
    sky: (f64, f64),
    model: &str,
    include_c0: bool,
    free_centre: bool,
    exclude: Vec<String>,
    residual_map: bool,
    out: Option<PathBuf>,
) -> PyResult<String> {
    let fit_err = |e: fit::Error| match e {
        fit::Error::Io { .. } | fit::Error::Fits { .. } => FileError::new_err(e.to_string()),
        e => input_err(e),
    };
    for (name, v) in [("sky_p_percent", sky.0), ("sky_chi_deg", sky.1)] {
        if !v.is_finite() {
            return Err(input_err(format!("{name} {v}: expected a finite number")));
        }
    }
    let sky = skyfield::solve::SkyPolarization::from_percent_deg(sky.0, sky.1).map_err(sky_err)?;
    let mut fo = fit::RadialFitOptions { include_c0, free_centre, ..Default::default() };
    for e in &exclude {
        fo.exclusions.push(e.parse().map_err(fit_err)?);
    }
    let mut opts = fit::models::pipeline::CalibrateOptions { fit: fo, residual_map, ..Default::default() };
    opts.set_model_name(model).map_err(fit_err)?;
    let inputs = [map.clone()];
    let name = frames_instrument(instrument, &inputs)?;
    let inst = instrument::Instrument::load(&name).map_err(inst_err)?;
    let mut all_inputs = inputs.to_vec();
    if std::path::Path::new(&name).is_file() {
        all_inputs.push(PathBuf::from(&name));
    }
    refuse_overwrite(out.as_deref(), &all_inputs)?;
    // The one step `instpol calibrate --map` makes (workflow::steps::calibrate_map): the map
    // read, the fit, the calibration saved to `out`.
    let (run, warning) = py
        .detach(|| workflow::steps::calibrate_map(&map, &sky, &inst, &opts, out.as_deref()))
        .map_err(|e| match e {
            fit::Error::Frames(e) => sky_err(e),
            e => fit_err(e),
        })?;
    if let Some(w) = warning {
        py.import("warnings")?.call_method1("warn", (w,))?;
    }
    let mut summary = fit::models::pipeline::FitSummary::new(&run);
    summary.calibration_file = out.as_ref().map(|o| o.display().to_string());
    serde_json::to_string(&summary).map_err(|e| input_err(format!("the fit's summary: {e}")))
}

/// The instrumental field from field-star catalogs (`fit::models::stars_field`, what `instpol
/// calibrate-stars` runs): the summary as JSON text (`calibrate-stars --json`'s keys, no
/// plots); the calibration written to `out` when given. `interstellar`: None for a fitted
/// term, `(0, 0)` with `zero` for none, or `(P percent, chi deg)`.
#[pyfunction]
#[pyo3(signature = (catalogs, instrument, filter, out, interstellar_free, interstellar, offsets, model, free_centre, reject_alpha, match_radius_arcsec, allow_mismatch))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn _calibrate_stars(
    py: Python<'_>,
    catalogs: Vec<PathBuf>,
    instrument: Option<&str>,
    filter: &str,
    out: Option<PathBuf>,
    interstellar_free: bool,
    interstellar: Option<(f64, f64)>,
    offsets: Option<Vec<(f64, f64)>>,
    model: &str,
    free_centre: bool,
    reject_alpha: f64,
    match_radius_arcsec: f64,
    allow_mismatch: bool,
) -> PyResult<String> {
    use fit::models::stars_field::{read_catalogs, stars_field, stars_meta, Interstellar, StarsOptions, StarsSummary};
    if catalogs.is_empty() {
        return Err(input_err("no catalogs given: the star catalogs of the pointings (instpol catalog --out)"));
    }
    refuse_same_data(&catalogs, skyfield::same::By::Content)?;
    refuse_overwrite(out.as_deref(), catalogs.iter())?;
    // The one rule of the instrument of catalogs (`instpol calibrate-stars`'s): an inferred or
    // assumed one is said as a Python warning.
    let fit_err = |e: fit::Error| match e {
        fit::Error::Io { .. } | fit::Error::Fits { .. } => FileError::new_err(e.to_string()),
        e => input_err(format!("{e} (instrument=)")),
    };
    let (name, chosen) = fit::models::stars_field::catalogs_instrument(instrument, &catalogs).map_err(fit_err)?;
    let said = match chosen {
        fit::models::stars_field::InstrumentChoice::Given => None,
        fit::models::stars_field::InstrumentChoice::Recorded(i) => {
            Some(format!("instrument {name}, which the catalogs say they are of (INSTRUME = '{i}')"))
        }
        fit::models::stars_field::InstrumentChoice::Assumed => Some(format!(
            "the catalogs do not say which instrument they are of (no INSTRUME keyword): taken as {name}; give instrument= if they are another's"
        )),
    };
    if let Some(w) = said {
        py.import("warnings")?.call_method1("warn", (w,))?;
    }
    let inst = instrument::Instrument::load(&name).map_err(inst_err)?;
    let interstellar = match (interstellar_free, interstellar) {
        (true, _) => Interstellar::Free,
        (false, None) => Interstellar::Zero,
        (false, Some((p, chi))) => {
            Interstellar::from_percent_deg(p, chi).map_err(|e| input_err(format!("interstellar: {e}")))?
        }
    };
    let mut calibrate = fit::models::pipeline::CalibrateOptions::default();
    calibrate.set_model_name(model).map_err(input_err)?;
    calibrate.fit.free_centre = free_centre;
    if !(match_radius_arcsec > 0.0 && match_radius_arcsec.is_finite()) {
        return Err(input_err(format!("match_radius_arcsec {match_radius_arcsec} must be positive")));
    }
    let opts = StarsOptions {
        calibrate,
        interstellar,
        offsets: offsets.map(|o| o.into_iter().map(|(x, y)| [x, y]).collect()),
        match_radius_arcmin: match_radius_arcsec / 60.0,
        reject_alpha,
    };
    let summary = py.detach(|| -> Result<StarsSummary, fit::Error> {
        let expect = (!allow_mismatch).then_some((inst.name.as_str(), filter));
        let (rows, z, notes) = read_catalogs(&catalogs, expect)?;
        let meta = stars_meta(&inst, filter, z, catalogs.iter().map(|p| p.display().to_string()).collect());
        let run = stars_field(&rows, catalogs.len(), meta, &opts)?;
        if let Some(p) = &out {
            run.run.calibration.save(p)?;
        }
        let mut s = StarsSummary::new(&run, &rows, reject_alpha);
        s.warnings.splice(0..0, notes);
        s.fit.calibration_file = out.as_ref().map(|p| p.display().to_string());
        Ok(s)
    });
    let summary = summary.map_err(|e| match e {
        fit::Error::Io { .. } | fit::Error::Fits { .. } => FileError::new_err(e.to_string()),
        e => input_err(e),
    })?;
    serde_json::to_string(&summary).map_err(|e| input_err(format!("the summary: {e}")))
}
