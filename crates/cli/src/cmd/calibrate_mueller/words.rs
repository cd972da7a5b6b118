//! The words of `instpol calibrate-mueller`: its report (the `--json` object) and the report as
//! text.

use fit::mueller_field::stars::ParamSummary;
use std::path::PathBuf;

/// What a fit reports (`schemas/calibrate-mueller.schema.json`).
#[derive(serde::Serialize)]
pub(super) struct Report {
    pub(super) output: PathBuf,
    pub(super) n_fields: usize,
    pub(super) n_stars: usize,
    pub(super) n_obs: usize,
    pub(super) deg: usize,
    pub(super) smooth: &'static str,
    pub(super) model: &'static str,
    pub(super) free: Vec<&'static str>,
    pub(super) chi2_dof: f64,
    pub(super) condition: Option<f64>,
    pub(super) parameters: Vec<ParamSummary>,
    pub(super) median_p: Option<f64>,
    pub(super) max_p: Option<f64>,
    pub(super) median_retardance_deg: Option<f64>,
    pub(super) max_retardance_deg: Option<f64>,
    pub(super) n_bins_fitted: Option<usize>,
    pub(super) n_bins_unconstrained: Option<usize>,
    pub(super) warnings: Vec<String>,
    /// What the calibration is: the maps' instrument file and detector, the run's inputs.
    pub(super) product: skyfield::provenance::Product,
}

/// The report as text (`condition`: the Fisher condition number, infinite ones too).
pub(super) fn print_report(rep: &Report, condition: f64) {
    outln!(
        "Mueller field from {} fields and {} stars, {} observations: {} model, free {}",
        rep.n_fields,
        rep.n_stars,
        rep.n_obs,
        rep.model,
        rep.free.join(", ")
    );
    let form = match rep.smooth {
        "poly" => format!("degree {} polynomials", rep.deg),
        "radial" => format!("radial patterns, powers 1..{} of r", rep.deg),
        _ => "interpolated per-bin fits".into(),
    };
    outln!("  {form}, chi2/dof {:.3}, Fisher condition number {:.3e}", rep.chi2_dof, condition);
    outln!("  {:<16} {:>12} {:>12} {:>12}", "parameter", "median", "rms", "median sigma");
    for p in &rep.parameters {
        outln!("  {:<16} {:>12.3e} {:>12.3e} {:>12.3e}", p.name, p.median_value, p.rms_value, p.median_sigma);
    }
    if let (Some(m), Some(x)) = (rep.median_p, rep.max_p) {
        outln!("  diattenuation p: median {:.4} %, largest {:.4} %", 100.0 * m, 100.0 * x);
    }
    if let (Some(m), Some(x)) = (rep.median_retardance_deg, rep.max_retardance_deg) {
        outln!("  retardance: median {m:.2} deg, largest {x:.2} deg");
    }
    if let (Some(n), Some(s)) = (rep.n_bins_fitted, rep.n_bins_unconstrained) {
        outln!("  per bin: {n} bins fitted, {s} not constrained on their own");
    }
    for w in &rep.warnings {
        eprintln!("WARNING: {w}");
    }
    outln!("  written: {}", rep.output.display());
}
