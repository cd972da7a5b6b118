//! The bad-input catalogue (docs/guide/bad-input.md): every bad input tried on the `instpol`
//! binary and what it must do. Each row of the table is one test here. A bad input must give
//! exit code 2, an `error: ...` message that names the input (file, key, row, HWP angle), no
//! panic, and no output file (nor a leftover temporary) in the output folder. Inputs that are
//! handled by design (duplicated HWP angles summed, NaN and saturated pixels masked) must say
//! so in a warning naming the file and still produce a result.
//!
//! A control test runs each command on the good version of the input first, so that an
//! error below is caused by the one thing that was broken.

use crate::common;

use common::{bin, listing, run};
use skyfield::fits::{write_frame, Bitpix, KeyValue};
use std::path::{Path, PathBuf};
use std::process::Command;

/// Run `args`, expect a clean refusal: exit 2, `error:` naming each of `names`, no panic, and
/// the folder `dir` unchanged (no output, no temporary left behind).
#[track_caller]
fn refuses<S: AsRef<std::ffi::OsStr> + std::fmt::Debug>(dir: &Path, args: &[S], names: &[&str]) -> String {
    let before = listing(dir);
    let (code, out, err) = run(args);
    if let Ok(log) = std::env::var("BAD_INPUTS_LOG") {
        use std::io::Write;
        let mut f = std::fs::OpenOptions::new().create(true).append(true).open(log).unwrap();
        let first = err.lines().find(|l| l.starts_with("error: ")).unwrap_or("").replace('|', "\\|");
        writeln!(f, "{} | {code} | {first}", std::thread::current().name().unwrap_or("?")).unwrap();
    }
    assert!(!err.contains("panicked"), "panic on {args:?}: {err}");
    assert_eq!(code, 2, "exit code for {args:?}: stdout {out} stderr {err}");
    // Warnings (naming masked pixels, say) may come first; the error is the last message:
    // `error: ...`, or under --json the JSON error object (schemas/error.schema.json).
    let json_msg = err.lines().last().and_then(|l| serde_json::from_str::<serde_json::Value>(l).ok()).map(|v| {
        assert_eq!(v["error"]["exit_code"], 2, "{err}");
        v["error"]["message"].as_str().unwrap_or_else(|| panic!("no message in {err}")).to_string()
    });
    let msg = match (json_msg, err.lines().position(|l| l.starts_with("error: "))) {
        (Some(m), _) => m,
        (None, Some(start)) => err.lines().skip(start).collect::<Vec<_>>().join("\n"),
        (None, None) => panic!("no 'error:' line for {args:?}: {err}"),
    };
    for n in names {
        assert!(msg.contains(n), "message for {args:?} does not name '{n}': {err}");
    }
    assert_eq!(listing(dir), before, "files left behind by {args:?}");
    err
}

// ---------------------------------------------------------------------------------------
// Inputs: a tiny instrument (96 x 96 px, 4"/px), frames, Stokes maps, a calibration file.
// ---------------------------------------------------------------------------------------

/// The tiny instrument's file (`common::MINI`).
fn mini() -> String {
    common::MINI.toml()
}

struct Fixture {
    dir: tempfile::TempDir,
}

impl Fixture {
    fn new() -> Self {
        let f = Fixture { dir: tempfile::tempdir().unwrap() };
        std::fs::write(f.p("mini.toml"), mini()).unwrap();
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
    /// angle `hwp` through an ideal prism, written to `name`; the masked strips dark, as the
    /// mask makes them. `edit` may change the pixels.
    fn frame(&self, name: &str, hwp: f64, filter: &str, edit: impl Fn(&mut Vec<f64>)) -> String {
        self.frame_of(&mini(), name, hwp, filter, edit)
    }

    /// [`Fixture::frame`] with the beams laid out by the instrument file `toml`.
    fn frame_of(&self, toml: &str, name: &str, hwp: f64, filter: &str, edit: impl Fn(&mut Vec<f64>)) -> String {
        let inst = instrument::Instrument::from_toml_str(toml, Path::new("mini.toml")).unwrap();
        let (nx, ny) = (inst.detector.nx, inst.detector.ny);
        let m = 0.02 * (4.0 * hwp.to_radians() - 2.0 * 30f64.to_radians()).cos();
        let mut data = vec![0.0; nx * ny];
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
        let path = self.p(&name);
        common::write_v_sky_map(&path, |_| true);
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

/// An ECSV whose `hwp_deg` column declares radians is read in degrees from its unit (the
/// numbers of the degree CSV); `--angles-in-radians` beside it is refused, naming the column:
/// it converted the angles a second time (0, 22.5, ... deg became 0, 1289, ... deg) with exit 0.
#[test]
fn stokes_angles_declared_in_radians_are_converted_once() {
    let f = Fixture::new();
    let mut e = String::from("# %ECSV 1.0\n# ---\n# datatype:\n# - {name: hwp_deg, unit: rad, datatype: float64}\n");
    e += "# - {name: f_o, datatype: float64}\n# - {name: f_e, datatype: float64}\n# schema: astropy-2.0\nhwp_deg f_o f_e\n";
    for line in GOOD_STOKES.lines().skip(1) {
        let v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        e += &format!("{:.17} {} {}\n", v[0].to_radians(), v[1], v[2]);
    }
    let rad = f.csv("rad.ecsv", &e);
    let good = f.csv("good.csv", GOOD_STOKES);
    let p = |path: &str| -> f64 {
        let (code, out, err) = run(&["stokes", "--input", path, "--json"]);
        assert_eq!(code, 0, "{err}");
        serde_json::from_str::<serde_json::Value>(&out).unwrap()["p"].as_f64().unwrap()
    };
    assert!((p(&rad) - p(&good)).abs() < 1e-12);
    let (code, _, err) = run(&["stokes", "--input", &rad, "--angles-in-radians"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("hwp_deg") && err.contains("rad") && err.contains("--angles-in-radians"), "{err}");
}

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

/// A repeated HWP angle is by design a repeated exposure: combined with a note (the 45 deg
/// row relabelled 22.5 leaves 0, 22.5 and 67.5: a complete-enough set), never silently.
#[test]
fn stokes_csv_duplicated_hwp_angle() {
    let f = Fixture::new();
    let p = f.csv("dup.csv", &GOOD_STOKES.replace("\n45,", "\n22.5,"));
    let (code, _, err) = run(&["stokes", "--input", &p]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("dup.csv") && err.contains("combined into 3 HWP positions"), "{err}");
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
    let p = f.csv("typo.toml", &mini().replace("pixel_scale_arcsec", "pixel_scal_arcsec"));
    let out = f.out_dir();
    let err = refuses(&out, &["raytrace", "--instrument", &p, "--filter", "V"], &["typo.toml", "pixel_scal_arcsec"]);
    let _ = err;
    let p2 = f.csv("extra.toml", &mini().replace("[field]", "[field]\ncolour = \"red\""));
    refuses(&out, &["raytrace", "--instrument", &p2, "--filter", "V"], &["extra.toml", "colour"]);
}

/// A quarter-wave plate's mistakes: plate angles that do not determine V (0, 90 deg), a
/// half-wave plate's zero angle in a quarter-wave instrument, a star more than fully polarized.
#[test]
fn quarter_wave_plate_mistakes_are_named() {
    let f = Fixture::new();
    let qwp = include_str!("../../../../instruments/calcite_qwp.toml");
    let inst = f.csv("qwp.toml", qwp);
    let out = f.out_dir();
    let scene = |name: &str, angles: &str, v: f64| {
        f.csv(
            name,
            &format!(
                "instrument = {inst:?}\nfilter = \"V\"\nhwp_angles_deg = {angles}\n[[stars]]\nx = 200\ny = 300\n\
                 coords = \"pixel\"\nflux_e = 1e6\nv = {v}\nfwhm_arcsec = 0.9\n"
            ),
        )
    };
    let s = scene("angles.toml", "[0, 90]", 0.01);
    refuses(
        &out,
        &["simulate", &s, "--out", &f.s("out/frames")],
        &["hwp_angles_deg", "[0, 90] deg do not determine V"],
    );
    let s = scene("bright.toml", "[-45, 45]", 1.2);
    refuses(&out, &["simulate", &s, "--out", &f.s("out/frames")], &["stars[0].v", "p^2 + v^2 <= 1"]);
    let bad = f.csv("hwpzero.toml", &qwp.replacen("qwp_zero_angle_deg = 0.0", "hwp_chi_offset_deg = 1.0", 1));
    refuses(
        &out,
        &["raytrace", "--instrument", &bad, "--filter", "V"],
        &["hwpzero.toml", "filters.V.hwp_chi_offset_deg"],
    );
}

#[test]
fn instrument_wrong_type_and_missing_key() {
    let f = Fixture::new();
    let p = f.csv("type.toml", &mini().replace("nx = 96", "nx = \"ninety-six\""));
    refuses(f.dir.path(), &["raytrace", "--instrument", &p, "--filter", "V"], &["type.toml", "nx"]);
    let p = f.csv("missing.toml", &mini().replace("gain_e_per_adu = 1.0\n", ""));
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
    let p = f.csv("neg.toml", &mini().replace("pixel_scale_arcsec = 4.0", "pixel_scale_arcsec = -4.0"));
    refuses(f.dir.path(), &["raytrace", "--instrument", &p, "--filter", "V"], &["neg.toml", "pixel_scale_arcsec"]);
    let p = f.csv("strips.toml", &mini().replace("strip_count = 5", "strip_count = 50"));
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
    // Both frames named, with the likely cause.
    refuses(
        &out,
        &calibrate_args(&f, &frames, out.join("cal.fits").to_str().unwrap()),
        &["zero.fits", "neg.fits", "bias"],
    );
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
    // Another exposure at 45 deg (a byte-identical copy would be the same data twice, refused):
    // one pixel outside the beams differs.
    frames.push(f.frame("again.fits", 45.0, "V", |d| d[0] += 1.0));
    let out = f.out_dir().join("cal.fits");
    let (code, _, err) = run(&calibrate_args(&f, &frames, out.to_str().unwrap()));
    assert!(!err.contains("panicked"));
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("again.fits") && err.contains("second frame at HWP angle 45"), "{err}");
}

#[test]
fn frames_mixed_filters() {
    let f = Fixture::new();
    let inst = mini().replace(
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
    // One validation of a (q, u, sigma, cov) measurement (mueller::Qu::unphysical): a
    // covariance beyond sigma_q sigma_u (a correlation coefficient of 1 given as cov_qu: it
    // made sigma_p0 = 0), P = 1.5 (percent for a fraction), and an error whose square
    // overflows (1e300: it wrote sigma_p0 = 0) are refused, naming the row and the rule.
    let with_cov = |v: &str| format!("id,x,y,q,u,sigma_q,sigma_u,cov_qu\n1,0.5,0.5,0.01,0.002,0.0005,0.0005,{v}\n");
    let cat = f.csv("cov.csv", &with_cov("1"));
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &cat, "--out", o.to_str().unwrap()],
        &["cov.csv", "row 1", "not a covariance"],
    );
    // The edge itself, cov_qu = sigma_q sigma_u (a degenerate but valid ellipse), is corrected.
    let cat = f.csv("cov_edge.csv", &with_cov("2.5e-7"));
    let (c, _, e) = common::run(&["correct", "--cal", &cal, "--in", &cat, "--out", o.to_str().unwrap()]);
    assert_eq!(c, 0, "{e}");
    std::fs::remove_file(&o).unwrap();
    let cat = f.csv("percent.csv", "id,x,y,q,u,sigma_q,sigma_u\n1,0.5,0.5,1.5,0.2,0.05,0.05\n");
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &cat, "--out", o.to_str().unwrap()],
        &["percent.csv", "more than fully polarized", "percent"],
    );
    let cat = f.csv("huge.csv", &GOOD_CAT.replace("0.002,0.0005,0.0005", "0.002,1e300,0.0005"));
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &cat, "--out", o.to_str().unwrap()],
        &["huge.csv", "sigma_q is too large"],
    );
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

/// A FORS1-sized Stokes map of `instrument` and `filter` with one valid bin (P = 1%).
fn one_bin_map(path: &Path, instrument: &str, filter: &str) {
    let geom = skyfield::BinGeometry::covering(60, 0, 0, 2048, 2048, 0.2);
    let mut map = skyfield::StokesMap::empty(geom, instrument, filter, vec![0.0, 22.5, 45.0, 67.5]);
    map.valid[0] = true;
    (map.q[0], map.u[0], map.p[0], map.chi[0], map.cov_qu[0]) = (0.01, 0.0, 0.01, 0.0, 0.0);
    map.sigma_q[0] = 1e-3;
    map.sigma_u[0] = 1e-3;
    map.n_pixels[0] = 10;
    (map.sigma_q_phot[0], map.sigma_u_phot[0], map.intensity[0], map.intensity_snr[0]) = (1e-3, 1e-3, 1e4, 100.0);
    map.write_fits(path).unwrap();
}

/// Regression (was a defect, fixed in 2e448c5): `correct` applied a FORS1 calibration to a Stokes map written for another
/// instrument (MAP instrument "OTHER") silently, exit 0. Fix (crates/cli/src/cmd/correct/mod.rs,
/// map path): compare the map's instrument and filter with the calibration's (filter names
/// through the instrument's aliases) and refuse with both names unless forced.
#[test]
fn correct_map_of_another_instrument() {
    // A Stokes map of instrument OTHER corrected with a FORS1 calibration.
    let f = Fixture::new();
    let cal = f.cal();
    one_bin_map(&f.p("other.fits"), "OTHER", "V");
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
    one_bin_map(&f.p("bmap.fits"), "FORS1", "B");
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
    // Two calibrations of the same filter (the same file twice, or a copy, is refused earlier,
    // as the same data twice).
    let cal2 = out.join("cal_again.fits");
    let map = f.map("map2.fits");
    let (code, _, err) =
        run(&["calibrate", "--map", &map, "--sky-p", "1.74", "--sky-chi", "-53.8", "--out", cal2.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    refuses(&out, &["wavelength-law", &cal, cal2.to_str().unwrap()], &["V"]);
    refuses(&out, &["wavelength-law", &cal, &cal], &["given twice"]);
    let copy = out.join("cal_copy.fits");
    std::fs::copy(&cal, &copy).unwrap();
    refuses(&out, &["wavelength-law", &cal, copy.to_str().unwrap()], &["cal_copy.fits", "same data"]);
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

/// `instpol import-map` of the Q and U cubes `q`, `u` (0.25"/px, 50 px bins, V) into `out`.
fn import_map_args(q: &str, u: &str, out: &str) -> Vec<String> {
    ["import-map", "--q", q, "--u", u, "--pixel-scale", "0.25", "--bin", "50", "--filter", "V", "--lambda-nm", "554"]
        .into_iter()
        .chain(["--out", out])
        .map(String::from)
        .collect()
}

#[test]
fn import_map_mismatched_and_bad_images() {
    let f = Fixture::new();
    write_image(&f.p("q.fits"), 20, 20, 0.001);
    write_image(&f.p("u.fits"), 20, 18, 0.001);
    write_image(&f.p("unan.fits"), 20, 20, f64::NAN);
    let out = f.out_dir();
    let o = out.join("cal.fits");
    let base = |u: &str| import_map_args(&f.s("q.fits"), &f.s(u), o.to_str().unwrap());
    let a = base("u.fits");
    refuses(&out, &a, &["u.fits", "18"]);
    let a = base("unan.fits");
    refuses(&out, &a, &["unan.fits"]);
    let a = base("missing.fits");
    refuses(&out, &a, &["missing.fits"]);
}

/// Physically impossible maps were once accepted: a negative error plane, and values in
/// percent (P = 1.4 > 1). Both refused naming the file and the map pixel; the control passes.
#[test]
fn import_map_negative_errors_and_p_above_one() {
    let f = Fixture::new();
    write_image(&f.p("q.fits"), 20, 20, 0.001);
    write_image(&f.p("u.fits"), 20, 20, 0.001);
    write_image(&f.p("qpct.fits"), 20, 20, 1.0);
    let neg = f.p("uneg.fits");
    {
        let d =
            fitsio::images::ImageDescription { data_type: fitsio::images::ImageType::Double, dimensions: &[2, 20, 20] };
        let mut fi = fitsio::FitsFile::create(&neg).with_custom_primary(&d).open().unwrap();
        let h = fi.primary_hdu().unwrap();
        let mut data = vec![0.001; 400];
        data.extend(vec![1e-4; 400]);
        data[400 + 3 * 20 + 5] = -1e-4; // pixel (5, 3) of the error plane
        h.write_image(&mut fi, &data).unwrap();
    }
    let out = f.out_dir();
    let o = out.join("cal.fits");
    let (code, _, err) = run(&import_map_args(&f.s("q.fits"), &f.s("u.fits"), o.to_str().unwrap()));
    assert_eq!(code, 0, "control: {err}");
    std::fs::remove_file(&o).unwrap();
    refuses(
        &out,
        &import_map_args(&f.s("q.fits"), &f.s("uneg.fits"), o.to_str().unwrap()),
        &["uneg.fits", "(5, 3)", "negative"],
    );
    refuses(
        &out,
        &import_map_args(&f.s("qpct.fits"), &f.s("u.fits"), o.to_str().unwrap()),
        &["qpct.fits", "above 1", "percent"],
    );
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

/// Regression (was a defect of fit::files::calfile + fitsio 0.21.10, fixed in 7bb1761): a calibration file whose INPUTS table has a string
/// column 24 (or 40, 56, ... : 8 mod 16) characters wide crashes every reader with heap
/// corruption (`free(): invalid pointer`, SIGABRT, exit 134). fitsio's
/// `read_col::<String>` allocates `width` bytes per row but CFITSIO's `ffgcvs` writes
/// `width + 1` (the terminating NUL); glibc has no slack in chunks of 8 mod 16 usable bytes.
/// Any input path of that length (e.g. `/tmp/.tmpXXXXXX/map.fits`, 24 chars) triggers it.
/// Fix in `Calibration::load` (crates/fit/src/files/calfile.rs): read the FILE column with buffers
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

/// The tiny instrument with two strips of 20 px; its name is still MINI.
fn mini2_toml() -> String {
    common::Mini { throw_arcsec: 80.0, strip_count: 2, ..common::MINI }.toml()
}

/// [`mini2_toml`] written as `mini2.toml`.
fn mini2(f: &Fixture) -> String {
    f.csv("mini2.toml", &mini2_toml())
}

/// A frame of [`Fixture::frame`] in the mini2 layout with an unpolarized star (Gaussian, peak
/// 20000 ADU) at (48, 14) in the ordinary image and one 20 px throw above, at (48, 34), in
/// the extraordinary image; `edit` may then change the pixels.
fn star_frame(f: &Fixture, name: &str, hwp: f64, filter: &str, edit: impl Fn(&mut Vec<f64>)) -> String {
    f.frame_of(&mini2_toml(), name, hwp, filter, |d| {
        for y in 0..96usize {
            for x in 0..96usize {
                let g = |yc: f64| {
                    let r2 = (x as f64 - 48.0).powi(2) + (y as f64 - yc).powi(2);
                    20000.0 * (-r2 / 4.5).exp()
                };
                d[y * 96 + x] += g(14.0) + g(34.0);
            }
        }
        edit(d);
    })
}

/// Four star frames `s0.fits` .. `s3.fits` at 0, 22.5, 45, 67.5 deg.
fn star_frames(f: &Fixture) -> Vec<String> {
    [0.0, 22.5, 45.0, 67.5]
        .iter()
        .enumerate()
        .map(|(i, &a)| star_frame(f, &format!("s{i}.fits"), a, "V", |_| {}))
        .collect()
}

/// `instpol photometry` of the star (aperture 3 px, annulus 4..6 px) in `frames`.
fn photometry_args(ins: &str, frames: &[String], extra: &[&str]) -> Vec<String> {
    let mut a: Vec<String> = ["photometry", "--instrument", ins, "--x", "48", "--y", "14"].map(String::from).to_vec();
    for (flag, value) in [("--aperture", "3"), ("--annulus", "4,6")] {
        if !extra.iter().any(|e| e.starts_with(flag)) {
            a.extend([flag.to_string(), value.to_string()]);
        }
    }
    a.extend(extra.iter().map(|s| s.to_string()));
    a.extend(frames.iter().cloned());
    a
}

/// `instpol validate` of calibration `cal` on the star in `frames`, measured as in
/// [`photometry_args`].
fn validate_args(cal: &str, ins: &str, frames: &[String], extra: &[&str]) -> Vec<String> {
    let mut a = photometry_args(ins, frames, extra);
    a[0] = "validate".into();
    a.splice(1..1, ["--cal".to_string(), cal.to_string()]);
    a
}

/// A calibration of the tiny instrument MINI (its pixel grid: 4"/px about pixel 47.5) with the
/// paper's V polynomial, valid for |x|, |y| <= `half` arcmin, saved as `name`.
fn mini_cal(f: &Fixture, name: &str, half: f64) -> String {
    let mut c = common::fors1_radial_calibration("V", common::V_COEFFS);
    c.instrument = "MINI".into();
    c.region = fit::FieldRegion { x_min: -half, x_max: half, y_min: -half, y_max: half };
    c.pixel = Some(fit::files::calfile::PixelGrid { scale_arcsec: 4.0, origin_px: [47.5, 47.5] });
    c.save(&f.p(name)).unwrap();
    f.s(name)
}

/// Run photometry and validate (a MINI calibration covering the detector) on `frames` and
/// expect both to refuse, naming each of `names`.
#[track_caller]
fn photometry_and_validate_refuse(f: &Fixture, frames: &[String], names: &[&str]) {
    let ins = mini2(f);
    let cal = mini_cal(f, "minical.fits", 3.2);
    refuses(f.dir.path(), &photometry_args(&ins, frames, &["--json"]), names);
    refuses(f.dir.path(), &validate_args(&cal, &ins, frames, &["--json"]), names);
}

/// Both commands on `frames` succeed; returns the JSON of each.
fn photometry_and_validate_json(f: &Fixture, frames: &[String]) -> (serde_json::Value, serde_json::Value, String) {
    let ins = mini2(f);
    let cal = mini_cal(f, "minical.fits", 3.2);
    let (code, out, err) = run(&photometry_args(&ins, frames, &["--json"]));
    assert_eq!(code, 0, "photometry: {err}");
    let (code, vout, verr) = run(&validate_args(&cal, &ins, frames, &["--json"]));
    assert_eq!(code, 0, "validate: {verr}");
    (serde_json::from_str(&out).unwrap(), serde_json::from_str(&vout).unwrap(), err + &verr)
}

#[test]
fn photometry_control_and_bad_geometry() {
    let f = Fixture::new();
    let frames = star_frames(&f);
    let ins = mini2(&f);
    let base = |x: &str, extra: &[&str]| {
        let mut a = photometry_args(&ins, &frames, extra);
        a[4] = x.to_string();
        a
    };
    let (code, _, err) = run(&base("48", &[]));
    assert_eq!(code, 0, "control: {err}");
    refuses(f.dir.path(), &base("5000", &[]), &["5000"]);
    refuses(f.dir.path(), &base("48", &["--aperture=-3"]), &["--aperture -3"]);
    refuses(f.dir.path(), &base("48", &["--annulus", "6,4"]), &["annulus (6, 4)"]);
}

/// The control of the frame rows below. The star is unpolarized (the same Gaussian in both
/// beams) and the annulus sees the same star wings in both beams on top of each beam's sky,
/// so the beam-by-beam background subtraction (section background) leaves P = 0 (to float32
/// rounding) however much of the wings the annulus holds; validate measures the same star.
#[test]
fn photometry_and_validate_control_good_frames() {
    let f = Fixture::new();
    let (p, v, _) = photometry_and_validate_json(&f, &star_frames(&f));
    assert!(p["p"].as_f64().unwrap() < 1e-6, "{p}");
    assert!((v["measured_p"].as_f64().unwrap() - p["p"].as_f64().unwrap()).abs() < 1e-12, "{v} vs {p}");
}

#[test]
fn photometry_and_validate_truncated_frame() {
    let f = Fixture::new();
    let mut frames = star_frames(&f);
    let bytes = std::fs::read(&frames[2]).unwrap();
    std::fs::write(f.p("trunc.fits"), &bytes[..bytes.len() / 2]).unwrap();
    frames[2] = f.s("trunc.fits");
    photometry_and_validate_refuse(&f, &frames, &["trunc.fits"]);
}

#[test]
fn photometry_and_validate_text_file_as_frame() {
    let f = Fixture::new();
    let mut frames = star_frames(&f);
    frames[1] = f.csv("text.fits", "this is not FITS\n");
    photometry_and_validate_refuse(&f, &frames, &["text.fits"]);
}

#[test]
fn photometry_and_validate_all_nan_frame() {
    let f = Fixture::new();
    let mut frames = star_frames(&f);
    frames[0] = star_frame(&f, "nan.fits", 0.0, "V", |d| d.iter_mut().for_each(|x| *x = f64::NAN));
    photometry_and_validate_refuse(&f, &frames, &["nan.fits"]);
}

/// A NaN or infinite pixel inside the aperture cannot be masked without biasing the flux:
/// refused, naming the file, the pixel and its beam.
#[test]
fn photometry_and_validate_nan_or_inf_pixel_in_the_aperture() {
    let f = Fixture::new();
    let mut frames = star_frames(&f);
    frames[1] = star_frame(&f, "nanap.fits", 22.5, "V", |d| d[14 * 96 + 48] = f64::NAN);
    photometry_and_validate_refuse(&f, &frames, &["nanap.fits", "(48, 14)", "o beam", "NaN"]);
    let mut frames = star_frames(&f);
    frames[3] = star_frame(&f, "infap.fits", 67.5, "V", |d| d[34 * 96 + 49] = f64::INFINITY);
    photometry_and_validate_refuse(&f, &frames, &["infap.fits", "(49, 34)", "e beam", "inf"]);
}

/// By design: NaN/inf pixels in the background annulus are left out of the sky estimate, with
/// a warning naming the file; two of the 42 annulus pixels change the sky estimate far less
/// than the photon noise (Q and U move by < 5% of their errors).
#[test]
fn photometry_and_validate_nan_pixels_in_the_annulus_are_masked_with_a_warning() {
    let f = Fixture::new();
    let (p0, _, _) = photometry_and_validate_json(&f, &star_frames(&f));
    let mut frames = star_frames(&f);
    frames[2] = star_frame(&f, "nanann.fits", 45.0, "V", |d| {
        d[14 * 96 + 53] = f64::NAN;
        d[34 * 96 + 43] = f64::NEG_INFINITY;
    });
    let (p, v, err) = photometry_and_validate_json(&f, &frames);
    assert!(err.contains("nanann.fits") && err.contains("2 NaN/infinite pixels masked"), "{err}");
    for k in ["q", "u"] {
        let sigma = p0[format!("sigma_{k}")].as_f64().unwrap();
        assert!((p[k].as_f64().unwrap() - p0[k].as_f64().unwrap()).abs() < 0.05 * sigma, "{k}: {p} vs {p0}");
    }
    assert!(v["measured_p"].as_f64().unwrap().is_finite(), "{v}");
}

#[test]
fn photometry_and_validate_wrong_dimensions() {
    let f = Fixture::new();
    let mut frames = star_frames(&f);
    let keys = vec![
        ("HIERARCH ESO INS RETA2 POSANG".to_string(), KeyValue::F64(45.0), String::new()),
        ("HIERARCH ESO INS FILT1 NAME".to_string(), KeyValue::Str("V".into()), String::new()),
    ];
    write_frame(&f.p("small.fits"), 64, 96, &vec![1000.0; 64 * 96], Bitpix::F32, &keys).unwrap();
    frames[2] = f.s("small.fits");
    photometry_and_validate_refuse(&f, &frames, &["small.fits", "64 x 96"]);
}

#[test]
fn photometry_and_validate_missing_hwp_angle_keyword() {
    let f = Fixture::new();
    let mut frames = star_frames(&f);
    let keys = vec![("HIERARCH ESO INS FILT1 NAME".to_string(), KeyValue::Str("V".into()), String::new())];
    write_frame(&f.p("nokey.fits"), 96, 96, &vec![1000.0; 96 * 96], Bitpix::F32, &keys).unwrap();
    frames[3] = f.s("nokey.fits");
    photometry_and_validate_refuse(&f, &frames, &["nokey.fits", "RETA2 POSANG"]);
}

#[test]
fn photometry_and_validate_missing_hwp_angle() {
    let f = Fixture::new();
    let mut frames = star_frames(&f);
    frames.remove(2);
    photometry_and_validate_refuse(&f, &frames, &["missing [45 deg]"]);
}

/// By design: a second exposure at one HWP angle is summed with the first (warning naming
/// both files). The same exposure twice leaves every F_i (eq:F), hence Q and U, unchanged.
#[test]
fn photometry_and_validate_duplicated_hwp_angle_is_summed_with_a_warning() {
    let f = Fixture::new();
    let (p0, v0, _) = photometry_and_validate_json(&f, &star_frames(&f));
    let mut frames = star_frames(&f);
    // Another exposure at 45 deg, one pixel in a corner off (a byte-identical copy would be the
    // same data twice, refused).
    frames.push(star_frame(&f, "again.fits", 45.0, "V", |d| d[0] += 1.0));
    let (p, v, err) = photometry_and_validate_json(&f, &frames);
    assert!(err.contains("again.fits") && err.contains("second frame at HWP angle 45"), "{err}");
    for k in ["q", "u"] {
        assert!((p[k].as_f64().unwrap() - p0[k].as_f64().unwrap()).abs() < 1e-9, "{k}: {p} vs {p0}");
    }
    assert_eq!(v["n_frames"], 5);
    assert!((v["predicted_p"].as_f64().unwrap() - v0["predicted_p"].as_f64().unwrap()).abs() < 1e-12);
}

#[test]
fn photometry_and_validate_mixed_filters() {
    let f = Fixture::new();
    let mut frames = star_frames(&f);
    frames[3] = star_frame(&f, "b.fits", 67.5, "B", |_| {});
    let two = common::Mini { throw_arcsec: 80.0, strip_count: 2, ..common::MINI }.toml().replace(
        "[[filters]]\nname = \"V\"",
        "[[filters]]\nname = \"B\"\nlambda_eff_nm = 429.0\n\n[[filters]]\nname = \"V\"",
    );
    let ins = f.csv("mini2b.toml", &two);
    let cal = mini_cal(&f, "minical.fits", 3.2);
    refuses(f.dir.path(), &photometry_args(&ins, &frames, &[]), &["b.fits", "B", "V"]);
    refuses(f.dir.path(), &validate_args(&cal, &ins, &frames, &[]), &["b.fits", "B", "V"]);
}

/// A frame of zero or negative counts (a failed readout, an over-subtracted bias) leaves no
/// source flux at its HWP angle: refused, naming the angle and the file.
#[test]
fn photometry_and_validate_zero_and_negative_flux_frames() {
    let f = Fixture::new();
    let mut frames = star_frames(&f);
    frames[0] = star_frame(&f, "zero.fits", 0.0, "V", |d| d.iter_mut().for_each(|x| *x = 0.0));
    photometry_and_validate_refuse(&f, &frames, &["zero.fits", "HWP angle 0 deg"]);
    let mut frames = star_frames(&f);
    frames[1] = star_frame(&f, "neg.fits", 22.5, "V", |d| d.iter_mut().for_each(|x| *x = -100.0));
    photometry_and_validate_refuse(&f, &frames, &["neg.fits", "HWP angle 22.5 deg"]);
}

/// No star at the position (empty sky): the background-subtracted flux is 0, not positive.
#[test]
fn photometry_and_validate_no_star_at_the_position() {
    let f = Fixture::new();
    let frames = star_frames(&f);
    let ins = mini2(&f);
    let cal = mini_cal(&f, "minical.fits", 3.2);
    let mut a = photometry_args(&ins, &frames, &[]);
    a[4] = "20".into();
    refuses(f.dir.path(), &a, &["no source", "(20.0, 14.0)"]);
    let mut a = validate_args(&cal, &ins, &frames, &[]);
    a[6] = "20".into();
    refuses(f.dir.path(), &a, &["no source", "(20.0, 14.0)"]);
}

/// A saturated star cannot be measured: refused, naming the file and the pixel.
#[test]
fn photometry_and_validate_saturated_star() {
    let f = Fixture::new();
    let mut frames = star_frames(&f);
    frames[2] = star_frame(&f, "sat.fits", 45.0, "V", |d| d[14 * 96 + 48] = 65000.0);
    photometry_and_validate_refuse(&f, &frames, &["sat.fits", "(48, 14)", "saturated"]);
}

#[test]
fn validate_position_outside_the_calibrated_field() {
    let f = Fixture::new();
    let frames = star_frames(&f);
    let ins = mini2(&f);
    // Valid within 1 arcmin of the centre; the star is at y = (14 - 47.5) x 4" = -2.23'.
    let cal = mini_cal(&f, "smallcal.fits", 1.0);
    refuses(f.dir.path(), &validate_args(&cal, &ins, &frames, &[]), &["outside the calibrated field", "-2.23"]);
    let (code, _, err) = run(&validate_args(&cal, &ins, &frames, &["--allow-extrapolation"]));
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("extrapolated"), "{err}");
}

#[test]
fn validate_bad_standards_file_and_unknown_star() {
    let f = Fixture::new();
    let cal = mini_cal(&f, "minical.fits", 3.2);
    let frames = star_frames(&f);
    let ins = mini2(&f);
    let std_text =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/standards.toml"))
            .unwrap();
    let typo = f.csv("typo_std.toml", &std_text.replacen("sigma_p_percent", "sigma_p_percnt", 1));
    let a = validate_args(&cal, &ins, &frames, &["--standards", &typo, "--star", "HD 14069"]);
    refuses(f.dir.path(), &a, &["typo_std.toml", "sigma_p_percnt"]);
    // Read even when no --star is named (was ignored then).
    let a = validate_args(&cal, &ins, &frames, &["--standards", &typo]);
    refuses(f.dir.path(), &a, &["typo_std.toml", "sigma_p_percnt"]);
    let nop = f.csv("nop_std.toml", &std_text.replacen("p_percent = 0.111\n", "", 1));
    let a = validate_args(&cal, &ins, &frames, &["--standards", &nop, "--star", "HD 14069"]);
    refuses(f.dir.path(), &a, &["nop_std.toml", "p_percent"]);
    refuses(f.dir.path(), &validate_args(&cal, &ins, &frames, &["--star", "HD 99999"]), &["HD 99999"]);
}

/// Regression (was a defect, fixed in e568d20): frames of the tiny instrument MINI validated
/// with a FORS1 calibration passed (exit 0, "star unpolarized in V ..."): the calibration's
/// instrument was never compared with the frames' (`--instrument`). Fix
/// (crates/cli/src/cmd/validate.rs): refuse when `cal.instrument` differs from the
/// instrument's name (case-insensitive), naming both.
#[test]
fn validate_calibration_of_another_instrument() {
    let f = Fixture::new();
    let cal = f.cal();
    let frames = star_frames(&f);
    let ins = mini2(&f);
    refuses(f.dir.path(), &validate_args(&cal, &ins, &frames, &[]), &["MINI", "FORS1"]);
}

/// Was a defect (found by fuzz/run.sh, fuzz_calibration_file; fixed in 2e5086f): a calibration whose UMAP
/// header claims NAXIS2 = 99999999999 aborts `instpol correct` with "memory allocation of
/// 55199999999448 bytes failed" (SIGABRT, no `error:` line): `fit::Calibration::load` reads the
/// image with the size its header claims. Fix (crates/fit/src/files/calfile.rs, `load`): check each
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

/// Was a defect (fixed in 2e5086f; same class, fit::files::import): a Q cube for `import-map` whose header claims NAXIS2 =
/// 99999999999 (the file holds 2 x 20 x 20) aborts with "memory allocation of 31999999999680
/// bytes failed". Fix (crates/fit/src/files/import.rs): check the claimed size against the file's
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
    refuses(&out, &import_map_args(&q, &u, o.to_str().unwrap()), &["q.fits"]);
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

// ---------------------------------------------------------------------------------------
// Every reader of a calibration file, every writer of an output
// ---------------------------------------------------------------------------------------

/// A calibration of a newer (99) or an invalid (0) format version is refused by every command
/// that reads one, naming the file and the version (`correct`:
/// `correct_calibration_of_newer_format_version`).
#[test]
fn every_calibration_reader_refuses_another_format_version() {
    let f = Fixture::new();
    let frames = star_frames(&f);
    let ins = mini2(&f);
    let cal = mini_cal(&f, "minical.fits", 3.2);
    let (code, _, err) = run(&validate_args(&cal, &ins, &frames, &[]));
    assert_eq!(code, 0, "control: {err}");
    let out = f.out_dir();
    for (version, word) in [("99", "99"), ("0", "version")] {
        patch_card(Path::new(&cal), "FORMAT VERSION", version);
        refuses(&out, &validate_args(&cal, &ins, &frames, &[]), &["minical.fits", word]);
        refuses(&out, &["fit", &cal, "--out", out.join("refit.fits").to_str().unwrap()], &["minical.fits", word]);
        refuses(&out, &["plot", &cal, "--out", out.join("plots").to_str().unwrap()], &["minical.fits", word]);
        // A second calibration of that version (a copy would be the same data twice, refused).
        let other = mini_cal(&f, "minical_other.fits", 3.3);
        patch_card(Path::new(&other), "FORMAT VERSION", version);
        refuses(&out, &["wavelength-law", &cal, &other], &["minical.fits", word]);
        std::fs::remove_file(&other).unwrap();
    }
}

/// Every command that writes a file or a folder, given an output whose parent is a regular
/// file (fails even as root): exit 2 naming that parent, nothing written anywhere
/// (`calibrate`, `correct`, `simulate`, `reduce`: their own rows above).
#[test]
fn every_writer_refuses_an_output_under_a_file() {
    let f = Fixture::new();
    let cal = f.cal();
    std::fs::write(f.p("afile"), "x").unwrap();
    let under = |name: &str| f.p("afile").join(name).to_str().unwrap().to_string();
    let d = f.dir.path();
    let map = f.map("map2.fits");
    // calibrate --plots under a file: refused before anything is saved (no calibration, no
    // plot, no temporary).
    let c2 = f.p("c2.fits");
    let (code, _, err) = run(&[
        "calibrate",
        "--map",
        &map,
        "--sky-p",
        "1.74",
        "--sky-chi",
        "-53.8",
        "--out",
        c2.to_str().unwrap(),
        "--plots",
        &under("plots"),
    ]);
    assert_eq!(code, 2, "{err}");
    assert!(err.lines().any(|l| l.starts_with("error: ")) && err.contains("afile"), "{err}");
    assert!(!c2.exists(), "calibrate saved a calibration although its plots folder cannot be made");
    refuses(d, &["fit", &cal, "--out", &under("refit.fits")], &["afile"]);
    refuses(d, &["fit", &cal, "--plots", &under("plots")], &["afile"]);
    refuses(d, &["plot", &cal, "--out", &under("plots")], &["afile"]);
    write_image(&f.p("q.fits"), 20, 20, 0.001);
    write_image(&f.p("u.fits"), 20, 20, 0.001);
    let (q, u) = (f.s("q.fits"), f.s("u.fits"));
    refuses(d, &import_map_args(&q, &u, &under("cal.fits")), &["afile"]);
    refuses(
        d,
        &["mc", "--accuracy-report", "--trials", "1000", "--noise", "gauss-qu", "--plot", &under("acc.png")],
        &["afile"],
    );
    refuses(d, &["mc", "--sweep", "--trials", "200", "--noise", "gauss-qu", "--plot", &under("sweep.png")], &["afile"]);
    refuses(d, &["raytrace", "--filter", "V", "--plot", &under("rt.png")], &["afile"]);
    refuses(d, &["raytrace", "--filter", "V", "--field-out", &under("field.json")], &["afile"]);
    refuses(d, &["demo", "--no-frames", "--out", &under("demo")], &["afile"]);
}

/// Whether `b` is a whole PNG: the signature, then chunks (length, type, data, CRC) that end
/// exactly at the end of the file with IEND.
fn is_complete_png(b: &[u8]) -> bool {
    if b.len() < 8 || &b[..8] != b"\x89PNG\r\n\x1a\n" {
        return false;
    }
    let mut i = 8;
    while i + 12 <= b.len() {
        let len = u32::from_be_bytes(b[i..i + 4].try_into().unwrap()) as usize;
        let end = i + 12 + len;
        if end > b.len() {
            return false;
        }
        if &b[i + 4..i + 8] == b"IEND" {
            return end == b.len();
        }
        i = end;
    }
    false
}

/// `instpol mc --accuracy-report --plot FILE` killed with SIGKILL while the plot is being
/// written (the moment its temporary appears, and when it has bytes) and at fixed delays
/// around the end of the run: the plot is either absent or a complete PNG, never a partial
/// one, and the only other names left are the writer's dot-temporaries (a killed process
/// cannot remove its own).
#[test]
fn killed_mc_accuracy_report_leaves_no_partial_plot() {
    let f = Fixture::new();
    let out = f.out_dir();
    let png = out.join("acc.png");
    let args = ["mc", "--accuracy-report", "--trials", "2000", "--noise", "gauss-qu", "--threads", "1", "--plot"];
    let (code, _, err) = run(&[&args[..], &[png.to_str().unwrap()]].concat());
    assert_eq!(code, 0, "{err}");
    assert!(is_complete_png(&std::fs::read(&png).unwrap()), "control plot is not a whole PNG");
    let temps = || listing(&out).into_iter().filter(|n| n.starts_with('.')).collect::<Vec<_>>();
    let check = |when: &str| {
        if png.exists() {
            assert!(is_complete_png(&std::fs::read(&png).unwrap()), "partial acc.png after kill {when}");
        }
        for name in listing(&out) {
            assert!(name == "acc.png" || name.starts_with(".instpol-"), "stray file {name} after kill {when}");
        }
    };
    let spawn = || {
        Command::new(bin())
            .args(args)
            .arg(&png)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap()
    };
    // Killed while writing: poll for the temporary (empty, then with bytes) and kill then.
    let mut caught = 0;
    for want_bytes in [false, true, false, true, false, true] {
        let _ = std::fs::remove_file(&png);
        let before = temps();
        let mut child = spawn();
        let t0 = std::time::Instant::now();
        loop {
            let fresh: Vec<String> = temps().into_iter().filter(|n| !before.contains(n)).collect();
            let hit = fresh
                .iter()
                .any(|n| !want_bytes || std::fs::metadata(out.join(n)).map(|m| m.len() > 0).unwrap_or(false));
            if hit || t0.elapsed().as_secs() > 20 || child.try_wait().unwrap().is_some() {
                let _ = child.kill();
                caught += hit as usize;
                break;
            }
        }
        let _ = child.wait();
        check(&format!("while writing (temporary with bytes: {want_bytes})"));
    }
    assert!(caught > 0, "never saw the plot's temporary: is the plot written through temp_beside?");
    // Killed at fixed moments.
    for delay_ms in [20u64, 60, 100, 140, 180, 250] {
        let _ = std::fs::remove_file(&png);
        let mut child = spawn();
        std::thread::sleep(std::time::Duration::from_millis(delay_ms));
        let _ = child.kill();
        let _ = child.wait();
        check(&format!("at {delay_ms} ms"));
    }
}

// ---------------------------------------------------------------------------------------
// Raw frame formats: tables, chip files, overscan keywords, filters, BLANK.
// ---------------------------------------------------------------------------------------

/// The shrunk FORS2 (`common::raw`) and its raw science set, written into the fixture.
fn fors2_fixture(f: &Fixture) -> (String, common::raw::RawSet) {
    std::fs::write(f.p("fors2.toml"), common::raw::fors2_tiny_text()).unwrap();
    let set = common::raw::write_raw_set(f.dir.path(), &common::raw::fors2_tiny());
    (f.s("fors2.toml"), set)
}

fn strs(v: &[PathBuf]) -> Vec<String> {
    v.iter().map(|p| p.to_str().unwrap().to_string()).collect()
}

#[test]
fn raw_fors2_control_reduces() {
    let f = Fixture::new();
    let (inst, set) = fors2_fixture(&f);
    let out = f.out_dir().join("m.fits");
    let mut a = vec!["reduce".to_string()];
    a.extend(strs(&set.science));
    a.extend(["--instrument".into(), inst, "--bin".into(), "8".into(), "--out".into(), out.to_str().unwrap().into()]);
    let (code, _, err) = run(&a);
    assert_eq!(code, 0, "{err}");
}

#[test]
fn reduce_an_extension_that_is_a_table() {
    let f = Fixture::new();
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../skyfield/tests/data/formats");
    let toml = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 12")
        .replace("ny = 2048", "ny = 20")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 2.0")
        .replace("strip_count = 9", "strip_count = 1")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 0");
    std::fs::write(f.p("t.toml"), toml).unwrap();
    let table = format!("{}[1]", data.join("mef.fits").display());
    let good = data.join("prim_f32.fits").display().to_string();
    let out = f.out_dir().join("m.fits");
    refuses(
        &f.out_dir(),
        &["reduce", &table, &good, "--instrument", &f.s("t.toml"), "--bin", "4", "--out", out.to_str().unwrap()],
        &["mef.fits", "HDU 1 (TAB) is a binary table, not an image"],
    );
}

#[test]
fn reduce_chip_files_of_different_exposures() {
    let f = Fixture::new();
    let (_, set) = fors2_fixture(&f);
    // Without exposure keywords the chip files of one exposure are taken next to each other:
    // CHIP1 of the exposure at 0 deg with CHIP2 of the one at 22.5 deg.
    let text = common::raw::fors2_tiny_text().replace("exposure_keywords = [\"HIERARCH ESO DET EXP NO\"]", "");
    std::fs::write(f.p("adjacent.toml"), text).unwrap();
    let inst = f.s("adjacent.toml");
    let mut files = strs(&set.science);
    files.swap(1, 3);
    let out = f.out_dir().join("m.fits");
    let mut a = vec!["reduce".to_string()];
    a.extend(files);
    a.extend(["--instrument".into(), inst, "--out".into(), out.to_str().unwrap().into()]);
    refuses(
        &f.out_dir(),
        &a,
        &["chip files of different exposures", "sci0_CHIP1.fits", "sci1_CHIP2.fits", "HIERARCH ESO INS RETA2 POSANG"],
    );
}

#[test]
fn reduce_missing_overscan_keywords() {
    let f = Fixture::new();
    let (_, set) = fors2_fixture(&f);
    // An instrument file that names overscan keywords these files do not have.
    let text = common::raw::fors2_tiny_text().replace("OUT1 PRSCY", "OUT9 PRSCY").replace("OUT1 OVSCY", "OUT9 OVSCY");
    std::fs::write(f.p("other.toml"), text).unwrap();
    let out = f.out_dir().join("m.fits");
    let mut a = vec!["reduce".to_string()];
    a.extend(strs(&set.science));
    a.extend(["--instrument".into(), f.s("other.toml"), "--out".into(), out.to_str().unwrap().into()]);
    refuses(
        &f.out_dir(),
        &a,
        &[
            "sci0_CHIP1.fits",
            "missing prescan/overscan header keywords",
            "'HIERARCH ESO DET OUT9 PRSCY'",
            "'HIERARCH ESO DET OUT9 OVSCY'",
        ],
    );
}

#[test]
fn reduce_and_photometry_unknown_filter() {
    let f = Fixture::new();
    let mut frames = f.frames();
    frames[2] = f.frame("zf.fits", 45.0, "z_GUNN", |_| {});
    let out = f.out_dir().join("m.fits");
    let mut a = vec!["reduce".to_string()];
    a.extend(frames.iter().cloned());
    a.extend(["--instrument".into(), f.s("mini.toml"), "--out".into(), out.to_str().unwrap().into()]);
    refuses(&f.out_dir(), &a, &["zf.fits", "filter 'z_GUNN'", "instrument MINI's filters (V)"]);
    let mut a = vec!["photometry".to_string()];
    a.extend(frames);
    a.extend(["--instrument".into(), f.s("mini.toml"), "--x".into(), "48".into(), "--y".into(), "14".into()]);
    refuses(&f.out_dir(), &a, &["zf.fits", "filter 'z_GUNN'"]);
}

/// BLANK pixels of an integer frame are no data: masked with a warning, by design.
#[test]
fn reduce_blank_pixels_are_masked_with_a_warning() {
    let f = Fixture::new();
    let mut frames = f.frames();
    let inst = instrument::Instrument::from_toml_str(&mini(), Path::new("mini.toml")).unwrap();
    let (nx, ny) = (inst.detector.nx, inst.detector.ny);
    let path = f.p("blank.fits");
    {
        use fitsio::images::{ImageDescription, ImageType};
        let d = ImageDescription { data_type: ImageType::Short, dimensions: &[ny, nx] };
        let mut ff = fitsio::FitsFile::create(&path).with_custom_primary(&d).open().unwrap();
        let h = ff.primary_hdu().unwrap();
        // The frame of f1 (22.5 deg), as integers, with three BLANK pixels in the beams.
        let mut fr = fitsio::FitsFile::open(&frames[1]).unwrap();
        let v: Vec<f32> = fr.primary_hdu().unwrap().read_image(&mut fr).unwrap();
        let mut v: Vec<i16> = v.iter().map(|x| x.round() as i16).collect();
        let s = inst.strips()[0];
        for k in 0..3 {
            v[(s.o_start + k) * nx + 10] = -32768;
        }
        h.write_image(&mut ff, &v).unwrap();
        h.write_key(&mut ff, "BLANK", -32768i64).unwrap();
        h.write_key(&mut ff, "HIERARCH ESO INS RETA2 POSANG", 22.5f64).unwrap();
        h.write_key(&mut ff, "HIERARCH ESO INS FILT1 NAME", "V").unwrap();
    }
    frames[1] = path.to_str().unwrap().to_string();
    let out = f.out_dir().join("m.fits");
    let mut a = vec!["reduce".to_string()];
    a.extend(frames);
    a.extend(["--instrument".into(), f.s("mini.toml"), "--out".into(), out.to_str().unwrap().into()]);
    let (code, _, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("blank.fits: 3 NaN/infinite pixels masked"), "{err}");
}

/// HWP angles from `--hwp-angles`: for an instrument that names no HWP keyword they
/// are required (and then used, in the frames' order); a count that does not match the
/// exposures, or an angle that contradicts the header, is refused naming the file.
#[test]
fn reduce_hwp_angles_from_the_command_line() {
    let f = Fixture::new();
    let frames = f.frames();
    std::fs::write(
        f.p("nokw.toml"),
        mini().replace("hwp_angle_keyword = \"HIERARCH ESO INS RETA2 POSANG\"", "hwp_angle_keyword = \"\""),
    )
    .unwrap();
    let out = f.out_dir().join("m.fits");
    let args = |inst: &str, extra: &[&str]| {
        let mut a = vec!["reduce".to_string()];
        a.extend(frames.iter().cloned());
        a.extend(["--instrument".into(), f.s(inst), "--out".into(), out.to_str().unwrap().into()]);
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    refuses(&f.out_dir(), &args("nokw.toml", &[]), &["f0.fits", "names no HWP-angle keyword", "--hwp-angles"]);
    refuses(
        &f.out_dir(),
        &args("nokw.toml", &["--hwp-angles", "0,22.5,45"]),
        &["--hwp-angles gives 3 angles for 4 exposures"],
    );
    refuses(
        &f.out_dir(),
        &args("mini.toml", &["--hwp-angles", "0,22.5,45,90"]),
        &["f3.fits", "--hwp-angles says 90 deg", "'HIERARCH ESO INS RETA2 POSANG' says 67.5 deg"],
    );
    refuses(&f.out_dir(), &args("mini.toml", &["--hwp-angles", "0,x"]), &["--hwp-angles '0,x'"]);
    let (code, _, err) = run(&args("nokw.toml", &["--hwp-angles", "0,22.5,45,67.5", "--json"]));
    assert_eq!(code, 0, "{err}");
    assert!(out.exists());
}

/// Messages that say what is wrong: saturated flats are called saturated (not "no positive
/// signal"); a NaN zero angle in a catalog is "not a number" (not "NaN differs from the first
/// row's NaN"); a Poisson mean too large to draw is called too large (not "must be finite and
/// >= 0" for 5.02e19).
#[test]
fn messages_name_the_actual_problem() {
    let f = Fixture::new();
    let out = f.out_dir();
    let flats: Vec<String> = (0..3)
        .map(|i| f.frame(&format!("flat{i}.fits"), 0.0, "V", |d| d.iter_mut().for_each(|v| *v = 65000.0 + i as f64)))
        .collect();
    let mut a = vec!["master-flat".to_string(), "--instrument".into(), f.s("mini.toml")];
    a.extend(["--out".into(), out.join("mf.fits").to_str().unwrap().to_string()]);
    a.extend(flats);
    let a: Vec<&str> = a.iter().map(String::as_str).collect();
    refuses(&out, &a, &["flat0.fits", "saturated", "9216 of 9216"]);
    let cal = f.cal();
    let cat =
        f.csv("zero_nan.csv", "x,y,q,u,sigma_q,sigma_u,hwp_chi_offset_deg\n0.5,0.5,0.01,0.002,0.0005,0.0005,nan\n");
    let o = out.join("c.csv");
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &cat, "--out", o.to_str().unwrap()],
        &["zero_nan.csv", "row 1", "is not a number"],
    );
    let (c, _, e) = common::run(&["mc", "--noise", "poisson", "--sky", "1e20", "--trials", "10"]);
    assert_eq!(c, 2, "{e}");
    assert!(e.contains("too large to draw") && !e.contains("must be finite"), "{e}");
}

/// Declared units are honoured (the class "percent read as a fraction, arcsec read as
/// pixels"): an ECSV table with q, u and their errors in %, cov_qu in %2 and x, y in arcsec
/// is corrected to the numbers of the plain CSV in fractions and arcmin (to rounding: 1 % is
/// 0.01); units that cannot be read, or that leave a column ambiguous, are refused with the
/// fix; --coords that contradicts the declared units is refused.
#[test]
fn correct_honours_declared_units() {
    let f = Fixture::new();
    let cal = f.cal();
    let out = f.out_dir();
    let ecsv = |units: [&str; 7], row: &str| {
        let mut s = "# %ECSV 1.0\n# ---\n# datatype:\n".to_string();
        for (n, u) in ["x", "y", "q", "u", "sigma_q", "sigma_u", "cov_qu"].iter().zip(units) {
            if u.is_empty() {
                s += &format!("# - {{name: {n}, datatype: float64}}\n");
            } else {
                s += &format!("# - {{name: {n}, unit: '{u}', datatype: float64}}\n");
            }
        }
        s + "# schema: astropy-2.0\nx y q u sigma_q sigma_u cov_qu\n" + row + "\n"
    };
    let plain = f.csv("plain.csv", "x,y,q,u,sigma_q,sigma_u,cov_qu\n0.5,-0.25,0.012,-0.004,0.0005,0.0006,1e-8\n");
    let declared = f.csv(
        "declared.ecsv",
        &ecsv(["arcsec", "arcsec", "%", "%", "%", "%", "%2"], "30.0 -15.0 1.2 -0.4 0.05 0.06 1e-4"),
    );
    let read = |p: &Path| -> Vec<f64> {
        let text = std::fs::read_to_string(p).unwrap();
        let mut lines = text.lines().filter(|l| !l.starts_with('#'));
        let head: Vec<String> = lines.next().unwrap().split([',', ' ']).map(String::from).collect();
        let row: Vec<String> = lines.next().unwrap().split([',', ' ']).map(String::from).collect();
        ["q0", "u0", "sigma_q0", "sigma_u0", "cov_qu0"]
            .iter()
            .map(|c| row[head.iter().position(|h| h == c).unwrap()].parse().unwrap())
            .collect()
    };
    let o1 = out.join("plain_c.csv");
    let (c, _, e) = common::run(&["correct", "--cal", &cal, "--in", &plain, "--out", o1.to_str().unwrap()]);
    assert_eq!(c, 0, "{e}");
    let o2 = out.join("declared_c.ecsv");
    let (c, _, e) = common::run(&["correct", "--cal", &cal, "--in", &declared, "--out", o2.to_str().unwrap()]);
    assert_eq!(c, 0, "{e}");
    for (a, b) in read(&o1).iter().zip(read(&o2)) {
        assert!((a - b).abs() <= 1e-12 * a.abs().max(1e-12), "{a} vs {b}");
    }
    let o = out.join("c.ecsv");
    let cases: [([&str; 7], &[&str]); 4] = [
        (["arcsec", "arcsec", "%", "%", "", "%", "%2"], &["sigma_q", "declares no unit", "%"]),
        (["mm", "mm", "", "", "", "", ""], &["'mm'", "pix, arcmin, arcsec or deg"]),
        (["arcmin", "arcmin", "%", "%", "%", "%", ""], &["cov_qu", "'%2'"]),
        (["arcmin", "arcmin", "deg", "", "", "", ""], &["column 'q'", "'deg'"]),
    ];
    for (k, (units, needles)) in cases.iter().enumerate() {
        let p = f.csv(&format!("bad{k}.ecsv"), &ecsv(*units, "0.5 -0.25 1.2 -0.4 0.05 0.06 1e-4"));
        let mut n = vec![format!("bad{k}.ecsv")];
        n.extend(needles.iter().map(|s| s.to_string()));
        let n: Vec<&str> = n.iter().map(String::as_str).collect();
        refuses(&out, &["correct", "--cal", &cal, "--in", &p, "--out", o.to_str().unwrap()], &n);
    }
    let p = f.csv("pix.ecsv", &ecsv(["pix", "pix", "", "", "", "", ""], "10 12 0.012 -0.004 0.0005 0.0006 0"));
    refuses(
        &out,
        &["correct", "--cal", &cal, "--in", &p, "--coords", "arcmin", "--out", o.to_str().unwrap()],
        &["pix.ecsv", "declare pixels", "arcmin"],
    );
}

#[test]
fn scan_and_run_bad_inputs() {
    let f = Fixture::new();
    let out = f.out_dir();
    let plan = out.join("plan.toml");
    let fors2 = || "fors2".to_string();
    let empty = f.p("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let scan = |dir: &Path, extra: &[&str]| {
        let mut a =
            vec!["scan".to_string(), dir.to_str().unwrap().into(), "--instrument".into(), fors2(), "--out".into()];
        a.push(plan.to_str().unwrap().into());
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    refuses(&out, &scan(&empty, &[]), &["empty", "no FITS file"]);
    refuses(&out, &scan(&f.p("missing"), &[]), &["missing"]);
    refuses(&out, &scan(&empty, &["--sky", "EMPTY:x:3"]), &["--sky 'EMPTY:x:3'"]);
    refuses(&out, &scan(&empty, &["--sky", "EMPTY"]), &["--sky 'EMPTY'", "TARGET:P_PERCENT:CHI_DEG"]);
    std::fs::write(empty.join("a.fits"), "x").unwrap();
    refuses(&out, &scan(&empty, &["--bin", "0"]), &["bin"]);
    refuses(&out, &scan(&empty, &["--pointing-tol", "-1"]), &["pointing tolerance -1"]);
    refuses(&out, &scan(&empty, &["--fwhm", "0"]), &["FWHM 0"]);
    let mut a = scan(&empty, &[]);
    a[3] = "fors1".into();
    refuses(&out, &a, &["fors1", "[headers]"]);

    // Plans: a unit that is not there, nonsense numbers, a plan that is not a plan.
    let good = f.p("good.toml");
    std::fs::write(
        &good,
        format!(
            "version = 1\ninstrument = \"fors2\"\nrecords = {:?}\n[[units]]\nid = \"A\"\nkind = \"master-bias\"\ninputs = [{:?}]\noutputs = [{:?}]\ncommand = [\"master-bias\"]\n",
            out.join("rec").display().to_string(),
            good.display().to_string(),
            out.join("a.fits").display().to_string()
        ),
    )
    .unwrap();
    let run = |extra: &[&str]| {
        let mut a = vec!["run".to_string(), good.to_str().unwrap().into()];
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    refuses(&out, &run(&["--unit", "B"]), &["unit B", "no such unit"]);
    refuses(&out, &run(&["--unit", "7"]), &["unit number 7", "units 0 to 0"]);
    refuses(&out, &run(&["--units", "1..0"]), &["--units '1..0'"]);
    refuses(&out, &run(&["--units", "0..3"]), &["--units '0..3'", "units 0 to 0"]);
    refuses(&out, &run(&["--jobs", "0"]), &["--jobs 0"]);
    std::fs::write(f.p("v2.toml"), std::fs::read_to_string(&good).unwrap().replace("version = 1", "version = 2"))
        .unwrap();
    refuses(&out, &["run", &f.s("v2.toml")], &["v2.toml", "version 2"]);
    std::fs::write(f.p("junk.json"), "{\"units\": 3}").unwrap();
    refuses(&out, &["run", &f.s("junk.json")], &["junk.json"]);
    refuses(&out, &["run", &f.s("nothing.toml")], &["nothing.toml"]);
}
