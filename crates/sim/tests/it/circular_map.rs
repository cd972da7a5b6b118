//! A per-pixel `V/I` map end to end: frames of a FORS-like strip polarimeter with a
//! quarter-wave plate (an instrument file written here: FORS1's layout, made small, with
//! `plate = "quarter_wave"` and a plate zero angle of 1.5 deg), simulated for a sky of known
//! `V/I` with 3 % linear polarization, a brightness gradient, photon and read noise, at 2
//! (-45, 45 deg) and 4 (-45, 45, 135, 225 deg) plate positions, and reduced to a binned map
//! (`skyfield::reduce::reduce_circular_files_with`).
//!
//! The expected `V/I` of every bin comes from a Jones calculation written here, independent of
//! the crates' Mueller and demodulation code: the sky's light (an unpolarized part plus a fully
//! polarized Jones vector with `V = 2 Im(E_x^* E_y)`, the IAU sign) through the Jones matrix of
//! a quarter-wave plate at its axis angles and an ideal Wollaston, demodulated with the closed
//! form of the offset-only projection these sets reduce to (`w_i = sin 2theta_i / sum sin^2
//! 2theta_j`).

use skyfield::reduce::{read_frames, reduce_circular_files_with, reduce_circular_set, FrameSet, ReduceConfig};
use std::path::{Path, PathBuf};

use crate::jones;
use jones::jones_fluxes;

/// FORS1's strip layout (instruments/fors1.toml) made small for a test: 200 x 260 px, three
/// strips of 40 px, a quarter-wave plate whose fast axis sits 1.5 deg from the header's angle.
fn instrument_file(dir: &Path) -> PathBuf {
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 200")
        .replace("ny = 2048", "ny = 260")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 8.0")
        .replace("strip_count = 9", "strip_count = 3")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 10")
        .replace("[polarimetry]\n", "[polarimetry]\nplate = \"quarter_wave\"\n")
        .replace("lambda_eff_nm = 554.0", "lambda_eff_nm = 554.0\nqwp_zero_angle_deg = 1.5");
    let p = dir.join("fors_qwp.toml");
    std::fs::write(&p, text).unwrap();
    p
}

const ZERO_DEG: f64 = 1.5;
const SKY_V: f64 = 0.02;
const SKY_P: f64 = 0.03;
const SKY_CHI_DEG: f64 = 20.0;

fn scene(dir: &Path, inst: &Path, angles: &str) -> sim::Scene {
    let body = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 5\nhwp_angles_deg = {angles}\n[output]\nbitpix = -32\n\
         [sky]\nbrightness_e = 5000\np = {SKY_P}\nchi_deg = {SKY_CHI_DEG}\nv = {SKY_V}\n\
         gradient_e_per_arcmin = [900, -600]\n\
         [effects]\nphoton_noise = true\nread_noise = true\nqwp_zero_angle_deg = {ZERO_DEG}\n",
        inst.display()
    );
    sim::Scene::from_toml_str(&body, &dir.join("scene.toml")).unwrap()
}

/// The Jones calculation's `V/I` for plate angles `angles_deg` (the fast axis 1.5 deg on):
/// `sum w_i F_i` with the closed-form weights. At these sets the offset, `cos 4theta` and
/// `sin 4theta` columns are one column, so the weights are `sin 2theta_i` less its mean,
/// normalized (which is `sin 2theta_i / sum sin^2 2theta_j` here, the mean being 0).
fn jones_v(angles_deg: &[f64]) -> f64 {
    let (q, u) = (SKY_P * (2.0 * SKY_CHI_DEG.to_radians()).cos(), SKY_P * (2.0 * SKY_CHI_DEG.to_radians()).sin());
    let axes: Vec<f64> = angles_deg.iter().map(|a| (a + ZERO_DEG).to_radians()).collect();
    let s2: Vec<f64> = axes.iter().map(|t| (2.0 * t).sin()).collect();
    let mean = s2.iter().sum::<f64>() / s2.len() as f64;
    let r: Vec<f64> = s2.iter().map(|s| s - mean).collect();
    let rr: f64 = r.iter().map(|x| x * x).sum();
    axes.iter()
        .zip(&r)
        .map(|(&t, ri)| {
            let (o, e) = jones_fluxes(q, u, SKY_V, t);
            ri / rr * (o - e) / (o + e)
        })
        .sum()
}

/// Simulated strip frames of a sky with V/I = 2 % (and 3 % linear polarization, a brightness
/// gradient, a plate zero angle of 1.5 deg) reduce at 2 and 4 plate positions to V maps whose
/// bins agree with the Jones calculation's V/I within their errors: pulls over every valid bin
/// with an RMS near 1 and none beyond 4.5; the photon error agrees with the scatter and with
/// the closed form `1 / sqrt(N n I)` (N positions, n pixels of I e- each); the map records the
/// plate angles and zero angle; the frames in memory give the same map to the bit.
#[test]
fn qwp_strip_frames_reduce_to_the_sky_v() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = instrument_file(dir.path());
    let inst = instrument::Instrument::load(inst_path.to_str().unwrap()).unwrap();
    let cfg = ReduceConfig { bin_px: 10, ..Default::default() };
    for (n, angles, list) in
        [(2, "[-45, 45]", vec![-45.0, 45.0]), (4, "[-45, 45, 135, 225]", vec![-45.0, 45.0, 135.0, 225.0])]
    {
        let want = jones_v(&list);
        // The Jones calculation's demodulation gives the sky's V/I (the linear terms cancel).
        assert!((want - SKY_V).abs() < 1e-12, "{n} positions: Jones V/I {want}");
        let out =
            sim::simulate(&scene(dir.path(), &inst_path, angles), &dir.path().join(format!("f{n}")), &|| {}).unwrap();
        let r = reduce_circular_files_with(&out.frames, &inst, &cfg, &Default::default(), &|| {}).unwrap();
        let m = &r.map;
        assert_eq!(m.plate_angles_deg, list);
        assert_eq!(m.qwp_zero_angle_deg, ZERO_DEG);
        // Three strips of 40 px: 4 bin rows each, 20 bins across.
        assert_eq!(m.n_valid(), 3 * 4 * 20, "{n} positions");
        let mut pulls = Vec::new();
        for (k, _, _) in m.valid_bins() {
            let pull = (m.v[k] - want) / m.sigma_v[k];
            assert!(pull.abs() < 4.5, "{n} positions, bin {k}: V/I {} +- {} vs {want}", m.v[k], m.sigma_v[k]);
            pulls.push(pull);
            // Photon + read noise of n pixels of I e- at N positions: sigma_F = 1/sqrt(I) per
            // pixel and exposure (sigma_F^2 = (I + 2 rn^2) / I^2, rn = 5 e-), sigma_v =
            // sigma_F / sqrt(N n) for weights +-1/N (the zero angle's cos 3 deg is 0.14 %).
            let closed = ((m.intensity[k] + 2.0 * 25.0) / m.intensity[k].powi(2)).sqrt()
                / ((n * m.n_pixels[k] as usize) as f64).sqrt();
            assert!((m.sigma_v_phot[k] / closed - 1.0).abs() < 0.02, "bin {k}: {} vs {closed}", m.sigma_v_phot[k]);
            assert!((m.sigma_v[k] / m.sigma_v_phot[k] - 1.0).abs() < 0.35, "bin {k}");
        }
        let rms = (pulls.iter().map(|p| p * p).sum::<f64>() / pulls.len() as f64).sqrt();
        let mean = pulls.iter().sum::<f64>() / pulls.len() as f64;
        eprintln!("{n} positions: {} bins, pull RMS {rms:.3}, mean {mean:+.3}", pulls.len());
        assert!((0.85..1.15).contains(&rms), "{n} positions: pull RMS {rms}");
        assert!(mean.abs() < 4.0 / (pulls.len() as f64).sqrt(), "{n} positions: mean pull {mean}");
        // The frames in memory reduce to the same map.
        let set = FrameSet::from_frames(read_frames(&out.frames, &inst, &|| {}).unwrap(), &inst, true).unwrap();
        let mem = reduce_circular_set(&set, &inst, &cfg).unwrap().map;
        assert_eq!(mem.valid, m.valid);
        for k in 0..m.v.len() {
            assert_eq!(mem.v[k].to_bits(), m.v[k].to_bits(), "bin {k}");
            assert_eq!(mem.sigma_v[k].to_bits(), m.sigma_v[k].to_bits(), "bin {k}");
        }
    }
}

/// The plate decides the map: a quarter-wave instrument's frames are refused by the linear
/// reduction (naming the plate and what works), a half-wave instrument's by the circular one;
/// the dispatching reduction gives the V map; a set that does not determine V (0, 90 deg) is
/// refused by name.
#[test]
fn the_plate_decides_the_map() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = instrument_file(dir.path());
    let inst = instrument::Instrument::load(inst_path.to_str().unwrap()).unwrap();
    let cfg = ReduceConfig { bin_px: 10, ..Default::default() };
    let out = sim::simulate(&scene(dir.path(), &inst_path, "[-45, 45]"), &dir.path().join("f"), &|| {}).unwrap();
    let refused = |r: Result<_, skyfield::Error>| match r {
        Ok(_) => panic!("accepted"),
        Err(e) => e.to_string(),
    };
    let e =
        refused(skyfield::reduce::reduce_files_with(&out.frames, &inst, &cfg, &Default::default(), &|| {}).map(|_| ()));
    assert!(e.contains("quarter-wave plate") && e.contains("V/I map"), "{e}");
    match skyfield::reduce::reduce_for_plate(&out.frames, &inst, &cfg, &Default::default(), &|| {}).unwrap() {
        skyfield::reduce::PlateReduced::Circular(r) => assert!(r.map.n_valid() > 0),
        skyfield::reduce::PlateReduced::Linear(_) => panic!("a quarter-wave plate gave a Q/U map"),
    }
    let hwp = instrument::Instrument::load("fors1").unwrap();
    let e = refused(reduce_circular_files_with(&out.frames, &hwp, &cfg, &Default::default(), &|| {}).map(|_| ()));
    assert!(e.contains("half-wave plate") && e.contains("does not modulate V/I"), "{e}");
    // 0 and 90 deg do not determine V: the simulator refuses such a scene, so the frames here
    // are the 2-position set read by an instrument file without the angle keyword, their
    // angles given as 0 and 90 deg.
    let text = std::fs::read_to_string(&inst_path).unwrap();
    // (With the plate's zero angle of 1.5 deg, 0 and 90 deg would be axes at 1.5 and 91.5 deg,
    // which determine V, poorly: the zero angle is set to 0 here.)
    let blind = text
        .replace("hwp_angle_keyword = \"HIERARCH ESO INS RETA2 POSANG\"", "hwp_angle_keyword = \"\"")
        .replace("qwp_zero_angle_deg = 1.5", "qwp_zero_angle_deg = 0.0");
    assert_ne!(blind, text);
    let blind = instrument::Instrument::from_toml_str(&blind, &dir.path().join("blind.toml")).unwrap();
    let opts = skyfield::calib::ReadOptions { hwp_angles_deg: Some(vec![0.0, 90.0]), ..Default::default() };
    let e = refused(reduce_circular_files_with(&out.frames, &blind, &cfg, &opts, &|| {}).map(|_| ()));
    assert!(e.contains("[0, 90] deg do not determine V"), "{e}");
}

/// The sky's V reaches the frames through the plate alone: a scene that puts the field's
/// elements or a telescope in front of it is refused, naming `sky.v` and why (a telescope in
/// front of a quarter-wave plate is refused already; the telescope case is a half-wave
/// instrument's, whose plate passes a little V when its retardance is off).
#[test]
fn a_sky_v_behind_the_field_or_a_telescope_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let inst = instrument_file(dir.path());
    let base = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nhwp_angles_deg = [-45, 45]\n[sky]\nbrightness_e = 100\nv = 0.01\n",
        inst.display()
    );
    let field = format!("{base}[effects]\ninstpol = {{ kind = \"radial\", coeffs_percent = [0, 0.05] }}\n");
    let e = match sim::Scene::from_toml_str(&field, &dir.path().join("field.toml")).map(|sc| sim::Plan::build(&sc)) {
        Ok(Ok(_)) => panic!("a sky's V behind an instrumental field was accepted"),
        Ok(Err(e)) | Err(e) => e.to_string(),
    };
    assert!(e.contains("sky.v") && e.contains("instrumental field"), "{e}");
    // (A quarter-wave instrument behind a telescope is refused as such: a half-wave one here.)
    let tel = "instrument = \"fors1\"\nfilter = \"V\"\n[sky]\nbrightness_e = 100\nv = 0.01\n\
               [telescope]\nmetal = \"aluminium\"\ndec_deg = -30\nha_start_deg = 15\n";
    let e = match sim::Scene::from_toml_str(tel, &dir.path().join("tel.toml")) {
        Ok(_) => panic!("a sky's V behind a telescope was accepted"),
        Err(e) => e.to_string(),
    };
    assert!(e.contains("sky.v") && e.contains("[telescope]"), "{e}");
}
