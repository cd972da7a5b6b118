//! The keywords shared by every calibration file (field, telescope and Mueller): the format
//! version, the model kinds, the `HIERARCH IP` keyword reader and writer, the opening check,
//! and the small file helpers the three writers share. The bottom of the calibration files'
//! layers: it imports none of them (`docs/calibration-file.md` describes the keywords).

use crate::{Error, Result};
use fitsio::hdu::FitsHdu;
use fitsio::FitsFile;
use std::path::{Path, PathBuf};

/// The calibration-file format this build writes for a file of one field element (its own
/// model): unchanged, so that older readers read such files as before.
pub const FORMAT_VERSION: i64 = 1;

/// The format of a file that holds several field elements in order
/// ([`crate::files::elements`]), which a reader of version 1 would correct with its own model
/// alone; the newest format this build reads.
pub const NEWEST_FORMAT_VERSION: i64 = 2;

/// `HIERARCH IP MODEL` of a file that holds a telescope model alone (`instpol fit-standards
/// --output`; beside a field model the field's kind is written).
pub const TELESCOPE_MODEL: &str = "TELESCOPE";

/// `HIERARCH IP MODEL` of a Mueller-field calibration (`instpol calibrate-mueller`).
pub const MUELLER_MODEL: &str = "MUELLER";

/// Open an existing calibration file and check its `IP FORMAT VERSION`: a missing file, a
/// newer version and one below 1 are refused by name.
pub(crate) fn open_versioned(path: &Path) -> Result<FitsFile> {
    if !path.is_file() {
        return Err(Error::Io {
            path: path.into(),
            err: std::io::Error::new(std::io::ErrorKind::NotFound, "no such calibration file"),
        });
    }
    let mut f = FitsFile::open(path).map_err(fits_err(path, "opening"))?;
    let hdu = f.primary_hdu().map_err(fits_err(path, "reading the primary HDU"))?;
    let version = KeyReader { f: &mut f, hdu: &hdu, path }.int("FORMAT VERSION")?;
    if version > NEWEST_FORMAT_VERSION {
        return Err(Error::NewerFormat { path: path.into(), found: version, supported: NEWEST_FORMAT_VERSION });
    }
    if version < 1 {
        return Err(Error::BadFile { path: path.into(), what: format!("format version {version} is not valid") });
    }
    Ok(f)
}

pub(crate) fn fits_err(path: &Path, doing: &str) -> impl Fn(fitsio::errors::Error) -> Error {
    let (path, doing) = (path.to_path_buf(), doing.to_string());
    move |err| Error::Fits { path: path.clone(), doing: doing.clone(), message: err.to_string() }
}

/// Writes `HIERARCH IP <name>` keywords (and plain ones) to one HDU.
pub(crate) struct KeyWriter<'a> {
    pub(crate) f: &'a mut FitsFile,
    pub(crate) hdu: &'a FitsHdu,
    pub(crate) path: &'a Path,
}

impl KeyWriter<'_> {
    fn err(&self, key: &str, e: fitsio::errors::Error) -> Error {
        Error::Fits { path: self.path.to_path_buf(), doing: format!("writing keyword {key}"), message: e.to_string() }
    }
    pub(crate) fn str(&mut self, name: &str, v: &str) -> Result<()> {
        let key = format!("HIERARCH IP {name}");
        // A HIERARCH card holds about 68 characters of name and value together.
        let max = 66usize.saturating_sub(key.len()).max(8);
        let v: String = v.chars().take(max).collect();
        self.hdu.write_key(self.f, &key, v).map_err(|e| self.err(&key, e))
    }
    pub(crate) fn real(&mut self, name: &str, v: f64) -> Result<()> {
        if !v.is_finite() {
            // FITS has no NaN keyword value: leave the keyword out (readers treat it as unknown).
            return Ok(());
        }
        let key = format!("HIERARCH IP {name}");
        self.hdu.write_key(self.f, &key, v).map_err(|e| self.err(&key, e))
    }
    pub(crate) fn int(&mut self, name: &str, v: i64) -> Result<()> {
        let key = format!("HIERARCH IP {name}");
        self.hdu.write_key(self.f, &key, v).map_err(|e| self.err(&key, e))
    }
    /// Replace the value of `HIERARCH IP <name>`, an integer keyword already written to this
    /// HDU (the format version of a file that turns out to hold several field elements).
    pub(crate) fn update_int(&mut self, name: &str, v: i64) -> Result<()> {
        let key = format!("HIERARCH IP {name}");
        let k = std::ffi::CString::new(key.as_str()).map_err(|_| Error::Input(format!("keyword {key}")))?;
        // The HDU made current, then CFITSIO's update of an existing card.
        self.hdu.read_key::<i64>(self.f, &key).map_err(|e| self.err(&key, e))?;
        let mut status = 0;
        // SAFETY: an open file whose current HDU is this one; a NUL-terminated name.
        unsafe { fitsio::sys::ffukyj(self.f.as_raw(), k.as_ptr(), v, std::ptr::null(), &mut status) };
        if status != 0 {
            return Err(Error::Fits {
                path: self.path.to_path_buf(),
                doing: format!("updating keyword {key}"),
                message: format!("CFITSIO status {status}"),
            });
        }
        Ok(())
    }
    pub(crate) fn plain(&mut self, key: &str, v: &str) -> Result<()> {
        self.hdu.write_key(self.f, key, v).map_err(|e| self.err(key, e))
    }
    pub(crate) fn plain_with_comment(&mut self, key: &str, v: &str, comment: &str) -> Result<()> {
        self.hdu.write_key(self.f, key, (v, comment)).map_err(|e| self.err(key, e))
    }
    pub(crate) fn plain_real(&mut self, key: &str, v: f64) -> Result<()> {
        self.hdu.write_key(self.f, key, v).map_err(|e| self.err(key, e))
    }
}

/// Reads `HIERARCH IP <name>` keywords, naming the keyword and file when one is missing.
pub(crate) struct KeyReader<'a> {
    pub(crate) f: &'a mut FitsFile,
    pub(crate) hdu: &'a FitsHdu,
    pub(crate) path: &'a Path,
}

impl KeyReader<'_> {
    fn missing(&self, key: &str, e: fitsio::errors::Error) -> Error {
        Error::BadFile {
            path: PathBuf::from(self.path),
            what: format!("keyword {key} is missing or unreadable ({e}); is this an instpol calibration file?"),
        }
    }
    pub(crate) fn str(&mut self, name: &str) -> Result<String> {
        let key = format!("HIERARCH IP {name}");
        skyfield::fits::read_key_str(self.f, self.hdu, &key).map_err(|e| self.missing(&key, e))
    }
    pub(crate) fn real(&mut self, name: &str) -> Result<f64> {
        let key = format!("HIERARCH IP {name}");
        self.hdu.read_key::<f64>(self.f, &key).map_err(|e| self.missing(&key, e))
    }
    pub(crate) fn int(&mut self, name: &str) -> Result<i64> {
        let key = format!("HIERARCH IP {name}");
        self.hdu.read_key::<i64>(self.f, &key).map_err(|e| self.missing(&key, e))
    }
    pub(crate) fn opt_str(&mut self, name: &str) -> Option<String> {
        self.str(name).ok()
    }
    pub(crate) fn opt_real(&mut self, name: &str) -> Option<f64> {
        self.real(name).ok()
    }
    pub(crate) fn opt_int(&mut self, name: &str) -> Option<i64> {
        self.int(name).ok()
    }
    pub(crate) fn plain_real(&mut self, key: &str) -> Result<f64> {
        self.hdu.read_key::<f64>(self.f, key).map_err(|e| self.missing(key, e))
    }
}

/// The error of a temporary file that could not be made beside `target`: says which file was
/// being written and why, without the temporary's random name.
pub(crate) fn temp_error(target: &Path, e: std::io::Error) -> std::io::Error {
    // tempfile appends ` at path "<temporary>"` to the OS error: keep only the reason.
    let text = e.to_string();
    let why = text.split(" at path ").next().unwrap_or(&text).to_string();
    std::io::Error::new(e.kind(), format!("cannot write {} in this folder: {why}", target.display()))
}

/// The current UTC time as ISO 8601 (no time-zone crate needed for this one stamp).
pub fn utc_now_iso() -> String {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    let days = (secs / 86400) as i64;
    let rem = secs % 86400;
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146_096) / 365;
    let y = yoe + era * 400;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = if m <= 2 { y + 1 } else { y };
    format!("{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z", rem / 3600, (rem % 3600) / 60, rem % 60)
}

/// Refuse an image whose header claims more values than its file has bytes (a corrupt or
/// hostile NAXISn), before anything is allocated for it: no image stores fewer than one byte
/// per value.
pub(crate) fn check_claimed_size(path: &Path, what: &str, shape: &[usize]) -> Result<()> {
    let len = std::fs::metadata(path).map(|m| m.len() as u128).unwrap_or(u128::MAX);
    let claimed = shape.iter().try_fold(1u128, |a, &n| a.checked_mul(n as u128)).unwrap_or(u128::MAX);
    if claimed > len {
        return Err(Error::BadFile {
            path: path.into(),
            what: format!("{what} claims {shape:?} values (header NAXISn) but the file holds only {len} bytes"),
        });
    }
    Ok(())
}

/// Write a new FITS file at `path` atomically, with the provenance stamped
/// ([`write_fits_atomically`] with `skyfield::provenance::stamp` after `write`).
pub(crate) fn save_fits_atomically(path: &Path, write: impl FnOnce(&mut FitsFile) -> Result<()>) -> Result<()> {
    write_fits_atomically(path, |f| {
        write(f)?;
        skyfield::provenance::stamp(f).map_err(|m| Error::Fits {
            path: path.to_path_buf(),
            doing: "writing the provenance".into(),
            message: m,
        })
    })
}

/// Write a new FITS file at `path` atomically: `write` fills a temporary file beside it, the
/// file is closed with its status checked and synced, then renamed (a full disk is an error
/// here, never a truncated calibration under the final name).
pub(crate) fn write_fits_atomically(path: &Path, write: impl FnOnce(&mut FitsFile) -> Result<()>) -> Result<()> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let tmp = skyfield::fits::temp_beside(path, ".fits")
        .map_err(|source| Error::Io { path: dir.to_path_buf(), err: temp_error(path, source) })?;
    let tmp = tmp.into_temp_path();
    {
        let mut f = FitsFile::create(&tmp).overwrite().open().map_err(fits_err(path, "creating the file"))?;
        write(&mut f)?;
        skyfield::durable::close_fits(f).map_err(|m| Error::Fits {
            path: path.to_path_buf(),
            doing: "closing the file".into(),
            message: m,
        })?;
    }
    skyfield::durable::finish(tmp, path).map_err(|err| Error::Io { path: path.to_path_buf(), err })
}

/// `HIERARCH IP MODEL` and `HIERARCH IP INSTRUMENT` of a calibration file, after the format
/// check of [`open_versioned`] (what tells the kinds of calibration file apart), and its product
/// keywords ([`read_product`]; `None` when it has none), read in one opening.
pub(crate) fn model_instrument_product(path: &Path) -> Result<(String, String, Option<skyfield::provenance::Product>)> {
    let mut f = open_versioned(path)?;
    let hdu = f.primary_hdu().map_err(fits_err(path, "reading the primary HDU"))?;
    let mut r = KeyReader { f: &mut f, hdu: &hdu, path };
    Ok((r.str("MODEL")?, r.str("INSTRUMENT")?, read_product(&mut r)?))
}

/// A calibration's product into its primary header, as the product keywords of every table
/// and map (`skyfield::provenance::Product::pairs`; plain FITS keywords beside the `HIERARCH
/// IP` ones), the inputs the run's when it lists none.
pub(crate) fn write_product(w: &mut KeyWriter, product: Option<&skyfield::provenance::Product>) -> Result<()> {
    for (k, v) in product.iter().flat_map(|p| p.with_run_inputs().pairs()) {
        w.plain(&k, &v)?;
    }
    Ok(())
}

/// The product keywords of the HDU `r` reads, `None` when it has none.
pub(crate) fn read_product(r: &mut KeyReader) -> Result<Option<skyfield::provenance::Product>> {
    skyfield::table::product_of_header(r.f, r.hdu)
        .map_err(|what| Error::BadFile { path: r.path.to_path_buf(), what: format!("product keywords: {what}") })
}
