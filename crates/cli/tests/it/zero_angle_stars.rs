//! `instpol zero-angle` with several standards in one run: the shipped maskless
//! scene plus a third polarized star, simulated through a plate whose zero angle is 41.3 deg.
//! The three standards (chi 136, 12 and 70 deg) give one zero angle within its error, agree
//! with each other (chi2/dof small, no outlier), and tell the sense of the angle (the
//! simulator's plate turns chi counter-clockwise, as the IAU). A fourth "standard" catalogued
//! 6 deg off its true chi (or 73 deg off, the wrong star) is named and left out: the zero angle
//! stays the three good ones'.

use crate::common;

use common::{fits_in, run};
use std::ffi::OsString;
use std::path::{Path, PathBuf};

const OFFSET: f64 = 41.3;

fn scene(dir: &Path) -> (PathBuf, Vec<PathBuf>) {
    scene_with(dir, "")
}

/// The scene with `more` (TOML `[[stars]]` tables) added to its stars.
fn scene_with(dir: &Path, more: &str) -> (PathBuf, Vec<PathBuf>) {
    let text = include_str!("../../../../instruments/calcite.toml")
        .replace("hwp_angle_keyword = \"\"", "hwp_angle_keyword = \"HWPANG\"");
    let inst = dir.join("calcite.toml");
    std::fs::write(&inst, &text).unwrap();
    let extra = "\n[[stars]]\nx = 500\ny = 300\ncoords = \"pixel\"\nflux_e = 3e5\np = 0.04\nchi_deg = 70.0\nfwhm_arcsec = 1.0\n\n[[stars]]\nx = 560\ny = 560\ncoords = \"pixel\"\nflux_e = 3e5\np = 0.05\nchi_deg = 100.0\nfwhm_arcsec = 1.0\n";
    let mut scene = include_str!("../../../../instruments/scenes/calcite_stars.toml")
        .replace("instrument = \"calcite\"", &format!("instrument = \"{}\"", inst.display()))
        .replace("[effects]", &format!("[effects]\nhwp_chi_offset_deg = {OFFSET}"));
    // The stars go before [effects] (TOML tables after it would belong to it).
    let at = scene.find("[effects]").unwrap();
    scene.insert_str(at, &format!("{}{more}", extra.trim_start()));
    let sp = dir.join("scene.toml");
    std::fs::write(&sp, scene).unwrap();
    let out = dir.join("f");
    let (code, _, err) = run(&["simulate".as_ref(), sp.as_os_str(), "--out".as_ref(), out.as_os_str()]);
    assert_eq!(code, 0, "{err}");
    (inst, fits_in(&out))
}

fn zero_angle(inst: &Path, frames: &[PathBuf], standards: &[&str]) -> (i32, serde_json::Value, String) {
    let mut args: Vec<OsString> = vec!["zero-angle".into()];
    args.extend(frames.iter().map(|f| f.clone().into_os_string()));
    for a in ["--instrument", inst.to_str().unwrap(), "--aperture", "9", "--annulus", "14,24", "--json"] {
        args.push(a.into());
    }
    for s in standards {
        args.push("--standard".into());
        args.push(s.into());
    }
    let (code, stdout, err) = run(&args);
    (code, serde_json::from_str(&stdout).unwrap_or(serde_json::Value::Null), err)
}

#[test]
fn zero_angle_from_three_standards_of_different_chi() {
    let dir = tempfile::tempdir().unwrap();
    let (inst, frames) = scene(dir.path());
    let three = ["150,200:136+-0.05", "300,600:12+-0.05", "500,300:70+-0.05"];
    let (code, j, err) = zero_angle(&inst, &frames, &three);
    assert_eq!(code, 0, "{err}");
    let f = |k: &str| j[k].as_f64().unwrap_or_else(|| panic!("{k}: {j}"));
    let (z, sz) = (f("zero_angle_deg"), f("sigma_zero_angle_deg"));
    assert!((z - OFFSET).abs() < 4.0 * sz && sz < 0.5, "zero angle {z} +- {sz}");
    assert_eq!(j["n_standards"], 3);
    assert_eq!(j["sense"], "iau", "{j}");
    assert!(j["outlier"].is_null(), "{j}");
    // Photon-limited stars agree with each other: chi2 of 2 dof below the 99.9 % point (13.8).
    assert!(f("chi2_dof") * 2.0 < 13.8, "{j}");
    // Each star's own offset is the measured-vs-catalogue difference, and the mean is their
    // weighted mean on the circle (independently recomputed here).
    let stars = j["standards"].as_array().unwrap();
    let (mut sw, mut ss, mut sc) = (0.0, 0.0, 0.0);
    for s in stars {
        let g = |k: &str| s[k].as_f64().unwrap();
        let d = (g("chi_catalogue_deg") - g("chi_measured_deg") + 90.0).rem_euclid(180.0) - 90.0;
        assert!((d - g("offset_deg")).abs() < 1e-9, "{s}");
        let w = 1.0 / (g("sigma_chi_measured_deg").powi(2) + g("sigma_chi_catalogue_deg").powi(2));
        sw += w;
        ss += w * (2.0 * d.to_radians()).sin();
        sc += w * (2.0 * d.to_radians()).cos();
    }
    let mean = 0.5 * ss.atan2(sc).to_degrees();
    assert!((mean - z).abs() < 1e-9, "{mean} vs {z}");
    assert!((sw.powf(-0.5) - sz).abs() < 1e-9);
    let scatter = f("sigma_scatter_zero_angle_deg");
    assert!((scatter - sz * f("chi2_dof").sqrt()).abs() < 1e-9);

    // A fourth standard whose catalogue angle is 6 deg off (a misidentified star): named and
    // left out, so the zero angle, its error and chi2 are the three good ones' again.
    let mut four = three.to_vec();
    four.push("560,560:106+-0.05");
    let (code, j4, err) = zero_angle(&inst, &frames, &four);
    assert_eq!(code, 0, "{err}");
    assert_eq!(j4["outlier"].as_str().unwrap(), "chi 106 deg at (560, 560)", "{j4}");
    assert_eq!(j4["excluded"].as_array().unwrap().len(), 1, "{j4}");
    assert!(j4["standards"][3]["excluded"].as_bool().unwrap() && j4["standards"][3]["pull"].as_f64().unwrap() > 3.0);
    assert!(err.contains("disagrees") && err.contains("left out"), "{err}");
    assert_eq!(j4["n_standards"], 3);
    for k in ["zero_angle_deg", "sigma_zero_angle_deg", "chi2_dof"] {
        assert!((j4[k].as_f64().unwrap() - j[k].as_f64().unwrap()).abs() < 1e-9, "{k}: {j4} vs {j}");
    }

    // A standard by name from the built-in list (Hiltner 652, V: 179.18 deg, Fossati et al.
    // 2007) put on the wrong star (true chi 100 deg: 79 deg off): looked up, named, left out,
    // and it neither drags the mean nor flips the sense.
    let mut named = three.to_vec();
    named.push("560,560:Hiltner 652");
    let (code, jn, err) = zero_angle(&inst, &frames, &named);
    assert_eq!(code, 0, "{err}");
    assert_eq!(jn["standards"][3]["chi_catalogue_deg"].as_f64().unwrap(), 179.18, "{jn}");
    assert_eq!(jn["outlier"].as_str().unwrap(), "Hiltner 652", "{jn}");
    assert_eq!(jn["sense"], "iau", "{jn}");
    assert!((jn["zero_angle_deg"].as_f64().unwrap() - z).abs() < 1e-9, "{jn}");

    // A bad --standard is a clear error naming it, exit code 2.
    let (code, _, err) = zero_angle(&inst, &frames, &["150;200:136"]);
    assert_eq!(code, 2);
    assert!(err.contains("150;200:136"), "{err}");
    let (code, _, err) = zero_angle(&inst, &frames, &["150,200:136"]);
    assert_eq!(code, 2);
    assert!(err.contains("+-"), "{err}");
}

/// A standard of the list by name whose values come from SOLVEPOL's V column (HD 147084: 4.17 %
/// at 32.9 deg, Turnshek et al. 1990; its chi error 0.05 deg derived by eq:sigchi from
/// sigma_P = 0.008 %, as instruments/standards.toml says): a star of that polarization in the
/// frames, named, is looked up with those catalogued values, agrees with the other three (no
/// outlier) and the zero angle stays within its error of the plate's.
#[test]
fn zero_angle_with_a_solvepol_standard_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let star = "\n[[stars]]\nx = 200\ny = 420\ncoords = \"pixel\"\nflux_e = 4e5\np = 0.0417\nchi_deg = 32.9\nfwhm_arcsec = 1.0\n";
    let (inst, frames) = scene_with(dir.path(), star);
    let four = ["150,200:136+-0.05", "300,600:12+-0.05", "500,300:70+-0.05", "200,420:HD 147084"];
    let (code, j, err) = zero_angle(&inst, &frames, &four);
    assert_eq!(code, 0, "{err}");
    let named = &j["standards"][3];
    assert_eq!(named["chi_catalogue_deg"].as_f64().unwrap(), 32.9, "{j}");
    assert_eq!(named["sigma_chi_catalogue_deg"].as_f64().unwrap(), 0.05, "{j}");
    assert!(j["outlier"].is_null(), "{j}");
    assert_eq!(j["n_standards"], 4);
    let (z, sz) = (j["zero_angle_deg"].as_f64().unwrap(), j["sigma_zero_angle_deg"].as_f64().unwrap());
    assert!((z - OFFSET).abs() < 4.0 * sz, "zero angle {z} +- {sz}");
    // Its own offset agrees with the plate's within its errors.
    let g = |k: &str| named[k].as_f64().unwrap();
    let s = (g("sigma_chi_measured_deg").powi(2) + 0.05f64.powi(2)).sqrt();
    assert!((g("offset_deg") - OFFSET).abs() < 4.0 * s, "{named}");
}
