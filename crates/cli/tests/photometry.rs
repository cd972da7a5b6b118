//! `instpol photometry` end to end: a polarized star on a polarized sky (section background).

use std::process::Command;

#[test]
fn star_polarization_after_vectorial_background_subtraction() {
    let dir = tempfile::tempdir().unwrap();
    let text = include_str!("../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 128")
        .replace("ny = 2048", "ny = 128")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 12.0")
        .replace("strip_count = 9", "strip_count = 1")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 4");
    let inst = dir.path().join("i.toml");
    std::fs::write(&inst, text).unwrap();
    let scene = dir.path().join("s.toml");
    std::fs::write(
        &scene,
        format!(
            "instrument = \"{}\"\nfilter = \"V\"\n[output]\nbitpix = -64\n[sky]\nbrightness_e = 500\np = 0.06\nchi_deg = 100\n\
             [[stars]]\nx = 64\ny = 34\ncoords = \"pixel\"\nflux_e = 3e5\np = 0.03\nchi_deg = 20\nfwhm_arcsec = 0.6\n",
            inst.display()
        ),
    )
    .unwrap();
    let out = dir.path().join("f");
    let o = Command::new(env!("CARGO_BIN_EXE_instpol"))
        .arg("simulate")
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut frames: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "fits"))
        .collect();
    frames.sort();
    let o = Command::new(env!("CARGO_BIN_EXE_instpol"))
        .arg("photometry")
        .args(&frames)
        .args(["--x", "64", "--y", "34", "--aperture", "8", "--annulus", "12,20", "--json", "--instrument"])
        .arg(&inst)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!((j["p"].as_f64().unwrap() - 0.03).abs() < 1e-6, "{j}");
    assert!((j["chi_deg"].as_f64().unwrap() - 20.0).abs() < 1e-3, "{j}");
    // An aperture reaching behind the mask is refused by name.
    let o = Command::new(env!("CARGO_BIN_EXE_instpol"))
        .arg("photometry")
        .args(&frames)
        .args(["--x", "64", "--y", "8", "--instrument"])
        .arg(&inst)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("behind the mask"));
}
