//! Fixtures shared by the `instpol` integration tests (each test file says `mod common;`):
//! running the binary, tiny instruments, FORS1 calibrations and the paper's V-field map.
//! Each test binary uses a part of it, hence the `dead_code` allowance.
#![allow(dead_code)]

pub mod invocations;
pub mod mueller_maps;
pub mod night;
pub mod raw;
#[path = "../../../fit/tests/common/shared_data.rs"]
pub mod shared_data;
#[allow(dead_code)]
pub mod standards;

use fit::files::calfile::{Model, PixelGrid, Provenance, FORMAT_VERSION};
use fit::models::synth::{sky_field, FnField};
use fit::{Calibration, FieldRegion, RadialModel};
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `instpol` binary under test.
pub fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_instpol")
}

/// A command for the binary under test.
pub fn instpol() -> Command {
    Command::new(bin())
}

/// Run the binary with `args`: (exit code, -1 on a signal; stdout; stderr).
pub fn run<S: AsRef<OsStr>>(args: &[S]) -> (i32, String, String) {
    let o: Output = instpol().args(args).output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into(),
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

/// [`run`] of the subcommand `sub`.
pub fn run_sub(sub: &str, args: &[&str]) -> (i32, String, String) {
    let mut a = vec![sub];
    a.extend_from_slice(args);
    run(&a)
}

/// Files in `dir` (names only), sorted.
pub fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> =
        std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

/// A tiny dual-beam imager in the layout of `instruments/fors1.toml` (strips along y from row
/// 4, the FORS header keywords, one V filter), small enough for a test to make its frames.
#[derive(Clone, Copy)]
pub struct Mini {
    pub name: &'static str,
    pub nx: usize,
    pub pixel_scale_arcsec: f64,
    pub gain_e_per_adu: f64,
    pub read_noise_e: f64,
    pub saturation_adu: f64,
    pub field_arcmin: f64,
    pub throw_arcsec: f64,
    pub strip_count: usize,
}

/// 96 x 96 px of 4": five strips of 8 px (the throw).
pub const MINI: Mini = Mini {
    name: "MINI",
    nx: 96,
    pixel_scale_arcsec: 4.0,
    gain_e_per_adu: 1.0,
    read_noise_e: 3.0,
    saturation_adu: 60000.0,
    field_arcmin: 6.4,
    throw_arcsec: 32.0,
    strip_count: 5,
};

/// A small FORS1-like instrument: 512 x 512 px of 0.8", FORS1's 6.8' field and nine strips,
/// so that a whole frame chain (simulate, reduce, calibrate) runs in a test.
pub const SMALL: Mini = Mini {
    name: "SMALL",
    nx: 512,
    pixel_scale_arcsec: 0.8,
    gain_e_per_adu: 1.25,
    read_noise_e: 5.0,
    saturation_adu: 65535.0,
    field_arcmin: 6.8,
    throw_arcsec: 22.4,
    strip_count: 9,
};

impl Mini {
    /// The instrument file (TOML).
    pub fn toml(&self) -> String {
        format!(
            r#"
name = "{name}"
description = "a tiny dual-beam imager for tests"

[detector]
nx = {nx}
ny = {nx}
pixel_scale_arcsec = {scale:?}
gain_e_per_adu = {gain:?}
read_noise_e = {rn:?}
saturation_adu = {sat:?}
bias_adu = 0.0

[field]
width_arcmin = {field:?}
height_arcmin = {field:?}

[polarimetry]
throw_arcsec = {throw:?}
strip_axis = "y"
strip_count = {strips}
first_strip_y_px = 4
extraordinary_offset_sign = 1
hwp_angle_keyword = "HIERARCH ESO INS RETA2 POSANG"
filter_keyword = "HIERARCH ESO INS FILT1 NAME"
exptime_keyword = "EXPTIME"

[[filters]]
name = "V"
lambda_eff_nm = 554.0
"#,
            name = self.name,
            nx = self.nx,
            scale = self.pixel_scale_arcsec,
            gain = self.gain_e_per_adu,
            rn = self.read_noise_e,
            sat = self.saturation_adu,
            field = self.field_arcmin,
            throw = self.throw_arcsec,
            strips = self.strip_count
        )
    }
}

/// A `plan` that runs in seconds: FORS1 in 200 px bins for a 0.05 % target, two candidate
/// fields (the paper's B sky, 6.45 % at 68.4 deg, and 4 % at 10 deg). Add `--plot FILE` and
/// the rest.
pub const QUICK_PLAN: [&str; 11] = [
    "plan",
    "--target-percent",
    "0.05",
    "--sky-rate",
    "2",
    "--bin",
    "200",
    "--candidate",
    "6.45:68.4",
    "--candidate",
    "4:10",
];

/// `instruments/fors1.toml` shrunk to a 128 x 128 detector with one strip of `throw_arcsec`
/// (pixels of 0.2") from row `first_strip_y_px`, written to `dir/tiny.toml`.
pub fn tiny_fors1(dir: &Path, throw_arcsec: f64, first_strip_y_px: usize) -> PathBuf {
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 128")
        .replace("ny = 2048", "ny = 128")
        .replace("throw_arcsec = 22.0", &format!("throw_arcsec = {throw_arcsec:?}"))
        .replace("strip_count = 9", "strip_count = 1")
        .replace("first_strip_y_px = 34", &format!("first_strip_y_px = {first_strip_y_px}"));
    let p = dir.join("tiny.toml");
    std::fs::write(&p, text).unwrap();
    p
}

/// The `.fits` files of a folder, sorted (the frames `instpol simulate` wrote).
pub fn fits_in(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "fits"))
        .collect();
    v.sort();
    v
}

/// FORS1: 2048 px at 0.2"/px, half-width 3.413 arcmin.
pub const FORS1_HALF_ARCMIN: f64 = 1024.0 * 0.2 / 60.0;

/// The paper's V polynomial (section `sec:fors1`), as fractions.
pub const V_COEFFS: [f64; 3] = [0.012e-2, 0.046e-2, 0.002e-2];

/// A FORS1 calibration with a centred radial model of `coeffs` (fractions, powers r^1..r^3)
/// over the whole detector, the paper's fit RMS (section sec:fors1: "of the order of
/// 0.05%"), no HWP zero angle and no wavelength.
pub fn fors1_radial_calibration(filter: &str, coeffs: [f64; 3]) -> Calibration {
    let h = FORS1_HALF_ARCMIN;
    Calibration {
        format_version: FORMAT_VERSION,
        instrument: "FORS1".into(),
        filter: filter.into(),
        lambda_nm: f64::NAN,
        hwp_chi_offset_deg: 0.0,
        model: Model::Radial(RadialModel::new(1, coeffs.to_vec(), [0.0, 0.0])),
        region: FieldRegion { x_min: -h, x_max: h, y_min: -h, y_max: h },
        rms_residual: 5e-4,
        n_bins_used: 0,
        polar_angle: None,
        exclusions: vec![],
        robust: "none".into(),
        pixel: Some(PixelGrid { scale_arcsec: 0.2, origin_px: [1023.5, 1023.5] }),
        provenance: Provenance::now("test", vec![]),
        bins: vec![],
        grid: None,
    }
}

/// A FORS1-like binned map (60 px bins: fast) of the V field (fig:insmapV) seen through the
/// sky of Table tab:empty, measured with noise 1e-4 per bin; `keep` selects the valid bins.
pub fn write_v_sky_map(path: &Path, keep: impl Fn(usize) -> bool) {
    let geom = skyfield::BinGeometry::covering(60, 0, 0, 2048, 2048, 0.2);
    let mut map = skyfield::StokesMap::empty(geom.clone(), "FORS1", "V", vec![0.0, 22.5, 45.0, 67.5]);
    let centres: Vec<(f64, f64)> = (0..geom.len()).map(|k| geom.centre_arcmin(k % geom.nx, k / geom.nx)).collect();
    let truth = RadialModel::new(1, V_COEFFS.to_vec(), [0.0, 0.0]);
    let sky = skyfield::solve::SkyPolarization::from_percent_deg(1.74, -53.8).unwrap();
    let (q0, u0) = sky.qu();
    let m = sky_field(&centres, &FnField(move |x, y| truth.qu(x, y)), q0, u0, 1e-4, 9);
    for (k, b) in m.iter().enumerate() {
        if !keep(k) {
            continue;
        }
        map.q[k] = b.qu.q;
        map.u[k] = b.qu.u;
        map.sigma_q[k] = 1e-4;
        map.sigma_u[k] = 1e-4;
        map.cov_qu[k] = 0.0;
        map.p[k] = b.qu.q.hypot(b.qu.u);
        map.chi[k] = 0.0;
        map.n_pixels[k] = 3600;
        map.valid[k] = true;
    }
    map.write_fits(path).unwrap();
}

/// The JSON printed by `instpol SUB ARGS --json` (which must succeed).
pub fn run_json(sub: &str, args: &[&str]) -> serde_json::Value {
    let mut a = args.to_vec();
    a.push("--json");
    let (code, out, err) = run_sub(sub, &a);
    assert_eq!(code, 0, "instpol {sub} {args:?}: {err}");
    serde_json::from_str(&out).unwrap()
}

/// `instpol import-map` arguments for the public FORS2 v_HIGH maps in `data_dir`
/// (../shared/data/fors2-instpol: 10 x 10 binned 0.25"/px pixels, README there), writing `out`.
pub fn import_fors2_v_args(data_dir: &Path, out: &Path) -> Vec<String> {
    let p = |f: &str| data_dir.join(f).to_string_lossy().into_owned();
    [
        "import-map",
        "--q",
        &p("v_HIGH_inlaQ_bin10.fits"),
        "--u",
        &p("v_HIGH_inlaU_bin10.fits"),
        "--pixel-scale",
        "0.25",
        "--bin",
        "10",
        "--filter",
        "v_HIGH",
        "--instrument",
        "FORS2",
        "--out",
        &out.to_string_lossy(),
    ]
    .iter()
    .map(|s| s.to_string())
    .collect()
}

/// `instpol calibrate` arguments for a sky-field map of the paper's V field (the sky's
/// P = 1.74 %, chi = -53.8 deg, Table tab:empty), writing `out`.
pub fn calibrate_v_args(map: &Path, out: &Path) -> Vec<String> {
    let (m, o) = (map.to_string_lossy(), out.to_string_lossy());
    ["calibrate", "--map", &m, "--sky-p", "1.74", "--sky-chi", "-53.8", "--out", &o]
        .iter()
        .map(|s| s.to_string())
        .collect()
}

/// BLAKE3 hashes of `files` (`blake3:<hex>`, in order) from an implementation other than the
/// tool's: the BLAKE3 team's `b3sum`, or Python's `blake3` package. `None`, said loudly, when
/// neither is here; with `INSTPOL_REQUIRE_B3=1` (CI sets it) that is a failure.
#[allow(dead_code)]
pub fn b3sum<P: AsRef<std::ffi::OsStr>>(files: &[P]) -> Option<Vec<String>> {
    let from_b3sum = std::process::Command::new("b3sum").arg("--no-names").args(files).output();
    let out = match from_b3sum {
        Ok(o) if o.status.success() => Some(o.stdout),
        _ => {
            let py = "import sys, blake3\nfor f in sys.argv[1:]:\n    print(blake3.blake3(open(f, 'rb').read()).hexdigest())";
            match std::process::Command::new("python3").arg("-c").arg(py).args(files).output() {
                Ok(o) if o.status.success() => Some(o.stdout),
                _ => None,
            }
        }
    };
    match out {
        Some(o) => Some(String::from_utf8(o).unwrap().lines().map(|h| format!("blake3:{}", h.trim())).collect()),
        None => {
            assert!(
                std::env::var("INSTPOL_REQUIRE_B3").map_or(true, |v| v != "1"),
                "INSTPOL_REQUIRE_B3=1 but neither b3sum nor Python's blake3 package is here"
            );
            eprintln!("WARNING: neither b3sum nor Python's blake3 package found: provenance hashes not checked against another BLAKE3");
            None
        }
    }
}

/// Check a JSON output's provenance inputs (`inputs`, in order) against [`b3sum`] of `files`:
/// each path and each hash (nothing checked, loudly, without another BLAKE3).
#[allow(dead_code)]
pub fn assert_inputs_hashed_as_b3sum<P: AsRef<std::ffi::OsStr>>(inputs: &[serde_json::Value], files: &[P]) {
    assert_eq!(inputs.len(), files.len(), "{inputs:?}");
    let Some(sums) = b3sum(files) else { return };
    assert_eq!(sums.len(), files.len());
    for ((want, inp), f) in sums.iter().zip(inputs).zip(files) {
        let path = std::path::Path::new(f.as_ref()).display().to_string();
        assert_eq!(inp["path"], path.as_str());
        assert_eq!(inp["hash"], want.as_str(), "{path}");
    }
}

/// Star catalogs of a dense field seen through the paper's V pattern (section `sec:fors1`,
/// `fit::models::paper::V_COEFFS_PCT`, angle radial about the detector centre), one CSV per pointing in
/// the columns `instpol catalog` writes (`x_arcmin, y_arcmin, q, u, sigma_q, sigma_u,
/// hwp_chi_offset_deg`): `n` stars at least 3" apart, uniform over the dithered field; the
/// first `n_pol` polarized in themselves at 1-5 %; every star shares the interstellar
/// `(iq, iu)`; each measurement drawn (seeded, Box-Muller) with Gaussian errors of `sigma`.
/// Returns the files and the sky positions of the polarized stars.
pub fn star_catalogs(
    dir: &Path,
    seed: u64,
    n: usize,
    n_pol: usize,
    (iq, iu): (f64, f64),
    sigma: f64,
    offsets: &[[f64; 2]],
) -> (Vec<PathBuf>, Vec<(f64, f64)>) {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
    let gauss = move |rng: &mut rand_xoshiro::Xoshiro256PlusPlus| {
        let (a, b): (f64, f64) = (rng.random_range(1e-300..1.0), rng.random_range(0.0..1.0));
        (-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()
    };
    let c = fit::models::paper::V_COEFFS_PCT;
    let field = |x: f64, y: f64| {
        let r = x.hypot(y);
        let p = (c[0] * r + c[1] * r * r + c[2] * r * r * r) / 100.0;
        let a = 2.0 * y.atan2(x);
        (p * a.cos(), p * a.sin())
    };
    let mut text: Vec<String> =
        offsets.iter().map(|_| "id,x_arcmin,y_arcmin,q,u,sigma_q,sigma_u,hwp_chi_offset_deg\n".to_string()).collect();
    let (mut sky, mut pol) = (Vec::<(f64, f64)>::new(), vec![]);
    for s in 0..n {
        let (sx, sy) = loop {
            let s: (f64, f64) = (rng.random_range(-3.3..3.6), rng.random_range(-3.3..3.6));
            if sky.iter().all(|&(x, y)| (x - s.0).hypot(y - s.1) > 0.05) {
                break s;
            }
        };
        sky.push((sx, sy));
        let (pq, pu) = if s < n_pol {
            let p: f64 = rng.random_range(0.01..0.05);
            let chi: f64 = rng.random_range(0.0..std::f64::consts::PI);
            pol.push((sx, sy));
            (p * (2.0 * chi).cos(), p * (2.0 * chi).sin())
        } else {
            (0.0, 0.0)
        };
        for (k, o) in offsets.iter().enumerate() {
            let (x, y) = (sx - o[0], sy - o[1]);
            if x.abs() > 3.41 || y.abs() > 3.41 {
                continue;
            }
            let (fq, fu) = field(x, y);
            let (q, u) = (fq + iq + pq + sigma * gauss(&mut rng), fu + iu + pu + sigma * gauss(&mut rng));
            text[k].push_str(&format!("{s},{x},{y},{q},{u},{sigma},{sigma},0\n"));
        }
    }
    let files = text
        .iter()
        .enumerate()
        .map(|(k, t)| {
            let p = dir.join(format!("pointing{}.csv", k + 1));
            std::fs::write(&p, t).unwrap();
            p
        })
        .collect();
    (files, pol)
}
