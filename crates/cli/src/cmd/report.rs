//! `instpol report`: a static HTML page of nights' plans and products and of their trend
//! (`workflow::night::report` gathers; this draws the figures and `report_html` prints the page).

use super::report_html::Figures;
use anyhow::{Context, Result};
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use workflow::night::report::{self, Report, StandardCheck};

/// Write a static HTML report of one or more nights (plans from `instpol scan`, run by
/// `instpol run`) into one folder: OUT/index.html and its figures as SVG files in OUT/figures/.
/// Per night: the files found by role, the sets and the files left out with the reasons, every
/// unit's outcome (from the run's records, with its outputs' BLAKE3 hashes) and its numbers, the
/// standards against their catalogued values with pulls ((measured - catalogued) / sigma), and
/// the sky-field calibration maps (map, radial profile, residuals); over all the plans given,
/// the trend of `instpol trend` (each series with its most significant step). No server, no
/// network, no script: open index.html in any browser, offline. Products are named by path,
/// not copied. The page ends with its provenance (version, command line, date, the plans'
/// hashes).
///
/// Example: instpol report night.toml --out report
///
/// Example: instpol report nights/*/night.toml --out archive-report --threshold 5
#[derive(clap::Args)]
pub struct Args {
    /// Plan files (`instpol scan --out`), each run by `instpol run`.
    #[arg(required = true)]
    pub plans: Vec<PathBuf>,
    /// Output folder (created if needed): index.html and figures/*.svg, each written atomically.
    #[arg(long)]
    pub out: PathBuf,
    /// Step significance (sigma) above which a trend's step is flagged (as `instpol trend`).
    #[arg(long, default_value_t = workflow::night::trend::DEFAULT_THRESHOLD_SIGMA)]
    pub threshold: f64,
    /// Report plans of several instruments together (refused otherwise, as `instpol trend`
    /// refuses them); the page says so.
    #[arg(long)]
    pub allow_mismatch: bool,
    /// Print what was written as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(serde::Serialize)]
struct Written {
    output: PathBuf,
    figures: Vec<PathBuf>,
    nights: usize,
    units: usize,
    units_done: usize,
    standards: usize,
    calibrations: usize,
    trend_points: usize,
    trend_series: usize,
    trend_flagged: usize,
}

/// A name safe in a file name and an URL: letters, digits, `.`, `-` and `_`, the rest `_`.
fn safe(name: &str) -> String {
    name.chars().map(|c| if c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_') { c } else { '_' }).collect()
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs(a.plans.iter().map(|p| p.as_path()))?;
    let r = report::gather(&a.plans, a.threshold, a.allow_mismatch)?;
    if let Some(m) = &r.trend.product.mismatch_allowed {
        eprintln!("warning: --allow-mismatch: {m} in one report");
    }
    let before = files_in(&a.out);
    let out_existed = a.out.exists();
    let result = write(&a, &r);
    if result.is_err() {
        // A failed report (a full disk at its fifth figure) leaves none of the files it made:
        // a page without its figures would look complete. Files of an earlier report stay.
        for p in files_in(&a.out).into_iter().filter(|p| !before.contains(p)) {
            let _ = std::fs::remove_file(p);
        }
        let _ = std::fs::remove_dir(a.out.join("figures"));
        if !out_existed {
            let _ = std::fs::remove_dir(&a.out);
        }
    }
    result
}

/// The files of a report folder: its page and its figures.
fn files_in(out: &Path) -> Vec<PathBuf> {
    let figures = std::fs::read_dir(out.join("figures")).into_iter().flatten().flatten().map(|e| e.path());
    figures.chain(std::iter::once(out.join("index.html")).filter(|p| p.exists())).collect()
}

/// Draw the figures and write the page of `r` (module docs).
fn write(a: &Args, r: &Report) -> Result<()> {
    // Nothing the nights read or wrote may be written over: the plans (registered above), their
    // products and records.
    let products: Vec<&Path> =
        r.nights.iter().flat_map(|n| n.units.iter()).flat_map(|u| u.outputs.iter()).map(|(p, _)| p.as_path()).collect();
    let figures_dir = a.out.join("figures");
    let index = a.out.join("index.html");
    let guard = |p: &Path| -> Result<()> {
        crate::util::check_output(p)?;
        skyfield::durable::refuse_overwrite(p, products.iter().copied()).map_err(anyhow::Error::msg)
    };
    guard(&index)?;
    std::fs::create_dir_all(&figures_dir).with_context(|| format!("cannot create {}", figures_dir.display()))?;
    let mut figs = Figures::default();
    let mut written = vec![];
    for (k, night) in r.nights.iter().enumerate() {
        let mut per_cal = vec![];
        for c in &night.calibrations {
            let stem = safe(&format!("n{k}-{}", c.unit));
            for name in ["map", "profile", "residual"] {
                guard(&figures_dir.join(format!("{stem}_{name}.svg")))?;
            }
            let run = crate::cmd::plot::refit_file(&c.file)?;
            let files = crate::cmd::plot::svg_figures(&figures_dir, &stem, &run)?;
            per_cal
                .push(files.iter().filter_map(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned()).collect());
            written.extend(files);
        }
        figs.calibrations.push(per_cal);
        let pulls = if night.standards.is_empty() {
            None
        } else {
            let name = format!("n{k}-pulls.svg");
            let path = figures_dir.join(&name);
            guard(&path)?;
            draw_pulls(&path, &night.standards)?;
            written.push(path);
            Some(name)
        };
        figs.pulls.push(pulls);
    }
    if !r.trend.points.is_empty() {
        let path = figures_dir.join("trend.svg");
        guard(&path)?;
        crate::cmd::trend::plot(&path, &r.trend)?;
        written.push(path);
        figs.trend = Some("trend.svg".into());
    }
    let provenance = skyfield::provenance::current();
    let html = crate::cmd::report_html::page(r, &figs, &provenance);
    crate::util::write_atomic(&index, html.as_bytes())?;
    let w = summary(r, index, written);
    if a.json {
        return crate::util::print_json(&w);
    }
    outln!(
        "{}: {} night(s), {} units ({} done), {} standard value(s), {} calibration(s), trend of {} point(s) in {} series ({} flagged); {} figures in {}",
        w.output.display(),
        w.nights,
        w.units,
        w.units_done,
        w.standards,
        w.calibrations,
        w.trend_points,
        w.trend_series,
        w.trend_flagged,
        w.figures.len(),
        figures_dir.display()
    );
    Ok(())
}

fn summary(r: &Report, output: PathBuf, figures: Vec<PathBuf>) -> Written {
    let units = r.nights.iter().flat_map(|n| n.units.iter());
    Written {
        output,
        figures,
        nights: r.nights.len(),
        units: units.clone().count(),
        units_done: units.filter(|u| u.state == report::UnitState::Done).count(),
        standards: r.nights.iter().map(|n| n.standards.len()).sum(),
        calibrations: r.nights.iter().map(|n| n.calibrations.len()).sum(),
        trend_points: r.trend.points.len(),
        trend_series: {
            let mut s: Vec<(&str, &str)> =
                r.trend.points.iter().map(|p| (p.quantity.as_str(), p.filter.as_str())).collect();
            s.dedup();
            s.len()
        },
        trend_flagged: r.trend.steps.iter().filter(|s| s.flagged).count(),
    }
}

/// The standards' pulls against the row number of the page's table, the 0, +-1 and +-3 sigma
/// lines drawn (a pull that is not a number, of a value without an error, is left out of the
/// figure; the table prints it).
fn draw_pulls(path: &Path, checks: &[StandardCheck]) -> Result<()> {
    crate::plot::save_image(path, (900, 500), |a| pulls_on(a, checks), |a| pulls_on(a, checks))
}

fn pulls_on<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    checks: &[StandardCheck],
) -> Result<()> {
    // At least +-5 sigma: the ticks at -5, 0 and 5 are labelled whatever the pulls.
    let top = (checks.iter().map(|c| c.pull.abs()).filter(|p| p.is_finite()).fold(0.0, f64::max) * 1.1).max(5.2);
    let n = checks.len() as f64;
    let whole = |x: &f64| if (x - x.round()).abs() < 1e-6 { format!("{}", x.round()) } else { String::new() };
    let ax = crate::plot::Axes::new(
        "standards against their catalogued values",
        "row of the standards table",
        "pull (sigma)",
    )
    .x_ticks(checks.len() + 2, &whole);
    let mut c = crate::plot::chart(area, &ax, 0.5..(n + 0.5), -top..top)?;
    let lines = [(0.0, BLACK), (-1.0, BLUE), (1.0, BLUE), (-3.0, RED), (3.0, RED)];
    for (y, colour) in lines {
        c.draw_series(LineSeries::new([(0.5, y), (n + 0.5, y)], colour.stroke_width(2))).map_err(crate::plot::pe)?;
    }
    let finite = checks.iter().enumerate().filter(|(_, ch)| ch.pull.is_finite());
    c.draw_series(finite.map(|(k, ch)| Circle::new(((k + 1) as f64, ch.pull), 6, BLACK.filled())))
        .map_err(crate::plot::pe)?;
    Ok(())
}
