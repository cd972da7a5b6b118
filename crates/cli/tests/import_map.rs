//! `instpol import-map` and `instpol fit` on the public FORS2 maps (real data, skipped when
//! ../shared/data/fors2-instpol is absent), and bad map input.

use std::path::PathBuf;
mod common;

use common::run as instpol;

#[test]
fn fors2_v_map_imports_fits_and_plots() {
    let d = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/fors2-instpol");
    if !d.join("v_HIGH_inlaQ_bin10.fits").is_file() {
        eprintln!("SKIPPED: FORS2 maps not found at {}", d.display());
        return;
    }
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
