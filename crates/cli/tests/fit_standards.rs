//! End-to-end: `instpol fit-standards` on a synthetic CSV made here from the closed form of an
//! aluminium M3 (Born & Wolf 14.2) turned by the parallactic angle, on the real EFOSC2 files
//! when present, and on bad input.

use std::process::Command;

fn run(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_instpol")).arg("fit-standards").args(args).output().expect("run instpol")
}

/// (Rs - Rp) / (Rs + Rp) at 45 deg for N = n + i k, in real arithmetic.
fn p45(n: f64, k: f64) -> f64 {
    let (er, ei) = (n * n - k * k - 0.5, 2.0 * n * k);
    let m = (er * er + ei * ei).sqrt();
    let (a, b) = (((m + er) / 2.0).sqrt(), ((m - er) / 2.0).sqrt());
    let c = 0.5f64.sqrt();
    let rs = ((c - a).powi(2) + b * b) / ((c + a).powi(2) + b * b);
    let (pr, pi) = ((n * n - k * k) * c, 2.0 * n * k * c);
    let rp = ((pr - a).powi(2) + (pi - b).powi(2)) / ((pr + a).powi(2) + (pi + b).powi(2));
    (rs - rp) / (rs + rp)
}

#[test]
fn synthetic_csv_recovers_factor_and_offset() {
    let dir = tempfile::tempdir().unwrap();
    // A flat table: n = 1, k = 6.5 at every wavelength.
    let table = dir.path().join("metal.txt");
    std::fs::write(&table, "lambda,n,k\n0.3,1.0,6.5\n0.9,1.0,6.5\n").unwrap();
    let (f, off) = (0.9, 25.0f64);
    let p = p45(f * 1.0, f * 6.5);
    let mut csv = String::from("filter,star,pa_deg,q,sigma_q,u,sigma_u,wavelength_um\n");
    for i in 0..12 {
        let pa = -165.0 + 30.0 * i as f64;
        let a = 2.0 * (off - pa).to_radians();
        csv += &format!("V,S{i},{pa},{},0.001,{},0.001,0.55\n", p * a.cos(), -p * a.sin());
    }
    let data = dir.path().join("std.csv");
    std::fs::write(&data, csv).unwrap();
    let plots = dir.path().join("plots");
    let o = run(&[
        data.to_str().unwrap(),
        "--model",
        "wiersema",
        "--metal",
        table.to_str().unwrap(),
        "--plot-dir",
        plots.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let params = &v[0]["params"];
    assert_eq!(params[0]["name"], "factor");
    assert!((params[0]["value"].as_f64().unwrap() - f).abs() < 1e-6, "{v}");
    assert_eq!(params[1]["unit"], "deg");
    assert!((params[1]["value"].as_f64().unwrap() - off).abs() < 1e-5, "{v}");
    assert!(v[0]["chi2"].as_f64().unwrap() < 1e-6);
    assert!(plots.join("standards_wiersema_V.png").is_file());
}

#[test]
fn real_efosc2_files_fit_in_every_band() {
    let d = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/efosc2-standards");
    if !d.is_dir() {
        eprintln!("\n*** SKIPPED: {} not found ***\n", d.display());
        return;
    }
    let files: Vec<String> = ["pu", "pb", "pv", "pr", "pi"]
        .iter()
        .map(|b| d.join(format!("{b}_standards.txt")).display().to_string())
        .collect();
    let mut args: Vec<&str> = files.iter().map(String::as_str).collect();
    args.extend(["--joint", "--json"]);
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    // 5 bands x 2 models + 2 joint fits.
    assert_eq!(v.as_array().unwrap().len(), 12);
    for f in v.as_array().unwrap() {
        assert!(f["chi2_dof"].as_f64().unwrap().is_finite());
        assert!(f["rms_q"].as_f64().unwrap() < 0.01, "{f}");
    }
}

#[test]
fn bad_input_is_named_and_help_has_an_example() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.txt");
    std::fs::write(&bad, "A, 10, 0.01, 0.001, 0.0, 0.001, 0.55\nB, x, 0.01, 0.001, 0.0, 0.001, 0.55\n").unwrap();
    let o = run(&[bad.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("bad.txt") && e.contains("line 2, column 2"), "{e}");
    let o = run(&[bad.to_str().unwrap(), "--model", "fancy"]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("--model"));
    let h = Command::new(env!("CARGO_BIN_EXE_instpol")).args(["fit-standards", "--help"]).output().unwrap();
    assert!(String::from_utf8_lossy(&h.stdout)
        .contains("instpol fit-standards ../shared/data/efosc2-standards/p?_standards.txt"));
}
