//! Raw frames to calibrated detector images, as the instrument's `[format]` describes them:
//! chip files (or HDUs) matched to the instrument's chips and grouped into exposures, each
//! chip trimmed of its prescan and overscan, its bias level (the robust mean of those regions)
//! and the master bias subtracted, converted to electrons with its gain, divided by the master
//! flat, and placed in one detector frame where pixels no chip covers are the gap. Saturated
//! raw pixels become [`SATURATED`], gap pixels [`GAP`] (both masked by the reduction), BLANK
//! pixels NaN. The result is what every later stage sees: one image per exposure, in
//! electrons ([`Conversion::electrons`]).
//!
//! The image is never made whole for the reduction: an exposure is its chip files' headers,
//! bias levels and the shared masters (`Calibrated`), and the reduction's bands read its
//! detector rows a few at a time, each raw row read once from its file, decoded and calibrated
//! in one pass into the buffer the row kernel folds (`Calibrated::load_rows_with`); the
//! masters' rows are read there too, once per group of rows for all its exposures
//! (`Masters::rows`). Whole frames ([`read_exposures`], the masters' inputs) are the same
//! rows, all of them, with the masters read whole once (`Calibrated::load_rows`).
//!
//! It also makes the calibration frames: [`master_bias`] (overscan-corrected ADU) and
//! [`master_flat`] (bias-free, normalized to a median of 1), each a sigma-clipped mean per
//! pixel, written by [`Master::write`] as FITS with provenance keywords.
//!
//! A frame that still carries its bias level is never reduced silently: with no overscan
//! subtracted and no master bias, a frame whose overscan sits far above zero, or (for an
//! instrument that declares `raw_bias_adu`) whose darkest pixels sit at that bias, is refused.
//!
//! Not done here: per-amplifier regions within one chip, flipped chip read-outs, non-linearity.

use crate::fits::{
    check_bitpix, direct_rows, open_image, parse_number, pixel_source, raw_kind, write_frame, Bitpix, ImageHdu,
    KeyValue, Pixels, RawKind, RowFile, StoredRows,
};
use crate::frame::{
    frame_header_with, read_frame_raw_with, require_hwp, Conversion, Frame, GAP, GAP_LIMIT, SATURATED, SATURATED_LIMIT,
};
use crate::{Error, Warning};
use instrument::{Chip, Correction, Instrument, NumberOrKeyword};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use stokes::stats::robust::{self, Middle, ZeroSpread, MAD_TO_SIGMA};

/// Options of reading: calibration frames and HWP angles given on the command line.
#[derive(Debug, Clone, Default)]
pub struct ReadOptions {
    /// Master bias (from [`master_bias`]): overscan-corrected ADU per detector pixel.
    pub bias: Option<PathBuf>,
    /// Master flat (from [`master_flat`]): relative response per detector pixel.
    pub flat: Option<PathBuf>,
    /// HWP angles (deg), one per exposure in the order given, for headers that have none.
    pub hwp_angles_deg: Option<Vec<f64>>,
    /// The frames are already trimmed, bias-subtracted and assembled into the detector frame
    /// (another pipeline's products): read as one image of the detector's size in ADU, not as
    /// the instrument's raw chip files ([`ReadOptions::instrument`]).
    pub assembled: bool,
    /// Apply `bias` and `flat` even to frames whose instrument declares that correction made
    /// already (`[format] already_corrected`); without it such a master is refused
    /// (`instrument::FrameFormat::check_masters`).
    pub correct_again: bool,
}

/// Why HWP angles given by hand ([`ReadOptions::hwp_angles_deg`]) are refused; a face words
/// it for its option ([`ReadOptions::check_hwp_angles`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HwpAnglesRefusal {
    /// No angle at all.
    Empty,
    /// An angle that is no finite number of degrees.
    NotFinite { index: usize, value: f64 },
}

impl ReadOptions {
    /// The rule of HWP angles given by hand, whichever face gives them: at least one, each a
    /// finite number of degrees.
    pub fn check_hwp_angles(angles_deg: &[f64]) -> Result<(), HwpAnglesRefusal> {
        if angles_deg.is_empty() {
            return Err(HwpAnglesRefusal::Empty);
        }
        match angles_deg.iter().position(|a| !a.is_finite()) {
            Some(index) => Err(HwpAnglesRefusal::NotFinite { index, value: angles_deg[index] }),
            None => Ok(()),
        }
    }

    /// True when frames are read as they are (the instrument's ADU, no calibration step).
    pub fn is_plain(&self, inst: &Instrument) -> bool {
        !self.instrument(inst).format.is_raw() && self.bias.is_none() && self.flat.is_none()
    }

    /// The instrument as these options read its frames: for [`ReadOptions::assembled`]
    /// frames, without its chips (one image of the detector's size, no pre/overscan, the
    /// detector's gain). A declared `raw_bias_adu` stays, so that assembled frames still
    /// carrying that bias are refused as raw ones are.
    pub fn instrument<'a>(&self, inst: &'a Instrument) -> std::borrow::Cow<'a, Instrument> {
        if self.assembled && !inst.format.chips.is_empty() {
            let mut i = inst.clone();
            i.format.chips.clear();
            std::borrow::Cow::Owned(i)
        } else {
            std::borrow::Cow::Borrowed(inst)
        }
    }
}

/// What an exposure is calibrated to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Stage {
    /// Overscan subtracted, ADU (for master biases).
    Bias,
    /// Bias-free electrons, not flat-fielded (for master flats).
    Flat,
    /// Electrons, flat-fielded.
    Science,
}

/// A calibration frame in the detector frame.
#[derive(Debug, Clone)]
pub struct Master {
    /// "BIAS" or "FLAT".
    pub kind: String,
    pub nx: usize,
    pub ny: usize,
    /// Row-major `[y * nx + x]`: ADU for a bias, relative response for a flat; NaN where no
    /// value (gap, every input rejected).
    pub data: Vec<f64>,
    pub inputs: Vec<PathBuf>,
    pub nsigma: f64,
    /// Overscan subtracted from the inputs.
    pub overscan: bool,
    /// The filter of a flat's frames (all one), written as `HIERARCH INSTPOL FILTER` and
    /// checked against the frames it flattens; `None` for a bias.
    pub filter: Option<String>,
    /// The binning of the frames combined (the instrument file's `[format] binning`), written
    /// as `HIERARCH INSTPOL BINNING` ("2x2") and checked against the frames' instrument file.
    pub binning: Option<[u32; 2]>,
    /// The chips assembled into the master (the instrument file's chip names, in its order;
    /// empty for an instrument without chips), written as `HIERARCH INSTPOL CHIPS` and checked
    /// against the frames' instrument file: a master of other chips puts another chip's bias or
    /// response under each pixel.
    pub chips: Vec<String>,
    pub warnings: Vec<Warning>,
}

/// What a master records of the frames' layout: their binning and their chips (`Master::binning`,
/// `Master::chips`).
fn layout_of(inst: &Instrument) -> (Option<[u32; 2]>, Vec<String>) {
    let b = &inst.format.binning;
    let binning = (b.len() == 2).then(|| [b[0], b[1]]);
    (binning, inst.format.chips.iter().map(|c| c.name.clone()).collect())
}

/// The instrument's chips, or one chip covering the detector when it declares none.
fn chips_of(inst: &Instrument) -> Vec<Chip> {
    if !inst.format.chips.is_empty() {
        return inst.format.chips.clone();
    }
    let d = &inst.detector;
    vec![Chip {
        name: "detector".into(),
        match_keyword: None,
        match_value: None,
        hdu: None,
        origin_px: [0, 0],
        size_px: [d.nx, d.ny],
        prescan_x: None,
        overscan_x: None,
        prescan_y: None,
        overscan_y: None,
        subtract_overscan: true,
        gain_e_per_adu: None,
        read_noise_e: None,
        saturation_adu: None,
    }]
}

/// One chip of one exposure: its file, the chip's index and the HDU spec to open it with.
/// (Opened again by the worker that calibrates it: CFITSIO handles cannot cross threads.)
struct ChipFile {
    path: PathBuf,
    chip: usize,
    spec: String,
}

/// Files grouped into exposures, each with one [`ChipFile`] per chip (in chip order). Chips in
/// separate files are matched by their keyword, and the files of one exposure are those that
/// share the format's `exposure_keywords` values, in whatever order the files are given (a
/// shell glob gives every file of one camera before the other's); the exposures come in the
/// order of their first file. A format without exposure keywords takes the files of one
/// exposure next to each other.
fn group_exposures(paths: &[PathBuf], inst: &Instrument, chips: &[Chip]) -> Result<Vec<Vec<ChipFile>>, Error> {
    if paths.is_empty() {
        return Err(Error::NoFrames);
    }
    let by_keyword = chips.iter().any(|c| c.match_keyword.is_some());
    if !by_keyword {
        // Every file is one exposure; each chip is an HDU of it (or the image HDU).
        let res: Vec<Result<Vec<ChipFile>, Error>> = paths
            .iter()
            .map(|p| {
                chips
                    .iter()
                    .enumerate()
                    .map(|(k, c)| {
                        let spec = c.hdu.clone().unwrap_or_else(|| inst.format.hdu.clone());
                        Ok(ChipFile { path: p.clone(), chip: k, spec })
                    })
                    .collect()
            })
            .collect();
        return res.into_iter().collect();
    }
    let opened: Vec<Result<(ChipFile, Vec<String>), Error>> =
        paths.par_iter().map(|p| chip_of_file(p, inst, chips)).collect();
    let opened: Vec<(ChipFile, Vec<String>)> = opened.into_iter().collect::<Result<_, _>>()?;
    if inst.format.exposure_keywords.is_empty() {
        return group_adjacent(opened.into_iter().map(|(c, _)| c), chips, inst);
    }
    group_by_keywords(opened, chips, inst)
}

/// Which chip the file `p` holds (its match keyword's value) and its exposure keywords' values
/// (in the format's order; a missing one is refused, as the file could not be grouped).
fn chip_of_file(p: &Path, inst: &Instrument, chips: &[Chip]) -> Result<(ChipFile, Vec<String>), Error> {
    let mut img = open_image(p, &inst.format.hdu)?;
    let key = chips[0].match_keyword.clone().unwrap_or_default();
    let mut found = None;
    for (k, c) in chips.iter().enumerate() {
        let kw = c.match_keyword.as_deref().unwrap_or_default();
        let v = match img.key(kw) {
            Some(v) => v,
            // A frame of the assembled detector's size without the chip keyword is most likely
            // another pipeline's product: say what to do with it.
            None if (img.nx, img.ny) == (inst.detector.nx, inst.detector.ny) => {
                return Err(Error::Invalid(format!(
                    "{}: missing header keyword '{kw}' (the name of a chip of instrument {}){}",
                    p.display(),
                    inst.name,
                    assembled_hint(img.nx, img.ny, inst)
                )))
            }
            None => return Err(Error::MissingKeyword { path: p.into(), keyword: kw.into() }),
        };
        if c.match_value.as_deref().is_some_and(|m| m.trim() == v) {
            found = Some(k);
            break;
        }
    }
    let chip = found.ok_or_else(|| {
        let v = img.key(&key).unwrap_or_default();
        Error::Invalid(format!(
            "{}: header keyword '{key}' = '{v}' names none of instrument {}'s chips ({}){}",
            p.display(),
            inst.name,
            chips.iter().map(|c| c.match_value.clone().unwrap_or_default()).collect::<Vec<_>>().join(", "),
            assembled_hint(img.nx, img.ny, inst)
        ))
    })?;
    let mut values = Vec::with_capacity(inst.format.exposure_keywords.len());
    for k in &inst.format.exposure_keywords {
        match img.key(k) {
            Some(v) => values.push(v.trim().to_string()),
            None => {
                return Err(Error::Invalid(format!(
                    "{}: missing header keyword '{k}': instrument {} groups its chip files into exposures by {}, so this file cannot be grouped",
                    p.display(),
                    inst.name,
                    inst.format.exposure_keywords.join(", ")
                )))
            }
        }
    }
    Ok((ChipFile { path: p.into(), chip, spec: inst.format.hdu.clone() }, values))
}

/// The chip files of each exposure next to each other (a format without exposure keywords).
fn group_adjacent(
    opened: impl Iterator<Item = ChipFile>,
    chips: &[Chip],
    inst: &Instrument,
) -> Result<Vec<Vec<ChipFile>>, Error> {
    let mut groups: Vec<Vec<ChipFile>> = Vec::new();
    let mut cur: Vec<ChipFile> = Vec::new();
    for cf in opened {
        if cur.iter().any(|c| c.chip == cf.chip) {
            return Err(incomplete(&cur, chips, inst));
        }
        cur.push(cf);
        if cur.len() == chips.len() {
            cur.sort_by_key(|c| c.chip);
            groups.push(std::mem::take(&mut cur));
        }
    }
    if !cur.is_empty() {
        return Err(incomplete(&cur, chips, inst));
    }
    Ok(groups)
}

/// `MOPRNUM = 1, MOPRPOS = 3`: an exposure's keyword values, for messages.
fn exposure_label(inst: &Instrument, values: &[String]) -> String {
    inst.format.exposure_keywords.iter().zip(values).map(|(k, v)| format!("{k} = {v}")).collect::<Vec<_>>().join(", ")
}

/// The files sharing their exposure keywords' values, one per chip, whatever their order; a
/// chip given twice for one exposure, or an exposure lacking a chip, is refused naming the file.
fn group_by_keywords(
    opened: Vec<(ChipFile, Vec<String>)>,
    chips: &[Chip],
    inst: &Instrument,
) -> Result<Vec<Vec<ChipFile>>, Error> {
    let by = inst.format.exposure_keywords.join(", ");
    let mut order: Vec<Vec<String>> = Vec::new();
    let mut slots: std::collections::HashMap<Vec<String>, Vec<Option<ChipFile>>> = Default::default();
    for (cf, values) in opened {
        let slot = slots.entry(values.clone()).or_insert_with(|| {
            order.push(values.clone());
            (0..chips.len()).map(|_| None).collect()
        });
        if let Some(prev) = &slot[cf.chip] {
            return Err(Error::Invalid(format!(
                "{}: chip {} of the exposure {} again ({} is that chip of that exposure already): instrument {} groups its chip files into exposures by {by}; give each exposure's file of each chip once",
                cf.path.display(),
                chips[cf.chip].name,
                exposure_label(inst, &values),
                prev.path.display(),
                inst.name
            )));
        }
        let k = cf.chip;
        slot[k] = Some(cf);
    }
    let mut groups = Vec::with_capacity(order.len());
    for values in order {
        let slot = slots.remove(&values).unwrap_or_default();
        let missing: Vec<&str> =
            slot.iter().zip(chips).filter(|(f, _)| f.is_none()).map(|(_, c)| c.name.as_str()).collect();
        if !missing.is_empty() {
            let have = slot.iter().flatten().next().map(|f| f.path.display().to_string()).unwrap_or_default();
            return Err(Error::Invalid(format!(
                "{have}: the exposure {} has no file of chip {} of instrument {} among the files given (chip files are grouped into exposures by {by}): give every chip's file of each exposure, or leave this one out",
                exposure_label(inst, &values),
                missing.join(", "),
                inst.name
            )));
        }
        groups.push(slot.into_iter().flatten().collect());
    }
    Ok(groups)
}

/// Each chip of the exposure whose (first) file is `first` among `paths`, with the file that
/// holds it: the file itself for an instrument without chips, the exposure's chip files for
/// chips in separate files; empty when the files cannot be grouped, and chips held as HDUs of
/// one file left out (what `crate::catalog::sky_positions` reads a WCS from).
pub(crate) fn first_exposure_chips(paths: &[PathBuf], first: &Path, inst: &Instrument) -> Vec<(Chip, PathBuf)> {
    let chips = chips_of(inst);
    if chips.iter().any(|c| c.hdu.is_some()) && inst.format.chips.len() > 1 {
        return vec![];
    }
    let Ok(groups) = group_exposures(paths, inst, &chips) else { return vec![] };
    let Some(g) = groups.into_iter().find(|g| g.first().is_some_and(|c| c.path == first)) else { return vec![] };
    g.into_iter().map(|c| (chips[c.chip].clone(), c.path)).collect()
}

/// How the files given were grouped into exposures, for the faces to report beside their
/// results: chip files (matched to the instrument's chips by a keyword) grouped by the format's
/// exposure keywords.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Grouping {
    /// Files given.
    pub files: usize,
    /// Exposures formed.
    pub exposures: usize,
    /// The keywords the files of one exposure share (empty: the files of one exposure were
    /// taken next to each other).
    pub exposure_keywords: Vec<String>,
    /// The keyword naming each file's chip (camera).
    pub chip_keyword: String,
}

impl Grouping {
    /// The grouping of `n_files` files read with `opts` into `n_exposures` exposures, when the
    /// instrument's chips come one per file (matched by a keyword); `None` otherwise (a file is
    /// an exposure).
    pub fn of(inst: &Instrument, opts: &ReadOptions, n_files: usize, n_exposures: usize) -> Option<Self> {
        let inst = opts.instrument(inst);
        let chip_keyword = inst.format.chips.iter().find_map(|c| c.match_keyword.clone())?;
        Some(Self {
            files: n_files,
            exposures: n_exposures,
            exposure_keywords: inst.format.exposure_keywords.clone(),
            chip_keyword,
        })
    }

    /// One line for a person: `64 chip files grouped into 32 exposures by MOPRNUM, MOPRPOS
    /// (chip by MOPCNUM)`.
    pub fn describe(&self) -> String {
        let by = if self.exposure_keywords.is_empty() {
            "as given (the files of one exposure next to each other)".to_string()
        } else {
            format!("by {}", self.exposure_keywords.join(", "))
        };
        format!(
            "{} chip files grouped into {} exposures {by} (chip by {})",
            self.files, self.exposures, self.chip_keyword
        )
    }
}

/// For an image of the assembled detector's size read as a raw chip file: what to do if it is
/// another pipeline's trimmed, assembled frame.
fn assembled_hint(nx: usize, ny: usize, inst: &Instrument) -> String {
    if (nx, ny) == (inst.detector.nx, inst.detector.ny) {
        format!(
            "; it has the size of the instrument's assembled detector ({nx} x {ny} px): if it is already trimmed and assembled (another pipeline's frame), give --assembled (Python: assembled=True)"
        )
    } else {
        String::new()
    }
}

fn incomplete(cur: &[ChipFile], chips: &[Chip], inst: &Instrument) -> Error {
    let have: Vec<String> = cur.iter().map(|c| format!("{} ({})", c.path.display(), chips[c.chip].name)).collect();
    let missing: Vec<&str> = chips
        .iter()
        .enumerate()
        .filter(|(k, _)| !cur.iter().any(|c| c.chip == *k))
        .map(|(_, c)| c.name.as_str())
        .collect();
    Error::Invalid(format!(
        "exposure of {} lacks chip {} of instrument {}: give the chip files of each exposure next to each other, all chips of every exposure",
        have.join(", "),
        missing.join(", "),
        inst.name
    ))
}

/// A number of the chip: from the instrument file or the header keyword it names;
/// `Err(name)` for a missing keyword.
fn resolve(
    cf: &mut Opened,
    v: &Option<NumberOrKeyword>,
    default: f64,
    what: &str,
) -> Result<Result<f64, String>, Error> {
    match v {
        None => Ok(Ok(default)),
        Some(NumberOrKeyword::Number(x)) => Ok(Ok(*x)),
        Some(NumberOrKeyword::Keyword(k)) => match cf.img.key(k) {
            None => Ok(Err(k.clone())),
            Some(s) => parse_number(&s).filter(|x| *x >= 0.0).map(Ok).ok_or_else(|| Error::BadKeyword {
                path: cf.path.clone(),
                keyword: k.clone(),
                value: s,
                expected: what.into(),
            }),
        },
    }
}

/// Append the finite values of `v` below `sat` to `out`, in order: every value written, the
/// length advanced only for those kept (no branch per value: nearly all are kept, and the
/// filtering iterator's branches were a third of the overscan's time).
fn push_usable(out: &mut Vec<f64>, v: &[f64], sat: f64) {
    let start = out.len();
    out.resize(start + v.len(), 0.0);
    let dst = &mut out[start..];
    let mut m = 0;
    for &x in v {
        dst[m] = x;
        m += (x.is_finite() & (x < sat)) as usize;
    }
    out.truncate(start + m);
}

/// Robust mean: the mean of the values within 3 robust sigmas (`MAD_TO_SIGMA` times the MAD) of
/// the median, only those equal to it when the MAD is zero (`robust::clipped_mean`).
fn robust_mean(v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    if let Some(m) = robust_mean_of_counts(&v) {
        return Some(m);
    }
    robust::clipped_mean(&v, 3.0, ZeroSpread::KeepMedian)
}

/// [`robust_mean`] of whole numbers spanning less than 2^16 (raw ADU, what a prescan or an
/// overscan holds), from their counts: the same median, MAD and kept mean (sums of whole
/// numbers below 2^53 are exact in any order), without the two selections over some 20 000
/// values per chip. `None` for other values (fractions, `-0`, wide or huge ranges).
fn robust_mean_of_counts(v: &[f64]) -> Option<f64> {
    // Whole numbers below 2^52 in magnitude: adding and taking away 2^52 rounds |x| to a whole
    // number, so it is unchanged exactly when |x| is whole (`fract` is a libm call per value
    // on the baseline target, and the round trip through i64 a scalar conversion: most of this
    // function's time). NaN fails it; values of 2^52 or more make the function answer None
    // below anyway. In blocks of eight with lane-wise accumulators, so that it vectorizes.
    const TWO52: f64 = 4_503_599_627_370_496.0;
    let neg_zero = (-0.0f64).to_bits();
    let (mut lo8, mut hi8, mut bad8) = ([f64::INFINITY; 8], [f64::NEG_INFINITY; 8], [0u64; 8]);
    let mut blocks = v.chunks_exact(8);
    for b in &mut blocks {
        for j in 0..8 {
            let x = b[j];
            lo8[j] = lo8[j].min(x);
            hi8[j] = hi8[j].max(x);
            let t = x.abs();
            bad8[j] |= (!((t + TWO52) - TWO52 == t) | (x.to_bits() == neg_zero)) as u64;
        }
    }
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut whole = bad8.iter().all(|&b| b == 0);
    for j in 0..8 {
        lo = lo.min(lo8[j]);
        hi = hi.max(hi8[j]);
    }
    for &x in blocks.remainder() {
        lo = lo.min(x);
        hi = hi.max(x);
        let t = x.abs();
        whole &= (t + TWO52) - TWO52 == t && x.to_bits() != neg_zero;
    }
    let n = v.len();
    let big = lo.abs().max(hi.abs());
    if !whole || !(hi - lo < 65536.0) || !(big * n as f64 * 2.0 < 9.0e15) {
        return None;
    }
    // Four interleaved histograms, added after: a narrow distribution sends neighbouring
    // values to one counter, and one histogram waited on each increment's store.
    let len = (hi - lo) as usize + 1;
    let mut parts = vec![[0u32; 4]; len];
    let mut quads = v.chunks_exact(4);
    for q in &mut quads {
        for j in 0..4 {
            parts[(q[j] - lo) as usize][j] += 1;
        }
    }
    let mut counts: Vec<usize> = parts.iter().map(|p| p.iter().map(|&c| c as usize).sum()).collect();
    for &x in quads.remainder() {
        counts[(x - lo) as usize] += 1;
    }
    // The index into `counts` of the value of rank `r` (0-based, ascending) of the multiset
    // `counts` describes (`counts[k]` copies of value `k`, in its own units).
    let rank = |counts: &[usize], r: usize| {
        let mut seen = 0;
        counts.iter().position(|&c| {
            seen += c;
            seen > r
        })
    };
    let median_of = |counts: &[usize], total: usize| -> Option<(usize, usize)> {
        let k = total / 2;
        let hi_k = rank(counts, k)?;
        let lo_k = if total % 2 == 1 { hi_k } else { rank(counts, k - 1)? };
        Some((lo_k, hi_k))
    };
    let (a, b) = median_of(&counts, n)?;
    let med = if a == b { lo + a as f64 } else { 0.5 * ((lo + a as f64) + (lo + b as f64)) };
    // Deviations |x - med| are whole or half numbers: counted as twice their value.
    let two_med = 2.0 * med;
    let mut dev = vec![0usize; 2 * counts.len() + 2];
    for (k, &c) in counts.iter().enumerate() {
        if c > 0 {
            dev[(2.0 * (lo + k as f64) - two_med).abs() as usize] += c;
        }
    }
    let (a, b) = median_of(&dev, n)?;
    let mad = if a == b { a as f64 / 2.0 } else { 0.5 * (a as f64 / 2.0 + b as f64 / 2.0) };
    let s = MAD_TO_SIGMA * mad;
    let (mut sum, mut kept) = (0.0, 0usize);
    for (k, &c) in counts.iter().enumerate() {
        let x = lo + k as f64;
        if c > 0 && (x - med).abs() <= 3.0 * s {
            sum += c as f64 * x;
            kept += c;
        }
    }
    Some(if kept == 0 { med } else { sum / kept as f64 })
}

/// What calibrating one exposure found.
pub(crate) struct Exposure {
    pub(crate) path: PathBuf,
    pub(crate) hwp_deg: Option<f64>,
    pub(crate) hwp_sweep_deg: f64,
    pub(crate) filter: String,
    pub(crate) exptime_s: Option<f64>,
    pub(crate) bitpix: i32,
    /// Its calibrated rows, computed as they are read.
    pub(crate) rows: Calibrated,
    /// Largest read-noise variance (e-^2) of its chips.
    pub(crate) rn2: f64,
}

/// The calibration frames of a run: the bias (ADU) and the inverse of the flat, opened once
/// (headers checked) and shared by every exposure.
#[derive(Debug, Default)]
pub(crate) struct Masters {
    bias: Option<OpenMaster>,
    flat: Option<OpenMaster>,
}

/// One master: its file, read by rows where the reduction needs them (each band reads the
/// masters' rows of its detector rows once for all exposures, see [`Masters::rows`]), or whole
/// for the callers that take whole frames (read once, on first use). Reading the two FORS2
/// masters whole was 7-11 ms, one eighth of a raw reduction, before its first row: fresh pages
/// for 34 MB, faulted in and filled on two threads while the other work waited.
#[derive(Debug)]
struct OpenMaster {
    path: PathBuf,
    /// Positioned reads of the stored rows, when the master is plain BITPIX -32 data.
    file: Option<RowFile>,
    nx: usize,
    /// Stored as the inverse (a flat): NaN where the response is not positive.
    inverse: bool,
    /// The filter a master flat records (`HIERARCH INSTPOL FILTER`), when it records one.
    filter: Option<String>,
    whole: std::sync::OnceLock<Vec<f32>>,
    loading: std::sync::Mutex<()>,
}

impl OpenMaster {
    #[inline(always)]
    fn value(&self, f: f32) -> f32 {
        if !self.inverse {
            f
        } else if f > 0.0 {
            1.0 / f
        } else {
            f32::NAN
        }
    }

    /// The whole frame (inverted for a flat), read on first use.
    fn whole(&self) -> Result<&[f32], Error> {
        if let Some(v) = self.whole.get() {
            return Ok(v);
        }
        let _one_reader = self.loading.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(v) = self.whole.get() {
            return Ok(v);
        }
        let mut img = open_image(&self.path, "")?;
        // Masters are written as f32: kept as read (f32 -> f64 -> f32 would be the identity).
        let mut v = match img.read_pixels(&self.path)? {
            Pixels::F32(v) => v,
            other => other.into_f64().into_iter().map(|v| v as f32).collect(),
        };
        if self.inverse {
            v.par_iter_mut().for_each(|f| *f = self.value(*f));
        }
        Ok(self.whole.get_or_init(|| v))
    }

    /// Detector rows `row0 ..` (as many as fill `out`, whole rows).
    fn rows(&self, row0: usize, out: &mut [f32], bytes: &mut Vec<u8>) -> Result<(), Error> {
        let at = row0 * self.nx;
        match (&self.file, self.whole.get()) {
            (Some(r), None) => {
                bytes.resize(4 * out.len(), 0);
                r.read_at(&self.path, at, bytes)?;
                for (o, b) in out.iter_mut().zip(bytes.chunks_exact(4)) {
                    *o = self.value(f32::from_be_bytes(b.try_into().expect("4 bytes")));
                }
            }
            _ => out.copy_from_slice(&self.whole()?[at..at + out.len()]),
        }
        Ok(())
    }
}

impl Masters {
    /// Whether a bias and a flat are given.
    fn given(&self) -> (bool, bool) {
        (self.bias.is_some(), self.flat.is_some())
    }

    /// Detector rows `row0 ..` of the bias and the inverse flat, those given (each as many
    /// rows as fill its slice).
    pub(crate) fn rows(
        &self,
        row0: usize,
        bias: &mut [f32],
        flat: &mut [f32],
        bytes: &mut Vec<u8>,
    ) -> Result<(), Error> {
        for (m, out) in [(&self.bias, bias), (&self.flat, flat)] {
            if let Some(m) = m {
                m.rows(row0, out, bytes)?;
            }
        }
        Ok(())
    }
}

/// Master rows a caller read for detector rows `row0 ..` (see [`Calibrated::load_rows_with`]).
#[derive(Clone, Copy)]
pub(crate) struct MasterRows<'a> {
    pub(crate) row0: usize,
    pub(crate) bias: &'a [f32],
    pub(crate) flat: &'a [f32],
}

/// A method `$name` whose body `$body` runs compiled for AVX-512 or AVX2 where the CPU has
/// them, else as compiled for the baseline: the compiler vectorizes the same IEEE operations 8-
/// or 4-wide (FMA is not enabled), so all give the same bits. Writes, from one signature, the
/// body as the `#[inline(always)]` method `$imp`, the `#[target_feature]` wrappers `$avx512`
/// and `$avx` and the run-time check; callable elsewhere in the crate as
/// `crate::calib::avx2_dispatch!`. (AVX-512 because it took the raw calibration's share of a
/// raw FORS2 reduction's profile from 18 % to 12 %, the fold's from 8 % to 4 %: bench/RESULTS.md.)
macro_rules! avx2_dispatch {
    ($(#[$m:meta])* fn $name:ident / $avx:ident / $avx512:ident => $imp:ident(&$s:ident, $($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        avx2_dispatch!(@ [$(#[$m])*] $name $avx $avx512 $imp $s [&$s] [$($arg: $ty),*] [$($ret)?] $body);
    };
    ($(#[$m:meta])* fn $name:ident / $avx:ident / $avx512:ident => $imp:ident(&mut $s:ident, $($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        avx2_dispatch!(@ [$(#[$m])*] $name $avx $avx512 $imp $s [&mut $s] [$($arg: $ty),*] [$($ret)?] $body);
    };
    (@ [$($m:tt)*] $name:ident $avx:ident $avx512:ident $imp:ident $s:ident [$($recv:tt)*] [$($arg:ident: $ty:ty),*] [$($ret:ty)?] $body:block) => {
        $($m)*
        #[inline]
        fn $name($($recv)*, $($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512bw")
                && std::arch::is_x86_feature_detected!("avx512dq")
                && std::arch::is_x86_feature_detected!("avx512vl")
            {
                // SAFETY: every feature the wrapper is compiled with was checked just above.
                return unsafe { $s.$avx512($($arg),*) };
            }
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: AVX2 support was checked just above.
                return unsafe { $s.$avx($($arg),*) };
            }
            $s.$imp($($arg),*)
        }

        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2")]
        #[allow(clippy::too_many_arguments)]
        unsafe fn $avx($($recv)*, $($arg: $ty),*) $(-> $ret)? {
            $s.$imp($($arg),*)
        }

        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx512f,avx512bw,avx512dq,avx512vl")]
        #[allow(clippy::too_many_arguments)]
        unsafe fn $avx512($($recv)*, $($arg: $ty),*) $(-> $ret)? {
            $s.$imp($($arg),*)
        }

        #[inline(always)]
        #[allow(clippy::too_many_arguments)]
        fn $imp($($recv)*, $($arg: $ty),*) $(-> $ret)? $body
    };
}
#[allow(unused_imports)]
pub(crate) use avx2_dispatch;

/// One chip of one exposure, calibrated row by row as its rows are read: trimmed, its bias
/// level and the master bias subtracted, times its gain, times the master flat's inverse.
#[derive(Debug)]
struct ChipRows {
    path: PathBuf,
    /// The raw chip image: read by rows from the file, or held whole (compressed files).
    src: StoredRows,
    /// Raw row length (prescan + chip + overscan columns).
    rnx: usize,
    prx: usize,
    pry: usize,
    cx: usize,
    cy: usize,
    x0: usize,
    y0: usize,
    /// Subtracted from every raw value (ADU): the overscan level, or the instrument's constant
    /// bias when neither overscan nor master bias is used.
    level: f64,
    /// ADU to what the stage wants (the gain, or 1 for a master bias).
    to_e: f64,
    /// Raw values at or above this are saturated.
    sat: f64,
    use_bias: bool,
    use_flat: bool,
}

impl ChipRows {
    /// Make raw rows `y .. y + n` (raw coordinates) available to [`ChipRows::decode`]: read as
    /// stored into `bytes` from a file (one positioned read), nothing to do when in memory.
    fn fetch(&self, y: usize, n: usize, bytes: &mut Vec<u8>) -> Result<(), Error> {
        if let StoredRows::File(r) = &self.src {
            let nb = n * self.rnx * r.kind().bytes();
            bytes.resize(nb, 0);
            r.read_at(&self.path, y * self.rnx, &mut bytes[..nb])?;
        }
        Ok(())
    }

    /// Raw values (f64 ADU, exact) of row `y + k` from column `x`, as many as fill `out`, after
    /// [`ChipRows::fetch`]`(y, ..)`.
    #[inline(always)]
    fn decode(&self, y: usize, k: usize, x: usize, bytes: &[u8], out: &mut [f64]) {
        match &self.src {
            StoredRows::File(r) => r.kind().decode_at(bytes, k * self.rnx + x, out),
            StoredRows::Memory(p) => p.view().load((y + k) * self.rnx + x, out),
        }
    }

    avx2_dispatch! {
        /// Decode and calibrate raw rows `ry ..` (fetched) into `rows` (whole detector rows of
        /// `nx`, the first at detector index `det0`): decoded into place, then calibrated in
        /// place (both passes stay in L1). 4-wide AVX2 where the CPU has it: the same IEEE
        /// operations (no FMA), so the same bits.
        #[allow(clippy::too_many_arguments)]
        fn calibrate_rows / calibrate_rows_avx2 / calibrate_rows_avx512 => calibrate_rows_impl(
            &self,
            ry: usize,
            det0: usize,
            nx: usize,
            bias: Option<&[f32]>,
            flat: Option<&[f32]>,
            bytes: &[u8],
            rows: &mut [f64],
        ) {
            for (k, row) in rows.chunks_exact_mut(nx).enumerate() {
                let base = det0 + k * nx + self.x0;
                let o = &mut row[self.x0..self.x0 + self.cx];
                self.decode(ry, k, self.prx, bytes, o);
                let bias = bias.map(|m| &m[base..base + self.cx]);
                let flat = flat.map(|m| &m[base..base + self.cx]);
                calibrate_row(o, bias, flat, self.level, self.to_e, self.sat);
            }
        }
    }

    /// Raw row `y` whole.
    fn raw_row(&self, y: usize, out: &mut [f64], bytes: &mut Vec<u8>) -> Result<(), Error> {
        self.fetch(y, 1, bytes)?;
        self.decode(y, 0, 0, bytes, out);
        Ok(())
    }
}

/// An exposure's detector frame, made on demand from its chips ([`ChipRows`]): what the
/// reduction reads in place of a frame in memory, a few rows at a time, so that the raw rows
/// are read, calibrated and folded into the bins in one pass (no whole-frame copies).
#[derive(Debug)]
pub(crate) struct Calibrated {
    chips: Vec<ChipRows>,
    masters: Arc<Masters>,
    nx: usize,
    ny: usize,
}

/// Raw rows of one chip calibrated at once (bounds the scratch buffer).
const CAL_ROWS: usize = 64;

/// Scratch of [`Calibrated::load_rows_summed`], kept between calls: each exposure's raw rows,
/// a decoded row (rows not read straight from a file) and the count weights of a row.
#[derive(Default)]
pub(crate) struct SumScratch {
    bytes: Vec<Vec<u8>>,
    row: Vec<f64>,
    w: Vec<u64>,
    /// A zero bias and a unit inverse flat for absent masters (only ever grown, with those
    /// values).
    zeros: Vec<f32>,
    ones: Vec<f32>,
}

/// One row's calibration as [`Cal::sum`] applies it: the masters' pixels of the row (a zero
/// bias and a unit inverse flat when absent), how many counted ranges cover each pixel, and
/// the chip's level, gain and saturation (raw ADU), and the level at which a calibrated value
/// is counted as saturated (the frames' conversion's).
struct Cal<'a> {
    bias: &'a [f32],
    flat: &'a [f32],
    w: &'a [u64],
    level: f64,
    to_e: f64,
    sat: f64,
    count_sat: f64,
}

impl Cal<'_> {
    /// How value `e` of a pixel covered `w` times counts: `(non-finite, saturated)`.
    #[inline(always)]
    fn weigh(&self, e: f64, w: u64) -> (u64, u64) {
        (if e.is_finite() { 0 } else { w }, if e >= self.count_sat { w } else { 0 })
    }

    /// Calibrate the decoded raw values `raw` (ADU, at least `out.len()`) as `calibrate_row`
    /// does, and set (`first`) or add them to `out`; returns the non-finite and saturated
    /// (`>= count_sat`) calibrated values, each counted `w[i]` times.
    #[inline(always)]
    fn sum(&self, first: bool, out: &mut [f64], raw: &[f64]) -> (usize, usize) {
        let n = out.len();
        let (bias, flat, w, raw) = (&self.bias[..n], &self.flat[..n], &self.w[..n], &raw[..n]);
        let (mut nb, mut ns) = (0u64, 0u64);
        // Two loops, so that neither tests `first` per value.
        if first {
            for i in 0..n {
                let e = calibrated(raw[i], bias[i] as f64, flat[i] as f64, self.level, self.to_e, self.sat);
                let (b, s) = self.weigh(e, w[i]);
                (nb, ns) = (nb + b, ns + s);
                out[i] = e;
            }
        } else {
            for i in 0..n {
                let e = calibrated(raw[i], bias[i] as f64, flat[i] as f64, self.level, self.to_e, self.sat);
                let (b, s) = self.weigh(e, w[i]);
                (nb, ns) = (nb + b, ns + s);
                out[i] += e;
            }
        }
        (nb as usize, ns as usize)
    }

    /// What [`Cal::sum`] counts, without summing: for the rows [`sum_u16_blocked`] flags.
    #[inline(always)]
    fn count<T: Copy>(&self, raw: &[T], value: impl Fn(T) -> f64) -> (usize, usize) {
        let n = raw.len();
        let (bias, flat, w) = (&self.bias[..n], &self.flat[..n], &self.w[..n]);
        let (mut nb, mut ns) = (0u64, 0u64);
        for i in 0..n {
            let e = calibrated(value(raw[i]), bias[i] as f64, flat[i] as f64, self.level, self.to_e, self.sat);
            let (b, s) = self.weigh(e, w[i]);
            (nb, ns) = (nb + b, ns + s);
        }
        (nb as usize, ns as usize)
    }
}

/// Most exposures [`sum_u16_blocked`] sums at once (more go exposure by exposure).
const MAX_BLOCKED: usize = 16;

/// A raw u16 value as stored (big-endian, `BZERO = 32768`: the sign bit flipped), exactly.
#[inline(always)]
fn u16_value(b: [u8; 2]) -> f64 {
    u16::from_be_bytes([b[0] ^ 0x80, b[1]]) as f64
}

/// One raw value calibrated: `(raw - level - bias) * to_e * flat_inv` rounded to f32, saturated
/// raw values [`SATURATED`], NaN raw values NaN (the formula of `calibrate_row`, `Cal::sum` and
/// `sum_u16_blocked`).
#[inline(always)]
fn calibrated(r: f64, b: f64, fi: f64, level: f64, to_e: f64, sat: f64) -> f64 {
    let e = ((r - level - b) * to_e * fi) as f32;
    let e = if r >= sat { SATURATED as f32 } else { e };
    (if r.is_nan() { f32::NAN } else { e }) as f64
}

/// The raw u16 rows `raws` of several exposures (each `(level, gain, saturation ADU)` in
/// `cals`) calibrated and summed in order into `out`, sixteen pixels at a time across all the
/// exposures, so that each sum is stored once rather than once per exposure (the same values
/// and additions in the same order: the same bits). Returns `true` when some calibrated value
/// may be non-finite or at or above `count_sat` (the caller then counts them with
/// [`Cal::count`]; `false` means none is).
#[inline(always)]
fn sum_u16_blocked(
    out: &mut [f64],
    raws: &[&[[u8; 2]]],
    cals: &[(f64, f64, f64)],
    bias: &[f32],
    flat: &[f32],
    count_sat: f64,
) -> bool {
    const B: usize = 16;
    let n = out.len();
    let (bias, flat) = (&bias[..n], &flat[..n]);
    // The largest |e| seen, as bits: for values without their sign the integer order of the
    // bits is the order of the values, with infinities and NaN above every finite value. Two
    // integer operations per value (a mask and a max) instead of two comparisons and their
    // combination; it flags a superset of the bad values (a large negative one too), and the
    // flagged rows are counted exactly.
    const MAGNITUDE: u64 = !(1u64 << 63);
    let mut big = [0u64; B];
    let mut x = 0;
    while x + B <= n {
        let (b, f) = (&bias[x..x + B], &flat[x..x + B]);
        let mut acc = [0.0f64; B];
        for (j, (raw, &(level, to_e, sat))) in raws.iter().zip(cals).enumerate() {
            let r = &raw[x..x + B];
            for i in 0..B {
                let e = calibrated(u16_value(r[i]), b[i] as f64, f[i] as f64, level, to_e, sat);
                big[i] = big[i].max(e.to_bits() & MAGNITUDE);
                acc[i] = if j == 0 { e } else { acc[i] + e };
            }
        }
        out[x..x + B].copy_from_slice(&acc);
        x += B;
    }
    let mut big = big.iter().copied().max().unwrap_or(0);
    for i in x..n {
        for (j, (raw, &(level, to_e, sat))) in raws.iter().zip(cals).enumerate() {
            let e = calibrated(u16_value(raw[i]), bias[i] as f64, flat[i] as f64, level, to_e, sat);
            big = big.max(e.to_bits() & MAGNITUDE);
            out[i] = if j == 0 { e } else { out[i] + e };
        }
    }
    // A threshold that is not a positive number: every row is counted.
    !(count_sat > 0.0) || big >= count_sat.to_bits()
}

/// Raw rows of one chip of every exposure fetched at once when summing exposures
/// ([`Calibrated::load_rows_summed`]): all of them stay in cache until summed.
const SUM_ROWS: usize = 8;

impl Calibrated {
    /// Detector rows `row0 ..` (as many as fill `out`, whole rows) in electrons (f32 values
    /// widened to f64, as a calibrated frame in memory holds them): the gap is [`GAP`], raw
    /// values at or above saturation [`SATURATED`], NaN raw values NaN. `bytes` is scratch.
    /// The masters are read whole (once); see [`Calibrated::load_rows_with`].
    pub(crate) fn load_rows(&self, row0: usize, out: &mut [f64], bytes: &mut Vec<u8>) -> Result<(), Error> {
        fn whole(m: &Option<OpenMaster>) -> Result<Option<&[f32]>, Error> {
            m.as_ref().map(|m| m.whole()).transpose()
        }
        let (bias, flat) = (whole(&self.masters.bias)?, whole(&self.masters.flat)?);
        self.load(row0, out, bytes, 0, bias, flat)
    }

    /// The masters this exposure is calibrated with (shared by the exposures of a run).
    pub(crate) fn masters(&self) -> &Arc<Masters> {
        &self.masters
    }

    /// [`Calibrated::load_rows`] with the masters' rows the caller read ([`Masters::rows`] of
    /// [`Calibrated::masters`]) for at least the rows loaded: the reduction's bands read them
    /// once for all the exposures of a group of rows.
    pub(crate) fn load_rows_with(
        &self,
        row0: usize,
        out: &mut [f64],
        bytes: &mut Vec<u8>,
        m: MasterRows,
    ) -> Result<(), Error> {
        let (bias, flat) = self.masters.given();
        self.load(row0, out, bytes, m.row0, bias.then_some(m.bias), flat.then_some(m.flat))
    }

    /// The rows, with the masters' pixels from detector row `m_row0` on.
    fn load(
        &self,
        row0: usize,
        out: &mut [f64],
        bytes: &mut Vec<u8>,
        m_row0: usize,
        bias: Option<&[f32]>,
        flat: Option<&[f32]>,
    ) -> Result<(), Error> {
        let nx = self.nx;
        let nrows = out.len() / nx;
        debug_assert!(out.len() == nrows * nx && row0 + nrows <= self.ny && m_row0 <= row0);
        // The gap: whatever no chip covers (chips never overlap; each writes all its columns
        // of its rows below), so the chips' pixels are written once, not filled first.
        let gap = GAP as f32 as f64;
        self.fill_gap(row0, out, |v| *v = gap);
        for c in &self.chips {
            // Detector rows of this chip within the request.
            let (a, b) = (row0.max(c.y0), (row0 + nrows).min(c.y0 + c.cy));
            let mut y = a;
            while y < b {
                let n = CAL_ROWS.min(b - y);
                let ry = c.pry + y - c.y0;
                c.fetch(ry, n, bytes)?;
                let rows = &mut out[(y - row0) * nx..(y - row0 + n) * nx];
                let (bias, flat) = (bias.filter(|_| c.use_bias), flat.filter(|_| c.use_flat));
                c.calibrate_rows(ry, (y - m_row0) * nx, nx, bias, flat, bytes, rows);
                y += n;
            }
        }
        Ok(())
    }

    /// The chip files of the exposure, in the instrument file's chip order.
    /// The chip files with their places on the detector.
    pub(crate) fn chip_places(&self) -> Vec<crate::frame::ChipPlace> {
        self.chips
            .iter()
            .map(|c| crate::frame::ChipPlace { path: c.path.clone(), x0: c.x0, y0: c.y0, nx: c.cx, ny: c.cy })
            .collect()
    }

    /// Whether `other`'s rows can be summed with this exposure's by
    /// [`Calibrated::load_rows_summed`]: the same masters and the same chips in the same places.
    pub(crate) fn summable_with(&self, other: &Calibrated) -> bool {
        let place = |c: &ChipRows| (c.x0, c.y0, c.cx, c.cy, c.use_bias, c.use_flat);
        Arc::ptr_eq(&self.masters, &other.masters)
            && (self.nx, self.ny) == (other.nx, other.ny)
            && self.chips.len() == other.chips.len()
            && self.chips.iter().zip(&other.chips).all(|(a, b)| place(a) == place(b))
    }

    /// Detector rows `row0 ..` of the exposures `exps` (each [`Calibrated::summable_with`] the
    /// first) calibrated as [`Calibrated::load_rows_with`] makes them and summed in the order
    /// given (the same values and the same additions in the same order, so the same bits as
    /// loading each and adding), one row at a time so that the row being summed stays in L1
    /// (summing whole groups of rows went through L2: a fifth of a raw FORS2 reduction). Each
    /// exposure's non-finite values and values at or above `sat` are counted into `counts`
    /// over the index ranges `counted` of `out` (ranges may overlap: a pixel is counted once
    /// per range, as the reduction counts its o and e pixels).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn load_rows_summed(
        exps: &[&Calibrated],
        row0: usize,
        out: &mut [f64],
        sc: &mut SumScratch,
        m: MasterRows,
        counted: &[(usize, usize)],
        sat: f64,
        counts: &mut [(usize, usize)],
    ) -> Result<(), Error> {
        let Some(first) = exps.first() else { return Ok(()) };
        debug_assert!(exps.iter().all(|e| first.summable_with(e)));
        let SumScratch { bytes, row, w, zeros, ones } = sc;
        bytes.resize_with(exps.len(), Vec::new);
        let nx = first.nx;
        let nrows = out.len() / nx;
        // The gap, summed as each exposure's gap value would be.
        let gap = GAP as f32 as f64;
        first.fill_gap(row0, out, |v| {
            *v = gap;
            for _ in 1..exps.len() {
                *v += gap;
            }
        });
        // Absent masters as a zero bias and a unit inverse flat: `x - 0` and `x * 1` are `x`
        // exactly, so the values are those of `calibrate_row`'s loops without them.
        let (has_bias, has_flat) = first.masters.given();
        if zeros.len() < nx * nrows {
            zeros.resize(nx * nrows, 0.0);
            ones.resize(nx * nrows, 1.0);
        }
        for (ci, c) in first.chips.iter().enumerate() {
            let (a, b) = (row0.max(c.y0), (row0 + nrows).min(c.y0 + c.cy));
            let mut y = a;
            while y < b {
                // Few rows at a time: every exposure's raw rows stay in cache until summed.
                let n = SUM_ROWS.min(b - y);
                let ry = c.pry + y - c.y0;
                for (e, buf) in exps.iter().zip(bytes.iter_mut()) {
                    e.chips[ci].fetch(ry, n, buf)?;
                }
                let bias = if has_bias && c.use_bias { (m.bias, m.row0) } else { (&zeros[..], row0) };
                let flat = if has_flat && c.use_flat { (m.flat, m.row0) } else { (&ones[..], row0) };
                first.sum_chip_rows(
                    exps,
                    ci,
                    (y, ry, n),
                    row0,
                    (bias, flat),
                    bytes,
                    (row, w),
                    out,
                    counted,
                    sat,
                    counts,
                );
                y += n;
            }
        }
        Ok(())
    }

    avx2_dispatch! {
        /// The rows `y .. y + n` (raw rows `ry ..`, fetched into `bytes`) of chip `ci` of every
        /// exposure, calibrated, counted and summed into `out` (see
        /// [`Calibrated::load_rows_summed`]). Each raw value is decoded, calibrated, counted and
        /// added in one step (no row of calibrated values is stored: stores were this loop's
        /// bound); `w` holds how many of the `counted` ranges cover each pixel of the row.
        #[allow(clippy::too_many_arguments)]
        fn sum_chip_rows / sum_chip_rows_avx2 / sum_chip_rows_avx512 => sum_chip_rows_impl(
            &self,
            exps: &[&Calibrated],
            ci: usize,
            rows: (usize, usize, usize),
            row0: usize,
            masters: ((&[f32], usize), (&[f32], usize)),
            bytes: &[Vec<u8>],
            scratch: (&mut Vec<f64>, &mut Vec<u64>),
            out: &mut [f64],
            counted: &[(usize, usize)],
            sat: f64,
            counts: &mut [(usize, usize)],
        ) {
            let ((y, ry, n), ((bias, b_row0), (flat, f_row0)), (row, w)) = (rows, masters, scratch);
            let (nx, c) = (self.nx, &self.chips[ci]);
            w.resize(c.cx, 0);
            row.resize(c.cx, 0.0);
            for k in 0..n {
                let at = (y + k - row0) * nx + c.x0;
                let (b0, f0) = ((y + k - b_row0) * nx + c.x0, (y + k - f_row0) * nx + c.x0);
                let (bias, flat) = (&bias[b0..b0 + c.cx], &flat[f0..f0 + c.cx]);
                // How many counted ranges cover each pixel of the row (made only where counts
                // are taken: the blocked sum needs them on flagged rows alone).
                let weights = |w: &mut Vec<u64>| {
                    w.fill(0);
                    for &(lo, hi) in counted {
                        let (lo, hi) = (lo.max(at), hi.min(at + c.cx));
                        if lo < hi {
                            w[lo - at..hi - at].iter_mut().for_each(|x| *x += 1);
                        }
                    }
                };
                let o = &mut out[at..at + c.cx];
                // The usual raw chip (u16 as stored, a few exposures): all exposures at once.
                if exps.len() <= MAX_BLOCKED {
                    let mut raws: [&[[u8; 2]]; MAX_BLOCKED] = [&[]; MAX_BLOCKED];
                    let mut cals = [(0.0, 0.0, 0.0); MAX_BLOCKED];
                    let mut all = true;
                    for (j, (e, buf)) in exps.iter().zip(bytes).enumerate() {
                        let ch = &e.chips[ci];
                        match &ch.src {
                            StoredRows::File(r) if r.kind() == RawKind::U16 => {
                                let at = (k * ch.rnx + ch.prx) * 2;
                                raws[j] = buf[at..at + 2 * c.cx].as_chunks::<2>().0;
                                cals[j] = (ch.level, ch.to_e, ch.sat);
                            }
                            _ => all = false,
                        }
                    }
                    if all {
                        let m = exps.len();
                        if sum_u16_blocked(o, &raws[..m], &cals[..m], bias, flat, sat) {
                            // Some value is bad: counted exposure by exposure (rows without
                            // one, nearly all, skip this).
                            weights(w);
                            for (j, (raw, &(level, to_e, sat_adu))) in raws[..m].iter().zip(&cals[..m]).enumerate() {
                                let cal = Cal { bias, flat, w, level, to_e, sat: sat_adu, count_sat: sat };
                                let (a, s) = cal.count(raw, u16_value);
                                counts[j].0 += a;
                                counts[j].1 += s;
                            }
                        }
                        continue;
                    }
                }
                weights(w);
                for (j, (e, buf)) in exps.iter().zip(bytes).enumerate() {
                    let ch = &e.chips[ci];
                    let cal = Cal { bias, flat, w, level: ch.level, to_e: ch.to_e, sat: ch.sat, count_sat: sat };
                    let first = j == 0;
                    // The rarer cases (other encodings, rows in memory, many exposures):
                    // decoded by the chip's own decoder, then calibrated and added.
                    ch.decode(ry, k, ch.prx, buf, row);
                    let (a, s) = cal.sum(first, o, row);
                    counts[j].0 += a;
                    counts[j].1 += s;
                }
            }
        }
    }

    /// Calls `fill` on every pixel of detector rows `row0 ..` (as many as `out` holds) that no
    /// chip covers.
    fn fill_gap(&self, row0: usize, out: &mut [f64], mut fill: impl FnMut(&mut f64)) {
        let nx = self.nx;
        let mut spans: Vec<(usize, usize)> = Vec::with_capacity(self.chips.len());
        for (k, row) in out.chunks_exact_mut(nx).enumerate() {
            let y = row0 + k;
            spans.clear();
            spans.extend(self.chips.iter().filter(|c| y >= c.y0 && y < c.y0 + c.cy).map(|c| (c.x0, c.x0 + c.cx)));
            spans.sort_unstable();
            let mut x = 0;
            for &(a, b) in &spans {
                if a > x {
                    row[x..a].iter_mut().for_each(&mut fill);
                }
                x = x.max(b);
            }
            if x < nx {
                row[x..].iter_mut().for_each(&mut fill);
            }
        }
    }

    /// The whole detector frame.
    fn whole(&self) -> Result<Vec<f64>, Error> {
        let mut out = vec![0.0; self.nx * self.ny];
        let mut bytes = Vec::new();
        for (k, chunk) in out.chunks_mut(CAL_ROWS * self.nx).enumerate() {
            self.load_rows(k * CAL_ROWS, chunk, &mut bytes)?;
        }
        Ok(out)
    }
}

/// Calibrate one row of raw values (ADU) to electrons in place: `(raw - level - bias) * to_e *
/// flat_inv` rounded to f32 (what a calibrated frame stores), saturated raw values
/// [`SATURATED`], NaN raw values NaN. Absent masters are a zero bias and a unit inverse flat.
#[inline(always)]
fn calibrate_row(v: &mut [f64], bias: Option<&[f32]>, flat_inv: Option<&[f32]>, level: f64, to_e: f64, sat: f64) {
    let n = v.len();
    // Four branch-free loops (so each vectorizes), by which masters are given.
    match (bias, flat_inv) {
        (Some(b), Some(f)) => {
            let (b, f) = (&b[..n], &f[..n]);
            for i in 0..n {
                v[i] = calibrated(v[i], b[i] as f64, f[i] as f64, level, to_e, sat);
            }
        }
        (Some(b), None) => {
            let b = &b[..n];
            for i in 0..n {
                v[i] = calibrated(v[i], b[i] as f64, 1.0, level, to_e, sat);
            }
        }
        (None, Some(f)) => {
            let f = &f[..n];
            for i in 0..n {
                v[i] = calibrated(v[i], 0.0, f[i] as f64, level, to_e, sat);
            }
        }
        (None, None) => {
            for i in 0..n {
                v[i] = calibrated(v[i], 0.0, 1.0, level, to_e, sat);
            }
        }
    }
}

/// The binning and chips a master records (`HIERARCH INSTPOL BINNING`, `CHIPS`) checked
/// against the frames' instrument file. A master that records neither (made by another tool)
/// is taken on its size alone.
fn check_master_layout(path: &Path, img: &mut ImageHdu, inst: &Instrument, kind: &str) -> Result<(), Error> {
    let (binning, chips) = layout_of(inst);
    let refuse = |key: &str, got: &str, want: String| {
        Error::Invalid(format!(
            "{}: master {} of {key} {got} (HIERARCH INSTPOL {key}), but instrument {} reads the frames as {key} {want}: make the master from frames of this layout",
            path.display(),
            kind.to_lowercase(),
            inst.name
        ))
    };
    if let (Some(got), Some([bx, by])) = (img.key("HIERARCH INSTPOL BINNING"), binning) {
        let got = got.trim();
        if !got.eq_ignore_ascii_case(&format!("{bx}x{by}")) {
            return Err(refuse("BINNING", got, format!("{bx}x{by}")));
        }
    }
    if let Some(got) = img.key("HIERARCH INSTPOL CHIPS") {
        let got = got.trim();
        let theirs: Vec<&str> = got.split(',').map(str::trim).collect();
        if !chips.is_empty() && theirs != chips.iter().map(String::as_str).collect::<Vec<_>>() {
            return Err(refuse("CHIPS", got, chips.join(",")));
        }
    }
    Ok(())
}

/// A master's header checked against the instrument and the role it is given in; its pixels
/// are read later, by rows or whole ([`OpenMaster`]).
fn open_master(path: &Path, inst: &Instrument, kind: &str) -> Result<OpenMaster, Error> {
    let mut img = open_image(path, "")?;
    check_bitpix(path, img.bitpix)?;
    let d = &inst.detector;
    crate::frame::check_size(path, &img, inst, || {
        format!("a master {} of instrument {} is {} x {}", kind.to_lowercase(), inst.name, d.nx, d.ny)
    })?;
    if let Some(k) = img.key("HIERARCH INSTPOL MASTER") {
        if !k.eq_ignore_ascii_case(kind) {
            return Err(Error::Invalid(format!(
                "{}: is a master {} (HIERARCH INSTPOL MASTER = '{k}'), given where a master {} is needed",
                path.display(),
                k.to_lowercase(),
                kind.to_lowercase()
            )));
        }
    }
    if let Some(i) = img.key("INSTRUME") {
        if !inst.writes(&i) {
            return Err(Error::Invalid(format!(
                "{}: master {} of instrument {i}, but the frames are read as instrument {}",
                path.display(),
                kind.to_lowercase(),
                inst.name
            )));
        }
    }
    check_master_layout(path, &mut img, inst, kind)?;
    let plain = !img.compressed && !img.blank && raw_kind(img.bitpix, img.bscale, img.bzero) == Some(RawKind::F32);
    let file = if plain { direct_rows(path, &mut img, RawKind::F32)? } else { None };
    Ok(OpenMaster {
        path: path.into(),
        file,
        nx: d.nx,
        inverse: kind == "FLAT",
        filter: img.key("HIERARCH INSTPOL FILTER").map(|f| f.trim().to_string()).filter(|f| !f.is_empty()),
        whole: Default::default(),
        loading: Default::default(),
    })
}

/// A chip file opened by the worker calibrating it.
struct Opened {
    path: PathBuf,
    chip: usize,
    img: ImageHdu,
}

/// Calibrate one exposure (its chip files) into the detector frame.
fn calibrate_exposure(
    files: Vec<ChipFile>,
    inst: &Instrument,
    chips: &[Chip],
    stage: Stage,
    masters: &Arc<Masters>,
) -> Result<Exposure, Error> {
    let d = &inst.detector;
    let fmt = &inst.format;
    let (nx, ny) = (d.nx, d.ny);
    let mut chip_rows = Vec::with_capacity(files.len());
    let mut rn2 = 0.0f64;
    let mut heads = Vec::new();
    let mut files: Vec<Opened> = files
        .into_iter()
        .map(|c| Ok(Opened { img: open_image(&c.path, &c.spec)?, path: c.path, chip: c.chip }))
        .collect::<Result<_, Error>>()?;
    for cf in files.iter_mut() {
        let path = cf.path.clone();
        check_bitpix(&path, cf.img.bitpix)?;
        let h = frame_header_with(&mut cf.img, &path, inst, stage == Stage::Science)?;
        let mut exp_keys = Vec::new();
        for k in &fmt.exposure_keywords {
            exp_keys.push((k.clone(), cf.img.key(k)));
        }
        heads.push((h, exp_keys));
        let (chip, rn) = calibrate_chip(cf, &chips[cf.chip], inst, stage, masters)?;
        rn2 = rn2.max(rn * rn);
        chip_rows.push(chip);
    }
    check_one_exposure(&files, &heads, inst)?;
    let (h0, _) = heads.swap_remove(0);
    Ok(Exposure {
        path: files[0].path.clone(),
        hwp_deg: h0.hwp_deg,
        hwp_sweep_deg: h0.hwp_sweep_deg,
        filter: h0.filter,
        exptime_s: h0.exptime_s,
        bitpix: files[0].img.bitpix,
        rows: Calibrated { chips: chip_rows, masters: masters.clone(), nx, ny },
        rn2,
    })
}

/// One chip file's calibration: its binning and regions checked against the instrument, its
/// gain and read noise, and the level to subtract (the pre/overscan's, else the instrument's
/// constant bias, none where a master bias is used or for a master bias itself). Returns the
/// chip's rows to read and its read noise in electrons.
fn calibrate_chip(
    cf: &mut Opened,
    c: &Chip,
    inst: &Instrument,
    stage: Stage,
    masters: &Masters,
) -> Result<(ChipRows, f64), Error> {
    let d = &inst.detector;
    let fmt = &inst.format;
    let path = cf.path.clone();
    check_binning(cf, inst)?;
    let counts = scan_counts(cf, c, inst)?;
    let [prx, _, pry, _] = counts;
    let [cx, cy] = c.size_px;
    let gain = match resolve(cf, &c.gain_e_per_adu, d.gain_e_per_adu, "a gain in e-/ADU")? {
        Ok(g) if g > 0.0 => g,
        Ok(g) => return Err(Error::Invalid(format!("{}: gain {g} e-/ADU must be positive", path.display()))),
        Err(k) => return Err(Error::MissingKeyword { path: path.clone(), keyword: k }),
    };
    let rn = match resolve(cf, &c.read_noise_e, d.read_noise_e, "a read noise in e-")? {
        Ok(r) => r,
        Err(k) => return Err(Error::MissingKeyword { path: path.clone(), keyword: k }),
    };
    let sat = c.saturation_adu.unwrap_or(d.saturation_adu);
    // The raw image stays in its file (read by rows later, as the reduction needs them)
    // unless only CFITSIO can decode it.
    let [x0, y0] = c.origin_px;
    let rnx = cf.img.nx;
    let mut chip = ChipRows {
        path: path.clone(),
        src: pixel_source(&path, &mut cf.img)?,
        rnx,
        prx,
        pry,
        cx,
        cy,
        x0,
        y0,
        level: 0.0,
        to_e: 1.0,
        sat,
        use_bias: false,
        use_flat: false,
    };
    let scan_level = scan_level(&chip, cf.img.ny, counts, c, (rn, gain))?;
    let subtract_scan = c.subtract_overscan && scan_level.is_some();
    let level = if subtract_scan { scan_level.unwrap_or(0.0) } else { 0.0 };
    let bias_map = if stage == Stage::Bias { None } else { masters.bias.as_ref() };
    // A frame still carrying its bias is refused, never reduced silently.
    if stage != Stage::Bias && !subtract_scan && bias_map.is_none() {
        check_bias_removed(&chip, c, inst, scan_level, rn / gain)?;
    }
    // Without overscan or master bias, the instrument's constant bias (as for plain frames),
    // unless the frames are declared bias corrected already.
    let const_bias = if stage != Stage::Bias && !subtract_scan && bias_map.is_none() && !fmt.already(Correction::Bias) {
        d.bias_adu
    } else {
        0.0
    };
    chip.level = level + const_bias;
    chip.to_e = if stage == Stage::Bias { 1.0 } else { gain };
    chip.use_bias = bias_map.is_some();
    chip.use_flat = stage == Stage::Science && masters.flat.is_some();
    Ok((chip, rn))
}

/// The chip file's binning, where the format names its keywords: the instrument's geometry is
/// for one binning only.
fn check_binning(cf: &mut Opened, inst: &Instrument) -> Result<(), Error> {
    let fmt = &inst.format;
    let path = cf.path.clone();
    if fmt.binning.len() == 2 && fmt.binning_keywords.len() == 2 {
        let mut got = [0.0; 2];
        for a in 0..2 {
            let k = &fmt.binning_keywords[a];
            got[a] = cf
                .img
                .number(&path, k, "a binning factor")?
                .ok_or_else(|| Error::MissingKeyword { path: path.clone(), keyword: k.clone() })?;
        }
        if got != [fmt.binning[0] as f64, fmt.binning[1] as f64] {
            return Err(Error::Invalid(format!(
                "{}: binned {} x {} ('{}', '{}') but instrument {} is defined for {} x {} binning; use an instrument file for this binning",
                path.display(),
                got[0],
                got[1],
                fmt.binning_keywords[0],
                fmt.binning_keywords[1],
                inst.name,
                fmt.binning[0],
                fmt.binning[1]
            )));
        }
    }
    Ok(())
}

/// The chip's prescan and overscan sizes `[prescan x, overscan x, prescan y, overscan y]` (in
/// pixels, given or read from the keywords the instrument names), checked to add up with the
/// chip to the file's image size.
fn scan_counts(cf: &mut Opened, c: &Chip, inst: &Instrument) -> Result<[usize; 4], Error> {
    let path = cf.path.clone();
    let mut missing = Vec::new();
    let mut counts = [0usize; 4];
    for (n, v) in [&c.prescan_x, &c.overscan_x, &c.prescan_y, &c.overscan_y].into_iter().enumerate() {
        match resolve(cf, v, 0.0, "a number of pixels")? {
            Ok(x) if x.fract() == 0.0 && x < 1e6 => counts[n] = x as usize,
            Ok(x) => {
                return Err(Error::Invalid(format!(
                    "{}: a pre/overscan of {x} px is not a whole number",
                    path.display()
                )))
            }
            Err(k) => missing.push(k),
        }
    }
    if !missing.is_empty() {
        return Err(Error::Invalid(format!(
            "{}: missing prescan/overscan header keyword{} {} (instrument {} reads the chip {} regions from them)",
            path.display(),
            if missing.len() > 1 { "s" } else { "" },
            missing.iter().map(|k| format!("'{k}'")).collect::<Vec<_>>().join(", "),
            inst.name,
            c.name
        )));
    }
    let [prx, ovx, pry, ovy] = counts;
    let [cx, cy] = c.size_px;
    if cf.img.nx != prx + cx + ovx || cf.img.ny != pry + cy + ovy {
        return Err(Error::SizeMismatch {
            path: path.clone(),
            got_nx: cf.img.nx,
            got_ny: cf.img.ny,
            expected: format!(
                "chip {} of instrument {} is {cx} x {cy} px plus prescan/overscan {prx} + {ovx} columns and {pry} + {ovy} rows{}",
                c.name,
                inst.name,
                if inst.format.chips.is_empty() { String::new() } else { assembled_hint(cf.img.nx, cf.img.ny, inst) }
            ),
        });
    }
    Ok(counts)
}

/// The bias level of the chip's prescan and overscan pixels (their robust mean; `None` when
/// none is usable), refused when a scan row or column holds light, or when the declared
/// regions have no usable pixel and the instrument subtracts the overscan. `noise` is the read
/// noise in electrons and the gain in e-/ADU; `ny` the file's rows; `counts` as
/// [`scan_counts`] gives them.
fn scan_level(
    chip: &ChipRows,
    ny: usize,
    counts: [usize; 4],
    c: &Chip,
    (rn, gain): (f64, f64),
) -> Result<Option<f64>, Error> {
    let [prx, ovx, pry, ovy] = counts;
    let (rnx, cx, cy, sat) = (chip.rnx, chip.cx, chip.cy, chip.sat);
    let path = &chip.path;
    let mut row = vec![0.0f64; rnx];
    let mut bytes = Vec::new();
    // The bias level from the prescan and overscan pixels (in row-major order: the mean
    // sums them in that order). Only those rows are read when the chip has no prescan or
    // overscan columns.
    let mut scan = Vec::new();
    // Each scan row's median, and each scan column's values beside the image rows, to see
    // light where only the bias should be.
    let mut row_levels: Vec<(usize, f64)> = Vec::new();
    let scan_cols: Vec<usize> = (0..prx).chain(prx + cx..rnx).collect();
    let mut col_values: Vec<Vec<f64>> = vec![Vec::new(); scan_cols.len()];
    for y in 0..ny {
        let in_rows = y < pry || y >= pry + cy;
        if !in_rows && prx + ovx == 0 {
            continue;
        }
        chip.raw_row(y, &mut row, &mut bytes)?;
        if in_rows {
            let before = scan.len();
            push_usable(&mut scan, &row, sat);
            if scan.len() > before {
                let mut r = scan[before..].to_vec();
                row_levels.push((y, robust::median(&mut r, Middle::Mean)));
            }
        } else {
            push_usable(&mut scan, &row[..prx], sat);
            push_usable(&mut scan, &row[prx + cx..], sat);
            for (vals, &x) in col_values.iter_mut().zip(&scan_cols) {
                push_usable(vals, &row[x..x + 1], sat);
            }
        }
    }
    let col_levels: Vec<(usize, f64)> = scan_cols
        .iter()
        .zip(col_values.iter_mut())
        .filter(|(_, v)| !v.is_empty())
        .map(|(&x, v)| (x, robust::median(v, Middle::Mean)))
        .collect();
    let declared = (prx + ovx) * cy + (pry + ovy) * rnx;
    let scan_level = robust_mean(scan);
    // A scan row far above the scan's level holds light: the pre/overscan keywords do
    // not fit the chip (7 + 3 rows given for 5 + 5 put two image rows in the "prescan",
    // and the bias taken from it 16 % of the sky too high). 20 read noises (at least 20
    // ADU) is far beyond a bias row's own structure.
    if let Some(level) = scan_level {
        let limit = (20.0 * rn / gain).max(20.0);
        let rows = row_levels.iter().map(|&(y, l)| ("row", y, l));
        let cols = col_levels.iter().map(|&(x, l)| ("column", x, l));
        if let Some((what, k, l)) = rows.chain(cols).find(|(_, _, l)| l - level > limit) {
            return Err(Error::Invalid(format!(
                "{}: chip {}: its prescan/overscan {what} {k} sits {:.0} ADU above the scan's level of {level:.1} ADU: it holds light, so the scan regions ({pry} + {ovy} rows, {prx} + {ovx} columns) do not fit the chip; check the pre/overscan keywords",
                path.display(),
                c.name,
                l - level
            )));
        }
    }
    // Declared pre/overscan regions with no usable pixel (all NaN, BLANK or saturated):
    // the bias level cannot be measured, and the frame would be reduced with it in.
    if c.subtract_overscan && declared > 0 && scan_level.is_none() {
        return Err(Error::Invalid(format!(
            "{}: chip {}: none of its {declared} prescan/overscan pixels is usable (NaN, BLANK or saturated): its bias level cannot be measured; the file is damaged or its scan keywords are wrong",
            path.display(),
            c.name
        )));
    }
    Ok(scan_level)
}

/// A frame from which no bias is removed (no overscan subtracted, no master bias) must not
/// still carry its bias: refused when its overscan sits well above zero, or when its darkest
/// 1 % of pixels reach the format's raw bias level. `rn_adu` is the read noise in ADU.
fn check_bias_removed(
    chip: &ChipRows,
    c: &Chip,
    inst: &Instrument,
    scan_level: Option<f64>,
    rn_adu: f64,
) -> Result<(), Error> {
    let path = &chip.path;
    let (prx, pry, cx, cy) = (chip.prx, chip.pry, chip.cx, chip.cy);
    if let Some(l) = scan_level.filter(|l| *l > 10.0 * rn_adu.max(1.0)) {
        return Err(Error::Invalid(format!(
            "{}: the chip {} overscan sits at {l:.1} ADU, so the frame still carries its bias level, and instrument {} does not subtract the overscan: give a master bias (--bias)",
            path.display(),
            c.name,
            inst.name
        )));
    }
    if let Some(b) = inst.format.raw_bias_adu {
        let mut row = vec![0.0f64; chip.rnx];
        let mut bytes = Vec::new();
        let mut sample: Vec<f64> = Vec::new();
        let step = ((cx * cy) / 20000).max(1);
        for y in (pry..pry + cy).step_by(1.max(step / cx.max(1))) {
            chip.raw_row(y, &mut row, &mut bytes)?;
            sample.extend(row[prx..prx + cx].iter().step_by(step.min(cx).max(1)).copied().filter(|v| v.is_finite()));
        }
        sample.sort_by(f64::total_cmp);
        let q = sample.get(sample.len() / 100).copied().unwrap_or(0.0);
        if q >= b - 5.0 * rn_adu.max(1.0) {
            return Err(Error::Invalid(format!(
                "{}: the frame still carries its bias level: its darkest 1% of pixels sit at {q:.1} ADU, at or above the raw bias of {b} ADU of instrument {} (format.raw_bias_adu), and no overscan is subtracted: give a master bias (--bias)",
                path.display(),
                inst.name
            )));
        }
    }
    Ok(())
}

/// The chip files of one exposure must agree on what the exposure was: plate angle (or range),
/// filter, exposure time and the format's exposure keywords; `Err` names both files and the
/// keyword.
fn check_one_exposure(
    files: &[Opened],
    heads: &[(crate::frame::FrameHeader, Vec<(String, Option<String>)>)],
    inst: &Instrument,
) -> Result<(), Error> {
    let fmt = &inst.format;
    let pol = &inst.polarimetry;
    let plate_keyword = match &pol.rotation {
        Some(r) if r.by_position() => r.position_keyword.clone(),
        Some(r) => format!("{}' and '{}", r.begin_keyword, r.end_keyword),
        None => pol.hwp_angle_keyword.clone(),
    };
    let (h0, k0) = &heads[0];
    let hint = if fmt.exposure_keywords.is_empty() {
        "give the chip files of each exposure next to each other".to_string()
    } else {
        format!(
            "they share the exposure keywords {} by which instrument {} groups chip files, yet disagree: check their headers",
            fmt.exposure_keywords.join(", "),
            inst.name
        )
    };
    for (n, (h, k)) in heads.iter().enumerate().skip(1) {
        let differ = |key: &str, a: String, b: String| {
            Error::Invalid(format!(
                "chip files of different exposures paired: {} has '{key}' = {a} but {} has {b}; {hint}",
                files[0].path.display(),
                files[n].path.display()
            ))
        };
        let fmt_opt = |v: Option<f64>| v.map_or("(none)".to_string(), |x| x.to_string());
        let range = |h: &crate::frame::FrameHeader| match &pol.rotation {
            Some(_) => format!("{} (sweep {} deg)", fmt_opt(h.hwp_deg), h.hwp_sweep_deg),
            None => fmt_opt(h.hwp_deg),
        };
        if h.hwp_deg != h0.hwp_deg || h.hwp_sweep_deg != h0.hwp_sweep_deg {
            return Err(differ(&plate_keyword, range(h0), range(h)));
        }
        if h.filter != h0.filter {
            return Err(differ(&pol.filter_keyword, h0.filter.clone(), h.filter.clone()));
        }
        if h.exptime_s != h0.exptime_s {
            return Err(differ(&pol.exptime_keyword, fmt_opt(h0.exptime_s), fmt_opt(h.exptime_s)));
        }
        for ((key, a), (_, b)) in k0.iter().zip(k) {
            if a != b {
                return Err(differ(key, a.clone().unwrap_or("(none)".into()), b.clone().unwrap_or("(none)".into())));
            }
        }
    }
    Ok(())
}

/// Calibrate every exposure of `paths` at `stage`, in parallel, in the order given.
pub(crate) fn calibrate_all(
    paths: &[PathBuf],
    inst: &Instrument,
    opts: &ReadOptions,
    stage: Stage,
) -> Result<Vec<Exposure>, Error> {
    let chips = chips_of(inst);
    // What the frames already had done is not done again, unless asked.
    inst.format
        .check_masters(&inst.name, opts.bias.is_some(), opts.flat.is_some(), opts.correct_again)
        .map_err(Error::Invalid)?;
    // Opened once for all exposures (headers checked); their pixels are read as needed.
    let master = |p: &Option<PathBuf>, kind| p.as_deref().map(|p| open_master(p, inst, kind)).transpose();
    let masters = Arc::new(Masters { bias: master(&opts.bias, "BIAS")?, flat: master(&opts.flat, "FLAT")? });
    let groups = group_exposures(paths, inst, &chips)?;
    let n = groups.len();
    // Errors in the order of the files (rayon's short-circuiting collect would pick any).
    let res: Vec<Result<Exposure, Error>> =
        groups.into_par_iter().map(|g| calibrate_exposure(g, inst, &chips, stage, &masters)).collect();
    let mut out: Vec<Exposure> = res.into_iter().collect::<Result<_, _>>()?;
    // A flat of another filter than the frames' (an R flat for V frames) is refused, as it
    // would flatten them with another filter's response without a word.
    if let Some(f) = masters.flat.as_ref().and_then(|m| m.filter.as_ref().map(|f| (m, f))) {
        for e in &out {
            if !e.filter.trim().is_empty() && !inst.same_filter(f.1, &e.filter) {
                return Err(Error::Invalid(format!(
                    "{}: master flat of filter {} (HIERARCH INSTPOL FILTER), but {} is filter {}: give the flat of the frames' filter",
                    f.0.path.display(),
                    f.1,
                    e.path.display(),
                    e.filter
                )));
            }
        }
    }
    if let Some(a) = &opts.hwp_angles_deg {
        check_given_angles(a, n)?;
        for (e, &ang) in out.iter_mut().zip(a) {
            if let Some(h) = e.hwp_deg {
                if (h - ang).abs() > 0.05 {
                    return Err(Error::Invalid(format!(
                        "{}: --hwp-angles says {ang} deg but its header keyword '{}' says {h} deg",
                        e.path.display(),
                        inst.polarimetry.hwp_angle_keyword
                    )));
                }
            }
            e.hwp_deg = Some(ang);
        }
    }
    if stage == Stage::Science {
        for e in &out {
            require_hwp(e.hwp_deg, &e.path, inst)?;
        }
    }
    Ok(out)
}

/// Read and calibrate frames to detector images in electrons (one [`Frame`] per exposure;
/// chip files of one exposure given next to each other), or read them as they are when
/// nothing needs calibrating ([`ReadOptions::is_plain`]); `--hwp-angles` applied either way.
pub fn read_exposures(paths: &[PathBuf], inst: &Instrument, opts: &ReadOptions) -> Result<Vec<Frame>, Error> {
    let inst = &*opts.instrument(inst);
    if opts.is_plain(inst) {
        let res: Vec<Result<Frame, Error>> = paths
            .par_iter()
            .map(|p| read_frame_raw_with(p, inst, opts.hwp_angles_deg.is_some()).map(|r| r.into_frame()))
            .collect();
        let mut frames: Vec<Frame> = res.into_iter().collect::<Result<_, _>>()?;
        apply_angles(frames.iter_mut().map(|f| (&f.path, &mut f.hwp_deg)), inst, opts)?;
        return Ok(frames);
    }
    let ex = calibrate_all(paths, inst, opts, Stage::Science)?;
    let res: Vec<Result<Frame, Error>> = ex
        .into_par_iter()
        .map(|e| {
            let chips = e.rows.chip_places();
            Ok(Frame {
                chips,
                data: e.rows.whole()?,
                path: e.path,
                nx: inst.detector.nx,
                ny: inst.detector.ny,
                hwp_deg: e.hwp_deg.unwrap_or(f64::NAN),
                hwp_sweep_deg: e.hwp_sweep_deg,
                filter: e.filter,
                exptime_s: e.exptime_s,
                bitpix: e.bitpix,
                conversion: Conversion::electrons(e.rn2),
            })
        })
        .collect();
    res.into_iter().collect()
}

/// The HWP angles a caller gives for `n` exposures (`--hwp-angles`, the Python `hwp_angles`):
/// one per exposure, in degrees.
fn check_given_angles(a: &[f64], n: usize) -> Result<(), Error> {
    if a.len() != n {
        return Err(Error::Invalid(format!(
            "--hwp-angles gives {} angles for {n} exposures (one angle per exposure, in the order of the frames)",
            a.len()
        )));
    }
    stokes::check_degrees(a).map_err(|e| Error::Invalid(format!("--hwp-angles holds {e}: give them in degrees")))
}

/// `--hwp-angles` onto plain frames (NaN: no header angle), checked against their headers.
pub(crate) fn apply_angles<'a>(
    frames: impl ExactSizeIterator<Item = (&'a PathBuf, &'a mut f64)>,
    inst: &Instrument,
    opts: &ReadOptions,
) -> Result<(), Error> {
    let Some(a) = &opts.hwp_angles_deg else { return Ok(()) };
    check_given_angles(a, frames.len())?;
    for ((p, h), &ang) in frames.zip(a) {
        if h.is_finite() && (*h - ang).abs() > 0.05 {
            return Err(Error::Invalid(format!(
                "{}: --hwp-angles says {ang} deg but its header keyword '{}' says {} deg",
                p.display(),
                inst.polarimetry.hwp_angle_keyword,
                h
            )));
        }
        *h = ang;
    }
    Ok(())
}

/// Sigma-clipped mean per pixel over `images` (values that are NaN, saturated or gap markers
/// left out): median and `MAD_TO_SIGMA` times the MAD, values beyond `nsigma` of it rejected
/// (none when the MAD is zero), mean of the rest (`robust::clipped_mean`).
fn combine(images: &[Vec<f32>], npx: usize, nsigma: f64) -> Vec<f64> {
    let mut out = vec![f64::NAN; npx];
    out.par_chunks_mut(4096).enumerate().for_each(|(c, chunk)| {
        let mut v = Vec::with_capacity(images.len());
        for (k, o) in chunk.iter_mut().enumerate() {
            let p = c * 4096 + k;
            v.clear();
            v.extend(
                images
                    .iter()
                    .map(|im| im[p] as f64)
                    .filter(|x| x.is_finite() && *x < SATURATED_LIMIT && *x > GAP_LIMIT),
            );
            if let Some(m) = robust::clipped_mean(&v, nsigma, ZeroSpread::KeepAll) {
                *o = m;
            }
        }
    });
    out
}

/// Every exposure's whole detector frame as f32 (the values are f32 already), in parallel.
fn whole_frames_f32(ex: Vec<Exposure>) -> Result<Vec<Vec<f32>>, Error> {
    let res: Vec<Result<Vec<f32>, Error>> =
        ex.into_par_iter().map(|e| Ok(e.rows.whole()?.into_iter().map(|v| v as f32).collect())).collect();
    res.into_iter().collect()
}

/// The median of the pixels that are finite, below saturation and not chip-gap markers; `None`
/// when there are none.
fn usable_median(v: &[f64]) -> Option<f64> {
    let mut w: Vec<f64> =
        v.iter().copied().filter(|x| x.is_finite() && *x < SATURATED_LIMIT && *x > GAP_LIMIT).collect();
    (!w.is_empty()).then(|| robust::median(&mut w, Middle::Mean))
}

/// A master bias from bias frames: each calibrated as far as its overscan (ADU), then a
/// `nsigma`-clipped mean per pixel.
pub fn master_bias(paths: &[PathBuf], inst: &Instrument, nsigma: f64) -> Result<Master, Error> {
    check_nsigma(nsigma)?;
    let ex = calibrate_all(paths, inst, &ReadOptions::default(), Stage::Bias)?;
    let npx = inst.detector.nx * inst.detector.ny;
    let imgs: Vec<Vec<f32>> = whole_frames_f32(ex)?;
    let data = combine(&imgs, npx, nsigma);
    let (binning, chips) = layout_of(inst);
    Ok(Master {
        kind: "BIAS".into(),
        binning,
        chips,
        nx: inst.detector.nx,
        ny: inst.detector.ny,
        data,
        inputs: paths.to_vec(),
        nsigma,
        filter: None,
        overscan: chips_of(inst).iter().any(|c| {
            c.subtract_overscan
                && (c.overscan_x.is_some() || c.overscan_y.is_some() || c.prescan_x.is_some() || c.prescan_y.is_some())
        }),
        warnings: vec![],
    })
}

/// A master flat from flat-field frames: each calibrated to bias-free electrons (overscan and
/// `bias` subtracted, gain applied) and divided by its own median, then a `nsigma`-clipped
/// mean per pixel, normalized to a median of 1 over the detector (gap excluded).
pub fn master_flat(paths: &[PathBuf], inst: &Instrument, bias: Option<&Path>, nsigma: f64) -> Result<Master, Error> {
    check_nsigma(nsigma)?;
    let opts = ReadOptions { bias: bias.map(|p| p.to_path_buf()), ..Default::default() };
    let ex = calibrate_all(paths, inst, &opts, Stage::Flat)?;
    // One filter per master flat: a flat of mixed filters is no filter's response.
    if let Some(e) = ex.iter().find(|e| !inst.same_filter(&e.filter, &ex[0].filter)) {
        return Err(Error::Invalid(format!(
            "{} is filter '{}' but {} is filter '{}': a master flat combines flats of one filter",
            ex[0].path.display(),
            ex[0].filter,
            e.path.display(),
            e.filter
        )));
    }
    let filter = ex.first().map(|e| e.filter.trim().to_string()).filter(|f| !f.is_empty());
    let npx = inst.detector.nx * inst.detector.ny;
    let names: Vec<PathBuf> = ex.iter().map(|e| e.path.clone()).collect();
    let mut imgs = Vec::with_capacity(ex.len());
    for (data, path) in whole_frames_f32(ex)?.into_iter().zip(names) {
        let v: Vec<f64> = data.iter().map(|&x| x as f64).collect();
        let m = usable_median(&v).filter(|m| *m > 0.0).ok_or_else(|| {
            let saturated = v.iter().filter(|x| **x >= SATURATED_LIMIT).count();
            if 2 * saturated > v.len() {
                Error::Invalid(format!(
                    "{}: flat field is saturated ({saturated} of {} pixels at or above the instrument's saturation_adu): take a shorter flat",
                    path.display(),
                    v.len()
                ))
            } else {
                Error::Invalid(format!(
                    "{}: flat field has no positive signal (median after bias removal <= 0)",
                    path.display()
                ))
            }
        })?;
        imgs.push(
            data.iter()
                .map(
                    |&x| if (x as f64) < SATURATED_LIMIT && (x as f64) > GAP_LIMIT { (x as f64 / m) as f32 } else { x },
                )
                .collect(),
        );
    }
    let mut data = combine(&imgs, npx, nsigma);
    let m = usable_median(&data)
        .filter(|m| *m > 0.0)
        .ok_or_else(|| Error::Invalid("master flat: no positive pixel".into()))?;
    for v in data.iter_mut() {
        *v = if *v / m > 0.0 { *v / m } else { f64::NAN };
    }
    let (binning, chips) = layout_of(inst);
    Ok(Master {
        kind: "FLAT".into(),
        binning,
        chips,
        nx: inst.detector.nx,
        ny: inst.detector.ny,
        data,
        inputs: paths.to_vec(),
        nsigma,
        overscan: true,
        filter,
        warnings: vec![],
    })
}

fn check_nsigma(nsigma: f64) -> Result<(), Error> {
    if !(nsigma.is_finite() && nsigma > 0.0) {
        return Err(Error::Invalid(format!("clipping threshold {nsigma} sigma must be positive")));
    }
    Ok(())
}

impl Master {
    /// Write as a FITS image (32-bit float) with provenance keywords, atomically.
    pub fn write(&self, path: &Path, inst: &Instrument) -> Result<(), Error> {
        let mut keys: Vec<(String, KeyValue, String)> = vec![
            ("INSTRUME".into(), KeyValue::Str(inst.name.clone()), String::new()),
            // A bias is in ADU; a flat is normalized (dimensionless: '' for astropy).
            (
                "BUNIT".into(),
                KeyValue::Str(if self.kind == "BIAS" { "adu".into() } else { String::new() }),
                String::new(),
            ),
            ("HIERARCH INSTPOL MASTER".into(), KeyValue::Str(self.kind.clone()), String::new()),
            ("NCOMBINE".into(), KeyValue::I64(self.inputs.len() as i64), "frames combined".into()),
            ("HIERARCH INSTPOL NSIGMA".into(), KeyValue::F64(self.nsigma), "clipping threshold per pixel".into()),
            (
                "HIERARCH INSTPOL UNITS".into(),
                KeyValue::Str(if self.kind == "BIAS" { "ADU".into() } else { "relative".into() }),
                String::new(),
            ),
            ("HIERARCH INSTPOL OVERSCAN".into(), KeyValue::I64(self.overscan as i64), "overscan subtracted".into()),
            ("HIERARCH INSTPOL VERSION".into(), KeyValue::Str(env!("CARGO_PKG_VERSION").into()), String::new()),
        ];
        if let Some(f) = &self.filter {
            keys.push(("HIERARCH INSTPOL FILTER".into(), KeyValue::Str(f.clone()), "filter of the flats".into()));
        }
        if let Some([bx, by]) = self.binning {
            keys.push(("HIERARCH INSTPOL BINNING".into(), KeyValue::Str(format!("{bx}x{by}")), "of the frames".into()));
        }
        if !self.chips.is_empty() {
            keys.push(("HIERARCH INSTPOL CHIPS".into(), KeyValue::Str(self.chips.join(",")), "assembled".into()));
        }
        for (k, p) in self.inputs.iter().enumerate().take(999) {
            let name = p.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
            let name: String = name.chars().filter(|c| c.is_ascii_graphic() || *c == ' ').take(40).collect();
            keys.push((format!("HIERARCH INSTPOL INPUT{}", k + 1), KeyValue::Str(name), String::new()));
        }
        write_frame(path, self.nx, self.ny, &self.data, Bitpix::F32, &keys)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition written plainly: the one median, the kept values summed in order.
    fn by_sorting(v: &[f64]) -> f64 {
        let median = |w: &[f64]| robust::median(&mut w.to_vec(), Middle::Mean);
        let med = median(v);
        let dev: Vec<f64> = v.iter().map(|x| (x - med).abs()).collect();
        let s = MAD_TO_SIGMA * median(&dev);
        let kept: Vec<f64> = v.iter().copied().filter(|x| (x - med).abs() <= 3.0 * s).collect();
        if kept.is_empty() {
            med
        } else {
            kept.iter().sum::<f64>() / kept.len() as f64
        }
    }

    /// The robust mean from counts is the sorted definition to the bit on whole numbers (odd and
    /// even counts, ties, all equal, outliers, negative values, a single value), and the other
    /// values (fractions, -0, a span of 2^16 or more) take the selection path, which is too.
    #[test]
    fn robust_mean_from_counts_is_the_sorted_definition() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(12);
        // The last set drops 12 with the MAD as the mean of the two middle deviations, and
        // keeps it with the upper one.
        let mut cases: Vec<Vec<f64>> = vec![
            vec![5.0],
            vec![3.0, 4.0],
            vec![7.0; 10],
            vec![-3.0, -3.0, 2.0, 9.0],
            vec![3.0, 4.0, 1.0, 12.0, 9.0, 2.0, 5.0, 4.0],
        ];
        for n in [2, 3, 10, 11, 200, 201, 20000] {
            let base: f64 = rng.random_range(-300.0..3000.0f64).round();
            let mut v: Vec<f64> = (0..n).map(|_| base + rng.random_range(-6.0..6.0f64).round()).collect();
            v[0] = base + 900.0;
            cases.push(v);
        }
        cases.push(vec![0.5, 1.0, 2.0]);
        cases.push(vec![-0.0, 0.0, 0.0, 1.0]);
        cases.push(vec![0.0, 70000.0, 3.0]);
        for (k, v) in cases.iter().enumerate() {
            let fast = robust_mean_of_counts(v);
            let whole = v.iter().all(|x| x.fract() == 0.0 && !(*x == 0.0 && x.is_sign_negative()));
            let span =
                v.iter().cloned().fold(f64::NEG_INFINITY, f64::max) - v.iter().cloned().fold(f64::INFINITY, f64::min);
            assert_eq!(fast.is_some(), whole && span < 65536.0, "case {k}: which path");
            let want = by_sorting(v);
            let got = robust_mean(v.clone()).unwrap();
            assert_eq!(got.to_bits(), want.to_bits(), "case {k} ({} values): {got} vs {want}", v.len());
        }
        assert_eq!(robust_mean(Vec::new()), None);
    }

    /// The all-exposures-at-once sum of raw u16 rows gives the bits of the exposure-by-exposure
    /// sum (`Cal::sum`, each exposure set or added in turn) and the same counts, over rows with
    /// saturated values, NaN and zero flat responses, huge inverse flats (values beyond f32:
    /// infinities) and a length that is not a multiple of the block. (The blocked sum itself is
    /// checked against an independent calibration by `sim/tests/it/raw_calibration_bits.rs`.)
    #[test]
    fn blocked_u16_sum_is_the_exposure_by_exposure_sum() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(7);
        let n = 203;
        for nexp in [1, 2, 4, 5] {
            for case in 0..4 {
                let raws: Vec<Vec<[u8; 2]>> = (0..nexp)
                    .map(|_| {
                        (0..n)
                            .map(|_| {
                                let v: u16 =
                                    if rng.random::<f64>() < 0.03 { 65535 } else { rng.random_range(150..4000) };
                                [(v >> 8) as u8 ^ 0x80, v as u8]
                            })
                            .collect()
                    })
                    .collect();
                let bias: Vec<f32> = (0..n).map(|_| rng.random_range(-3.0..3.0)).collect();
                let flat: Vec<f32> = (0..n)
                    .map(|i| match (case, i % 17) {
                        (1, 3) => f32::NAN,
                        (2, 5) => 3e38,
                        (3, _) => 1.0,
                        _ => rng.random_range(0.8..1.2),
                    })
                    .collect();
                let w: Vec<u64> = (0..n).map(|i| [0, 1, 1, 2][i % 4]).collect();
                let cals: Vec<(f64, f64, f64)> =
                    (0..nexp).map(|j| (200.0 + j as f64, 1.25, if case == 3 { 70000.0 } else { 60000.0 })).collect();
                let count_sat = SATURATED_LIMIT;
                let mut want = vec![0.0; n];
                let mut want_counts = Vec::new();
                for (j, raw) in raws.iter().enumerate() {
                    let (level, to_e, sat) = cals[j];
                    let cal = Cal { bias: &bias, flat: &flat, w: &w, level, to_e, sat, count_sat };
                    let decoded: Vec<f64> = raw.iter().map(|&b| u16_value(b)).collect();
                    want_counts.push(cal.sum(j == 0, &mut want, &decoded));
                }
                let mut got = vec![0.0; n];
                let refs: Vec<&[[u8; 2]]> = raws.iter().map(|r| &r[..]).collect();
                let flagged = sum_u16_blocked(&mut got, &refs, &cals, &bias, &flat, count_sat);
                assert!(
                    got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()),
                    "{nexp} exposures, case {case}: sums differ"
                );
                let any_bad = want_counts.iter().any(|&(a, s)| a + s > 0);
                assert!(flagged || !any_bad, "{nexp} exposures, case {case}: bad values not flagged");
                let got_counts: Vec<(usize, usize)> = refs
                    .iter()
                    .zip(&cals)
                    .map(|(r, &(level, to_e, sat))| {
                        Cal { bias: &bias, flat: &flat, w: &w, level, to_e, sat, count_sat }.count(r, u16_value)
                    })
                    .collect();
                assert_eq!(got_counts, want_counts, "{nexp} exposures, case {case}");
                if case != 3 {
                    assert!(any_bad, "case {case}: the row holds bad values");
                }
            }
        }
    }
}
