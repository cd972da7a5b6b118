//! Numbers of record: the JSON of `demo`, `stokes`, `catalog` (maskless), `validate`, `fit`,
//! `bias`, `fresnel`, `raytrace` and `mc` for fixed inputs and seeds, compared with the outputs
//! stored in `tests/record/` to 1e-12 relative.
//!
//! This is a guard for refactors, not a check of correctness (the other tests of each command
//! check their numbers against the paper, closed forms and independent implementations): a
//! change that moves code keeps every number, and this test says which one moved if it did not.
//! The stored files were written by the code before the instrument-chain refactor. After a
//! change that is meant to move a number, rewrite them with `INSTPOL_RECORD=1 cargo test -p
//! instpol --test it numbers_of_record::` and say in the commit which numbers moved and why.
//!
//! What is compared: every number and string of each JSON document, except the `provenance`
//! record (dates, command lines, hashes of files that hold dates), the Monte Carlo's wall time,
//! and the paths of the temporary directory and of the repository, written as `{OUT}` and
//! `{REPO}` (the record must hold in any clone).

use crate::common;

use serde_json::Value;
use std::path::{Path, PathBuf};

/// Relative tolerance of the comparison, and the absolute floor below which two numbers are
/// rounding noise about zero (a covariance of -5e-23 between two errors of 1e-3).
const REL: f64 = 1e-12;
const ABS: f64 = 1e-18;

/// Keys that are not numbers of record: the provenance record and the Monte Carlo's wall time.
/// The `product` of a catalog is what it is (instrument and input hashes, of files that hold
/// dates), not a number.
const VOLATILE: &[&str] = &["provenance", "product", "seconds", "trials_per_second"];

fn record_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/record")
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The JSON printed by `instpol ARGS` (which must succeed), with `provenance` removed and the
/// temporary directory's path replaced by `{OUT}`.
fn json_of(args: &[String], out: &Path) -> Value {
    let (code, stdout, stderr) = common::run(args);
    assert_eq!(code, 0, "instpol {args:?} failed: {stderr}");
    let mut v: Value = serde_json::from_str(&stdout).unwrap_or_else(|e| panic!("instpol {args:?}: not JSON ({e})"));
    normalize(&mut v, &out.display().to_string(), "{OUT}");
    normalize(&mut v, &repo().display().to_string(), "{REPO}");
    v
}

/// `v` without its volatile keys, with every occurrence of the path `path` written `name`.
fn normalize(v: &mut Value, path: &str, name: &str) {
    match v {
        Value::Object(m) => {
            for k in VOLATILE {
                m.remove(*k);
            }
            m.values_mut().for_each(|x| normalize(x, path, name));
        }
        Value::Array(a) => a.iter_mut().for_each(|x| normalize(x, path, name)),
        Value::String(s) if s.contains(path) => *s = s.replace(path, name),
        _ => {}
    }
}

/// Every difference between `got` and `want` beyond the tolerance, as `path: got vs want`.
fn differences(got: &Value, want: &Value, path: &str, out: &mut Vec<String>) {
    match (got, want) {
        (Value::Number(a), Value::Number(b)) => {
            let (a, b) = (a.as_f64().unwrap(), b.as_f64().unwrap());
            if (a - b).abs() > REL * a.abs().max(b.abs()) + ABS {
                out.push(format!("{path}: {a:e} vs recorded {b:e} (relative {:.1e})", (a - b).abs() / b.abs()));
            }
        }
        (Value::Object(a), Value::Object(b)) => {
            for (k, wb) in b {
                match a.get(k) {
                    Some(ga) => differences(ga, wb, &format!("{path}.{k}"), out),
                    None => out.push(format!("{path}.{k}: missing (recorded {wb})")),
                }
            }
            for k in a.keys().filter(|k| !b.contains_key(*k)) {
                out.push(format!("{path}.{k}: not in the record"));
            }
        }
        (Value::Array(a), Value::Array(b)) if a.len() == b.len() => {
            for (i, (ga, wb)) in a.iter().zip(b).enumerate() {
                differences(ga, wb, &format!("{path}[{i}]"), out);
            }
        }
        (a, b) if a == b => {}
        (a, b) => out.push(format!("{path}: {a} vs recorded {b}")),
    }
}

/// Compare one command's JSON with its record (or write the record under `INSTPOL_RECORD=1`).
fn check(name: &str, got: &Value, failures: &mut Vec<String>) {
    let path = record_dir().join(format!("{name}.json"));
    if std::env::var_os("INSTPOL_RECORD").is_some() {
        std::fs::create_dir_all(record_dir()).unwrap();
        std::fs::write(&path, serde_json::to_string_pretty(got).unwrap() + "\n").unwrap();
        return;
    }
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let want: Value = serde_json::from_str(&text).unwrap();
    let mut diff = vec![];
    differences(got, &want, name, &mut diff);
    failures.extend(diff);
}

fn s(v: &[&str]) -> Vec<String> {
    v.iter().map(|x| x.to_string()).collect()
}

#[test]
fn numbers_of_record() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().to_path_buf();
    let o = |p: &str| out.join(p).display().to_string();
    let r = |p: &str| repo().join(p).display().to_string();
    let mut failures = vec![];

    // The main job without frames (the frame chain takes minutes in a test build): the three
    // fields, their fits, the wavelength law and the corner standard.
    let demo = json_of(&s(&["demo", "--no-frames", "--json", "--out", &o("demo")]), &out);
    check("demo", &demo, &mut failures);

    for (name, input) in [("stokes_n16", "tests/data/fors1_v_star_n16.csv"), ("stokes_n4", "tests/data/example_n4.csv")]
    {
        let j = json_of(&s(&["stokes", "--input", &r(input), "--json"]), &out);
        check(name, &j, &mut failures);
    }

    // Maskless calcite frames of the shipped scene (seed 7), every star measured.
    json_of(&s(&["simulate", &r("instruments/scenes/calcite_stars.toml"), "--out", &o("calcite"), "--json"]), &out);
    let frames: Vec<String> = common::fits_in(&out.join("calcite")).iter().map(|p| p.display().to_string()).collect();
    let mut a =
        s(&["catalog", "--instrument", "calcite", "--hwp-angles", "0,22.5,45,67.5,90,112.5,135,157.5", "--json"]);
    a.extend(frames);
    check("catalog_calcite", &json_of(&a, &out), &mut failures);

    // The shipped corner standard (seed 104) against the demo's V calibration.
    json_of(&s(&["simulate", &r("instruments/scenes/standard_V_corner.toml"), "--out", &o("std"), "--json"]), &out);
    let frames: Vec<String> = common::fits_in(&out.join("std")).iter().map(|p| p.display().to_string()).collect();
    let mut a = s(&["validate", "--cal", &o("demo/cal_V.fits"), "--x", "1900", "--y", "90", "--json"]);
    a.extend(frames);
    check("validate_corner", &json_of(&a, &out), &mut failures);

    // Refits of the demo's calibrations: fixed centre, and the asymmetric B field with a free one.
    check("fit_v", &json_of(&s(&["fit", &o("demo/cal_V.fits"), "--json"]), &out), &mut failures);
    check("fit_b_free", &json_of(&s(&["fit", &o("demo/cal_B.fits"), "--free-centre", "--json"]), &out), &mut failures);

    for (name, p, sigma) in [("bias_snr3", "0.01", "0.003"), ("bias_snr1", "0.002", "0.002")] {
        check(name, &json_of(&s(&["bias", "--p", p, "--sigma", sigma, "--json"]), &out), &mut failures);
    }

    check(
        "fresnel_coated",
        &json_of(
            &s(&[
                "fresnel",
                "--n-real",
                "1.52",
                "--aoi-deg",
                "30",
                "--wavelength-nm",
                "550",
                "--coating",
                "1.38:81.52",
                "--json",
            ]),
            &out,
        ),
        &mut failures,
    );
    check(
        "fresnel_aluminium",
        &json_of(&s(&["fresnel", "--metal", "aluminium", "--aoi-deg", "45", "--coating", "1.77:5", "--json"]), &out),
        &mut failures,
    );

    check(
        "raytrace_fors1_v",
        &json_of(&s(&["raytrace", "--instrument", "fors1", "--filter", "V", "--json"]), &out),
        &mut failures,
    );

    for (name, noise) in [("mc_poisson", "poisson"), ("mc_gauss_qu", "gauss-qu")] {
        let a = s(&["mc", "--trials", "20000", "--noise", noise, "--seed", "11", "--threads", "2", "--json"]);
        check(name, &json_of(&a, &out), &mut failures);
    }

    assert!(
        failures.is_empty(),
        "{} numbers differ from the record (tests/record/; see this file's doc):\n{}",
        failures.len(),
        failures.join("\n")
    );
}
