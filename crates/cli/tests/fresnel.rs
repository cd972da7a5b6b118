//! End-to-end: `instpol fresnel` against closed forms written here from the textbook
//! (Born & Wolf 1.5; Macleod, single quarter-wave layer).

use std::process::Command;

fn run(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_instpol")).arg("fresnel").args(args).output().expect("run instpol")
}

fn json(args: &[&str]) -> serde_json::Value {
    let o = run(args);
    assert!(o.status.success(), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).expect("JSON on stdout")
}

#[test]
fn uncoated_glass_at_30_deg_sec_cause() {
    let v = json(&["--n-real", "1.5", "--aoi-deg", "30", "--json"]);
    let (n, i) = (1.5f64, 30f64.to_radians());
    let t = (i.sin() / n).asin();
    let k = n * t.cos() / i.cos();
    let ts = k * (2.0 * i.cos() / (i.cos() + n * t.cos())).powi(2);
    let tp = k * (2.0 * i.cos() / (n * i.cos() + t.cos())).powi(2);
    let get = |f: &str| v[f].as_f64().unwrap_or_else(|| panic!("missing {f}"));
    assert!((get("Ts") - ts).abs() < 1e-12 && (get("Tp") - tp).abs() < 1e-12);
    assert!((get("Ts") + get("Rs") - 1.0).abs() < 1e-12 && (get("Tp") + get("Rp") - 1.0).abs() < 1e-12);
    let d = (tp - ts) / (tp + ts);
    assert!((get("diattenuation") - d).abs() < 1e-12);
    assert!((d - 0.017).abs() < 5e-4, "sec:cause: about 1.7%, got {d}");
    assert!(get("retardance_deg").abs() < 1e-9);
}

#[test]
fn quarter_wave_mgf2_at_normal_incidence() {
    let d = 550.0 / (4.0 * 1.38);
    let v = json(&["--n-real", "1.52", "--aoi-deg", "0", "--coating", &format!("1.38:{d}"), "--json"]);
    let r = ((1.52 - 1.38f64.powi(2)) / (1.52 + 1.38f64.powi(2))).powi(2);
    assert!((v["Rs"].as_f64().unwrap() - r).abs() < 1e-12, "{v}");
    assert!(v["diattenuation"].as_f64().unwrap().abs() < 1e-15);
}

#[test]
fn bad_input_exits_2_with_a_named_error() {
    for (args, needle) in [
        (vec!["--n-real=-1.5", "--aoi-deg", "30"], "--n-real"),
        (vec!["--n-real", "1.5", "--aoi-deg", "90"], "--aoi-deg"),
        (vec!["--n-real", "1.5", "--aoi-deg", "10", "--coating", "1.38-99"], "--coating layer 1"),
        (vec!["--n-real", "1.5", "--aoi-deg", "10", "--coating", "1.38:99,x:3"], "--coating layer 2"),
    ] {
        let o = run(&args);
        assert_eq!(o.status.code(), Some(2), "{args:?}");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains("error") && e.contains(needle), "{args:?}: {e}");
    }
}
