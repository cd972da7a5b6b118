//! CSV tables: one header row, comma-separated, `#` lines comments; columns typed by their
//! fields (module docs of `table`).

use super::model::{read_text, terr, Column, Data, Table};
use crate::Error;
use std::path::Path;

impl Table {
    /// CSV: a header row and one row per record; NaN as an empty field (what spreadsheets and
    /// pandas read as missing).
    pub fn csv_bytes(&self) -> Result<Vec<u8>, String> {
        // What the rows are, as `# KEY = value` comment lines before the header (readers that
        // skip `#` lines, as pandas' `comment='#'` and astropy's do, see the plain table).
        let mut head = String::new();
        for (k, v) in self.product_pairs() {
            head.push_str(&format!("# {k} = {v}\n"));
        }
        let mut w = csv::Writer::from_writer(head.into_bytes());
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

pub(super) fn read_csv(path: &Path) -> Result<Table, Error> {
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
    let product = crate::provenance::Product::from_pairs(comment_pairs(&text))
        .map_err(|m| terr(path, format!("its product comment lines: {m}")))?;
    Ok(Table { columns: typed(names, cells), lines, meta: Vec::new(), product })
}

/// The `# KEY = value` comment lines before a CSV table's header row.
fn comment_pairs(text: &str) -> Vec<(&str, &str)> {
    text.lines()
        .map(str::trim_start)
        .take_while(|l| l.starts_with('#') || l.is_empty())
        .filter_map(|l| l.trim_start_matches('#').split_once('='))
        .map(|(k, v)| (k.trim(), v.trim()))
        .collect()
}
