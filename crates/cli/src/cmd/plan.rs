//! `instpol plan`: what a Mueller-field calibration costs: how many sky fields,
//! which, and how long per HWP angle reach a target accuracy, from `fit::mueller_field::plan`.

use anyhow::{anyhow, bail, Result};
use fit::mueller_field::plan::{PlanRequest, PlanRow, PlanSetup, SIMULATION_TOLERANCE};
use fit::mueller_field::{Kind, MuellerField};
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Plan a calibration of the Mueller field: for a target accuracy (RMS over the field of the
/// corrected q, u of polarized targets, model error only), the instrument, the sky brightness
/// and the candidate sky fields with their polarization, find for every number of fields the
/// cheapest choice and its exposure per HWP angle, from the error propagation of the same fit
/// `calibrate-mueller` runs (its inverse Fisher matrix, per-bin errors from eq:sigp with photon
/// and read noise). One field never constrains a retardance: such choices are listed as
/// refused, with the reason. The retardance's errors are Gaussian only where a retardance is
/// present (|g| has no derivative at zero): give --expected (a previous calibration) and use
/// --check, which exits with code 1 and a warning when the simulation misses the target by
/// more than 25 %. --check simulates the cheapest plan (noisy maps of the expected
/// field, fitted and used to correct targets) and reports the accuracy it reaches.
///
/// Example: instpol plan --target-percent 0.02 --sky-rate 2 --candidate 6.45:68.4
/// --candidate 4:10 --candidate 8:130 --expected mueller_B.json --check --plot plan.png
#[derive(clap::Args)]
pub struct Args {
    /// Target RMS of the corrected q, u over the field, in PERCENT (0.02 = 2e-4).
    #[arg(long)]
    pub target_percent: f64,
    /// Built-in instrument name or instrument TOML file (detector size, scale, read noise).
    #[arg(long, default_value = "fors1")]
    pub instrument: String,
    /// Sky count rate, o + e beams, e- per sky pixel per second.
    #[arg(long)]
    pub sky_rate: f64,
    /// A candidate field's sky polarization: P_PERCENT:CHI_DEG. Repeat (at most 8).
    #[arg(long = "candidate", required = true, allow_hyphen_values = true)]
    pub candidates: Vec<String>,
    /// Bin side in detector pixels of the calibration maps.
    #[arg(long, default_value_t = 64)]
    pub bin: usize,
    /// Number of HWP angles per field (optimal set: 4, 8 or 16).
    #[arg(long, default_value_t = 4)]
    pub angles: usize,
    /// Effects besides the diattenuation, as for calibrate-mueller.
    #[arg(long, default_value = "retardance")]
    pub free: String,
    /// Polynomial degree of the model.
    #[arg(long, default_value_t = 4)]
    pub deg: usize,
    /// Polarization degree of the targets (PERCENT).
    #[arg(long, default_value_t = 5.0)]
    pub target_p_percent: f64,
    /// A Mueller field (calibrate-mueller --out: the FITS calibration or the JSON, told apart
    /// by content) to linearize at and, with --check, to simulate; without it: no
    /// instrumental effect.
    #[arg(long)]
    pub expected: Option<PathBuf>,
    /// Simulate the cheapest plan (4 noise draws) and report the accuracy it reaches.
    #[arg(long)]
    pub check: bool,
    /// Plot accuracy against total observing time (.png or .svg, by the extension).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Run even when the estimated run time exceeds 10 minutes or the memory 2 GB (the
    /// estimate, from a timed fit of a sample of the bins, is printed first).
    #[arg(long)]
    pub force: bool,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(serde::Serialize)]
struct Row {
    n_fields: usize,
    fields: Vec<usize>,
    exposure_s: f64,
    total_s: f64,
    rms_qu: f64,
}

#[derive(serde::Serialize)]
struct Report {
    target_rms_qu: f64,
    n_bins: usize,
    sigma_qu_at_plan: Option<f64>,
    plans: Vec<Row>,
    refused: Vec<String>,
    best: Option<Row>,
    simulated_rms_qu: Option<f64>,
    output: Option<PathBuf>,
}

fn parse_candidate(s: &str) -> Result<(f64, f64)> {
    let v: Option<Vec<f64>> = s.split(':').map(|t| t.trim().parse().ok().filter(|x: &f64| x.is_finite())).collect();
    match v.as_deref() {
        Some([p, chi]) if (0.0..100.0).contains(p) => Ok((p / 100.0, chi.to_radians())),
        _ => bail!("--candidate '{s}': expected P_PERCENT:CHI_DEG with 0 <= P < 100, e.g. 6.45:68.4"),
    }
}

pub fn run(a: Args) -> Result<()> {
    if !(a.target_percent > 0.0 && a.target_percent.is_finite()) {
        bail!("--target-percent {}: must be a positive number (percent)", a.target_percent);
    }
    if !(a.sky_rate > 0.0 && a.sky_rate.is_finite()) {
        bail!("--sky-rate {}: must be a positive count rate (e-/px/s)", a.sky_rate);
    }
    if ![4, 8, 16].contains(&a.angles) {
        bail!("--angles {}: the optimal sets have 4, 8 or 16 angles", a.angles);
    }
    if a.deg > 8 {
        bail!("--deg {}: at most 8", a.deg);
    }
    let inst = instrument::Instrument::load(&a.instrument).map_err(|e| anyhow!("{e}"))?;
    crate::util::check_bin(a.bin, &inst)?;
    let candidates: Vec<(f64, f64)> = a.candidates.iter().map(|s| parse_candidate(s)).collect::<Result<_>>()?;
    if candidates.len() > 8 {
        bail!("--candidate given {} times: at most 8", candidates.len());
    }
    let kind = Kind::parse_free(&a.free).map_err(|e| anyhow!("--free '{}': {e}", a.free))?;
    let expected: Option<Arc<MuellerField>> = match &a.expected {
        Some(p) => {
            crate::util::inputs([p.as_path()])?;
            Some(Arc::new(fit::mueller_field::cal::load_field(p).map_err(|e| anyhow!("{e}"))?.field))
        }
        None => None,
    };
    if let Some(p) = &a.plot {
        crate::plot::ImageFormat::of(p)?;
        crate::util::check_output(p)?;
    }
    let positions = fit::mueller_field::plan::detector_bin_centres(&inst, a.bin);
    if let (Some(m), Some(p)) = (&expected, &a.expected) {
        // The interpolant has no value outside the hull of its bins: no silent NaN field.
        if let Some((x, y)) = fit::mueller_field::plan::uncovered_position(m, &positions) {
            bail!(
                "--expected {}: the {} form has no value at the plan's bin centre ({x:.2}, {y:.2}) arcmin (outside the bins it was built from): give a poly or radial field, or a --bin whose centres lie inside",
                p.display(),
                m.smooth.name()
            );
        }
    }
    let req = PlanRequest {
        bin_px: a.bin,
        n_angles: a.angles,
        sky_rate: a.sky_rate,
        candidates,
        kind,
        deg: a.deg,
        target_p: a.target_p_percent / 100.0,
        expected,
    };
    let setup = PlanSetup::for_instrument(&inst, req).map_err(|e| anyhow!("{e}"))?;
    let work = setup.estimate().map_err(|e| anyhow!("{e}"))?;
    if work.seconds > 10.0 && !a.json {
        eprintln!(
            "note: {} bins: estimated {} of fitting, {:.2} GB of memory",
            work.bins,
            crate::util::human_seconds(work.seconds),
            work.bytes / 1e9
        );
    }
    if let (Some(why), false) = (work.over_limit(), a.force) {
        bail!("--bin {}: {why}; use a larger --bin (the calibration maps' own), or pass --force to run it", a.bin);
    }
    let target = a.target_percent / 100.0;
    let bar = indicatif::ProgressBar::with_draw_target(None, indicatif::ProgressDrawTarget::hidden());
    let start = std::time::Instant::now();
    let shown = std::cell::Cell::new(false);
    let (rows, refused) = setup
        .plan_with_progress(target, &|done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
            if !a.json && !shown.get() && start.elapsed().as_secs_f64() > 1.0 {
                shown.set(true);
                bar.set_draw_target(indicatif::ProgressDrawTarget::stderr());
            }
        })
        .map_err(|e| anyhow!("{e}"))?;
    bar.finish_and_clear();
    let best: Option<PlanRow> = PlanSetup::cheapest(&rows);
    let simulated = match (&best, a.check) {
        (Some(b), true) => Some(setup.simulated_rms(b).map_err(|e| anyhow!("{e}"))?),
        _ => None,
    };
    if let (Some(path), Some(b)) = (&a.plot, &best) {
        plot_plan(path, b, &rows, &setup, a.target_percent)?;
    }
    let conv = |r: &PlanRow| Row {
        n_fields: r.n_fields,
        fields: r.fields.clone(),
        exposure_s: r.exposure_s,
        total_s: r.total_s,
        rms_qu: r.rms_qu,
    };
    let rep = Report {
        target_rms_qu: target,
        n_bins: setup.positions.len(),
        sigma_qu_at_plan: best.as_ref().map(|b| setup.sigma_qu(b.exposure_s)),
        plans: rows.iter().map(conv).collect(),
        refused,
        best: best.as_ref().map(conv),
        simulated_rms_qu: simulated,
        output: a.plot.clone(),
    };
    let missed = rep.simulated_rms_qu.filter(|&s| s > SIMULATION_TOLERANCE * target);
    if a.json {
        crate::util::print_json(&rep)?;
        return check_result(missed, target);
    }
    print_plan(&rep, &a);
    check_result(missed, target)
}

/// A --check that missed the target is a failed check (exit code 1), never a quiet 0.
fn check_result(missed: Option<f64>, target: f64) -> Result<()> {
    match missed {
        Some(s) => Err(crate::util::CheckFailed(format!(
            "WARNING: the simulated plan reaches an RMS of {:.4} %, not the target {:.4} %: the Fisher prediction does not hold at this field (near zero retardance the errors are not Gaussian); give --expected or plan for a smaller target",
            100.0 * s,
            100.0 * target
        ))
        .into()),
        None => Ok(()),
    }
}

/// A legend's words for the candidate fields `f` (0-based, as the table numbers them):
/// "field 0", "fields 0 and 1", "fields 0, 1 and 3".
fn fields_label(f: &[usize]) -> String {
    let n: Vec<String> = f.iter().map(|i| i.to_string()).collect();
    match n.as_slice() {
        [] => "no field".into(),
        [one] => format!("field {one}"),
        [rest @ .., last] => format!("fields {} and {last}", rest.join(", ")),
    }
}

/// Accuracy against total observing time, one curve per number of fields (either backend).
fn draw_plan<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    curves: &[(usize, Vec<usize>, Vec<(f64, f64)>)],
    target_percent: f64,
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
) -> Result<()> {
    let ax = crate::plot::Axes::new(
        format!("Accuracy vs time (target {} %)", target_percent),
        "total observing time (s)",
        "RMS corrected q, u (%)",
    )
    .log_labels(Some((x0, x1)), Some((y0, y1)));
    let mut marks: Vec<Vec<(f64, f64)>> =
        curves.iter().map(|c| c.2.iter().map(|p| (p.0, 100.0 * p.1)).collect()).collect();
    marks.push(vec![(x0, target_percent), (x1, target_percent)]);
    use crate::plot::{key, Mark};
    let mut keys: Vec<crate::plot::Key> = (curves.iter().enumerate())
        .map(|(k, (_, f, _))| key(fields_label(f), Mark::Line(crate::plot::series_colour(k).stroke_width(2))))
        .collect();
    keys.push(key("target", Mark::Line(BLACK.stroke_width(1))));
    let (x, y) = (|| crate::plot::log_axis(x0, x1), || crate::plot::log_axis(y0, y1));
    let (mut c, place) = crate::plot::chart_with_legend(root, &ax, x, y, &marks, &keys)?;
    for (m, k) in marks.iter().zip(&keys) {
        let Mark::Line(style) = k.mark else { continue };
        c.draw_series(LineSeries::new(m.iter().copied(), style)).map_err(crate::plot::pe)?;
    }
    crate::plot::draw_legend(&c, place, &keys)
}

/// The plot of each plan's RMS against exposure time, over a decade either side of the
/// cheapest plan's, with the target (percent) marked.
fn plot_plan(path: &Path, b: &PlanRow, rows: &[PlanRow], setup: &PlanSetup, target_percent: f64) -> Result<()> {
    let ts: Vec<f64> = (0..40).map(|k| b.exposure_s * 10f64.powf(-1.0 + 2.0 * k as f64 / 39.0)).collect();
    let mut curves = Vec::new();
    for r in rows {
        curves.push((r.n_fields, r.fields.clone(), setup.curve(&r.fields, &ts).map_err(|e| anyhow!("{e}"))?));
    }
    let (x0, x1) =
        curves.iter().flat_map(|c| c.2.iter().map(|p| p.0)).fold((f64::MAX, 0.0f64), |(a, b), x| (a.min(x), b.max(x)));
    let (y0, y1) = curves
        .iter()
        .flat_map(|c| c.2.iter().map(|p| 100.0 * p.1))
        .fold((f64::MAX, 0.0f64), |(a, b), y| (a.min(y), b.max(y)));
    crate::plot::save_image(
        path,
        (900, 600),
        |r| draw_plan(r, &curves, target_percent, (x0, x1), (y0, y1)),
        |r| draw_plan(r, &curves, target_percent, (x0, x1), (y0, y1)),
    )?;
    Ok(())
}

/// The report as text.
fn print_plan(rep: &Report, a: &Args) {
    outln!(
        "Plan for an RMS of {} % in corrected q, u ({} bins, {} HWP angles per field)",
        a.target_percent,
        rep.n_bins,
        a.angles
    );
    outln!("  {:>8} {:<16} {:>14} {:>12}", "fields", "candidates", "s per angle", "total s");
    for r in &rep.plans {
        outln!("  {:>8} {:<16} {:>14.1} {:>12.0}", r.n_fields, format!("{:?}", r.fields), r.exposure_s, r.total_s);
    }
    for r in &rep.refused {
        outln!("  refused: {r}");
    }
    if let Some(b) = &rep.best {
        outln!(
            "  cheapest: {} field(s) {:?}, {:.1} s per HWP angle, {:.0} s in all",
            b.n_fields,
            b.fields,
            b.exposure_s,
            b.total_s
        );
    } else {
        eprintln!("WARNING: no choice of the candidates constrains the model: see the refusals");
    }
    if let Some(s) = rep.simulated_rms_qu {
        outln!(
            "  simulated ({} noise draws): RMS {:.4} % against the target {} %",
            fit::mueller_field::plan::SIMULATION_DRAWS,
            100.0 * s,
            a.target_percent
        );
    }
    if let Some(p) = &rep.output {
        outln!("  plot: {}", p.display());
    }
}
