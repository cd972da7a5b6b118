//! The table value: typed columns ([`Column`], [`Data`]), the [`Table`] with its rows' source
//! lines and table-level numbers, the formats ([`Format`]), and what every format's reader
//! shares (the text of a file, a column's cells as its declared type).

use crate::Error;
use std::path::Path;

/// A table format (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Csv,
    Fits,
    Ecsv,
    Votable,
}

/// The extensions each format is chosen by, for messages.
pub const EXTENSIONS: &str = ".csv, .fits (.fit, .fts), .ecsv, .vot (.xml, .votable)";

impl Format {
    /// The format a file's extension names (case-insensitive), or an error naming the file.
    pub fn from_path(path: &Path) -> Result<Self, Error> {
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
        Ok(match ext.as_str() {
            "csv" => Format::Csv,
            "fits" | "fit" | "fts" => Format::Fits,
            "ecsv" => Format::Ecsv,
            "vot" | "xml" | "votable" => Format::Votable,
            _ => {
                return Err(terr(
                    path,
                    format!(
                        "unknown table format '{}' (from the extension): use one of {EXTENSIONS}",
                        if ext.is_empty() { "(no extension)".to_string() } else { format!(".{ext}") }
                    ),
                ))
            }
        })
    }
}

/// The values of one column.
#[derive(Debug, Clone, PartialEq)]
pub enum Data {
    F64(Vec<f64>),
    I64(Vec<i64>),
    Str(Vec<String>),
}

impl Data {
    pub fn len(&self) -> usize {
        match self {
            Data::F64(v) => v.len(),
            Data::I64(v) => v.len(),
            Data::Str(v) => v.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Row `i` as text, as the CSV and ECSV writers write it (NaN as `nan`, or empty for CSV).
    pub(super) fn text(&self, i: usize) -> String {
        match self {
            Data::F64(v) => fmt_f64(v[i]),
            Data::I64(v) => v[i].to_string(),
            Data::Str(v) => v[i].clone(),
        }
    }
}

/// Shortest text that reads back to the same f64; NaN as `nan`, infinities as `inf`/`-inf`
/// (the spellings numpy and astropy read).
fn fmt_f64(x: f64) -> String {
    if x.is_nan() {
        "nan".into()
    } else if x.is_infinite() {
        if x > 0.0 { "inf" } else { "-inf" }.into()
    } else {
        format!("{x:?}")
    }
}

/// One column: name, unit (a FITS/astropy unit string such as `pix`, `deg`, `arcmin`,
/// `electron`; None for a dimensionless or unitless column), description, values.
#[derive(Debug, Clone, PartialEq)]
pub struct Column {
    pub name: String,
    pub unit: Option<String>,
    pub description: Option<String>,
    pub data: Data,
}

impl Column {
    pub fn f64(name: &str, unit: Option<&str>, description: &str, v: Vec<f64>) -> Self {
        Self { name: name.into(), unit: unit.map(Into::into), description: nonempty(description), data: Data::F64(v) }
    }
    pub fn i64(name: &str, description: &str, v: Vec<i64>) -> Self {
        Self { name: name.into(), unit: None, description: nonempty(description), data: Data::I64(v) }
    }
    pub fn text(name: &str, description: &str, v: Vec<String>) -> Self {
        Self { name: name.into(), unit: None, description: nonempty(description), data: Data::Str(v) }
    }
}

fn nonempty(s: &str) -> Option<String> {
    (!s.is_empty()).then(|| s.to_string())
}

/// A table: columns of equal length, and where each row came from (for error messages).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Table {
    pub columns: Vec<Column>,
    /// Source line of each data row (CSV and ECSV), for messages; empty otherwise.
    pub lines: Vec<u64>,
    /// Table-level numbers (module docs): keyword-like names (at most 8 characters, upper case,
    /// digits, `_` or `-`, as FITS keywords), finite values.
    pub meta: Vec<(String, f64)>,
    /// What the table's rows are (instrument, filter, plate, frame, geometry, inputs:
    /// [`crate::provenance::Product`]), written and read by every format; `None` for a table
    /// that does not say (written by other software).
    pub product: Option<crate::provenance::Product>,
}

/// The column of a catalog table holding the HWP zero angle (deg) its q, u already carry
/// ([`Table::frame`]).
pub const ZERO_ANGLE_COLUMN: &str = "hwp_chi_offset_deg";

/// The column of a catalog table holding the instrument's position angle on the sky (deg) its
/// q, u were turned by into the celestial frame ([`Table::frame`]; `instrument::SkyAngle`).
pub const SKY_PA_COLUMN: &str = "sky_pa_deg";

pub(super) fn terr(path: &Path, message: impl Into<String>) -> Error {
    Error::Table { path: path.to_path_buf(), message: message.into() }
}

impl Table {
    pub fn new(columns: Vec<Column>) -> Self {
        Self { columns, lines: Vec::new(), meta: Vec::new(), product: None }
    }

    /// The product's keyword and value pairs as written ([`crate::provenance::Product::pairs`]):
    /// a product that lists no inputs gets the run's (the provenance's hashes), as every FITS
    /// writer stamps the run's provenance without each command passing it down. Empty without
    /// a product.
    pub(super) fn product_pairs(&self) -> Vec<(String, String)> {
        self.product.as_ref().map_or_else(Vec::new, |p| p.with_run_inputs().pairs())
    }

    pub fn n_rows(&self) -> usize {
        self.columns.first().map_or(0, |c| c.data.len())
    }

    /// "row 3" (1-based data row), with its line in text formats ("row 3 (line 5)"), for
    /// messages.
    pub fn row_label(&self, i: usize) -> String {
        match self.lines.get(i) {
            Some(l) => format!("row {} (line {l})", i + 1),
            None => format!("row {}", i + 1),
        }
    }

    /// The column named `name` (case-insensitive, surrounding blanks ignored).
    pub fn column(&self, name: &str) -> Option<&Column> {
        self.columns.iter().find(|c| c.name.trim().eq_ignore_ascii_case(name))
    }

    /// The column names, for messages.
    pub fn names(&self) -> Vec<String> {
        self.columns.iter().map(|c| c.name.clone()).collect()
    }

    /// The frame of the table's q, u: the sky's, with the HWP zero angle (deg) they carry in
    /// the column [`ZERO_ANGLE_COLUMN`] (what `instpol catalog` writes; one value for every row,
    /// else an error naming the first row that differs); the celestial frame when the column
    /// [`SKY_PA_COLUMN`] gives the instrument's position angle they were turned by too (one
    /// value for every row); the plate's without the zero-angle column (q, u as measured).
    pub fn frame(&self, path: &Path) -> Result<mueller::Frame, Error> {
        let zero = ("the HWP zero angle the row's q, u carry", "HWP zero angle");
        let Some(z) = self.one_value(ZERO_ANGLE_COLUMN, zero, path)? else {
            if self.column(SKY_PA_COLUMN).is_some() {
                return Err(terr(
                    path,
                    format!("column '{SKY_PA_COLUMN}' without '{ZERO_ANGLE_COLUMN}': the rows' frame is not whole"),
                ));
            }
            return Ok(mueller::Frame::Plate);
        };
        let pa = ("the instrument's position angle on the sky the row's q, u were turned by", "position angle");
        let pa = self.one_value(SKY_PA_COLUMN, pa, path)?;
        Ok(mueller::Frame::carrying_on_sky(Some(z), pa).expect("a zero angle under the position angle"))
    }

    /// The one value (deg) of column `name` that every row shares (`what` it is at length and
    /// in short, for the errors that name the first row that is not a number or differs);
    /// `None` without the column.
    fn one_value(&self, name: &str, (what, short): (&str, &str), path: &Path) -> Result<Option<f64>, Error> {
        if self.column(name).is_none() {
            return Ok(None);
        }
        let z = self.numbers(name, path)?;
        let z0 = z.first().copied().unwrap_or(0.0);
        if let Some(i) = z.iter().position(|v| !v.is_finite()) {
            return Err(terr(
                path,
                format!(
                    "{}: column '{name}' = {} is not a number: {what} must be given (0 for none)",
                    self.row_label(i),
                    z[i]
                ),
            ));
        }
        if let Some(i) = z.iter().position(|v| (v - z0).abs() > 1e-9) {
            return Err(terr(
                path,
                format!(
                    "{}: column '{name}' = {} differs from the first row's {z0}: one catalog has one {short}",
                    self.row_label(i),
                    z[i]
                ),
            ));
        }
        Ok(Some(z0))
    }

    /// The unit column `name` declares (astropy's unit string, trimmed), `None` when it
    /// declares none (a CSV table, or an empty unit).
    pub fn unit_of(&self, name: &str) -> Option<&str> {
        self.column(name).and_then(|c| c.unit.as_deref()).map(str::trim).filter(|u| !u.is_empty())
    }

    /// Columns `names` (a quantity and its errors, such as `q, u, sigma_q, sigma_u`) as
    /// fractions, by their declared units: none or `''`/`dimensionless` as they are, `%` or
    /// `percent` divided by 100. Another unit is refused, and so are columns that disagree
    /// (`q` in % with `sigma_q` undeclared), with the fix in the message: percent read as a
    /// fraction made every correction 100 times too large. Returns the values and the scale.
    pub fn fractions(&self, names: &[&str], path: &Path) -> Result<(Vec<Vec<f64>>, f64), Error> {
        let scale = |n: &str| match self.unit_of(n) {
            None => Ok(None),
            Some(u) if u.eq_ignore_ascii_case("dimensionless") || u == "1" => Ok(Some(1.0)),
            Some(u) if u == "%" || u.eq_ignore_ascii_case("percent") => Ok(Some(0.01)),
            Some(u) => Err(terr(path, format!("column '{n}' has unit '{u}': a fraction needs none (or '') or '%'"))),
        };
        let scales: Vec<(&str, Option<f64>)> =
            names.iter().map(|n| Ok((*n, scale(n)?))).collect::<Result<_, Error>>()?;
        let declared = scales.iter().find_map(|(n, s)| s.map(|s| (*n, s)));
        let mut out = Vec::with_capacity(names.len());
        for (n, s) in &scales {
            let k = match (s, declared) {
                (Some(s), Some((first, d))) if *s != d => {
                    return Err(terr(
                        path,
                        format!("column '{n}' and column '{first}' declare different units: give them one unit (% or none)"),
                    ))
                }
                (None, Some((first, d))) if d != 1.0 => {
                    return Err(terr(
                        path,
                        format!("column '{first}' is in %, but column '{n}' declares no unit: declare it (%) so that it is not read as a fraction"),
                    ))
                }
                (Some(s), _) => *s,
                (None, _) => 1.0,
            };
            let v = self.values(n, path)?;
            out.push(if k == 1.0 { v } else { v.into_iter().map(|x| x * k).collect() });
        }
        Ok((out, declared.map_or(1.0, |d| d.1)))
    }

    /// Column `name` as numbers (an empty text field is NaN) in the unit its name promises
    /// (`q`, `sigma_q`, ... fractions; `..._deg`, `..._arcmin` those angles; `..._percent`
    /// percent): a declared unit is converted, or refused when it cannot be (the rule is in
    /// `units`). An error names the file, the column and the first row that is not a number, or
    /// the columns there are when it is missing.
    pub fn numbers(&self, name: &str, path: &Path) -> Result<Vec<f64>, Error> {
        let v = self.values(name, path)?;
        let k = self.named_factor(name).map_err(|m| terr(path, m))?;
        Ok(if k == 1.0 { v } else { v.into_iter().map(|x| x * k).collect() })
    }

    /// The factor from column `name`'s declared unit to the unit its name promises.
    fn named_factor(&self, name: &str) -> Result<f64, String> {
        let unit = self.unit_of(name);
        let percent_beside = self.columns.iter().find_map(|c| {
            let other = !c.name.trim().eq_ignore_ascii_case(name.trim());
            let pct = matches!(self.unit_of(&c.name), Some(u) if u == "%" || u.eq_ignore_ascii_case("percent"));
            (other && pct && super::units::named(&c.name) == Some(super::units::Named::Fraction))
                .then_some(c.name.as_str())
        });
        super::units::factor(name, unit, percent_beside)
    }

    /// The table with every column whose name promises a unit converted to it
    /// ([`Self::numbers`]) and its declared unit dropped, for a reader that goes on from the
    /// table's text (a CSV of plain numbers).
    pub fn in_named_units(&self, path: &Path) -> Result<Table, Error> {
        let mut t = self.clone();
        for c in t.columns.iter_mut() {
            if matches!(c.data, Data::Str(_)) || super::units::named(&c.name).is_none() {
                continue;
            }
            c.data = Data::F64(self.numbers(&c.name, path)?);
            c.unit = None;
        }
        Ok(t)
    }

    /// Column `name` as numbers, as they are written (no unit looked at).
    fn values(&self, name: &str, path: &Path) -> Result<Vec<f64>, Error> {
        let c = self
            .column(name)
            .ok_or_else(|| terr(path, format!("no column '{name}' (columns: {})", self.names().join(", "))))?;
        match &c.data {
            Data::F64(v) => Ok(v.clone()),
            Data::I64(v) => Ok(v.iter().map(|&x| x as f64).collect()),
            Data::Str(v) => v
                .iter()
                .enumerate()
                .map(|(i, s)| {
                    if s.trim().is_empty() {
                        return Ok(f64::NAN); // an empty field is a missing value
                    }
                    s.trim().parse::<f64>().map_err(|_| {
                        terr(path, format!("{}: column '{}' = '{s}' is not a number", self.row_label(i), c.name))
                    })
                })
                .collect(),
        }
    }

    pub(super) fn check(&self, path: &Path) -> Result<(), Error> {
        let n = self.n_rows();
        for c in &self.columns {
            if c.data.len() != n {
                return Err(terr(path, format!("column '{}' has {} rows, the table {n}", c.name, c.data.len())));
            }
            if c.name.trim().is_empty() {
                return Err(terr(path, "a column has an empty name"));
            }
        }
        for (i, c) in self.columns.iter().enumerate() {
            if self.columns[..i].iter().any(|d| d.name.eq_ignore_ascii_case(&c.name)) {
                return Err(terr(path, format!("column '{}' appears twice", c.name)));
            }
        }
        for (k, v) in &self.meta {
            let name_ok = !k.is_empty()
                && k.len() <= 8
                && k.chars().all(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_' || c == '-');
            if !name_ok || !v.is_finite() {
                return Err(terr(
                    path,
                    format!("table value {k} = {v}: a name of up to 8 of A-Z 0-9 _ - and a finite number"),
                ));
            }
        }
        Ok(())
    }
}

pub(super) fn read_text(path: &Path) -> Result<String, Error> {
    std::fs::read_to_string(path).map_err(|e| terr(path, format!("cannot read: {e}")))
}

/// What a column's declared type makes of its text cells.
#[derive(Clone, Copy)]
pub(super) enum Kind {
    Float,
    Int,
    Bool,
    Text,
}

/// The text cells of one column as `kind`: `num` parses a float cell in the format's spellings
/// (empty = missing = NaN), `bad(row, cell)` is the error for a cell that is not of the type.
/// Integers with a missing cell become floats with NaN there.
pub(super) fn cells_to_data(
    v: Vec<String>,
    kind: Kind,
    num: impl Fn(usize, &str) -> Result<f64, Error>,
    bad: impl Fn(usize, &str) -> Error,
) -> Result<Data, Error> {
    let floats = |v: &[String]| v.iter().enumerate().map(|(i, s)| num(i, s)).collect::<Result<Vec<f64>, Error>>();
    Ok(match kind {
        Kind::Float => Data::F64(floats(&v)?),
        Kind::Int if v.iter().any(|s| s.is_empty()) => Data::F64(floats(&v)?),
        Kind::Int => {
            Data::I64(v.iter().enumerate().map(|(i, s)| s.parse().map_err(|_| bad(i, s))).collect::<Result<_, _>>()?)
        }
        Kind::Bool => Data::I64(
            v.iter()
                .enumerate()
                .map(|(i, s)| match s.to_ascii_lowercase().as_str() {
                    "t" | "true" | "1" => Ok(1),
                    "f" | "false" | "0" => Ok(0),
                    _ => Err(bad(i, s)),
                })
                .collect::<Result<_, _>>()?,
        ),
        Kind::Text => Data::Str(v),
    })
}
