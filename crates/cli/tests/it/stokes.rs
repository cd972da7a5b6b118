//! End-to-end tests of `instpol stokes`: the binary on the shipped example inputs (made by
//! `cargo run -p instpol-stokes --example make_example_data` with the mueller forward model; their
//! true parameters are in the files' comment lines) and on bad input.

use serde_json::Value;
use std::path::PathBuf;
use std::process::{Command, Output};

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data").join(name)
}

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_instpol")).args(args).output().expect("run instpol")
}

fn json(args: &[&str]) -> Value {
    let mut a = vec!["stokes"];
    a.extend_from_slice(args);
    a.push("--json");
    let o = run(&a);
    assert!(o.status.success(), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).expect("valid JSON")
}

fn f(v: &Value, k: &str) -> f64 {
    v[k].as_f64().unwrap_or_else(|| panic!("field {k} is not a number: {}", v[k]))
}

/// The FORS1-like N = 16 star of fig:fourier: unpolarized star, 0.4% instrumental
/// polarization at 20 deg, kappa = 4e-3 (t = 0.502), SNR 1600. Every recovered number is
/// within 3 sigma of the truth, and the errors are eq:sigp / eq:fourcoeff's.
#[test]
fn fors1_n16_recovers_the_generator() {
    let v = json(&["--input", data("fors1_v_star_n16.csv").to_str().unwrap()]);
    assert_eq!(v["n_hwp"], 16);
    let sp = f(&v, "sigma_p");
    // eq:sigp at SNR 1600, N = 16 (to O(P^2) and the SNR scatter of the noisy counts).
    assert!((sp - 1.0 / (8f64.sqrt() * 1600.0)).abs() < 0.01 * sp, "sigma_p = {sp}");
    assert!((f(&v, "p") - 0.004).abs() < 3.0 * sp, "p = {}", f(&v, "p"));
    let chi = f(&v, "chi_deg");
    assert!((0.0..180.0).contains(&chi));
    assert!((chi - 20.0).abs() < 3.0 * f(&v, "sigma_chi_deg"), "chi = {chi}");
    // q, u are fractions and agree with p, chi.
    assert!((f(&v, "q").hypot(f(&v, "u")) - f(&v, "p")).abs() < 1e-15);
    // a0 ~ kappa (eq:a0), error sigma_F/sqrt(N) ~ 1.6e-4.
    assert!((f(&v, "a0") - 0.004).abs() < 3.0 * 6.25e-4 / 4.0, "a0 = {}", f(&v, "a0"));
    let kappa = v["kappa"].as_array().unwrap();
    assert_eq!(kappa.len(), 14, "kappa_j for j = 1..N-2");
    assert!((f(&v, "mean_kappa") - 0.004).abs() < 5e-4);
    let four = v["fourier"].as_array().unwrap();
    assert_eq!(four.len(), 9, "harmonics 0..N/2");
    for (k, h) in four.iter().enumerate() {
        assert_eq!(h["k"], k);
        for key in ["a", "b", "sigma_a", "sigma_b"] {
            assert!(h[key].is_f64(), "fourier[{k}].{key}");
        }
    }
    // a_4 = Q/I, b_4 = U/I; b_8 = 0 (Nyquist); sigma_a_k = sqrt(2/N)/SNR for 0 < k < 8.
    assert!((f(&four[4], "a") - f(&v, "q")).abs() < 1e-15);
    assert!((f(&four[4], "b") - f(&v, "u")).abs() < 1e-15);
    assert_eq!(f(&four[8], "b"), 0.0);
    let sa = f(&four[1], "sigma_a");
    assert!((sa - (2.0f64 / 16.0).sqrt() / 1600.0).abs() < 0.01 * sa);
    assert!(v["warnings"].is_array());
}

/// example_n4.csv: 2% at 40 deg, t = 0.51, explicit per-beam errors; and --kappa removes a0.
#[test]
fn example_n4_and_kappa_correction() {
    let path = data("example_n4.csv");
    let v = json(&["--input", path.to_str().unwrap()]);
    assert_eq!(v["n_hwp"], 4);
    let sp = f(&v, "sigma_p");
    assert!((f(&v, "p") - 0.02).abs() < 3.0 * sp);
    assert!((f(&v, "chi_deg") - 40.0).abs() < 3.0 * f(&v, "sigma_chi_deg"));
    assert_eq!(v["kappa"].as_array().unwrap().len(), 2);
    assert!((f(&v, "mean_kappa") - 0.02).abs() < 3.0 * 1e-3);
    assert_eq!(v["fourier"].as_array().unwrap().len(), 3);
    // Correcting for the measured kappa leaves a0 ~ 0 (exactly the mean of two pairs' F).
    let km = f(&v, "mean_kappa").to_string();
    let c = json(&["--input", path.to_str().unwrap(), "--kappa", &km]);
    assert!(f(&c, "a0").abs() < 1e-4, "a0 after correction = {}", f(&c, "a0"));
    assert!((f(&c, "p") - f(&v, "p")).abs() < 1e-4);
    // --kappa-from-data does both runs in one: the same kappa applied (stated in the output),
    // the same result as the second run above to rounding of the printed kappa.
    let one = json(&["--input", path.to_str().unwrap(), "--kappa-from-data"]);
    assert!((f(&one, "kappa_correction") - f(&v, "mean_kappa")).abs() < 1e-15);
    for k in ["q", "u", "p", "a0"] {
        assert!((f(&one, k) - f(&c, k)).abs() < 1e-12, "{k}: {} vs {}", f(&one, k), f(&c, k));
    }
    let o = run(&["stokes", "--input", path.to_str().unwrap(), "--kappa-from-data"]);
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(t.contains("estimated from these data"), "{t}");
    // Both at once is a usage error; two angles cannot give kappa.
    let o = run(&["stokes", "--input", path.to_str().unwrap(), "--kappa-from-data", "--kappa", "0.01"]);
    assert_eq!(o.status.code(), Some(2));
    let d = tempfile::tempdir().unwrap();
    let two = write(&d, "two.csv", "hwp_deg,f_o,f_e\n0,510,490\n22.5,500,500\n");
    let o = run(&["stokes", "--input", &two, "--kappa-from-data"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("kappa cannot be estimated") && e.contains("N >= 4"), "{e}");
}

#[test]
fn table_output_is_readable() {
    let o = run(&["stokes", "--input", data("fors1_v_star_n16.csv").to_str().unwrap()]);
    assert!(o.status.success());
    let s = String::from_utf8(o.stdout).unwrap();
    for needle in ["P ", " %", "chi", "deg", "kappa", "Harmonics", "#"] {
        assert!(s.contains(needle), "table lacks {needle:?}:\n{s}");
    }
}

fn write(dir: &tempfile::TempDir, name: &str, text: &str) -> String {
    let p = dir.path().join(name);
    std::fs::write(&p, text).unwrap();
    p.to_str().unwrap().to_string()
}

/// Runs on `text`, expects exit code 2, an `error:` line containing every `needles`, no panic.
fn bad(text: &str, needles: &[&str]) {
    let dir = tempfile::tempdir().unwrap();
    let p = write(&dir, "in.csv", text);
    let o = run(&["stokes", "--input", &p]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "stderr: {err}");
    assert!(err.starts_with("error: "), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    for n in needles {
        assert!(err.contains(n), "{err:?} lacks {n:?}");
    }
    assert!(o.stdout.is_empty());
}

#[test]
fn bad_input_names_the_problem() {
    bad("hwp_deg,f_o\n0,1\n22.5,2\n", &["missing column 'f_e'"]);
    bad("hwp_deg,f_o,f_e\n0,1,1\n22.5,abc,1\n", &["row 2", "f_o", "'abc' is not a number"]);
    bad("hwp_deg,f_o,f_e\n0,1,1\n22.5,1,1\n45,-3,1\n67.5,1,1\n", &["row 3", "not positive"]);
    bad("hwp_deg,f_o,f_e\n0,1,1\n22.5,0,0\n", &["row 2", "not positive"]);
    bad("hwp_deg,f_o,f_e\n0,1,1\n", &["at least 2 HWP angles", "found 1"]);
    bad("hwp_deg,f_o,f_e\n", &["at least 2 HWP angles", "found 0"]);
    bad("hwp_deg,f_o,f_e,sigma_o\n0,1,1,1\n22.5,1,1,1\n", &["sigma_o", "without 'sigma_e'"]);
    bad("hwp_deg,f_o,f_e,sigma_o,sigma_e\n0,1,1,1,-1\n22.5,1,1,1,1\n", &["row 1", "sigma_E"]);
    bad("hwp_deg,f_o,f_e\n0,1,1\n22.5,nan,1\n", &["row 2", "f_o", "not a finite number"]);
    bad("", &["missing column 'hwp_deg'"]);
}

#[test]
fn missing_file_and_bad_kappa() {
    let o = run(&["stokes", "--input", "/nonexistent/x.csv"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("/nonexistent/x.csv"));
    let o = run(&["stokes", "--input", data("example_n4.csv").to_str().unwrap(), "--kappa", "1"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("kappa"));
}

/// Any column order, extra columns ignored; P = 0 gives sigma_chi_deg null, chi flagged;
/// N = 2 warns; kappa empty and kappa_mean null when N < 4.
#[test]
fn column_order_p_zero_and_n2() {
    let dir = tempfile::tempdir().unwrap();
    let p =
        write(&dir, "z.csv", "f_e,comment,f_o,hwp_deg\n500,a,500,0\n500,b,500,22.5\n500,c,500,45\n500,d,500,67.5\n");
    let v = json(&["--input", &p]);
    assert_eq!(f(&v, "p"), 0.0);
    assert!(v["sigma_chi_deg"].is_null());
    assert_eq!(v["chi_defined"], false);
    assert!(v["warnings"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().contains("undefined")));
    // Poisson: sigma_P = 1/(sqrt(N/2) sqrt(1000)).
    assert!((f(&v, "sigma_p") - 1.0 / (2f64.sqrt() * 1000f64.sqrt())).abs() < 1e-12);

    let p = write(&dir, "n2.csv", "hwp_deg,f_o,f_e\n0,510,490\n22.5,500,500\n");
    let v = json(&["--input", &p]);
    assert_eq!(v["n_hwp"], 2);
    assert!((f(&v, "q") - 0.02).abs() < 1e-15 && f(&v, "u").abs() < 1e-15);
    assert!(v["kappa"].as_array().unwrap().is_empty());
    assert!(v["mean_kappa"].is_null());
    assert!(v["fourier"].as_array().unwrap().is_empty());
    assert!(v["warnings"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().contains("N = 2")));
}

/// Repeated exposures: two cycles of 8 positions, the second at theta + 360
/// deg (the same plate positions), are combined, not refused: the result is the reduction of
/// the summed fluxes (summed here, in the test), and every exposure's pull about its
/// position's mean is reported. One exposure with 3 % more flux in the o beam is flagged, with
/// the pull of two equal-error exposures computed here: (F_1 - F_2) / (sqrt(2) sigma_F).
#[test]
fn repeated_exposures_are_combined_and_outliers_flagged() {
    let d = tempfile::tempdir().unwrap();
    let (q, u) = (0.03, -0.01);
    let mut rows = vec![];
    for cycle in 0..2 {
        for i in 0..8 {
            let th = (i as f64 * 22.5_f64).to_radians();
            let m = q * (4.0 * th).cos() + u * (4.0 * th).sin();
            let (mut o, e) = (5e5 * (1.0 + m), 5e5 * (1.0 - m));
            if cycle == 1 && i == 3 {
                o *= 1.03;
            }
            rows.push((i as f64 * 22.5 + 360.0 * cycle as f64, o.round(), e.round()));
        }
    }
    let text: String = rows.iter().map(|(a, o, e)| format!("{a},{o},{e}\n")).collect();
    let both = write(&d, "both.csv", &format!("hwp_deg,f_o,f_e\n{text}"));
    let summed: String = (0..8)
        .map(|i| format!("{},{},{}\n", rows[i].0, rows[i].1 + rows[i + 8].1, rows[i].2 + rows[i + 8].2))
        .collect();
    let sum = write(&d, "sum.csv", &format!("hwp_deg,f_o,f_e\n{summed}"));
    let v = json(&["--input", &both]);
    let w = json(&["--input", &sum]);
    assert_eq!(v["n_hwp"], 8);
    for k in ["q", "u", "sigma_q", "sigma_u", "p"] {
        assert_eq!(f(&v, k), f(&w, k), "{k}");
    }
    let ex = v["exposures"].as_array().unwrap();
    assert_eq!(ex.len(), 16);
    let fj = |o: f64, e: f64| (o - e) / (o + e);
    let sig = |o: f64, e: f64| 2.0 * (o * e * e + e * o * o).sqrt() / (o + e).powi(2);
    for (k, x) in ex.iter().enumerate() {
        let i = k % 8;
        let (a, b) = (rows[i], rows[i + 8]);
        let s = sig(a.1, a.2).hypot(sig(b.1, b.2)) / 2f64.sqrt();
        let mut want = (fj(a.1, a.2) - fj(b.1, b.2)) / (2f64.sqrt() * s);
        if k >= 8 {
            want = -want;
        }
        // Equal errors to 1e-3 here, so the equal-error pull holds to that.
        assert!((x["pull"].as_f64().unwrap() - want).abs() < 1e-2 * want.abs().max(1.0), "{x} vs {want}");
        assert_eq!(x["outlier"].as_bool().unwrap(), i == 3, "{x}");
    }
    let o = run(&["stokes", "--input", &both]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("16 exposures combined into 8 HWP positions") && e.contains("row 12") && e.contains("outlier"),
        "{e}"
    );
}
