//! Regression tests for defects found by the cargo-fuzz targets (fuzz/FINDINGS.md).

use std::path::Path;

const MINI: &str = r#"name = "MINI"
[detector]
nx = 64
ny = 64
pixel_scale_arcsec = 4.0
gain_e_per_adu = 1.25
read_noise_e = 5.0
saturation_adu = 65535.0
[field]
width_arcmin = 4.27
height_arcmin = 4.27
[polarimetry]
throw_arcsec = 24.0
strip_axis = "y"
strip_count = 4
first_strip_y_px = 4
extraordinary_offset_sign = 1
hwp_angle_keyword = "HIERARCH ESO INS RETA2 POSANG"
filter_keyword = "HIERARCH ESO INS FILT1 NAME"
[[filters]]
name = "V"
lambda_eff_nm = 554.0
"#;

/// Replace the value of header card `key` (an integer, right-justified in columns 11-30).
fn patch_card(path: &Path, key: &str, value: &str) {
    let mut b = std::fs::read(path).unwrap();
    let k = format!("{key:<8}= ");
    let at = b.windows(k.len()).position(|w| w == k.as_bytes()).unwrap_or_else(|| panic!("no {key} card"));
    b[at + 10..at + 30].copy_from_slice(format!("{value:>20}").as_bytes());
    std::fs::write(path, b).unwrap();
}

fn plan_with_map(dir: &Path) -> Result<sim::Plan, sim::Error> {
    let scene = r#"instrument = "mini.toml"
filter = "V"
[sky]
brightness_e = 1000
[effects]
instpol = { kind = "map", q_file = "q.fits", u_file = "q.fits", bin_px = 8 }
"#;
    std::fs::write(dir.join("mini.toml"), MINI).unwrap();
    let s = sim::Scene::from_toml_str(scene, &dir.join("scene.toml")).unwrap();
    sim::Plan::build(&s)
}

/// fuzz/FINDINGS.md, sim_map 1: a Q/U map (or extended-source image) whose header claims an
/// empty axis (a cube with NAXIS3 = 0) panicked in `read_map` ("range end index 64 out of
/// range for slice of length 0"), and one claiming more pixels than its file holds made
/// CFITSIO's read allocate what the header said (NAXIS2 = 99999999999: an abort). Both are now
/// errors naming the file; the unpatched map still builds.
#[test]
fn map_with_empty_or_absurd_axes_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let q = dir.path().join("q.fits");
    let v: Vec<f64> = (0..64).map(|k| 1e-3 * (k % 8) as f64).collect();
    let write = |shape3: bool| {
        let _ = std::fs::remove_file(&q);
        if shape3 {
            use fitsio::images::{ImageDescription, ImageType};
            let desc = ImageDescription { data_type: ImageType::Double, dimensions: &[2, 8, 8] };
            let mut f = fitsio::FitsFile::create(&q).with_custom_primary(&desc).open().unwrap();
            let hdu = f.primary_hdu().unwrap();
            let mut w = v.clone();
            w.extend_from_slice(&v);
            hdu.write_image(&mut f, &w).unwrap();
        } else {
            skyfield::fits::write_frame(&q, 8, 8, &v, skyfield::fits::Bitpix::F64, &[]).unwrap();
        }
    };
    write(false);
    assert!(plan_with_map(dir.path()).is_ok(), "the valid 8 x 8 map builds");
    write(true);
    assert!(plan_with_map(dir.path()).is_ok(), "the valid 2 x 8 x 8 cube builds");

    patch_card(&q, "NAXIS3", "0");
    let e = plan_with_map(dir.path()).err().expect("empty cube refused").to_string();
    assert!(e.contains("q.fits") && e.contains("no pixels"), "{e}");

    write(false);
    patch_card(&q, "NAXIS2", "99999999999");
    let e = plan_with_map(dir.path()).err().expect("absurd size refused").to_string();
    assert!(e.contains("q.fits") && e.contains("claims"), "{e}");
}
