//! `instpol photometry` end to end: a polarized star on a polarized sky (section background).

mod common;

use common::{fits_in, instpol};

#[test]
fn star_polarization_after_vectorial_background_subtraction() {
    let dir = tempfile::tempdir().unwrap();
    let inst = common::tiny_fors1(dir.path(), 12.0, 4);
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
    let o = instpol().arg("simulate").arg(&scene).arg("--out").arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let frames = fits_in(&out);
    let o = instpol()
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
    let o = instpol()
        .arg("photometry")
        .args(&frames)
        .args(["--x", "64", "--y", "8", "--instrument"])
        .arg(&inst)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("behind the mask"));
}
