//! End-to-end: `instpol calibrate` on a Stokes map of a simulated V-band empty field (the
//! paper's V pattern and sky, section sec:fors1), then `fit`, `plot` and bad input.

use crate::common;

use common::{run as instpol, write_v_sky_map as write_map, V_COEFFS as V};

#[test]
fn calibrate_map_recovers_the_v_pattern_and_writes_a_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("map_v.fits");
    write_map(&map, |_| true);
    let cal = dir.path().join("cal_v.fits");
    let (code, out, err) = instpol(&[
        "calibrate",
        "--map",
        map.to_str().unwrap(),
        "--sky-p",
        "1.74",
        "--sky-chi",
        "-53.8",
        "--out",
        cal.to_str().unwrap(),
        "--json",
    ]);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    // The keys of calibrate's JSON that scripts rely on (`schemas/calibrate.schema.json`).
    for key in [
        "filter",
        "centre_arcmin",
        "coefficients",
        "sigma_coefficients",
        "rms_residual",
        "polar_angle_slope",
        "polar_angle_intercept_deg",
        "n_bins_used",
        "centre_px",
    ] {
        assert!(j.get(key).is_some(), "missing {key} in {out}");
    }
    assert_eq!(j["filter"], "V");
    let c: Vec<f64> = serde_json::from_value(j["coefficients"].clone()).unwrap();
    let e: Vec<f64> = serde_json::from_value(j["sigma_coefficients"].clone()).unwrap();
    for k in 0..3 {
        assert!(((c[k] - V[k]) / e[k]).abs() < 4.0, "c{} {} +- {} vs {}", k + 1, c[k], e[k], V[k]);
    }
    assert!((j["polar_angle_slope"].as_f64().unwrap() - 1.0).abs() < 0.01);
    assert!((j["rms_residual"].as_f64().unwrap() / 1e-4 - 1.0).abs() < 0.2);
    // Fixed centre at the detector centre: pixel (1023.5, 1023.5) of FORS1.
    assert_eq!(j["centre_px"][0].as_f64().unwrap(), 1023.5);
    assert!(cal.is_file());

    // Refit with a free centre: same JSON shape, centre near the detector centre.
    let (code, out, err) = instpol(&["fit", cal.to_str().unwrap(), "--free-centre", "--json"]);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    let cx = j["centre_arcmin"][0].as_f64().unwrap();
    let cy = j["centre_arcmin"][1].as_f64().unwrap();
    assert!(cx.hypot(cy) < 0.05, "free centre ({cx}, {cy})");

    // The table says how the errors were scaled, with the factor the JSON reports.
    let (code, out, err) = instpol(&["fit", cal.to_str().unwrap(), "--error-scaling", "absolute"]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("errors: covariance x 1.000 (absolute)"), "{out}");
    let (_, out, _) = instpol(&["fit", cal.to_str().unwrap(), "--json"]);
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    let (chi2, scale) = (j["chi2_dof"].as_f64().unwrap(), j["covariance_scale"].as_f64().unwrap());
    assert_eq!(j["error_scaling"], "conservative");
    assert_eq!(scale, chi2.max(1.0), "conservative scale is max(1, chi2_red)");

    // Plots.
    let plots = dir.path().join("plots");
    let (code, _, err) = instpol(&["plot", cal.to_str().unwrap(), "--out", plots.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    for f in ["cal_v_map.png", "cal_v_map.svg", "cal_v_profile.png", "cal_v_residual.png"] {
        assert!(plots.join(f).is_file(), "{f}");
    }
}

#[test]
fn bad_input_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cal.fits");
    // Frames without the sky values.
    let (code, _, err) = instpol(&["calibrate", "a.fits", "b.fits", "--out", out.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("error:") && err.contains("--sky-p"), "{err}");
    // A sky field with too few valid bins.
    let map = dir.path().join("sparse.fits");
    write_map(&map, |k| k % 200 == 0 && k < 800);
    let (code, _, err) = instpol(&[
        "calibrate",
        "--map",
        map.to_str().unwrap(),
        "--sky-p",
        "1.74",
        "--sky-chi",
        "-53.8",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 2);
    assert!(err.contains("too few usable bins"), "{err}");
    assert!(!out.exists(), "no calibration may be written on error");
    // A calibration file from a newer format version.
    let full = dir.path().join("full.fits");
    write_map(&full, |_| true);
    let (code, _, err) = instpol(&common::calibrate_v_args(&full, &out));
    assert_eq!(code, 0, "{err}");
    {
        let mut f = fitsio::FitsFile::edit(&out).unwrap();
        let h = f.primary_hdu().unwrap();
        h.write_key(&mut f, "HIERARCH IP FORMAT VERSION", 99i64).unwrap();
    }
    let (code, _, err) = instpol(&["fit", out.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("newer") && err.contains("cal.fits") && err.contains("99"), "{err}");
    // A bad exclusion spec is named.
    let (code, _, err) = instpol(&[
        "calibrate",
        "--map",
        full.to_str().unwrap(),
        "--sky-p",
        "1.74",
        "--sky-chi",
        "-53.8",
        "--exclude",
        "sector:10",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 2);
    assert!(err.contains("sector:10"), "{err}");
}

#[test]
fn calibrate_from_simulated_frames_through_the_whole_chain() {
    // sim -> FITS frames -> skyfield reduce -> sky-field solution -> radial fit. (The
    // simulator's coeffs_percent start at r^0; the paper's polynomial has no constant.)
    let dir = tempfile::tempdir().unwrap();
    let inst = dir.path().join("small.toml");
    std::fs::write(&inst, common::SMALL.toml()).unwrap();
    let scene = format!(
        "instrument = {:?}\nfilter = \"V\"\nseed = 5\n[output]\nbitpix = -32\n[sky]\nbrightness_e = 40000.0\np = 0.0174\nchi_deg = -53.8\n\
         [effects]\nphoton_noise = true\n[effects.instpol]\nkind = \"radial\"\ncoeffs_percent = [0.0, 0.012, 0.046, 0.002]\n",
        inst.display().to_string()
    );
    let scene = sim::Scene::from_toml_str(&scene, std::path::Path::new("<test scene>")).unwrap();
    let simd = sim::simulate(&scene, &dir.path().join("frames"), &|| {}).unwrap();
    let cal = dir.path().join("cal.fits");
    let mut args: Vec<String> = vec!["calibrate".into()];
    args.extend(simd.frames.iter().map(|p| p.display().to_string()));
    for a in [
        "--instrument",
        inst.to_str().unwrap(),
        "--sky-p",
        "1.74",
        "--sky-chi",
        "-53.8",
        "--bin",
        "8",
        "--out",
        cal.to_str().unwrap(),
        "--json",
    ] {
        args.push(a.into());
    }
    let argv: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
    let (code, out, err) = instpol(&argv);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    let c: Vec<f64> = serde_json::from_value(j["coefficients"].clone()).unwrap();
    let e: Vec<f64> = serde_json::from_value(j["sigma_coefficients"].clone()).unwrap();
    for k in 0..3 {
        assert!(((c[k] - V[k]) / e[k]).abs() < 4.0, "c{} {} +- {} vs {}", k + 1, c[k], e[k], V[k]);
    }
    assert!((j["polar_angle_slope"].as_f64().unwrap() - 1.0).abs() < 0.02, "{out}");
    // Only the strips see the sky: about half the field.
    assert!(j["n_bins_used"].as_u64().unwrap() > 1000, "{out}");
}

/// A map that records another HWP zero angle (`HWPZERO` = 2 deg) than the instrument file gives
/// its filter now (FORS1 V: 0): `calibrate --map` says so and records the instrument's (the
/// calibration file's `HWP CHI OFFSET DEG`, read back here); a map that records the same, or
/// none, draws no such warning.
#[test]
fn a_map_reduced_with_another_zero_angle_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let calibrate = |map: &std::path::Path, cal: &std::path::Path| {
        instpol(&[
            "calibrate",
            "--map",
            map.to_str().unwrap(),
            "--sky-p",
            "1.74",
            "--sky-chi",
            "-53.8",
            "--out",
            cal.to_str().unwrap(),
        ])
    };
    for (recorded, warned) in [(Some(2.0), true), (Some(0.0), false), (None, false)] {
        let map = dir.path().join("map.fits");
        write_map(&map, |_| true);
        let mut m = skyfield::StokesMap::read_fits(&map).unwrap();
        m.hwp_zero_angle_deg = recorded;
        std::fs::remove_file(&map).unwrap();
        m.write_fits(&map).unwrap();
        let cal = dir.path().join(format!("cal_{recorded:?}.fits"));
        let (code, _, err) = calibrate(&map, &cal);
        assert_eq!(code, 0, "{err}");
        assert_eq!(err.contains("HWPZERO"), warned, "{recorded:?}: {err}");
        if warned {
            assert!(err.contains("2 deg") && err.contains("0 deg is used"), "{err}");
        }
        assert_eq!(fit::Calibration::load(&cal).unwrap().hwp_chi_offset_deg, 0.0);
    }
}
