//! `instpol correct`: apply a calibration to a catalog or a Stokes map. `fit::correction`'s
//! `request` plans the correction (and corrects a map's bins), its `columns` reads a catalog's
//! rows and corrects them, `skyfield` reads and writes the files; this module parses the
//! options and prints the summary, the notes and the refusals in the command's words.

use anyhow::{anyhow, Context, Result};
use fit::correction::columns::{self, TableColumns, Units};
use fit::correction::correct::Method;
use fit::correction::request::{self, Request};
use fit::Calibration;
use serde::Serialize;
use skyfield::maps::FileKind as Kind;
use skyfield::table::Format;
use std::path::PathBuf;
use stokes::stats::Estimator;

mod words;

// `instpol correct`'s options; the long help (what is read, written and reported, with the
// telescope's and the Mueller field's cases) is the text file beside this one (users read it).
#[derive(clap::Args)]
#[command(long_about = include_str!("help.txt").trim_end())]
pub struct Args {
    /// Calibration file (instpol calibration FITS: `instpol calibrate`, `instpol import-map`,
    /// `instpol fit-standards --output`, `instpol calibrate-mueller --out CAL.fits` or
    /// `instpol efficiency --output CAL.fits`).
    #[arg(long, value_name = "CAL.fits")]
    pub cal: PathBuf,
    /// Catalog (CSV or FITS table) or Stokes map (FITS) to correct.
    #[arg(long = "in", value_name = "CATALOG")]
    pub input: PathBuf,
    /// Output file: a catalog in the format of its extension (.csv, .fits, .ecsv, .vot), or a
    /// Stokes map (FITS).
    #[arg(long, value_name = "OUT")]
    pub out: PathBuf,
    /// Units of the catalog's x, y: arcmin from the detector centre, or 0-based detector
    /// pixels of the calibration's pixel grid. Default: the units the table declares (ECSV,
    /// FITS, VOTable: pix, arcmin, arcsec, deg), else arcmin.
    #[arg(long, value_enum)]
    pub coords: Option<Coords>,
    /// Inversion: exact (M_I inverted, eq:instpol) or first-order (eq:approx).
    #[arg(long, value_enum, default_value = "exact")]
    pub method: MethodArg,
    /// Estimator of the bias-corrected P0 column: naive, as, wk, ml, mp2, mas, mb, pr06
    /// (see `stokes::stats`; mas, Plaszczynski et al. 2014, handles unequal sigma_q, sigma_u
    /// and never returns 0).
    #[arg(long, default_value = "mas", value_name = "NAME")]
    pub estimator: String,
    /// Correct positions outside the calibrated field (flagged, inflated errors) instead of
    /// failing.
    #[arg(long)]
    pub allow_extrapolation: bool,
    /// F of the inflation rule outside the field: (F p)^2 added to each component's
    /// calibration variance (fraction of the instrumental polarization).
    #[arg(long, default_value_t = 0.5, value_name = "F")]
    pub extrapolation_error: f64,
    /// Stokes maps: correct even when the map's instrument or filter differs from the
    /// calibration's (normally an error).
    #[arg(long)]
    pub allow_mismatch: bool,
    /// FITS catalogs: name of the table HDU (default: the first binary table).
    #[arg(long, value_name = "NAME")]
    pub hdu: Option<String>,
    /// The telescope model's band (calibrations with a TELESCOPE model; default: the field
    /// calibration's filter, or the model's only band).
    #[arg(long, value_name = "BAND")]
    pub band: Option<String>,
    /// With a telescope model: the parallactic angle (deg) over the exposures, START or
    /// START,END, for a Stokes map or a catalog without a parang_deg column.
    #[arg(long, value_name = "START[,END]", allow_hyphen_values = true)]
    pub parang: Option<String>,
    /// With a telescope model fitted with rotator angles: the exposures' rotator / adapter
    /// angle (deg), for a Stokes map or a catalog without a rotator_deg column.
    #[arg(long, value_name = "DEG", allow_hyphen_values = true)]
    pub rotator: Option<f64>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Coords {
    Pixel,
    Arcmin,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum MethodArg {
    Exact,
    FirstOrder,
}

/// The JSON summary: the paths and options, and what the correction did (`columns::Report`).
#[derive(Serialize)]
struct Summary {
    input: PathBuf,
    output: PathBuf,
    method: MethodArg,
    coords: Option<Coords>,
    #[serde(flatten)]
    report: columns::Report,
    /// What the output is, as it records it (a table written by other software: none).
    #[serde(skip_serializing_if = "Option::is_none")]
    product: Option<skyfield::provenance::Product>,
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs([a.cal.as_path(), a.input.as_path()])?;
    crate::util::check_output(&a.out)?;
    let est: Estimator = a.estimator.parse().map_err(|e| anyhow!("--estimator: {e}"))?;
    request::check_extrapolation_error(a.extrapolation_error)
        .map_err(|f| anyhow!("--extrapolation-error {f} must be a non-negative number"))?;
    let loaded = fit::files::calibration::load(&a.cal)
        .with_context(|| format!("cannot load calibration {}", a.cal.display()))?;
    let parang = a.parang.as_deref().map(crate::util::parse_parang).transpose()?;
    let rotator = a.rotator.map(crate::util::parse_rotator).transpose()?;
    let method = if a.method == MethodArg::Exact { Method::Exact } else { Method::FirstOrder };
    let base = Request::new(method, a.allow_extrapolation, a.extrapolation_error);
    let request = Request { band: a.band.as_deref(), parang, rotator, allow_mismatch: a.allow_mismatch, ..base };
    request::check_options(&loaded, &request).map_err(|e| words::rows_error(&a.cal, &a.input, None, e))?;
    let kind = skyfield::maps::file_kind(&a.input)?;
    if kind == Kind::StokesMap {
        return run_map(&a, &loaded, &request);
    }
    run_table(&a, &loaded, &request, kind, est)
}

/// The first line of the summary of a correction by a field calibration.
fn field_line(a: &Args, s: &columns::Report, cal: &Calibration) -> String {
    format!(
        "corrected {} {} with {} ({} {}, HWP zero angle {:+.2} deg)",
        s.rows,
        words::what_counted(s),
        a.cal.display(),
        cal.instrument,
        cal.filter,
        cal.hwp_chi_offset_deg
    )
}

/// Correct a catalog's rows with any calibration (`fit::correction::request`): read the table and its angles,
/// correct every row in parallel, write the table with the corrected columns and report.
fn run_table(
    a: &Args,
    loaded: &fit::files::calibration::CalibrationFile,
    base: &Request<'_>,
    kind: Kind,
    est: Estimator,
) -> Result<()> {
    let out_format = Some(Format::from_path(&a.out)?);
    let mut table = columns::read_catalog(&a.input, kind == Kind::FitsTable, a.hdu.as_deref())?;
    let angles = columns::TableAngles::read(&table, &a.input, loaded)?;
    if angles.setup.is_none() {
        eprintln!(
            "warning: {} does not say which instrument and filter it was measured with (no INSTRUME and FILTER among its keywords: not a table of instpol catalog), so it cannot be checked against {}: make sure they are the calibration's",
            a.input.display(),
            a.cal.display()
        );
    }
    let n = table.n_rows();
    let plan = request::plan_rows(loaded, &angles.request(*base), n)
        .map_err(|e| words::rows_error(&a.cal, &a.input, Some(&table), e))?;
    words::print_notes(&a.cal, &a.input, a.parang.as_deref(), &plan.notes);
    let mut cols = TableColumns::read(&table, &a.input)?;
    let given = a.coords.map(|c| if c == Coords::Pixel { Units::Pixel } else { Units::Arcmin });
    let units = cols.place(given, loaded).map_err(|e| match e {
        columns::PlaceError::Conflict(m) => anyhow!("{}: {m}", a.input.display()),
        columns::PlaceError::NoPixelGrid => {
            let (input, row) = (a.input.display(), table.row_label(0));
            anyhow!(
                "{input} {row}: the calibration has no pixel grid: give the catalog positions in arcmin (--coords arcmin)"
            )
        }
    })?;
    // The root-finding estimators take ~1 us a row: show progress on big catalogs.
    let pb = if n >= 500_000 { indicatif::ProgressBar::new(n as u64) } else { indicatif::ProgressBar::hidden() };
    let out = columns::correct_columns(&cols.inputs(angles.frame), Some(est), &|k| pb.inc(k as u64), |i, m| {
        plan.correct(i, m)
    })
    .map_err(|(i, e)| anyhow!("{} {}: {e}", a.input.display(), table.row_label(i)));
    pb.finish_and_clear();
    let out = out?;
    let text = if kind == Kind::TextTable { "catalog (text table)" } else { "catalog (FITS table)" };
    let report = columns::Report::of_rows(loaded, text, &out, est, &plan);
    let rows = out.extrapolated.len();
    crate::util::check_output(&a.out)?;
    table.product = plan.recorded(table.product.take());
    let product = table.product.as_ref().map(|p| p.with_run_inputs());
    if kind == Kind::FitsTable && out_format == Some(Format::Fits) {
        let keys: Vec<(String, String)> = table
            .product
            .as_ref()
            .map(|p| p.pairs().into_iter().filter(|(k, _)| k == "MISMATCH").collect())
            .unwrap_or_default();
        skyfield::table::append_fits_columns(&a.input, a.hdu.as_deref(), &out.into_table_columns(), &keys, &a.out)?;
    } else {
        table.columns.extend(out.into_table_columns());
        table.write(&a.out)?;
    }
    let telescope = plan.telescope.as_ref().map(|t| {
        let how = match t.exposures {
            0 => "the parallactic angle per row".to_string(),
            k => format!("exposure by exposure ({k}, as the catalog recorded them)"),
        };
        format!(
            "corrected {rows} rows with {} ({} model, band {}{}), {how}",
            a.cal.display(),
            t.fit.model.name(),
            t.band,
            first(loaded)
        )
    });
    finish(
        a,
        Summary {
            input: a.input.clone(),
            output: a.out.clone(),
            method: a.method,
            coords: Some(if units == Units::Pixel { Coords::Pixel } else { Coords::Arcmin }),
            report,
            product,
        },
        loaded,
        telescope,
    )
}

/// How a telescope correction's line says whether the field was undone first.
fn first(loaded: &fit::files::calibration::CalibrationFile) -> &'static str {
    [", no field model", ", field model first"][loaded.field.is_some() as usize]
}

/// Print the summary (`telescope`: the model's name and the line that says what was done, when a
/// telescope model was applied), after the warning for extrapolated positions.
fn finish(
    a: &Args,
    s: Summary,
    loaded: &fit::files::calibration::CalibrationFile,
    telescope: Option<String>,
) -> Result<()> {
    let r = &s.report;
    if let Some(c) = &loaded.response {
        let line = format!(
            "corrected {} {} with the constant response of {} ({} {}: efficiency {:.4}, offset {:+.2} deg, (q0, u0) = ({:.5}, {:.5})), exact inverse",
            r.rows,
            words::what_counted(r),
            a.cal.display(),
            c.instrument,
            c.filter,
            c.response.efficiency,
            c.response.offset_deg,
            c.response.q0,
            c.response.u0
        );
        return report(a, &s, &line, "");
    }
    match (&loaded.mueller, telescope, &loaded.field) {
        (Some(m), _, _) => {
            words::warn_extrapolated(r, "fitted Mueller field");
            report(a, &s, &(mueller_line(a, r, m) + &words::chain(loaded)), " (unpolarized light)")
        }
        (None, Some(line), _) => {
            words::warn_extrapolated(r, "calibrated field");
            report(a, &s, &line, "")
        }
        (None, None, Some(cal)) => {
            words::warn_extrapolated(r, "calibrated field");
            report(a, &s, &(field_line(a, r, cal) + &words::chain(loaded)), "")
        }
        (None, None, None) => unreachable!("the loader refuses a file without a model"),
    }
}

/// The first line of the summary of a correction by a Mueller field.
fn mueller_line(a: &Args, s: &columns::Report, cal: &fit::mueller_field::cal::MuellerCal) -> String {
    format!(
        "corrected {} {} with the Mueller field of {} ({} {}, {} model: {}), exact inverse",
        s.rows,
        words::what_counted(s),
        a.cal.display(),
        cal.instrument,
        cal.filter,
        cal.field.kind.model_name(),
        cal.field.kind.free_words().join(", ")
    )
}

// The column a catalog carries when its q, u already have the instrument's HWP zero angle
// applied (`instpol catalog` writes it): they are then in the sky's frame.

/// The summary on stdout: the JSON object (--json), or `line`, the medians of the
/// instrumental p removed (`of`: what it is the p of, "" or " (unpolarized light)") and of
/// the corrected P0, and the output written.
fn report(a: &Args, s: &Summary, line: &str, of: &str) -> Result<()> {
    if a.json {
        return crate::util::print_json(s);
    }
    outln!("{line}");
    if let (Some(p0), Some(pi)) = (s.report.median_p0, s.report.median_p_inst) {
        outln!("median instrumental p{of} removed: {:.3} %, median corrected P0: {:.3} %", 100.0 * pi, 100.0 * p0);
    }
    outln!("wrote {}", a.out.display());
    Ok(())
}

/// Correct a Stokes map with any calibration (`request::plan_map`): every valid bin at
/// its centre, written with the correction's record, and report.
fn run_map(a: &Args, loaded: &fit::files::calibration::CalibrationFile, request: &Request<'_>) -> Result<()> {
    let map = skyfield::StokesMap::read_uncorrected(&a.input)
        .with_context(|| format!("cannot read Stokes map {}", a.input.display()))?;
    let plan = request::plan_map(loaded, request, &map).map_err(|e| words::rows_error(&a.cal, &a.input, None, e))?;
    words::print_notes(&a.cal, &a.input, a.parang.as_deref(), &plan.notes);
    let name = a.cal.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
    let (c, stamp) = plan.correct(&map, &name).map_err(|e| words::map_error(e, &a.input))?;
    crate::util::check_output(&a.out)?;
    c.map.write_corrected_fits(&a.out, &stamp).with_context(|| format!("cannot write {}", a.out.display()))?;
    let (n, filter) = ((c.n_bins, c.n_extrapolated, 0), map.filter.clone());
    let used = plan.telescope.as_ref().map(|t| (t.fit.model.name(), t.band.clone(), plan.exposures));
    let zero = (filter, stamp.hwp_chi_offset_deg);
    let report = columns::Report::new(loaded, "Stokes map", n, a.estimator.clone(), zero, c.p0, c.p_inst, used);
    // A Mueller field's summary names no telescope model.
    let telescope = plan.telescope.as_ref().filter(|_| loaded.mueller.is_none()).map(|t| {
        let (input, cal, track) = (a.input.display(), a.cal.display(), t.track);
        let line = format!(
            "corrected {} bins of {input} with {cal} ({} model, band {}{}), parallactic angle {:.2} to {:.2} deg",
            n.0,
            t.fit.model.name(),
            t.band,
            first(loaded),
            track.start.to_degrees(),
            track.end.to_degrees()
        );
        line
    });
    let product = c.map.product.as_ref().map(|p| p.with_run_inputs());
    let s = Summary { input: a.input.clone(), output: a.out.clone(), method: a.method, coords: None, report, product };
    finish(a, s, loaded, telescope)
}
