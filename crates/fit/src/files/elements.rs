//! Several field elements in one calibration file, in the order light meets them: the file's
//! own model (a field model of `M_I(p, phi)` or a Mueller field, named by `IP MODEL`) and
//! others beside it, such as a stressed lens measured on its own (`docs/calibration-file.md`,
//! "Several field elements"). The correction builds its `field::FieldChain` from all of them
//! in this order and inverts the whole chain (`crate::correction::chain`).
//!
//! The layout: the primary header says how many field elements there are (`IP NELEM`) and
//! where the file's own model stands among them (`IP MODEL PLACE`, 1-based); the others are
//! the rows of the binary table `ELEMENTS`, each with its place (`ORDER`), its kind (`KIND`)
//! and its parameters. Such a file is format version [`NEWEST_FORMAT_VERSION`] (a reader of
//! version 1 would correct with the file's own model alone); a file without `IP NELEM` holds
//! its own model alone and reads as before.

use crate::files::keys::{fits_err, KeyReader, KeyWriter, NEWEST_FORMAT_VERSION};
use crate::{Error, Result};
use fitsio::tables::{ColumnDataType, ColumnDescription};
use fitsio::FitsFile;
use std::path::Path;

/// The table of the elements besides the file's own model.
pub const HDU: &str = "ELEMENTS";

/// `KIND` of a stressed lens ([`field::StressedLens`]).
pub const STRESSED_LENS: &str = "STRESSED_LENS";

/// The parameter columns of the table (degrees and arcmin, as every file's keywords).
const PARAMS: [&str; 5] =
    ["RETARDANCE_EDGE_DEG", "RADIUS_ARCMIN", "CENTRE_X_ARCMIN", "CENTRE_Y_ARCMIN", "AXIS_OFFSET_DEG"];

/// One field element of a calibration file.
#[derive(Debug, Clone, PartialEq)]
pub enum Element {
    /// The file's own model (a field model, or a Mueller field), named by `IP MODEL`.
    Model,
    /// A stressed lens (`KIND = 'STRESSED_LENS'`): its retardance at a radius from a stress
    /// centre and the offset of its fast axis from radial (90 deg: tangential).
    StressedLens(field::StressedLens),
}

/// Refuse an order that is not one of the file's own model among at least two elements, or
/// a lens whose parameters are not usable, naming the element.
pub fn check(order: &[Element]) -> Result<()> {
    let models = order.iter().filter(|e| **e == Element::Model).count();
    if order.len() < 2 || models != 1 {
        return Err(Error::Input(format!(
            "several field elements: {} elements, {models} of them the file's own model (need at least two, one the model)",
            order.len()
        )));
    }
    for (k, e) in order.iter().enumerate() {
        if let Element::StressedLens(l) = e {
            let finite = [l.retardance_edge, l.centre_arcmin[0], l.centre_arcmin[1], l.axis_offset]
                .iter()
                .all(|v| v.is_finite());
            if !(finite && l.radius_arcmin > 0.0 && l.radius_arcmin.is_finite()) {
                return Err(Error::Input(format!(
                    "field element {}: a stressed lens needs finite values and a positive radius ({l:?})",
                    k + 1
                )));
            }
        }
    }
    Ok(())
}

/// What a calibration's `save_with` writes after its model for a file of the field elements
/// `order` ([`check`]ed first, unless empty: the model alone): the `ELEMENTS` table, then
/// `extra`'s HDUs (a telescope model). The one body of every `save_with_elements`.
pub fn writing_then<'a>(
    order: &'a [Element],
    extra: impl FnOnce(&mut FitsFile, &Path) -> Result<()> + 'a,
) -> Result<impl FnOnce(&mut FitsFile, &Path) -> Result<()> + 'a> {
    check_unless_empty(order)?;
    Ok(move |f: &mut FitsFile, p: &Path| {
        write(f, p, order)?;
        extra(f, p)
    })
}

/// [`check`] of a non-empty order; an empty one (the model alone) passes.
pub fn check_unless_empty(order: &[Element]) -> Result<()> {
    if order.is_empty() {
        Ok(())
    } else {
        check(order)
    }
}

/// Write `order` into the file being written (`f`, for `path`): the primary header's
/// `IP NELEM`, `IP MODEL PLACE` and format version, and the `ELEMENTS` table. Nothing for an
/// empty order (the file's own model alone).
pub(crate) fn write(f: &mut FitsFile, path: &Path, order: &[Element]) -> Result<()> {
    if order.is_empty() {
        return Ok(());
    }
    check(order)?;
    let e = |doing: &str| fits_err(path, doing);
    let place = order.iter().position(|x| *x == Element::Model).unwrap_or(0) + 1;
    {
        let hdu = f.primary_hdu().map_err(e("opening the primary HDU"))?;
        let mut w = KeyWriter { f, hdu: &hdu, path };
        w.update_int("FORMAT VERSION", NEWEST_FORMAT_VERSION)?;
        w.int("NELEM", order.len() as i64)?;
        w.int("MODEL PLACE", place as i64)?;
    }
    let mut descs = vec![
        ColumnDescription::new("ORDER").with_type(ColumnDataType::Int).create().map_err(e("describing ELEMENTS"))?,
        ColumnDescription::new("KIND")
            .with_type(ColumnDataType::String)
            .that_repeats(16)
            .create()
            .map_err(e("describing ELEMENTS"))?,
    ];
    for c in PARAMS {
        descs.push(
            ColumnDescription::new(c).with_type(ColumnDataType::Double).create().map_err(e("describing ELEMENTS"))?,
        );
    }
    let h = f.create_table(HDU, &descs).map_err(e("creating table ELEMENTS"))?;
    let mut rows: (Vec<i32>, Vec<String>, Vec<[f64; 5]>) = (vec![], vec![], vec![]);
    for (k, el) in order.iter().enumerate() {
        if let Element::StressedLens(l) = el {
            rows.0.push(k as i32 + 1);
            rows.1.push(STRESSED_LENS.to_string());
            rows.2.push([
                l.retardance_edge.to_degrees(),
                l.radius_arcmin,
                l.centre_arcmin[0],
                l.centre_arcmin[1],
                l.axis_offset.to_degrees(),
            ]);
        }
    }
    h.write_col(f, "ORDER", &rows.0).map_err(e("writing ELEMENTS"))?;
    h.write_col(f, "KIND", &rows.1).map_err(e("writing ELEMENTS"))?;
    for (i, c) in PARAMS.iter().enumerate() {
        let v: Vec<f64> = rows.2.iter().map(|r| r[i]).collect();
        h.write_col(f, *c, &v).map_err(e("writing ELEMENTS"))?;
    }
    Ok(())
}

/// The field elements of the calibration file at `path` in order; empty for a file that
/// holds its own model alone (no `IP NELEM`: every file of format version 1). A table that
/// does not give each place but the model's exactly once, an unknown kind or an unusable
/// lens is refused, naming the row.
pub(crate) fn read(path: &Path) -> Result<Vec<Element>> {
    let e = |doing: &str| fits_err(path, doing);
    let mut f = FitsFile::open(path).map_err(e("opening"))?;
    let hdu = f.primary_hdu().map_err(e("reading the primary HDU"))?;
    let mut r = KeyReader { f: &mut f, hdu: &hdu, path };
    let Some(n) = r.opt_int("NELEM") else { return Ok(vec![]) };
    let place = r.int("MODEL PLACE")?;
    let bad = |what: String| Error::BadFile { path: path.into(), what };
    if !(2..=64).contains(&n) || !(1..=n).contains(&place) {
        return Err(bad(format!("HIERARCH IP NELEM = {n} with IP MODEL PLACE = {place}: need 2 to 64 elements, the model's place among them")));
    }
    let h = f.hdu(HDU).map_err(e("finding table ELEMENTS (IP NELEM says the file holds several field elements)"))?;
    let order: Vec<i32> = h.read_col(&mut f, "ORDER").map_err(e("reading ELEMENTS column ORDER"))?;
    let kinds: Vec<String> = h.read_col(&mut f, "KIND").map_err(e("reading ELEMENTS column KIND"))?;
    let mut params = vec![];
    for c in PARAMS {
        params.push(h.read_col::<f64>(&mut f, c).map_err(e(&format!("reading ELEMENTS column {c}")))?);
    }
    let mut out: Vec<Option<Element>> = vec![None; n as usize];
    out[place as usize - 1] = Some(Element::Model);
    if order.len() != n as usize - 1 {
        return Err(bad(format!("ELEMENTS has {} rows, IP NELEM = {n} needs {}", order.len(), n - 1)));
    }
    for (row, (&k, kind)) in order.iter().zip(&kinds).enumerate() {
        let slot = usize::try_from(k).ok().filter(|&k| (1..=n as usize).contains(&k)).map(|k| k - 1);
        let Some(slot) = slot.filter(|&s| out[s].is_none()) else {
            return Err(bad(format!("ELEMENTS row {}: ORDER = {k} is not a free place among 1..{n}", row + 1)));
        };
        let p = |i: usize| params[i][row];
        out[slot] = Some(match kind.trim() {
            STRESSED_LENS => Element::StressedLens(field::StressedLens {
                retardance_edge: p(0).to_radians(),
                radius_arcmin: p(1),
                centre_arcmin: [p(2), p(3)],
                axis_offset: p(4).to_radians(),
            }),
            other => return Err(bad(format!("ELEMENTS row {}: KIND = '{other}' is not a known element", row + 1))),
        });
    }
    let order: Vec<Element> = out.into_iter().flatten().collect();
    check(&order).map_err(|err| bad(format!("ELEMENTS: {err}")))?;
    Ok(order)
}
