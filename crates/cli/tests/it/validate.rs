//! `instpol validate` end to end: frames of an unpolarized standard star in the lower-right
//! corner of the FORS1 field, made with the Mueller forward model (the FORS1 V instrumental
//! field `M_I`, an ideal HWP and Wollaston, section `sec:fors1`'s geometry), written as FITS,
//! measured by the photometry and judged against the V calibration (passes) and the I
//! calibration (fails) — the paper's own check.

use crate::common;

use common::fors1_radial_calibration as calibration;
use fit::{Calibration, FieldModel};
use instrument::Instrument;
use mueller::{stokes_p_chi, DualBeam, Element};
use skyfield::fits::{write_frame, Bitpix, KeyValue};
use skyfield::BeamGeometry;
use std::path::{Path, PathBuf};

/// The paper's V and I polynomials (section `sec:fors1`), fractions.
fn v_cal() -> Calibration {
    calibration("V", [0.012e-2, 0.046e-2, 0.002e-2])
}
fn i_cal() -> Calibration {
    calibration("I", [-0.017e-2, 0.105e-2, -0.006e-2])
}

/// Where the V map gives 0.96% at -51.9 deg: r = 4.10' at polar angle -51.9 deg (see
/// crates/fit/tests/it/correct.rs), in o-image pixels of FORS1.
fn paper_star_px(inst: &Instrument) -> (f64, f64) {
    let mut r = 4.0f64;
    for _ in 0..20 {
        r -= (0.012 * r + 0.046 * r * r + 0.002 * r * r * r - 0.96) / (0.012 + 0.092 * r + 0.006 * r * r);
    }
    let a = (-51.9f64).to_radians();
    inst.arcmin_to_pixel(r * a.cos(), r * a.sin())
}

/// Four frames (HWP 0, 22.5, 45, 67.5 deg) of a star of intrinsic `(p0, chi0)` at o-pixel
/// `(x, y)` seen through the V field: Gaussian PSF (sigma 3 px) in the o image and at the same
/// place in the e image of its strip, on a flat unpolarized sky; noise-free pixel values (the
/// photometry's errors are the photon and read noise of these counts).
fn write_star_frames(dir: &Path, inst: &Instrument, x: f64, y: f64, p0: f64, chi0: f64) -> Vec<PathBuf> {
    let v = v_cal();
    let (xa, ya) = inst.pixel_to_arcmin(x, y);
    let (p, phi) = v.eval(xa, ya).p_chi();
    let train = DualBeam { pre: vec![Element::PartialPolarizer { p, phi }], ..Default::default() }.compile();
    let g = BeamGeometry::new(inst);
    let (nx, ny) = (inst.detector.nx, inst.detector.ny);
    let (ex, ey) = g.e_pixel_of_sky(x.round() as usize, y.round() as usize).unwrap();
    let (dex, dey) = (ex as f64 - x.round(), ey as f64 - y.round());
    let total = 3.0e6; // e- per exposure: sigma_P ~ 0.04%, as the paper's star
    let sky = 200.0; // e- per pixel and beam
    let gain = inst.detector.gain_e_per_adu;
    let s = 3.0;
    let pol = &inst.polarimetry;
    let mut paths = vec![];
    for (k, hwp) in [0.0f64, 22.5, 45.0, 67.5].iter().enumerate() {
        let f = train.fluxes(&stokes_p_chi(total, p0, chi0), &[hwp.to_radians()])[0];
        let mut data = vec![0.0; nx * ny];
        for py in 0..ny {
            for px in 0..nx {
                match g.kind(px, py) {
                    skyfield::beams::PixelKind::Masked => {}
                    _ => data[py * nx + px] = sky / gain,
                }
            }
        }
        for (cx, cy, flux) in [(x, y, f.f_o), (x + dex, y + dey, f.f_e)] {
            let (x0, x1) = ((cx - 6.0 * s) as usize, (cx + 6.0 * s) as usize);
            let (y0, y1) = ((cy - 6.0 * s) as usize, (cy + 6.0 * s) as usize);
            for py in y0..=y1 {
                for px in x0..=x1 {
                    let r2 = (px as f64 - cx).powi(2) + (py as f64 - cy).powi(2);
                    data[py * nx + px] +=
                        flux * (-r2 / (2.0 * s * s)).exp() / (2.0 * std::f64::consts::PI * s * s) / gain;
                }
            }
        }
        let path = dir.join(format!("star_{k}.fits"));
        let keys = vec![
            (pol.hwp_angle_keyword.clone(), KeyValue::F64(*hwp), "HWP angle [deg]".to_string()),
            (pol.filter_keyword.clone(), KeyValue::Str("V".into()), String::new()),
        ];
        write_frame(&path, nx, ny, &data, Bitpix::F32, &keys).unwrap();
        paths.push(path);
    }
    paths
}

fn validate(
    cal: &Path,
    frames: &[PathBuf],
    x: f64,
    y: f64,
    extra: &[&str],
) -> (std::process::Output, serde_json::Value) {
    let mut args: Vec<String> = vec![
        "validate".into(),
        "--cal".into(),
        cal.display().to_string(),
        "--x".into(),
        x.to_string(),
        "--y".into(),
        y.to_string(),
        "--json".into(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    // The frames written here carry no INSTRUME: they are FORS1's, said.
    if !extra.contains(&"--instrument") {
        args.extend(["--instrument".to_string(), "fors1".to_string()]);
    }
    args.extend(frames.iter().map(|p| p.display().to_string()));
    let o = common::instpol().args(&args).output().unwrap();
    let js = serde_json::from_slice(&o.stdout).unwrap_or(serde_json::Value::Null);
    (o, js)
}

/// Section `sec:fors1`: an unpolarized standard in the lower-right corner of the V field. The
/// V calibration predicts 0.96% at -51.9 deg (= 128.1 deg) there and passes; the I
/// calibration predicts 1.28% and fails.
#[test]
fn unpolarized_standard_in_the_corner_passes_with_v_fails_with_i() {
    let dir = tempfile::tempdir().unwrap();
    let inst = Instrument::load("fors1").unwrap();
    let (x, y) = paper_star_px(&inst);
    let frames = write_star_frames(dir.path(), &inst, x, y, 0.0, 0.0);
    let (vp, ip) = (dir.path().join("V.fits"), dir.path().join("I.fits"));
    v_cal().save(&vp).unwrap();
    i_cal().save(&ip).unwrap();
    let (o, v) = validate(&vp, &frames, x, y, &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for k in [
        "measured_p",
        "measured_chi_deg",
        "sigma_p",
        "sigma_chi_deg",
        "predicted_p",
        "predicted_chi_deg",
        "pull",
        "pass",
    ] {
        assert!(!v[k].is_null(), "JSON field {k} missing: {v}");
    }
    let f = |k: &str| v[k].as_f64().unwrap();
    assert!((f("predicted_p") - 0.0096).abs() < 2e-6, "{v}");
    assert!((f("predicted_chi_deg") - 128.1).abs() < 0.05, "{v}");
    // The star shows the instrumental polarization, measured to the paper's precision.
    assert!((f("measured_p") - 0.0096).abs() < 3.0 * f("sigma_p"), "{v}");
    assert!(f("sigma_p") > 1e-4 && f("sigma_p") < 1e-3, "{v}");
    assert!(f("pull") < 1.0, "{v}");
    assert_eq!(v["pass"], true);
    assert!(f("corrected_p") < 3.0 * f("sigma_corrected_p"), "{v}");
    // A check that ran and failed exits 1 (scripts: 0 pass, 1 fail, 2 bad input), with the
    // JSON still printed and, under --json, the JSON error (kind check) naming the star on
    // stderr.
    let (o, i) = validate(&ip, &frames, x, y, &[]);
    assert_eq!(o.status.code(), Some(1), "{}", String::from_utf8_lossy(&o.stderr));
    let err = String::from_utf8_lossy(&o.stderr);
    let last: serde_json::Value = serde_json::from_str(err.lines().last().unwrap_or("")).unwrap();
    assert_eq!(last["error"]["kind"], "check", "{err}");
    assert!(last["error"]["message"].as_str().unwrap().starts_with("FAIL: unpolarized"), "{err}");
    assert!((i["predicted_p"].as_f64().unwrap() - 0.0128).abs() < 1e-4, "{i}");
    assert!(i["pull"].as_f64().unwrap() > 3.0, "{i}");
    assert_eq!(i["pass"], false);
    // The same in arcmin coordinates, and in the human-readable form.
    let (xa, ya) = inst.pixel_to_arcmin(x, y);
    let (o, va) = validate(&vp, &frames, xa, ya, &["--coords", "arcmin"]);
    assert!(o.status.success());
    assert!((va["pull"].as_f64().unwrap() - f("pull")).abs() < 1e-9);
    // A named polarized standard claimed for this unpolarized star fails.
    let (o, h) = validate(&vp, &frames, x, y, &["--star", "Hiltner 652"]);
    assert_eq!(o.status.code(), Some(1), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(h["pass"], false);
    assert_eq!(h["star"], "Hiltner 652");
    // Errors: a position behind the focal-plane mask names the pixel; an unknown star names it.
    let (o, _) = validate(&vp, &frames, x, 20.0, &[]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("mask"));
    let (o, _) = validate(&vp, &frames, x, y, &["--star", "Vega"]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("no standard star 'Vega'"));
}

/// A polarized standard of the list by name whose value comes from SOLVEPOL's V column:
/// HD 147084, 4.17 +- 0.008 % at 32.9 deg (Turnshek et al. 1990). A star of exactly that
/// polarization in the V field's corner is expected at the catalogued 4.17 % and passes; the
/// same frames claimed as HD 23512 (2.26 +- 0.01 % at 29.9 deg, Hsu & Breger 1982) fail.
#[test]
fn polarized_standard_from_solvepol_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let inst = Instrument::load("fors1").unwrap();
    let (x, y) = paper_star_px(&inst);
    let frames = write_star_frames(dir.path(), &inst, x, y, 0.0417, 32.9f64.to_radians());
    let vp = dir.path().join("V.fits");
    v_cal().save(&vp).unwrap();
    let (o, v) = validate(&vp, &frames, x, y, &["--star", "HD 147084"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(v["star"], "HD 147084");
    assert!((v["expected_p"].as_f64().unwrap() - 0.0417).abs() < 1e-12, "{v}");
    assert_eq!(v["pass"], true, "{v}");
    let (o, w) = validate(&vp, &frames, x, y, &["--star", "HD23512"]);
    assert_eq!(o.status.code(), Some(1), "{}", String::from_utf8_lossy(&o.stderr));
    assert!((w["expected_p"].as_f64().unwrap() - 0.0226).abs() < 1e-12, "{w}");
    assert_eq!(w["pass"], false, "{w}");
}
