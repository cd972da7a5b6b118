//! IVOA VOTable 1.4 tables in the `TABLEDATA` serialization.

use super::model::{cells_to_data, read_text, terr, Column, Data, Kind, Table};
use crate::Error;
use std::path::Path;

impl Table {
    /// VOTable 1.4, TABLEDATA.
    pub fn votable_bytes(&self) -> Result<Vec<u8>, String> {
        let mut s = String::from(
            "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n\
             <VOTABLE version=\"1.4\" xmlns:xsi=\"http://www.w3.org/2001/XMLSchema-instance\" \
             xmlns=\"http://www.ivoa.net/xml/VOTable/v1.3\" \
             xsi:schemaLocation=\"http://www.ivoa.net/xml/VOTable/v1.3 http://www.ivoa.net/xml/VOTable/VOTable-1.4.xsd\">\n\
             <RESOURCE type=\"results\">\n<TABLE>\n",
        );
        for (k, v) in self.product_pairs() {
            s.push_str(&format!(
                "<PARAM name=\"{}\" datatype=\"char\" arraysize=\"*\" value=\"{}\"/>\n",
                xml_escape(&k),
                xml_escape(&v)
            ));
        }
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

pub(super) fn read_votable(path: &Path) -> Result<Table, Error> {
    let text = read_text(path)?;
    let Parsed { fields, rows, params, product_pairs } = parse(path, &text)?;
    let columns = columns_of(path, fields, rows)?;
    let product = crate::provenance::Product::from_pairs(product_pairs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
        .map_err(|m| terr(path, format!("its PARAMs: {m}")))?;
    Ok(Table { meta: params, product, ..Table::new(columns) })
}

/// A FIELD of the VOTable: a column's name, datatype, unit and description.
struct Field {
    name: String,
    datatype: String,
    unit: Option<String>,
    description: Option<String>,
}

/// What the first TABLE holds, as read: its FIELDs, its rows' TD cells as text, its numeric
/// PARAMs and the PARAMs of its product's provenance.
struct Parsed {
    fields: Vec<Field>,
    rows: Vec<Vec<String>>,
    params: Vec<(String, f64)>,
    product_pairs: Vec<(String, String)>,
}

/// The first TABLE of the VOTable `text` (read from `path`), as TABLEDATA; other
/// serializations and array FIELDs are refused.
fn parse(path: &Path, text: &str) -> Result<Parsed, Error> {
    use quick_xml::events::Event;
    let mut r = quick_xml::Reader::from_str(text);
    let xerr = |e: &dyn std::fmt::Display, pos: u64| terr(path, format!("malformed VOTable XML near byte {pos}: {e}"));
    let mut fields: Vec<Field> = Vec::new();
    let mut rows: Vec<Vec<String>> = Vec::new();
    // The table's numeric PARAMs (Table::meta); a PARAM's own DESCRIPTION is not a FIELD's.
    let mut params: Vec<(String, f64)> = Vec::new();
    let mut product_pairs: Vec<(String, String)> = Vec::new();
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
                        if crate::provenance::Product::is_key(&n) {
                            product_pairs.push((n, v));
                        } else if let Ok(x) = v.trim().parse::<f64>() {
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
    Ok(Parsed { fields, rows, params, product_pairs })
}

/// The table's columns: each FIELD's cells, one per row, as data of its datatype.
fn columns_of(path: &Path, fields: Vec<Field>, rows: Vec<Vec<String>>) -> Result<Vec<Column>, Error> {
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
    Ok(columns)
}
