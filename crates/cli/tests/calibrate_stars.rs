//! `instpol calibrate-stars` end to end on star catalogs: 200 stars over 4 dithered pointings
//! of FORS1 through the paper's V pattern (section `sec:fors1`), 20 of them polarized at
//! 1-5 %, sharing an interstellar 0.5 % at 30 deg, each measurement drawn in the test with
//! 0.05 % errors (`common::star_catalogs`). The radial coefficients come out within errors of
//! the paper's, the interstellar polarization within its error, every polarized star is named;
//! the file is the sky-field calibration's (read back by `fit::calibration::load`, IP SOURCE
//! "field stars"). The refusals name their input.

mod common;

use common::{run, star_catalogs};
use std::path::{Path, PathBuf};

const OFFSETS: [[f64; 2]; 4] = [[0.0, 0.0], [0.6, 0.25], [-0.35, 0.55], [0.3, -0.6]];

fn args(files: &[PathBuf], extra: &[&str]) -> Vec<String> {
    let mut a = vec!["calibrate-stars".to_string()];
    a.extend(files.iter().map(|f| f.display().to_string()));
    a.extend(["--filter", "V"].map(String::from));
    a.extend(extra.iter().map(|s| s.to_string()));
    a
}

fn offsets_args() -> Vec<String> {
    OFFSETS.iter().flat_map(|o| ["--offset".to_string(), format!("{},{}", o[0], o[1])]).collect()
}

#[test]
fn field_interstellar_and_polarized_stars_from_catalogs() {
    let dir = tempfile::tempdir().unwrap();
    let (iq, iu) = (0.0025, 0.005 * 3f64.sqrt() / 2.0);
    let (files, pol) = star_catalogs(dir.path(), 21, 200, 20, (iq, iu), 5e-4, &OFFSETS);
    let out = dir.path().join("cal_V.fits");
    let mut a = args(&files, &["--out", out.to_str().unwrap(), "--json"]);
    a.extend(offsets_args());
    let (code, stdout, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    for (k, t) in fit::paper::V_COEFFS_PCT.iter().enumerate() {
        let (c, s) = (f(&j["coefficients"][k]), f(&j["sigma_coefficients"][k]));
        assert!(((c - t / 100.0) / s).abs() < 3.0, "c_{}: {c} +- {s} against {t} %", k + 1);
    }
    let i = &j["interstellar"];
    assert_eq!(i["mode"], "free");
    assert!(((f(&i["q"]) - iq) / f(&i["sigma_q"])).abs() < 3.0, "{i}");
    assert!(((f(&i["u"]) - iu) / f(&i["sigma_u"])).abs() < 3.0, "{i}");
    assert!((f(&i["p"]) - 0.005).abs() < 1e-4 && (f(&i["chi_deg"]) - 30.0).abs() < 1.0, "{i}");
    assert_eq!(j["n_stars"], 200);
    assert_eq!(j["n_catalogs"], 4);
    // Every polarized star named, at its sky position; at most 2 others (0.18 expected).
    let rejected = j["rejected"].as_array().unwrap();
    for (x, y) in &pol {
        assert!(
            rejected.iter().any(|r| (f(&r["x_arcmin"]) - x).hypot(f(&r["y_arcmin"]) - y) < 1e-6),
            "polarized star at ({x}, {y}) not named"
        );
    }
    assert!(rejected.len() <= pol.len() + 2, "{} rejected", rejected.len());
    assert!(f(&j["expected_false_rejections"]) < 0.2);
    // The calibration file is the sky-field calibration's, read by the one loader.
    let loaded = fit::calibration::load(&out).unwrap();
    let cal = loaded.field.expect("a field calibration");
    assert_eq!(cal.provenance.source, "field stars");
    assert_eq!(cal.model.kind(), "RADIAL");
    assert_eq!(cal.provenance.inputs.len(), 4);
    // The table form names the rejected stars too.
    let mut t = args(&files, &["--out", dir.path().join("cal2.fits").to_str().unwrap()]);
    t.extend(offsets_args());
    let (code, text, err) = run(&t);
    assert_eq!(code, 0, "{err}");
    assert!(text.contains("rejected as polarized: ") && text.contains("interstellar (free)"), "{text}");
}

fn refused(a: &[String], needle: &str) {
    let (code, _, err) = run(a);
    assert_eq!(code, 2, "{a:?}: {err}");
    assert!(err.contains(needle), "expected '{needle}' in: {err}");
}

#[test]
fn refusals_name_their_input() {
    let dir = tempfile::tempdir().unwrap();
    let (files, _) = star_catalogs(dir.path(), 22, 120, 0, (0.0, 0.0), 5e-4, &OFFSETS);
    let out = dir.path().join("c.fits");
    let o = out.to_str().unwrap();
    // A catalog without the zero-angle column: its q, u frame is unknown.
    let bare = dir.path().join("bare.csv");
    let text = std::fs::read_to_string(&files[0]).unwrap();
    let stripped: String = text.lines().map(|l| l.rsplit_once(',').unwrap().0.to_string() + "\n").collect();
    std::fs::write(&bare, stripped).unwrap();
    refused(&args(&[bare.clone()], &["--out", o]), "no column 'hwp_chi_offset_deg'");
    // Pointings not matching: the third catalog of another field (another draw of stars),
    // the offsets to measure.
    let other_dir = dir.path().join("other");
    std::fs::create_dir_all(&other_dir).unwrap();
    let (others, _) = star_catalogs(&other_dir, 23, 120, 0, (0.0, 0.0), 5e-4, &OFFSETS);
    let other = others[2].clone();
    let three = [files[0].clone(), files[1].clone(), other, files[3].clone()];
    refused(&args(&three, &["--out", o]), "pointing 3: only");
    // With the offsets given, the same catalogs run and the JSON says the third shares (next to)
    // no star.
    let mut a = args(&three, &["--out", o, "--json"]);
    a.extend(offsets_args());
    let (code, stdout, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let w = j["warnings"][0].as_str().unwrap();
    assert!(w.starts_with("pointing 3 shares ") && w.contains("stars of their own"), "{j}");
    assert!(err.contains("warning: pointing 3 shares "), "{err}");
    std::fs::remove_file(o).unwrap();
    // Offsets of the wrong number.
    refused(&args(&files, &["--out", o, "--offset", "0,0"]), "1 --offset for 4 catalogs");
    // Too few stars for the model.
    let few = dir.path().join("few.csv");
    let head: String = text.lines().take(3).map(|l| format!("{l}\n")).collect();
    std::fs::write(&few, head).unwrap();
    refused(&args(&[few], &["--out", o]), "too few star measurements");
    // Errors understated 100 times: every star rejected.
    let tight: Vec<PathBuf> = files
        .iter()
        .map(|f| {
            let t = std::fs::read_to_string(f).unwrap().replace(",0.0005,0.0005,", ",0.000005,0.000005,");
            let p = f.with_extension("tight.csv");
            std::fs::write(&p, t).unwrap();
            p
        })
        .collect();
    let mut a = args(&tight, &["--out", o]);
    a.extend(offsets_args());
    refused(&a, "every one of the 120 stars was rejected");
    assert!(!Path::new(o).exists(), "a refused run wrote its output");
}
