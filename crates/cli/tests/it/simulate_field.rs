//! `instpol simulate --field CAL.fits`: a calibration's model goes into the frames directly
//! (the simulator and the fitter share `field::FieldModel`; the numbers are checked pixel by
//! pixel in `crates/sim/tests/it/field_model.rs`), and a calibration of another filter is refused.

use crate::common;

use common::*;

#[test]
fn simulate_takes_a_calibration_as_its_field() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_fors1(dir.path(), 8.0, 20);
    let scene = dir.path().join("scene.toml");
    std::fs::write(
        &scene,
        format!(
            "instrument = \"{}\"\nfilter = \"V\"\nseed = 1\n[output]\nbitpix = -64\n[sky]\nbrightness_e = 1000.0\n",
            inst.display()
        ),
    )
    .unwrap();
    let cal_v = dir.path().join("cal_V.fits");
    fors1_radial_calibration("V", V_COEFFS).save(&cal_v).unwrap();
    let out = dir.path().join("frames");
    let (code, _, err) = run_sub(
        "simulate",
        &[scene.to_str().unwrap(), "--out", out.to_str().unwrap(), "--field", cal_v.to_str().unwrap(), "--explain"],
    );
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("calibration of FORS1 V, model RADIAL"), "{err}");
    assert_eq!(fits_in(&out).len(), 4);

    let cal_i = dir.path().join("cal_I.fits");
    fors1_radial_calibration("I", V_COEFFS).save(&cal_i).unwrap();
    let (code, _, err) = run_sub(
        "simulate",
        &[scene.to_str().unwrap(), "--out", out.to_str().unwrap(), "--field", cal_i.to_str().unwrap()],
    );
    assert_ne!(code, 0);
    assert!(err.contains("calibrates FORS1 I but the scene is FORS1 V"), "{err}");
}

/// A field without an optical axis end to end: a plane (`q = 0.2 % + 0.05 % x - 0.03 % y`,
/// `u = -0.1 % + 0.02 % x + 0.04 % y`, x, y in arcmin) put into the frames of the 96 px test
/// instrument through a POLY calibration, the frames calibrated against their 2 % sky with
/// `--model plane`: the six coefficients come back (noise-free frames: to 1e-5, the bins'
/// averaging of a plane's nonlinear composition with the sky), and the file read back holds
/// the polynomial.
#[test]
fn a_plane_field_through_the_frames_and_back() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let ins = d.join("mini.toml");
    std::fs::write(&ins, MINI.toml()).unwrap();
    let (tq, tu) = ([2e-3, 5e-4, -3e-4], [-1e-3, 2e-4, 4e-4]);
    let mut cal = fors1_radial_calibration("V", V_COEFFS);
    cal.instrument = "MINI".into();
    cal.model = fit::Model::Poly(fit::PolyModel {
        degree: 1,
        q: tq.to_vec(),
        u: tu.to_vec(),
        cov: vec![0.0; 36],
        scaling: None,
    });
    let h = 3.2;
    cal.region = fit::FieldRegion { x_min: -h, x_max: h, y_min: -h, y_max: h };
    cal.pixel = Some(fit::files::calfile::PixelGrid { scale_arcsec: 4.0, origin_px: [47.5, 47.5] });
    let cal_path = d.join("plane.fits");
    cal.save(&cal_path).unwrap();
    let scene = d.join("scene.toml");
    std::fs::write(
        &scene,
        "instrument = \"mini.toml\"\nfilter = \"V\"\nseed = 1\n[output]\nbitpix = -64\n[sky]\nbrightness_e = 20000\np = 0.02\nchi_deg = 30\n",
    )
    .unwrap();
    let out = d.join("frames");
    let (code, _, err) = run_sub(
        "simulate",
        &[scene.to_str().unwrap(), "--out", out.to_str().unwrap(), "--field", cal_path.to_str().unwrap()],
    );
    assert_eq!(code, 0, "{err}");
    let mut args: Vec<String> = ["calibrate", "--instrument", ins.to_str().unwrap(), "--sky-p", "2", "--sky-chi", "30"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    args.extend(["--bin", "4", "--model", "plane", "--json", "--out"].iter().map(|s| s.to_string()));
    args.push(d.join("back.fits").display().to_string());
    args.extend(fits_in(&out).iter().map(|p| p.display().to_string()));
    let (code, o, err) = run(&args);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&o).unwrap();
    assert_eq!(j["model"], "POLY", "{j}");
    let p = &j["poly"];
    for k in 0..3 {
        let (q, u) = (p["q"][k].as_f64().unwrap(), p["u"][k].as_f64().unwrap());
        assert!(
            (q - tq[k]).abs() < 1e-5 && (u - tu[k]).abs() < 1e-5,
            "term {k}: ({q}, {u}) for ({}, {}): {p}",
            tq[k],
            tu[k]
        );
    }
    assert_eq!(p["powers"], serde_json::json!([[0, 0], [1, 0], [0, 1]]));
    let back = fit::Calibration::load(&d.join("back.fits")).unwrap();
    assert_eq!(back.model.kind(), "POLY");
}
