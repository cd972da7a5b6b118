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
//!
//! The module's files: the table value (`model`), one file per format (`csv_table`, `ecsv`
//! with its YAML flow-mapping reader, `votable`, `fits_table`), and here the choice of format
//! by extension. Only the value, the format names, the FITS table lookup and the appending of columns to a
//! copy of a FITS table are public.

mod csv_table;
mod ecsv;
mod fits_table;
mod model;
mod units;
mod votable;

pub(crate) use fits_table::header_product_pairs;
pub use fits_table::product_of_header;
pub use fits_table::{append_fits_columns, fits_table_hdu};
pub use model::{Column, Data, Format, Table, EXTENSIONS, SKY_PA_COLUMN, ZERO_ANGLE_COLUMN};

use crate::Error;
use model::terr;
use std::io::Write;
use std::path::Path;

impl Table {
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
            Format::Csv => csv_table::read_csv(path)?,
            Format::Fits => fits_table::read_fits(path, hdu)?,
            Format::Ecsv => ecsv::read_ecsv(path)?,
            Format::Votable => votable::read_votable(path)?,
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
            return crate::fits::write_fits_atomic(path, |f| self.write_fits_into(f, path));
        }
        let bytes = match format {
            Format::Csv => self.csv_bytes(),
            Format::Ecsv => self.ecsv_bytes(),
            _ => self.votable_bytes(),
        }
        .map_err(|m| terr(path, format!("cannot format the table: {m}")))?;
        let werr = |e: std::io::Error| Error::Write { path: path.into(), message: e.to_string() };
        let mut tmp = crate::fits::temp_beside(path, ".tmp").map_err(werr)?;
        tmp.write_all(&bytes).and_then(|_| tmp.flush()).map_err(werr)?;
        crate::durable::finish(tmp.into_temp_path(), path).map_err(werr)
    }
}
