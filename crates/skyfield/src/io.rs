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
    /// BITPIX of the file (16, 32, -32, -64).
    pub bitpix: i32,
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
        for (k, v, c) in keys {
            match v {
                KeyValue::F64(x) => hdu.write_key(f, k, (*x, c.as_str())),
                KeyValue::I64(x) => hdu.write_key(f, k, (*x, c.as_str())),
                KeyValue::Str(s) => hdu.write_key(f, k, s.as_str()),
            }
            .map_err(|x| Error::Write { path: path.into(), message: format!("keyword {k}: {x}") })?;
        }
        Ok(())
    })
}

fn read_key_string(f: &mut FitsFile, hdu: &fitsio::hdu::FitsHdu, key: &str) -> Option<String> {
    read_key_str(f, hdu, key).ok().map(|s| s.trim().to_string())
}

/// Read the string value of keyword `key` of `hdu`: the one string-keyword reader for
/// untrusted files. fitsio 0.21's `read_key::<String>` gives CFITSIO a 71-byte value buffer,
/// and CFITSIO writes 72 bytes for a card whose value starts right after the `=` and fills
/// the card (a heap overflow, found by the frame_fits fuzz target): this reads into buffers
/// longer than a whole card.
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

    /// Number of non-finite pixels and of pixels at or above `sat`, in one pass.
    pub(crate) fn count_bad(&self, sat: f64) -> (usize, usize) {
        fn go<T: Copy>(v: &[T], f: impl Fn(T) -> f64, sat: f64) -> (usize, usize) {
            v.iter().fold((0, 0), |(a, b), &x| {
                let x = f(x);
                (a + !x.is_finite() as usize, b + (x >= sat) as usize)
            })
        }
        match self {
            PixelView::F32(v) => go(v, |x| x as f64, sat),
            PixelView::U16(v) => go(v, |x| x as f64, sat),
            PixelView::I16(v) => go(v, |x| x as f64, sat),
            PixelView::F64(v) => go(v, |x| x, sat),
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
}

impl RawFrame {
    pub(crate) fn into_frame(self) -> Frame {
        let RawFrame { path, nx, ny, pixels, hwp_deg, filter, exptime_s, bitpix } = self;
        Frame { path, nx, ny, data: pixels.into_f64(), hwp_deg, filter, exptime_s, bitpix }
    }
}

/// Read one frame, checking what reduction needs: a 2-D image in the primary HDU of a
/// detector pixel type, the size of `inst`'s detector, and the HWP-angle and filter keywords
/// the instrument names (the exposure-time keyword is optional).
pub fn read_frame(path: &Path, inst: &Instrument) -> Result<Frame, Error> {
    read_frame_raw(path, inst).map(RawFrame::into_frame)
}

/// Header facts of a frame, checked against the instrument.
struct FrameHeader {
    nx: usize,
    ny: usize,
    hwp_deg: f64,
    filter: String,
    exptime_s: Option<f64>,
    bitpix: i32,
    ty: ImageType,
    bscale: f64,
    bzero: f64,
}

/// Open a frame and check its header: a 2-D image in the primary HDU of a detector pixel
/// type, the size of `inst`'s detector, the HWP-angle and filter keywords the instrument names.
fn open_checked(path: &Path, inst: &Instrument) -> Result<(FitsFile, fitsio::hdu::FitsHdu, FrameHeader), Error> {
    let mut f = FitsFile::open(path).map_err(|e| fits_err(path, format!("cannot open as FITS: {e}")))?;
    let hdu = f.primary_hdu().map_err(|e| fits_err(path, format!("unreadable primary HDU: {e}")))?;
    let (shape, ty) = match &hdu.info {
        fitsio::hdu::HduInfo::ImageInfo { shape, image_type } => (shape.clone(), *image_type),
        _ => return Err(Error::NotImage { path: path.into(), shape: vec![] }),
    };
    let bitpix = match ty {
        ImageType::Short | ImageType::UnsignedShort => 16,
        ImageType::Long | ImageType::UnsignedLong => 32,
        ImageType::Float => -32,
        ImageType::Double => -64,
        ImageType::UnsignedByte | ImageType::Byte => return Err(Error::BadBitpix { path: path.into(), bitpix: 8 }),
        ImageType::LongLong => return Err(Error::BadBitpix { path: path.into(), bitpix: 64 }),
    };
    if shape.len() != 2 {
        return Err(Error::NotImage { path: path.into(), shape });
    }
    let (ny, nx) = (shape[0], shape[1]);
    let d = &inst.detector;
    if nx != d.nx || ny != d.ny {
        return Err(Error::SizeMismatch {
            path: path.into(),
            got_nx: nx,
            got_ny: ny,
            expected: format!("instrument {} has a {} x {} detector", inst.name, d.nx, d.ny),
        });
    }
    let pol = &inst.polarimetry;
    let hwp_s = read_key_string(&mut f, &hdu, &pol.hwp_angle_keyword)
        .ok_or_else(|| Error::MissingKeyword { path: path.into(), keyword: pol.hwp_angle_keyword.clone() })?;
    let hwp_deg: f64 = hwp_s.parse().ok().filter(|v: &f64| v.is_finite()).ok_or_else(|| Error::BadKeyword {
        path: path.into(),
        keyword: pol.hwp_angle_keyword.clone(),
        value: hwp_s.clone(),
        expected: "an angle in degrees".into(),
    })?;
    let filter = read_key_string(&mut f, &hdu, &pol.filter_keyword)
        .ok_or_else(|| Error::MissingKeyword { path: path.into(), keyword: pol.filter_keyword.clone() })?;
    let exptime_s = read_key_string(&mut f, &hdu, &pol.exptime_keyword).and_then(|s| s.parse().ok());
    let bscale = hdu.read_key::<f64>(&mut f, "BSCALE").unwrap_or(1.0);
    let bzero = hdu.read_key::<f64>(&mut f, "BZERO").unwrap_or(0.0);
    Ok((f, hdu, FrameHeader { nx, ny, hwp_deg, filter, exptime_s, bitpix, ty, bscale, bzero }))
}

fn read_error(path: &Path, e: impl std::fmt::Display) -> Error {
    fits_err(path, format!("cannot read the image data (truncated or corrupt file?): {e}"))
}

/// All pixels of an open frame through CFITSIO, in the stored type when that needs no
/// scaling (f32 frames are half the memory of f64 and need no conversion pass), else as f64.
fn read_pixels(path: &Path, f: &mut FitsFile, hdu: &fitsio::hdu::FitsHdu, h: &FrameHeader) -> Result<Pixels, Error> {
    let rerr = |e: fitsio::errors::Error| read_error(path, e);
    let pixels = match raw_kind(h) {
        Some(RawKind::F32) => Pixels::F32(hdu.read_image(f).map_err(rerr)?),
        Some(RawKind::U16) => Pixels::U16(hdu.read_image(f).map_err(rerr)?),
        Some(RawKind::I16) => Pixels::I16(hdu.read_image(f).map_err(rerr)?),
        _ => Pixels::F64(hdu.read_image(f).map_err(rerr)?),
    };
    if pixels.len() != h.nx * h.ny {
        return Err(fits_err(path, format!("read {} pixels, header says {} x {}", pixels.len(), h.nx, h.ny)));
    }
    Ok(pixels)
}

/// [`read_frame`] keeping the stored pixel type; scaled data (BSCALE/BZERO other than the
/// unsigned 16-bit convention) is read as f64.
pub(crate) fn read_frame_raw(path: &Path, inst: &Instrument) -> Result<RawFrame, Error> {
    let (mut f, hdu, h) = open_checked(path, inst)?;
    let pixels = read_pixels(path, &mut f, &hdu, &h)?;
    let FrameHeader { nx, ny, hwp_deg, filter, exptime_s, bitpix, .. } = h;
    Ok(RawFrame { path: path.into(), nx, ny, pixels, hwp_deg, filter, exptime_s, bitpix })
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
    fn decode(self, bytes: &[u8], out: &mut [f64]) {
        match self {
            RawKind::F32 => out
                .iter_mut()
                .zip(bytes.chunks_exact(4))
                .for_each(|(o, b)| *o = f32::from_be_bytes([b[0], b[1], b[2], b[3]]) as f64),
            RawKind::F64 => out
                .iter_mut()
                .zip(bytes.chunks_exact(8))
                .for_each(|(o, b)| *o = f64::from_be_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]])),
            RawKind::I16 => out
                .iter_mut()
                .zip(bytes.chunks_exact(2))
                .for_each(|(o, b)| *o = i16::from_be_bytes([b[0], b[1]]) as f64),
            // Flipping the sign bit adds 32768 to a two's-complement i16.
            RawKind::U16 => out
                .iter_mut()
                .zip(bytes.chunks_exact(2))
                .for_each(|(o, b)| *o = u16::from_be_bytes([b[0] ^ 0x80, b[1]]) as f64),
        }
    }
}

fn raw_kind(h: &FrameHeader) -> Option<RawKind> {
    match (h.ty, h.bscale == 1.0, h.bzero) {
        (ImageType::Float, true, z) if z == 0.0 => Some(RawKind::F32),
        (ImageType::Double, true, z) if z == 0.0 => Some(RawKind::F64),
        (ImageType::Short, true, z) if z == 0.0 => Some(RawKind::I16),
        (ImageType::UnsignedShort, true, z) if z == 32768.0 => Some(RawKind::U16),
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
}

/// Where a frame's rows come from: the file itself, or pixels CFITSIO read whole (compressed
/// files such as `.fits.gz`, scaled data).
#[derive(Debug)]
pub(crate) enum FrameRows {
    File(RowFile),
    Memory(Pixels),
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
}

/// Open a frame for reduction: the header is checked now; the pixels are read later, by rows,
/// except where only CFITSIO can decode them.
pub(crate) fn open_frame(path: &Path, inst: &Instrument) -> Result<OpenFrame, Error> {
    let (mut f, hdu, h) = open_checked(path, inst)?;
    let direct = match raw_kind(&h) {
        Some(kind) => direct_rows(path, &mut f, &h, kind)?,
        None => None,
    };
    let rows = match direct {
        Some(r) => FrameRows::File(r),
        None => FrameRows::Memory(read_pixels(path, &mut f, &hdu, &h)?),
    };
    Ok(OpenFrame { path: path.into(), nx: h.nx, ny: h.ny, hwp_deg: h.hwp_deg, filter: h.filter, rows })
}

/// The data offset of the primary image when the file on disk is plain FITS (not a compressed
/// stream CFITSIO inflates); `None` sends the frame through CFITSIO. A file too short for its
/// image is refused here, as CFITSIO would refuse it when reading.
fn direct_rows(path: &Path, f: &mut FitsFile, h: &FrameHeader, kind: RawKind) -> Result<Option<RowFile>, Error> {
    use std::os::unix::fs::FileExt;
    let (mut head, mut start, mut end, mut status) = (0i64, 0i64, 0i64, 0i32);
    // SAFETY: the pointer is CFITSIO's own open file, positioned at the primary HDU; the
    // outputs are plain integers.
    unsafe {
        fitsio::sys::ffghadll(f.as_raw(), &mut head, &mut start, &mut end, &mut status);
    }
    if status != 0 || head != 0 || start <= 0 {
        return Ok(None);
    }
    let Ok(file) = std::fs::File::open(path) else { return Ok(None) };
    let mut magic = [0u8; 9];
    if file.read_exact_at(&mut magic, 0).is_err() || &magic != b"SIMPLE  =" {
        return Ok(None);
    }
    let len = file.metadata().map_err(|e| read_error(path, e))?.len();
    let need = start as u64 + (h.nx * h.ny * kind.bytes()) as u64;
    if len < need {
        return Err(read_error(path, format!("the file has {len} bytes, its {} x {} image needs {need}", h.nx, h.ny)));
    }
    Ok(Some(RowFile { file, data_start: start as u64, kind, nx: h.nx }))
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
                let nb = out.len() * r.kind.bytes();
                bytes.resize(nb, 0);
                self.read_raw(r, row0, &mut bytes[..nb])?;
                r.kind.decode(&bytes[..nb], out);
                Ok(())
            }
        }
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

    #[test]
    fn failed_write_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.fits");
        let r = write_fits_atomic(&p, |_| Err(Error::Invalid("boom".into())));
        assert!(r.is_err());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
