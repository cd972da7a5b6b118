//! `instpol correct`: apply a calibration to a catalog or a Stokes map (`fit::correct` does the
//! work; this module reads and writes tables).

use anyhow::{anyhow, bail, Context, Result};
use fit::correct::{CorrectOptions, Corrected, Corrector, Measurement, Method};
use fit::Calibration;
use fitsio::tables::{ColumnDataType, ColumnDescription};
use fitsio::FitsFile;
use serde::Serialize;
use std::path::{Path, PathBuf};
use stokes::stats::{Estimator, PolMeasurement};

/// Remove the instrumental polarization from measured Stokes parameters with a calibration
/// file: exact inversion of the instrument's Mueller matrix M_I (eq:instpol) or the
/// first-order form eq:approx, the HWP chromatic zero angle of the calibration's filter
/// applied first, and the errors of the measurement and of the calibration propagated.
///
/// Input (--in), detected by content:
///
///   catalog, CSV (header row; lines starting with # are comments) or a FITS binary table
///   (the first table HDU, or --hdu NAME), with columns (names case-insensitive):
///     x, y               position (--coords: arcmin from the detector centre, or 0-based
///                        pixels on the calibration's detector grid)
///     q, u               measured Q/I, U/I (fractions, not percent)
///     sigma_q, sigma_u   their 1-sigma errors
///     cov_qu             (optional) their covariance
///   Every input column is kept; added are q0, u0, sigma_q0, sigma_u0, cov_qu0 (corrected
///   Q0/I0, U0/I0 and covariance), p0, sigma_p0 (fraction, not bias-corrected), chi0_deg,
///   sigma_chi0_deg ([0, 180) deg), p0_<estimator> (bias-corrected P0, see --estimator),
///   q_inst, u_inst (the instrumental polarization removed) and extrapolated (0/1).
///   The output has the input's format (CSV or FITS).
///
///   Stokes map, a FITS file written by `instpol reduce` (primary keyword MAPVERS): every
///   valid bin is corrected at its centre and a Stokes map of the same layout is written,
///   with Q, U, P, CHI corrected and SIGMA_Q/U, COV_QU, SIGQ_PHOT/SIGU_PHOT propagated.
///
/// Positions outside the calibrated field are an error naming the row or bin, unless
/// --allow-extrapolation: then they are corrected, flagged, and the calibration's variance
/// is inflated by (F p)^2 per component (F = --extrapolation-error, default 0.5).
///
/// Output files are written atomically (a temporary file renamed when complete). The summary
/// goes to stdout (--json for scripts: input, output, kind, rows, extrapolated, method,
/// estimator, coords, filter, hwp_chi_offset_deg, median_p0, median_p_inst).
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// Calibration file (instpol calibration FITS: `instpol calibrate` or `instpol import-map`).
    #[arg(long, value_name = "CAL.fits")]
    pub cal: PathBuf,
    /// Catalog (CSV or FITS table) or Stokes map (FITS) to correct.
    #[arg(long = "in", value_name = "CATALOG")]
    pub input: PathBuf,
    /// Output file (same format as the input).
    #[arg(long, value_name = "OUT")]
    pub out: PathBuf,
    /// Units of the catalog's x, y: arcmin from the detector centre, or 0-based detector
    /// pixels of the calibration's pixel grid.
    #[arg(long, value_enum, default_value = "arcmin")]
    pub coords: Coords,
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

#[derive(Serialize)]
struct Summary {
    input: PathBuf,
    output: PathBuf,
    kind: &'static str,
    #[serde(rename = "n_rows")]
    rows: usize,
    #[serde(rename = "n_extrapolated")]
    extrapolated: usize,
    method: MethodArg,
    estimator: String,
    coords: Option<Coords>,
    filter: String,
    hwp_chi_offset_deg: f64,
    median_p0: Option<f64>,
    median_p_inst: Option<f64>,
}

/// Names of the columns `instpol correct` adds, in order (the estimator column is
/// `p0_<name>`, inserted after `sigma_chi0_deg`).
const ADDED: [&str; 9] =
    ["q0", "u0", "sigma_q0", "sigma_u0", "cov_qu0", "p0", "sigma_p0", "chi0_deg", "sigma_chi0_deg"];

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs([a.cal.as_path(), a.input.as_path()])?;
    crate::util::check_output(&a.out)?;
    let cal = Calibration::load(&a.cal).with_context(|| format!("cannot load calibration {}", a.cal.display()))?;
    let est: Estimator = a.estimator.parse().map_err(|e| anyhow!("--estimator: {e}"))?;
    if !(a.extrapolation_error.is_finite() && a.extrapolation_error >= 0.0) {
        bail!("--extrapolation-error {} must be a non-negative number", a.extrapolation_error);
    }
    let opts = options(&cal, &a);
    let kind = detect(&a.input)?;
    let summary = match kind {
        Kind::Map => correct_map(&cal, opts, &a)?,
        Kind::Csv | Kind::FitsTable => {
            let table = match kind {
                Kind::Csv => read_csv(&a.input)?,
                _ => read_fits_table(&a.input, a.hdu.as_deref())?,
            };
            let meas = measurements(&table, &cal, a.coords, &a.input)?;
            let cor = Corrector::new(&cal, opts);
            let mut out = vec![Corrected::default(); meas.len()];
            let n_extra = correct_rows(&cor, &meas, &mut out, &a.input)?;
            let p0est = estimates(&out, est);
            match kind {
                Kind::Csv => write_csv(&table, &out, &p0est, est, &a.out)?,
                _ => write_fits_table(&a.input, a.hdu.as_deref(), &out, &p0est, est, &a.out)?,
            }
            Summary {
                input: a.input.clone(),
                output: a.out.clone(),
                kind: if kind == Kind::Csv { "catalog (CSV)" } else { "catalog (FITS table)" },
                rows: out.len(),
                extrapolated: n_extra,
                method: a.method,
                estimator: est.name().into(),
                coords: Some(a.coords),
                filter: cal.filter.clone(),
                hwp_chi_offset_deg: cal.hwp_chi_offset_deg,
                median_p0: median(out.iter().map(|r| r.p0)),
                median_p_inst: median(out.iter().map(|r| r.inst.q.hypot(r.inst.u))),
            }
        }
    };
    if summary.extrapolated > 0 {
        eprintln!(
            "warning: {} of {} positions lie outside the calibrated field; corrected by extrapolation with inflated errors (flagged)",
            summary.extrapolated, summary.rows
        );
    }
    if a.json {
        crate::util::print_json(&summary)
    } else {
        println!(
            "corrected {} {} with {} ({} {}, HWP zero angle {:+.2} deg)",
            summary.rows,
            if kind == Kind::Map { "bins" } else { "rows" },
            a.cal.display(),
            cal.instrument,
            cal.filter,
            cal.hwp_chi_offset_deg
        );
        if let (Some(p0), Some(pi)) = (summary.median_p0, summary.median_p_inst) {
            println!("median instrumental p removed: {:.3} %, median corrected P0: {:.3} %", 100.0 * pi, 100.0 * p0);
        }
        println!("wrote {}", a.out.display());
        Ok(())
    }
}

/// The correction options for a calibration and the command's flags.
pub fn options(cal: &Calibration, a: &Args) -> CorrectOptions {
    CorrectOptions {
        method: match a.method {
            MethodArg::Exact => Method::Exact,
            MethodArg::FirstOrder => Method::FirstOrder,
        },
        allow_extrapolation: a.allow_extrapolation,
        extrapolation_rel_error: a.extrapolation_error,
        chi_offset: cal.hwp_chi_offset_deg.to_radians(),
    }
}

fn median(v: impl Iterator<Item = f64>) -> Option<f64> {
    let mut v: Vec<f64> = v.filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) })
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Kind {
    Csv,
    FitsTable,
    Map,
}

/// FITS by its first bytes ("SIMPLE  ="), Stokes map by the MAPVERS keyword; else CSV.
fn detect(path: &Path) -> Result<Kind> {
    use std::io::Read;
    let mut head = [0u8; 9];
    let mut f = std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let n = f.read(&mut head).with_context(|| format!("cannot read {}", path.display()))?;
    if n == 9 && &head == b"SIMPLE  =" {
        let mut ff = FitsFile::open(path).map_err(|e| anyhow!("{}: cannot open as FITS: {e}", path.display()))?;
        let ph = ff.primary_hdu().map_err(|e| anyhow!("{}: {e}", path.display()))?;
        if ph.read_key::<i64>(&mut ff, "MAPVERS").is_ok() {
            return Ok(Kind::Map);
        }
        return Ok(Kind::FitsTable);
    }
    Ok(Kind::Csv)
}

/// A catalog read into memory: the needed columns as numbers and, for CSV, every field as text.
struct Table {
    headers: Vec<String>,
    /// CSV only: all fields of each row, as read.
    records: Vec<csv::StringRecord>,
    /// Row labels for errors ("line 12", "row 3").
    labels: Vec<String>,
    x: Vec<f64>,
    y: Vec<f64>,
    q: Vec<f64>,
    u: Vec<f64>,
    sq: Vec<f64>,
    su: Vec<f64>,
    cov: Option<Vec<f64>>,
}

fn find_col(headers: &[String], name: &str, path: &Path) -> Result<usize> {
    headers.iter().position(|h| h.trim().eq_ignore_ascii_case(name)).ok_or_else(|| {
        anyhow!(
            "{}: no column '{name}' (columns: {}); need x, y, q, u, sigma_q, sigma_u",
            path.display(),
            headers.join(", ")
        )
    })
}

fn check_no_clash(headers: &[String], path: &Path) -> Result<()> {
    for h in headers {
        let l = h.trim().to_ascii_lowercase();
        if ADDED.contains(&l.as_str()) || l.starts_with("p0_") || l == "q_inst" || l == "u_inst" || l == "extrapolated"
        {
            bail!("{}: column '{h}' would be overwritten by the corrected columns; rename it", path.display());
        }
    }
    Ok(())
}

fn read_csv(path: &Path) -> Result<Table> {
    let mut rdr = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .trim(csv::Trim::All)
        .from_path(path)
        .with_context(|| format!("cannot read catalog {}", path.display()))?;
    let headers: Vec<String> = rdr
        .headers()
        .with_context(|| format!("{}: cannot read the header row", path.display()))?
        .iter()
        .map(String::from)
        .collect();
    check_no_clash(&headers, path)?;
    let idx: Vec<usize> = ["x", "y", "q", "u", "sigma_q", "sigma_u"]
        .iter()
        .map(|n| find_col(&headers, n, path))
        .collect::<Result<_>>()?;
    let icov = headers.iter().position(|h| h.trim().eq_ignore_ascii_case("cov_qu"));
    let mut t = Table {
        headers: headers.clone(),
        records: Vec::new(),
        labels: Vec::new(),
        x: vec![],
        y: vec![],
        q: vec![],
        u: vec![],
        sq: vec![],
        su: vec![],
        cov: icov.map(|_| vec![]),
    };
    for rec in rdr.records() {
        let rec = rec.with_context(|| format!("{}: malformed CSV", path.display()))?;
        let line = rec.position().map(|p| p.line()).unwrap_or(0);
        let num = |i: usize| -> Result<f64> {
            let s = rec.get(i).unwrap_or("");
            s.parse::<f64>()
                .map_err(|_| anyhow!("{} line {line}: column '{}' = '{s}' is not a number", path.display(), headers[i]))
        };
        t.x.push(num(idx[0])?);
        t.y.push(num(idx[1])?);
        t.q.push(num(idx[2])?);
        t.u.push(num(idx[3])?);
        t.sq.push(num(idx[4])?);
        t.su.push(num(idx[5])?);
        if let (Some(i), Some(c)) = (icov, t.cov.as_mut()) {
            c.push(num(i)?);
        }
        t.labels.push(format!("line {line}"));
        t.records.push(rec);
    }
    if t.x.is_empty() {
        bail!("{}: the catalog has no data rows", path.display());
    }
    Ok(t)
}

/// The table HDU of a FITS catalog: `name`, or the first binary/ASCII table.
fn table_hdu(f: &mut FitsFile, name: Option<&str>, path: &Path) -> Result<(fitsio::hdu::FitsHdu, Vec<String>, usize)> {
    use fitsio::hdu::HduInfo;
    let hdu = match name {
        Some(n) => f.hdu(n).map_err(|_| anyhow!("{}: no HDU named '{n}'", path.display()))?,
        None => {
            let n_hdu = f.iter().count();
            let mut found = None;
            for i in 0..n_hdu {
                let h = f.hdu(i).map_err(|e| anyhow!("{}: HDU {i}: {e}", path.display()))?;
                if matches!(h.info, HduInfo::TableInfo { .. }) {
                    found = Some(h);
                    break;
                }
            }
            found.ok_or_else(|| anyhow!("{}: no table HDU (a FITS catalog needs a binary table)", path.display()))?
        }
    };
    match &hdu.info {
        HduInfo::TableInfo { column_descriptions, num_rows } => {
            let names = column_descriptions.iter().map(|c| c.name.clone()).collect();
            let n = *num_rows;
            Ok((hdu, names, n))
        }
        _ => bail!("{}: HDU '{}' is not a table", path.display(), name.unwrap_or("?")),
    }
}

fn read_fits_table(path: &Path, name: Option<&str>) -> Result<Table> {
    let mut f = FitsFile::open(path).map_err(|e| anyhow!("{}: cannot open as FITS: {e}", path.display()))?;
    let (hdu, headers, n) = table_hdu(&mut f, name, path)?;
    check_no_clash(&headers, path)?;
    if n == 0 {
        bail!("{}: the catalog table has no rows", path.display());
    }
    let mut col = |c: &str| -> Result<Vec<f64>> {
        let i = find_col(&headers, c, path)?;
        hdu.read_col::<f64>(&mut f, &headers[i])
            .map_err(|e| anyhow!("{}: column '{}': {e}", path.display(), headers[i]))
    };
    let (x, y, q, u, sq, su) = (col("x")?, col("y")?, col("q")?, col("u")?, col("sigma_q")?, col("sigma_u")?);
    let cov = if headers.iter().any(|h| h.eq_ignore_ascii_case("cov_qu")) { Some(col("cov_qu")?) } else { None };
    Ok(Table {
        headers,
        records: vec![],
        labels: (1..=n).map(|r| format!("row {r}")).collect(),
        x,
        y,
        q,
        u,
        sq,
        su,
        cov,
    })
}

/// Catalog positions in arcmin from the detector centre.
fn measurements(t: &Table, cal: &Calibration, coords: Coords, path: &Path) -> Result<Vec<Measurement>> {
    let to_arcmin = |x: f64, y: f64| -> Result<(f64, f64)> {
        match coords {
            Coords::Arcmin => Ok((x, y)),
            Coords::Pixel => {
                let g = cal.pixel.ok_or_else(|| {
                    anyhow!("the calibration has no pixel grid: give the catalog positions in arcmin (--coords arcmin)")
                })?;
                Ok(g.to_arcmin(x, y))
            }
        }
    };
    (0..t.x.len())
        .map(|i| {
            let (x, y) = to_arcmin(t.x[i], t.y[i]).with_context(|| format!("{} {}", path.display(), t.labels[i]))?;
            Ok(Measurement {
                x,
                y,
                q: t.q[i],
                u: t.u[i],
                sigma_q: t.sq[i],
                sigma_u: t.su[i],
                cov_qu: t.cov.as_ref().map(|c| c[i]).unwrap_or(0.0),
            })
        })
        .collect()
}

/// Correct all rows (in parallel), naming the file and row of the first failure.
fn correct_rows(
    cor: &Corrector<'_, Calibration>,
    m: &[Measurement],
    out: &mut [Corrected],
    path: &Path,
) -> Result<usize> {
    cor.par_correct_batch(m, out).map_err(|e| match e {
        fit::correct::Error::Row { row, source } => anyhow!("{} data row {}: {source}", path.display(), row + 1),
        e => anyhow!("{}: {e}", path.display()),
    })
}

/// The bias-corrected P0 of each row with the chosen estimator (NaN when the errors are not
/// usable, e.g. zero).
fn estimates(out: &[Corrected], est: Estimator) -> Vec<f64> {
    use indicatif::{ParallelProgressIterator, ProgressBar};
    use rayon::prelude::*;
    // The root-finding estimators take ~1 us a row: show progress on big catalogs.
    let pb = if out.len() >= 500_000 { ProgressBar::new(out.len() as u64) } else { ProgressBar::hidden() };
    let v = out
        .par_iter()
        .progress_with(pb.clone())
        .map(|r| match PolMeasurement::new(r.q0, r.u0, r.var_q0.sqrt(), r.var_u0.sqrt()) {
            Ok(m) => est.estimate(&m).value,
            Err(_) => f64::NAN,
        })
        .collect();
    pb.finish_and_clear();
    v
}

fn added_values(r: &Corrected, p0e: f64) -> [f64; 12] {
    [
        r.q0,
        r.u0,
        r.var_q0.sqrt(),
        r.var_u0.sqrt(),
        r.cov_qu0,
        r.p0,
        r.sigma_p0,
        r.chi0.to_degrees(),
        r.sigma_chi0.to_degrees(),
        p0e,
        r.inst.q,
        r.inst.u,
    ]
}

fn added_names(est: Estimator) -> Vec<String> {
    let mut v: Vec<String> = ADDED.iter().map(|s| s.to_string()).collect();
    v.push(format!("p0_{}", est.name()));
    v.push("q_inst".into());
    v.push("u_inst".into());
    v
}

fn write_csv(t: &Table, out: &[Corrected], p0e: &[f64], est: Estimator, path: &Path) -> Result<()> {
    let mut w = csv::Writer::from_writer(Vec::new());
    let mut h: Vec<String> = t.headers.clone();
    h.extend(added_names(est));
    h.push("extrapolated".into());
    w.write_record(&h)?;
    for ((rec, r), e) in t.records.iter().zip(out).zip(p0e) {
        let mut row: Vec<String> = rec.iter().map(String::from).collect();
        row.extend(added_values(r, *e).iter().map(|v| if v.is_finite() { format!("{v}") } else { String::new() }));
        row.push((r.extrapolated as u8).to_string());
        w.write_record(&row)?;
    }
    let bytes = w.into_inner().map_err(|e| anyhow!("cannot format the CSV output: {e}"))?;
    crate::util::write_atomic(path, &bytes)
}

/// Copy the input FITS file byte for byte to a temporary file beside the output, append the
/// corrected columns to its catalog table, and rename it over the output: every HDU, header
/// keyword and column of the input is kept.
fn write_fits_table(
    input: &Path,
    name: Option<&str>,
    out: &[Corrected],
    p0e: &[f64],
    est: Estimator,
    path: &Path,
) -> Result<()> {
    let names = added_names(est);
    let werr = |m: String| anyhow!("cannot write {}: {m}", path.display());
    crate::util::write_via_temp(path, ".fits.tmp", |tmp| {
        let dir = tmp.parent().unwrap_or(Path::new("."));
        std::fs::copy(input, tmp).with_context(|| format!("cannot copy {} to {}", input.display(), dir.display()))?;
        let mut f = FitsFile::edit(tmp).map_err(|e| werr(e.to_string()))?;
        let (mut t, _, _) = table_hdu(&mut f, name, input)?;
        for (k, n) in names.iter().enumerate() {
            let col: Vec<f64> = out.iter().zip(p0e).map(|(r, e)| added_values(r, *e)[k]).collect();
            let d = ColumnDescription::new(n)
                .with_type(ColumnDataType::Double)
                .create()
                .map_err(|e| werr(e.to_string()))?;
            t = t.append_column(&mut f, &d).map_err(|e| werr(format!("adding column {n}: {e}")))?;
            t.write_col(&mut f, n, &col).map_err(|e| werr(format!("writing column {n}: {e}")))?;
        }
        let flags: Vec<i32> = out.iter().map(|r| r.extrapolated as i32).collect();
        let d = ColumnDescription::new("extrapolated")
            .with_type(ColumnDataType::Int)
            .create()
            .map_err(|e| werr(e.to_string()))?;
        t = t.append_column(&mut f, &d).map_err(|e| werr(format!("adding column extrapolated: {e}")))?;
        t.write_col(&mut f, "extrapolated", &flags).map_err(|e| werr(format!("writing column extrapolated: {e}")))?;
        // Closed explicitly: CFITSIO flushes its buffers here and a full disk must fail the run.
        skyfield::durable::close_fits(f).map_err(werr)
    })
}

/// A calibration applies to one instrument and filter: refuse a map of another (names
/// compared case-insensitively, filters through the instrument's aliases when it is known;
/// "unknown" or empty names are not checked).
fn check_same_setup(inst: &str, filter: &str, cal: &Calibration, input: &Path, calp: &Path, allow: bool) -> Result<()> {
    if !fit::setup::matches_calibration(inst, filter, cal) && !allow {
        bail!(
            "{} is a {} {} map but {} calibrates {} {}: use the calibration of the map's instrument and filter (or --allow-mismatch)",
            input.display(),
            inst,
            filter,
            calp.display(),
            cal.instrument,
            cal.filter
        );
    }
    Ok(())
}

/// Correct a Stokes map bin by bin at the bin centres.
fn correct_map(cal: &Calibration, opts: CorrectOptions, a: &Args) -> Result<Summary> {
    let map = skyfield::StokesMap::read_fits(&a.input)
        .with_context(|| format!("cannot read Stokes map {}", a.input.display()))?;
    check_same_setup(&map.instrument, &map.filter, cal, &a.input, &a.cal, a.allow_mismatch)?;
    let c = fit::correct::correct_map(cal, &map, opts).map_err(|e| match e {
        fit::correct::MapError::NoValidBins => anyhow!("{}: {e}", a.input.display()),
        e => anyhow!("{} {e}", a.input.display()),
    })?;
    let m = c.map;
    // Written beside the output, stamped with the correction's provenance, then renamed.
    crate::util::write_via_temp(&a.out, ".fits.tmp", |tmp| {
        m.write_fits(tmp).with_context(|| format!("cannot write {}", a.out.display()))?;
        let werr = |e: fitsio::errors::Error| anyhow!("cannot write {}: {e}", a.out.display());
        let mut f = FitsFile::edit(tmp).map_err(werr)?;
        let ph = f.primary_hdu().map_err(werr)?;
        let name = a.cal.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
        ph.write_key(&mut f, "INSTCORR", (name.as_str(), "instrumental polarization removed with")).map_err(werr)?;
        let meth = match a.method {
            MethodArg::Exact => "exact M_I inverse (eq:instpol)",
            MethodArg::FirstOrder => "first order (eq:approx)",
        };
        ph.write_key(&mut f, "CORRMETH", meth).map_err(werr)?;
        ph.write_key(&mut f, "CORRHWP", (cal.hwp_chi_offset_deg, "HWP zero angle added to chi [deg]")).map_err(werr)?;
        skyfield::durable::close_fits(f).map_err(|m| anyhow!("cannot write {}: {m}", a.out.display()))
    })?;
    Ok(Summary {
        input: a.input.clone(),
        output: a.out.clone(),
        kind: "Stokes map",
        rows: c.n_bins,
        extrapolated: c.n_extrapolated,
        method: a.method,
        estimator: a.estimator.clone(),
        coords: None,
        filter: cal.filter.clone(),
        hwp_chi_offset_deg: cal.hwp_chi_offset_deg,
        median_p0: median(c.p0.into_iter()),
        median_p_inst: median(c.p_inst.into_iter()),
    })
}
