//! What a night's report shows, gathered from what the night's commands already wrote: the
//! plan (`instpol scan`: the files found, the sets, what was left out and why, the units), the
//! run's records (`instpol run`: which units finished, with the hashes of what they read and
//! wrote, and the checks that did not pass), the units' outputs (the standards' measurements
//! against their catalogued values, the sky-field calibrations), and over the nights given the
//! trend of [`super::trend`]. `instpol report` renders it as a static page; nothing here is
//! computed anew but the pulls, each `(measured - catalogued) / sigma` with both errors
//! combined.

use super::plan::{LeftOut, Plan, Unit};
use super::run::up_to_date;
use super::trend::{self, number, read_json, Trend};
use super::Error;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Where a unit stands (from its record: `workflow::night::run`).
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "snake_case", tag = "state", content = "reason")]
pub enum UnitState {
    /// Finished, and its record matches its inputs and outputs now.
    Done,
    /// A check that ran and did not pass (its output is written), with the command's message.
    CheckFailed(String),
    /// Its outputs exist but no record matches them: changed since, or made by hand.
    NotRecorded,
    /// Not run (or failed): no output.
    NotRun,
}

/// One unit of the plan and its outcome.
#[derive(Debug, Clone, Serialize)]
pub struct UnitSummary {
    pub id: String,
    pub kind: String,
    pub state: UnitState,
    /// Its outputs with their recorded hashes (`blake3:<hex>`; empty when not recorded).
    pub outputs: Vec<(PathBuf, String)>,
    /// The number of files it reads.
    pub n_inputs: usize,
    /// The outcome in a few numbers read from its output (JSON outputs only): name and value
    /// as written, in the output's units.
    pub values: Vec<(String, f64)>,
}

/// A set of exposures found (a unit reading raw frames of one target and filter).
#[derive(Debug, Clone, Serialize)]
pub struct SetFound {
    /// `<night>-<target>-<filter>`, as the set's units are named.
    pub name: String,
    pub filter: Option<String>,
    /// Start of the set (MJD).
    pub mjd: Option<f64>,
    /// The standard star it observes, if any.
    pub standard: Option<String>,
    /// Its exposures' files.
    pub n_files: usize,
    /// The units that use it.
    pub units: Vec<String>,
}

/// A standard star's measured value against its catalogued (or expected) one.
#[derive(Debug, Clone, Serialize)]
pub struct StandardCheck {
    pub unit: String,
    /// The unit's kind (`zero-angle`, `photometry`, `validate`).
    pub kind: String,
    pub star: String,
    pub filter: String,
    /// `p` (zero-angle units: the measured `P` against the standards list's), `q`, `u`
    /// (photometry of an unpolarized standard: against 0), `p_corrected` (validate units: the
    /// corrected `P` against the published one, or 0).
    pub quantity: String,
    pub measured: f64,
    pub sigma: f64,
    pub catalogue: f64,
    pub sigma_catalogue: f64,
    /// `(measured - catalogue) / sqrt(sigma^2 + sigma_catalogue^2)`.
    pub pull: f64,
}

/// A sky-field calibration made by the night.
#[derive(Debug, Clone, Serialize)]
pub struct CalibrationProduct {
    pub unit: String,
    pub filter: String,
    pub file: PathBuf,
    /// The instrumental `P` at the field's edge and its error (`fit::Calibration::p_at_edge`).
    pub p_edge: Option<(f64, f64)>,
}

/// One night: its plan and products (module docs).
#[derive(Debug, Clone, Serialize)]
pub struct NightReport {
    pub plan: PathBuf,
    pub instrument: String,
    /// Usable files by role (bias, flat, polarimetry, standard).
    pub roles: BTreeMap<String, usize>,
    pub sets: Vec<SetFound>,
    pub left_out: Vec<LeftOut>,
    pub units: Vec<UnitSummary>,
    pub standards: Vec<StandardCheck>,
    pub calibrations: Vec<CalibrationProduct>,
}

/// The report of one or more nights and their trend.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub nights: Vec<NightReport>,
    pub trend: Trend,
}

/// Gather the report of `plans` (plan files; module docs), the trend's steps at
/// `threshold_sigma` ([`trend::gather`]: plans of one instrument, unless `allow_mismatch`).
/// An output that does not hold what its kind writes is an error naming the file.
pub fn gather(plans: &[PathBuf], threshold_sigma: f64, allow_mismatch: bool) -> Result<Report, Error> {
    let trend = trend::gather(plans, threshold_sigma, allow_mismatch)?;
    let nights = plans.iter().map(|p| night(p)).collect::<Result<_, _>>()?;
    Ok(Report { nights, trend })
}

/// The report of one plan file.
pub fn night(path: &Path) -> Result<NightReport, Error> {
    let plan = Plan::load(path)?;
    let mut roles = BTreeMap::new();
    for f in &plan.files {
        *roles.entry(f.role.clone()).or_insert(0) += 1;
    }
    let mut units = Vec::new();
    let mut standards = Vec::new();
    let mut calibrations = Vec::new();
    for u in &plan.units {
        let summary = unit_summary(&plan, u)?;
        if summary.state != UnitState::NotRun {
            standards.extend(standard_checks(u)?);
            if u.kind == "calibrate" {
                let file = u.outputs[0].clone();
                let cal = fit::Calibration::load(&file)
                    .map_err(|e| Error::Input { path: file.clone(), why: e.to_string() })?;
                calibrations.push(CalibrationProduct {
                    unit: u.id.clone(),
                    filter: u.filter.clone().unwrap_or_else(|| cal.filter.clone()),
                    file,
                    p_edge: cal.p_at_edge(),
                });
            }
        }
        units.push(summary);
    }
    Ok(NightReport {
        plan: path.into(),
        instrument: plan.instrument.clone(),
        roles,
        sets: sets(&plan),
        left_out: plan.left_out.clone(),
        units,
        standards,
        calibrations,
    })
}

/// The sets of the plan: the raw files a unit reads (its inputs that are usable files of the
/// plan, not masters) grouped by the name its units share after their kind.
fn sets(plan: &Plan) -> Vec<SetFound> {
    let raw: std::collections::BTreeSet<&Path> = plan.files.iter().map(|f| f.path.as_path()).collect();
    let mut out: Vec<SetFound> = Vec::new();
    for u in &plan.units {
        if matches!(u.kind.as_str(), "master-bias" | "master-flat") {
            continue;
        }
        let n_files = u.inputs.iter().filter(|p| raw.contains(p.as_path())).count();
        if n_files == 0 {
            continue;
        }
        let name = u.id.strip_prefix(&format!("{}-", u.kind)).unwrap_or(&u.id).to_string();
        match out.iter_mut().find(|s| s.name == name) {
            Some(s) => {
                s.units.push(u.id.clone());
                s.standard = s.standard.take().or_else(|| u.standard.clone());
            }
            None => out.push(SetFound {
                name,
                filter: u.filter.clone(),
                mjd: u.mjd,
                standard: u.standard.clone(),
                n_files,
                units: vec![u.id.clone()],
            }),
        }
    }
    out
}

fn unit_summary(plan: &Plan, u: &Unit) -> Result<UnitSummary, Error> {
    let record = up_to_date(plan, u);
    let state = match &record {
        Some(r) => r.check_failed.clone().map_or(UnitState::Done, UnitState::CheckFailed),
        None if u.outputs.iter().all(|o| o.is_file()) => UnitState::NotRecorded,
        None => UnitState::NotRun,
    };
    let outputs = match record {
        Some(r) => r.outputs,
        None => u.outputs.iter().map(|o| (o.clone(), String::new())).collect(),
    };
    let values = if state == UnitState::NotRun { vec![] } else { values(u)? };
    Ok(UnitSummary { id: u.id.clone(), kind: u.kind.clone(), state, outputs, n_inputs: u.inputs.len(), values })
}

/// The numbers of a unit's JSON output that say its outcome, by kind.
const VALUES: &[(&str, &[&str])] = &[
    ("zero-angle", &["zero_angle_deg", "sigma_zero_angle_deg", "n_standards"]),
    ("photometry", &["q", "sigma_q", "u", "sigma_u", "p", "sigma_p"]),
    ("validate", &["measured_p", "corrected_p", "sigma_corrected_p", "expected_p", "corrected_pull", "threshold"]),
];

fn values(u: &Unit) -> Result<Vec<(String, f64)>, Error> {
    let Some((_, keys)) = VALUES.iter().find(|(k, _)| *k == u.kind) else { return Ok(vec![]) };
    let v = read_json(&u.outputs[0])?;
    Ok(keys.iter().filter_map(|k| v.get(*k).and_then(|x| x.as_f64()).map(|x| (k.to_string(), x))).collect())
}

fn check(u: &Unit, star: &str, quantity: &str, (m, s): (f64, f64), (c, sc): (f64, f64)) -> StandardCheck {
    StandardCheck {
        unit: u.id.clone(),
        kind: u.kind.clone(),
        star: star.into(),
        filter: u.filter.clone().unwrap_or_default(),
        quantity: quantity.into(),
        measured: m,
        sigma: s,
        catalogue: c,
        sigma_catalogue: sc,
        pull: (m - c) / s.hypot(sc),
    }
}

/// The standards' values a unit measured against their catalogued ones (module docs).
fn standard_checks(u: &Unit) -> Result<Vec<StandardCheck>, Error> {
    let Some(star) = u.standard.as_deref() else { return Ok(vec![]) };
    let out = &u.outputs[0];
    match u.kind.as_str() {
        "zero-angle" => {
            let v = read_json(out)?;
            let Some((p, sp)) = trend::measured_p(&v) else { return Ok(vec![]) };
            Ok(trend::catalogue_p(u, out)?.map(|c| check(u, star, "p", (p, sp), c)).into_iter().collect())
        }
        "photometry" => {
            let v = read_json(out)?;
            if v.get("p_true").is_some_and(|p| !p.is_null()) {
                return Ok(vec![]);
            }
            let q = (number(&v, "q", out)?, number(&v, "sigma_q", out)?);
            let w = (number(&v, "u", out)?, number(&v, "sigma_u", out)?);
            Ok(vec![check(u, star, "q", q, (0.0, 0.0)), check(u, star, "u", w, (0.0, 0.0))])
        }
        "validate" => {
            let v = read_json(out)?;
            let m = (number(&v, "corrected_p", out)?, number(&v, "sigma_corrected_p", out)?);
            Ok(vec![check(u, star, "p_corrected", m, (number(&v, "expected_p", out)?, 0.0))])
        }
        _ => Ok(vec![]),
    }
}
