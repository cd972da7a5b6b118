//! `instpol zero-angle --measured FILE`: standards measured in separate runs are
//! combined in one, and a grossly wrong standard is named and left out (leave-one-out: each
//! star against the weighted circular mean of the others).
//!
//! The rows are written here from a known zero angle (41.3 deg, IAU sense): measured chi =
//! catalogued chi - 41.3 deg plus small fixed errors, so the expected mean is the weighted
//! mean of the good rows' offsets, computed in the test.

use crate::common;

use common::run;
use std::path::Path;

const OFFSET: f64 = 41.3;

/// (label, catalogued chi, error added to the measured chi, measured sigma) of the good stars.
const GOOD: [(&str, f64, f64, f64); 3] = [("A", 15.0, 0.10, 0.20), ("B", 70.0, -0.15, 0.30), ("C", 125.0, 0.05, 0.25)];

fn csv_row(label: &str, chi_cat: f64, err: f64, sigma: f64) -> String {
    let chi_m = (chi_cat - OFFSET + err).rem_euclid(180.0);
    format!("{label},V,{chi_m},{sigma},{chi_cat},0.1\n")
}

const HEADER: &str = "label,filter,chi_measured_deg,sigma_chi_measured_deg,chi_catalogue_deg,sigma_chi_catalogue_deg\n";

fn zero_angle(files: &[&Path], extra: &[&str]) -> (i32, serde_json::Value, String) {
    let mut args: Vec<String> = vec!["zero-angle".into()];
    for f in files {
        args.push("--measured".into());
        args.push(f.display().to_string());
    }
    args.extend(extra.iter().map(|s| s.to_string()));
    args.push("--json".into());
    let (code, out, err) = run(&args);
    (code, serde_json::from_str(&out).unwrap_or(serde_json::Value::Null), err)
}

/// The weighted mean (weights 1 / (sigma_m^2 + sigma_c^2)) of the good rows' offsets, and its
/// error: the offsets lie within 0.3 deg, so the arithmetic mean equals the circular one to
/// 1e-6 deg.
fn expected() -> (f64, f64) {
    let (mut sw, mut s) = (0.0, 0.0);
    for &(_, _, err, sig) in &GOOD {
        let w = 1.0 / (sig * sig + 0.01);
        sw += w;
        s += w * (OFFSET - err);
    }
    (s / sw, sw.powf(-0.5))
}

#[test]
fn a_standard_80_deg_off_is_named_and_left_out() {
    let dir = tempfile::tempdir().unwrap();
    let mut text = HEADER.to_string();
    for &(l, c, e, s) in &GOOD {
        text += &csv_row(l, c, e, s);
    }
    // The wrong star: catalogued at 160 deg, but what was measured is a star at 80 deg.
    text += &csv_row("WRONG", 160.0, -80.0, 0.2);
    let f = dir.path().join("all.csv");
    std::fs::write(&f, text).unwrap();
    let (code, j, err) = zero_angle(&[&f], &[]);
    assert_eq!(code, 0, "{err}");
    let (want, sigma) = expected();
    let z = j["zero_angle_deg"].as_f64().unwrap();
    assert!((z - want).abs() < 1e-5, "{z} vs {want}: {j}");
    assert!((j["sigma_zero_angle_deg"].as_f64().unwrap() - sigma).abs() < 1e-9, "{j}");
    // Within its error of the truth.
    assert!((z - OFFSET).abs() < 2.0 * sigma, "{z} +- {sigma}");
    assert_eq!(j["outlier"], "WRONG", "{j}");
    assert_eq!(j["excluded"], serde_json::json!(["WRONG"]));
    assert_eq!(j["n_standards"], 3);
    assert_eq!(j["sense"], "iau", "{j}");
    let st = j["standards"].as_array().unwrap();
    assert!(st[3]["excluded"].as_bool().unwrap() && st[3]["pull"].as_f64().unwrap().abs() > 50.0, "{j}");
    assert!(st[..3].iter().all(|s| !s["excluded"].as_bool().unwrap() && s["pull"].as_f64().unwrap().abs() < 2.0));
    assert!(err.contains("WRONG") && err.contains("left out"), "{err}");
    assert_eq!(j["filter"], "V");
}

#[test]
fn two_files_give_the_result_of_one_file_with_both() {
    let dir = tempfile::tempdir().unwrap();
    // One file with every row.
    let mut all = HEADER.to_string();
    for &(l, c, e, s) in &GOOD {
        all += &csv_row(l, c, e, s);
    }
    let one = dir.path().join("all.csv");
    std::fs::write(&one, &all).unwrap();
    // The same rows split: A and B in the JSON form zero-angle --json writes (written out by
    // hand here), C in a table without a filter column.
    let row = |l: &str, c: f64, e: f64, s: f64| {
        serde_json::json!({"label": l, "x": 100.0, "y": 200.0, "chi_measured_deg": (c - OFFSET + e).rem_euclid(180.0),
            "sigma_chi_measured_deg": s, "chi_catalogue_deg": c, "sigma_chi_catalogue_deg": 0.1,
            "p_measured": 0.05, "sigma_p_measured": 0.001, "offset_deg": 0.0, "pull": 0.0})
    };
    let night1 = serde_json::json!({"filter": "V", "standards": [
        row(GOOD[0].0, GOOD[0].1, GOOD[0].2, GOOD[0].3), row(GOOD[1].0, GOOD[1].1, GOOD[1].2, GOOD[1].3)]});
    let j1 = dir.path().join("night1.json");
    std::fs::write(&j1, night1.to_string()).unwrap();
    let (l, c, e, s) = GOOD[2];
    let chi_m = (c - OFFSET + e).rem_euclid(180.0);
    let n2 = dir.path().join("night2.csv");
    std::fs::write(&n2, format!("label,chi_measured_deg,sigma_chi_measured_deg,chi_catalogue_deg,sigma_chi_catalogue_deg\n{l},{chi_m},{s},{c},0.1\n")).unwrap();

    let (code, a, err) = zero_angle(&[&one], &[]);
    assert_eq!(code, 0, "{err}");
    let (code, b, err) = zero_angle(&[&j1, &n2], &[]);
    assert_eq!(code, 0, "{err}");
    for k in ["zero_angle_deg", "sigma_zero_angle_deg", "sigma_scatter_zero_angle_deg", "chi2_dof"] {
        let (x, y) = (a[k].as_f64().unwrap(), b[k].as_f64().unwrap());
        assert!((x - y).abs() <= 1e-12 * x.abs().max(1.0), "{k}: {x} vs {y}");
    }
    for k in ["sense", "n_standards", "excluded", "filter", "instrument_file_line"] {
        assert_eq!(a[k], b[k], "{k}");
    }
    let (want, _) = expected();
    assert!((a["zero_angle_deg"].as_f64().unwrap() - want).abs() < 1e-5);
    // Each row says where it came from.
    assert_eq!(b["standards"][0]["source"], j1.display().to_string());
    assert_eq!(b["standards"][2]["source"], n2.display().to_string());
}

#[test]
fn bad_measured_files_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    // A value that is not a number: the file, the row and the column are named.
    let bad = dir.path().join("bad.csv");
    std::fs::write(&bad, format!("{HEADER}A,V,10,0.2,51.3,0.1\nB,V,ten,0.2,20,0.1\n")).unwrap();
    let (code, _, err) = zero_angle(&[&bad], &[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("bad.csv") && err.contains("row 2") && err.contains("chi_measured_deg"), "{err}");
    // A zero or negative measured error.
    let zero = dir.path().join("zero.csv");
    std::fs::write(&zero, format!("{HEADER}A,V,10,0,51.3,0.1\n")).unwrap();
    let (code, _, err) = zero_angle(&[&zero], &[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("zero.csv") && err.contains("row 1"), "{err}");
    // Two filters in one run.
    let v = dir.path().join("v.csv");
    std::fs::write(&v, format!("{HEADER}A,V,10,0.2,51.3,0.1\n")).unwrap();
    let r = dir.path().join("r.csv");
    std::fs::write(&r, format!("{HEADER}A,R,10,0.2,51.3,0.1\n")).unwrap();
    let (code, _, err) = zero_angle(&[&v, &r], &[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("r.csv") && err.contains("per filter"), "{err}");
    // No filter anywhere: asked for; given by --filter, accepted.
    let nf = dir.path().join("nf.csv");
    std::fs::write(
        &nf,
        "label,chi_measured_deg,sigma_chi_measured_deg,chi_catalogue_deg,sigma_chi_catalogue_deg\nA,10,0.2,51.3,0.1\n",
    )
    .unwrap();
    let (code, _, err) = zero_angle(&[&nf], &[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("--filter"), "{err}");
    let (code, j, err) = zero_angle(&[&nf], &["--filter", "V"]);
    assert_eq!(code, 0, "{err}");
    assert!((j["zero_angle_deg"].as_f64().unwrap() - 41.3).abs() < 1e-9, "{j}");
    // A JSON file that is not a zero-angle output.
    let nj = dir.path().join("other.json");
    std::fs::write(&nj, "{\"rows\": []}").unwrap();
    let (code, _, err) = zero_angle(&[&nj], &[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("other.json") && err.contains("standards"), "{err}");
    // Neither frames nor files.
    let (code, _, err) = run(&["zero-angle", "--json"]);
    assert_eq!(code, 2, "{err}");
}
