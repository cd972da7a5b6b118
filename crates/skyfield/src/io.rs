//! The frame entry point: [`read_frame`] reads one exposure whatever the instrument's format
//! (a plain frame, [`crate::frame`], or raw chip files calibrated on reading,
//! [`crate::calib`]), and `open_exposures` opens a reduction's exposures to be read by rows
//! (`OpenFrame`). The top of the frame I/O: below it the raw calibration, the frame and the FITS
//! primitives ([`crate::fits`]; simulated frames are written by its `write_frame` and read
//! back by [`read_frame`], the same function that reads real frames).

use crate::calib::{apply_angles, calibrate_all, read_exposures, Calibrated, ReadOptions, Stage};
use crate::fits::{pixel_source, PixelView, Pixels, RowFile, StoredRows};
use crate::frame::{open_checked, read_frame_raw, Conversion, Frame, RawFrame};
use crate::Error;
use instrument::Instrument;
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Read one frame, checking what reduction needs: a 2-D image of a detector pixel type (in
/// the primary HDU or an extension, see `open_image`), the size of `inst`'s detector, and the
/// HWP-angle and filter keywords the instrument names (the exposure-time keyword is optional).
/// Frames of instruments whose `[format]` declares chips or a raw bias level go through
/// [`crate::calib`] (trimmed, overscan-corrected, assembled, in electrons).
/// The instrument a set of files is read as, when the caller names none: the built-in one whose
/// name the first file's `INSTRUME` keyword carries ([`instrument::builtin_for_keyword`]),
/// with a sentence that says so. No silent default: a file without the keyword, or with a
/// value no built-in writes, is an error that names the file, the value and the built-ins,
/// for the caller to ask for the instrument (`--instrument`, `instrument=`).
pub fn instrument_from_headers(first: &Path) -> Result<(String, String), Error> {
    let known = instrument::builtin_names().join(", ");
    if !first.is_file() {
        return Err(Error::Invalid(format!("cannot read {}: no such file", first.display())));
    }
    let mut f = fitsio::FitsFile::open(first)
        .map_err(|_| Error::Invalid(format!("{}: not a FITS file CFITSIO can open", first.display())))?;
    let ph = f.primary_hdu().map_err(|e| Error::Invalid(format!("{}: {e}", first.display())))?;
    let value =
        crate::fits::read_key_str(&mut f, &ph, "INSTRUME").ok().map(|v| v.trim().to_string()).filter(|v| !v.is_empty());
    let Some(value) = value else {
        return Err(Error::Invalid(format!(
            "{}: no INSTRUME keyword says which instrument wrote it: name the instrument (a built-in one: {known}; or an instrument file)",
            first.display()
        )));
    };
    match instrument::builtin_for_keyword(&value) {
        Some(name) => Ok((
            name.to_string(),
            format!("read as the built-in instrument {name} (INSTRUME = '{value}' in {})", first.display()),
        )),
        None => Err(Error::Invalid(format!(
            "{}: INSTRUME = '{value}' is none of the built-in instruments ({known}): name its instrument file",
            first.display()
        ))),
    }
}

pub fn read_frame(path: &Path, inst: &Instrument) -> Result<Frame, Error> {
    if inst.format.is_raw() {
        let mut v = read_exposures(&[path.to_path_buf()], inst, &ReadOptions::default())?;
        return v.pop().ok_or(Error::NoFrames);
    }
    read_frame_raw(path, inst).map(RawFrame::into_frame)
}

/// Where a frame's rows come from: the file itself, pixels CFITSIO read whole (compressed
/// files such as `.fits.gz`, scaled data), or raw chip files calibrated row by row as they
/// are read ([`Calibrated`]: overscan, bias, gain and flat applied on the fly).
#[derive(Debug)]
pub(crate) enum FrameRows {
    File(RowFile),
    Memory(Pixels),
    Calibrated(Calibrated),
}

impl FrameRows {
    /// The chip files with their places, for rows assembled from chips (else none).
    pub(crate) fn chip_places(&self) -> Vec<crate::frame::ChipPlace> {
        match self {
            FrameRows::Calibrated(c) => c.chip_places(),
            _ => Vec::new(),
        }
    }
}

impl From<StoredRows> for FrameRows {
    fn from(s: StoredRows) -> Self {
        match s {
            StoredRows::File(r) => FrameRows::File(r),
            StoredRows::Memory(p) => FrameRows::Memory(p),
        }
    }
}

/// A frame opened for reduction, its header checked as by [`read_frame`].
#[derive(Debug)]
pub(crate) struct OpenFrame {
    pub path: PathBuf,
    pub nx: usize,
    pub ny: usize,
    pub hwp_deg: f64,
    /// The plate angle swept during the exposure (deg; 0: fixed).
    pub hwp_sweep_deg: f64,
    pub filter: String,
    pub rows: FrameRows,
    /// How the values become electrons.
    pub conversion: Conversion,
}

impl OpenFrame {
    /// Whether the frame is plain (its values as stored), not assembled from raw chip files.
    pub fn is_plain(&self) -> bool {
        !matches!(self.rows, FrameRows::Calibrated(_))
    }

    /// The chip files the exposure was assembled from, with their places (empty for a plain
    /// frame).
    pub fn chip_places(&self) -> Vec<crate::frame::ChipPlace> {
        self.rows.chip_places()
    }
}

/// Open a plain frame for reduction: the header is checked now; the pixels are read later, by
/// rows, except where only CFITSIO can decode them (gzip, tile compression, scaling, BLANK).
/// `hwp_optional`: a missing HWP angle is NaN (it comes from `--hwp-angles`).
pub(crate) fn open_frame_with(path: &Path, inst: &Instrument, hwp_optional: bool) -> Result<OpenFrame, Error> {
    let (mut img, h) = open_checked(path, inst, hwp_optional)?;
    let rows = pixel_source(path, &mut img)?.into();
    Ok(OpenFrame {
        path: path.into(),
        nx: img.nx,
        ny: img.ny,
        hwp_deg: h.hwp_deg.unwrap_or(f64::NAN),
        hwp_sweep_deg: h.hwp_sweep_deg,
        filter: h.filter,
        rows,
        conversion: Conversion::of_instrument(inst),
    })
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
                r.kind().decode(self.stored_rows(r, row0, out.len(), bytes)?, out);
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
            FrameRows::File(r) => Ok(r.kind().decode_counting(self.stored_rows(r, row0, out.len(), bytes)?, out, sat)),
            _ => {
                self.load_rows(row0, out, bytes)?;
                Ok(PixelView::F64(out).count_bad(sat))
            }
        }
    }

    /// The stored bytes of `n` pixels from row `row0` on, read into `bytes` (scratch).
    fn stored_rows<'b>(&self, r: &RowFile, row0: usize, n: usize, bytes: &'b mut Vec<u8>) -> Result<&'b [u8], Error> {
        let nb = n * r.kind().bytes();
        bytes.resize(nb, 0);
        self.read_raw(r, row0, &mut bytes[..nb])?;
        Ok(&bytes[..nb])
    }

    /// Rows from `row0` as stored (big-endian, `r.kind()`), as many as fill `out`.
    pub(crate) fn read_raw(&self, r: &RowFile, row0: usize, out: &mut [u8]) -> Result<(), Error> {
        r.read_rows(&self.path, row0, out)
    }
}

/// [`read_exposures`] for the reduction: plain frames stay on disk to be read by rows; raw
/// ones too, calibrated row by row as the reduction reads them ([`Calibrated`]; `--hwp-angles`
/// applied either way).
pub(crate) fn open_exposures(
    paths: &[PathBuf],
    inst: &Instrument,
    opts: &ReadOptions,
) -> Result<Vec<OpenFrame>, Error> {
    let inst = &*opts.instrument(inst);
    if opts.is_plain(inst) {
        let res: Vec<Result<OpenFrame, Error>> =
            paths.par_iter().map(|p| open_frame_with(p, inst, opts.hwp_angles_deg.is_some())).collect();
        let mut frames: Vec<OpenFrame> = res.into_iter().collect::<Result<_, _>>()?;
        apply_angles(frames.iter_mut().map(|f| (&f.path, &mut f.hwp_deg)), inst, opts)?;
        return Ok(frames);
    }
    let ex = calibrate_all(paths, inst, opts, Stage::Science)?;
    Ok(ex
        .into_iter()
        .map(|e| OpenFrame {
            path: e.path,
            nx: inst.detector.nx,
            ny: inst.detector.ny,
            hwp_deg: e.hwp_deg.unwrap_or(f64::NAN),
            hwp_sweep_deg: e.hwp_sweep_deg,
            filter: e.filter,
            rows: FrameRows::Calibrated(e.rows),
            conversion: Conversion::electrons(e.rn2),
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fits::{write_fits_atomic, write_frame, Bitpix, KeyValue};

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
    /// `tests/it/formats.rs` checks against astropy).
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
