//! FORS2-format raw frames from known pixel values: a FORS2 shrunk to a 64 x 68 px
//! mosaic (two 64 x 32 chips in separate files, a 4-row gap, 2x2 binning keywords, 5-row
//! prescan and overscan, gain and read noise in ESO keywords), a uniformly polarized sky with
//! `F_i = Q cos 4theta + U sin 4theta` (eq:F) behind the strip mask, a flat-field pattern, a
//! bias level with a column pattern, photon and read noise; written by `sim::raw`.

use instrument::Instrument;
use sim::raw::{write_raw_exposure, RawChip, RawExposure};
use skyfield::beams::BeamGeometry;
use std::path::{Path, PathBuf};

pub const Q0: f64 = 0.021;
pub const U0: f64 = -0.013;
/// Sky electrons per pixel pair (o + e).
pub const I0: f64 = 40000.0;
pub const ANGLES: [f64; 4] = [0.0, 22.5, 45.0, 67.5];

/// The shrunk FORS2 instrument file's text.
pub fn fors2_tiny_text() -> String {
    include_str!("../../../../instruments/fors2.toml")
        .replace("nx = 2048", "nx = 64")
        .replace("ny = 2064", "ny = 68")
        .replace("origin_px = [0, 1040]", "origin_px = [0, 36]")
        .replace("size_px = [2048, 1024]", "size_px = [64, 32]")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 2.0")
        // Three evenly spaced strips, e above o, one whole-pixel throw (not FORS2's published
        // strips and o/e offset polynomial, which need the full-size detector).
        .replace(
            "strip_starts_px = [432.0, 613.5, 796.0, 975.5, 1156.5, 1338.0, 1520.5, 1701.5, 1884.0]",
            "strip_count = 3\nfirst_strip_y_px = 2",
        )
        .replace("strip_margin_px = 8.6 ", "strip_margin_px = 0 ")
        .replace("extraordinary_offset_sign = -1", "extraordinary_offset_sign = 1")
        .replace("\nthrow_terms = [", "\n# throw_terms = [")
}

/// EFOSC2 shrunk to one 64 x 64 px chip (three strips, a 1.92" = 8 px throw), its 6 + 6
/// unusable over-scan rows and columns and its declared raw bias level kept.
pub fn efosc2_tiny_text() -> String {
    include_str!("../../../../instruments/efosc2.toml")
        .replace("nx = 1024", "nx = 64")
        .replace("ny = 1024", "ny = 64")
        .replace("size_px = [1024, 1024]", "size_px = [64, 64]")
        .replace("throw_arcsec = 20.0", "throw_arcsec = 1.92")
        .replace("strip_count = 6 ", "strip_count = 3 ")
        .replace("first_strip_y_px = 12 ", "first_strip_y_px = 2 ")
        .replace("strip_margin_px = 1 ", "strip_margin_px = 0 ")
}

pub fn fors2_tiny() -> Instrument {
    Instrument::from_toml_str(&fors2_tiny_text(), Path::new("fors2_tiny.toml")).unwrap()
}

/// The two chips' read-outs: different bias levels and gains (read from their headers).
pub const CHIPS: [RawChip; 2] = [
    RawChip { bias_adu: 200.0, gain_e_per_adu: 1.25, read_noise_e: 3.0, scan: [0, 0, 5, 5] },
    RawChip { bias_adu: 212.0, gain_e_per_adu: 1.40, read_noise_e: 3.5, scan: [0, 0, 5, 5] },
];

/// The flat-field pattern (relative response, known).
pub fn flat(inst: &Instrument) -> Vec<f64> {
    let (nx, ny) = (inst.detector.nx, inst.detector.ny);
    (0..nx * ny).map(|p| 1.0 + 0.08 * ((p % nx) as f64 / 5.0).sin() * ((p / nx) as f64 / 7.0).cos()).collect()
}

/// A bias pattern on top of the chips' levels: a 4 ADU ramp along x.
pub fn bias_pattern(inst: &Instrument) -> Vec<f64> {
    let nx = inst.detector.nx;
    (0..nx * inst.detector.ny).map(|p| 4.0 * (p % nx) as f64 / nx as f64).collect()
}

/// The ideal sky in electrons at HWP angle `a` (deg): the o and e images of every sky pixel.
pub fn sky_electrons(inst: &Instrument, a: f64) -> Vec<f64> {
    let g = BeamGeometry::new(inst);
    let t = 4.0 * a.to_radians();
    let f = Q0 * t.cos() + U0 * t.sin();
    let mut d = vec![0.0; g.nx * g.ny];
    for (x, y) in g.sky_pixels() {
        let (o, e) = g.beams_of_sky(x, y).unwrap();
        d[o] = 0.5 * I0 * (1.0 + f);
        d[e] = 0.5 * I0 * (1.0 - f);
    }
    d
}

fn exposure<'a>(e: &'a [f64], hwp: Option<f64>, no: i64) -> RawExposure<'a> {
    RawExposure { electrons: e, hwp_deg: hwp, filter: "v_HIGH".into(), exptime_s: 10.0, exposure_no: no, binning: None }
}

/// Science frames (4 HWP angles), bias frames (5) and flats (3): the chip files of each, in
/// exposure order (chip files of one exposure next to each other).
pub struct RawSet {
    pub science: Vec<PathBuf>,
    pub bias: Vec<PathBuf>,
    pub flats: Vec<PathBuf>,
}

pub fn write_raw_set(dir: &Path, inst: &Instrument) -> RawSet {
    let fl = flat(inst);
    let bp = bias_pattern(inst);
    // One exposure's chip files: electrons, HWP angle, exposure number, flat applied or not,
    // photon noise, seed and name.
    let write = |e: &[f64], hwp: f64, no: i64, flat: bool, noise: bool, seed: u64, name: String| {
        write_raw_exposure(
            inst,
            &exposure(e, Some(hwp), no),
            flat.then_some(&fl[..]),
            Some(&bp),
            &CHIPS,
            noise,
            seed,
            dir,
            &name,
        )
        .unwrap()
    };
    let mut s = RawSet { science: vec![], bias: vec![], flats: vec![] };
    for (k, &a) in ANGLES.iter().enumerate() {
        let e = sky_electrons(inst, a);
        s.science.extend(write(&e, a, k as i64, true, true, 100 + k as u64, format!("sci{k}")));
    }
    let zero = vec![0.0; inst.detector.nx * inst.detector.ny];
    for k in 0..5 {
        s.bias.extend(write(&zero, 0.0, 10 + k, false, false, 200 + k as u64, format!("bias{k}")));
    }
    let lamp = vec![30000.0; inst.detector.nx * inst.detector.ny];
    for k in 0..3 {
        s.flats.extend(write(&lamp, 0.0, 20 + k, true, true, 300 + k as u64, format!("flat{k}")));
    }
    s
}
