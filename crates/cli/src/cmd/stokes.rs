//! `instpol stokes`: reduce one source's dual-beam fluxes (the `stokes` crate does the work).

use anyhow::{anyhow, bail, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use stokes::{Error as RedError, Reduction};

/// Reduce the ordinary/extraordinary fluxes of one source at N half-wave-plate angles to
/// Q/I, U/I, P, chi with errors, the Fourier harmonics of F_i and the Wollaston kappa
/// (Patat & Romaniello 2006, eq:F, eq:Q, eq:U, eq:sigp, eq:sigchi, eq:fourcoeff, eq:kappa2).
///
/// Input: a CSV file with a header row naming the columns (any order; other columns are
/// ignored; lines starting with # are comments):
///
///   hwp_deg  HWP angle in degrees; rows in observing order (the optimal set is row i at
///            i*22.5 deg: 0, 22.5, 45, ...)
///   f_o      ordinary-beam flux
///   f_e      extraordinary-beam flux
///   sigma_o  (optional) 1-sigma error of f_o
///   sigma_e  (optional) 1-sigma error of f_e
///
/// Without sigma_o/sigma_e the fluxes must be photon counts in electrons and their Poisson
/// errors sqrt(f) are used. With N = 4k angles on the optimal set, Q/I and U/I are the
/// Fourier sums eq:Q/eq:U and the harmonics are computed; other sets use (weighted) least
/// squares. kappa_j (eq:g, eq:kappa2) comes from rows j-1 and j+1 when they are 45 deg
/// apart (j = 1..N-2) and needs N >= 4.
///
/// Output: a table (P in %, angles in deg) or, with --json, the fields n_hwp, q, u, p
/// (fractions), chi_deg in [0, 180), sigma_p, sigma_chi_deg (null when P = 0), a0, kappa
/// (array), kappa_mean (null when none), fourier (array of {k, a, b, sigma_a, sigma_b}),
/// warnings, plus extra detail fields.
///
/// Example: instpol stokes --input tests/data/fors1_v_star_n16.csv --plot fourier.png
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// Table with columns hwp_deg,f_o,f_e[,sigma_o,sigma_e]: CSV (header required), FITS,
    /// ECSV or VOTable, by extension.
    #[arg(long, value_name = "FILE.csv")]
    pub input: PathBuf,
    #[command(flatten)]
    pub kappa: super::frame_opts::KappaOpts,
    /// Also draw the paper's fig:fourier as a PNG (1000 x 1300 px): F_i with their 1-sigma
    /// errors (from sigma_o/sigma_e, else Poisson) against the HWP angle, with the curve
    /// Q cos 4theta + U sin 4theta of the fitted Q, U (eq:system), raised by a_0 = mean F_i
    /// (eq:a0) on the optimal angle sets; below, the harmonic amplitudes with their 1-sigma
    /// noise (optimal angle sets only). Written whole or not at all.
    #[arg(long, value_name = "FILE.png")]
    pub plot: Option<PathBuf>,
    /// Print JSON instead of the table.
    #[arg(long)]
    pub json: bool,
    /// The hwp_deg column holds radians, not degrees. Without it, a column whose angles all lie
    /// within 0..2pi (as radians of an HWP set do, and no degree set of use does) is refused.
    #[arg(long)]
    pub angles_in_radians: bool,
}

/// The parsed CSV: one entry per data row.
struct Table {
    hwp_deg: Vec<f64>,
    f_o: Vec<f64>,
    f_e: Vec<f64>,
    sigma: Option<(Vec<f64>, Vec<f64>)>,
    /// File line number of each data row (1-based).
    lines: Vec<u64>,
}

fn read_table(path: &Path, angles_in_radians: bool) -> Result<Table> {
    let name = path.display();
    let t = skyfield::table::Table::read(path, None)?;
    // A declared unit is converted to degrees when the column is read: the flag would convert
    // the angles a second time.
    if let (true, Some(u)) = (angles_in_radians, t.unit_of("hwp_deg")) {
        bail!(
            "{name}: column 'hwp_deg' declares its unit ({u}) and is read in degrees from it: drop --angles-in-radians"
        );
    }
    let col = |c: &str| -> Result<Option<Vec<f64>>> {
        if t.column(c).is_none() {
            return Ok(None);
        }
        let v = t.numbers(c, path)?;
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            bail!("{name}: {}, column '{c}': '{}' is not a finite number", t.row_label(i), v[i]);
        }
        Ok(Some(v))
    };
    let need = |c: &str| -> Result<Vec<f64>> {
        col(c)?.ok_or_else(|| {
            anyhow!(
                "{name}: missing column '{c}' (header has: {}; need hwp_deg,f_o,f_e[,sigma_o,sigma_e])",
                t.names().join(",")
            )
        })
    };
    let (hwp_deg, f_o, f_e) = (need("hwp_deg")?, need("f_o")?, need("f_e")?);
    let sigma = match (col("sigma_o")?, col("sigma_e")?) {
        (Some(a), Some(b)) => Some((a, b)),
        (None, None) => None,
        (Some(_), None) => bail!("{name}: column 'sigma_o' is given without 'sigma_e' (give both or neither)"),
        (None, Some(_)) => bail!("{name}: column 'sigma_e' is given without 'sigma_o' (give both or neither)"),
    };
    let lines = (0..hwp_deg.len()).map(|i| t.lines.get(i).copied().unwrap_or(i as u64 + 1)).collect();
    Ok(Table { hwp_deg, f_o, f_e, sigma, lines })
}

/// A repeated exposure's check, for the JSON (`stokes::repeats::ExposureCheck` with its row).
#[derive(Serialize)]
struct JsonExposure {
    row: usize,
    line: u64,
    hwp_deg: f64,
    f: f64,
    pull: f64,
    outlier: bool,
}

/// The table as the reduction combined it (`stokes::repeats::reduce_repeated`: exposures at
/// the same plate position, rows at theta and theta + 360 deg too, one row each), with every
/// exposure's check; `None` when no position repeats (the table is returned as read).
fn combine_repeats(t: Table, combined: Option<stokes::repeats::Combined>) -> (Table, Option<Vec<JsonExposure>>) {
    let Some(c) = combined else { return (t, None) };
    let checks = c
        .checks
        .iter()
        .map(|k| JsonExposure {
            row: k.index + 1,
            line: t.lines[k.index],
            hwp_deg: t.hwp_deg[k.index],
            f: k.f,
            pull: k.pull,
            outlier: k.outlier,
        })
        .collect();
    let first: Vec<usize> = c.groups.iter().map(|g| g[0]).collect();
    let combined = Table {
        hwp_deg: first.iter().map(|&i| t.hwp_deg[i]).collect(),
        sigma: t.sigma.as_ref().map(|_| (c.sigma_o.clone(), c.sigma_e.clone())),
        f_o: c.f_o,
        f_e: c.f_e,
        lines: first.iter().map(|&i| t.lines[i]).collect(),
    };
    (combined, Some(checks))
}

/// Say which row a library error is about.
fn explain(e: RedError, t: &Table, name: &str) -> anyhow::Error {
    let row = |i: usize| format!("row {} (line {}, hwp_deg = {})", i + 1, t.lines[i], t.hwp_deg[i]);
    match e {
        RedError::TooFewAngles(n) => anyhow!("{name}: need at least 2 HWP angles (data rows), found {n}"),
        RedError::DuplicateAngle { first, second, deg } => anyhow!(
            "{name}: rows {} (line {}) and {} (line {}) are the same HWP position ({deg} deg, equal modulo 360 deg)",
            first + 1,
            t.lines[first],
            second + 1,
            t.lines[second]
        ),
        RedError::NegativeCount { index } => anyhow!("{name}: row {} (line {}): {e}", index + 1, t.lines[index]),
        RedError::NonPositiveFlux { index, total } => {
            anyhow!("{name}: {}: total flux f_o + f_e = {total} is not positive", row(index))
        }
        RedError::Invalid { index, .. } | RedError::NonFinite { index, .. } | RedError::Undetermined { index, .. }
            if index < t.lines.len() =>
        {
            anyhow!("{name}: {}: {e}", row(index))
        }
        e => anyhow!("{name}: {e}"),
    }
}

#[derive(Serialize)]
struct JsonHarmonic {
    k: usize,
    a: f64,
    b: f64,
    sigma_a: f64,
    sigma_b: f64,
    power: f64,
}

/// The JSON output. The first fields are the contract scripts rely on (the reduction's q, u, P,
/// chi and errors); the rest is detail. `schemas/stokes.schema.json` lists every key.
#[derive(Serialize)]
struct JsonOut {
    n_hwp: usize,
    q: f64,
    u: f64,
    p: f64,
    chi_deg: f64,
    sigma_p: f64,
    sigma_chi_deg: Option<f64>,
    a0: f64,
    kappa: Vec<f64>,
    #[serde(rename = "mean_kappa")]
    kappa_mean: Option<f64>,
    fourier: Vec<JsonHarmonic>,
    warnings: Vec<String>,
    input: String,
    estimator: stokes::Estimator,
    kappa_correction: Option<f64>,
    sigma_q: f64,
    sigma_u: f64,
    cov_qu: f64,
    chi_defined: bool,
    snr: f64,
    sigma_p_analytic: f64,
    sigma_chi_analytic_deg: Option<f64>,
    sigma_a0: f64,
    f: Vec<f64>,
    sigma_f: Vec<f64>,
    /// Repeated exposures: every input row's F and its pull about its position's mean
    /// (null when no HWP position repeats).
    exposures: Option<Vec<JsonExposure>>,
}

fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs([a.input.as_path()])?;
    if let Some(p) = &a.plot {
        crate::util::check_output(p)?;
        crate::plot::ImageFormat::of(p)?;
    }
    let name = a.input.display().to_string();
    let mut t = read_table(&a.input, a.angles_in_radians)?;
    if a.angles_in_radians {
        t.hwp_deg.iter_mut().for_each(|r| *r = r.to_degrees());
    } else if let Err(e) = stokes::check_degrees(&t.hwp_deg) {
        bail!("{name}: column 'hwp_deg' holds {e}. Give the angles in degrees, or pass --angles-in-radians");
    }
    // The one composition of instpol.stokes too (stokes::repeats::reduce_repeated): repeats
    // combined, the measurement, kappa, the reduction.
    let theta: Vec<f64> = t.hwp_deg.iter().map(|d| d.to_radians()).collect();
    let sigma = t.sigma.as_ref().map(|(a, b)| (&a[..], &b[..]));
    let kappa = a.kappa.correction()?;
    let (r, applied, combined) = match stokes::repeats::reduce_repeated(&theta, &t.f_o, &t.f_e, sigma, kappa) {
        Ok(r) => (r.reduction, r.kappa_applied, r.combined),
        Err(stokes::repeats::RepeatedError::Combine(e)) => return Err(explain(e, &t, &name)),
        Err(stokes::repeats::RepeatedError::Reduce { error, combined }) => {
            return Err(explain(error, &combine_repeats(t, combined).0, &name))
        }
    };
    let (t, exposures) = combine_repeats(t, combined);
    if let Some(ex) = &exposures {
        let n_pos = t.hwp_deg.len();
        if !a.json {
            eprintln!("note: {name}: {} exposures combined into {n_pos} HWP positions (fluxes summed)", ex.len());
        }
        for e in ex.iter().filter(|e| e.outlier) {
            eprintln!(
                "warning: {name}: row {} (line {}, hwp_deg = {}): its F = {:.5} lies {:.1} sigma from its repeats' mean: an outlier exposure (kept in the sum; remove the row to drop it)",
                e.row, e.line, e.hwp_deg, e.f, e.pull
            );
        }
    }
    let kappa = applied.map(|k| (k, a.kappa.kappa_from_data));
    // kappa = (t - s)/(t + s): beyond 0.2 one beam carries 1.5 times the other, far beyond any
    // working Wollaston prism; a column swap or a flux in the wrong units is more likely.
    if let Some(k) = r.kappa_mean.filter(|k| k.abs() > 0.2) {
        eprintln!(
            "warning: {name}: extreme Wollaston imbalance kappa = {k:.3} (beam ratio {:.2}): check the f_o, f_e columns",
            (1.0 + k) / (1.0 - k)
        );
    }
    // The plot first: a plot that cannot be written fails the command before anything is
    // printed.
    if let Some(path) = &a.plot {
        super::stokes_plot::fourier_png(path, &super::stokes_plot::data::fourier_plot(&r))?;
    }
    if a.json {
        let mut j = json(&r, &name, applied);
        j.exposures = exposures;
        crate::util::print_json(&j)
    } else {
        crate::util::write_stdout(
            super::stokes_text::table(&r, &t.hwp_deg, t.sigma.is_some(), &name, kappa).as_bytes(),
        );
        Ok(())
    }
}

fn json(r: &Reduction, name: &str, kappa: Option<f64>) -> JsonOut {
    JsonOut {
        n_hwp: r.n,
        q: r.qu.q,
        u: r.qu.u,
        p: r.p,
        chi_deg: r.chi_deg(),
        sigma_p: r.sigma_p,
        sigma_chi_deg: r.sigma_chi_deg_reported(),
        a0: r.a0,
        kappa: r.kappa.iter().map(|e| e.kappa).collect(),
        kappa_mean: r.kappa_mean,
        fourier: r
            .fourier
            .iter()
            .map(|h| JsonHarmonic { k: h.k, a: h.a, b: h.b, sigma_a: h.sigma_a, sigma_b: h.sigma_b, power: h.power() })
            .collect(),
        warnings: r.warnings.iter().map(|w| w.to_string()).collect(),
        input: name.to_string(),
        estimator: r.estimator,
        kappa_correction: kappa,
        sigma_q: r.qu.var_q.sqrt(),
        sigma_u: r.qu.var_u.sqrt(),
        cov_qu: r.qu.cov_qu,
        chi_defined: r.chi_defined,
        snr: r.snr,
        sigma_p_analytic: r.sigma_p_analytic,
        sigma_chi_analytic_deg: finite(r.sigma_chi_analytic.to_degrees()),
        sigma_a0: r.sigma_a0,
        f: r.f.clone(),
        sigma_f: r.sigma_f.clone(),
        exposures: None,
    }
}
