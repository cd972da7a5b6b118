//! Raw frames as an instrument's read-out writes them: an image in electrons on the detector
//! frame is cut into the chips of the instrument's `[format]`, multiplied by a flat-field
//! pattern, converted to ADU with each chip's gain, given a bias level (plus an optional
//! per-pixel bias pattern), read noise and photon noise, padded with prescan and overscan
//! regions that hold only bias and read noise, and written one file per chip with the header
//! keywords the format names (chip name, binning, pre/overscan sizes, gain, read noise,
//! exposure number, HWP angle, filter, exposure time). What `skyfield::calib` undoes.

use crate::Error;
use instrument::{Instrument, NumberOrKeyword};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;
use skyfield::io::{write_frame, Bitpix, KeyValue};
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
    let fmt = &inst.format;
    let npx = d.nx * d.ny;
    let bad = |m: String| Error::File { path: dir.join(stem), message: m };
    if exp.electrons.len() != npx
        || flat.is_some_and(|f| f.len() != npx)
        || bias_pattern.is_some_and(|b| b.len() != npx)
    {
        return Err(bad(format!("images must have {} x {} px", d.nx, d.ny)));
    }
    if chips.len() != fmt.chips.len() || fmt.chips.is_empty() {
        return Err(bad(format!(
            "instrument {} has {} chips, {} read-outs given",
            inst.name,
            fmt.chips.len(),
            chips.len()
        )));
    }
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let unit = Normal::new(0.0, 1.0).expect("unit normal");
    let mut out = Vec::new();
    for (c, rc) in fmt.chips.iter().zip(chips) {
        let count = |v: &Option<NumberOrKeyword>, k: usize| match v {
            Some(NumberOrKeyword::Number(x)) => *x as usize,
            Some(NumberOrKeyword::Keyword(_)) => rc.scan[k],
            None => 0,
        };
        let [prx, ovx, pry, ovy] =
            [count(&c.prescan_x, 0), count(&c.overscan_x, 1), count(&c.prescan_y, 2), count(&c.overscan_y, 3)];
        let [cx, cy] = c.size_px;
        let [x0, y0] = c.origin_px;
        let (rnx, rny) = (prx + cx + ovx, pry + cy + ovy);
        let rn_adu = rc.read_noise_e / rc.gain_e_per_adu;
        let mut img = vec![0.0; rnx * rny];
        for ry in 0..rny {
            for rx in 0..rnx {
                let mut v = rc.bias_adu + rn_adu * unit.sample(&mut rng);
                let inside = rx >= prx && rx < prx + cx && ry >= pry && ry < pry + cy;
                if inside {
                    let p = (y0 + ry - pry) * d.nx + x0 + rx - prx;
                    let e = exp.electrons[p] * flat.map_or(1.0, |f| f[p]);
                    let noise = if photon_noise { e.max(0.0).sqrt() * unit.sample(&mut rng) } else { 0.0 };
                    v += (e + noise) / rc.gain_e_per_adu + bias_pattern.map_or(0.0, |b| b[p]);
                }
                img[ry * rnx + rx] = v;
            }
        }
        let pol = &inst.polarimetry;
        let mut keys: Vec<(String, KeyValue, String)> = Vec::new();
        if let (Some(k), Some(v)) = (&c.match_keyword, &c.match_value) {
            keys.push((k.clone(), KeyValue::Str(v.clone()), String::new()));
        }
        if let Some(h) = exp.hwp_deg {
            keys.push((pol.hwp_angle_keyword.clone(), KeyValue::F64(h), "HWP angle [deg]".into()));
        }
        keys.push((pol.filter_keyword.clone(), KeyValue::Str(exp.filter.clone()), String::new()));
        keys.push((pol.exptime_keyword.clone(), KeyValue::F64(exp.exptime_s), "[s]".into()));
        for k in &fmt.exposure_keywords {
            keys.push((k.clone(), KeyValue::I64(exp.exposure_no), String::new()));
        }
        let binning = exp
            .binning
            .unwrap_or([fmt.binning.first().copied().unwrap_or(1), fmt.binning.get(1).copied().unwrap_or(1)]);
        for (k, b) in fmt.binning_keywords.iter().zip(binning) {
            keys.push((k.clone(), KeyValue::I64(b as i64), String::new()));
        }
        for (v, n) in [(&c.prescan_x, prx), (&c.overscan_x, ovx), (&c.prescan_y, pry), (&c.overscan_y, ovy)] {
            if let Some(NumberOrKeyword::Keyword(k)) = v {
                keys.push((k.clone(), KeyValue::I64(n as i64), "[px]".into()));
            }
        }
        if let Some(NumberOrKeyword::Keyword(k)) = &c.gain_e_per_adu {
            keys.push((k.clone(), KeyValue::F64(rc.gain_e_per_adu), "[e-/ADU]".into()));
        }
        if let Some(NumberOrKeyword::Keyword(k)) = &c.read_noise_e {
            keys.push((k.clone(), KeyValue::F64(rc.read_noise_e), "[e-]".into()));
        }
        let path = dir.join(format!("{stem}_{}.fits", c.name));
        write_frame(&path, rnx, rny, &img, Bitpix::U16, &keys)?;
        out.push(path);
    }
    Ok(out)
}
