//! Raw frames to calibrated detector images, as the instrument's `[format]` describes them:
//! chip files (or HDUs) matched to the instrument's chips and grouped into exposures, each
//! chip trimmed of its prescan and overscan, its bias level (the robust mean of those regions)
//! and the master bias subtracted, converted to electrons with its gain, divided by the master
//! flat, and placed in one detector frame where pixels no chip covers are the gap. Saturated
//! raw pixels become [`SATURATED`], gap pixels [`GAP`] (both masked by the reduction), BLANK
//! pixels NaN. The result is what every later stage sees: one image per exposure, in
//! electrons ([`Conversion::electrons`]).
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

use crate::io::{
    check_bitpix, frame_header_with, open_image, parse_number, require_hwp, write_frame, Bitpix, Conversion, Frame,
    FrameRows, ImageHdu, KeyValue, OpenFrame, Pixels, GAP, GAP_LIMIT, SATURATED, SATURATED_LIMIT,
};
use crate::{Error, Warning};
use instrument::{Chip, Instrument, NumberOrKeyword};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Options of reading: calibration frames and HWP angles given on the command line.
#[derive(Debug, Clone, Default)]
pub struct ReadOptions {
    /// Master bias (from [`master_bias`]): overscan-corrected ADU per detector pixel.
    pub bias: Option<PathBuf>,
    /// Master flat (from [`master_flat`]): relative response per detector pixel.
    pub flat: Option<PathBuf>,
    /// HWP angles (deg), one per exposure in the order given, for headers that have none.
    pub hwp_angles_deg: Option<Vec<f64>>,
}

impl ReadOptions {
    /// True when frames are read as they are (the instrument's ADU, no calibration step).
    pub fn is_plain(&self, inst: &Instrument) -> bool {
        !inst.format.is_raw() && self.bias.is_none() && self.flat.is_none()
    }
}

/// What an exposure is calibrated to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stage {
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
    pub warnings: Vec<Warning>,
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

/// Files grouped into exposures, each with one [`ChipFile`] per chip (in chip order).
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
    // Chips in separate files: match each file to its chip; the chip files of one exposure
    // are given next to each other (as a time-sorted archive listing puts them).
    let opened: Vec<Result<ChipFile, Error>> = paths
        .par_iter()
        .map(|p| {
            let mut img = open_image(p, &inst.format.hdu)?;
            let key = chips[0].match_keyword.clone().unwrap_or_default();
            let mut found = None;
            for (k, c) in chips.iter().enumerate() {
                let kw = c.match_keyword.as_deref().unwrap_or_default();
                let v = img.key(kw).ok_or_else(|| Error::MissingKeyword { path: p.clone(), keyword: kw.into() })?;
                if c.match_value.as_deref().is_some_and(|m| m.trim() == v) {
                    found = Some(k);
                    break;
                }
            }
            let chip = found.ok_or_else(|| {
                let v = img.key(&key).unwrap_or_default();
                Error::Invalid(format!(
                    "{}: header keyword '{key}' = '{v}' names none of instrument {}'s chips ({})",
                    p.display(),
                    inst.name,
                    chips.iter().map(|c| c.match_value.clone().unwrap_or_default()).collect::<Vec<_>>().join(", ")
                ))
            })?;
            Ok(ChipFile { path: p.clone(), chip, spec: inst.format.hdu.clone() })
        })
        .collect();
    let mut groups: Vec<Vec<ChipFile>> = Vec::new();
    let mut cur: Vec<ChipFile> = Vec::new();
    for cf in opened {
        let cf = cf?;
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

/// Robust mean: the mean of the values within 3 robust sigmas (1.4826 MAD) of the median.
fn robust_mean(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let med = crate::bin::median_in_place(&mut v);
    let mut dev: Vec<f64> = v.iter().map(|x| (x - med).abs()).collect();
    let s = 1.4826 * crate::bin::median_in_place(&mut dev);
    let kept: Vec<f64> = v.iter().copied().filter(|x| (x - med).abs() <= 3.0 * s).collect();
    if kept.is_empty() {
        return Some(med);
    }
    Some(kept.iter().sum::<f64>() / kept.len() as f64)
}

/// What calibrating one exposure found.
struct Exposure {
    path: PathBuf,
    hwp_deg: Option<f64>,
    filter: String,
    exptime_s: Option<f64>,
    bitpix: i32,
    data: Vec<f32>,
    /// Largest read-noise variance (e-^2) of its chips.
    rn2: f64,
}

/// Loaded calibration frames: the bias (ADU) and the inverse of the flat.
struct Masters {
    bias: Option<Vec<f32>>,
    flat: Option<Vec<f32>>,
}

fn load_master(path: &Path, inst: &Instrument, kind: &str) -> Result<Vec<f32>, Error> {
    let mut img = open_image(path, "")?;
    check_bitpix(path, img.bitpix)?;
    let d = &inst.detector;
    if img.nx != d.nx || img.ny != d.ny {
        return Err(Error::SizeMismatch {
            path: path.into(),
            got_nx: img.nx,
            got_ny: img.ny,
            expected: format!("a master {} of instrument {} is {} x {}", kind.to_lowercase(), inst.name, d.nx, d.ny),
        });
    }
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
        if !i.eq_ignore_ascii_case(&inst.name) {
            return Err(Error::Invalid(format!(
                "{}: master {} of instrument {i}, but the frames are read as instrument {}",
                path.display(),
                kind.to_lowercase(),
                inst.name
            )));
        }
    }
    Ok(img.read_pixels(path)?.into_f64().into_iter().map(|v| v as f32).collect())
}

/// Calibrate one exposure (its chip files) into the detector frame.
/// A chip file opened by the worker calibrating it.
struct Opened {
    path: PathBuf,
    chip: usize,
    img: ImageHdu,
}

fn calibrate_exposure(
    files: Vec<ChipFile>,
    inst: &Instrument,
    chips: &[Chip],
    stage: Stage,
    masters: &Masters,
) -> Result<Exposure, Error> {
    let d = &inst.detector;
    let fmt = &inst.format;
    let (nx, ny) = (d.nx, d.ny);
    let mut data = vec![GAP as f32; nx * ny];
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
        let c = &chips[cf.chip];
        // Binning: the instrument's geometry is for one binning only.
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
                    "chip {} of instrument {} is {cx} x {cy} px plus prescan/overscan {prx} + {ovx} columns and {pry} + {ovy} rows",
                    c.name, inst.name
                ),
            });
        }
        let gain = match resolve(cf, &c.gain_e_per_adu, d.gain_e_per_adu, "a gain in e-/ADU")? {
            Ok(g) if g > 0.0 => g,
            Ok(g) => return Err(Error::Invalid(format!("{}: gain {g} e-/ADU must be positive", path.display()))),
            Err(k) => return Err(Error::MissingKeyword { path: path.clone(), keyword: k }),
        };
        let rn = match resolve(cf, &c.read_noise_e, d.read_noise_e, "a read noise in e-")? {
            Ok(r) => r,
            Err(k) => return Err(Error::MissingKeyword { path: path.clone(), keyword: k }),
        };
        rn2 = rn2.max(rn * rn);
        let sat = c.saturation_adu.unwrap_or(d.saturation_adu);
        let pixels = cf.img.read_pixels(&path)?;
        let view = pixels.view();
        let rnx = cf.img.nx;
        let mut row = vec![0.0f64; rnx];
        // The bias level from the prescan and overscan pixels.
        let mut scan = Vec::new();
        for y in 0..cf.img.ny {
            let in_rows = y < pry || y >= pry + cy;
            if !in_rows && prx + ovx == 0 {
                continue;
            }
            view.load(y * rnx, &mut row);
            let take = |x: usize| in_rows || x < prx || x >= prx + cx;
            scan.extend((0..rnx).filter(|&x| take(x)).map(|x| row[x]).filter(|v| v.is_finite() && *v < sat));
        }
        let scan_level = robust_mean(scan);
        let subtract_scan = c.subtract_overscan && scan_level.is_some();
        let level = if subtract_scan { scan_level.unwrap_or(0.0) } else { 0.0 };
        let bias_map = if stage == Stage::Bias { None } else { masters.bias.as_ref() };
        // A frame still carrying its bias is refused, never reduced silently.
        if stage != Stage::Bias && !subtract_scan && bias_map.is_none() {
            let rn_adu = rn / gain;
            if let Some(l) = scan_level.filter(|l| *l > 10.0 * rn_adu.max(1.0)) {
                return Err(Error::Invalid(format!(
                    "{}: the chip {} overscan sits at {l:.1} ADU, so the frame still carries its bias level, and instrument {} does not subtract the overscan: give a master bias (--bias)",
                    path.display(),
                    c.name,
                    inst.name
                )));
            }
            if let Some(b) = fmt.raw_bias_adu {
                let mut sample: Vec<f64> = Vec::new();
                let step = ((cx * cy) / 20000).max(1);
                for y in (pry..pry + cy).step_by(1.max(step / cx.max(1))) {
                    view.load(y * rnx, &mut row);
                    sample.extend(
                        row[prx..prx + cx].iter().step_by(step.min(cx).max(1)).copied().filter(|v| v.is_finite()),
                    );
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
        }
        // Without overscan or master bias, the instrument's constant bias (as for plain frames).
        let const_bias = if stage != Stage::Bias && !subtract_scan && bias_map.is_none() { d.bias_adu } else { 0.0 };
        let flat_map = if stage == Stage::Science { masters.flat.as_ref() } else { None };
        let [x0, y0] = c.origin_px;
        let to_e = if stage == Stage::Bias { 1.0 } else { gain };
        // One branch-free pass per row (so it vectorizes): absent masters are a zero bias and
        // a unit inverse flat; NaN and saturated raw values are selected after.
        let (zeros, ones) = (vec![0.0f32; cx], vec![1.0f32; cx]);
        let level = level + const_bias;
        for j in 0..cy {
            view.load((pry + j) * rnx, &mut row);
            let base = (y0 + j) * nx + x0;
            let out = &mut data[base..base + cx];
            let raw = &row[prx..prx + cx];
            let b = bias_map.map_or(&zeros[..], |m| &m[base..base + cx]);
            let fi = flat_map.map_or(&ones[..], |m| &m[base..base + cx]);
            for i in 0..cx {
                let r = raw[i];
                let e = ((r - level - b[i] as f64) * to_e * fi[i] as f64) as f32;
                let e = if r >= sat { SATURATED as f32 } else { e };
                out[i] = if r.is_nan() { f32::NAN } else { e };
            }
        }
    }
    // The chip files of one exposure must agree on what the exposure was.
    let pol = &inst.polarimetry;
    let (h0, k0) = &heads[0];
    for (n, (h, k)) in heads.iter().enumerate().skip(1) {
        let differ = |key: &str, a: String, b: String| {
            Error::Invalid(format!(
                "chip files of different exposures paired: {} has '{key}' = {a} but {} has {b}; give the chip files of each exposure next to each other",
                files[0].path.display(),
                files[n].path.display()
            ))
        };
        let fmt_opt = |v: Option<f64>| v.map_or("(none)".to_string(), |x| x.to_string());
        if h.hwp_deg != h0.hwp_deg {
            return Err(differ(&pol.hwp_angle_keyword, fmt_opt(h0.hwp_deg), fmt_opt(h.hwp_deg)));
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
    let (h0, _) = heads.swap_remove(0);
    Ok(Exposure {
        path: files[0].path.clone(),
        hwp_deg: h0.hwp_deg,
        filter: h0.filter,
        exptime_s: h0.exptime_s,
        bitpix: files[0].img.bitpix,
        data,
        rn2,
    })
}

/// Calibrate every exposure of `paths` at `stage`, in parallel, in the order given.
fn calibrate_all(
    paths: &[PathBuf],
    inst: &Instrument,
    opts: &ReadOptions,
    stage: Stage,
) -> Result<Vec<Exposure>, Error> {
    let chips = chips_of(inst);
    let masters = Masters {
        bias: opts.bias.as_deref().map(|p| load_master(p, inst, "BIAS")).transpose()?,
        // Stored as its inverse (NaN where the response is not positive): a multiply per pixel.
        flat: opts
            .flat
            .as_deref()
            .map(|p| {
                load_master(p, inst, "FLAT")
                    .map(|v| v.into_iter().map(|f| if f > 0.0 { 1.0 / f } else { f32::NAN }).collect())
            })
            .transpose()?,
    };
    let groups = group_exposures(paths, inst, &chips)?;
    let n = groups.len();
    // Errors in the order of the files (rayon's short-circuiting collect would pick any).
    let res: Vec<Result<Exposure, Error>> =
        groups.into_par_iter().map(|g| calibrate_exposure(g, inst, &chips, stage, &masters)).collect();
    let mut out: Vec<Exposure> = res.into_iter().collect::<Result<_, _>>()?;
    if let Some(a) = &opts.hwp_angles_deg {
        if a.len() != n {
            return Err(Error::Invalid(format!(
                "--hwp-angles gives {} angles for {n} exposures (one angle per exposure, in the order of the frames)",
                a.len()
            )));
        }
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
    if opts.is_plain(inst) {
        let res: Vec<Result<Frame, Error>> = paths
            .par_iter()
            .map(|p| crate::io::read_frame_raw_with(p, inst, opts.hwp_angles_deg.is_some()).map(|r| r.into_frame()))
            .collect();
        let mut frames: Vec<Frame> = res.into_iter().collect::<Result<_, _>>()?;
        apply_angles(frames.iter_mut().map(|f| (&f.path, &mut f.hwp_deg)), inst, opts)?;
        return Ok(frames);
    }
    let ex = calibrate_all(paths, inst, opts, Stage::Science)?;
    Ok(ex
        .into_iter()
        .map(|e| Frame {
            path: e.path,
            nx: inst.detector.nx,
            ny: inst.detector.ny,
            data: e.data.iter().map(|&v| v as f64).collect(),
            hwp_deg: e.hwp_deg.unwrap_or(f64::NAN),
            filter: e.filter,
            exptime_s: e.exptime_s,
            bitpix: e.bitpix,
            conversion: Conversion::electrons(e.rn2),
        })
        .collect())
}

/// [`read_exposures`] for the reduction: plain frames stay on disk to be read by rows;
/// calibrated ones are held in memory as f32 electrons.
pub(crate) fn open_exposures(
    paths: &[PathBuf],
    inst: &Instrument,
    opts: &ReadOptions,
) -> Result<Vec<OpenFrame>, Error> {
    if opts.is_plain(inst) {
        let res: Vec<Result<OpenFrame, Error>> =
            paths.par_iter().map(|p| crate::io::open_frame_with(p, inst, opts.hwp_angles_deg.is_some())).collect();
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
            filter: e.filter,
            rows: FrameRows::Memory(Pixels::F32(e.data)),
            conversion: Conversion::electrons(e.rn2),
        })
        .collect())
}

/// `--hwp-angles` onto plain frames (NaN: no header angle), checked against their headers.
fn apply_angles<'a>(
    frames: impl ExactSizeIterator<Item = (&'a PathBuf, &'a mut f64)>,
    inst: &Instrument,
    opts: &ReadOptions,
) -> Result<(), Error> {
    let Some(a) = &opts.hwp_angles_deg else { return Ok(()) };
    if a.len() != frames.len() {
        return Err(Error::Invalid(format!(
            "--hwp-angles gives {} angles for {} exposures (one angle per exposure, in the order of the frames)",
            a.len(),
            frames.len()
        )));
    }
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
/// left out): median and 1.4826 MAD, values beyond `nsigma` of it rejected, mean of the rest.
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
            if v.is_empty() {
                continue;
            }
            let mut w = v.clone();
            let med = crate::bin::median_in_place(&mut w);
            for x in w.iter_mut() {
                *x = (*x - med).abs();
            }
            let s = 1.4826 * crate::bin::median_in_place(&mut w);
            let (sum, n) = v
                .iter()
                .filter(|x| s == 0.0 || (*x - med).abs() <= nsigma * s)
                .fold((0.0, 0usize), |(a, n), x| (a + x, n + 1));
            *o = if n > 0 { sum / n as f64 } else { med };
        }
    });
    out
}

fn median_of(v: &[f64]) -> Option<f64> {
    let mut w: Vec<f64> =
        v.iter().copied().filter(|x| x.is_finite() && *x < SATURATED_LIMIT && *x > GAP_LIMIT).collect();
    (!w.is_empty()).then(|| crate::bin::median_in_place(&mut w))
}

/// A master bias from bias frames: each calibrated as far as its overscan (ADU), then a
/// `nsigma`-clipped mean per pixel.
pub fn master_bias(paths: &[PathBuf], inst: &Instrument, nsigma: f64) -> Result<Master, Error> {
    check_nsigma(nsigma)?;
    let ex = calibrate_all(paths, inst, &ReadOptions::default(), Stage::Bias)?;
    let npx = inst.detector.nx * inst.detector.ny;
    let imgs: Vec<Vec<f32>> = ex.into_iter().map(|e| e.data).collect();
    let data = combine(&imgs, npx, nsigma);
    Ok(Master {
        kind: "BIAS".into(),
        nx: inst.detector.nx,
        ny: inst.detector.ny,
        data,
        inputs: paths.to_vec(),
        nsigma,
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
    let opts = ReadOptions { bias: bias.map(|p| p.to_path_buf()), flat: None, hwp_angles_deg: None };
    let ex = calibrate_all(paths, inst, &opts, Stage::Flat)?;
    let npx = inst.detector.nx * inst.detector.ny;
    let mut imgs = Vec::with_capacity(ex.len());
    for e in ex {
        let v: Vec<f64> = e.data.iter().map(|&x| x as f64).collect();
        let m = median_of(&v).filter(|m| *m > 0.0).ok_or_else(|| {
            Error::Invalid(format!(
                "{}: flat field has no positive signal (median after bias removal <= 0)",
                e.path.display()
            ))
        })?;
        imgs.push(
            e.data
                .iter()
                .map(
                    |&x| if (x as f64) < SATURATED_LIMIT && (x as f64) > GAP_LIMIT { (x as f64 / m) as f32 } else { x },
                )
                .collect(),
        );
    }
    let mut data = combine(&imgs, npx, nsigma);
    let m =
        median_of(&data).filter(|m| *m > 0.0).ok_or_else(|| Error::Invalid("master flat: no positive pixel".into()))?;
    for v in data.iter_mut() {
        *v = if *v / m > 0.0 { *v / m } else { f64::NAN };
    }
    Ok(Master {
        kind: "FLAT".into(),
        nx: inst.detector.nx,
        ny: inst.detector.ny,
        data,
        inputs: paths.to_vec(),
        nsigma,
        overscan: true,
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
        for (k, p) in self.inputs.iter().enumerate().take(999) {
            let name = p.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
            let name: String = name.chars().filter(|c| c.is_ascii_graphic() || *c == ' ').take(40).collect();
            keys.push((format!("HIERARCH INSTPOL INPUT{}", k + 1), KeyValue::Str(name), String::new()));
        }
        write_frame(path, self.nx, self.ny, &self.data, Bitpix::F32, &keys)
    }
}
