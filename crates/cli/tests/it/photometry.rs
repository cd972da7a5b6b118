//! `instpol photometry` end to end: a polarized star on a polarized sky (section background).

use crate::common;

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
    // No zero angle in the file: said so, not silently taken as the sky's frame.
    assert!(String::from_utf8_lossy(&o.stderr).contains("gives no HWP zero angle for filter V"));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!((j["p"].as_f64().unwrap() - 0.03).abs() < 1e-6, "{j}");
    assert!((j["chi_deg"].as_f64().unwrap() - 20.0).abs() < 1e-3, "{j}");
    // The filter's HWP zero angle (the angle to add to a measured chi, instrument file) is
    // applied to chi, Q and U as for calibrations (photometry once ignored it): the same
    // frames read with a V offset of 7.5 deg give chi = 27.5 deg, Q = P cos 55 deg,
    // U = P sin 55 deg, P unchanged.
    let text = std::fs::read_to_string(&inst).unwrap();
    let v = text.find("name = \"V\"").unwrap();
    // The shipped V block gives no zero angle (chi then the plate's, with a warning): add one.
    let at = v + text[v..].find("lambda_eff_nm").unwrap();
    let text = format!("{}hwp_chi_offset_deg = 7.5\n{}", &text[..at], &text[at..]);
    let inst2 = dir.path().join("offset.toml");
    std::fs::write(&inst2, text).unwrap();
    let o = instpol()
        .arg("photometry")
        .args(&frames)
        .args(["--x", "64", "--y", "34", "--aperture", "8", "--annulus", "12,20", "--json", "--instrument"])
        .arg(&inst2)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!String::from_utf8_lossy(&o.stderr).contains("no HWP zero angle"));
    let k: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!((k["chi_deg"].as_f64().unwrap() - 27.5).abs() < 1e-3, "{k}");
    assert!((k["p"].as_f64().unwrap() - 0.03).abs() < 1e-6, "{k}");
    assert!((k["q"].as_f64().unwrap() - 0.03 * 55f64.to_radians().cos()).abs() < 1e-6, "{k}");
    assert!((k["u"].as_f64().unwrap() - 0.03 * 55f64.to_radians().sin()).abs() < 1e-6, "{k}");
    assert_eq!(k["hwp_chi_offset_deg"].as_f64(), Some(7.5));
    // What the measurement is: q, u in the sky frame of that zero angle, of this instrument file.
    assert_eq!(k["product"]["zero_angle_deg"].as_f64(), Some(7.5), "{k}");
    assert_eq!(k["product"]["at_plate"], false, "{k}");
    let def = format!("blake3:{}", blake3::hash(&std::fs::read(&inst2).unwrap()).to_hex());
    assert_eq!(k["product"]["instrument_hash"], def.as_str(), "{k}");
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

/// FORS2's exposures are two chip files (CHIP1 above, CHIP2 below, instrument file): a star
/// saturated at (1000, 476), a pixel of CHIP2's place (origin (0, 0), 1024 rows), is named in
/// the CHIP2 file in the photometry's error and in the saturation warnings, and never in a
/// CHIP1 file, where both named the exposure's first (CHIP1) file.
#[test]
fn a_saturated_pixel_is_named_in_the_chip_file_it_came_from() {
    let inst = instrument::Instrument::load("fors2").unwrap();
    let holder = inst
        .format
        .chips
        .iter()
        .find(|c| {
            (c.origin_px[0]..c.origin_px[0] + c.size_px[0]).contains(&1000)
                && (c.origin_px[1]..c.origin_px[1] + c.size_px[1]).contains(&476)
        })
        .unwrap();
    assert_eq!(holder.name, "CHIP2");
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("s.toml");
    std::fs::write(
        &scene,
        "instrument = \"fors2\"\nfilter = \"v_HIGH\"\nhwp_angles_deg = [0, 22.5, 45, 67.5]\nexposure_s = 30\nseed = 21\n\
         [sky]\nbrightness_e = 300\np = 0.0\n[[stars]]\nx = 1000\ny = 476\ncoords = \"pixel\"\nflux_e = 2e6\np = 0.05\n\
         chi_deg = 30\nfwhm_arcsec = 0.8\n[effects]\nphoton_noise = true\nread_noise = true\n",
    )
    .unwrap();
    let out = dir.path().join("f");
    let o = instpol().arg("simulate").arg(&scene).arg("--out").arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let frames = fits_in(&out);
    let o = instpol()
        .arg("photometry")
        .args(&frames)
        .args(["--instrument", "fors2", "--x", "1000", "--y", "476"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    let error = err.lines().find(|l| l.starts_with("error")).unwrap();
    assert!(error.contains("is saturated") && error.contains("_CHIP2.fits"), "{err}");
    let warned: Vec<&str> = err.lines().filter(|l| l.contains("saturated pixels")).collect();
    assert!(!warned.is_empty(), "{err}");
    for w in warned {
        assert!(w.contains("_CHIP2.fits") && !w.contains("_CHIP1.fits"), "{w}");
    }
}
