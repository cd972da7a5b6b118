//! `instpol simulate --field CAL.fits`: a calibration's model goes into the frames directly
//! (the simulator and the fitter share `field::FieldModel`; the numbers are checked pixel by
//! pixel in `crates/sim/tests/field_model.rs`), and a calibration of another filter is refused.

mod common;

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
