//! FITS frame input and output: one image per exposure in the primary HDU, the HWP angle,
//! filter and exposure time in the header keywords the instrument file names (for FORS:
//! `HIERARCH ESO INS RETA2 POSANG`, `HIERARCH ESO INS FILT1 NAME`, `EXPTIME`).
//!
//! Simulated frames are written by [`write_frame`] and read back by [`read_frame`], the same
//! function that reads real frames. Keywords longer than 8 characters are written with the
//! ESO `HIERARCH` convention (CFITSIO does this for any name that starts with `HIERARCH `).
//! Every file is written atomically: a temporary file in the target folder, renamed into
//! place only when complete, so a failed run leaves no partial output.

use crate::{fits_err, Error};
use fitsio::images::{ImageDescription, ImageType};
use fitsio::FitsFile;
use instrument::Instrument;
use std::path::{Path, PathBuf};

/// One exposure as read from disk.
#[derive(Debug, Clone)]
pub struct Frame {
    pub path: PathBuf,
    pub nx: usize,
    pub ny: usize,
    /// Pixel values (ADU, BZERO/BSCALE applied), row-major `[y * nx + x]`.
    pub data: Vec<f64>,
    /// HWP angle (deg) from the instrument's keyword.
    pub hwp_deg: f64,
    /// Filter name as found in the header.
    pub filter: String,
    /// Exposure time (s), if the keyword is present.
    pub exptime_s: Option<f64>,
    /// BITPIX of the file (8, 16, 32, 64, -32, -64).
    pub bitpix: i32,
    /// How the values become electrons (the instrument's ADU, or already electrons).
    pub conversion: Conversion,
}

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

/// A temporary file (`.instpol-*SUFFIX`) in the folder of `path`, to be renamed onto it: the
/// one way the workspace starts writing an output, so that a failed run leaves no half file.
/// It gets the permissions of an ordinary new file (0o666 less the umask) rather than
/// tempfile's private 0o600, which a rename would otherwise carry into the output.
pub fn temp_beside(path: &Path, suffix: &str) -> std::io::Result<tempfile::NamedTempFile> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let mut b = tempfile::Builder::new();
    b.prefix(".instpol-").suffix(suffix);
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

/// The celestial WCS of a frame file's first image HDU (see [`crate::maps::CelestialWcs::read`]),
/// when that image is `nx x ny` px (the map's detector pixels); `Err(why)` when there is one
/// that cannot be carried.
pub fn celestial_wcs_of(path: &Path, nx: usize, ny: usize) -> Result<Option<crate::maps::CelestialWcs>, String> {
    let mut f = FitsFile::open(path).map_err(|e| e.to_string())?;
    let n_hdu = f.iter().count();
    for i in 0..n_hdu {
        let h = f.hdu(i).map_err(|e| e.to_string())?;
        if let fitsio::hdu::HduInfo::ImageInfo { shape, .. } = &h.info {
            if shape.len() == 2 {
                let w = crate::maps::CelestialWcs::read(&mut f, &h)?;
                return match w {
                    Some(_) if shape[..] != [ny, nx] => {
                        Err(format!("the image is {} x {} px, the reduced frame {nx} x {ny} px", shape[1], shape[0]))
                    }
                    w => Ok(w),
                };
            }
        }
    }
    Ok(None)
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

/// How a frame's values become electrons: `(value - bias) * gain`; values at or above
/// `saturation` are saturated; `read_noise_e2` is each pixel's read-noise variance (e-^2).
/// Plain frames use the instrument's `[detector]`; frames calibrated on reading (trimmed,
/// overscan- and bias-subtracted, flat-fielded, chips assembled) are already in electrons
/// ([`Conversion::electrons`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Conversion {
    pub bias: f64,
    pub gain: f64,
    pub saturation: f64,
    pub read_noise_e2: f64,
}

/// The value a calibrated image carries for a pixel saturated in the raw frame: far above
/// any number of electrons, finite in f32, so it still counts as saturated (not NaN) after
/// summing repeated exposures (see [`SATURATED_LIMIT`]).
pub const SATURATED: f64 = 1e38;
/// Calibrated values at or above this are saturated: [`SATURATED`] divided by 100, so a sum
/// of up to 100 exposures with one saturated value still reaches `nexp * SATURATED_LIMIT`.
pub const SATURATED_LIMIT: f64 = 1e36;
/// The value of detector pixels no chip covers (the gap of a mosaic): finite and hugely
/// negative, so the reduction masks them as pixels without flux, silently.
pub const GAP: f64 = -1e38;
/// Values at or below this are gap pixels.
pub const GAP_LIMIT: f64 = -1e36;

impl Conversion {
    /// The instrument's `[detector]` numbers (raw ADU frames).
    pub fn of_instrument(inst: &Instrument) -> Self {
        let d = &inst.detector;
        Self {
            bias: d.bias_adu,
            gain: d.gain_e_per_adu,
            saturation: d.saturation_adu,
            read_noise_e2: d.read_noise_e.powi(2),
        }
    }

    /// Frames already in electrons with a read-noise variance `read_noise_e2` (e-^2).
    pub fn electrons(read_noise_e2: f64) -> Self {
        Self { bias: 0.0, gain: 1.0, saturation: SATURATED_LIMIT, read_noise_e2 }
    }

    /// True for frames calibrated to electrons on reading.
    pub fn is_electrons(&self) -> bool {
        self.saturation == SATURATED_LIMIT
    }

    /// `(bias, gain, saturation, read-noise variance)` as the reduction kernel takes them.
    pub(crate) fn det(&self) -> (f64, f64, f64, f64) {
        (self.bias, self.gain, self.saturation, self.read_noise_e2)
    }

    /// The saturation level as people read it.
    pub(crate) fn saturation_label(&self) -> String {
        if self.is_electrons() {
            "the chip's saturation level".into()
        } else {
            format!("{} ADU", self.saturation)
        }
    }
}

/// A frame as stored: header facts and the pixels in their own type.
#[derive(Debug, Clone)]
pub(crate) struct RawFrame {
    pub path: PathBuf,
    pub nx: usize,
    pub ny: usize,
    pub pixels: Pixels,
    pub hwp_deg: f64,
    pub filter: String,
    pub exptime_s: Option<f64>,
    pub bitpix: i32,
    pub conversion: Conversion,
}

impl RawFrame {
    pub(crate) fn into_frame(self) -> Frame {
        let RawFrame { path, nx, ny, pixels, hwp_deg, filter, exptime_s, bitpix, conversion } = self;
        Frame { path, nx, ny, data: pixels.into_f64(), hwp_deg, filter, exptime_s, bitpix, conversion }
    }
}

/// Read one frame, checking what reduction needs: a 2-D image of a detector pixel type (in
/// the primary HDU or an extension, see `open_image`), the size of `inst`'s detector, and the
/// HWP-angle and filter keywords the instrument names (the exposure-time keyword is optional).
/// Frames of instruments whose `[format]` declares chips or a raw bias level go through
/// [`crate::calib`] (trimmed, overscan-corrected, assembled, in electrons).
pub fn read_frame(path: &Path, inst: &Instrument) -> Result<Frame, Error> {
    if inst.format.is_raw() {
        let mut v = crate::calib::read_exposures(&[path.to_path_buf()], inst, &crate::calib::ReadOptions::default())?;
        return v.pop().ok_or(Error::NoFrames);
    }
    read_frame_raw(path, inst).map(RawFrame::into_frame)
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

/// Header facts of a frame, checked against the instrument.
pub(crate) struct FrameHeader {
    pub hwp_deg: Option<f64>,
    pub filter: String,
    pub exptime_s: Option<f64>,
}

/// The HWP angle, filter and exposure time of a frame (image HDU, then primary header), with
/// conflicting duplicates of those and of the pixel keywords refused. The HWP angle is
/// optional here (it may come from `--hwp-angles`); a present but non-numeric one is an error.
pub(crate) fn frame_header(img: &mut ImageHdu, path: &Path, inst: &Instrument) -> Result<FrameHeader, Error> {
    frame_header_with(img, path, inst, true)
}

/// [`frame_header`]; `need_filter` false: a missing filter keyword is an empty name (bias
/// frames are often taken without one).
pub(crate) fn frame_header_with(
    img: &mut ImageHdu,
    path: &Path,
    inst: &Instrument,
    need_filter: bool,
) -> Result<FrameHeader, Error> {
    let pol = &inst.polarimetry;
    let mut keys = vec![pol.hwp_angle_keyword.as_str(), pol.filter_keyword.as_str(), pol.exptime_keyword.as_str()];
    keys.extend(pol.hwp_angle_fallback_keywords.iter().map(|s| s.as_str()));
    keys.extend(inst.format.binning_keywords.iter().map(|s| s.as_str()));
    keys.extend(inst.format.chips.iter().filter_map(|c| c.match_keyword.as_deref()));
    keys.extend(inst.format.exposure_keywords.iter().map(|s| s.as_str()));
    img.check_duplicates(path, &keys)?;
    // The instrument's keyword, else its fallbacks in order: the first one present.
    let mut hwp_deg = None;
    if !pol.hwp_angle_keyword.is_empty() {
        for k in std::iter::once(&pol.hwp_angle_keyword).chain(&pol.hwp_angle_fallback_keywords) {
            hwp_deg = img.number(path, k, "an angle in degrees")?;
            if hwp_deg.is_some() {
                break;
            }
        }
    }
    let filter = match img.key(&pol.filter_keyword) {
        Some(f) => f,
        None if !need_filter => String::new(),
        None => return Err(Error::MissingKeyword { path: path.into(), keyword: pol.filter_keyword.clone() }),
    };
    let exptime_s = img.key(&pol.exptime_keyword).and_then(|s| parse_number(&s));
    Ok(FrameHeader { hwp_deg, filter, exptime_s })
}

/// The HWP angle of a frame or the error that says where it should have come from.
pub(crate) fn require_hwp(h: Option<f64>, path: &Path, inst: &Instrument) -> Result<f64, Error> {
    let k = &inst.polarimetry.hwp_angle_keyword;
    h.ok_or_else(|| {
        if k.is_empty() {
            Error::Invalid(format!(
                "{}: no HWP angle: instrument {} names no HWP-angle keyword; give the angles with --hwp-angles",
                path.display(),
                inst.name
            ))
        } else {
            let mut keyword = k.clone();
            for f in &inst.polarimetry.hwp_angle_fallback_keywords {
                keyword.push_str(&format!("' or '{f}"));
            }
            Error::MissingKeyword { path: path.into(), keyword }
        }
    })
}

/// Open a plain frame (one image, already trimmed, in the instrument's ADU) and check it: a
/// 2-D image of a detector type, the size of `inst`'s detector, its keywords.
fn open_checked(path: &Path, inst: &Instrument, hwp_optional: bool) -> Result<(ImageHdu, FrameHeader), Error> {
    let mut img = open_image(path, &inst.format.hdu)?;
    check_bitpix(path, img.bitpix)?;
    let d = &inst.detector;
    if img.nx != d.nx || img.ny != d.ny {
        return Err(Error::SizeMismatch {
            path: path.into(),
            got_nx: img.nx,
            got_ny: img.ny,
            expected: format!("instrument {} has a {} x {} detector", inst.name, d.nx, d.ny),
        });
    }
    let mut h = frame_header(&mut img, path, inst)?;
    if !hwp_optional {
        h.hwp_deg = Some(require_hwp(h.hwp_deg, path, inst)?);
    }
    Ok((img, h))
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

/// [`read_frame`] of a plain frame keeping the stored pixel type; scaled data (BSCALE/BZERO
/// other than the unsigned 16-bit convention) and BLANK-flagged or compressed images are
/// read as f64.
pub(crate) fn read_frame_raw(path: &Path, inst: &Instrument) -> Result<RawFrame, Error> {
    read_frame_raw_with(path, inst, false)
}

/// [`read_frame_raw`]; `hwp_optional`: a missing HWP angle is NaN (it comes from elsewhere).
pub(crate) fn read_frame_raw_with(path: &Path, inst: &Instrument, hwp_optional: bool) -> Result<RawFrame, Error> {
    let (mut img, h) = open_checked(path, inst, hwp_optional)?;
    let pixels = img.read_pixels(path)?;
    Ok(RawFrame {
        path: path.into(),
        nx: img.nx,
        ny: img.ny,
        pixels,
        hwp_deg: h.hwp_deg.unwrap_or(f64::NAN),
        filter: h.filter,
        exptime_s: h.exptime_s,
        bitpix: img.bitpix,
        conversion: Conversion::of_instrument(inst),
    })
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

/// Where a frame's rows come from: the file itself, pixels CFITSIO read whole (compressed
/// files such as `.fits.gz`, scaled data), or raw chip files calibrated row by row as they
/// are read ([`crate::calib::Calibrated`]: overscan, bias, gain and flat applied on the fly).
#[derive(Debug)]
pub(crate) enum FrameRows {
    File(RowFile),
    Memory(Pixels),
    Calibrated(crate::calib::Calibrated),
}

/// A frame opened for reduction, its header checked as by [`read_frame`].
#[derive(Debug)]
pub(crate) struct OpenFrame {
    pub path: PathBuf,
    pub nx: usize,
    pub ny: usize,
    pub hwp_deg: f64,
    pub filter: String,
    pub rows: FrameRows,
    /// How the values become electrons.
    pub conversion: Conversion,
}

/// Open a plain frame for reduction: the header is checked now; the pixels are read later, by
/// rows, except where only CFITSIO can decode them (gzip, tile compression, scaling, BLANK).
/// `hwp_optional`: a missing HWP angle is NaN (it comes from `--hwp-angles`).
pub(crate) fn open_frame_with(path: &Path, inst: &Instrument, hwp_optional: bool) -> Result<OpenFrame, Error> {
    let (mut img, h) = open_checked(path, inst, hwp_optional)?;
    let rows = pixel_source(path, &mut img)?;
    Ok(OpenFrame {
        path: path.into(),
        nx: img.nx,
        ny: img.ny,
        hwp_deg: h.hwp_deg.unwrap_or(f64::NAN),
        filter: h.filter,
        rows,
        conversion: Conversion::of_instrument(inst),
    })
}

/// Where the pixels of an opened image will be read from: the file itself by rows when it is
/// plain FITS in a stored type the row decoder knows, else the whole image through CFITSIO now.
pub(crate) fn pixel_source(path: &Path, img: &mut ImageHdu) -> Result<FrameRows, Error> {
    let direct = match raw_kind(img.bitpix, img.bscale, img.bzero) {
        Some(kind) if !img.compressed && !img.blank => direct_rows(path, img, kind)?,
        _ => None,
    };
    Ok(match direct {
        Some(r) => FrameRows::File(r),
        None => FrameRows::Memory(img.read_pixels(path)?),
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

impl OpenFrame {
    /// Rows `row0 .. row0 + out.len() / nx` as f64 ADU into `out`; `bytes` is scratch.
    pub(crate) fn load_rows(&self, row0: usize, out: &mut [f64], bytes: &mut Vec<u8>) -> Result<(), Error> {
        match &self.rows {
            FrameRows::Memory(p) => {
                p.view().load(row0 * self.nx, out);
                Ok(())
            }
            FrameRows::File(r) => {
                r.kind.decode(self.stored_rows(r, row0, out.len(), bytes)?, out);
                Ok(())
            }
            FrameRows::Calibrated(c) => c.load_rows(row0, out, bytes),
        }
    }

    /// [`OpenFrame::load_rows`] and [`PixelView::count_bad`] of the rows loaded, in one pass
    /// over them where the rows come from the file as stored (the count re-read every row
    /// decoded: 3 % of a catalog's CPU time).
    pub(crate) fn load_rows_counting(
        &self,
        row0: usize,
        out: &mut [f64],
        bytes: &mut Vec<u8>,
        sat: f64,
    ) -> Result<(usize, usize), Error> {
        match &self.rows {
            FrameRows::File(r) => Ok(r.kind.decode_counting(self.stored_rows(r, row0, out.len(), bytes)?, out, sat)),
            _ => {
                self.load_rows(row0, out, bytes)?;
                Ok(PixelView::F64(out).count_bad(sat))
            }
        }
    }

    /// The stored bytes of `n` pixels from row `row0` on, read into `bytes` (scratch).
    fn stored_rows<'b>(&self, r: &RowFile, row0: usize, n: usize, bytes: &'b mut Vec<u8>) -> Result<&'b [u8], Error> {
        let nb = n * r.kind.bytes();
        bytes.resize(nb, 0);
        self.read_raw(r, row0, &mut bytes[..nb])?;
        Ok(&bytes[..nb])
    }

    /// Rows from `row0` as stored (big-endian, `r.kind`), as many as fill `out`.
    pub(crate) fn read_raw(&self, r: &RowFile, row0: usize, out: &mut [u8]) -> Result<(), Error> {
        use std::os::unix::fs::FileExt;
        let at = r.data_start + (row0 * r.nx * r.kind.bytes()) as u64;
        r.file.read_exact_at(out, at).map_err(|e| read_error(&self.path, e))
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn tiny_instrument() -> Instrument {
        let text = include_str!("../../../instruments/fors1.toml")
            .replace("nx = 2048", "nx = 64")
            .replace("ny = 2048", "ny = 64")
            .replace("throw_arcsec = 22.0", "throw_arcsec = 2.0")
            .replace("strip_count = 9", "strip_count = 3")
            .replace("first_strip_y_px = 34", "first_strip_y_px = 2");
        Instrument::from_toml_str(&text, Path::new("tiny.toml")).unwrap()
    }

    fn keys(inst: &Instrument, hwp: f64) -> Vec<(String, KeyValue, String)> {
        vec![
            (inst.polarimetry.hwp_angle_keyword.clone(), KeyValue::F64(hwp), "HWP angle [deg]".into()),
            (inst.polarimetry.filter_keyword.clone(), KeyValue::Str("V_BESS".into()), String::new()),
            ("EXPTIME".into(), KeyValue::F64(30.0), "[s]".into()),
        ]
    }

    #[test]
    fn hierarch_keywords_and_pixels_round_trip() {
        let inst = tiny_instrument();
        let dir = tempfile::tempdir().unwrap();
        let data: Vec<f64> = (0..64 * 64).map(|i| 1000.0 + i as f64 * 0.25).collect();
        for (bp, tol) in [(Bitpix::F64, 0.0), (Bitpix::F32, 1e-3), (Bitpix::U16, 0.5)] {
            let p = dir.path().join(format!("f{bp:?}.fits"));
            write_frame(&p, 64, 64, &data, bp, &keys(&inst, 22.5)).unwrap();
            let fr = read_frame(&p, &inst).unwrap();
            assert_eq!(fr.hwp_deg, 22.5);
            assert_eq!(fr.filter, "V_BESS");
            assert_eq!(fr.exptime_s, Some(30.0));
            assert_eq!(
                fr.bitpix,
                match bp {
                    Bitpix::U16 => 16,
                    Bitpix::F32 => -32,
                    Bitpix::F64 => -64,
                }
            );
            for (a, b) in fr.data.iter().zip(&data) {
                assert!((a - b).abs() <= tol, "{bp:?}: {a} vs {b}");
            }
            // The keyword is written as an ESO HIERARCH card, readable by its full name.
            let text = std::fs::read(&p).unwrap();
            let s = String::from_utf8_lossy(&text[..2880]);
            assert!(s.contains("HIERARCH ESO INS RETA2 POSANG"), "{s}");
        }
    }

    #[test]
    fn missing_keyword_is_named() {
        let inst = tiny_instrument();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("nokey.fits");
        let mut k = keys(&inst, 0.0);
        k.remove(1);
        write_frame(&p, 64, 64, &vec![1.0; 64 * 64], Bitpix::F32, &k).unwrap();
        let e = read_frame(&p, &inst).unwrap_err().to_string();
        assert!(e.contains("HIERARCH ESO INS FILT1 NAME") && e.contains("nokey.fits"), "{e}");
    }

    #[test]
    fn truncated_and_wrong_size_are_errors() {
        let inst = tiny_instrument();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.fits");
        write_frame(&p, 64, 64, &vec![1.0; 64 * 64], Bitpix::F64, &keys(&inst, 0.0)).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..2880 + 1000]).unwrap();
        let e = read_frame(&p, &inst).unwrap_err().to_string();
        assert!(e.contains("t.fits"), "{e}");
        let p2 = dir.path().join("small.fits");
        write_frame(&p2, 32, 64, &vec![1.0; 32 * 64], Bitpix::F64, &keys(&inst, 0.0)).unwrap();
        let e = read_frame(&p2, &inst).unwrap_err().to_string();
        assert!(e.contains("32 x 64") && e.contains("small.fits"), "{e}");
        let p3 = dir.path().join("garbage.fits");
        std::fs::write(&p3, b"not a fits file at all").unwrap();
        assert!(read_frame(&p3, &inst).unwrap_err().to_string().contains("garbage.fits"));
    }

    /// The reduction's fast path reads rows straight from the file for images in an extension
    /// (`[CHIP1]`, found automatically) as for the primary, and CFITSIO reads gzip, tile
    /// compression and BLANK images whole: either way the pixels of `read_frame` (which
    /// `tests/formats.rs` checks against astropy).
    #[test]
    fn rows_of_extension_and_compressed_frames_are_the_frame_pixels() {
        let text = include_str!("../../../instruments/fors1.toml")
            .replace("nx = 2048", "nx = 12")
            .replace("ny = 2048", "ny = 20")
            .replace("throw_arcsec = 22.0", "throw_arcsec = 2.0")
            .replace("strip_count = 9", "strip_count = 1")
            .replace("first_strip_y_px = 34", "first_strip_y_px = 0");
        let inst = Instrument::from_toml_str(&text, Path::new("t.toml")).unwrap();
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/formats");
        for (name, direct) in [
            ("ext1.fits", true),
            ("mef.fits[CHIP1]", true),
            ("prim_i16.fits", true),
            ("rice_u16.fits.fz", false),
            ("gz_u16.fits.gz", false),
            ("prim_blank.fits", false),
            ("prim_scaled.fits", false),
        ] {
            let p = dir.join(name);
            let want = read_frame(&p, &inst).unwrap().data;
            let of = open_frame_with(&p, &inst, false).unwrap();
            assert_eq!(matches!(of.rows, FrameRows::File(_)), direct, "{name}");
            let mut got = vec![0.0; 12 * 20];
            of.load_rows(0, &mut got, &mut Vec::new()).unwrap();
            for (a, b) in got.iter().zip(&want) {
                assert!(a == b || (a.is_nan() && b.is_nan()), "{name}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn failed_write_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.fits");
        let r = write_fits_atomic(&p, |_| Err(Error::Invalid("boom".into())));
        assert!(r.is_err());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
