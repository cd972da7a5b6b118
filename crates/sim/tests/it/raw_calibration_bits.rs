//! Raw FORS2-format frames calibrated and reduced by the library give the same bits as a
//! straightforward calibration written here, independently of `skyfield::calib` (the
//! calibration folded into the reduction's row pass for speed must not change a number).
//!
//! The reference reads every chip file whole with CFITSIO (`fitsio`, u16 as stored), takes each
//! chip's bias level as the robust mean of its prescan and overscan pixels (a full sort for the
//! median and the MAD, then the mean of the values within 3 x `MAD_TO_SIGMA` MAD, summed in row-major
//! order), computes `((raw - level - bias) * gain * (1 / flat))` per pixel with the masters read
//! by CFITSIO, marks saturated raw values and the chip gap, and places the chips in the
//! detector frame. Those frames go through `FrameSet::from_frames` + `reduce_set` (frames in
//! memory); the library's `read_exposures` must give the same frames and `reduce_files_with`
//! (frames read from the files) the same map, bit for bit, with one and with two exposures per
//! HWP angle, with and without master frames, and with a chip that has x prescan/overscan
//! columns as well as y rows.

use fitsio::FitsFile;
use instrument::Instrument;
use sim::raw::{write_raw_exposure, RawChip, RawExposure};
use skyfield::beams::BeamGeometry;
use skyfield::calib::{read_exposures, ReadOptions};
use skyfield::frame::{Conversion, Frame, GAP, SATURATED};
use skyfield::reduce::{reduce_files_with, reduce_set, FrameSet, ReduceConfig};
use std::path::{Path, PathBuf};

const ANGLES: [f64; 4] = [0.0, 22.5, 45.0, 67.5];

/// FORS2 shrunk to a 96 x 76 px mosaic: two 96 x 36 chips, a 4-row gap, three strips.
fn tiny_text() -> String {
    include_str!("../../../../instruments/fors2.toml")
        .replace("nx = 2048", "nx = 96")
        .replace("ny = 2064", "ny = 76")
        .replace("origin_px = [0, 1040]", "origin_px = [0, 40]")
        .replace("size_px = [2048, 1024]", "size_px = [96, 36]")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 2.0")
        // Three evenly spaced strips, e above o, one whole-pixel throw (not FORS2's published
        // strips and o/e offset polynomial, which need the full-size detector).
        .replace(
            "strip_starts_px = [432.0, 613.5, 796.0, 975.5, 1156.5, 1338.0, 1520.5, 1701.5, 1884.0]",
            "strip_count = 3\nfirst_strip_y_px = 3",
        )
        .replace("strip_margin_px = 8.6 ", "strip_margin_px = 0 ")
        .replace("extraordinary_offset_sign = -1", "extraordinary_offset_sign = 1")
        .replace("\nthrow_terms = [", "\n# throw_terms = [")
}

/// Chip 1 has 3 prescan and 4 overscan columns besides its 5 + 5 rows; chip 2 rows only.
const CHIPS: [RawChip; 2] = [
    RawChip { bias_adu: 200.0, gain_e_per_adu: 1.25, read_noise_e: 3.0, scan: [3, 4, 5, 5] },
    RawChip { bias_adu: 212.0, gain_e_per_adu: 1.40, read_noise_e: 3.5, scan: [0, 0, 5, 5] },
];

struct Set {
    science: Vec<PathBuf>,
    bias: PathBuf,
    flat: PathBuf,
}

/// `per_angle` exposures at each HWP angle (chip files of each exposure next to each other),
/// and a master bias and flat made by the library from raw bias and flat frames.
fn write_set(dir: &Path, inst: &Instrument, per_angle: usize) -> Set {
    let (nx, ny) = (inst.detector.nx, inst.detector.ny);
    let g = BeamGeometry::new(inst);
    let flat: Vec<f64> = (0..nx * ny).map(|p| 1.0 + 0.06 * ((p % nx) as f64 / 7.0).sin()).collect();
    let pattern: Vec<f64> = (0..nx * ny).map(|p| 3.0 * (p % nx) as f64 / nx as f64).collect();
    fn ex(e: &[f64], a: f64, no: i64) -> RawExposure<'_> {
        RawExposure {
            electrons: e,
            hwp_deg: Some(a),
            filter: "v_HIGH".into(),
            exptime_s: 10.0,
            exposure_no: no,
            binning: None,
        }
    }
    let mut science = Vec::new();
    for r in 0..per_angle {
        for (k, &a) in ANGLES.iter().enumerate() {
            let t = 4.0 * a.to_radians();
            let f = 0.02 * t.cos() - 0.011 * t.sin();
            let mut e = vec![0.0; nx * ny];
            for (n, (x, y)) in g.sky_pixels().enumerate() {
                let (o, ee) = g.beams_of_sky(x, y).unwrap();
                // A few saturating stars among the sky.
                let i = if n % 97 == 5 { 2.0e5 } else { 3000.0 + 10.0 * (x % 13) as f64 };
                e[o] = i * (1.0 + f);
                e[ee] = i * (1.0 - f);
            }
            let no = (r * ANGLES.len() + k) as i64;
            let stem = format!("sci{no:02}");
            science.extend(
                write_raw_exposure(
                    inst,
                    &ex(&e, a, no),
                    Some(&flat),
                    Some(&pattern),
                    &CHIPS,
                    true,
                    no as u64,
                    dir,
                    &stem,
                )
                .unwrap(),
            );
        }
    }
    let (mut b, mut fl) = (Vec::new(), Vec::new());
    let zero = vec![0.0; nx * ny];
    let lamp = vec![20000.0; nx * ny];
    for k in 0..3 {
        let s = 100 + k as u64;
        b.extend(
            write_raw_exposure(
                inst,
                &ex(&zero, 0.0, 100 + k),
                None,
                Some(&pattern),
                &CHIPS,
                false,
                s,
                dir,
                &format!("b{k}"),
            )
            .unwrap(),
        );
        let s = 200 + k as u64;
        let f = write_raw_exposure(
            inst,
            &ex(&lamp, 0.0, 200 + k),
            Some(&flat),
            Some(&pattern),
            &CHIPS,
            true,
            s,
            dir,
            &format!("f{k}"),
        );
        fl.extend(f.unwrap());
    }
    let (bias, flatp) = (dir.join("BIAS.fits"), dir.join("FLAT.fits"));
    skyfield::calib::master_bias(&b, inst, 3.0).unwrap().write(&bias, inst).unwrap();
    skyfield::calib::master_flat(&fl, inst, Some(&bias), 3.0).unwrap().write(&flatp, inst).unwrap();
    Set { science, bias, flat: flatp }
}

fn key_f64(f: &mut FitsFile, key: &str) -> f64 {
    let h = f.primary_hdu().unwrap();
    h.read_key::<f64>(f, key).unwrap_or_else(|e| panic!("{key}: {e}"))
}

fn read_f32(p: &Path) -> Vec<f32> {
    let mut f = FitsFile::open(p).unwrap();
    let h = f.primary_hdu().unwrap();
    h.read_image(&mut f).unwrap()
}

/// Mean of the values within 3 robust sigmas (`MAD_TO_SIGMA` MAD) of the median, medians by sorting.
fn robust_mean(v: &[f64]) -> f64 {
    let median = |w: &[f64]| {
        let mut s = w.to_vec();
        s.sort_by(f64::total_cmp);
        let n = s.len();
        if n % 2 == 1 {
            s[n / 2]
        } else {
            0.5 * (s[n / 2 - 1] + s[n / 2])
        }
    };
    let med = median(v);
    let dev: Vec<f64> = v.iter().map(|x| (x - med).abs()).collect();
    let s = stokes::stats::robust::MAD_TO_SIGMA * median(&dev);
    let kept: Vec<f64> = v.iter().copied().filter(|x| (x - med).abs() <= 3.0 * s).collect();
    if kept.is_empty() {
        return med;
    }
    kept.iter().sum::<f64>() / kept.len() as f64
}

/// The reference frames: one per exposure, in electrons (f32 values, as the library holds
/// calibrated frames), from the chip files given two by two.
fn reference_frames(inst: &Instrument, science: &[PathBuf], masters: Option<(&Path, &Path)>) -> Vec<Frame> {
    let (nx, ny) = (inst.detector.nx, inst.detector.ny);
    let sat = inst.detector.saturation_adu;
    let bias = masters.map(|(b, _)| read_f32(b));
    let inv_flat: Option<Vec<f32>> =
        masters.map(|(_, f)| read_f32(f).into_iter().map(|v| if v > 0.0 { 1.0 / v } else { f32::NAN }).collect());
    let mut frames = Vec::new();
    for pair in science.chunks(2) {
        let mut data = vec![GAP as f32; nx * ny];
        let mut rn2 = 0.0f64;
        let mut hwp = 0.0;
        for (c, path) in inst.format.chips.iter().zip(pair) {
            assert!(path.to_string_lossy().ends_with(&format!("{}.fits", c.name)), "{}", path.display());
            let mut f = FitsFile::open(path).unwrap();
            let k = |f: &mut FitsFile, s: &str| key_f64(f, &format!("HIERARCH ESO DET OUT1 {s}")) as usize;
            let (prx, ovx, pry, ovy) = (k(&mut f, "PRSCX"), k(&mut f, "OVSCX"), k(&mut f, "PRSCY"), k(&mut f, "OVSCY"));
            let gain = key_f64(&mut f, "HIERARCH ESO DET OUT1 CONAD");
            let rn = key_f64(&mut f, "HIERARCH ESO DET OUT1 RON");
            rn2 = rn2.max(rn * rn);
            hwp = key_f64(&mut f, "HIERARCH ESO INS RETA2 POSANG");
            let h = f.primary_hdu().unwrap();
            let raw: Vec<u16> = h.read_image(&mut f).unwrap();
            let [cx, cy] = c.size_px;
            let rnx = prx + cx + ovx;
            assert_eq!(raw.len(), rnx * (pry + cy + ovy));
            let scan: Vec<f64> = (0..pry + cy + ovy)
                .flat_map(|y| (0..rnx).map(move |x| (x, y)))
                .filter(|&(x, y)| y < pry || y >= pry + cy || x < prx || x >= prx + cx)
                .map(|(x, y)| raw[y * rnx + x] as f64)
                .filter(|v| *v < sat)
                .collect();
            let level = robust_mean(&scan);
            let [x0, y0] = c.origin_px;
            for j in 0..cy {
                for i in 0..cx {
                    let r = raw[(pry + j) * rnx + prx + i] as f64;
                    let p = (y0 + j) * nx + x0 + i;
                    let b = bias.as_ref().map_or(0.0, |m| m[p] as f64);
                    let fi = inv_flat.as_ref().map_or(1.0, |m| m[p] as f64);
                    data[p] = if r >= sat { SATURATED as f32 } else { ((r - level - b) * gain * fi) as f32 };
                }
            }
        }
        frames.push(Frame {
            chips: vec![],
            path: pair[0].clone(),
            nx,
            ny,
            data: data.into_iter().map(f64::from).collect(),
            hwp_deg: hwp,
            hwp_sweep_deg: 0.0,
            filter: "v_HIGH".into(),
            exptime_s: Some(10.0),
            bitpix: 16,
            conversion: Conversion::electrons(rn2),
        });
    }
    frames
}

/// Saturated values (the calibration's marker) among the o and e pixels of the sky pixels the
/// bins of `cfg` cover, each pixel counted once per beam it serves.
fn saturated_used(inst: &Instrument, cfg: &ReduceConfig, frame: &[f64]) -> usize {
    let g = BeamGeometry::new(inst);
    let geom = skyfield::reduce::bin_geometry(inst, cfg.bin_px);
    let xs = geom.origin_x..geom.origin_x + geom.nx * geom.bin_px;
    let ys = geom.origin_y..geom.origin_y + geom.ny * geom.bin_px;
    let sat = SATURATED as f32 as f64;
    g.sky_pixels()
        .filter(|(x, y)| xs.contains(x) && ys.contains(y))
        .filter_map(|(x, y)| g.beams_of_sky(x, y))
        .map(|(o, e)| usize::from(frame[o] == sat) + usize::from(frame[e] == sat))
        .sum()
}

fn same_bits(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

#[test]
fn raw_calibration_and_reduction_are_the_straightforward_computation_to_the_bit() {
    let inst = Instrument::from_toml_str(&tiny_text(), Path::new("fors2_tiny.toml")).unwrap();
    let cfg = ReduceConfig { bin_px: 8, ..Default::default() };
    for per_angle in [1, 2] {
        let dir = tempfile::tempdir().unwrap();
        let set = write_set(dir.path(), &inst, per_angle);
        for with_masters in [true, false] {
            let label = format!("{per_angle} exposure(s) per angle, masters {with_masters}");
            let opts = if with_masters {
                ReadOptions { bias: Some(set.bias.clone()), flat: Some(set.flat.clone()), ..Default::default() }
            } else {
                ReadOptions::default()
            };
            let masters = with_masters.then_some((set.bias.as_path(), set.flat.as_path()));
            let reference = reference_frames(&inst, &set.science, masters);
            assert_eq!(reference.len(), 4 * per_angle);
            // Some raw pixels saturated, some in the gap: the markers are exercised.
            let all: Vec<f64> = reference.iter().flat_map(|f| f.data.iter().copied()).collect();
            assert!(all.contains(&(SATURATED as f32 as f64)), "{label}: no saturated pixel");
            assert!(all.contains(&(GAP as f32 as f64)), "{label}: no gap pixel");

            let lib = read_exposures(&set.science, &inst, &opts).unwrap();
            assert_eq!(lib.len(), reference.len());
            for (a, b) in lib.iter().zip(&reference) {
                assert!(same_bits(&a.data, &b.data), "{label}: {} calibrated differently", b.path.display());
                assert_eq!(a.conversion, b.conversion, "{label}");
            }

            // Saturated values each file's reduction counts: over the o and e pixels of every
            // binned sky pixel, counted here from the reference frames.
            let want_sat: Vec<usize> = reference.iter().map(|f| saturated_used(&inst, &cfg, &f.data)).collect();
            assert!(want_sat.iter().any(|&n| n > 0), "{label}: no saturated pixel among those used");
            let want = reduce_set(&FrameSet::from_frames(reference, &inst, true).unwrap(), &inst, &cfg).unwrap().map;
            let reduced = reduce_files_with(&set.science, &inst, &cfg, &opts, &|| {}).unwrap();
            // Each chip file names its own (the exposure's notes are per chip): their sum is the
            // exposure's count.
            for (p, &n) in set.science.iter().filter(|p| p.to_string_lossy().contains("CHIP1")).zip(&want_sat) {
                let chip2 = PathBuf::from(p.to_string_lossy().replace("CHIP1", "CHIP2"));
                let said = reduced
                    .warnings
                    .iter()
                    .filter(|w| {
                        let of = |q: &Path| w.file.as_deref() == Some(q);
                        (of(p) || of(&chip2)) && w.message.contains("saturated")
                    })
                    .map(|w| w.message.split_whitespace().next().unwrap().parse::<usize>().unwrap())
                    .sum::<usize>();
                assert_eq!(said, n, "{label}: saturated values counted for {}", p.display());
            }
            let got = reduced.map;
            assert!(want.n_valid() > 20, "{label}: {} valid bins", want.n_valid());
            assert_eq!(got.valid, want.valid, "{label}");
            assert_eq!(got.n_pixels, want.n_pixels, "{label}");
            for (name, a, b) in [
                ("q", &got.q, &want.q),
                ("u", &got.u, &want.u),
                ("sigma_q", &got.sigma_q, &want.sigma_q),
                ("sigma_u", &got.sigma_u, &want.sigma_u),
                ("sigma_q_phot", &got.sigma_q_phot, &want.sigma_q_phot),
                ("intensity", &got.intensity, &want.intensity),
            ] {
                assert!(same_bits(a, b), "{label}: {name} differs");
            }
        }
    }
}
