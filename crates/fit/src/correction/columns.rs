//! A table's rows corrected column by column: the one reading of the input columns (positions
//! in arcmin, or in pixels of the calibration's grid), the output columns in their one order
//! ([`crate::correction::correct::output_columns`]), filled in parallel. `instpol correct` (a catalog's
//! columns) and the Python `Calibration.correct` (arrays) both call [`correct_columns`] with the
//! row correction `fit::correction::request` planned, so the two give the same values under the same names.

use crate::correction::correct::{output_columns, Corrected, Measurement, ESTIMATE_AT, EXTRAPOLATED_COLUMN};
use crate::files::calfile::PixelGrid;
use crate::files::calibration::CalibrationFile;
use skyfield::table::{Column, Table};
use std::borrow::Cow;
use std::mem::MaybeUninit;
use std::path::Path;
use stokes::stats::Estimator;

/// The units of a table's positions `x, y`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Units {
    /// Arcmin from the detector centre (the field coordinates of the models).
    Arcmin,
    /// 0-based pixels of the calibration's detector grid ([`PixelGrid`]).
    Pixel,
}

impl Units {
    /// The name a person reads ("arcmin", "pixels").
    pub fn name(self) -> &'static str {
        match self {
            Units::Arcmin => "arcmin",
            Units::Pixel => "pixels",
        }
    }
}

/// Positions in pixels and a calibration without a pixel grid (a telescope-only file, or a
/// field calibration imported without one).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("the calibration has no pixel grid")]
pub struct NoPixelGrid;

/// The pixel grid of a calibration file's field: the p, phi field's or the Mueller field's;
/// none for a telescope model alone.
pub fn pixel_grid(loaded: &CalibrationFile) -> Option<PixelGrid> {
    match (&loaded.field, &loaded.mueller) {
        (Some(c), _) => c.pixel,
        (None, Some(m)) => m.pixel(),
        _ => None,
    }
}

/// Positions `x, y` in arcmin from the detector centre: as given, or converted from pixels of
/// `grid` ([`PixelGrid::to_arcmin`]).
pub fn arcmin_positions<'a>(
    x: &'a [f64],
    y: &'a [f64],
    units: Units,
    grid: Option<PixelGrid>,
) -> Result<(Cow<'a, [f64]>, Cow<'a, [f64]>), NoPixelGrid> {
    match units {
        Units::Arcmin => Ok((Cow::Borrowed(x), Cow::Borrowed(y))),
        Units::Pixel => {
            let g = grid.ok_or(NoPixelGrid)?;
            let (ax, ay): (Vec<f64>, Vec<f64>) = x.iter().zip(y).map(|(&x, &y)| g.to_arcmin(x, y)).unzip();
            Ok((Cow::Owned(ax), Cow::Owned(ay)))
        }
    }
}

/// Why a table's positions cannot be placed ([`TableColumns::place`]).
#[derive(Debug, Clone, PartialEq)]
pub enum PlaceError {
    /// The declared units contradict the asked ones.
    Conflict(String),
    /// Pixels, and a calibration without a pixel grid.
    NoPixelGrid,
}

/// The measured columns of a table to correct, as read ([`TableColumns::read`]).
pub struct TableColumns {
    pub x: Vec<f64>,
    pub y: Vec<f64>,
    pub q: Vec<f64>,
    pub u: Vec<f64>,
    pub sigma_q: Vec<f64>,
    pub sigma_u: Vec<f64>,
    pub cov_qu: Option<Vec<f64>>,
    /// The units `x, y` declare (arcsec and deg already turned into arcmin), `None` when they
    /// declare none ([`TableColumns::units`] decides then).
    pub declared: Option<Units>,
}

impl TableColumns {
    /// The columns `x, y, q, u, sigma_q, sigma_u` (names in any case) and the optional `cov_qu`
    /// of table `t` read from `path`; a missing column is an error naming the table's columns.
    /// Declared units are honoured (`skyfield::table::Table::fractions`): `q, u` and their
    /// errors in % become fractions, `cov_qu` in `%2` too (undeclared beside `q, u` in % it is
    /// refused); `x, y` in `pix` are pixels, in `arcmin`, `arcsec` or `deg` arcmin.
    pub fn read(t: &Table, path: &Path) -> Result<Self, skyfield::Error> {
        let need = |c: &str| -> Result<(), skyfield::Error> {
            if t.column(c).is_none() {
                return Err(skyfield::Error::Table {
                    path: path.to_path_buf(),
                    message: format!(
                        "no column '{c}' (columns: {}); need x, y, q, u, sigma_q, sigma_u",
                        t.names().join(", ")
                    ),
                });
            }
            Ok(())
        };
        let col = |c: &str| need(c).and_then(|()| t.numbers(c, path));
        let (mut x, mut y) = (col("x")?, col("y")?);
        for c in ["q", "u", "sigma_q", "sigma_u"] {
            need(c)?;
        }
        let (mut v, scale) = t.fractions(&["q", "u", "sigma_q", "sigma_u"], path)?;
        let (sigma_u, sigma_q, u, q) = (v.pop().unwrap(), v.pop().unwrap(), v.pop().unwrap(), v.pop().unwrap());
        let bad = |message: String| skyfield::Error::Table { path: path.to_path_buf(), message };
        let cov_qu = if t.column("cov_qu").is_some() {
            let k = match t.unit_of("cov_qu") {
                None if scale == 1.0 => 1.0,
                None => {
                    return Err(bad(
                        "q, u are in % but column 'cov_qu' declares no unit: declare it ('%2', or '' for a fraction squared)"
                            .into(),
                    ))
                }
                Some(u) if u.is_empty() || u.eq_ignore_ascii_case("dimensionless") => 1.0,
                Some(u) if ["%2", "%^2", "percent2"].contains(&u) => 1e-4,
                Some(u) => return Err(bad(format!("column 'cov_qu' has unit '{u}': expected none, '' or '%2'"))),
            };
            Some(col("cov_qu")?.into_iter().map(|c| c * k).collect())
        } else {
            None
        };
        let declared = match (t.unit_of("x"), t.unit_of("y")) {
            (None, None) => None,
            (Some(a), Some(b)) if a == b => {
                let (units, k) = match a {
                    "pix" | "pixel" | "px" => (Units::Pixel, 1.0),
                    "arcmin" => (Units::Arcmin, 1.0),
                    "arcsec" => (Units::Arcmin, 1.0 / 60.0),
                    "deg" => (Units::Arcmin, 60.0),
                    u => {
                        return Err(bad(format!(
                            "columns 'x', 'y' have unit '{u}': expected pix, arcmin, arcsec or deg"
                        )))
                    }
                };
                if k != 1.0 {
                    x.iter_mut().chain(y.iter_mut()).for_each(|v| *v *= k);
                }
                Some(units)
            }
            (a, b) => {
                return Err(bad(format!(
                    "columns 'x' and 'y' declare different units ({} and {}): give both one unit",
                    a.unwrap_or("none"),
                    b.unwrap_or("none")
                )))
            }
        };
        Ok(Self { x, y, q, u, sigma_q, sigma_u, cov_qu, declared })
    }

    /// Put `x, y` in arcmin for a correction with `loaded` ([`Self::units`], then
    /// [`Self::to_arcmin`] on the calibration's pixel grid), and return the units they were
    /// read in. A telescope model alone, or a constant response, does not look at positions:
    /// they are left as they are.
    pub fn place(&mut self, given: Option<Units>, loaded: &CalibrationFile) -> Result<Units, PlaceError> {
        if loaded.field.is_none() && loaded.mueller.is_none() {
            return Ok(self.declared.or(given).unwrap_or(Units::Arcmin));
        }
        let units = self.units(given).map_err(PlaceError::Conflict)?;
        self.to_arcmin(units, pixel_grid(loaded)).map_err(|_| PlaceError::NoPixelGrid)?;
        Ok(units)
    }

    /// The units of `x, y` for the correction: the declared ones, else `given` (a caller's
    /// `--coords`), else arcmin. Declared units that contradict the given ones are refused:
    /// the table knows what its columns are.
    pub fn units(&self, given: Option<Units>) -> Result<Units, String> {
        match (self.declared, given) {
            (Some(d), Some(g)) if d != g => Err(format!(
                "its columns x, y declare {} but {} were asked for: the declared unit is used; drop the option or fix the table",
                d.name(),
                g.name()
            )),
            (Some(d), _) => Ok(d),
            (None, Some(g)) => Ok(g),
            (None, None) => Ok(Units::Arcmin),
        }
    }

    /// Turn `x, y` into arcmin from the detector centre ([`arcmin_positions`]).
    pub fn to_arcmin(&mut self, units: Units, grid: Option<PixelGrid>) -> Result<(), NoPixelGrid> {
        if let (Cow::Owned(x), Cow::Owned(y)) = arcmin_positions(&self.x, &self.y, units, grid)? {
            (self.x, self.y) = (x, y);
        }
        Ok(())
    }

    /// The columns as the input of [`correct_columns`] (positions in arcmin: [`Self::to_arcmin`]),
    /// their `q, u` in `frame` (the table's: [`TableAngles::frame`]).
    pub fn inputs(&self, frame: mueller::Frame) -> Inputs<'_> {
        Inputs {
            frame,
            x: &self.x,
            y: &self.y,
            q: &self.q,
            u: &self.u,
            sigma_q: &self.sigma_q,
            sigma_u: &self.sigma_u,
            cov_qu: self.cov_qu.as_deref(),
        }
    }
}

/// The column of each row's parallactic angle at the exposure's start (deg), and the optional
/// one at its end (the telescope model is then averaged over the track).
pub const PARANG_COLUMNS: [&str; 2] = ["parang_deg", "parang_end_deg"];

/// The column of each row's rotator / adapter angle (deg), read for a telescope model fitted
/// with rotator angles.
pub const ROTATOR_COLUMN: &str = "rotator_deg";

/// A catalog to correct, read from `path` (a FITS table, the HDU `hdu` or the first, when
/// `fits`; else the format of its extension): refused when a column would be overwritten by the
/// corrected ones ([`crate::correction::correct::is_output_column`]) or when it has no row.
pub fn read_catalog(path: &Path, fits: bool, hdu: Option<&str>) -> Result<Table, skyfield::Error> {
    let table =
        if fits { Table::read_format(path, skyfield::table::Format::Fits, hdu)? } else { Table::read(path, hdu)? };
    let refuse = |message: String| Err(skyfield::Error::Table { path: path.to_path_buf(), message });
    if let Some(h) = table.names().into_iter().find(|h| crate::correction::correct::is_output_column(h)) {
        return refuse(format!("column '{h}' would be overwritten by the corrected columns; rename it"));
    }
    if table.n_rows() == 0 {
        return refuse("the catalog has no data rows".into());
    }
    Ok(table)
}

/// What a catalog says of its frames, for [`crate::correction::request::Request`]: the frame of its `q, u`
/// (`skyfield::table::Table::frame`: the HWP zero angle they carry, or none), each row's telescope angles
/// ([`PARANG_COLUMNS`], and [`ROTATOR_COLUMN`] only where it is used: per-row angles and a model
/// fitted with rotator angles), or else, for a telescope model, the angles of the exposures
/// the catalog recorded (`instpol catalog` writes them into ECSV, FITS and VOTable tables).
pub struct TableAngles {
    pub frame: mueller::Frame,
    pub parang_deg: Option<Vec<f64>>,
    pub parang_end_deg: Option<Vec<f64>>,
    pub rotator_deg: Option<Vec<f64>>,
    pub recorded: Option<skyfield::RecordedAngles>,
    /// What the table says its rows are (instrument, filter, plate: its product keywords),
    /// checked against the calibration; `None` for a table that does not say.
    pub setup: Option<crate::correction::setup::Setup>,
}

impl TableAngles {
    /// The angles of table `t` read from `path`, for a correction with `loaded`.
    pub fn read(t: &Table, path: &Path, loaded: &CalibrationFile) -> Result<Self, skyfield::Error> {
        let frame = t.frame(path)?;
        let column = |name: &str| t.column(name).map(|_| t.numbers(name, path)).transpose();
        let (parang_deg, parang_end_deg) = (column(PARANG_COLUMNS[0])?, column(PARANG_COLUMNS[1])?);
        let with_rotator = loaded.telescope.as_ref().is_some_and(|t| t.with_rotator);
        let rotator_deg = if parang_deg.is_some() && with_rotator { column(ROTATOR_COLUMN)? } else { None };
        let recorded = if parang_deg.is_none() && loaded.telescope.is_some() {
            Some(skyfield::RecordedAngles::from_meta(&t.meta, path)?)
        } else {
            None
        };
        let setup = t.product.as_ref().and_then(crate::correction::setup::Setup::of_product);
        Ok(Self { frame, parang_deg, parang_end_deg, rotator_deg, recorded, setup })
    }

    /// `base` with these angles: the rows' data, not a caller's arguments.
    pub fn request<'a>(
        &'a self,
        base: crate::correction::request::Request<'a>,
    ) -> crate::correction::request::Request<'a> {
        crate::correction::request::Request {
            frame: self.frame,
            recorded: self.recorded.as_ref(),
            data: self.setup.as_ref(),
            per_row: self.parang_deg.as_deref().map(|s| crate::correction::request::PerRowAngles {
                start_deg: s,
                end_deg: self.parang_end_deg.as_deref(),
                rotator_deg: self.rotator_deg.as_deref(),
            }),
            ..base
        }
    }
}

/// The filter and the HWP zero angle (deg) a correction of rows reports: a field calibration's
/// own (the rows were turned by it less what they carry), else the one applied, with the
/// field calibration's filter, the Mueller field's, or the telescope model's band.
pub fn reported_zero_angle(loaded: &CalibrationFile, plan: &crate::correction::request::RowsPlan<'_>) -> (String, f64) {
    if let Some(r) = &loaded.response {
        return (r.filter.clone(), r.hwp_chi_offset_deg);
    }
    match (&loaded.field, &loaded.mueller, &plan.telescope) {
        (Some(c), _, None) => (c.filter.clone(), c.hwp_chi_offset_deg),
        (None, Some(m), _) => (m.filter.clone(), plan.to_sky_deg.to_radians().to_degrees()),
        (field, _, t) => (
            field
                .as_ref()
                .map(|c| c.filter.clone())
                .unwrap_or_else(|| t.as_ref().map_or(String::new(), |t| t.band.clone())),
            plan.to_sky_deg,
        ),
    }
}

/// What a correction did, as `instpol correct --json` reports it beside the paths and
/// options: the rows (or bins) corrected and extrapolated, the estimator, the filter and HWP
/// zero angle reported, the medians of the corrected `P0` and of the instrumental `p` removed,
/// and the telescope model or Mueller field applied.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Report {
    pub kind: &'static str,
    #[serde(rename = "n_rows")]
    pub rows: usize,
    #[serde(rename = "n_extrapolated")]
    pub extrapolated: usize,
    /// Rows not measured (q, u NaN: flagged stars), passed through with NaN ([`Outputs::n_unmeasured`]).
    #[serde(rename = "n_unmeasured")]
    pub unmeasured: usize,
    pub estimator: String,
    pub filter: String,
    pub hwp_chi_offset_deg: f64,
    pub median_p0: Option<f64>,
    pub median_p_inst: Option<f64>,
    /// The telescope model applied (wiersema / oxide) and its band, when the calibration has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telescope_model: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telescope_band: Option<String>,
    /// The exposures undone one by one (a map's or catalog's recorded ones); absent: one track.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telescope_exposures: Option<usize>,
    /// A Mueller-field calibration's model (physical / general) and free effects.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mueller_model: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mueller_free: Option<Vec<&'static str>>,
}

impl Report {
    /// The report of a table's rows corrected as `plan` planned into `out` (`kind`: what the
    /// input was, for the summary): the median corrected `P0` and instrumental `p` removed
    /// (`hypot(q_inst, u_inst)` of each row), the filter and zero angle reported, the telescope
    /// applied.
    pub fn of_rows(
        loaded: &CalibrationFile,
        kind: &'static str,
        out: &Outputs,
        est: Estimator,
        plan: &crate::correction::request::RowsPlan<'_>,
    ) -> Self {
        let col = |name: &str| out.column(name).expect("an output column of a correction");
        let p_inst: Vec<f64> = col("q_inst").iter().zip(col("u_inst")).map(|(q, u)| q.hypot(*u)).collect();
        let used = plan.telescope.as_ref().map(|t| (t.fit.model.name(), t.band.clone(), t.exposures));
        Report::new(
            loaded,
            kind,
            (out.extrapolated.len(), out.n_extrapolated, out.n_unmeasured),
            est.name().into(),
            reported_zero_angle(loaded, plan),
            col("p0").to_vec(),
            p_inst,
            used,
        )
    }

    /// The report of a correction with `loaded` of `kind` ("Stokes map", "catalog (text
    /// table)", ...): `n` = (rows or bins, extrapolated ones, unmeasured ones), the estimator's name, the filter
    /// and zero angle the correction reports (the file's own filter replaces `filter` for a
    /// Mueller field or a field model without a telescope), the corrected `P0` and the
    /// instrumental `p` removed (their medians, the mean of the two middles), and the telescope
    /// applied (model, band, exposures undone one by one).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        loaded: &CalibrationFile,
        kind: &'static str,
        n: (usize, usize, usize),
        estimator: String,
        (filter, hwp_chi_offset_deg): (String, f64),
        p0: Vec<f64>,
        p_inst: Vec<f64>,
        telescope: Option<(&'static str, String, usize)>,
    ) -> Self {
        use stokes::stats::robust::{finite_median, Middle};
        let telescope = telescope.filter(|_| loaded.mueller.is_none());
        let filter = match (&loaded.mueller, &telescope, &loaded.field) {
            _ if loaded.response.is_some() => loaded.response.as_ref().map_or(filter, |r| r.filter.clone()),
            (Some(m), _, _) => m.filter.clone(),
            (None, None, Some(c)) => c.filter.clone(),
            _ => filter,
        };
        Report {
            kind,
            rows: n.0,
            extrapolated: n.1,
            unmeasured: n.2,
            estimator,
            filter,
            hwp_chi_offset_deg,
            median_p0: finite_median(p0, Middle::Mean),
            median_p_inst: finite_median(p_inst, Middle::Mean),
            telescope_model: telescope.as_ref().map(|t| t.0),
            telescope_band: telescope.as_ref().map(|t| t.1.clone()),
            telescope_exposures: telescope.as_ref().and_then(|t| (t.2 > 0).then_some(t.2)),
            mueller_model: loaded.mueller.as_ref().map(|m| m.field.kind.model_name()),
            mueller_free: loaded.mueller.as_ref().map(|m| m.field.kind.free_words()),
        }
    }
}

/// The input columns of a correction: positions in arcmin from the detector centre, the
/// measured `q, u` (fractions) in `frame`, their 1-sigma errors and optional covariance (0 when
/// absent), all of one length.
#[derive(Clone, Copy)]
pub struct Inputs<'a> {
    pub frame: mueller::Frame,
    pub x: &'a [f64],
    pub y: &'a [f64],
    pub q: &'a [f64],
    pub u: &'a [f64],
    pub sigma_q: &'a [f64],
    pub sigma_u: &'a [f64],
    pub cov_qu: Option<&'a [f64]>,
}

/// The corrected columns: `values[k]` is the column named `names[k]`
/// ([`crate::correction::correct::output_columns`]), then the flags of the extrapolated rows.
pub struct Outputs {
    pub names: Vec<String>,
    pub values: Vec<Vec<f64>>,
    pub extrapolated: Vec<bool>,
    pub n_extrapolated: usize,
    /// Rows not measured (`q` and `u` both NaN, as `instpol catalog` writes a flagged star):
    /// passed through with every output NaN, not refused, so that a catalog with a flagged
    /// star can be corrected.
    pub n_unmeasured: usize,
}

impl Outputs {
    /// The columns of rows already corrected one by one (`catalog --cal`'s stars), `None` for a
    /// row not measured (every value NaN, not extrapolated): the same columns, in the same
    /// order, as [`correct_columns`] writes without an estimator.
    pub fn of_rows(rows: &[Option<Corrected>]) -> Outputs {
        let each: Vec<[f64; N_OUT]> =
            rows.iter().map(|r| r.as_ref().map_or([f64::NAN; N_OUT], Corrected::output_values)).collect();
        let values = (0..N_OUT).map(|k| each.iter().map(|v| v[k]).collect()).collect();
        let extrapolated: Vec<bool> = rows.iter().map(|r| r.as_ref().is_some_and(|r| r.extrapolated)).collect();
        Outputs {
            names: output_columns(None),
            values,
            n_extrapolated: extrapolated.iter().filter(|&&e| e).count(),
            extrapolated,
            n_unmeasured: rows.iter().filter(|r| r.is_none()).count(),
        }
    }

    /// The column named `name`, if written.
    pub fn column(&self, name: &str) -> Option<&[f64]> {
        self.names.iter().position(|n| n == name).map(|k| self.values[k].as_slice())
    }

    /// The columns to append to a table: the values (unit `deg` for the angles, the rest
    /// dimensionless), then the 0/1 column [`EXTRAPOLATED_COLUMN`].
    pub fn into_table_columns(self) -> Vec<Column> {
        let mut cols: Vec<Column> = (self.names.iter().zip(self.values))
            .map(|(n, v)| Column::f64(n, n.ends_with("_deg").then_some("deg"), "", v))
            .collect();
        let flags = self.extrapolated.iter().map(|&e| e as i64).collect();
        cols.push(Column::i64(EXTRAPOLATED_COLUMN, "1 = outside the calibrated field", flags));
        cols
    }
}

/// Correct every row of `input` with `correct` (the row correction `fit::correction::request` planned,
/// given the row's index and measurement) and write the output columns directly, with the
/// bias-corrected `P0` of `est` when given: no row structs in between, so the time is the
/// library's and not the copying. Halves run on rayon's pool; `progress` is told the number of
/// rows of each finished chunk. The error returned is the one of the lowest row, with its index.
///
/// Panics if the input columns differ in length (the callers check their inputs first).
pub fn correct_columns<F, E>(
    input: &Inputs<'_>,
    est: Option<Estimator>,
    progress: &(dyn Fn(usize) + Sync),
    correct: F,
) -> Result<Outputs, (usize, E)>
where
    F: Fn(usize, &Measurement) -> Result<Corrected, E> + Sync,
    E: Send,
{
    let n = input.x.len();
    let lens = [input.y.len(), input.q.len(), input.u.len(), input.sigma_q.len(), input.sigma_u.len()];
    assert!(lens.iter().chain(input.cov_qu.map(|c| c.len()).as_ref()).all(|&l| l == n), "input columns of one length");
    let mut cols: Vec<Vec<f64>> = (0..N_OUT).map(|_| reserved_column(n)).collect();
    let mut p0e: Option<Vec<f64>> = est.map(|_| reserved_column(n));
    let mut extrapolated = vec![false; n];
    let mut it = cols.iter_mut();
    let sink = Sink {
        cols: std::array::from_fn(|_| slots(it.next().expect("N_OUT columns"), n)),
        p0e: p0e.as_mut().zip(est).map(|(c, e)| (slots(c, n), e)),
        extra: &mut extrapolated,
        start: 0,
    };
    let (n_extrapolated, n_unmeasured) = fill(&correct, input, sink, progress)?;
    for c in cols.iter_mut().chain(p0e.as_mut()) {
        // SAFETY: `fill` returns Ok only after writing every row 0..n of every output column
        // (and of `p0e` when it is Some); on Err the columns are dropped with length 0 above.
        unsafe { c.set_len(n) };
    }
    let mut values = cols;
    if let Some(v) = p0e {
        values.insert(ESTIMATE_AT, v);
    }
    Ok(Outputs { names: output_columns(est), values, extrapolated, n_extrapolated, n_unmeasured })
}

/// The number of [`crate::correction::correct::OUTPUT_NAMES`].
const N_OUT: usize = crate::correction::correct::OUTPUT_NAMES.len();

/// An output column of `n` values that `fill` writes whole before it is read: reserved, not
/// zeroed. Zeroing it first cost a memset of every column (6 % of the Python `correct`, perf:
/// glibc's calloc clears heap memory that malloc would hand back as it is) that the fill
/// overwrites.
fn reserved_column(n: usize) -> Vec<f64> {
    let v = Vec::with_capacity(n);
    // Correcting 1e6 positions writes 11 columns (88 MB) into fresh pages: in 4 kB pages the
    // page faults took a sixth of the time (bench/python_correct.sh, one core: 8.2e6
    // positions/s without the hint, 9.8e6 with it).
    skyfield::advise_huge_pages(v.as_ptr() as usize, n * std::mem::size_of::<f64>());
    v
}

/// The first `n` slots of a [`reserved_column`], to be written.
fn slots(v: &mut Vec<f64>, n: usize) -> &mut [MaybeUninit<f64>] {
    &mut v.spare_capacity_mut()[..n]
}

/// Mutable windows of the output columns for rows `start ..`.
struct Sink<'a> {
    cols: [&'a mut [MaybeUninit<f64>]; N_OUT],
    p0e: Option<(&'a mut [MaybeUninit<f64>], Estimator)>,
    extra: &'a mut [bool],
    start: usize,
}

impl<'a> Sink<'a> {
    fn split(self, mid: usize) -> (Sink<'a>, Sink<'a>) {
        let mut left: [&'a mut [MaybeUninit<f64>]; N_OUT] = Default::default();
        let mut right: [&'a mut [MaybeUninit<f64>]; N_OUT] = Default::default();
        for (k, c) in self.cols.into_iter().enumerate() {
            (left[k], right[k]) = c.split_at_mut(mid);
        }
        let (pa, pb) = match self.p0e {
            Some((c, e)) => {
                let (l, r) = c.split_at_mut(mid);
                (Some((l, e)), Some((r, e)))
            }
            None => (None, None),
        };
        let (ea, eb) = self.extra.split_at_mut(mid);
        (
            Sink { cols: left, p0e: pa, extra: ea, start: self.start },
            Sink { cols: right, p0e: pb, extra: eb, start: self.start + mid },
        )
    }
}

/// [`correct_columns`] on the rows of `s`, halved down to chunks; returns the numbers of
/// extrapolated and of unmeasured rows.
fn fill<F, E>(
    cor: &F,
    i: &Inputs<'_>,
    s: Sink<'_>,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<(usize, usize), (usize, E)>
where
    F: Fn(usize, &Measurement) -> Result<Corrected, E> + Sync,
    E: Send,
{
    const CHUNK: usize = 4096;
    let n = s.extra.len();
    if n > CHUNK {
        let (a, b) = s.split(n / 2);
        let (ra, rb) = rayon::join(|| fill(cor, i, a, progress), || fill(cor, i, b, progress));
        return match (ra, rb) {
            (Ok(x), Ok(y)) => Ok((x.0 + y.0, x.1 + y.1)),
            (Err(e), _) | (Ok(_), Err(e)) => Err(e),
        };
    }
    let r0 = s.start;
    let (x, y, q, u) = (&i.x[r0..r0 + n], &i.y[r0..r0 + n], &i.q[r0..r0 + n], &i.u[r0..r0 + n]);
    let (sq, su) = (&i.sigma_q[r0..r0 + n], &i.sigma_u[r0..r0 + n]);
    let cov = i.cov_qu.map(|c| &c[r0..r0 + n]);
    let Sink { cols, mut p0e, extra, .. } = s;
    let [c_q0, c_u0, c_sq0, c_su0, c_cov0, c_p0, c_sp0, c_chi0, c_sc0, c_qi, c_ui] = cols;
    let (mut n_extra, mut n_unmeasured) = (0, 0);
    for k in 0..n {
        if q[k].is_nan() && u[k].is_nan() {
            // Not measured (a flagged star): nothing to correct, every output NaN.
            for c in [&mut *c_q0, &mut *c_u0, &mut *c_sq0, &mut *c_su0, &mut *c_cov0, &mut *c_p0, &mut *c_sp0] {
                c[k].write(f64::NAN);
            }
            for c in [&mut *c_chi0, &mut *c_sc0, &mut *c_qi, &mut *c_ui] {
                c[k].write(f64::NAN);
            }
            if let Some((c, _)) = p0e.as_mut() {
                c[k].write(f64::NAN);
            }
            extra[k] = false;
            n_unmeasured += 1;
            continue;
        }
        let qu = mueller::Qu::from_sigmas(q[k], u[k], sq[k], su[k], cov.map_or(0.0, |c| c[k]));
        let m = Measurement::at(x[k], y[k], qu, i.frame);
        let r = cor(r0 + k, &m).map_err(|e| (r0 + k, e))?;
        // Written column by column here, not through an array of columns: this loop is the 1e7/s
        // path (bench/python_correct.sh) and the array-of-slices loop measured ~20 % slower.
        // The values are those of Corrected::output_values (checked in the tests).
        c_q0[k].write(r.q0);
        c_u0[k].write(r.u0);
        c_sq0[k].write(r.var_q0.sqrt());
        c_su0[k].write(r.var_u0.sqrt());
        c_cov0[k].write(r.cov_qu0);
        c_p0[k].write(r.p0);
        c_sp0[k].write(r.sigma_p0);
        c_chi0[k].write(r.chi0.to_degrees());
        c_sc0[k].write(r.sigma_chi0.to_degrees());
        c_qi[k].write(r.inst.q);
        c_ui[k].write(r.inst.u);
        if let Some((c, e)) = p0e.as_mut() {
            c[k].write(r.p0_estimate(*e));
        }
        extra[k] = r.extrapolated;
        n_extra += r.extrapolated as usize;
    }
    progress(n);
    Ok((n_extra, n_unmeasured))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::correction::correct::{CorrectOptions, Corrector};
    use crate::models::model::{FieldModel, InstPol};
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// A field of 2 % along x at the centre growing with radius, inside |x|, |y| <= 3 arcmin.
    struct Radial;
    impl FieldModel for Radial {
        fn eval(&self, x: f64, y: f64) -> InstPol {
            let p = 0.02 * (1.0 + 0.1 * (x * x + y * y));
            let phi = y.atan2(x);
            InstPol { q: p * (2.0 * phi).cos(), u: p * (2.0 * phi).sin(), var_q: 1e-8, var_u: 2e-8, cov_qu: 1e-9 }
        }
        fn contains(&self, x: f64, y: f64) -> bool {
            x.abs() <= 3.0 && y.abs() <= 3.0
        }
    }

    fn rows(n: usize) -> [Vec<f64>; 7] {
        let f = |k: usize, a: f64, b: f64| a + b * ((k * 7919) % 1000) as f64 / 1000.0;
        [
            (0..n).map(|k| f(k, -3.5, 7.0)).collect(),
            (0..n).map(|k| f(k + 3, -3.0, 6.0)).collect(),
            (0..n).map(|k| f(k + 5, -0.05, 0.1)).collect(),
            (0..n).map(|k| f(k + 7, -0.05, 0.1)).collect(),
            (0..n).map(|k| f(k + 11, 1e-4, 1e-3)).collect(),
            (0..n).map(|k| f(k + 13, 1e-4, 1e-3)).collect(),
            (0..n).map(|k| f(k + 17, -1e-8, 2e-8)).collect(),
        ]
    }

    /// Every column of every row, over several chunks run in parallel, is the row's
    /// `Corrected::output_row` under `output_columns`' names, row by row with the same
    /// corrector; the flags and their count are the rows'; the progress adds up to the rows.
    #[test]
    fn columns_are_the_rows_output() {
        let n = 10_000;
        let [x, y, q, u, sq, su, cov] = rows(n);
        let frame = mueller::Frame::Sky { zero_angle_deg: -0.4 };
        let input = Inputs { frame, x: &x, y: &y, q: &q, u: &u, sigma_q: &sq, sigma_u: &su, cov_qu: Some(&cov) };
        let opts = CorrectOptions { allow_extrapolation: true, zero_angle_deg: 1.2, ..CorrectOptions::default() };
        let cor = Corrector::new(&Radial, opts);
        let est: Estimator = "mas".parse().unwrap();
        let done = AtomicUsize::new(0);
        let count = |k: usize| {
            done.fetch_add(k, Ordering::Relaxed);
        };
        let out = correct_columns(&input, Some(est), &count, |_, m| cor.correct(m)).unwrap();
        assert_eq!(done.into_inner(), n);
        assert_eq!(out.names, output_columns(Some(est)));
        assert_eq!(out.names[9], "p0_mas");
        assert_eq!(out.values.len(), out.names.len());
        let mut n_extra = 0;
        for k in 0..n {
            let m = Measurement::at(x[k], y[k], mueller::Qu::from_sigmas(q[k], u[k], sq[k], su[k], cov[k]), frame);
            let r = cor.correct(&m).unwrap();
            let want = r.output_row(Some(est));
            let got: Vec<f64> = out.values.iter().map(|c| c[k]).collect();
            assert_eq!(
                got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                want.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
            assert_eq!(out.extrapolated[k], r.extrapolated);
            n_extra += r.extrapolated as usize;
        }
        assert!(n_extra > 0 && n_extra < n);
        assert_eq!(out.n_extrapolated, n_extra);
        // Without an estimator: the eleven OUTPUT_NAMES, the same values.
        let bare = correct_columns(&input, None, &|_| {}, |_, m| cor.correct(m)).unwrap();
        assert_eq!(bare.names, crate::correction::correct::OUTPUT_NAMES);
        let mut with = out.values.clone();
        with.remove(9);
        assert_eq!(bare.values, with);
    }

    /// The error returned is the lowest failing row's, whichever chunk finished first.
    #[test]
    fn error_is_the_lowest_row() {
        let n = 20_000;
        let [mut x, mut y, q, u, sq, su, _] = rows(n);
        for v in x.iter_mut().chain(y.iter_mut()) {
            *v *= 0.5;
        }
        for k in [17_000, 9_001, 12_345] {
            y[k] = 50.0;
        }
        let input = Inputs {
            frame: mueller::Frame::Plate,
            x: &x,
            y: &y,
            q: &q,
            u: &u,
            sigma_q: &sq,
            sigma_u: &su,
            cov_qu: None,
        };
        let cor = Corrector::new(&Radial, CorrectOptions::default());
        let e = correct_columns(&input, None, &|_| {}, |_, m| cor.correct(m)).err().map(|e| e.0);
        assert_eq!(e, Some(9_001));
    }

    /// The columns a table gets: the values with `deg` on the angles, then the 0/1 flags.
    #[test]
    fn table_columns_units_and_flag() {
        let out = Outputs {
            names: output_columns(None),
            values: vec![vec![1.0]; 11],
            extrapolated: vec![true],
            n_extrapolated: 1,
            n_unmeasured: 0,
        };
        let cols = out.into_table_columns();
        assert_eq!(cols.len(), 12);
        let units: Vec<Option<&str>> = cols.iter().map(|c| c.unit.as_deref()).collect();
        assert_eq!(units[7], Some("deg"));
        assert_eq!(units[8], Some("deg"));
        assert_eq!(units.iter().filter(|u| u.is_some()).count(), 2);
        assert_eq!(cols[11].name, EXTRAPOLATED_COLUMN);
        assert_eq!(cols[11].data, skyfield::table::Data::I64(vec![1]));
    }

    /// The input columns a correction would overwrite: the output names in any case and any
    /// estimator's `p0_<name>`, not others that only look alike.
    #[test]
    fn overwritten_columns() {
        for n in ["q0", " P0_MAS", "p0_anything", "Q_INST", "extrapolated", "sigma_chi0_deg"] {
            assert!(crate::correction::correct::is_output_column(n), "{n}");
        }
        for n in ["p0x", "mag", "q", "sigma_q", "chi0", "inst_q"] {
            assert!(!crate::correction::correct::is_output_column(n), "{n}");
        }
    }

    /// Pixels through the grid, arcmin as given, and pixels without a grid refused.
    #[test]
    fn positions_in_arcmin() {
        let g = PixelGrid { scale_arcsec: 0.2, origin_px: [1023.5, 1023.5] };
        let (x, y) = arcmin_positions(&[1323.5], &[723.5], Units::Pixel, Some(g)).unwrap();
        // 300 px of 0.2" = 60" = 1 arcmin along x, -1 arcmin along y.
        assert!((x[0] - 1.0).abs() < 1e-12 && (y[0] + 1.0).abs() < 1e-12, "{x:?} {y:?}");
        let (x, _) = arcmin_positions(&[1.5], &[2.0], Units::Arcmin, None).unwrap();
        assert_eq!(x[0], 1.5);
        assert_eq!(arcmin_positions(&[1.0], &[1.0], Units::Pixel, None).unwrap_err(), NoPixelGrid);
    }
}
