//! Defects the hostile-input generator (hostile.rs) found, each checked here on its own with
//! the input that showed it, so that the fix is tested where it is explained.

mod common;

use std::path::Path;

/// A NaN or infinite option value was taken as given when the run did not check it: an imported
/// map with a zero angle of NaN, a star's FWHM of inf. Every floating-point option is now
/// refused unless finite (exit 2), naming the option and the value, and nothing is written.
#[test]
fn a_non_finite_option_is_refused_naming_it() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let field = fit::RadialModel::new(1, vec![1e-4, 4e-4, 0.0], [0.0, 0.0]);
    fit::synth::write_qu_cubes(&d.path().join("q.fits"), &d.path().join("u.fits"), &field, 96, 96, 4.0, 8, 1e-4)
        .unwrap();
    let import = |flag: &str, value: &str| {
        let a = [
            "import-map",
            "--q",
            &p("q.fits"),
            "--u",
            &p("u.fits"),
            "--pixel-scale",
            "4",
            "--bin",
            "8",
            "--filter",
            "V",
            "--out",
            &p("imported.fits"),
            flag,
            value,
        ];
        common::run(&a)
    };
    let (code, _, err) = import("--zero-angle", "0");
    assert_eq!(code, 0, "control: {err}");
    std::fs::remove_file(p("imported.fits")).unwrap();
    for (flag, value) in [("--zero-angle", "NaN"), ("--lambda-nm", "inf"), ("--zero-angle", "-inf")] {
        let (code, _, err) = import(flag, value);
        assert_eq!(code, 2, "{flag} {value}: {err}");
        assert!(err.contains(flag) && err.contains("not a finite number"), "{flag} {value}: {err}");
        assert!(!Path::new(&p("imported.fits")).exists(), "{flag} {value}: a calibration was written");
    }
    // Under --json the refusal is the JSON error object.
    let (code, _, err) = common::run(&["bias", "--p", "0.01", "--sigma", "0.003", "--chi", "NaN", "--json"]);
    assert_eq!(code, 2, "{err}");
    let j: serde_json::Value = serde_json::from_str(err.trim()).unwrap();
    assert!(j["error"]["message"].as_str().unwrap().contains("'--chi'"), "{err}");
}

/// `scan --out` named like its `--instrument` file (the same path, a hard link, a symlink)
/// wrote the plan over the instrument file with exit 0, and `--products` naming an input file
/// was taken; both are refused now (exit 2) and the file is unchanged.
#[test]
fn scan_refuses_to_write_its_plan_over_an_input() {
    let d = tempfile::tempdir().unwrap();
    let inst = d.path().join("inst.toml");
    std::fs::copy(common::night::tiny_fors2(), &inst).unwrap();
    let before = std::fs::read(&inst).unwrap();
    let raw = d.path().join("raw");
    std::fs::create_dir(&raw).unwrap();
    // A file the scan leaves out (not FITS): the plan is written, with no unit.
    std::fs::write(raw.join("x.fits"), "not FITS\n").unwrap();
    let hard = d.path().join("hard.toml");
    std::fs::hard_link(&inst, &hard).unwrap();
    let soft = d.path().join("soft.toml");
    std::os::unix::fs::symlink(&inst, &soft).unwrap();
    let s = |p: &Path| p.to_str().unwrap().to_string();
    for (flag, out) in [("--out", &inst), ("--out", &hard), ("--out", &soft), ("--products", &inst)] {
        let mut a = vec!["scan".to_string(), s(&raw), "--instrument".into(), s(&inst)];
        if flag != "--out" {
            a.extend(["--out".to_string(), s(&d.path().join("plan.toml"))]);
        }
        a.extend([flag.to_string(), s(out)]);
        let (code, _, err) = common::run(&a);
        assert_eq!(code, 2, "{flag} {}: {err}", out.display());
        assert!(err.contains("refusing to write over an input"), "{err}");
        assert_eq!(std::fs::read(&inst).unwrap(), before, "{flag} {}: the instrument file changed", out.display());
    }
}

/// `zero-angle --measured FILE` with no frames took a `--bias`, `--flat`, `--hwp-angles` or
/// `--assembled` it never used, a broken master included, with exit 0; such an option is now
/// refused naming itself, as `calibrate --map` does.
#[test]
fn zero_angle_without_frames_refuses_frame_options() {
    let d = tempfile::tempdir().unwrap();
    let m = d.path().join("measured.csv");
    std::fs::write(
        &m,
        "label,chi_measured_deg,sigma_chi_measured_deg,chi_catalogue_deg,sigma_chi_catalogue_deg\nA,31.2,0.3,30.0,0.2\n",
    )
    .unwrap();
    let broken = d.path().join("broken.fits");
    std::fs::write(&broken, "not a master\n").unwrap();
    let m = m.to_str().unwrap();
    let (code, _, err) = common::run(&["zero-angle", "--measured", m, "--filter", "V"]);
    assert_eq!(code, 0, "control: {err}");
    for extra in [&["--bias", broken.to_str().unwrap()][..], &["--flat", broken.to_str().unwrap()], &["--assembled"]] {
        let mut a = vec!["zero-angle", "--measured", m, "--filter", "V"];
        a.extend_from_slice(extra);
        let (code, _, err) = common::run(&a);
        assert_eq!(code, 2, "{extra:?}: {err}");
        assert!(err.contains(extra[0]) && err.contains("applies to frames"), "{extra:?}: {err}");
    }
}
