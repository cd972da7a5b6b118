//! End-to-end: `instpol raytrace` on the FORS1-like prescription.

use std::process::Command;

fn run(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_instpol")).arg("raytrace").args(args).output().expect("run instpol")
}

#[test]
fn json_contract_and_physics() {
    let dir = tempfile::tempdir().unwrap();
    let field = dir.path().join("field.json");
    let png = dir.path().join("p.png");
    let o = run(&[
        "--instrument",
        "fors1",
        "--filter",
        "V",
        "--field-points",
        "7",
        "--pupil-rays",
        "64",
        "--json",
        "--field-out",
        field.to_str().unwrap(),
        "--plot",
        png.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let arr = |k: &str| -> Vec<f64> {
        v[k].as_array().unwrap_or_else(|| panic!("missing {k}")).iter().map(|x| x.as_f64().unwrap()).collect()
    };
    let (r, p, phi) = (arr("radius_arcmin"), arr("p"), arr("phi_deg"));
    assert_eq!(r.len(), 7);
    assert_eq!(p.len(), 7);
    assert_eq!(phi.len(), 7);
    // Zero on the axis, growing outwards, radial along the 45 deg diagonal.
    assert!(p[0] < 1e-12);
    assert!(p.windows(2).all(|w| w[1] > w[0]));
    for (x, f) in phi.iter().zip(&p).skip(1) {
        assert!((x - 45.0).abs() < 0.1, "phi {x} at p {f}");
    }
    let per = v["per_surface"].as_array().unwrap();
    assert!(per.len() >= 5 && per.iter().all(|s| s["surface"].is_string() && s["p_at_edge"].as_f64().unwrap() >= 0.0));
    let b = v["wavelength_law"]["b"].as_f64().unwrap();
    let a = v["wavelength_law"]["a"].as_f64().unwrap();
    // Same sign of slope as the paper's 0.02 + 1.73e-3 lambda, and a + 550 b ~ 1.
    assert!(b > 0.0 && (a + 550.0 * b - 1.0).abs() < 0.1, "a {a} b {b}");
    // The field file is the documented format and matches the profile.
    let ff: serde_json::Value = serde_json::from_slice(&std::fs::read(&field).unwrap()).unwrap();
    assert_eq!(ff["format"], "instpol-field-v1");
    assert_eq!(ff["p"].as_array().unwrap().len(), 7);
    assert!(std::fs::metadata(&png).unwrap().len() > 1000);
}

#[test]
fn bad_input_exits_2() {
    for (args, needle) in [
        (vec!["--instrument", "nosuch"], "nosuch"),
        (vec!["--filter", "Z"], "Z"),
        (vec!["--wavelength-nm", "5"], "--wavelength-nm"),
        (vec!["--field-points", "2"], "--field-points"),
    ] {
        let o = run(&args);
        assert_eq!(o.status.code(), Some(2), "{args:?}");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains("error") && e.contains(needle), "{args:?}: {e}");
    }
}
