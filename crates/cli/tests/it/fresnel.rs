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
    assert!((get("t_s") - ts).abs() < 1e-12 && (get("t_p") - tp).abs() < 1e-12);
    assert!((get("t_s") + get("r_s") - 1.0).abs() < 1e-12 && (get("t_p") + get("r_p") - 1.0).abs() < 1e-12);
    let d = (tp - ts) / (tp + ts);
    assert!((get("transmission_diattenuation") - d).abs() < 1e-12);
    assert!((d - 0.017).abs() < 5e-4, "sec:cause: about 1.7%, got {d}");
    assert!(get("retardance_deg").abs() < 1e-9);
}

#[test]
fn quarter_wave_mgf2_at_normal_incidence() {
    let d = 550.0 / (4.0 * 1.38);
    let v = json(&["--n-real", "1.52", "--aoi-deg", "0", "--coating", &format!("1.38:{d}"), "--json"]);
    let r = ((1.52 - 1.38f64.powi(2)) / (1.52 + 1.38f64.powi(2))).powi(2);
    assert!((v["r_s"].as_f64().unwrap() - r).abs() < 1e-12, "{v}");
    assert!(v["transmission_diattenuation"].as_f64().unwrap().abs() < 1e-15);
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

/// The row of a `lambda,n,k` table at `lambda` (micron), read here without instpol.
fn table_row(file: &str, lambda: &str) -> (f64, f64) {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/metals").join(file);
    let text = std::fs::read_to_string(&p).expect("shipped table");
    let line = text.lines().find(|l| l.starts_with(&format!("{lambda},"))).expect("row");
    let v: Vec<f64> = line.split(',').map(|x| x.trim().parse().unwrap()).collect();
    (v[1], v[2])
}

#[test]
fn aluminium_mirror_at_45_deg_reflection_output() {
    let v = json(&["--metal", "aluminium", "--aoi-deg", "45", "--wavelength-nm", "550", "--json"]);
    let (n, k) = table_row("aluminium.txt", "0.550");
    // Born & Wolf 14.2: n cos t = sqrt(N^2 - sin^2 i), complex arithmetic by hand.
    let (er, ei) = (n * n - k * k - 0.5, 2.0 * n * k); // N^2 - sin^2(45)
    let m = (er * er + ei * ei).sqrt();
    let (a, b) = (((m + er) / 2.0).sqrt(), ((m - er) / 2.0).sqrt()); // sqrt: a + i b
    let c = 0.5f64.sqrt();
    let rs = ((c - a).powi(2) + b * b) / ((c + a).powi(2) + b * b);
    // r_p = (N^2 c - w) / (N^2 c + w), N^2 = (n^2 - k^2) + 2nk i, w = a + i b.
    let (pr, pi) = ((n * n - k * k) * c, 2.0 * n * k * c);
    let rp = ((pr - a).powi(2) + (pi - b).powi(2)) / ((pr + a).powi(2) + (pi + b).powi(2));
    let get = |f: &str| v[f].as_f64().unwrap_or_else(|| panic!("missing {f}: {v}"));
    assert!((get("r_s") - rs).abs() < 1e-12 && (get("r_p") - rp).abs() < 1e-12, "{v}");
    assert!((get("reflection_polarization") - (rs - rp) / (rs + rp)).abs() < 1e-12);
    assert!((0.025..0.045).contains(&get("reflection_polarization")), "{v}");
    assert!((get("index_imag") - k).abs() < 1e-12);
    // The table labels which diattenuation is which.
    let o = run(&["--metal", "aluminium", "--aoi-deg", "45"]);
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(t.contains("transmission diattenuation") && t.contains("reflection polarization (Rs-Rp)/(Rs+Rp)"), "{t}");
}

#[test]
fn absorbing_layer_is_accepted_and_thin_is_invisible() {
    let bare = json(&["--n-real", "0.96", "--n-imag", "6.69", "--aoi-deg", "45", "--json"]);
    let thin = json(&["--n-real", "0.96", "--n-imag", "6.69", "--aoi-deg", "45", "--coating", "2.0:0.5:0", "--json"]);
    assert!((bare["r_s"].as_f64().unwrap() - thin["r_s"].as_f64().unwrap()).abs() < 1e-13);
    let thick = json(&["--n-real", "0.96", "--n-imag", "6.69", "--aoi-deg", "45", "--coating", "2.0:0.5:20", "--json"]);
    assert!(thick["r_s"].as_f64().unwrap() < bare["r_s"].as_f64().unwrap() - 0.01, "{thick}");
    assert_eq!(thick["layers"][0]["index_imag"].as_f64(), Some(0.5));
}

#[test]
fn bad_metal_is_named() {
    for (args, needle) in [
        (vec!["--metal", "gold", "--aoi-deg", "45"], "gold"),
        (vec!["--metal", "aluminium", "--aoi-deg", "45", "--wavelength-nm", "5000"], "outside"),
        (vec!["--metal", "aluminium", "--n-real", "1.5", "--aoi-deg", "45"], "--n-real"),
        (vec!["--n-real", "1.5", "--aoi-deg", "10", "--coating", "1.38:-1:3"], "--coating layer 1"),
    ] {
        let o = run(&args);
        assert_eq!(o.status.code(), Some(2), "{args:?}");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains(needle), "{args:?}: {e}");
    }
}
