//! FITS primitives, the bottom of the frame I/O: nothing here knows an instrument or a
//! calibration. Writing: [`write_frame`] (one image with its header keywords) and
//! [`write_fits_atomic`] (any content), each through a temporary file in the target folder
//! renamed into place only when complete, so a failed run leaves no partial output
//! ([`temp_beside`] starts any other output that way). Keywords longer than 8 characters are
//! written with the ESO `HIERARCH` convention (CFITSIO does this for any name that starts with
//! `HIERARCH `). Reading: keyword values ([`read_key_str`]), the image HDU of a file found and
//! opened (`open_image`: primary, extension, CFITSIO suffix), its pixels whole in their stored
//! type or by rows straight from the file (`pixel_source`).

use crate::{fits_err, Error};
use fitsio::images::{ImageDescription, ImageType};
use fitsio::FitsFile;
use std::path::{Path, PathBuf};

/// Pixel type of a written frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Bitpix {
    /// Unsigned 16-bit integers (BITPIX 16 with BZERO 32768), like raw CCD frames: values are
    /// rounded and clipped to [0, 65535].
    U16,
    /// 32-bit floats.
    F32,
    /// 64-bit floats (exact round trips for tests).
    F64,
}

impl Bitpix {
    /// From the FITS BITPIX number (16, -32, -64).
    pub fn from_fits(b: i32) -> Option<Self> {
        match b {
            16 => Some(Self::U16),
            -32 => Some(Self::F32),
            -64 => Some(Self::F64),
            _ => None,
        }
    }
}

/// A header keyword value to write.
#[derive(Debug, Clone, PartialEq)]
pub enum KeyValue {
    F64(f64),
    I64(i64),
    Str(String),
}

impl KeyValue {
    /// Write it as keyword `key` of `hdu`, numbers with their `comment` (text without one).
    pub(crate) fn write(
        &self,
        f: &mut FitsFile,
        hdu: &fitsio::hdu::FitsHdu,
        key: &str,
        comment: &str,
    ) -> fitsio::errors::Result<()> {
        match self {
            KeyValue::F64(x) => hdu.write_key(f, key, (*x, comment)),
            KeyValue::I64(x) => hdu.write_key(f, key, (*x, comment)),
            KeyValue::Str(s) => hdu.write_key(f, key, s.as_str()),
        }
    }
}

/// Write a FITS file through a temporary file in the same folder and a rename. `fill`
/// creates the content; if it fails, nothing is left behind.
pub fn write_fits_atomic(path: &Path, fill: impl FnOnce(&mut FitsFile) -> Result<(), Error>) -> Result<(), Error> {
    write_fits_atomic_with(path, None, fill)
}

/// The environment variable that tags the temporaries of a command with the unit of a plan it
/// runs for (`workflow::night::run`): they are named `.instpol-<tag>.*` ([`temp_prefix`]), so
/// that the next run of that unit, under the unit's lock, finds and removes the ones a killed
/// run left, and no other unit's.
pub const TEMP_TAG_ENV: &str = "INSTPOL_TEMP_TAG";

/// The name every temporary of the workspace starts with: `.instpol-`, then, for a tagged
/// one, the tag (letters, digits, `-` and `_` kept, anything else made `_`) and a dot.
pub fn temp_prefix(tag: Option<&str>) -> String {
    match tag {
        Some(t) => {
            let t: String = t.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' { c } else { '_' }).collect();
            format!(".instpol-{t}.")
        }
        None => ".instpol-".into(),
    }
}

/// A temporary file (`.instpol-*SUFFIX`) in the folder of `path`, to be renamed onto it: the
/// one way the workspace starts writing an output, so that a failed run leaves no half file.
/// It gets the permissions of an ordinary new file (0o666 less the umask) rather than
/// tempfile's private 0o600, which a rename would otherwise carry into the output. Tagged by
/// [`TEMP_TAG_ENV`] when it is set.
pub fn temp_beside(path: &Path, suffix: &str) -> std::io::Result<tempfile::NamedTempFile> {
    // A run scoped within the process (`crate::provenance::scoped`) has its tag in place of
    // the environment's.
    let tag = crate::provenance::scope_tag().or_else(|| std::env::var(TEMP_TAG_ENV).ok()).filter(|t| !t.is_empty());
    temp_beside_tagged(path, tag.as_deref(), suffix)
}

/// [`temp_beside`] with the tag given ([`temp_prefix`]).
pub fn temp_beside_tagged(path: &Path, tag: Option<&str>, suffix: &str) -> std::io::Result<tempfile::NamedTempFile> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let mut b = tempfile::Builder::new();
    let prefix = temp_prefix(tag);
    b.prefix(&prefix).suffix(suffix);
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        b.permissions(std::fs::Permissions::from_mode(0o666));
    }
    b.tempfile_in(dir)
}

/// [`write_fits_atomic`] with a primary image of the given type and shape.
fn write_fits_atomic_with(
    path: &Path,
    primary: Option<&ImageDescription>,
    fill: impl FnOnce(&mut FitsFile) -> Result<(), Error>,
) -> Result<(), Error> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let werr = |m: String| Error::Write { path: path.into(), message: m };
    let tmp = temp_beside(path, ".fits.tmp")
        .map_err(|e| werr(format!("cannot create a temporary file in {}: {e}", dir.display())))?
        .into_temp_path();
    {
        let mut b = FitsFile::create(&tmp).overwrite();
        if let Some(d) = primary {
            b = b.with_custom_primary(d);
        }
        let mut f = b.open().map_err(|e| werr(e.to_string()))?;
        // On an error here `f` is dropped (closed, status ignored) and so is `tmp` (deleted).
        fill(&mut f)?;
        crate::provenance::stamp(&mut f).map_err(werr)?;
        // CFITSIO writes its last blocks at close: a full disk shows up here, not in `fill`.
        crate::durable::close_fits(f).map_err(werr)?;
    }
    crate::durable::finish(tmp, path).map_err(|e| werr(e.to_string()))?;
    Ok(())
}

/// Write one frame (`data` row-major `[y * nx + x]`, ADU) with header keywords, atomically.
pub fn write_frame(
    path: &Path,
    nx: usize,
    ny: usize,
    data: &[f64],
    bitpix: Bitpix,
    keys: &[(String, KeyValue, String)],
) -> Result<(), Error> {
    if data.len() != nx * ny {
        return Err(Error::Invalid(format!("frame data has {} pixels, expected {nx} x {ny}", data.len())));
    }
    let dims = [ny, nx];
    let ty = match bitpix {
        Bitpix::U16 => ImageType::UnsignedShort,
        Bitpix::F32 => ImageType::Float,
        Bitpix::F64 => ImageType::Double,
    };
    let desc = ImageDescription { data_type: ty, dimensions: &dims };
    write_fits_atomic_with(path, Some(&desc), |f| {
        let e = |x: fitsio::errors::Error| Error::Write { path: path.into(), message: x.to_string() };
        let hdu = f.primary_hdu().map_err(e)?;
        match bitpix {
            Bitpix::U16 => {
                let v: Vec<u16> =
                    data.iter().map(|&x| if x.is_nan() { 0 } else { x.round().clamp(0.0, 65535.0) as u16 }).collect();
                hdu.write_image(f, &v).map_err(e)?;
            }
            Bitpix::F32 => {
                let v: Vec<f32> = data.iter().map(|&x| x as f32).collect();
                hdu.write_image(f, &v).map_err(e)?;
            }
            Bitpix::F64 => hdu.write_image(f, data).map_err(e)?,
        }
        // A frame is in ADU unless the caller says otherwise (a normalized flat is
        // dimensionless): astropy's CCDData needs a BUNIT to read it.
        if !keys.iter().any(|(k, _, _)| k.eq_ignore_ascii_case("BUNIT")) {
            hdu.write_key(f, "BUNIT", ("adu", "analog-to-digital units")).map_err(e)?;
        }
        for (k, v, c) in keys {
            // fitsio names the primary HDU EXTNAME = '_PRIMARY'; an EXTNAME of our own (a chip
            // name) replaces that card rather than adding a conflicting second one.
            if let (true, KeyValue::Str(s)) = (k.eq_ignore_ascii_case("EXTNAME"), v) {
                let name = std::ffi::CString::new("EXTNAME").expect("no NUL");
                let val = std::ffi::CString::new(s.as_str())
                    .map_err(|x| Error::Write { path: path.into(), message: format!("keyword {k}: {x}") })?;
                let mut status = 0;
                // SAFETY: an open file at its primary HDU; NUL-terminated strings.
                unsafe { fitsio::sys::ffukys(f.as_raw(), name.as_ptr(), val.as_ptr(), std::ptr::null(), &mut status) };
                if status != 0 {
                    return Err(Error::Write {
                        path: path.into(),
                        message: format!("keyword {k}: CFITSIO status {status}"),
                    });
                }
                continue;
            }
            v.write(f, &hdu, k, c)
                .map_err(|x| Error::Write { path: path.into(), message: format!("keyword {k}: {x}") })?;
        }
        Ok(())
    })
}

pub fn read_key_str(f: &mut FitsFile, hdu: &fitsio::hdu::FitsHdu, key: &str) -> fitsio::errors::Result<String> {
    use std::os::raw::{c_char, c_int};
    let name = std::ffi::CString::new(key)?;
    let mut value = [0 as c_char; 160];
    let mut comment = [0 as c_char; 160];
    let (mut status, mut hdu_type): (c_int, c_int) = (0, 0);
    // SAFETY: `f` is an open file; both buffers exceed the 81 bytes of a card, the most CFITSIO
    // copies into either; `name` is NUL-terminated.
    unsafe {
        let fptr = f.as_raw();
        fitsio::sys::ffmahd(fptr, hdu.number as c_int + 1, &mut hdu_type, &mut status);
        fitsio::sys::ffgkys(fptr, name.as_ptr(), value.as_mut_ptr(), comment.as_mut_ptr(), &mut status);
    }
    fitsio::errors::check_status(status)?;
    let bytes: Vec<u8> = value.iter().take_while(|&&c| c != 0).map(|&c| c as u8).collect();
    Ok(String::from_utf8(bytes).map_err(|e| e.utf8_error())?)
}

/// Pixel values as stored (no scaling), or as f64 when the file scales them.
#[derive(Debug, Clone)]
pub(crate) enum Pixels {
    F32(Vec<f32>),
    U16(Vec<u16>),
    I16(Vec<i16>),
    F64(Vec<f64>),
}

impl Pixels {
    /// Borrowed view.
    pub(crate) fn view(&self) -> PixelView<'_> {
        match self {
            Pixels::F32(v) => PixelView::F32(v),
            Pixels::U16(v) => PixelView::U16(v),
            Pixels::I16(v) => PixelView::I16(v),
            Pixels::F64(v) => PixelView::F64(v),
        }
    }

    pub(crate) fn len(&self) -> usize {
        match self {
            Pixels::F32(v) => v.len(),
            Pixels::U16(v) => v.len(),
            Pixels::I16(v) => v.len(),
            Pixels::F64(v) => v.len(),
        }
    }

    /// As f64 (every stored type converts exactly).
    pub(crate) fn into_f64(self) -> Vec<f64> {
        match self {
            Pixels::F64(v) => v,
            other => {
                let mut out = vec![0.0; other.len()];
                other.view().load(0, &mut out);
                out
            }
        }
    }
}

/// A borrowed frame (or per-angle sum) in its stored type.
#[derive(Debug, Clone, Copy)]
pub(crate) enum PixelView<'a> {
    F32(&'a [f32]),
    U16(&'a [u16]),
    I16(&'a [i16]),
    F64(&'a [f64]),
}

impl PixelView<'_> {
    /// Copy `out.len()` pixels from `start` as f64 (exact for every type).
    #[inline]
    pub(crate) fn load(&self, start: usize, out: &mut [f64]) {
        let n = out.len();
        match self {
            PixelView::F32(v) => out.iter_mut().zip(&v[start..start + n]).for_each(|(o, &x)| *o = x as f64),
            PixelView::U16(v) => out.iter_mut().zip(&v[start..start + n]).for_each(|(o, &x)| *o = x as f64),
            PixelView::I16(v) => out.iter_mut().zip(&v[start..start + n]).for_each(|(o, &x)| *o = x as f64),
            PixelView::F64(v) => out.copy_from_slice(&v[start..start + n]),
        }
    }

    /// Number of non-finite pixels and of pixels at or above `sat`, in one pass (inlined, so a
    /// vectorized caller counts with its own vector width).
    #[inline(always)]
    pub(crate) fn count_bad(&self, sat: f64) -> (usize, usize) {
        // A plain loop with u64 counters (as wide as the f64 lanes): it vectorizes, where the
        // tuple fold did not (7 % of a raw FORS2 reduction's profile).
        #[inline(always)]
        fn go<T: Copy>(v: &[T], f: impl Fn(T) -> f64, sat: f64) -> (usize, usize) {
            let (mut a, mut b) = (0u64, 0u64);
            for &x in v {
                let x = f(x);
                a += !x.is_finite() as u64;
                b += (x >= sat) as u64;
            }
            (a as usize, b as usize)
        }
        match self {
            PixelView::F32(v) => go(v, |x| x as f64, sat),
            PixelView::U16(v) => go(v, |x| x as f64, sat),
            PixelView::I16(v) => go(v, |x| x as f64, sat),
            PixelView::F64(v) => go(v, |x| x, sat),
        }
    }
}

/// An image HDU opened for reading (any HDU of a plain, gzipped or tile-compressed file).
pub(crate) struct ImageHdu {
    pub f: FitsFile,
    /// The file on disk (the name without a CFITSIO `[...]` suffix).
    pub disk: PathBuf,
    /// 0-based HDU index.
    pub index: usize,
    /// `HDU n` or `HDU n (EXTNAME)`, for messages.
    pub label: String,
    pub nx: usize,
    pub ny: usize,
    pub bitpix: i32,
    pub bscale: f64,
    pub bzero: f64,
    /// A BLANK keyword is present (integer images): such pixels read as NaN.
    pub blank: bool,
    /// Tile-compressed (`.fz`): only CFITSIO decodes it.
    pub compressed: bool,
}

/// CFITSIO status codes this module tells apart.
const HDU_IMAGE: i32 = 0;

/// Move to HDU `index` (0-based); its CFITSIO HDU type.
fn move_to(f: &mut FitsFile, index: usize) -> Result<i32, i32> {
    let (mut ty, mut status) = (0, 0);
    // SAFETY: an open file; plain integer outputs.
    unsafe { fitsio::sys::ffmahd(f.as_raw(), index as i32 + 1, &mut ty, &mut status) };
    if status != 0 {
        Err(status)
    } else {
        Ok(ty)
    }
}

/// The string value of `key` in HDU `index`, `None` when absent. Reads into buffers longer
/// than a card (see [`read_key_str`]).
pub(crate) fn key_at(f: &mut FitsFile, index: usize, key: &str) -> Option<String> {
    use std::os::raw::c_char;
    let name = std::ffi::CString::new(key).ok()?;
    move_to(f, index).ok()?;
    let mut value = [0 as c_char; 160];
    let mut comment = [0 as c_char; 160];
    let mut status = 0;
    // SAFETY: buffers exceed a card; name is NUL-terminated.
    unsafe { fitsio::sys::ffgkys(f.as_raw(), name.as_ptr(), value.as_mut_ptr(), comment.as_mut_ptr(), &mut status) };
    if status != 0 {
        return None;
    }
    let bytes: Vec<u8> = value.iter().take_while(|&&c| c != 0).map(|&c| c as u8).collect();
    Some(String::from_utf8_lossy(&bytes).trim().to_string())
}

impl ImageHdu {
    /// `key` in the image HDU, else in the primary header (ESO writes its keywords there when
    /// the image is in an extension).
    pub(crate) fn key(&mut self, key: &str) -> Option<String> {
        key_at(&mut self.f, self.index, key).or_else(|| if self.index > 0 { key_at(&mut self.f, 0, key) } else { None })
    }

    /// A numeric keyword (number or numeric string; Fortran `D` exponents accepted).
    pub(crate) fn number(&mut self, path: &Path, key: &str, expected: &str) -> Result<Option<f64>, Error> {
        let Some(s) = self.key(key) else { return Ok(None) };
        parse_number(&s).map(Some).ok_or_else(|| Error::BadKeyword {
            path: path.into(),
            keyword: key.into(),
            value: s,
            expected: expected.into(),
        })
    }

    /// All pixels through CFITSIO: in the stored type when that needs no scaling and has no
    /// BLANK (f32 frames are half the memory of f64), else as f64 with BLANK pixels NaN.
    pub(crate) fn read_pixels(&mut self, path: &Path) -> Result<Pixels, Error> {
        let n = self.nx * self.ny;
        move_to(&mut self.f, self.index).map_err(|s| read_error(path, format!("CFITSIO status {s}")))?;
        let rerr = |e: fitsio::errors::Error| read_error(path, e);
        let kind = if self.compressed || self.blank { None } else { raw_kind(self.bitpix, self.bscale, self.bzero) };
        let pixels = match kind {
            Some(k @ (RawKind::F32 | RawKind::U16 | RawKind::I16)) => {
                let hdu = self.f.hdu(self.index).map_err(rerr)?;
                match k {
                    RawKind::F32 => Pixels::F32(hdu.read_image(&mut self.f).map_err(rerr)?),
                    RawKind::U16 => Pixels::U16(hdu.read_image(&mut self.f).map_err(rerr)?),
                    _ => Pixels::I16(hdu.read_image(&mut self.f).map_err(rerr)?),
                }
            }
            _ => {
                let mut v = vec![0.0f64; n];
                let (mut anynul, mut status) = (0, 0);
                // SAFETY: `v` holds `n` values, the number requested; CFITSIO applies BSCALE and
                // BZERO and sets undefined (BLANK) pixels to the non-zero null value NaN.
                unsafe {
                    fitsio::sys::ffgpvd(
                        self.f.as_raw(),
                        1,
                        1,
                        n as i64,
                        f64::NAN,
                        v.as_mut_ptr(),
                        &mut anynul,
                        &mut status,
                    )
                };
                if status != 0 {
                    return Err(read_error(path, format!("CFITSIO status {status}")));
                }
                Pixels::F64(v)
            }
        };
        if pixels.len() != n {
            return Err(fits_err(path, format!("read {} pixels, header says {} x {}", pixels.len(), self.nx, self.ny)));
        }
        Ok(pixels)
    }

    /// Refuse keywords that appear twice with different values among `keys` (and the ones
    /// that say how to read the pixels): which one CFITSIO uses is not a choice to make
    /// silently.
    pub(crate) fn check_duplicates(&mut self, path: &Path, keys: &[&str]) -> Result<(), Error> {
        let mut watched: Vec<String> =
            ["BITPIX", "NAXIS", "NAXIS1", "NAXIS2", "BZERO", "BSCALE", "BLANK"].iter().map(|s| s.to_string()).collect();
        watched.extend(keys.iter().filter(|k| !k.is_empty()).map(|k| k.to_ascii_uppercase()));
        let mut indices = vec![self.index];
        if self.index > 0 {
            indices.push(0);
        }
        for idx in indices {
            move_to(&mut self.f, idx).map_err(|s| read_error(path, format!("CFITSIO status {s}")))?;
            let (mut nkeys, mut more, mut status) = (0, 0, 0);
            // SAFETY: plain integer outputs.
            unsafe { fitsio::sys::ffghsp(self.f.as_raw(), &mut nkeys, &mut more, &mut status) };
            let mut seen: Vec<(String, String)> = Vec::new();
            for n in 1..=nkeys.max(0) {
                let mut card = [0 as std::os::raw::c_char; 100];
                let mut st = 0;
                // SAFETY: a card is at most 81 bytes with its NUL.
                unsafe { fitsio::sys::ffgrec(self.f.as_raw(), n, card.as_mut_ptr(), &mut st) };
                if st != 0 {
                    break;
                }
                let bytes: Vec<u8> = card.iter().take_while(|&&c| c != 0).map(|&c| c as u8).collect();
                let card = String::from_utf8_lossy(&bytes).to_string();
                let Some((name, value)) = split_card(&card) else { continue };
                if !watched.contains(&name) {
                    continue;
                }
                match seen.iter().find(|(k, _)| *k == name) {
                    Some((_, v0)) if !same_value(v0, &value) => {
                        let where_ = if idx == 0 { "primary header".to_string() } else { self.label.clone() };
                        return Err(fits_err(
                            path,
                            format!(
                                "keyword '{name}' appears twice in the {where_} with different values ({v0} and {value}); remove one"
                            ),
                        ));
                    }
                    Some(_) => {}
                    None => seen.push((name, value)),
                }
            }
        }
        Ok(())
    }
}

/// A number from a header value: `22.5`, `'22.5'`, `2.25D+01`.
pub(crate) fn parse_number(s: &str) -> Option<f64> {
    let t = s.trim().trim_matches('\'').trim();
    t.parse::<f64>().ok().or_else(|| t.replace(['D', 'd'], "E").parse().ok()).filter(|v: &f64| v.is_finite())
}

/// Keyword name (upper case, `HIERARCH ` kept) and value text of a header card.
fn split_card(card: &str) -> Option<(String, String)> {
    let (name, rest) = if let Some(h) = card.strip_prefix("HIERARCH ") {
        let eq = h.find('=')?;
        (format!("HIERARCH {}", h[..eq].trim()), &h[eq + 1..])
    } else {
        if card.len() < 10 || &card[8..10] != "= " {
            return None;
        }
        (card[..8].trim().to_string(), &card[10..])
    };
    let rest = rest.trim_start();
    let value = if let Some(q) = rest.strip_prefix('\'') {
        // A quoted string ends at a quote not doubled.
        let mut out = String::new();
        let mut it = q.chars().peekable();
        while let Some(c) = it.next() {
            if c == '\'' {
                if it.peek() == Some(&'\'') {
                    it.next();
                    out.push('\'');
                    continue;
                }
                break;
            }
            out.push(c);
        }
        out.trim_end().to_string()
    } else {
        rest.split('/').next().unwrap_or("").trim().to_string()
    };
    Some((name.to_ascii_uppercase(), value))
}

fn same_value(a: &str, b: &str) -> bool {
    match (parse_number(a), parse_number(b)) {
        (Some(x), Some(y)) => x == y,
        _ => a.trim() == b.trim(),
    }
}

/// Open `path` and move to its image HDU: the HDU a CFITSIO suffix names (`f.fits[1]`,
/// `f.fits[CHIP1]`), else `spec` (the instrument's: a number or an EXTNAME), else the primary
/// HDU if it holds an image, else the one image extension with data. A file whose own name
/// contains brackets is opened by that name (no suffix parsing). A table where an image is
/// wanted, no image or several: errors naming the file and the HDUs.
pub(crate) fn open_image(path: &Path, spec: &str) -> Result<ImageHdu, Error> {
    let name = path.to_str().ok_or_else(|| fits_err(path, "file name is not valid UTF-8"))?;
    let open_err = |e: String| fits_err(path, format!("cannot open as FITS: {e}"));
    let literal = path.is_file();
    let (mut f, explicit, disk) = if literal && name.contains('[') {
        // CFITSIO would read the brackets as an HDU selector: open the disk file by its name.
        let c = std::ffi::CString::new(name).map_err(|e| open_err(e.to_string()))?;
        let (mut fptr, mut status) = (std::ptr::null_mut(), 0);
        // SAFETY: `c` is NUL-terminated; CFITSIO sets `fptr` on success.
        unsafe { fitsio::sys::ffdkopn(&mut fptr, c.as_ptr(), 0, &mut status) };
        if status != 0 || fptr.is_null() {
            return Err(open_err(format!("CFITSIO status {status}")));
        }
        // SAFETY: a file CFITSIO just opened read-only, owned from here on.
        let f =
            unsafe { FitsFile::from_raw(fptr, fitsio::FileOpenMode::READONLY) }.map_err(|e| open_err(e.to_string()))?;
        (f, false, path.to_path_buf())
    } else {
        let f = FitsFile::open(path).map_err(|e| open_err(e.to_string()))?;
        let explicit = !literal && name.ends_with(']') && name.contains('[');
        let disk = if explicit { PathBuf::from(&name[..name.find('[').unwrap_or(name.len())]) } else { path.into() };
        (f, explicit, disk)
    };
    let nhdus = f.num_hdus().map_err(|e| open_err(e.to_string()))?;
    let index = if explicit {
        let mut n = 0;
        // SAFETY: an open file.
        unsafe { fitsio::sys::ffghdn(f.as_raw(), &mut n) };
        (n - 1).max(0) as usize
    } else if !spec.is_empty() {
        match spec.parse::<usize>() {
            Ok(i) if i < nhdus => i,
            Ok(i) => {
                return Err(fits_err(
                    path,
                    format!("has no HDU {i} (it has {nhdus}); the instrument's format names HDU {i}"),
                ))
            }
            Err(_) => (0..nhdus)
                .find(|&i| key_at(&mut f, i, "EXTNAME").is_some_and(|v| v.eq_ignore_ascii_case(spec)))
                .ok_or_else(|| fits_err(path, format!("has no HDU named '{spec}' (EXTNAME)")))?,
        }
    } else {
        let images: Vec<usize> = (0..nhdus).filter(|&i| image_dims(&mut f, i).is_some_and(|d| !d.is_empty())).collect();
        match images[..] {
            [i] => i,
            [] => {
                return Err(fits_err(
                    path,
                    format!(
                        "has no image HDU with data ({}), so there is no frame to read",
                        describe_hdus(&mut f, nhdus)
                    ),
                ))
            }
            _ if images.contains(&0) => 0,
            _ => {
                return Err(fits_err(
                    path,
                    format!(
                        "has {} image HDUs ({}): name the one to read, e.g. {}[{}]",
                        images.len(),
                        describe_hdus(&mut f, nhdus),
                        path.display(),
                        images[0]
                    ),
                ))
            }
        }
    };
    let label = hdu_label(&mut f, index);
    let ty = move_to(&mut f, index).map_err(|s| open_err(format!("CFITSIO status {s}")))?;
    if ty != HDU_IMAGE {
        let kind = if ty == 1 { "an ASCII table" } else { "a binary table" };
        return Err(fits_err(path, format!("{label} is {kind}, not an image: name an image HDU (e.g. [0] or [1])")));
    }
    let dims = image_dims(&mut f, index).unwrap_or_default();
    if dims.len() != 2 {
        return Err(Error::NotImage { path: path.into(), shape: dims });
    }
    let (mut bitpix, mut status) = (0, 0);
    // SAFETY: an open file at an image HDU.
    unsafe { fitsio::sys::ffgidt(f.as_raw(), &mut bitpix, &mut status) };
    let mut compressed = false;
    // SAFETY: as above.
    unsafe { compressed |= fitsio::sys::fits_is_compressed_image(f.as_raw(), &mut status) != 0 };
    let bscale = key_at(&mut f, index, "BSCALE").and_then(|s| parse_number(&s)).unwrap_or(1.0);
    let bzero = key_at(&mut f, index, "BZERO").and_then(|s| parse_number(&s)).unwrap_or(0.0);
    let blank = bitpix > 0 && key_at(&mut f, index, "BLANK").is_some();
    Ok(ImageHdu { f, disk, index, label, nx: dims[1], ny: dims[0], bitpix, bscale, bzero, blank, compressed })
}

/// Dimensions `[ny, nx, ...]` (slowest first) of HDU `index` when it is an image.
fn image_dims(f: &mut FitsFile, index: usize) -> Option<Vec<usize>> {
    if move_to(f, index).ok()? != HDU_IMAGE {
        return None;
    }
    let (mut naxis, mut status) = (0, 0);
    // SAFETY: plain outputs.
    unsafe { fitsio::sys::ffgidm(f.as_raw(), &mut naxis, &mut status) };
    if status != 0 || !(0..=9).contains(&naxis) {
        return None;
    }
    let mut ax = [0i64; 9];
    // SAFETY: `ax` holds 9 >= naxis values.
    unsafe { fitsio::sys::ffgiszll(f.as_raw(), naxis, ax.as_mut_ptr(), &mut status) };
    if status != 0 || ax[..naxis as usize].iter().any(|&a| a <= 0) {
        return Some(vec![]);
    }
    Some(ax[..naxis as usize].iter().rev().map(|&a| a as usize).collect())
}

fn hdu_label(f: &mut FitsFile, index: usize) -> String {
    match key_at(f, index, "EXTNAME") {
        Some(n) if !n.is_empty() => format!("HDU {index} ({n})"),
        _ => format!("HDU {index}"),
    }
}

fn describe_hdus(f: &mut FitsFile, n: usize) -> String {
    (0..n.min(20))
        .map(|i| {
            let what = match move_to(f, i) {
                Ok(HDU_IMAGE) => match image_dims(f, i) {
                    Some(d) if !d.is_empty() => format!("image {:?}", d.iter().rev().collect::<Vec<_>>()),
                    _ => "header only".to_string(),
                },
                Ok(1) => "ASCII table".to_string(),
                Ok(_) => "binary table".to_string(),
                Err(_) => "unreadable".to_string(),
            };
            format!("{}: {what}", hdu_label(f, i))
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// Every FITS image type is read (8, 16, 32, 64-bit integers with any BZERO/BSCALE, 32 and
/// 64-bit floats); anything else is not a FITS image.
pub(crate) fn check_bitpix(path: &Path, bitpix: i32) -> Result<(), Error> {
    match bitpix {
        8 | 16 | 32 | 64 | -32 | -64 => Ok(()),
        b => Err(Error::BadBitpix { path: path.into(), bitpix: b }),
    }
}

pub(crate) fn read_error(path: &Path, e: impl std::fmt::Display) -> Error {
    fits_err(path, format!("cannot read the image data (truncated or corrupt file?): {e}"))
}

/// Stored pixel encodings the reduction reads without CFITSIO's conversion: FITS data are
/// big-endian, and these need no scaling beyond the unsigned 16-bit `BZERO = 32768`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum RawKind {
    F32,
    F64,
    I16,
    /// Stored as i16 with `BZERO = 32768`.
    U16,
}

impl RawKind {
    /// Bytes per pixel.
    pub(crate) fn bytes(self) -> usize {
        match self {
            RawKind::F32 => 4,
            RawKind::F64 => 8,
            RawKind::I16 | RawKind::U16 => 2,
        }
    }

    /// Decode big-endian pixels into f64 (exact for every kind).
    #[inline(always)]
    pub(crate) fn decode(self, bytes: &[u8], out: &mut [f64]) {
        self.decode_each(bytes, out, |_| {});
    }

    /// [`RawKind::decode`], counting as it goes the non-finite values and those at or above
    /// `sat` ([`PixelView::count_bad`] of `out`).
    pub(crate) fn decode_counting(self, bytes: &[u8], out: &mut [f64], sat: f64) -> (usize, usize) {
        let (mut a, mut b) = (0u64, 0u64);
        self.decode_each(bytes, out, |x| {
            a += !x.is_finite() as u64;
            b += (x >= sat) as u64;
        });
        (a as usize, b as usize)
    }

    /// The one decoding loop: each pixel of `bytes` decoded into `out` and handed to `visit`
    /// (always inlined, so that a caller's empty `visit` leaves the plain loop).
    #[inline(always)]
    fn decode_each(self, bytes: &[u8], out: &mut [f64], visit: impl FnMut(f64)) {
        #[inline(always)]
        fn go<const B: usize>(bytes: &[u8], out: &mut [f64], f: impl Fn(&[u8; B]) -> f64, mut visit: impl FnMut(f64)) {
            for (o, c) in out.iter_mut().zip(bytes.chunks_exact(B)) {
                let x = f(c.try_into().expect("B bytes"));
                *o = x;
                visit(x);
            }
        }
        match self {
            RawKind::F32 => go::<4>(bytes, out, |b| f32::from_be_bytes(*b) as f64, visit),
            RawKind::F64 => go::<8>(bytes, out, |b| f64::from_be_bytes(*b), visit),
            RawKind::I16 => go::<2>(bytes, out, |b| i16::from_be_bytes(*b) as f64, visit),
            // Flipping the sign bit adds 32768 to a two's-complement i16.
            RawKind::U16 => go::<2>(bytes, out, |b| u16::from_be_bytes([b[0] ^ 0x80, b[1]]) as f64, visit),
        }
    }
}

pub(crate) fn raw_kind(bitpix: i32, bscale: f64, bzero: f64) -> Option<RawKind> {
    match (bitpix, bscale == 1.0, bzero) {
        (-32, true, 0.0) => Some(RawKind::F32),
        (-64, true, 0.0) => Some(RawKind::F64),
        (16, true, 0.0) => Some(RawKind::I16),
        (16, true, 32768.0) => Some(RawKind::U16),
        _ => None,
    }
}

/// An uncompressed primary image read by rows straight from the file (positioned reads, no
/// CFITSIO buffer and no whole-frame copy): what lets the reduction read a few rows of every
/// frame while the other threads compute, with the rows still in cache when they are used.
/// (A memory map was tried: decoding from it ran at the speed of its page faults and cache
/// misses, slower than the kernel's sequential copy into a buffer that stays in cache.)
#[derive(Debug)]
pub(crate) struct RowFile {
    file: std::fs::File,
    data_start: u64,
    kind: RawKind,
    nx: usize,
}

impl RowFile {
    pub(crate) fn kind(&self) -> RawKind {
        self.kind
    }

    /// Pixels from pixel index `px` of the image as stored (big-endian), as many as fill `out`.
    pub(crate) fn read_at(&self, path: &Path, px: usize, out: &mut [u8]) -> Result<(), Error> {
        use std::os::unix::fs::FileExt;
        let at = self.data_start + (px * self.kind.bytes()) as u64;
        self.file.read_exact_at(out, at).map_err(|e| read_error(path, e))
    }

    /// Rows from `row0` as stored (big-endian), as many as fill `out`.
    pub(crate) fn read_rows(&self, path: &Path, row0: usize, out: &mut [u8]) -> Result<(), Error> {
        use std::os::unix::fs::FileExt;
        let at = self.data_start + (row0 * self.nx * self.kind.bytes()) as u64;
        self.file.read_exact_at(out, at).map_err(|e| read_error(path, e))
    }

    /// The file's bytes before its image data and after the data's `ny` rows: with the rows'
    /// bytes as they are read in order, the whole file (its provenance hash from one read).
    pub(crate) fn bytes_around_data(&self, path: &Path, ny: usize) -> Result<(Vec<u8>, Vec<u8>), Error> {
        use std::os::unix::fs::FileExt;
        let len = self.file.metadata().map_err(|e| read_error(path, e))?.len();
        let end = self.data_start + (self.nx * ny * self.kind.bytes()) as u64;
        let (Ok(h), Some(t)) = (usize::try_from(self.data_start), len.checked_sub(end)) else {
            return Err(read_error(path, "the file is shorter than its header says"));
        };
        let mut head = vec![0u8; h];
        self.file.read_exact_at(&mut head, 0).map_err(|e| read_error(path, e))?;
        let mut tail = vec![0u8; t as usize];
        self.file.read_exact_at(&mut tail, end).map_err(|e| read_error(path, e))?;
        Ok((head, tail))
    }
}

/// Where an image's pixels are read from: the file itself, by rows, or pixels CFITSIO read
/// whole (compressed files such as `.fits.gz`, scaled data, BLANK).
#[derive(Debug)]
pub(crate) enum StoredRows {
    File(RowFile),
    Memory(Pixels),
}

/// Where the pixels of an opened image will be read from: the file itself by rows when it is
/// plain FITS in a stored type the row decoder knows, else the whole image through CFITSIO now.
pub(crate) fn pixel_source(path: &Path, img: &mut ImageHdu) -> Result<StoredRows, Error> {
    let direct = match raw_kind(img.bitpix, img.bscale, img.bzero) {
        Some(kind) if !img.compressed && !img.blank => direct_rows(path, img, kind)?,
        _ => None,
    };
    Ok(match direct {
        Some(r) => StoredRows::File(r),
        None => StoredRows::Memory(img.read_pixels(path)?),
    })
}

/// The data offset of the image when the file on disk is plain FITS (not a compressed stream
/// CFITSIO inflates); `None` sends the frame through CFITSIO. A file too short for its image
/// is refused here, as CFITSIO would refuse it when reading.
pub(crate) fn direct_rows(path: &Path, img: &mut ImageHdu, kind: RawKind) -> Result<Option<RowFile>, Error> {
    use std::os::unix::fs::FileExt;
    if move_to(&mut img.f, img.index).is_err() {
        return Ok(None);
    }
    let (mut head, mut start, mut end, mut status) = (0i64, 0i64, 0i64, 0i32);
    // SAFETY: the pointer is CFITSIO's own open file, positioned at the image HDU; the
    // outputs are plain integers.
    unsafe {
        fitsio::sys::ffghadll(img.f.as_raw(), &mut head, &mut start, &mut end, &mut status);
    }
    if status != 0 || start <= 0 {
        return Ok(None);
    }
    let Ok(file) = std::fs::File::open(&img.disk) else { return Ok(None) };
    let mut magic = [0u8; 9];
    if file.read_exact_at(&mut magic, 0).is_err() || &magic != b"SIMPLE  =" {
        return Ok(None);
    }
    let len = file.metadata().map_err(|e| read_error(path, e))?.len();
    let need = start as u64 + (img.nx * img.ny * kind.bytes()) as u64;
    if len < need {
        return Err(read_error(
            path,
            format!("the file has {len} bytes, its {} x {} image needs {need}", img.nx, img.ny),
        ));
    }
    Ok(Some(RowFile { file, data_start: start as u64, kind, nx: img.nx }))
}

impl RawKind {
    /// Decode `out.len()` pixels starting at pixel `start` of `bytes` (exact for every kind);
    /// always inlined so that a vectorized caller decodes with its own vector width.
    #[inline(always)]
    pub(crate) fn decode_at(self, bytes: &[u8], start: usize, out: &mut [f64]) {
        let b = self.bytes();
        self.decode(&bytes[start * b..(start + out.len()) * b], out)
    }
}
