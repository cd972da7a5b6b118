//! A night's raw files sorted into a plan and the plan run (`instpol.scan`, `instpol.run`, as
//! `instpol scan` and `instpol run`).

use crate::errors::*;
use pyo3::prelude::*;
use std::path::PathBuf;

/// A folder of raw files sorted by their headers into a plan (`workflow::night::scan::scan`,
/// what `instpol scan` runs): the plan as JSON text (`instpol scan --json`'s keys but
/// `provenance`); written to `out` too when given (TOML, or JSON for a .json name).
#[pyfunction]
#[pyo3(signature = (dirs, instrument, products, sky, sky_table, standards, pointing_tol_arcsec, max_gap_min, bin, fwhm, aperture, out))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn _scan(
    py: Python<'_>,
    dirs: Vec<PathBuf>,
    instrument: String,
    products: PathBuf,
    sky: Vec<(String, f64, f64)>,
    sky_table: Option<PathBuf>,
    standards: Option<PathBuf>,
    pointing_tol_arcsec: f64,
    max_gap_min: f64,
    bin: usize,
    fwhm: f64,
    aperture: f64,
    out: Option<PathBuf>,
) -> PyResult<String> {
    let mut opts = workflow::night::ScanOptions::new(&instrument, &products);
    opts.sky_fields = sky
        .into_iter()
        .map(|(target, p_percent, chi_deg)| workflow::night::SkyField { target, p_percent, chi_deg })
        .collect();
    if let Some(t) = &sky_table {
        opts.sky_fields.extend(workflow::night::SkyField::read_table(t).map_err(night_err)?);
    }
    opts.standards = standards;
    opts.pointing_tol_arcsec = pointing_tol_arcsec;
    opts.max_gap_min = max_gap_min;
    opts.bin_px = bin;
    opts.fwhm_px = fwhm;
    opts.aperture_px = aperture;
    let plan = py.detach(|| workflow::night::scan(&dirs, &opts)).map_err(night_err)?;
    if let Some(o) = &out {
        plan.write(o).map_err(night_err)?;
    }
    serde_json::to_string(&plan).map_err(|e| input_err(format!("the plan: {e}")))
}

/// Run a plan, given as JSON text or as a plan file (TOML, or JSON for a .json name;
/// `workflow::night::run::run`, what `instpol run` runs), each unit in process through the
/// library (`workflow::night::library_executor`), a command it does not know whole through the
/// `instpol` binary `program` when given: the report as JSON text (`instpol run --json`'s keys but `provenance`).
/// A plan that cannot run (a cycle, a missing input, an unknown kind or unit, outputs over
/// inputs): InputError, nothing run.
#[pyfunction]
#[pyo3(signature = (plan_text, plan_path, jobs, only, dry_run, program))]
pub(crate) fn _run(
    py: Python<'_>,
    plan_text: Option<String>,
    plan_path: Option<PathBuf>,
    jobs: usize,
    only: Option<Vec<String>>,
    dry_run: bool,
    program: Option<PathBuf>,
) -> PyResult<String> {
    let plan: workflow::night::Plan = match (plan_text, plan_path) {
        (Some(t), _) => serde_json::from_str(&t).map_err(|e| input_err(format!("the plan is not a plan: {e}")))?,
        (None, Some(p)) => workflow::night::Plan::load(&p).map_err(|e| match e {
            workflow::night::Error::Input { .. } => FileError::new_err(e.to_string()),
            e => input_err(e),
        })?,
        (None, None) => return Err(input_err("no plan")),
    };
    if jobs == 0 {
        return Err(input_err("jobs = 0: run at least one unit at a time"));
    }
    if let Some(ids) = &only {
        for id in ids {
            plan.unit(id).map_err(night_err)?;
        }
    }
    let opts = workflow::night::RunOptions { jobs, only, dry_run };
    let exec = workflow::night::library_executor(program, plan.records.clone());
    let report = py.detach(|| workflow::night::run::run(&plan, &opts, &exec, &|_| {})).map_err(night_err)?;
    serde_json::to_string(&report).map_err(|e| input_err(format!("the report: {e}")))
}
