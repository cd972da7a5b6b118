//! A frame: one exposure's detector image with the header facts the reduction needs, the HWP
//! angle, filter and exposure time in the header keywords the instrument file names (for FORS:
//! `HIERARCH ESO INS RETA2 POSANG`, `HIERARCH ESO INS FILT1 NAME`, `EXPTIME`), and how its
//! values become electrons ([`Conversion`]); and the reading of a plain frame (one image,
//! already trimmed, in the instrument's ADU). Above the FITS primitives ([`crate::fits`]),
//! below the raw calibration ([`crate::calib`]), which makes frames of raw chip files, and the
//! entry point ([`crate::io`]), which chooses between the two.

use crate::fits::{check_bitpix, open_image, parse_number, ImageHdu, Pixels};
use crate::Error;
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
    /// HWP angle (deg) from the instrument's keyword; for a plate that turns during the
    /// exposure (`[polarimetry.rotation]`), the middle of the range it swept.
    pub hwp_deg: f64,
    /// The plate angle (deg) swept during the exposure: 0 for a fixed plate.
    pub hwp_sweep_deg: f64,
    /// Filter name as found in the header.
    pub filter: String,
    /// Exposure time (s), if the keyword is present.
    pub exptime_s: Option<f64>,
    /// BITPIX of the file (8, 16, 32, 64, -32, -64).
    pub bitpix: i32,
    /// How the values become electrons (the instrument's ADU, or already electrons).
    pub conversion: Conversion,
    /// The chip files the exposure was assembled from, each with its place on the detector
    /// (empty for a plain frame): what [`file_of`] names a pixel's file by.
    pub chips: Vec<ChipPlace>,
}

/// One chip file's place in an exposure assembled from chips: detector pixels
/// `x0 .. x0 + nx` by `y0 .. y0 + ny`.
#[derive(Debug, Clone, PartialEq)]
pub struct ChipPlace {
    pub path: PathBuf,
    pub x0: usize,
    pub y0: usize,
    pub nx: usize,
    pub ny: usize,
}

impl ChipPlace {
    /// Whether detector pixel `(px, py)` is on this chip.
    pub fn holds(&self, px: usize, py: usize) -> bool {
        (self.x0..self.x0 + self.nx).contains(&px) && (self.y0..self.y0 + self.ny).contains(&py)
    }
}

/// The one decision of which file a detector pixel of an exposure came from: the chip file
/// whose place holds it, else the exposure's `file` (a plain frame, or a pixel between the
/// chips). Every message about a pixel names its file by this.
pub fn file_of<'a>(chips: &'a [ChipPlace], file: &'a Path, px: usize, py: usize) -> &'a Path {
    chips.iter().find(|c| c.holds(px, py)).map_or(file, |c| c.path.as_path())
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
    pub hwp_sweep_deg: f64,
    pub filter: String,
    pub exptime_s: Option<f64>,
    pub bitpix: i32,
    pub conversion: Conversion,
}

impl RawFrame {
    pub(crate) fn into_frame(self) -> Frame {
        let RawFrame { path, nx, ny, pixels, hwp_deg, hwp_sweep_deg, filter, exptime_s, bitpix, conversion } = self;
        Frame {
            path,
            nx,
            ny,
            data: pixels.into_f64(),
            hwp_deg,
            hwp_sweep_deg,
            filter,
            exptime_s,
            bitpix,
            conversion,
            chips: Vec::new(),
        }
    }
}

/// Header facts of a frame, checked against the instrument.
pub(crate) struct FrameHeader {
    pub hwp_deg: Option<f64>,
    /// The plate angle (deg) swept during the exposure (0: fixed).
    pub hwp_sweep_deg: f64,
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
    if let Some(r) = &pol.rotation {
        keys.extend([r.begin_keyword.as_str(), r.end_keyword.as_str(), r.position_keyword.as_str()]);
        keys.retain(|k| !k.is_empty());
    }
    img.check_duplicates(path, &keys)?;
    // A frame that says it is another instrument's is not read as this one's (its detector,
    // keywords and zero angles would be the wrong ones, with no word).
    let ikey = inst.headers.as_ref().map_or("INSTRUME", |h| h.instrument_keyword.as_str());
    if let Some(v) = img.key(ikey).filter(|v| !v.trim().is_empty() && !inst.writes(v)) {
        return Err(Error::Invalid(format!(
            "{}: {ikey} = '{}' says the frame is of another instrument than {}, which it is read as: give that instrument's file (--instrument), or, if it is {}'s, list '{}' in [headers] instrument_values of its file",
            path.display(),
            v.trim(),
            inst.name,
            inst.name,
            v.trim()
        )));
    }
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
    let mut hwp_sweep_deg = 0.0;
    if let Some((mid, sweep)) = rotation_range(img, path, inst)? {
        (hwp_deg, hwp_sweep_deg) = (Some(mid), sweep);
    }
    Ok(FrameHeader { hwp_deg, hwp_sweep_deg, filter, exptime_s })
}

/// The middle angle and sweep (deg) of an exposure of a turning plate
/// (`[polarimetry.rotation]`, `instrument::HwpRotation`): from its begin and end keywords, or
/// from its rotor position. `None` for a fixed plate, or when the header carries none of the
/// keywords (a bias; a science frame is then refused by [`require_hwp`]).
fn rotation_range(img: &mut ImageHdu, path: &Path, inst: &Instrument) -> Result<Option<(f64, f64)>, Error> {
    let Some(r) = &inst.polarimetry.rotation else { return Ok(None) };
    if r.by_position() {
        let Some(pos) = img.number(path, &r.position_keyword, "a rotor position (an integer)")? else {
            return Ok(None);
        };
        let bad = |why: String| Error::BadKeyword {
            path: path.into(),
            keyword: r.position_keyword.clone(),
            value: pos.to_string(),
            expected: why,
        };
        if pos.fract() != 0.0 || pos.abs() > 1e9 {
            return Err(bad("a rotor position (an integer)".into()));
        }
        return r.position_range(pos as i64).map(Some).map_err(bad);
    }
    let begin = img.number(path, &r.begin_keyword, "the plate angle at the exposure's start in degrees")?;
    let end = img.number(path, &r.end_keyword, "the plate angle at the exposure's end in degrees")?;
    match (begin, end) {
        (Some(b), Some(e)) => Ok(Some(instrument::HwpRotation::range(b, e))),
        (None, None) => Ok(None),
        (Some(_), None) => Err(Error::MissingKeyword { path: path.into(), keyword: r.end_keyword.clone() }),
        (None, Some(_)) => Err(Error::MissingKeyword { path: path.into(), keyword: r.begin_keyword.clone() }),
    }
}

/// The HWP angle of a frame or the error that says where it should have come from.
pub(crate) fn require_hwp(h: Option<f64>, path: &Path, inst: &Instrument) -> Result<f64, Error> {
    let k = &inst.polarimetry.hwp_angle_keyword;
    h.ok_or_else(|| {
        if let Some(r) = &inst.polarimetry.rotation {
            let keyword = if r.by_position() {
                r.position_keyword.clone()
            } else {
                format!("{}' and '{}", r.begin_keyword, r.end_keyword)
            };
            Error::MissingKeyword { path: path.into(), keyword }
        } else if k.is_empty() {
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

/// A frame or master `img` read from `path` must be the size of `inst`'s detector; `expected`
/// says what it should have been, in the caller's words.
pub(crate) fn check_size(
    path: &Path,
    img: &ImageHdu,
    inst: &Instrument,
    expected: impl FnOnce() -> String,
) -> Result<(), Error> {
    let d = &inst.detector;
    if img.nx != d.nx || img.ny != d.ny {
        return Err(Error::SizeMismatch { path: path.into(), got_nx: img.nx, got_ny: img.ny, expected: expected() });
    }
    Ok(())
}

/// Open a plain frame (one image, already trimmed, in the instrument's ADU) and check it: a
/// 2-D image of a detector type, the size of `inst`'s detector, its keywords.
pub(crate) fn open_checked(
    path: &Path,
    inst: &Instrument,
    hwp_optional: bool,
) -> Result<(ImageHdu, FrameHeader), Error> {
    let mut img = open_image(path, &inst.format.hdu)?;
    check_bitpix(path, img.bitpix)?;
    check_size(path, &img, inst, || {
        let d = &inst.detector;
        format!("instrument {} has a {} x {} detector", inst.name, d.nx, d.ny)
    })?;
    let mut h = frame_header(&mut img, path, inst)?;
    if !hwp_optional {
        h.hwp_deg = Some(require_hwp(h.hwp_deg, path, inst)?);
    }
    Ok((img, h))
}

/// [`crate::io::read_frame`] of a plain frame keeping the stored pixel type; scaled data (BSCALE/BZERO
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
        hwp_sweep_deg: h.hwp_sweep_deg,
        filter: h.filter,
        exptime_s: h.exptime_s,
        bitpix: img.bitpix,
        conversion: Conversion::of_instrument(inst),
    })
}
