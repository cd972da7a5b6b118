//! `instpol trend`: the standards of many nights against date (`workflow::night::trend`).

use anyhow::{bail, Result};
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use workflow::night::trend::{self, Trend};

/// Gather the results of many nights (the plans `instpol scan` wrote and `instpol run` ran):
/// each polarized standard's HWP zero angle per filter and its P less the catalogued P, the
/// telescope model's parameters where a night's standards were fitted, the unpolarized standards'
/// instrumental polarization (q, u, P) and the sky-field calibrations' instrumental P at the
/// field's edge (the mean over the midpoints of its four sides) against date, and in each
/// series the most significant
/// step (the split into earlier and later nights whose weighted means differ most in units of
/// their error, the errors widened by each part's scatter); a step beyond --threshold sigma
/// is flagged (a mirror recoating, a moved zero angle). Writes one row per measurement
/// (quantity, filter, star, mjd, value, sigma, after_step) as a table of the extension's
/// format; --plot draws one panel per series, date on x, errors and the step's two means.
///
/// Example:
///   instpol trend nights/*/night.toml --out trend.ecsv --plot trend.png
#[derive(clap::Args)]
pub struct Args {
    /// Plans of the nights (from `instpol scan`, run by `instpol run`).
    #[arg(required = true)]
    pub plans: Vec<PathBuf>,
    /// The table to write (.ecsv, .csv, .fits or .vot).
    #[arg(long)]
    pub out: PathBuf,
    /// Also draw the series (PNG, or SVG for a .svg name).
    #[arg(long, value_name = "TREND.png")]
    pub plot: Option<PathBuf>,
    /// Significance (sigma) above which a step is flagged.
    #[arg(long, default_value_t = workflow::night::trend::DEFAULT_THRESHOLD_SIGMA)]
    pub threshold: f64,
    /// Put plans of several instruments into one trend (refused otherwise: a step between two
    /// instruments is no step); the table records it (MISMATCH).
    #[arg(long)]
    pub allow_mismatch: bool,
    /// Print the points and steps as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs(a.plans.iter().map(|p| p.as_path()))?;
    crate::util::check_output(&a.out)?;
    if let Some(p) = &a.plot {
        crate::util::check_output(p)?;
        if p == &a.out {
            bail!("--plot {} is also --out: choose two names", p.display());
        }
    }
    let t = trend::gather(&a.plans, a.threshold, a.allow_mismatch)?;
    if let Some(m) = &t.product.mismatch_allowed {
        eprintln!("warning: --allow-mismatch: {m} in one trend; the table records it (MISMATCH)");
    }
    t.table().write(&a.out)?;
    if let Some(p) = &a.plot {
        plot(p, &t)?;
    }
    if a.json {
        return crate::util::print_json(&t);
    }
    match t.points.len() {
        0 => outln!(
            "{}: no measurements: no unit done in these plans measured a standard or made a sky-field calibration (run them first: instpol run PLAN)",
            a.out.display()
        ),
        n => outln!("{}: {n} measurements of {} series", a.out.display(), t.steps.len()),
    }
    outln!(
        "{:<16} {:<10} {:>4} {:>14} {:>14} {:>12} {:>8}  step after MJD",
        "quantity",
        "filter",
        "n",
        "before",
        "after",
        "delta",
        "sigma"
    );
    for s in &t.steps {
        outln!(
            "{:<16} {:<10} {:>4} {:>14.6} {:>14.6} {:>12.6} {:>8.1}  {:.1}{}",
            s.quantity,
            s.filter,
            s.n_before + s.n_after,
            s.before,
            s.after,
            s.delta,
            s.significance,
            s.last_before_mjd,
            if s.flagged { "  FLAGGED" } else { "" }
        );
    }
    Ok(())
}

/// One panel per series: the points with their errors against MJD, the step's two weighted
/// means as horizontal lines (red when flagged).
pub fn plot(path: &Path, t: &Trend) -> Result<()> {
    let mut series: Vec<(String, String)> = t.points.iter().map(|p| (p.quantity.clone(), p.filter.clone())).collect();
    series.dedup();
    if series.is_empty() {
        bail!("--plot {}: the plans hold no measured standard to draw", path.display());
    }
    // 900 px wide (one journal column, `crate::plot`), 260 px per series.
    let size = (900, (260 * series.len() as u32).max(300));
    crate::plot::save_image(path, size, |root| draw(root, t, &series), |root| draw(root, t, &series))
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    t: &Trend,
    series: &[(String, String)],
) -> Result<()> {
    {
        let panels = root.split_evenly((series.len(), 1));
        for ((q, f), area) in series.iter().zip(panels.iter()) {
            let pts: Vec<_> = t.points.iter().filter(|p| &p.quantity == q && &p.filter == f).collect();
            let (x0, x1) =
                pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.mjd), b.max(p.mjd)));
            let (y0, y1) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
                (a.min(p.value - p.sigma), b.max(p.value + p.sigma))
            });
            let (dx, dy) = ((x1 - x0).max(1.0) * 0.05, (y1 - y0).max(1e-6) * 0.1);
            let ax = crate::plot::Axes::new(format!("{q} {f}"), "MJD", q.as_str());
            let mut c = crate::plot::chart(area, &ax, (x0 - dx)..(x1 + dx), (y0 - dy)..(y1 + dy))?;
            for p in &pts {
                c.draw_series(std::iter::once(PathElement::new(
                    [(p.mjd, p.value - p.sigma), (p.mjd, p.value + p.sigma)],
                    BLUE,
                )))
                .map_err(crate::plot::pe)?;
                c.draw_series(std::iter::once(Circle::new((p.mjd, p.value), 4, BLUE.filled())))
                    .map_err(crate::plot::pe)?;
            }
            if let Some(s) = t.steps.iter().find(|s| &s.quantity == q && &s.filter == f) {
                let col = if s.flagged { RED } else { BLACK };
                let mid = 0.5 * (s.last_before_mjd + s.first_after_mjd);
                c.draw_series(LineSeries::new([(x0 - dx, s.before), (mid, s.before)], col.stroke_width(2)))
                    .map_err(crate::plot::pe)?;
                c.draw_series(LineSeries::new([(mid, s.after), (x1 + dx, s.after)], col.stroke_width(2)))
                    .map_err(crate::plot::pe)?;
            }
        }
        Ok(())
    }
}
