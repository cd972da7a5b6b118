//! Tables in and out: the one reader and writer of every star or catalog table of the workspace,
//! in the four formats astronomers exchange them in, chosen by the file's extension:
//!
//! | extension            | format                                                     | units   |
//! |----------------------|------------------------------------------------------------|---------|
//! | `.csv`               | comma-separated, one header row; `#` lines are comments    | none    |
//! | `.fits` `.fit` `.fts`| FITS binary table (first table HDU, or one named)           | `TUNITn`|
//! | `.ecsv`              | astropy's Enhanced CSV 1.0 (YAML header, space-delimited)   | header  |
//! | `.vot` `.xml` `.votable` | IVOA VOTable 1.4, `TABLEDATA` serialization            | `unit=` |
//!
//! Any other extension is refused with an error naming it. Columns are typed: 64-bit floats,
//! 64-bit integers, or text. A CSV column is an integer when every field is one, a float when
//! every field is a number (an empty field is NaN), else text.
//!
//! A table may carry table-level numbers ([`Table::meta`]): keywords of the FITS table HDU, the
//! ECSV header's `meta` mapping, VOTable `PARAM`s; a CSV file has no place for them (they are
//! left out, and read as none).
//!
//! The ECSV and VOTable readers are strict subsets, enough for what astropy writes for a plain
//! table (scalar columns; the tests read files astropy wrote, `tests/data/tables/`): a
//! multidimensional column, an ECSV column of `complex`/`object` type, or a VOTable in a
//! `BINARY`/`BINARY2`/`FITS` serialization is refused with an error that says so.

use crate::Error;
use std::io::Write;
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
    fn text(&self, i: usize) -> String {
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
}

/// The column of a catalog table holding the HWP zero angle (deg) its q, u already carry
/// ([`Table::carried_zero_angle`]).
pub const ZERO_ANGLE_COLUMN: &str = "hwp_chi_offset_deg";

fn terr(path: &Path, message: impl Into<String>) -> Error {
    Error::Table { path: path.to_path_buf(), message: message.into() }
}

impl Table {
    pub fn new(columns: Vec<Column>) -> Self {
        Self { columns, lines: Vec::new(), meta: Vec::new() }
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

    /// The HWP zero angle (deg) the table's q, u already carry, from its column
    /// [`ZERO_ANGLE_COLUMN`] (what `instpol catalog` writes; one value for every row, else an
    /// error naming the first row that differs); `None` without the column (q, u as measured,
    /// at the plate).
    pub fn carried_zero_angle(&self, path: &Path) -> Result<Option<f64>, Error> {
        if self.column(ZERO_ANGLE_COLUMN).is_none() {
            return Ok(None);
        }
        let z = self.numbers(ZERO_ANGLE_COLUMN, path)?;
        let z0 = z.first().copied().unwrap_or(0.0);
        if let Some(i) = z.iter().position(|v| !(v.is_finite() && (v - z0).abs() <= 1e-9)) {
            return Err(terr(
                path,
                format!(
                    "{}: column '{ZERO_ANGLE_COLUMN}' = {} differs from the first row's {z0}: one catalog has one HWP zero angle",
                    self.row_label(i),
                    z[i]
                ),
            ));
        }
        Ok(Some(z0))
    }

    /// Column `name` as numbers (an empty text field is NaN); an error names the file, the column and the first row that is
    /// not a number, or the columns there are when it is missing.
    pub fn numbers(&self, name: &str, path: &Path) -> Result<Vec<f64>, Error> {
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

    fn check(&self, path: &Path) -> Result<(), Error> {
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

    /// Read a table in the format its extension names; for FITS, the HDU named `hdu` or the
    /// first table HDU.
    pub fn read(path: &Path, hdu: Option<&str>) -> Result<Self, Error> {
        Self::read_format(path, Format::from_path(path)?, hdu)
    }

    /// [`Self::read`] in a given format, whatever the extension (a FITS file recognized by its
    /// content).
    pub fn read_format(path: &Path, format: Format, hdu: Option<&str>) -> Result<Self, Error> {
        if hdu.is_some() && format != Format::Fits {
            return Err(terr(path, "an HDU name applies to FITS tables only"));
        }
        let t = match format {
            Format::Csv => read_csv(path)?,
            Format::Fits => read_fits(path, hdu)?,
            Format::Ecsv => read_ecsv(path)?,
            Format::Votable => read_votable(path)?,
        };
        t.check(path)?;
        Ok(t)
    }

    /// Write the table in the format the extension of `path` names, atomically (a temporary
    /// file beside it renamed onto it when complete: a failed write leaves no file).
    pub fn write(&self, path: &Path) -> Result<(), Error> {
        let format = Format::from_path(path)?;
        self.check(path)?;
        if format == Format::Fits {
            return crate::io::write_fits_atomic(path, |f| self.write_fits_into(f, path));
        }
        let bytes = match format {
            Format::Csv => self.csv_bytes(),
            Format::Ecsv => self.ecsv_bytes(),
            _ => self.votable_bytes(),
        }
        .map_err(|m| terr(path, format!("cannot format the table: {m}")))?;
        let werr = |e: std::io::Error| Error::Write { path: path.into(), message: e.to_string() };
        let mut tmp = crate::io::temp_beside(path, ".tmp").map_err(werr)?;
        tmp.write_all(&bytes).and_then(|_| tmp.flush()).map_err(werr)?;
        crate::durable::finish(tmp.into_temp_path(), path).map_err(werr)
    }

    /// CSV: a header row and one row per record; NaN as an empty field (what spreadsheets and
    /// pandas read as missing).
    pub fn csv_bytes(&self) -> Result<Vec<u8>, String> {
        let mut w = csv::Writer::from_writer(Vec::new());
        w.write_record(self.columns.iter().map(|c| c.name.as_str())).map_err(|e| e.to_string())?;
        for i in 0..self.n_rows() {
            w.write_record(self.columns.iter().map(|c| match &c.data {
                Data::F64(v) if v[i].is_nan() => String::new(),
                d => d.text(i),
            }))
            .map_err(|e| e.to_string())?;
        }
        w.into_inner().map_err(|e| e.to_string())
    }

    /// ECSV 1.0 with a space delimiter.
    pub fn ecsv_bytes(&self) -> Result<Vec<u8>, String> {
        let mut s = String::from("# %ECSV 1.0\n# ---\n# datatype:\n");
        for c in &self.columns {
            let dt = match c.data {
                Data::F64(_) => "float64",
                Data::I64(_) => "int64",
                Data::Str(_) => "string",
            };
            s.push_str(&format!("# - {{name: {}", yaml_scalar(&c.name)));
            if let Some(u) = &c.unit {
                s.push_str(&format!(", unit: {}", yaml_scalar(u)));
            }
            s.push_str(&format!(", datatype: {dt}"));
            if let Some(d) = &c.description {
                s.push_str(&format!(", description: {}", yaml_scalar(d)));
            }
            s.push_str("}\n");
        }
        if !self.meta.is_empty() {
            s.push_str("# meta: !!omap\n");
            for (k, v) in &self.meta {
                s.push_str(&format!("# - {{{}: {v:?}}}\n", yaml_scalar(k)));
            }
        }
        s.push_str("# schema: astropy-2.0\n");
        let line = |fields: Vec<String>| fields.iter().map(|f| ecsv_field(f)).collect::<Vec<_>>().join(" ") + "\n";
        s.push_str(&line(self.names()));
        for i in 0..self.n_rows() {
            s.push_str(&line(self.columns.iter().map(|c| c.data.text(i)).collect()));
        }
        Ok(s.into_bytes())
    }

    /// VOTable 1.4, TABLEDATA.
    pub fn votable_bytes(&self) -> Result<Vec<u8>, String> {
        let mut s = String::from(
            "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n\
             <VOTABLE version=\"1.4\" xmlns:xsi=\"http://www.w3.org/2001/XMLSchema-instance\" \
             xmlns=\"http://www.ivoa.net/xml/VOTable/v1.3\" \
             xsi:schemaLocation=\"http://www.ivoa.net/xml/VOTable/v1.3 http://www.ivoa.net/xml/VOTable/VOTable-1.4.xsd\">\n\
             <RESOURCE type=\"results\">\n<TABLE>\n",
        );
        for (k, v) in &self.meta {
            s.push_str(&format!("<PARAM name=\"{}\" datatype=\"double\" value=\"{v:?}\"/>\n", xml_escape(k)));
        }
        for c in &self.columns {
            let dt = match c.data {
                Data::F64(_) => "datatype=\"double\"",
                Data::I64(_) => "datatype=\"long\"",
                Data::Str(_) => "datatype=\"char\" arraysize=\"*\"",
            };
            s.push_str(&format!("<FIELD name=\"{}\" {dt}", xml_escape(&c.name)));
            if let Some(u) = &c.unit {
                s.push_str(&format!(" unit=\"{}\"", xml_escape(u)));
            }
            match &c.description {
                Some(d) => s.push_str(&format!(">\n  <DESCRIPTION>{}</DESCRIPTION>\n</FIELD>\n", xml_escape(d))),
                None => s.push_str("/>\n"),
            }
        }
        s.push_str("<DATA>\n<TABLEDATA>\n");
        for i in 0..self.n_rows() {
            s.push_str("<TR>");
            for c in &self.columns {
                let t = match &c.data {
                    Data::F64(v) if v[i].is_nan() => "NaN".to_string(),
                    Data::F64(v) if v[i].is_infinite() => if v[i] > 0.0 { "+Inf" } else { "-Inf" }.to_string(),
                    d => d.text(i),
                };
                s.push_str(&format!("<TD>{}</TD>", xml_escape(&t)));
            }
            s.push_str("</TR>\n");
        }
        s.push_str("</TABLEDATA>\n</DATA>\n</TABLE>\n</RESOURCE>\n</VOTABLE>\n");
        Ok(s.into_bytes())
    }

    fn write_fits_into(&self, f: &mut fitsio::FitsFile, path: &Path) -> Result<(), Error> {
        use fitsio::tables::{ColumnDataType, ColumnDescription};
        let e = |m: String| Error::Write { path: path.into(), message: m };
        let mut descs = Vec::new();
        for c in &self.columns {
            let mut d = ColumnDescription::new(&c.name);
            let d = match &c.data {
                Data::F64(_) => d.with_type(ColumnDataType::Double),
                Data::I64(_) => d.with_type(ColumnDataType::LongLong),
                Data::Str(v) => d
                    .with_type(ColumnDataType::String)
                    .that_repeats(v.iter().map(|s| s.len()).max().unwrap_or(1).max(1)),
            };
            descs.push(d.create().map_err(|x| e(format!("column {}: {x}", c.name)))?);
        }
        let h = f.create_table("CATALOG", &descs).map_err(|x| e(x.to_string()))?;
        for (k, c) in self.columns.iter().enumerate() {
            if let Some(u) = &c.unit {
                h.write_key(f, &format!("TUNIT{}", k + 1), u.as_str()).map_err(|x| e(x.to_string()))?;
            }
            if let Some(d) = &c.description {
                let d: String = d.chars().filter(|c| (' '..='~').contains(c)).take(68).collect();
                h.write_key(f, &format!("TCOMM{}", k + 1), d.as_str()).map_err(|x| e(x.to_string()))?;
            }
            if self.n_rows() == 0 {
                continue;
            }
            match &c.data {
                Data::F64(v) => h.write_col(f, &c.name, v),
                Data::I64(v) => h.write_col(f, &c.name, v),
                Data::Str(v) => h.write_col(f, &c.name, v),
            }
            .map_err(|x| e(format!("column {}: {x}", c.name)))?;
        }
        for (k, v) in &self.meta {
            write_key_exact(f, k, *v).map_err(|x| e(format!("keyword {k}: {x}")))?;
        }
        Ok(())
    }
}

/// A YAML flow scalar: plain when safe, else single-quoted (`'` doubled).
fn yaml_scalar(s: &str) -> String {
    let plain = !s.is_empty()
        && s.chars().all(|c| c.is_ascii_alphanumeric() || "_-./ ()^*+".contains(c))
        && !s.starts_with([' ', '-', '*'])
        && !s.ends_with(' ')
        && s.parse::<f64>().is_err()
        && !["true", "false", "null", "yes", "no", "on", "off", "~"].contains(&s.to_ascii_lowercase().as_str());
    if plain {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', "''"))
    }
}

/// An ECSV data field: quoted (CSV style, `"` doubled) when empty or holding a blank or quote.
fn ecsv_field(s: &str) -> String {
    if s.is_empty() || s.contains([' ', '"', '\t', '\n', ',']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

fn xml_escape(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&apos;"),
            c if (c as u32) < 0x20 && c != '\t' && c != '\n' => o.push(' '),
            c => o.push(c),
        }
    }
    o
}

/// Columns of text typed as in the module docs (integers, numbers with empty = NaN, text).
fn typed(names: Vec<String>, cells: Vec<Vec<String>>) -> Vec<Column> {
    names
        .into_iter()
        .zip(cells)
        .map(|(name, v)| {
            let data = if !v.is_empty() && v.iter().all(|s| s.trim().parse::<i64>().is_ok()) {
                Data::I64(v.iter().map(|s| s.trim().parse().unwrap_or(0)).collect())
            } else if !v.is_empty()
                && v.iter().all(|s| s.trim().is_empty() || s.trim().parse::<f64>().is_ok())
                && v.iter().any(|s| !s.trim().is_empty())
            {
                Data::F64(v.iter().map(|s| s.trim().parse().unwrap_or(f64::NAN)).collect())
            } else {
                Data::Str(v)
            };
            Column { name, unit: None, description: None, data }
        })
        .collect()
}

fn read_text(path: &Path) -> Result<String, Error> {
    std::fs::read_to_string(path).map_err(|e| terr(path, format!("cannot read: {e}")))
}

fn read_csv(path: &Path) -> Result<Table, Error> {
    let text = read_text(path)?;
    let mut rdr = csv::ReaderBuilder::new().comment(Some(b'#')).trim(csv::Trim::All).from_reader(text.as_bytes());
    let names: Vec<String> = rdr
        .headers()
        .map_err(|e| terr(path, format!("cannot read the header row: {e}")))?
        .iter()
        .map(String::from)
        .collect();
    if names.is_empty() || (names.len() == 1 && names[0].is_empty()) {
        // An empty file: a table without columns (its reader names the columns it lacks).
        return Ok(Table::default());
    }
    let mut cells: Vec<Vec<String>> = vec![Vec::new(); names.len()];
    let mut lines = Vec::new();
    for rec in rdr.records() {
        let rec = rec.map_err(|e| terr(path, format!("malformed CSV: {e}")))?;
        for (c, v) in cells.iter_mut().zip(rec.iter()) {
            c.push(v.to_string());
        }
        lines.push(rec.position().map_or(0, |p| p.line()));
    }
    Ok(Table { columns: typed(names, cells), lines, meta: Vec::new() })
}

/// Split one `{k: v, k: 'v, w'}` YAML flow mapping into pairs (quotes honoured).
fn flow_mapping(s: &str) -> Option<Vec<(String, String)>> {
    let inner = s.trim().strip_prefix('{')?.strip_suffix('}')?;
    let mut items = Vec::new();
    let mut cur = String::new();
    let mut quote: Option<char> = None;
    let mut chars = inner.chars().peekable();
    while let Some(c) = chars.next() {
        match (quote, c) {
            (Some('\''), '\'') if chars.peek() == Some(&'\'') => {
                chars.next();
                cur.push_str("''");
            }
            (Some(q), c) if c == q => {
                quote = None;
                cur.push(c);
            }
            (None, '\'' | '"') => {
                quote = Some(c);
                cur.push(c);
            }
            (None, ',') => items.push(std::mem::take(&mut cur)),
            (None, '{' | '[') => return None,
            _ => cur.push(c),
        }
    }
    if quote.is_some() {
        return None;
    }
    if !cur.trim().is_empty() {
        items.push(cur);
    }
    items
        .iter()
        .map(|it| {
            let (k, v) = it.split_once(':')?;
            Some((k.trim().to_string(), yaml_unquote(v.trim())?))
        })
        .collect()
}

fn yaml_unquote(v: &str) -> Option<String> {
    if let Some(x) = v.strip_prefix('\'') {
        Some(x.strip_suffix('\'')?.replace("''", "'"))
    } else if let Some(x) = v.strip_prefix('"') {
        Some(x.strip_suffix('"')?.replace("\\\"", "\"").replace("\\\\", "\\"))
    } else {
        Some(v.to_string())
    }
}

fn read_ecsv(path: &Path) -> Result<Table, Error> {
    let text = read_text(path)?;
    let mut lines = text.lines().enumerate().peekable();
    match lines.peek() {
        Some((_, l)) if l.starts_with("# %ECSV ") => {}
        _ => return Err(terr(path, "not an ECSV file: the first line must be '# %ECSV <version>'")),
    }
    lines.next();
    // The YAML header: every '#' line; the columns are the entries of its `datatype:` list.
    let mut header: Vec<(usize, String)> = Vec::new();
    while let Some((i, l)) = lines.peek() {
        if let Some(h) = l.strip_prefix('#') {
            header.push((*i + 1, h.strip_prefix(' ').unwrap_or(h).to_string()));
            lines.next();
        } else {
            break;
        }
    }
    let mut entries: Vec<(usize, String)> = Vec::new();
    let mut delimiter = b' ';
    let (mut in_dt, mut in_meta) = (false, false);
    // The header's `meta` mapping: its numeric entries (`- {KEY: 1.5}` as astropy writes an
    // ordered map, or `KEY: 1.5` lines of a block mapping); others are not this reader's.
    let mut table_meta: Vec<(String, f64)> = Vec::new();
    for (ln, h) in &header {
        if h.trim() == "---" || h.trim().is_empty() {
            continue;
        }
        let top = !h.starts_with(' ') && !h.starts_with('-');
        if !top && in_meta {
            // An entry of the ordered map (`- {KEY: 1.5}`) or a line of a block mapping
            // (`KEY: 1.5`), read as the column entries' flow mappings are.
            let item = h.trim().trim_start_matches("- ").trim();
            let pairs = if item.starts_with('{') { flow_mapping(item) } else { flow_mapping(&format!("{{{item}}}")) };
            for (k, v) in pairs.into_iter().flatten() {
                if let (Some(k), Ok(v)) = (yaml_unquote(&k), v.parse::<f64>()) {
                    table_meta.push((k, v));
                }
            }
            continue;
        }
        if top {
            in_dt = h.trim_end() == "datatype:";
            in_meta = h.starts_with("meta:");
            if let Some(d) = h.strip_prefix("delimiter:") {
                delimiter = match yaml_unquote(d.trim()).as_deref() {
                    Some(",") => b',',
                    Some(" ") => b' ',
                    _ => return Err(terr(path, format!("line {ln}: ECSV delimiter must be ' ' or ','"))),
                };
            }
            continue;
        }
        if !in_dt {
            continue;
        }
        if let Some(e) = h.strip_prefix("- ") {
            entries.push((*ln, e.to_string()));
        } else if let Some(last) = entries.last_mut() {
            // A continuation of a long entry (YAML folds long flow mappings over lines), or a
            // block-style mapping's next key.
            last.1.push(if last.1.trim_start().starts_with('{') { ' ' } else { '\n' });
            last.1.push_str(h.trim());
        }
    }
    if entries.is_empty() {
        return Err(terr(path, "the ECSV header has no 'datatype:' column list"));
    }
    let mut meta = Vec::new();
    for (ln, e) in &entries {
        let pairs = if e.trim_start().starts_with('{') {
            flow_mapping(e)
        } else {
            e.lines()
                .map(|l| l.split_once(':').and_then(|(k, v)| Some((k.trim().to_string(), yaml_unquote(v.trim())?))))
                .collect()
        }
        .ok_or_else(|| terr(path, format!("line {ln}: cannot read the column entry '{e}'")))?;
        let get = |k: &str| pairs.iter().find(|(a, _)| a == k).map(|(_, b)| b.clone());
        let name = get("name").ok_or_else(|| terr(path, format!("line {ln}: a column entry has no name")))?;
        let dt = get("datatype").unwrap_or_else(|| "string".into());
        if get("subtype").is_some() {
            return Err(terr(
                path,
                format!("line {ln}: column '{name}' has a subtype (arrays or objects): not supported"),
            ));
        }
        meta.push((*ln, name, dt, get("unit"), get("description")));
    }
    let body = lines.map(|(_, l)| l).collect::<Vec<_>>().join("\n");
    let mut rdr =
        csv::ReaderBuilder::new().delimiter(delimiter).has_headers(false).flexible(true).from_reader(body.as_bytes());
    let first_data_line = header.last().map_or(1, |h| h.0) + 1;
    let mut records = rdr.records();
    let names: Vec<String> = match records.next() {
        Some(r) => r.map_err(|e| terr(path, format!("malformed ECSV: {e}")))?.iter().map(String::from).collect(),
        None => return Err(terr(path, "no column-name row after the ECSV header")),
    };
    let expected: Vec<&String> = meta.iter().map(|m| &m.1).collect();
    if names.iter().collect::<Vec<_>>() != expected {
        return Err(terr(
            path,
            format!(
                "line {first_data_line}: the column names ({}) differ from the header's ({})",
                names.join(" "),
                meta.iter().map(|m| m.1.as_str()).collect::<Vec<_>>().join(" ")
            ),
        ));
    }
    let mut cells: Vec<Vec<String>> = vec![Vec::new(); names.len()];
    let mut src_lines = Vec::new();
    for rec in records {
        let rec = rec.map_err(|e| terr(path, format!("malformed ECSV: {e}")))?;
        let line = rec.position().map_or(0, |p| p.line()) + first_data_line as u64 - 1;
        if rec.len() != names.len() {
            return Err(terr(
                path,
                format!("line {line}: {} fields, the header has {} columns", rec.len(), names.len()),
            ));
        }
        for (c, v) in cells.iter_mut().zip(rec.iter()) {
            c.push(v.to_string());
        }
        src_lines.push(line);
    }
    let mut columns = Vec::new();
    for ((ln, name, dt, unit, description), v) in meta.into_iter().zip(cells) {
        let bad = |i: usize, s: &str| {
            terr(
                path,
                format!("line {}: column '{name}' = '{s}' is not a {dt}", src_lines.get(i).copied().unwrap_or(0)),
            )
        };
        let kind = match dt.as_str() {
            "float16" | "float32" | "float64" | "float128" => Kind::Float,
            "int8" | "int16" | "int32" | "int64" | "uint8" | "uint16" | "uint32" | "uint64" => Kind::Int,
            "bool" => Kind::Bool,
            "string" => Kind::Text,
            other => {
                return Err(terr(path, format!("line {ln}: column '{name}' has datatype '{other}': not supported")))
            }
        };
        let num = |i: usize, s: &str| if s.is_empty() { Ok(f64::NAN) } else { s.parse().map_err(|_| bad(i, s)) };
        let data = cells_to_data(v, kind, num, bad)?;
        columns.push(Column { name, unit, description, data });
    }
    Ok(Table { columns, lines: src_lines, meta: table_meta })
}

/// What a column's declared type makes of its text cells.
#[derive(Clone, Copy)]
enum Kind {
    Float,
    Int,
    Bool,
    Text,
}

/// The text cells of one column as `kind`: `num` parses a float cell in the format's spellings
/// (empty = missing = NaN), `bad(row, cell)` is the error for a cell that is not of the type.
/// Integers with a missing cell become floats with NaN there.
fn cells_to_data(
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

fn read_votable(path: &Path) -> Result<Table, Error> {
    use quick_xml::events::Event;
    let text = read_text(path)?;
    let mut r = quick_xml::Reader::from_str(&text);
    let xerr = |e: &dyn std::fmt::Display, pos: u64| terr(path, format!("malformed VOTable XML near byte {pos}: {e}"));
    struct Field {
        name: String,
        datatype: String,
        unit: Option<String>,
        description: Option<String>,
    }
    let mut fields: Vec<Field> = Vec::new();
    let mut rows: Vec<Vec<String>> = Vec::new();
    // The table's numeric PARAMs (Table::meta); a PARAM's own DESCRIPTION is not a FIELD's.
    let mut params: Vec<(String, f64)> = Vec::new();
    let mut in_param = false;
    let (mut in_table, mut seen_table, mut in_desc, mut in_td, mut in_tabledata) = (false, false, false, false, false);
    let mut td = String::new();
    let mut desc = String::new();
    loop {
        let pos = r.buffer_position();
        let ev = r.read_event().map_err(|e| xerr(&e, pos))?;
        let (start, empty) = match &ev {
            Event::Start(e) => (Some(e.clone()), false),
            Event::Empty(e) => (Some(e.clone()), true),
            _ => (None, false),
        };
        if let Some(e) = start {
            let tag = String::from_utf8_lossy(e.local_name().as_ref()).to_string();
            let attr = |k: &str| -> Result<Option<String>, Error> {
                for a in e.attributes() {
                    let a = a.map_err(|x| xerr(&x, pos))?;
                    if a.key.local_name().as_ref() == k.as_bytes() {
                        return Ok(Some(a.unescape_value().map_err(|x| xerr(&x, pos))?.to_string()));
                    }
                }
                Ok(None)
            };
            match tag.as_str() {
                "TABLE" if !seen_table => {
                    in_table = !empty;
                    seen_table = true;
                }
                "FIELD" if in_table => {
                    let name = attr("name")?.or(attr("ID")?).ok_or_else(|| terr(path, "a FIELD has no name"))?;
                    let datatype = attr("datatype")?.ok_or_else(|| terr(path, format!("FIELD '{name}' has no datatype")))?;
                    let arr = attr("arraysize")?;
                    let is_char = datatype == "char" || datatype == "unicodeChar";
                    if arr.is_some() && !is_char && arr.as_deref() != Some("1") {
                        return Err(terr(path, format!("FIELD '{name}' is an array (arraysize {}): not supported", arr.unwrap_or_default())));
                    }
                    fields.push(Field { name, datatype, unit: attr("unit")?, description: None });
                }
                "PARAM" if in_table => {
                    if let (Some(n), Some(v)) = (attr("name")?, attr("value")?) {
                        if let Ok(x) = v.trim().parse::<f64>() {
                            params.push((n, x));
                        }
                    }
                    in_param = !empty;
                }
                "DESCRIPTION" if in_table && !in_param && !empty => {
                    in_desc = true;
                    desc.clear();
                }
                "BINARY" | "BINARY2" | "FITS" if in_table => {
                    return Err(terr(
                        path,
                        format!("VOTable serialization {tag} is not supported: write it as TABLEDATA (astropy: tabledata_format='tabledata')"),
                    ))
                }
                "TABLEDATA" if in_table => in_tabledata = !empty,
                "TR" if in_tabledata => rows.push(Vec::new()),
                "TD" if in_tabledata => {
                    td.clear();
                    if empty {
                        if let Some(row) = rows.last_mut() {
                            row.push(String::new());
                        }
                    } else {
                        in_td = true;
                    }
                }
                _ => {}
            }
            continue;
        }
        match ev {
            Event::Text(t) if in_td || in_desc => {
                let s = t.unescape().map_err(|x| xerr(&x, pos))?;
                if in_td {
                    td.push_str(&s)
                } else {
                    desc.push_str(&s)
                }
            }
            Event::CData(t) if in_td => td.push_str(&String::from_utf8_lossy(&t)),
            Event::End(e) => match e.local_name().as_ref() {
                b"TD" if in_td => {
                    in_td = false;
                    if let Some(row) = rows.last_mut() {
                        row.push(std::mem::take(&mut td));
                    }
                }
                b"DESCRIPTION" if in_desc => {
                    in_desc = false;
                    if let Some(f) = fields.last_mut() {
                        f.description = Some(desc.trim().to_string());
                    }
                }
                b"PARAM" => in_param = false,
                b"TABLEDATA" => in_tabledata = false,
                b"TABLE" => in_table = false,
                _ => {}
            },
            Event::Eof => break,
            _ => {}
        }
    }
    if !seen_table {
        return Err(terr(path, "no TABLE element: is this a VOTable?"));
    }
    if fields.is_empty() {
        return Err(terr(path, "the VOTable's first TABLE has no FIELD"));
    }
    let mut cells: Vec<Vec<String>> = vec![Vec::with_capacity(rows.len()); fields.len()];
    for (i, row) in rows.iter().enumerate() {
        if row.len() != fields.len() {
            return Err(terr(
                path,
                format!("row {}: {} TD cells, the table has {} FIELDs", i + 1, row.len(), fields.len()),
            ));
        }
        for (c, v) in cells.iter_mut().zip(row) {
            c.push(v.trim().to_string());
        }
    }
    let mut columns = Vec::new();
    for (f, v) in fields.into_iter().zip(cells) {
        let bad = |i: usize, s: &str| {
            terr(path, format!("row {}: FIELD '{}' = '{s}' is not a {}", i + 1, f.name, f.datatype))
        };
        let num = |i: usize, s: &str| -> Result<f64, Error> {
            match s {
                "" | "NaN" | "nan" => Ok(f64::NAN),
                "+Inf" | "Inf" | "inf" => Ok(f64::INFINITY),
                "-Inf" | "-inf" => Ok(f64::NEG_INFINITY),
                s => s.parse().map_err(|_| bad(i, s)),
            }
        };
        let kind = match f.datatype.as_str() {
            "double" | "float" => Kind::Float,
            "long" | "int" | "short" | "unsignedByte" => Kind::Int,
            "boolean" => Kind::Bool,
            "char" | "unicodeChar" => Kind::Text,
            other => return Err(terr(path, format!("FIELD '{}' has datatype '{other}': not supported", f.name))),
        };
        let data = cells_to_data(v, kind, num, bad)?;
        columns.push(Column { name: f.name, unit: f.unit, description: f.description, data });
    }
    Ok(Table { meta: params, ..Table::new(columns) })
}

/// The table HDU `name`, or the first table HDU, with its column descriptions and row count.
pub fn fits_table_hdu(
    f: &mut fitsio::FitsFile,
    name: Option<&str>,
    path: &Path,
) -> Result<(fitsio::hdu::FitsHdu, Vec<fitsio::tables::ConcreteColumnDescription>, usize), Error> {
    use fitsio::hdu::HduInfo;
    let hdu = match name {
        Some(n) => f.hdu(n).map_err(|_| terr(path, format!("no HDU named '{n}'")))?,
        None => {
            let n_hdu = f.iter().count();
            let mut found = None;
            for i in 0..n_hdu {
                let h = f.hdu(i).map_err(|e| terr(path, format!("HDU {i}: {e}")))?;
                if matches!(h.info, HduInfo::TableInfo { .. }) {
                    found = Some(h);
                    break;
                }
            }
            found.ok_or_else(|| terr(path, "no table HDU (a FITS catalog needs a binary table)"))?
        }
    };
    match &hdu.info {
        HduInfo::TableInfo { column_descriptions, num_rows } => {
            let (c, n) = (column_descriptions.clone(), *num_rows);
            Ok((hdu, c, n))
        }
        _ => Err(terr(path, format!("HDU '{}' is not a table", name.unwrap_or("?")))),
    }
}

/// A string column through CFITSIO with a buffer one byte longer than the field (fitsio 0.21's
/// own string reader writes its terminating NUL one byte past its buffer).
fn read_fits_strings(f: &mut fitsio::FitsFile, col: usize, width: usize, n: usize) -> Result<Vec<String>, String> {
    let mut bufs: Vec<Vec<std::os::raw::c_char>> = (0..n).map(|_| vec![0; width + 1]).collect();
    let mut ptrs: Vec<*mut std::os::raw::c_char> = bufs.iter_mut().map(|b| b.as_mut_ptr()).collect();
    let mut status = 0;
    let nul = std::ffi::CString::new("").expect("no NUL");
    if n > 0 {
        // SAFETY: the current HDU is the table; `ptrs` holds n buffers of width+1 bytes, the
        // most CFITSIO writes for a width-character field and its NUL.
        unsafe {
            fitsio::sys::ffgcvs(
                f.as_raw(),
                col as i32 + 1,
                1,
                1,
                n as i64,
                nul.as_ptr() as *mut _,
                ptrs.as_mut_ptr(),
                std::ptr::null_mut(),
                &mut status,
            );
        }
    }
    if status != 0 {
        return Err(format!("CFITSIO status {status}"));
    }
    Ok(bufs
        .iter()
        .map(|b| {
            let bytes: Vec<u8> = b.iter().take_while(|&&c| c != 0).map(|&c| c as u8).collect();
            String::from_utf8_lossy(&bytes).trim_end().to_string()
        })
        .collect())
}

fn read_fits(path: &Path, name: Option<&str>) -> Result<Table, Error> {
    use fitsio::tables::ColumnDataType as T;
    let mut f = fitsio::FitsFile::open(path).map_err(|e| terr(path, format!("cannot open as FITS: {e}")))?;
    let (hdu, descs, n) = fits_table_hdu(&mut f, name, path)?;
    let mut columns = Vec::new();
    for (k, d) in descs.iter().enumerate() {
        let cerr = |e: &dyn std::fmt::Display| terr(path, format!("column '{}': {e}", d.name));
        let unit = crate::io::read_key_str(&mut f, &hdu, &format!("TUNIT{}", k + 1)).ok().filter(|u| !u.is_empty());
        let description =
            crate::io::read_key_str(&mut f, &hdu, &format!("TCOMM{}", k + 1)).ok().filter(|u| !u.is_empty());
        let rep = d.data_type.repeat;
        let data = match d.data_type.typ {
            T::String => {
                // Make the table the current HDU for the raw call.
                let mut st = 0;
                let mut ty = 0;
                // SAFETY: an open file; a valid HDU number.
                unsafe { fitsio::sys::ffmahd(f.as_raw(), hdu.number as i32 + 1, &mut ty, &mut st) };
                Data::Str(read_fits_strings(&mut f, k, rep.max(1), n).map_err(|e| cerr(&e))?)
            }
            _ if rep != 1 => {
                return Err(terr(
                    path,
                    format!("column '{}' is a vector ({rep} values per row): not supported", d.name),
                ))
            }
            T::Float | T::Double => Data::F64(hdu.read_col::<f64>(&mut f, &d.name).map_err(|e| cerr(&e))?),
            T::Bit | T::Logical => {
                return Err(terr(path, format!("column '{}' is a bit or logical column: not supported", d.name)))
            }
            _ => Data::I64(hdu.read_col::<i64>(&mut f, &d.name).map_err(|e| cerr(&e))?),
        };
        columns.push(Column { name: d.name.clone(), unit, description, data });
    }
    let meta =
        fits_table_numbers(&mut f, &hdu).map_err(|e| terr(path, format!("reading the table's keywords: {e}")))?;
    Ok(Table { meta, ..Table::new(columns) })
}

/// A number as a keyword of the current HDU with 17 significant digits, so that it reads back
/// to the bit (fitsio's `write_key` keeps 15).
fn write_key_exact(f: &mut fitsio::FitsFile, name: &str, v: f64) -> Result<(), String> {
    let key = std::ffi::CString::new(name).map_err(|x| x.to_string())?;
    let mut st = 0;
    // SAFETY: an open file positioned on the table HDU just created; a NUL-terminated name; a
    // null comment is allowed.
    unsafe { fitsio::sys::ffpkyd(f.as_raw(), key.as_ptr(), v, -17, std::ptr::null_mut(), &mut st) };
    if st == 0 {
        Ok(())
    } else {
        Err(format!("CFITSIO status {st}"))
    }
}

/// The numeric keywords of a table HDU other than the ones that describe its columns and
/// layout ([`Table::meta`]).
fn fits_table_numbers(f: &mut fitsio::FitsFile, hdu: &fitsio::hdu::FitsHdu) -> Result<Vec<(String, f64)>, String> {
    use std::ffi::CStr;
    let mut st = 0;
    let mut ty = 0;
    // SAFETY: an open file; a valid HDU number.
    unsafe { fitsio::sys::ffmahd(f.as_raw(), hdu.number as i32 + 1, &mut ty, &mut st) };
    let (mut nkeys, mut more) = (0, 0);
    // SAFETY: an open file positioned on the HDU; out-parameters of the right types.
    unsafe { fitsio::sys::ffghsp(f.as_raw(), &mut nkeys, &mut more, &mut st) };
    if st != 0 {
        return Err(format!("CFITSIO status {st}"));
    }
    let structural = |k: &str| {
        matches!(k, "XTENSION" | "BITPIX" | "PCOUNT" | "GCOUNT" | "TFIELDS" | "THEAP" | "EXTVER" | "EXTLEVEL")
            || k.starts_with("NAXIS")
            || ["TTYPE", "TFORM", "TUNIT", "TCOMM", "TNULL", "TDISP", "TSCAL", "TZERO", "TDIM"]
                .iter()
                .any(|p| k.strip_prefix(p).is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit())))
    };
    let mut out = Vec::new();
    for i in 1..=nkeys {
        let mut name = [0 as std::os::raw::c_char; 80];
        let mut value = [0 as std::os::raw::c_char; 80];
        let mut comment = [0 as std::os::raw::c_char; 80];
        // SAFETY: buffers of FLEN_KEYWORD/FLEN_VALUE/FLEN_COMMENT (<= 80) characters.
        unsafe {
            fitsio::sys::ffgkyn(f.as_raw(), i, name.as_mut_ptr(), value.as_mut_ptr(), comment.as_mut_ptr(), &mut st)
        };
        if st != 0 {
            return Err(format!("CFITSIO status {st} at keyword {i}"));
        }
        // SAFETY: CFITSIO wrote NUL-terminated strings.
        let (k, v) = unsafe { (CStr::from_ptr(name.as_ptr()), CStr::from_ptr(value.as_ptr())) };
        let (k, v) = (k.to_string_lossy().into_owned(), v.to_string_lossy().replace(['D', 'd'], "E"));
        if k.is_empty() || structural(&k) {
            continue;
        }
        if let Ok(x) = v.trim().parse::<f64>() {
            if x.is_finite() {
                out.push((k, x));
            }
        }
    }
    Ok(out)
}
