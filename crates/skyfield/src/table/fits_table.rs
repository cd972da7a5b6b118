//! FITS binary tables: the first table HDU or a named one, units in `TUNITn`, descriptions in
//! `TCOMMn`, table-level numbers as keywords written to 17 significant digits.

use super::model::{terr, Column, Data, Table};
use crate::Error;
use std::path::Path;

impl Table {
    pub(super) fn write_fits_into(&self, f: &mut fitsio::FitsFile, path: &Path) -> Result<(), Error> {
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
        for (k, v) in self.product_pairs() {
            // What the rows are: numbers as numbers, names as strings.
            match k.as_str() {
                "WAVELEN" | "HWPZERO" | "PIXSCALE" => match v.parse::<f64>() {
                    Ok(x) => write_key_exact(f, &k, x),
                    Err(_) => Err(format!("not a number: {v}")),
                },
                _ => h.write_key(f, &k, v.as_str()).map_err(|x| x.to_string()),
            }
            .map_err(|x| e(format!("keyword {k}: {x}")))?;
        }
        for (k, v) in &self.meta {
            write_key_exact(f, k, *v).map_err(|x| e(format!("keyword {k}: {x}")))?;
        }
        Ok(())
    }
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

/// Write `path` as a copy of the FITS file `input` with `columns` appended to its table HDU
/// `hdu` (or its first table HDU): every HDU, header keyword and column of the input is kept
/// byte for byte, the run's provenance is stamped in the primary header. Atomic as
/// [`Table::write`]: the copy is edited in a temporary file beside `path` and renamed onto it
/// once closed, so a failed write leaves no file.
///
/// Each column must have one value per row of the table. The new columns get a name and a type
/// (`TTYPEn`, `TFORMn`), not `TUNITn`/`TCOMMn`: floats are written as 64-bit (`D`), integers as
/// 32-bit (`J`) when every value fits and 64-bit (`K`) otherwise, text as fixed-width strings.
/// `keys`: string keywords set on the table HDU, replacing one of the same name (a product's
/// `MISMATCH` when the correction allowed one).
pub fn append_fits_columns(
    input: &Path,
    hdu: Option<&str>,
    columns: &[Column],
    keys: &[(String, String)],
    path: &Path,
) -> Result<(), Error> {
    use fitsio::tables::{ColumnDataType as T, ColumnDescription};
    let werr = |m: String| Error::Write { path: path.into(), message: m };
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let tmp = crate::fits::temp_beside(path, ".fits.tmp")
        .map_err(|e| werr(format!("cannot create a temporary file in {}: {e}", dir.display())))?
        .into_temp_path();
    std::fs::copy(input, &tmp).map_err(|e| werr(format!("cannot copy {}: {e}", input.display())))?;
    let mut f = fitsio::FitsFile::edit(&tmp).map_err(|e| werr(e.to_string()))?;
    let (mut t, _, n_rows) = fits_table_hdu(&mut f, hdu, input)?;
    for c in columns {
        if c.data.len() != n_rows {
            return Err(terr(input, format!("column '{}' has {} values for {n_rows} rows", c.name, c.data.len())));
        }
        let narrow: Option<Vec<i32>> = match &c.data {
            Data::I64(v) => v.iter().map(|&x| i32::try_from(x).ok()).collect(),
            _ => None,
        };
        let mut d = ColumnDescription::new(&c.name);
        let d = match (&c.data, &narrow) {
            (Data::F64(_), _) => d.with_type(T::Double),
            (Data::I64(_), Some(_)) => d.with_type(T::Int),
            (Data::I64(_), None) => d.with_type(T::LongLong),
            (Data::Str(v), _) => {
                d.with_type(T::String).that_repeats(v.iter().map(|s| s.len()).max().unwrap_or(1).max(1))
            }
        };
        let d = d.create().map_err(|e| werr(e.to_string()))?;
        t = t.append_column(&mut f, &d).map_err(|e| werr(format!("adding column {}: {e}", c.name)))?;
        match (&c.data, &narrow) {
            (Data::F64(v), _) => t.write_col(&mut f, &c.name, v),
            (Data::I64(_), Some(v)) => t.write_col(&mut f, &c.name, v),
            (Data::I64(v), None) => t.write_col(&mut f, &c.name, v),
            (Data::Str(v), _) => t.write_col(&mut f, &c.name, v),
        }
        .map_err(|e| werr(format!("writing column {}: {e}", c.name)))?;
    }
    for (k, v) in keys {
        update_key_str(&mut f, k, v).map_err(|e| werr(format!("keyword {k}: {e}")))?;
    }
    crate::provenance::stamp(&mut f).map_err(werr)?;
    // Closed explicitly: CFITSIO flushes its buffers here and a full disk must fail the write.
    crate::durable::close_fits(f).map_err(werr)?;
    crate::durable::finish(tmp, path).map_err(|e| werr(e.to_string()))
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

pub(super) fn read_fits(path: &Path, name: Option<&str>) -> Result<Table, Error> {
    use fitsio::tables::ColumnDataType as T;
    let mut f = fitsio::FitsFile::open(path).map_err(|e| terr(path, format!("cannot open as FITS: {e}")))?;
    let (hdu, descs, n) = fits_table_hdu(&mut f, name, path)?;
    let mut columns = Vec::new();
    for (k, d) in descs.iter().enumerate() {
        let cerr = |e: &dyn std::fmt::Display| terr(path, format!("column '{}': {e}", d.name));
        let unit = crate::fits::read_key_str(&mut f, &hdu, &format!("TUNIT{}", k + 1)).ok().filter(|u| !u.is_empty());
        let description =
            crate::fits::read_key_str(&mut f, &hdu, &format!("TCOMM{}", k + 1)).ok().filter(|u| !u.is_empty());
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
    let (meta, pairs) =
        fits_table_numbers(&mut f, &hdu).map_err(|e| terr(path, format!("reading the table's keywords: {e}")))?;
    let product = crate::provenance::Product::from_pairs(pairs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
        .map_err(|m| terr(path, format!("its keywords: {m}")))?;
    Ok(Table { meta, product, ..Table::new(columns) })
}

/// A number as a keyword of the current HDU with 17 significant digits, so that it reads back
/// to the bit (fitsio's `write_key` keeps 15).
/// Set string keyword `name` of the current HDU to `v`, replacing one of that name (CFITSIO's
/// update, where `write_key` would add a second).
fn update_key_str(f: &mut fitsio::FitsFile, name: &str, v: &str) -> Result<(), String> {
    let key = std::ffi::CString::new(name).map_err(|x| x.to_string())?;
    let val = std::ffi::CString::new(v).map_err(|x| x.to_string())?;
    let mut st = 0;
    // SAFETY: an open file positioned on the table HDU; NUL-terminated name and value; a null
    // comment keeps the existing one (or none).
    unsafe { fitsio::sys::ffukys(f.as_raw(), key.as_ptr(), val.as_ptr() as *mut _, std::ptr::null_mut(), &mut st) };
    if st == 0 {
        Ok(())
    } else {
        Err(format!("CFITSIO status {st}"))
    }
}

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
/// layout ([`Table::meta`]), and apart the keywords of what its rows are
/// ([`crate::provenance::Product`]) with their values as text.
type Numbers = Vec<(String, f64)>;
type Pairs = Vec<(String, String)>;

/// The keywords of a [`crate::provenance::Product`] in any HDU of `f` (a Stokes map's primary
/// header), with their values as text, as a table's are read.
pub(crate) fn header_product_pairs(f: &mut fitsio::FitsFile, hdu: &fitsio::hdu::FitsHdu) -> Result<Pairs, String> {
    fits_table_numbers(f, hdu).map(|(_, pairs)| pairs)
}

/// The product a FITS header records (any HDU of `f`: a map's or a calibration file's primary
/// header, a table's), read as a table's keywords are
/// ([`crate::provenance::Product::from_pairs`]); `None` when it records none. The error says
/// which keyword did not parse.
pub fn product_of_header(
    f: &mut fitsio::FitsFile,
    hdu: &fitsio::hdu::FitsHdu,
) -> Result<Option<crate::provenance::Product>, String> {
    let pairs = header_product_pairs(f, hdu)?;
    crate::provenance::Product::from_pairs(pairs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
}

fn fits_table_numbers(f: &mut fitsio::FitsFile, hdu: &fitsio::hdu::FitsHdu) -> Result<(Numbers, Pairs), String> {
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
    let mut pairs = Vec::new();
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
        let k = k.to_string_lossy().into_owned();
        if k.is_empty() || structural(&k) {
            continue;
        }
        if crate::provenance::Product::is_key(&k) {
            let raw = v.to_string_lossy();
            let text = raw
                .trim()
                .strip_prefix('\'')
                .and_then(|s| s.strip_suffix('\''))
                .map(|s| s.trim_end().replace("''", "'"));
            pairs.push((k, text.unwrap_or_else(|| raw.trim().replace(['D', 'd'], "E"))));
            continue;
        }
        let v = v.to_string_lossy().replace(['D', 'd'], "E");
        if let Ok(x) = v.trim().parse::<f64>() {
            if x.is_finite() {
                out.push((k, x));
            }
        }
    }
    Ok((out, pairs))
}
