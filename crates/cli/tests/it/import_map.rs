//! `instpol import-map` and `instpol fit` on the public FORS2 maps (real data, skipped when
//! ../shared/data/fors2-instpol is absent), and bad map input.

use crate::common;

use common::run as instpol;

#[test]
fn fors2_v_map_imports_fits_and_plots() {
    let Some(d) =
        crate::common::shared_data::shared_data("fors2-instpol", &["v_HIGH_inlaQ_bin10.fits"], "the FORS2 map import")
    else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cal = dir.path().join("fors2_v.fits");
    let mut args = common::import_fors2_v_args(&d, &cal);
    args.extend(["--lambda-nm", "557", "--json"].map(String::from));
    let (code, out, err) = instpol(&args);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    // About 25% of the 205 x 209 grid is NaN (README).
    let n = j["n_pixels"].as_u64().unwrap() as f64 / (205.0 * 209.0);
    assert!(n > 0.6 && n < 0.85, "{n}");
    let (code, out, err) = instpol(&["fit", cal.to_str().unwrap(), "--free-centre", "--json"]);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    let c: Vec<f64> = serde_json::from_value(j["centre_px"].clone()).unwrap();
    // Within ~0.5 arcmin of the README's (1025, 1226) binned px (see fit's fors2 test).
    assert!((c[0] - 1025.0).hypot(c[1] - 1226.0) < 120.0, "{c:?}");
    assert!((j["polar_angle_slope"].as_f64().unwrap() - 1.0).abs() < 0.05);
    let plots = dir.path().join("plots");
    let (code, _, err) = instpol(&["plot", cal.to_str().unwrap(), "--out", plots.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(plots.join("fors2_v_map.png").is_file() && plots.join("fors2_v_profile.svg").is_file());
}

#[test]
fn a_plain_image_is_not_a_map_cube() {
    let dir = tempfile::tempdir().unwrap();
    let img = dir.path().join("flat.fits");
    {
        let desc =
            fitsio::images::ImageDescription { data_type: fitsio::images::ImageType::Double, dimensions: &[4, 5] };
        let mut f = fitsio::FitsFile::create(&img).with_custom_primary(&desc).open().unwrap();
        let h = f.primary_hdu().unwrap();
        h.write_image(&mut f, &[0.0f64; 20]).unwrap();
    }
    let out = dir.path().join("cal.fits");
    // A copy as the U map: the same file as both maps is refused earlier, as a duplicate.
    let img_u = dir.path().join("flat_u.fits");
    std::fs::copy(&img, &img_u).unwrap();
    let (code, _, err) = instpol(&[
        "import-map",
        "--q",
        img.to_str().unwrap(),
        "--u",
        img_u.to_str().unwrap(),
        "--pixel-scale",
        "0.25",
        "--bin",
        "10",
        "--filter",
        "V",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 2);
    assert!(err.contains("flat.fits") && err.contains("(2, NY, NX)"), "{err}");
    assert!(!out.exists());
}

/// The frame of a correction's output: a FORS2 catalog carries v_HIGH's HWP zero angle
/// (-1.80 deg, `instruments/fors2.toml`, the column `hwp_chi_offset_deg` that `instpol catalog`
/// writes), so its q, u are in the sky frame already. Maps of no instrumental polarization
/// imported for FORS2 v_HIGH record that same zero angle, and correcting the catalog with
/// them leaves every row as it is (q0 = q, u0 = u). Before, import-map recorded 0 and each
/// chi0 came out 1.8 deg larger. Stating another frame (`--zero-angle 0`) turns the rows by
/// the difference, checked against the rotation by hand, with a warning naming both angles.
#[test]
fn identity_maps_keep_a_catalog_in_its_sky_frame() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let zero = fit::RadialModel::new(1, vec![0.0, 0.0, 0.0], [0.0, 0.0]);
    fit::models::synth::write_qu_cubes(
        &d.path().join("q.fits"),
        &d.path().join("u.fits"),
        &zero,
        400,
        400,
        0.25,
        20,
        1e-5,
    )
    .unwrap();
    let (q, u) = (0.031, -0.012);
    std::fs::write(
        p("cat.csv"),
        format!("x,y,q,u,sigma_q,sigma_u,hwp_chi_offset_deg\n0.1,-0.2,{q},{u},0.001,0.001,-1.8\n"),
    )
    .unwrap();
    let (qf, uf) = (p("q.fits"), p("u.fits"));
    let import = |out: &str, extra: &[&str]| {
        let mut a = vec!["import-map", "--q", &qf, "--u", &uf, "--pixel-scale", "0.25"];
        a.extend(["--bin", "20", "--filter", "v_HIGH", "--instrument", "fors2", "--json", "--out", out]);
        a.extend(extra);
        let (c, o, e) = instpol(&a);
        assert_eq!(c, 0, "{e}");
        serde_json::from_str::<serde_json::Value>(&o).unwrap()["hwp_chi_offset_deg"].as_f64().unwrap()
    };
    assert_eq!(import(&p("id.fits"), &[]), -1.8);
    let corrected = |cal: &str, out: &str| {
        let (c, _, e) = instpol(&["correct", "--cal", cal, "--in", &p("cat.csv"), "--out", out]);
        assert_eq!(c, 0, "{e}");
        let text = std::fs::read_to_string(out).unwrap();
        let (head, row) = text.split_once('\n').unwrap();
        let col = |name: &str| -> f64 {
            let i = head.split(',').position(|h| h == name).unwrap();
            row.trim().split(',').nth(i).unwrap().parse().unwrap()
        };
        (col("q0"), col("u0"), e)
    };
    let (q0, u0, e) = corrected(&p("id.fits"), &p("out.csv"));
    assert!((q0 - q).abs() < 1e-15 && (u0 - u).abs() < 1e-15, "({q0}, {u0}) for ({q}, {u})");
    // No warning but that the hand-written table does not say its instrument and filter.
    assert!(!e.lines().any(|l| l.contains("warning") && !l.contains("does not say which instrument")), "{e}");
    assert_eq!(import(&p("plate.fits"), &["--zero-angle", "0"]), 0.0);
    let (q0, u0, e) = corrected(&p("plate.fits"), &p("out2.csv"));
    let t = 2.0 * 1.8f64.to_radians();
    let (qr, ur) = (t.cos() * q - t.sin() * u, t.sin() * q + t.cos() * u);
    assert!((q0 - qr).abs() < 1e-12 && (u0 - ur).abs() < 1e-12, "({q0}, {u0}) for ({qr}, {ur})");
    assert!(e.contains("warning") && e.contains("-1.8") && e.contains("1.8 deg"), "{e}");
}

/// A field free of instrumental polarization (an imported map of q = u = 0, the case a
/// polarization-free instrument gives) is a calibration, not "0 of 400 bins usable": the
/// radial fit of zero data is zero (the least-squares solution of a zero right-hand side), its
/// errors finite, the polar-angle line undefined (null in JSON, no angle to fit) while the test
/// against noise holds (chi^2 = 0: p = 1), and the plots draw.
#[test]
fn a_map_of_no_polarization_fits_to_zero() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let zero = fit::RadialModel::new(1, vec![0.0, 0.0, 0.0], [0.0, 0.0]);
    fit::models::synth::write_qu_cubes(
        &d.path().join("q.fits"),
        &d.path().join("u.fits"),
        &zero,
        400,
        400,
        0.25,
        20,
        1e-5,
    )
    .unwrap();
    let (c, _, e) = instpol(&[
        "import-map",
        "--q",
        &p("q.fits"),
        "--u",
        &p("u.fits"),
        "--pixel-scale",
        "0.25",
        "--bin",
        "20",
        "--filter",
        "V",
        "--out",
        &p("zero.fits"),
    ]);
    assert_eq!(c, 0, "{e}");
    let (c, out, e) = instpol(&["fit", &p("zero.fits"), "--json", "--out", &p("fitted.fits")]);
    assert_eq!(c, 0, "{e}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(j["n_bins_used"].as_u64(), Some(400), "{j}");
    for (c, s) in j["coefficients"].as_array().unwrap().iter().zip(j["sigma_coefficients"].as_array().unwrap()) {
        assert_eq!(c.as_f64(), Some(0.0), "{j}");
        assert!(s.as_f64().is_some_and(|s| s > 0.0 && s.is_finite()), "{j}");
    }
    assert!(j["polar_angle_slope"].is_null() && j["polar_angle_intercept_deg"].is_null(), "{j}");
    assert_eq!(j["polar_angle_noise_pvalue"].as_f64(), Some(1.0));
    assert_eq!(j["polar_angle_pattern"].as_bool(), Some(false));
    let (c, _, e) = instpol(&["plot", &p("fitted.fits"), "--out", &p("plots")]);
    assert_eq!(c, 0, "{e}");
}
