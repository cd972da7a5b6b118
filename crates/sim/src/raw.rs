//! Raw frames as an instrument's read-out writes them: an image in electrons on the detector
//! frame is cut into the chips of the instrument's `[format]`, multiplied by a flat-field
//! pattern, converted to ADU with each chip's gain, given a bias level (plus an optional
//! per-pixel bias pattern), read noise and photon noise, padded with prescan and overscan
//! regions that hold only bias and read noise, and written one file per chip with the header
//! keywords the format names (chip name, binning, pre/overscan sizes, gain, read noise,
//! exposure number, HWP angle, filter, exposure time). What `skyfield::calib` undoes.

use crate::Error;
use instrument::{Chip, Instrument, NumberOrKeyword};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;
use skyfield::fits::{write_frame, Bitpix, KeyValue};
use std::path::{Path, PathBuf};

/// The read-out of one chip.
#[derive(Debug, Clone, Copy)]
pub struct RawChip {
    /// Bias level (ADU).
    pub bias_adu: f64,
    pub gain_e_per_adu: f64,
    pub read_noise_e: f64,
    /// Prescan and overscan sizes written where the format names keywords:
    /// `[prescan x, overscan x, prescan y, overscan y]` (binned px).
    pub scan: [usize; 4],
}

/// One exposure to write.
#[derive(Debug, Clone)]
pub struct RawExposure<'a> {
    /// Signal in electrons, row-major over the detector frame (`nx * ny`).
    pub electrons: &'a [f64],
    /// HWP angle keyword value (none: the keyword is left out).
    pub hwp_deg: Option<f64>,
    pub filter: String,
    pub exptime_s: f64,
    /// Written to every `format.exposure_keywords` keyword.
    pub exposure_no: i64,
    /// Binning written to `format.binning_keywords` (default: the format's binning).
    pub binning: Option<[u32; 2]>,
}

/// Write one exposure's chip files `DIR/STEM_<chip>.fits` (16-bit unsigned, as CCD
/// controllers write). `flat`: relative response per detector pixel; `bias_pattern`: ADU
/// added per detector pixel on top of the chip's level; `photon_noise`: Gaussian noise of
/// variance equal to the signal; `seed`: the noise draws. Returns the files in chip order.
#[allow(clippy::too_many_arguments)]
pub fn write_raw_exposure(
    inst: &Instrument,
    exp: &RawExposure,
    flat: Option<&[f64]>,
    bias_pattern: Option<&[f64]>,
    chips: &[RawChip],
    photon_noise: bool,
    seed: u64,
    dir: &Path,
    stem: &str,
) -> Result<Vec<PathBuf>, Error> {
    let d = &inst.detector;
    let npx = d.nx * d.ny;
    let bad = |m: String| Error::File { path: dir.join(stem), message: m };
    if exp.electrons.len() != npx
        || flat.is_some_and(|f| f.len() != npx)
        || bias_pattern.is_some_and(|b| b.len() != npx)
    {
        return Err(bad(format!("images must have {} x {} px", d.nx, d.ny)));
    }
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let unit = Normal::new(0.0, 1.0).expect("unit normal");
    let pol = &inst.polarimetry;
    let mut keys: Vec<(String, KeyValue, String)> = Vec::new();
    if let Some(h) = exp.hwp_deg {
        keys.push((pol.hwp_angle_keyword.clone(), KeyValue::F64(h), "HWP angle [deg]".into()));
    }
    keys.push((pol.filter_keyword.clone(), KeyValue::Str(exp.filter.clone()), String::new()));
    keys.push((pol.exptime_keyword.clone(), KeyValue::F64(exp.exptime_s), "[s]".into()));
    let readout = Readout { chips, exposure_no: exp.exposure_no, binning: exp.binning, bitpix: Bitpix::U16 };
    write_chip_files(inst, &readout, &keys, true, &mut rng, dir, stem, &mut |c, p, rng| {
        let e = exp.electrons[p] * flat.map_or(1.0, |f| f[p]);
        let noise = if photon_noise { e.max(0.0).sqrt() * unit.sample(rng) } else { 0.0 };
        (e + noise) / chips[c].gain_e_per_adu + bias_pattern.map_or(0.0, |b| b[p])
    })
}

/// How one exposure is read out: each chip's read-out, the exposure number the format's
/// `exposure_keywords` carry, the binning written to its `binning_keywords` (default: the
/// format's) and the files' BITPIX.
#[derive(Debug, Clone, Copy)]
pub struct Readout<'a> {
    pub chips: &'a [RawChip],
    pub exposure_no: i64,
    pub binning: Option<[u32; 2]>,
    pub bitpix: Bitpix,
}

/// Write one exposure's chip files `DIR/STEM_<chip>.fits`: every raw pixel is the chip's bias
/// level plus its read noise (drawn from `rng`; inside the chip's image area only when
/// `read_noise_inside`, for signals that carry their own), and pixels of the image area add
/// `signal(chip, p, rng)` ADU for detector pixel `p` of chip number `chip`. Each file carries `keys` and the chip's own
/// keywords (its match keyword, exposure number, binning, pre/overscan sizes, gain, read
/// noise). Returns the files in chip order.
#[allow(clippy::too_many_arguments)]
pub fn write_chip_files(
    inst: &Instrument,
    readout: &Readout,
    keys: &[(String, KeyValue, String)],
    read_noise_inside: bool,
    rng: &mut Xoshiro256PlusPlus,
    dir: &Path,
    stem: &str,
    signal: &mut dyn FnMut(usize, usize, &mut Xoshiro256PlusPlus) -> f64,
) -> Result<Vec<PathBuf>, Error> {
    let d = &inst.detector;
    let fmt = &inst.format;
    let chips = readout.chips;
    if chips.len() != fmt.chips.len() || fmt.chips.is_empty() {
        return Err(Error::File {
            path: dir.join(stem),
            message: format!("instrument {} has {} chips, {} read-outs given", inst.name, fmt.chips.len(), chips.len()),
        });
    }
    let unit = Normal::new(0.0, 1.0).expect("unit normal");
    let mut out = Vec::new();
    for (ci, (c, rc)) in fmt.chips.iter().zip(chips).enumerate() {
        let [prx, ovx, pry, ovy] = scan_sizes(c, rc);
        let [cx, cy] = c.size_px;
        let [x0, y0] = c.origin_px;
        let (rnx, rny) = (prx + cx + ovx, pry + cy + ovy);
        let rn_adu = rc.read_noise_e / rc.gain_e_per_adu;
        let mut img = vec![0.0; rnx * rny];
        for ry in 0..rny {
            for rx in 0..rnx {
                let inside = rx >= prx && rx < prx + cx && ry >= pry && ry < pry + cy;
                let mut v = rc.bias_adu;
                if read_noise_inside || !inside {
                    v += rn_adu * unit.sample(rng);
                }
                if inside {
                    v += signal(ci, (y0 + ry - pry) * d.nx + x0 + rx - prx, rng);
                }
                img[ry * rnx + rx] = v;
            }
        }
        let mut ck: Vec<(String, KeyValue, String)> = Vec::new();
        if let (Some(k), Some(v)) = (&c.match_keyword, &c.match_value) {
            ck.push((k.clone(), KeyValue::Str(v.clone()), String::new()));
        }
        ck.extend(keys.iter().cloned());
        // The exposure number under each exposure keyword the exposure's own keys do not hold
        // already (a rotor's position is both: its value is the exposure's).
        for k in &fmt.exposure_keywords {
            if !ck.iter().any(|(n, _, _)| n == k) {
                ck.push((k.clone(), KeyValue::I64(readout.exposure_no), String::new()));
            }
        }
        let binning = readout
            .binning
            .unwrap_or([fmt.binning.first().copied().unwrap_or(1), fmt.binning.get(1).copied().unwrap_or(1)]);
        for (k, b) in fmt.binning_keywords.iter().zip(binning) {
            ck.push((k.clone(), KeyValue::I64(b as i64), String::new()));
        }
        for (v, n) in [(&c.prescan_x, prx), (&c.overscan_x, ovx), (&c.prescan_y, pry), (&c.overscan_y, ovy)] {
            if let Some(NumberOrKeyword::Keyword(k)) = v {
                ck.push((k.clone(), KeyValue::I64(n as i64), "[px]".into()));
            }
        }
        if let Some(NumberOrKeyword::Keyword(k)) = &c.gain_e_per_adu {
            ck.push((k.clone(), KeyValue::F64(rc.gain_e_per_adu), "[e-/ADU]".into()));
        }
        if let Some(NumberOrKeyword::Keyword(k)) = &c.read_noise_e {
            ck.push((k.clone(), KeyValue::F64(rc.read_noise_e), "[e-]".into()));
        }
        let path = dir.join(format!("{stem}_{}.fits", c.name));
        write_frame(&path, rnx, rny, &img, readout.bitpix, &ck)?;
        out.push(path);
    }
    Ok(out)
}

/// A chip's `[prescan x, overscan x, prescan y, overscan y]` (binned px): the format's numbers,
/// the read-out's where the format names a keyword, 0 where it declares none.
pub fn scan_sizes(c: &Chip, rc: &RawChip) -> [usize; 4] {
    let count = |v: &Option<NumberOrKeyword>, k: usize| match v {
        Some(NumberOrKeyword::Number(x)) => *x as usize,
        Some(NumberOrKeyword::Keyword(_)) => rc.scan[k],
        None => 0,
    };
    [count(&c.prescan_x, 0), count(&c.overscan_x, 1), count(&c.prescan_y, 2), count(&c.overscan_y, 3)]
}
