//! The bad-input catalogue (the README section "Bad input"): every bad input tried on the `instpol`
//! binary and what it must do. Each row of the table is one test here. A bad input must give
//! exit code 2, an `error: ...` message that names the input (file, key, row, HWP angle), no
//! panic, and no output file (nor a leftover temporary) in the output folder. Inputs that are
//! handled by design (duplicated HWP angles summed, NaN and saturated pixels masked) must say
//! so in a warning naming the file and still produce a result.
//!
//! A control test runs each command on the good version of the input first, so that an
//! error below is caused by the one thing that was broken.

use fit::synth::{sky_field, FnField};
use fit::RadialModel;
use skyfield::io::{write_frame, Bitpix, KeyValue};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_instpol")
}

fn run(args: &[&str]) -> (i32, String, String) {
    let o: Output = Command::new(bin()).args(args).output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into(),
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

/// Files in `dir` (names only), sorted.
fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> =
        std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

/// Run `args`, expect a clean refusal: exit 2, `error:` naming each of `names`, no panic, and
/// the folder `dir` unchanged (no output, no temporary left behind).
#[track_caller]
fn refuses(dir: &Path, args: &[&str], names: &[&str]) -> String {
    let before = listing(dir);
    let (code, out, err) = run(args);
    if let Ok(log) = std::env::var("BAD_INPUTS_LOG") {
        use std::io::Write;
        let mut f = std::fs::OpenOptions::new().create(true).append(true).open(log).unwrap();
        let first = err.lines().next().unwrap_or("").replace('|', "\\|");
        writeln!(f, "{} | {code} | {first}", std::thread::current().name().unwrap_or("?")).unwrap();
    }
    assert!(!err.contains("panicked"), "panic on {args:?}: {err}");
    assert_eq!(code, 2, "exit code for {args:?}: stdout {out} stderr {err}");
    assert!(err.starts_with("error: "), "no 'error:' prefix: {err}");
    for n in names {
        assert!(err.contains(n), "message for {args:?} does not name '{n}': {err}");
    }
    assert_eq!(listing(dir), before, "files left behind by {args:?}");
    err
}

// ---------------------------------------------------------------------------------------
// Inputs: a tiny instrument (96 x 96 px, 4"/px), frames, Stokes maps, a calibration file.
// ---------------------------------------------------------------------------------------

const MINI: &str = r#"
name = "MINI"
description = "a tiny dual-beam imager for tests"

[detector]
nx = 96
ny = 96
pixel_scale_arcsec = 4.0
gain_e_per_adu = 1.0
read_noise_e = 3.0
saturation_adu = 60000.0
bias_adu = 0.0

[field]
width_arcmin = 6.4
height_arcmin = 6.4

[polarimetry]
throw_arcsec = 32.0
strip_axis = "y"
strip_count = 5
first_strip_y_px = 4
extraordinary_offset_sign = 1
hwp_angle_keyword = "HIERARCH ESO INS RETA2 POSANG"
filter_keyword = "HIERARCH ESO INS FILT1 NAME"
exptime_keyword = "EXPTIME"

[[filters]]
name = "V"
lambda_eff_nm = 554.0
"#;

struct Fixture {
    dir: tempfile::TempDir,
}

impl Fixture {
    fn new() -> Self {
        let f = Fixture { dir: tempfile::tempdir().unwrap() };
        std::fs::write(f.p("mini.toml"), MINI).unwrap();
        f
    }
    fn p(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }
    fn s(&self, name: &str) -> String {
        self.p(name).to_str().unwrap().to_string()
    }
    /// An output folder of its own (so that listing checks see only outputs).
    fn out_dir(&self) -> PathBuf {
        let d = self.p("out");
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// A frame of the tiny instrument: sky of 2000 ADU polarized 2% at 30 deg, seen at HWP
    /// angle `hwp` through an ideal prism, written to `name`. `edit` may change the pixels.
    fn frame(&self, name: &str, hwp: f64, filter: &str, edit: impl Fn(&mut Vec<f64>)) -> String {
        let inst = instrument::Instrument::from_toml_str(MINI, Path::new("mini.toml")).unwrap();
        let (nx, ny) = (inst.detector.nx, inst.detector.ny);
        let m = 0.02 * (4.0 * hwp.to_radians() - 2.0 * 30f64.to_radians()).cos();
        let mut data = vec![2000.0; nx * ny];
        for s in inst.strips() {
            for y in 0..s.height {
                for x in 0..nx {
                    data[(s.o_start + y) * nx + x] = 2000.0 * (1.0 + m);
                    data[(s.e_start + y) * nx + x] = 2000.0 * (1.0 - m);
                }
            }
        }
        edit(&mut data);
        let keys = vec![
            ("HIERARCH ESO INS RETA2 POSANG".to_string(), KeyValue::F64(hwp), "HWP angle".to_string()),
            ("HIERARCH ESO INS FILT1 NAME".to_string(), KeyValue::Str(filter.into()), String::new()),
            ("EXPTIME".to_string(), KeyValue::F64(10.0), String::new()),
        ];
        let path = self.p(name);
        write_frame(&path, nx, ny, &data, Bitpix::F32, &keys).unwrap();
        path.to_str().unwrap().to_string()
    }

    /// Four good frames at 0, 22.5, 45, 67.5 deg.
    fn frames(&self) -> Vec<String> {
        [0.0, 22.5, 45.0, 67.5]
            .iter()
            .enumerate()
            .map(|(i, &a)| self.frame(&format!("f{i}.fits"), a, "V", |_| {}))
            .collect()
    }

    /// A FORS1-like Stokes map (60 px bins) of the V field (the paper's pattern, fig:insmapV)
    /// through the V sky of Table tab:empty.
    fn map(&self, name: &str) -> String {
        // Keep clear of the fitsio string-column defect (see
        // `calibration_whose_input_name_is_24_chars_is_readable`): the calibration stores this
        // path in a string column, which fitsio 0.21 overflows when its width is 8 mod 16.
        let mut name = name.to_string();
        while self.p(&name).to_str().unwrap().len() % 16 == 8 {
            name.insert(0, '_');
        }
        let name = name.as_str();
        let geom = skyfield::BinGeometry::covering(60, 0, 0, 2048, 2048, 0.2);
        let mut map = skyfield::StokesMap::empty(geom.clone(), "FORS1", "V", vec![0.0, 22.5, 45.0, 67.5]);
        let centres: Vec<(f64, f64)> = (0..geom.len()).map(|k| geom.centre_arcmin(k % geom.nx, k / geom.nx)).collect();
        let truth = RadialModel::new(1, vec![0.012e-2, 0.046e-2, 0.002e-2], [0.0, 0.0]);
        let sky = skyfield::solve::SkyPolarization::from_percent_deg(1.74, -53.8).unwrap();
        let (q0, u0) = sky.qu();
        let m = sky_field(&centres, &FnField(move |x, y| truth.qu(x, y)), q0, u0, 1e-4, 9);
        for (k, b) in m.iter().enumerate() {
            map.q[k] = b.q1;
            map.u[k] = b.u1;
            map.sigma_q[k] = 1e-4;
            map.sigma_u[k] = 1e-4;
            map.cov_qu[k] = 0.0;
            map.p[k] = b.q1.hypot(b.u1);
            map.chi[k] = 0.0;
            map.n_pixels[k] = 3600;
            map.valid[k] = true;
        }
        let path = self.p(name);
        map.write_fits(&path).unwrap();
        path.to_str().unwrap().to_string()
    }

    /// A calibration file made by `instpol calibrate --map` (checked to succeed).
    fn cal(&self) -> String {
        let map = self.map("map.fits");
        let cal = self.s("cal.fits");
        let (code, _, err) =
            run(&["calibrate", "--map", &map, "--sky-p", "1.74", "--sky-chi", "-53.8", "--out", &cal, "--json"]);
        assert_eq!(code, 0, "calibrate --map failed: {err}");
        cal
    }

    fn csv(&self, name: &str, text: &str) -> String {
        std::fs::write(self.p(name), text).unwrap();
        self.s(name)
    }
}

/// Good CSV of `instpol stokes`: P = 2% at chi = 30 deg, 1e6 counts, N = 4.
const GOOD_STOKES: &str =
    "hwp_deg,f_o,f_e\n0,505000,495000\n22.5,508660.25,491339.75\n45,495000,505000\n67.5,491339.75,508660.25\n";

// ---------------------------------------------------------------------------------------
// instpol stokes: the CSV reader
// ---------------------------------------------------------------------------------------

#[test]
fn stokes_control_good_csv_reduces() {
    let f = Fixture::new();
    let good = f.csv("good.csv", GOOD_STOKES);
    let (code, out, err) = run(&["stokes", "--input", &good, "--json"]);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert!((j["p"].as_f64().unwrap() - 0.02).abs() < 1e-6, "{out}");
}

#[test]
fn stokes_missing_file() {
    let f = Fixture::new();
    refuses(f.dir.path(), &["stokes", "--input", &f.s("nope.csv")], &["nope.csv"]);
}

#[test]
fn stokes_csv_missing_column() {
    let f = Fixture::new();
    let p = f.csv("nofe.csv", "hwp_deg,f_o\n0,1\n22.5,1\n45,1\n67.5,1\n");
    refuses(f.dir.path(), &["stokes", "--input", &p], &["nofe.csv", "f_e"]);
}

#[test]
fn stokes_csv_empty_and_header_only() {
    let f = Fixture::new();
    let p = f.csv("empty.csv", "");
    refuses(f.dir.path(), &["stokes", "--input", &p], &["empty.csv"]);
    let p = f.csv("header.csv", "hwp_deg,f_o,f_e\n");
    refuses(f.dir.path(), &["stokes", "--input", &p], &["header.csv"]);
}

#[test]
fn stokes_csv_not_a_number() {
    let f = Fixture::new();
    let p = f.csv("text.csv", &GOOD_STOKES.replace("508660.25,491339.75", "lots,491339.75"));
    refuses(f.dir.path(), &["stokes", "--input", &p], &["text.csv", "lots", "f_o"]);
}

#[test]
fn stokes_csv_nan_and_inf_flux() {
    let f = Fixture::new();
    for (name, bad) in [("nan.csv", "NaN"), ("inf.csv", "inf"), ("ninf.csv", "-inf")] {
        let p = f.csv(name, &GOOD_STOKES.replace("495000,505000", &format!("{bad},505000")));
        refuses(f.dir.path(), &["stokes", "--input", &p], &[name, "f_o"]);
    }
}

#[test]
fn stokes_csv_zero_total_flux() {
    let f = Fixture::new();
    let p = f.csv("zero.csv", &GOOD_STOKES.replace("495000,505000", "0,0"));
    refuses(f.dir.path(), &["stokes", "--input", &p], &["zero.csv", "45"]);
}

#[test]
fn stokes_csv_negative_counts() {
    let f = Fixture::new();
    let p = f.csv("neg.csv", &GOOD_STOKES.replace("495000,505000", "-5,505000"));
    refuses(f.dir.path(), &["stokes", "--input", &p], &["neg.csv", "row 3", "hwp_deg = 45", "f_O", "-5"]);
}

#[test]
fn stokes_csv_duplicated_hwp_angle() {
    let f = Fixture::new();
    let p = f.csv("dup.csv", &GOOD_STOKES.replace("\n45,", "\n22.5,"));
    refuses(f.dir.path(), &["stokes", "--input", &p], &["dup.csv", "22.5"]);
}

#[test]
fn stokes_csv_missing_hwp_angles() {
    let f = Fixture::new();
    // One angle only.
    let p = f.csv("one.csv", "hwp_deg,f_o,f_e\n0,505000,495000\n");
    refuses(f.dir.path(), &["stokes", "--input", &p], &["one.csv", "angle"]);
    // Two angles 45 deg apart: Q only, U unconstrained.
    let p = f.csv("degen.csv", "hwp_deg,f_o,f_e\n0,505000,495000\n45,495000,505000\n");
    refuses(f.dir.path(), &["stokes", "--input", &p], &["degen.csv", "angle"]);
}

#[test]
fn stokes_csv_negative_sigma() {
    let f = Fixture::new();
    let p = f.csv(
        "sig.csv",
        "hwp_deg,f_o,f_e,sigma_o,sigma_e\n0,505,495,1,1\n22.5,508,491,1,-1\n45,495,505,1,1\n67.5,491,508,1,1\n",
    );
    refuses(f.dir.path(), &["stokes", "--input", &p], &["sig.csv", "row 2", "sigma_E"]);
}

#[test]
fn stokes_kappa_out_of_range() {
    let f = Fixture::new();
    let good = f.csv("good.csv", GOOD_STOKES);
    refuses(f.dir.path(), &["stokes", "--input", &good, "--kappa", "1.5"], &["kappa", "1.5"]);
}

#[test]
fn stokes_binary_garbage() {
    let f = Fixture::new();
    std::fs::write(f.p("garbage.csv"), [0u8, 159, 146, 150, 255, 0, 10, 13, 44, 44]).unwrap();
    refuses(f.dir.path(), &["stokes", "--input", &f.s("garbage.csv")], &["garbage.csv"]);
}

// ---------------------------------------------------------------------------------------
// Instrument files (--instrument PATH)
// ---------------------------------------------------------------------------------------

#[test]
fn instrument_unknown_key() {
    let f = Fixture::new();
    let p = f.csv("typo.toml", &MINI.replace("pixel_scale_arcsec", "pixel_scal_arcsec"));
    let out = f.out_dir();
    let err = refuses(&out, &["raytrace", "--instrument", &p, "--filter", "V"], &["typo.toml", "pixel_scal_arcsec"]);
    let _ = err;
    let p2 = f.csv("extra.toml", &MINI.replace("[field]", "[field]\ncolour = \"red\""));
    refuses(&out, &["raytrace", "--instrument", &p2, "--filter", "V"], &["extra.toml", "colour"]);
}

#[test]
fn instrument_wrong_type_and_missing_key() {
    let f = Fixture::new();
    let p = f.csv("type.toml", &MINI.replace("nx = 96", "nx = \"ninety-six\""));
    refuses(f.dir.path(), &["raytrace", "--instrument", &p, "--filter", "V"], &["type.toml", "nx"]);
    let p = f.csv("missing.toml", &MINI.replace("gain_e_per_adu = 1.0\n", ""));
    refuses(f.dir.path(), &["raytrace", "--instrument", &p, "--filter", "V"], &["missing.toml", "gain_e_per_adu"]);
}

#[test]
fn instrument_unknown_name_and_missing_file() {
    let f = Fixture::new();
    refuses(f.dir.path(), &["raytrace", "--instrument", "fors9", "--filter", "V"], &["fors9"]);
    refuses(f.dir.path(), &["raytrace", "--instrument", &f.s("gone.toml"), "--filter", "V"], &["gone.toml"]);
}

#[test]
fn instrument_invalid_values() {
    let f = Fixture::new();
    let p = f.csv("neg.toml", &MINI.replace("pixel_scale_arcsec = 4.0", "pixel_scale_arcsec = -4.0"));
    refuses(f.dir.path(), &["raytrace", "--instrument", &p, "--filter", "V"], &["neg.toml", "pixel_scale_arcsec"]);
    let p = f.csv("strips.toml", &MINI.replace("strip_count = 5", "strip_count = 50"));
    refuses(f.dir.path(), &["raytrace", "--instrument", &p, "--filter", "V"], &["strips.toml", "strip"]);
}

#[test]
fn raytrace_unknown_filter() {
    let f = Fixture::new();
    refuses(f.dir.path(), &["raytrace", "--filter", "Z"], &["Z"]);
}

#[test]
fn raytrace_instrument_without_optics() {
    let f = Fixture::new();
    refuses(f.dir.path(), &["raytrace", "--instrument", &f.s("mini.toml"), "--filter", "V"], &["MINI", "optics"]);
}

// ---------------------------------------------------------------------------------------
// Frames: instpol calibrate FRAMES (the FITS reader and the frame-set checks)
// ---------------------------------------------------------------------------------------

fn calibrate_args<'a>(f: &'a Fixture, frames: &'a [String], out: &'a str) -> Vec<&'a str> {
    let mut a =
        vec!["calibrate", "--instrument", "", "--sky-p", "1.74", "--sky-chi", "-53.8", "--bin", "8", "--out", out];
    a[2] = Box::leak(f.s("mini.toml").into_boxed_str());
    a.extend(frames.iter().map(|s| s.as_str()));
    a
}

#[test]
fn frames_control_good_set_calibrates() {
    let f = Fixture::new();
    let frames = f.frames();
    let out = f.out_dir().join("cal.fits");
    let (code, _, err) = run(&calibrate_args(&f, &frames, out.to_str().unwrap()));
    assert_eq!(code, 0, "good frames must calibrate: {err}");
    assert!(out.is_file());
}

#[test]
fn frames_truncated_fits() {
    let f = Fixture::new();
    let mut frames = f.frames();
    let bytes = std::fs::read(&frames[2]).unwrap();
    std::fs::write(f.p("trunc.fits"), &bytes[..bytes.len() / 2]).unwrap();
    frames[2] = f.s("trunc.fits");
    let out = f.out_dir();
    refuses(&out, &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()), &["trunc.fits"]);
}

#[test]
fn frames_corrupt_fits() {
    let f = Fixture::new();
    let mut frames = f.frames();
    // A text file, and a FITS header with its END card destroyed.
    std::fs::write(f.p("text.fits"), "this is not FITS\n").unwrap();
    frames[1] = f.s("text.fits");
    let out = f.out_dir();
    refuses(&out, &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()), &["text.fits"]);
    let mut frames = f.frames();
    let mut bytes = std::fs::read(&frames[3]).unwrap();
    let end = bytes.windows(8).position(|w| w == b"END     ").unwrap();
    bytes[end..end + 3].copy_from_slice(b"XYZ");
    std::fs::write(f.p("noend.fits"), &bytes).unwrap();
    frames[3] = f.s("noend.fits");
    refuses(&out, &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()), &["noend.fits"]);
}

#[test]
fn frames_wrong_dimensions() {
    let f = Fixture::new();
    let mut frames = f.frames();
    let keys = vec![
        ("HIERARCH ESO INS RETA2 POSANG".to_string(), KeyValue::F64(45.0), String::new()),
        ("HIERARCH ESO INS FILT1 NAME".to_string(), KeyValue::Str("V".into()), String::new()),
    ];
    write_frame(&f.p("small.fits"), 64, 96, &vec![1000.0; 64 * 96], Bitpix::F32, &keys).unwrap();
    frames[2] = f.s("small.fits");
    let out = f.out_dir();
    refuses(&out, &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()), &["small.fits", "64"]);
}

#[test]
fn frames_all_nan_pixels() {
    let f = Fixture::new();
    let mut frames = f.frames();
    frames[0] = f.frame("nan.fits", 0.0, "V", |d| d.iter_mut().for_each(|x| *x = f64::NAN));
    let out = f.out_dir();
    refuses(&out, &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()), &["nan.fits"]);
}

/// By design: some NaN/inf pixels are masked with a warning naming the file.
#[test]
fn frames_some_nan_and_inf_pixels_are_masked_with_a_warning() {
    let f = Fixture::new();
    let mut frames = f.frames();
    frames[1] = f.frame("somenan.fits", 22.5, "V", |d| {
        d[40 * 96 + 10] = f64::NAN;
        d[41 * 96 + 11] = f64::INFINITY;
    });
    let out = f.out_dir().join("cal.fits");
    let (code, _, err) = run(&calibrate_args(&f, &frames, out.to_str().unwrap()));
    assert!(!err.contains("panicked"));
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("somenan.fits") && err.contains("2 NaN/infinite pixels masked"), "{err}");
}

/// By design: saturated pixels (a bright star) are masked with a warning naming the file.
#[test]
fn frames_saturated_star_is_masked_with_a_warning() {
    let f = Fixture::new();
    let mut frames = f.frames();
    frames[2] = f.frame("sat.fits", 45.0, "V", |d| {
        for y in 40..44 {
            for x in 40..44 {
                d[y * 96 + x] = 65000.0;
            }
        }
    });
    let out = f.out_dir().join("cal.fits");
    let (code, _, err) = run(&calibrate_args(&f, &frames, out.to_str().unwrap()));
    assert!(!err.contains("panicked"));
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("sat.fits") && err.contains("16 saturated pixels"), "{err}");
}

#[test]
fn frames_zero_and_negative_flux() {
    let f = Fixture::new();
    let mut frames = f.frames();
    frames[0] = f.frame("zero.fits", 0.0, "V", |d| d.iter_mut().for_each(|x| *x = 0.0));
    frames[1] = f.frame("neg.fits", 22.5, "V", |d| d.iter_mut().for_each(|x| *x = -100.0));
    let out = f.out_dir();
    refuses(&out, &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()), &["flux"]);
}

#[test]
fn frames_missing_hwp_angle_keyword() {
    let f = Fixture::new();
    let mut frames = f.frames();
    let keys = vec![("HIERARCH ESO INS FILT1 NAME".to_string(), KeyValue::Str("V".into()), String::new())];
    write_frame(&f.p("nokey.fits"), 96, 96, &vec![1000.0; 96 * 96], Bitpix::F32, &keys).unwrap();
    frames[3] = f.s("nokey.fits");
    let out = f.out_dir();
    refuses(
        &out,
        &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()),
        &["nokey.fits", "RETA2 POSANG"],
    );
}

#[test]
fn frames_missing_hwp_angles() {
    let f = Fixture::new();
    let mut frames = f.frames();
    frames.remove(2);
    let out = f.out_dir();
    refuses(&out, &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()), &["45"]);
}

/// By design: a second frame at the same HWP angle is summed with the first, with a warning.
#[test]
fn frames_duplicated_hwp_angle_is_summed_with_a_warning() {
    let f = Fixture::new();
    let mut frames = f.frames();
    frames.push(f.frame("again.fits", 45.0, "V", |_| {}));
    let out = f.out_dir().join("cal.fits");
    let (code, _, err) = run(&calibrate_args(&f, &frames, out.to_str().unwrap()));
    assert!(!err.contains("panicked"));
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("again.fits") && err.contains("second frame at HWP angle 45"), "{err}");
}

#[test]
fn frames_mixed_filters() {
    let f = Fixture::new();
    let inst = MINI.replace(
        "[[filters]]\nname = \"V\"",
        "[[filters]]\nname = \"B\"\nlambda_eff_nm = 429.0\n\n[[filters]]\nname = \"V\"",
    );
    std::fs::write(f.p("mini.toml"), inst).unwrap();
    let mut frames = f.frames();
    frames[3] = f.frame("b.fits", 67.5, "B", |_| {});
    let out = f.out_dir();
    refuses(&out, &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()), &["b.fits", "B", "V"]);
}

#[test]
fn frames_of_another_instrument() {
    // FORS1 frames are 2048 x 2048: given to the tiny instrument they are the wrong size; the
    // message must name the file and both sizes.
    let f = Fixture::new();
    let mut frames = f.frames();
    let keys = vec![
        ("HIERARCH ESO INS RETA2 POSANG".to_string(), KeyValue::F64(45.0), String::new()),
        ("HIERARCH ESO INS FILT1 NAME".to_string(), KeyValue::Str("V".into()), String::new()),
    ];
    write_frame(&f.p("fors.fits"), 2048, 2048, &vec![1000.0; 2048 * 2048], Bitpix::U16, &keys).unwrap();
    frames[2] = f.s("fors.fits");
    let out = f.out_dir();
    refuses(&out, &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()), &["fors.fits", "2048"]);
}

#[test]
fn calibrate_output_not_writable() {
    let f = Fixture::new();
    let frames = f.frames();
    // The parent of the output is a regular file (works even as root).
    std::fs::write(f.p("afile"), "x").unwrap();
    let out = f.p("afile").join("cal.fits");
    refuses(f.dir.path(), &calibrate_args(&f, &frames, out.to_str().unwrap()), &["afile", "Not a directory"]);
    let out = f.p("no_such_dir").join("cal.fits");
    refuses(f.dir.path(), &calibrate_args(&f, &frames, out.to_str().unwrap()), &["no_such_dir"]);
}

#[test]
fn calibrate_missing_sky_polarization() {
    let f = Fixture::new();
    let map = f.map("map.fits");
    let out = f.out_dir();
    let cal = out.join("cal.fits");
    refuses(&out, &["calibrate", "--map", &map, "--sky-p", "1.74", "--out", cal.to_str().unwrap()], &["sky-chi"]);
    refuses(
        &out,
        &["calibrate", "--map", &map, "--sky-p", "150", "--sky-chi", "0", "--out", cal.to_str().unwrap()],
        &["sky polarization", "150"],
    );
}

// ---------------------------------------------------------------------------------------
// Calibration files and instpol correct / fit / plot / wavelength-law
// ---------------------------------------------------------------------------------------

const GOOD_CAT: &str =
    "id,x,y,q,u,sigma_q,sigma_u\n1,0.5,0.5,0.01,0.002,0.0005,0.0005\n2,-1.0,2.0,0.0,0.001,0.0005,0.0005\n";

#[test]
fn correct_control_good_catalog() {
    let f = Fixture::new();
    let cal = f.cal();
    let cat = f.csv("cat.csv", GOOD_CAT);
    let out = f.out_dir().join("corr.csv");
    let (code, _, err) = run(&["correct", "--cal", &cal, "--in", &cat, "--out", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(out.is_file());
}

#[test]
fn correct_catalog_missing_column() {
    let f = Fixture::new();
    let cal = f.cal();
    let cat = f.csv("cat.csv", "id,x,y,q,u,sigma_q\n1,0.5,0.5,0.01,0.002,0.0005\n");
    let out = f.out_dir();
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &cat, "--out", out.join("c.csv").to_str().unwrap()],
        &["cat.csv", "sigma_u"],
    );
}

#[test]
fn correct_catalog_bad_values() {
    let f = Fixture::new();
    let cal = f.cal();
    let out = f.out_dir();
    let o = out.join("c.csv");
    let cat = f.csv("text.csv", &GOOD_CAT.replace("0.01,0.002", "abc,0.002"));
    refuses(&out, &["correct", "--cal", &cal, "--in", &cat, "--out", o.to_str().unwrap()], &["text.csv", "abc"]);
    let cat = f.csv("nan.csv", &GOOD_CAT.replace("0.01,0.002", "NaN,0.002"));
    refuses(&out, &["correct", "--cal", &cal, "--in", &cat, "--out", o.to_str().unwrap()], &["nan.csv"]);
    let cat = f.csv("negsig.csv", &GOOD_CAT.replace("0.002,0.0005,0.0005", "0.002,-0.0005,0.0005"));
    refuses(&out, &["correct", "--cal", &cal, "--in", &cat, "--out", o.to_str().unwrap()], &["negsig.csv", "sigma_q"]);
}

#[test]
fn correct_position_outside_calibrated_field() {
    let f = Fixture::new();
    let cal = f.cal();
    let cat = f.csv("far.csv", &GOOD_CAT.replace("-1.0,2.0", "-1.0,40.0"));
    let out = f.out_dir();
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &cat, "--out", out.join("c.csv").to_str().unwrap()],
        &["far.csv", "40"],
    );
}

#[test]
fn correct_calibration_not_fits_or_truncated() {
    let f = Fixture::new();
    let cal = f.cal();
    let cat = f.csv("cat.csv", GOOD_CAT);
    let out = f.out_dir();
    let o = out.join("c.csv");
    std::fs::write(f.p("text_cal.fits"), "SIMPLE = nonsense").unwrap();
    refuses(
        &out,
        &["correct", "--cal", &f.s("text_cal.fits"), "--in", &cat, "--out", o.to_str().unwrap()],
        &["text_cal.fits"],
    );
    let bytes = std::fs::read(&cal).unwrap();
    std::fs::write(f.p("trunc_cal.fits"), &bytes[..bytes.len() * 2 / 3]).unwrap();
    refuses(
        &out,
        &["correct", "--cal", &f.s("trunc_cal.fits"), "--in", &cat, "--out", o.to_str().unwrap()],
        &["trunc_cal.fits"],
    );
    // A frame is a FITS file but not a calibration.
    let frame = f.frame("frame.fits", 0.0, "V", |_| {});
    refuses(&out, &["correct", "--cal", &frame, "--in", &cat, "--out", o.to_str().unwrap()], &["frame.fits"]);
}

/// Overwrite the value of a header card (keyword text `key`) in a FITS file, keeping 80-char
/// cards; the value field is columns 11..30 (fixed format).
fn patch_card(path: &Path, key: &str, value: &str) {
    let mut b = std::fs::read(path).unwrap();
    let pos = b.windows(key.len()).position(|w| w == key.as_bytes()).unwrap_or_else(|| panic!("no card {key}"));
    let card = pos - pos % 80;
    let eq = card + b[card..card + 80].iter().position(|&c| c == b'=').unwrap();
    let mut field = format!(" {value}");
    while field.len() < 80 - (eq + 1 - card) {
        field.push(' ');
    }
    // Keep the comment out: a plain value to the end of the card.
    b[eq + 1..card + 80].copy_from_slice(&field.as_bytes()[..card + 80 - eq - 1]);
    std::fs::write(path, b).unwrap();
}

#[test]
fn correct_calibration_of_newer_format_version() {
    let f = Fixture::new();
    let cal = f.cal();
    patch_card(Path::new(&cal), "FORMAT VERSION", "99");
    let cat = f.csv("cat.csv", GOOD_CAT);
    let out = f.out_dir();
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &cat, "--out", out.join("c.csv").to_str().unwrap()],
        &["cal.fits", "99"],
    );
    patch_card(Path::new(&cal), "FORMAT VERSION", "0");
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &cat, "--out", out.join("c.csv").to_str().unwrap()],
        &["cal.fits", "version"],
    );
}

/// Regression (was a defect, fixed in 2e448c5): `correct` applied a FORS1 calibration to a Stokes map written for another
/// instrument (MAP instrument "OTHER") silently, exit 0. Fix (crates/cli/src/cmd/correct.rs,
/// map path): compare the map's instrument and filter with the calibration's (filter names
/// through the instrument's aliases) and refuse with both names unless forced.
#[test]
fn correct_map_of_another_instrument() {
    // A Stokes map of instrument OTHER corrected with a FORS1 calibration.
    let f = Fixture::new();
    let cal = f.cal();
    let geom = skyfield::BinGeometry::covering(60, 0, 0, 2048, 2048, 0.2);
    let mut map = skyfield::StokesMap::empty(geom.clone(), "OTHER", "V", vec![0.0, 22.5, 45.0, 67.5]);
    map.valid[0] = true;
    (map.q[0], map.u[0], map.p[0], map.chi[0], map.cov_qu[0]) = (0.01, 0.0, 0.01, 0.0, 0.0);
    map.sigma_q[0] = 1e-3;
    map.sigma_u[0] = 1e-3;
    map.n_pixels[0] = 10;
    (map.sigma_q_phot[0], map.sigma_u_phot[0], map.intensity[0], map.intensity_snr[0]) = (1e-3, 1e-3, 1e4, 100.0);
    map.write_fits(&f.p("other.fits")).unwrap();
    let out = f.out_dir();
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &f.s("other.fits"), "--out", out.join("c.fits").to_str().unwrap()],
        &["OTHER", "FORS1"],
    );
}

/// Regression (fixed in 2e448c5): likewise a B-band map corrected with a V calibration gave
/// exit 0 and no warning.
#[test]
fn correct_map_of_another_filter() {
    let f = Fixture::new();
    let cal = f.cal();
    let geom = skyfield::BinGeometry::covering(60, 0, 0, 2048, 2048, 0.2);
    let mut map = skyfield::StokesMap::empty(geom.clone(), "FORS1", "B", vec![0.0, 22.5, 45.0, 67.5]);
    map.valid[0] = true;
    (map.q[0], map.u[0], map.p[0], map.chi[0], map.cov_qu[0]) = (0.01, 0.0, 0.01, 0.0, 0.0);
    map.sigma_q[0] = 1e-3;
    map.sigma_u[0] = 1e-3;
    map.n_pixels[0] = 10;
    (map.sigma_q_phot[0], map.sigma_u_phot[0], map.intensity[0], map.intensity_snr[0]) = (1e-3, 1e-3, 1e4, 100.0);
    map.write_fits(&f.p("bmap.fits")).unwrap();
    let out = f.out_dir();
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &f.s("bmap.fits"), "--out", out.join("c.fits").to_str().unwrap()],
        &["B", "V"],
    );
}

#[test]
fn correct_output_not_writable() {
    let f = Fixture::new();
    let cal = f.cal();
    let cat = f.csv("cat.csv", GOOD_CAT);
    std::fs::write(f.p("afile"), "x").unwrap();
    let o = f.p("afile").join("c.csv");
    refuses(
        f.dir.path(),
        &["correct", "--cal", &cal, "--in", &cat, "--out", o.to_str().unwrap()],
        &["afile", "Not a directory"],
    );
}

#[test]
fn correct_unknown_estimator() {
    let f = Fixture::new();
    let cal = f.cal();
    let cat = f.csv("cat.csv", GOOD_CAT);
    let out = f.out_dir();
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &cat, "--out", out.join("c.csv").to_str().unwrap(), "--estimator", "mle"],
        &["mle"],
    );
}

#[test]
fn fit_plot_wavelength_law_on_a_corrupt_calibration() {
    let f = Fixture::new();
    std::fs::write(f.p("bad_cal.fits"), vec![b'A'; 2880]).unwrap();
    let out = f.out_dir();
    refuses(&out, &["fit", &f.s("bad_cal.fits"), "--out", out.join("refit.fits").to_str().unwrap()], &["bad_cal.fits"]);
    refuses(&out, &["plot", &f.s("bad_cal.fits"), "--out", out.join("plots").to_str().unwrap()], &["bad_cal.fits"]);
    refuses(&out, &["wavelength-law", &f.s("bad_cal.fits"), &f.s("bad_cal.fits")], &["bad_cal.fits"]);
}

/// Regression (fixed in 7bb1761): the message was "degenerate fit: all calibrations are at the same
/// wavelength", naming neither the files nor the filter; it should say e.g. "cal.fits and
/// cal.fits are both filter V (554 nm): the wavelength law needs two filters".
#[test]
fn wavelength_law_needs_two_filters() {
    let f = Fixture::new();
    let cal = f.cal();
    let out = f.out_dir();
    refuses(&out, &["wavelength-law", &cal, &cal], &["V"]);
}

// ---------------------------------------------------------------------------------------
// import-map
// ---------------------------------------------------------------------------------------

fn write_image(path: &Path, nx: usize, ny: usize, v: f64) {
    // The (2, NY, NX) cube of import-map: plane 1 the value, plane 2 its error.
    let d = fitsio::images::ImageDescription { data_type: fitsio::images::ImageType::Double, dimensions: &[2, ny, nx] };
    let mut f = fitsio::FitsFile::create(path).with_custom_primary(&d).open().unwrap();
    let h = f.primary_hdu().unwrap();
    let mut data = vec![v; nx * ny];
    data.extend(vec![1e-4; nx * ny]);
    h.write_image(&mut f, &data).unwrap();
}

#[test]
fn import_map_mismatched_and_bad_images() {
    let f = Fixture::new();
    write_image(&f.p("q.fits"), 20, 20, 0.001);
    write_image(&f.p("u.fits"), 20, 18, 0.001);
    write_image(&f.p("unan.fits"), 20, 20, f64::NAN);
    let out = f.out_dir();
    let o = out.join("cal.fits");
    let base = |u: &str| {
        vec![
            "import-map".to_string(),
            "--q".into(),
            f.s("q.fits"),
            "--u".into(),
            f.s(u),
            "--pixel-scale".into(),
            "0.25".into(),
            "--bin".into(),
            "50".into(),
            "--filter".into(),
            "V".into(),
            "--lambda-nm".into(),
            "554".into(),
            "--out".into(),
            o.to_str().unwrap().to_string(),
        ]
    };
    let a = base("u.fits");
    refuses(&out, &a.iter().map(|s| s.as_str()).collect::<Vec<_>>(), &["u.fits", "18"]);
    let a = base("unan.fits");
    refuses(&out, &a.iter().map(|s| s.as_str()).collect::<Vec<_>>(), &["unan.fits"]);
    let a = base("missing.fits");
    refuses(&out, &a.iter().map(|s| s.as_str()).collect::<Vec<_>>(), &["missing.fits"]);
}

// ---------------------------------------------------------------------------------------
// Numbers on the command line
// ---------------------------------------------------------------------------------------

/// Regression (fixed in 447c778): `--n-real -1.5` was taken by clap as an unknown flag `-1` ("unexpected
/// argument '-1' found") instead of the number; `allow_negative_numbers = true` on the
/// fresnel number arguments (as `instpol stokes --kappa` has) would let the range check speak.
#[test]
fn fresnel_negative_number_is_read_as_a_flag() {
    let f = Fixture::new();
    refuses(f.dir.path(), &["fresnel", "--n-real", "-1.5", "--aoi-deg", "10"], &["-1.5"]);
}

#[test]
fn fresnel_bad_numbers() {
    let f = Fixture::new();
    refuses(f.dir.path(), &["fresnel", "--n-real=-1.5", "--aoi-deg", "10"], &["-1.5"]);
    refuses(f.dir.path(), &["fresnel", "--n-real", "1.5", "--aoi-deg", "95"], &["95"]);
    refuses(f.dir.path(), &["fresnel", "--n-real", "NaN", "--aoi-deg", "10"], &["NaN"]);
}

// ---------------------------------------------------------------------------------------
// Atomic writes: a run killed mid-write leaves no partial final file.
// ---------------------------------------------------------------------------------------

/// `instpol correct` of a large catalog, killed with SIGKILL at several moments: the output
/// name either does not exist or holds the complete file (every row), never a partial one.
#[test]
fn killed_correct_leaves_no_partial_output() {
    let f = Fixture::new();
    let cal = f.cal();
    let mut text = String::from("id,x,y,q,u,sigma_q,sigma_u\n");
    let n = 300_000;
    for i in 0..n {
        let x = -2.5 + 5.0 * ((i * 7919) % 1000) as f64 / 1000.0;
        let y = -2.5 + 5.0 * ((i * 104729) % 1000) as f64 / 1000.0;
        text.push_str(&format!("{i},{x:.4},{y:.4},0.01,0.002,0.0005,0.0005\n"));
    }
    let cat = f.csv("big.csv", &text);
    let out = f.out_dir();
    let o = out.join("corr.csv");
    let mut complete_seen = false;
    for delay_ms in [50u64, 200, 500, 1000, 2000, 4000] {
        let _ = std::fs::remove_file(&o);
        let mut child = Command::new(bin())
            .args(["correct", "--cal", &cal, "--in", &cat, "--out", o.to_str().unwrap(), "--estimator", "naive"])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(std::time::Duration::from_millis(delay_ms));
        let _ = child.kill();
        let status = child.wait().unwrap();
        if o.exists() {
            let body = std::fs::read_to_string(&o).unwrap();
            assert_eq!(body.lines().count(), n + 1, "partial output after kill at {delay_ms} ms ({status:?})");
            complete_seen = true;
        }
        // Only tempfile-style hidden temporaries may remain after SIGKILL.
        for name in listing(&out) {
            assert!(name == "corr.csv" || name.starts_with('.'), "stray file {name} after kill at {delay_ms} ms");
        }
    }
    let _ = complete_seen;
}

/// Regression (was a defect of fit::calfile + fitsio 0.21.10, fixed in 7bb1761): a calibration file whose INPUTS table has a string
/// column 24 (or 40, 56, ... : 8 mod 16) characters wide crashes every reader with heap
/// corruption (`free(): invalid pointer`, SIGABRT, exit 134). fitsio's
/// `read_col::<String>` allocates `width` bytes per row but CFITSIO's `ffgcvs` writes
/// `width + 1` (the terminating NUL); glibc has no slack in chunks of 8 mod 16 usable bytes.
/// Any input path of that length (e.g. `/tmp/.tmpXXXXXX/map.fits`, 24 chars) triggers it.
/// Fix in `Calibration::load` (crates/fit/src/calfile.rs): read the FILE column with buffers
/// of `width + 1` bytes via `fitsio::sys::ffgcvs` (or store the inputs as header cards),
/// never with `read_col::<String>`.
#[test]
fn calibration_whose_input_name_is_24_chars_is_readable() {
    let f = Fixture::new();
    let map = f.map("map.fits");
    // A folder whose map path is exactly 24 (or 40, ...) bytes long.
    let mut d = String::from("/tmp/ip");
    while (d.len() + "/m.fits".len()) % 16 != 8 {
        d.push('x');
    }
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    let m = format!("{d}/m.fits");
    std::fs::copy(&map, &m).unwrap();
    let cal = f.s("cal24.fits");
    let (code, _, err) = run(&["calibrate", "--map", &m, "--sky-p", "1.74", "--sky-chi", "-53.8", "--out", &cal]);
    let _ = std::fs::remove_dir_all(&d);
    assert_eq!(code, 0, "{err}");
    let cat = f.csv("cat.csv", GOOD_CAT);
    let out = f.out_dir().join("c.csv");
    let (code, _, err) = run(&["correct", "--cal", &cal, "--in", &cat, "--out", out.to_str().unwrap()]);
    assert_eq!(code, 0, "correct on a calibration with a {}-char input name: exit {code}, {err}", m.len());
}

// ---------------------------------------------------------------------------------------
// instpol simulate: scene files; instpol reduce: frames
// ---------------------------------------------------------------------------------------

fn scene_v() -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/scenes/empty_V.toml"))
        .unwrap()
}

#[test]
fn scene_unknown_and_mistyped_keys() {
    let f = Fixture::new();
    let out = f.out_dir();
    let o = out.join("sim");
    let p = f.csv("typo.toml", &scene_v().replace("brightness_e", "brightnes_e"));
    refuses(&out, &["simulate", &p, "--out", o.to_str().unwrap()], &["typo.toml", "brightnes_e"]);
    let p = f.csv("extra.toml", &scene_v().replace("[sky]", "[sky]\ncolour = 3"));
    refuses(&out, &["simulate", &p, "--out", o.to_str().unwrap()], &["extra.toml", "colour"]);
    let p = f.csv("type.toml", &scene_v().replace("seed = 102", "seed = \"abc\""));
    refuses(&out, &["simulate", &p, "--out", o.to_str().unwrap()], &["type.toml", "seed"]);
}

#[test]
fn scene_bad_values() {
    let f = Fixture::new();
    let out = f.out_dir();
    let o = out.join("sim");
    let p = f.csv("pbig.toml", &scene_v().replace("p = 0.0174", "p = 1.5"));
    refuses(&out, &["simulate", &p, "--out", o.to_str().unwrap()], &["pbig.toml", "1.5"]);
    let p = f.csv("dup.toml", &scene_v().replace("[0, 22.5, 45, 67.5]", "[0, 22.5, 22.5, 67.5]"));
    refuses(&out, &["simulate", &p, "--out", o.to_str().unwrap()], &["dup.toml", "22.5"]);
    let p = f.csv("filt.toml", &scene_v().replace("filter = \"V\"", "filter = \"Q\""));
    refuses(&out, &["simulate", &p, "--out", o.to_str().unwrap()], &["filter 'Q'", "FORS1"]);
    let p = f.csv("inst.toml", &scene_v().replace("instrument = \"fors1\"", "instrument = \"fors7\""));
    refuses(&out, &["simulate", &p, "--out", o.to_str().unwrap()], &["fors7"]);
    let p = f.csv("nan.toml", &scene_v().replace("brightness_e = 12000", "brightness_e = nan"));
    refuses(&out, &["simulate", &p, "--out", o.to_str().unwrap()], &["nan.toml", "brightness_e"]);
}

#[test]
fn simulate_output_not_writable() {
    let f = Fixture::new();
    std::fs::write(f.p("afile"), "x").unwrap();
    let p = f.csv("v.toml", &scene_v());
    refuses(f.dir.path(), &["simulate", &p, "--out", f.p("afile").join("sim").to_str().unwrap()], &["afile"]);
}

#[test]
fn reduce_truncated_frame_and_unwritable_output() {
    let f = Fixture::new();
    let mut frames = f.frames();
    let ins = f.s("mini.toml");
    std::fs::write(f.p("afile"), "x").unwrap();
    let bad_out = f.p("afile").join("map.fits");
    let mut a = vec!["reduce", "--instrument", ins.as_str(), "--bin", "8", "--out", bad_out.to_str().unwrap()];
    a.extend(frames.iter().map(|s| s.as_str()));
    refuses(f.dir.path(), &a, &["afile"]);
    let bytes = std::fs::read(&frames[0]).unwrap();
    std::fs::write(f.p("trunc.fits"), &bytes[..bytes.len() - 1000]).unwrap();
    frames[0] = f.s("trunc.fits");
    let out = f.out_dir();
    let o = out.join("map.fits");
    let mut a = vec!["reduce", "--instrument", ins.as_str(), "--bin", "8", "--out", o.to_str().unwrap()];
    a.extend(frames.iter().map(|s| s.as_str()));
    refuses(&out, &a, &["trunc.fits"]);
}

/// `instpol simulate` of the FORS1 V scene (four 2048 x 2048 frames, ~2 s) killed with SIGKILL
/// at several moments: every frame file present under its final name is complete (the size of
/// the frame of a full run); only dot-named temporaries may remain.
#[test]
fn killed_simulate_leaves_no_partial_frame() {
    let f = Fixture::new();
    let p = f.csv("v.toml", &scene_v());
    let full = f.p("full");
    let (code, _, err) = run(&["simulate", &p, "--out", full.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let sizes: std::collections::BTreeMap<String, u64> =
        listing(&full).into_iter().map(|n| (n.clone(), std::fs::metadata(full.join(&n)).unwrap().len())).collect();
    for delay_ms in [150u64, 400, 700, 1000, 1400] {
        let out = f.p(&format!("k{delay_ms}"));
        let mut child = Command::new(bin())
            .args(["simulate", &p, "--out", out.to_str().unwrap()])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(std::time::Duration::from_millis(delay_ms));
        let _ = child.kill();
        let _ = child.wait();
        if !out.exists() {
            continue;
        }
        for name in listing(&out) {
            if name.starts_with('.') {
                continue;
            }
            let len = std::fs::metadata(out.join(&name)).unwrap().len();
            assert_eq!(Some(&len), sizes.get(&name), "partial or unexpected file {name} after kill at {delay_ms} ms");
        }
    }
}

// ---------------------------------------------------------------------------------------
// instpol photometry and validate (a variant of the tiny instrument with 20 px strips, so
// that an aperture and its annulus fit inside the ordinary image of strip 0: rows 4..24)
// ---------------------------------------------------------------------------------------

/// Four frames with a star at (48, 14) in the ordinary image and one 20 px throw above in the
/// extraordinary image (the mini2 geometry), on the flat sky of [`Fixture::frame`].
fn star_frames(f: &Fixture) -> Vec<String> {
    [0.0, 22.5, 45.0, 67.5]
        .iter()
        .enumerate()
        .map(|(i, &a)| {
            f.frame(&format!("s{i}.fits"), a, "V", |d| {
                for y in 0..96usize {
                    for x in 0..96usize {
                        let g = |yc: f64| {
                            let r2 = (x as f64 - 48.0).powi(2) + (y as f64 - yc).powi(2);
                            20000.0 * (-r2 / 4.5).exp()
                        };
                        d[y * 96 + x] += g(14.0) + g(34.0);
                    }
                }
            })
        })
        .collect()
}

#[test]
fn photometry_control_and_bad_geometry() {
    let f = Fixture::new();
    let frames = star_frames(&f);
    let ins = f.csv(
        "mini2.toml",
        &MINI.replace("throw_arcsec = 32.0", "throw_arcsec = 80.0").replace("strip_count = 5", "strip_count = 2"),
    );
    let base = |x: &str, extra: &[&str]| {
        let mut a: Vec<String> = vec![
            "photometry".into(),
            "--instrument".into(),
            ins.clone(),
            "--x".into(),
            x.into(),
            "--y".into(),
            "14".into(),
        ];
        a.extend(extra.iter().map(|s| s.to_string()));
        a.extend(frames.iter().cloned());
        a
    };
    let a = base("48", &["--aperture", "3", "--annulus", "4,6"]);
    let (code, _, err) = run(&a.iter().map(|s| s.as_str()).collect::<Vec<_>>());
    assert_eq!(code, 0, "control: {err}");
    let a = base("5000", &["--aperture", "3", "--annulus", "4,6"]);
    refuses(f.dir.path(), &a.iter().map(|s| s.as_str()).collect::<Vec<_>>(), &["5000"]);
    let a = base("48", &["--aperture=-3", "--annulus", "4,6"]);
    refuses(f.dir.path(), &a.iter().map(|s| s.as_str()).collect::<Vec<_>>(), &["aperture"]);
    let a = base("48", &["--aperture", "3", "--annulus", "6,4"]);
    refuses(f.dir.path(), &a.iter().map(|s| s.as_str()).collect::<Vec<_>>(), &["annulus"]);
}

#[test]
fn validate_bad_standards_file_and_unknown_star() {
    let f = Fixture::new();
    let cal = f.cal();
    let frames = star_frames(&f);
    let ins = f.csv(
        "mini2.toml",
        &MINI.replace("throw_arcsec = 32.0", "throw_arcsec = 80.0").replace("strip_count = 5", "strip_count = 2"),
    );
    let std_text =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/standards.toml"))
            .unwrap();
    let typo = f.csv("typo_std.toml", &std_text.replacen("sigma_p_percent", "sigma_p_percnt", 1));
    let base = |extra: &[&str]| {
        let mut a: Vec<String> = vec![
            "validate".into(),
            "--cal".into(),
            cal.clone(),
            "--instrument".into(),
            ins.clone(),
            "--x".into(),
            "48".into(),
            "--y".into(),
            "14".into(),
            "--aperture".into(),
            "3".into(),
            "--annulus".into(),
            "4,6".into(),
        ];
        a.extend(extra.iter().map(|s| s.to_string()));
        a.extend(frames.iter().cloned());
        a
    };
    let a = base(&["--standards", &typo, "--star", "HD 14069"]);
    refuses(f.dir.path(), &a.iter().map(|s| s.as_str()).collect::<Vec<_>>(), &["typo_std.toml", "sigma_p_percnt"]);
    let a = base(&["--star", "HD 99999"]);
    refuses(f.dir.path(), &a.iter().map(|s| s.as_str()).collect::<Vec<_>>(), &["HD 99999"]);
}

/// Regression (was a defect, fixed in e568d20): frames of the tiny instrument MINI validated with a FORS1 calibration pass (exit 0,
/// "star unpolarized in V ..."): the calibration's instrument is never compared with the
/// frames' (`--instrument`). Fix (crates/cli/src/cmd/validate.rs): refuse when
/// `cal.instrument` differs from the instrument's name (case-insensitive), naming both.
/// (Also noted, not tested: `--standards FILE` is not even read unless `--star` is given, so a
/// broken standards file passes silently.)
#[test]
fn validate_calibration_of_another_instrument() {
    let f = Fixture::new();
    let cal = f.cal();
    let frames = star_frames(&f);
    let ins = f.csv(
        "mini2.toml",
        &MINI.replace("throw_arcsec = 32.0", "throw_arcsec = 80.0").replace("strip_count = 5", "strip_count = 2"),
    );
    let mut a: Vec<String> = vec![
        "validate".into(),
        "--cal".into(),
        cal.clone(),
        "--instrument".into(),
        ins.clone(),
        "--x".into(),
        "48".into(),
        "--y".into(),
        "14".into(),
        "--aperture".into(),
        "3".into(),
        "--annulus".into(),
        "4,6".into(),
    ];
    a.extend(frames.iter().cloned());
    refuses(f.dir.path(), &a.iter().map(|s| s.as_str()).collect::<Vec<_>>(), &["MINI", "FORS1"]);
}

/// Was a defect (found by fuzz/run.sh, fuzz_calibration_file; fixed in 2e5086f): a calibration whose UMAP
/// header claims NAXIS2 = 99999999999 aborts `instpol correct` with "memory allocation of
/// 55199999999448 bytes failed" (SIGABRT, no `error:` line): `fit::Calibration::load` reads the
/// image with the size its header claims. Fix (crates/fit/src/calfile.rs, `load`): check each
/// map's NAXIS1 x NAXIS2 against the grid of the primary header (and the bytes left in the
/// file) before `read_image`, and refuse naming the extension.
#[test]
fn calibration_with_absurd_image_size_is_refused() {
    let f = Fixture::new();
    let cal = f.cal();
    let mut b = std::fs::read(&cal).unwrap();
    let ext = b.windows(14).position(|w| w == b"EXTNAME = 'UMA").expect("UMAP extension");
    let start = ext - ext % 2880;
    let naxis2 = start + b[start..ext].windows(8).position(|w| w == b"NAXIS2  ").expect("NAXIS2 of UMAP");
    b[naxis2 + 10..naxis2 + 30].copy_from_slice(format!("{:>20}", 99_999_999_999u64).as_bytes());
    std::fs::write(&cal, &b).unwrap();
    let cat = f.csv("cat.csv", GOOD_CAT);
    let out = f.out_dir();
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &cat, "--out", out.join("c.csv").to_str().unwrap()],
        &["cal.fits", "UMAP"],
    );
}

/// Was a defect (fixed in 2e5086f; same class, fit::import): a Q cube for `import-map` whose header claims NAXIS2 =
/// 99999999999 (the file holds 2 x 20 x 20) aborts with "memory allocation of 31999999999680
/// bytes failed". Fix (crates/fit/src/import.rs): check the claimed size against the file's
/// length (NAXIS1 x NAXIS2 x NAXIS3 x |BITPIX|/8 <= bytes after the header) before reading.
#[test]
fn import_map_with_absurd_image_size_is_refused() {
    let f = Fixture::new();
    write_image(&f.p("q.fits"), 20, 20, 0.001);
    write_image(&f.p("u.fits"), 20, 20, 0.001);
    let mut b = std::fs::read(f.p("q.fits")).unwrap();
    let naxis2 = b.windows(8).position(|w| w == b"NAXIS2  ").unwrap();
    b[naxis2 + 10..naxis2 + 30].copy_from_slice(format!("{:>20}", 99_999_999_999u64).as_bytes());
    std::fs::write(f.p("q.fits"), &b).unwrap();
    let out = f.out_dir();
    let o = out.join("cal.fits");
    let (q, u) = (f.s("q.fits"), f.s("u.fits"));
    refuses(
        &out,
        &[
            "import-map",
            "--q",
            &q,
            "--u",
            &u,
            "--pixel-scale",
            "0.25",
            "--bin",
            "50",
            "--filter",
            "V",
            "--lambda-nm",
            "554",
            "--out",
            o.to_str().unwrap(),
        ],
        &["q.fits"],
    );
}

/// A frame whose header claims NAXIS2 = 99999999999 is refused by the detector-size check
/// before any pixel is read (no huge allocation).
#[test]
fn frame_with_absurd_image_size_is_refused() {
    let f = Fixture::new();
    let mut frames = f.frames();
    let mut b = std::fs::read(&frames[1]).unwrap();
    let naxis2 = b.windows(8).position(|w| w == b"NAXIS2  ").unwrap();
    b[naxis2 + 10..naxis2 + 30].copy_from_slice(format!("{:>20}", 99_999_999_999u64).as_bytes());
    std::fs::write(f.p("huge.fits"), &b).unwrap();
    frames[1] = f.s("huge.fits");
    let out = f.out_dir();
    refuses(&out, &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()), &["huge.fits", "99999999999"]);
}
