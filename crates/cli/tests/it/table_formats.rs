//! Catalog formats and provenance through the CLI: `instpol correct` reads a catalog in CSV,
//! ECSV and VOTable and writes each format (the corrected numbers identical whatever the
//! formats: all go through `skyfield::table` and the one `Corrector`); unknown extensions
//! refused with exit 2 and nothing written; the `--json` provenance hashes the inputs as
//! `b3sum` (the BLAKE3 team's tool, or Python's `blake3` package) does.

use crate::common;

use std::path::Path;

fn run(args: &[&str]) -> std::process::Output {
    common::instpol().args(args).output().unwrap()
}

/// A FORS1 V calibration and a small catalog (arcmin positions) in every text format.
fn setup(dir: &Path) -> (String, String) {
    let cal = common::fors1_radial_calibration("V", common::V_COEFFS);
    let calp = dir.join("v.fits");
    cal.save(&calp).unwrap();
    let mut csv = String::from("id,x,y,q,u,sigma_q,sigma_u,name\n");
    for k in 0..12 {
        let (x, y) = (-3.0 + 0.5 * k as f64, 2.5 - 0.4 * k as f64);
        csv.push_str(&format!("{k},{x},{y},{},{},0.001,0.0012,star {k}\n", 0.01 - 0.001 * k as f64, 0.003));
    }
    let p = dir.join("cat.csv");
    std::fs::write(&p, csv).unwrap();
    (calp.to_str().unwrap().into(), p.to_str().unwrap().into())
}

fn q0_of(path: &Path) -> Vec<f64> {
    let t = skyfield::table::Table::read(path, None).unwrap();
    t.numbers("q0", path).unwrap()
}

#[test]
fn every_format_in_and_out_gives_the_same_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let (cal, cat) = setup(dir.path());
    let d = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let o = run(&["correct", "--cal", &cal, "--in", &cat, "--out", &d("a.csv")]);
    assert_eq!(o.status.code(), Some(0), "{}", String::from_utf8_lossy(&o.stderr));
    let reference = q0_of(&dir.path().join("a.csv"));
    assert_eq!(reference.len(), 12);
    // The same catalog written as ECSV, VOTable and FITS gives the same q0 to the last bit.
    for (i, ext) in ["ecsv", "vot", "fits"].iter().enumerate() {
        let out = d(&format!("b{i}.{ext}"));
        let o = run(&["correct", "--cal", &cal, "--in", &cat, "--out", &out]);
        assert_eq!(o.status.code(), Some(0), "{}", String::from_utf8_lossy(&o.stderr));
        let q0 = q0_of(Path::new(&out));
        assert_eq!(q0, reference, "{ext}");
        // The output read back as the input of another correction keeps its columns: the
        // added ones clash (refused by name), which proves they were read from this format.
        let o = run(&["correct", "--cal", &cal, "--in", &out, "--out", &d(&format!("c{i}.csv"))]);
        assert_eq!(o.status.code(), Some(2));
        assert!(String::from_utf8_lossy(&o.stderr).contains("'q0' would be overwritten"));
    }
    // The text column survives ECSV and VOTable with its blank.
    let t = skyfield::table::Table::read(&dir.path().join("b0.ecsv"), None).unwrap();
    assert_eq!(
        t.column("name").unwrap().data,
        skyfield::table::Data::Str((0..12).map(|k| format!("star {k}")).collect())
    );
    let t = skyfield::table::Table::read(&dir.path().join("b1.vot"), None).unwrap();
    assert_eq!(t.column("chi0_deg").unwrap().unit.as_deref(), Some("deg"));
}

#[test]
fn unknown_extensions_are_refused_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let (cal, cat) = setup(dir.path());
    let out = dir.path().join("out.parquet");
    let o = run(&["correct", "--cal", &cal, "--in", &cat, "--out", out.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("out.parquet") && err.contains("unknown table format") && err.contains(".ecsv"), "{err}");
    assert!(!out.exists());
    let txt = dir.path().join("cat.txt");
    std::fs::copy(&cat, &txt).unwrap();
    let o = run(&["correct", "--cal", &cal, "--in", txt.to_str().unwrap(), "--out", &format!("{}.csv", txt.display())]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("cat.txt") && err.contains("unknown table format"), "{err}");
}

#[test]
fn json_provenance_hashes_inputs_as_b3sum_does() {
    let dir = tempfile::tempdir().unwrap();
    let (cal, cat) = setup(dir.path());
    let out = dir.path().join("o.csv");
    let o = run(&["correct", "--cal", &cal, "--in", &cat, "--out", out.to_str().unwrap(), "--json"]);
    assert_eq!(o.status.code(), Some(0), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let p = &j["provenance"];
    assert_eq!(p["program"], "instpol");
    assert_eq!(p["version"], env!("CARGO_PKG_VERSION"));
    assert!(p["command_line"].as_str().unwrap().contains(" correct --cal "));
    let inputs = p["inputs"].as_array().unwrap();
    common::assert_inputs_hashed_as_b3sum(inputs, &[&cal, &cat]);
}
