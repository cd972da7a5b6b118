//! astropy's Enhanced CSV 1.0: a YAML header (read by the small flow-mapping reader here,
//! enough for what astropy writes for a plain table) and space-delimited rows.

use super::model::{cells_to_data, read_text, terr, Column, Data, Kind, Table};
use crate::Error;
use std::path::Path;

impl Table {
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
        let product = self.product_pairs();
        if !self.meta.is_empty() || !product.is_empty() {
            s.push_str("# meta: !!omap\n");
            // What the rows are, as quoted text (a product's numbers are read back from it).
            for (k, v) in &product {
                s.push_str(&format!("# - {{{}: '{}'}}\n", yaml_scalar(k), v.replace('\'', "''")));
            }
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

pub(super) fn read_ecsv(path: &Path) -> Result<Table, Error> {
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
    let Header { delimiter, meta, table_meta, product_pairs } = parse_header(path, &header)?;
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
    let product = crate::provenance::Product::from_pairs(product_pairs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
        .map_err(|m| terr(path, format!("its meta: {m}")))?;
    Ok(Table { columns, lines: src_lines, meta: table_meta, product })
}

/// A column as the ECSV header declares it: its header line, name, datatype, unit and
/// description.
type ColumnEntry = (usize, String, String, Option<String>, Option<String>);

/// What the ECSV header says: the delimiter, the columns, the numeric entries of its `meta`
/// mapping and the provenance pairs among them.
struct Header {
    delimiter: u8,
    meta: Vec<ColumnEntry>,
    table_meta: Vec<(String, f64)>,
    product_pairs: Vec<(String, String)>,
}

/// The YAML header's lines (with their line numbers, '#' taken off): the columns are the
/// entries of its `datatype:` list; arrays and objects (a `subtype`) are refused.
fn parse_header(path: &Path, header: &[(usize, String)]) -> Result<Header, Error> {
    let mut entries: Vec<(usize, String)> = Vec::new();
    let mut delimiter = b' ';
    let (mut in_dt, mut in_meta) = (false, false);
    // The header's `meta` mapping: its numeric entries (`- {KEY: 1.5}` as astropy writes an
    // ordered map, or `KEY: 1.5` lines of a block mapping); others are not this reader's.
    let mut table_meta: Vec<(String, f64)> = Vec::new();
    let mut product_pairs: Vec<(String, String)> = Vec::new();
    for (ln, h) in header {
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
                let Some(k) = yaml_unquote(&k) else { continue };
                if crate::provenance::Product::is_key(&k) {
                    product_pairs.push((k, yaml_unquote(v.trim()).unwrap_or_default()));
                } else if let Ok(v) = v.parse::<f64>() {
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
    Ok(Header { delimiter, meta, table_meta, product_pairs })
}
