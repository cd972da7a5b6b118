//! An instrument calibrated the way MOPTOP, RoboPol and SPARC4 are, end to end: frames of
//! standards simulated through a constant response (`[effects.constant_response]`: an
//! instrumental (q0, u0) = (0.4 %, -0.3 %), an efficiency of 0.90 and an angle offset of 3 deg,
//! in the instrument's frame), on a rotator at three position angles on the sky, catalogued;
//! `instpol efficiency` recovers the four numbers within their errors from three unpolarized
//! and three polarized standards; `instpol correct` with the file it writes gives back a
//! different polarized star, catalogued at a fourth position angle, within its errors of the
//! scene's truth. A Stokes map of a polarized sky seen through the response comes back to the
//! sky's polarization by a response file of the scene's numbers. The truth is the scene's.

use crate::common;

use common::{fits_in, run};
use std::path::{Path, PathBuf};

/// The scene's response: q0, u0, efficiency, offset (deg, the angle to add to a measured chi).
const TRUTH: (f64, f64, f64, f64) = (0.004, -0.003, 0.90, 3.0);
/// The filter's HWP zero angle, which the simulator applies too.
const ZERO: f64 = 2.5;
const UNPOL: (f64, f64) = (100.0, 120.0);
const POL: (f64, f64) = (220.0, 280.0);

fn s(p: &Path) -> String {
    p.display().to_string()
}

/// The 400 x 400 px maskless calcite instrument with a zero angle in V and its position angle
/// on the sky in ROTSKYPA (sense -1, offset 90 deg).
fn instrument(dir: &Path) -> PathBuf {
    let text = include_str!("../../../../instruments/calcite.toml")
        .replace("hwp_angle_keyword = \"\"", "hwp_angle_keyword = \"HWPANG\"")
        .replace("nx = 700", "nx = 400")
        .replace("ny = 700", "ny = 400")
        .replace("width_arcmin = 2.49", "width_arcmin = 1.43")
        .replace("height_arcmin = 2.49", "height_arcmin = 1.43")
        .replacen("lambda_eff_nm = 530.0", &format!("lambda_eff_nm = 530.0\nhwp_chi_offset_deg = {ZERO}"), 1)
        .replace(
            "exptime_keyword = \"EXPTIME\"\n",
            "exptime_keyword = \"EXPTIME\"\nsky_angle = { keyword = \"ROTSKYPA\", sense = -1, offset_deg = 90.0 }\n",
        );
    let p = dir.join("rotator.toml");
    std::fs::write(&p, text).unwrap();
    p
}

/// The `[effects]` of every scene: noise, the filter's zero angle and the response.
fn effects(zero_angle: bool) -> String {
    let (q0, u0, eta, k) = TRUTH;
    format!(
        "[effects]\nphoton_noise = true\nread_noise = true\nhwp_chi_offset_from_filter = {zero_angle}\n\
         [effects.constant_response]\nq0 = {q0}\nu0 = {u0}\nefficiency = {eta}\noffset_deg = {k}\n"
    )
}

/// Frames of `stars` (x, y px; p; chi deg on the sky) with the instrument at `pa` deg,
/// catalogued: the catalog's path.
fn catalog(dir: &Path, inst: &Path, name: &str, pa: f64, seed: u64, stars: &[(f64, f64, f64, f64)]) -> PathBuf {
    let mut body = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = {seed}\nsky_pa_deg = {pa}\n\
         hwp_angles_deg = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]\n[output]\nbitpix = -64\n\
         [sky]\nbrightness_e = 50\np = 0.0\nchi_deg = 0\n{}",
        s(inst),
        effects(true)
    );
    for (x, y, p, chi) in stars {
        body += &format!(
            "[[stars]]\nx = {x}\ny = {y}\ncoords = \"pixel\"\nflux_e = 8e5\np = {p}\nchi_deg = {chi}\nfwhm_arcsec = 0.9\n"
        );
    }
    let scene = dir.join(format!("{name}.toml"));
    std::fs::write(&scene, body).unwrap();
    let frames = dir.join(name);
    let (code, _, err) = run(&["simulate", &s(&scene), "--out", &s(&frames)]);
    assert_eq!(code, 0, "simulate {name}: {err}");
    let out = dir.join(format!("{name}.csv"));
    let mut a = vec!["catalog".to_string()];
    a.extend(fits_in(&frames).iter().map(|p| s(p)));
    a.extend(["--instrument", &s(inst), "--aperture", "8", "--annulus", "14,24", "--out", &s(&out)].map(String::from));
    let (code, _, err) = run(&a);
    assert_eq!(code, 0, "catalog {name}: {err}");
    out
}

/// The row of `table` (CSV) nearest `(x, y)`: its named columns.
fn row(table: &Path, (x, y): (f64, f64), names: &[&str]) -> Vec<f64> {
    let mut r = csv::ReaderBuilder::new().comment(Some(b'#')).from_path(table).unwrap();
    let head: Vec<String> = r.headers().unwrap().iter().map(str::to_string).collect();
    let col = |n: &str| head.iter().position(|h| h == n).unwrap_or_else(|| panic!("{n} not in {head:?}"));
    let rows: Vec<Vec<f64>> = r
        .records()
        .map(|rec| rec.unwrap().iter().map(|v| v.trim().parse::<f64>().unwrap_or(f64::NAN)).collect())
        .collect();
    let best = rows
        .iter()
        .min_by(|a, b| {
            let d = |r: &Vec<f64>| (r[col("x")] - x).hypot(r[col("y")] - y);
            d(a).total_cmp(&d(b))
        })
        .unwrap();
    names.iter().map(|n| best[col(n)]).collect()
}

/// The standards at three position angles, the response recovered within 3 of its errors,
/// and a fourth star corrected to the scene's truth within 3 of its errors.
#[test]
fn response_from_simulated_standards_and_applied_by_correct() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let inst = instrument(d);
    // One unpolarized and one polarized standard at each position angle.
    let pol = [(0.0, 0.04, 35.0), (60.0, 0.05, 110.0), (-142.0, 0.03, 160.0)];
    let mut args = vec!["efficiency".to_string()];
    for (k, &(pa, p, chi)) in pol.iter().enumerate() {
        let cat = catalog(
            d,
            &inst,
            &format!("std{k}"),
            pa,
            41 + k as u64,
            &[(UNPOL.0, UNPOL.1, 0.0, 0.0), (POL.0, POL.1, p, chi)],
        );
        args.push("--standard".into());
        args.push(format!("{}:{},{}:unpolarized", s(&cat), UNPOL.0, UNPOL.1));
        args.push("--standard".into());
        args.push(format!("{}:{},{}:{p}+-0.0001/{chi}+-0.05", s(&cat), POL.0, POL.1));
    }
    let cal = d.join("response_V.fits");
    args.extend(["--output".to_string(), s(&cal), "--json".to_string()]);
    let (code, out, err) = run(&args);
    assert_eq!(code, 0, "efficiency: {err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    let num = |k: &str| j[k].as_f64().unwrap_or_else(|| panic!("{k} in {out}"));
    let (q0, u0, eta, k) = TRUTH;
    for (name, truth) in [("q_inst", q0), ("u_inst", u0), ("efficiency", eta), ("offset_deg", k)] {
        let (v, e) = (num(name), num(&format!("sigma_{name}")));
        eprintln!("{name}: {v:.5} +- {e:.5} (truth {truth})");
        assert!((v - truth).abs() < 3.0 * e, "{name} = {v} +- {e}, truth {truth}");
        assert!(e > 0.0 && e < 0.2 * truth.abs().max(0.01), "{name}: error {e} not a measurement's");
    }
    assert_eq!(j["hwp_chi_offset_deg"].as_f64(), Some(ZERO), "the response lives in the catalogs' zero angle");
    // The file says what it is: the catalogs' instrument file and detector (what `catalog`
    // recorded, checked against b3sum there), and the catalogs as its inputs.
    let product = fit::files::calibration::load(&cal).unwrap().product.expect("the response file's product");
    let def = instrument::Instrument::from_file(&inst).unwrap();
    assert_eq!(product.detector_px, Some((def.detector.nx, def.detector.ny)));
    assert_eq!(product.plate.as_deref(), Some("half_wave"));
    if let Some(sums) = common::b3sum(std::slice::from_ref(&inst)) {
        assert_eq!(product.instrument_hash.as_deref(), Some(sums[0].as_str()), "the instrument file's BLAKE3");
    }

    // A different star, at a fourth position angle, corrected to the truth.
    let (p, chi, at): (f64, f64, _) = (0.025, 75.0, (160.0, 200.0));
    let target = catalog(d, &inst, "target", 30.0, 47, &[(at.0, at.1, p, chi)]);
    let corrected = d.join("target_corr.csv");
    let (code, out, err) = run(&["correct", "--cal", &s(&cal), "--in", &s(&target), "--out", &s(&corrected)]);
    assert_eq!(code, 0, "correct: {err}");
    assert!(out.contains("constant response"), "{out}");
    let v = row(&corrected, at, &["q0", "u0", "sigma_q0", "sigma_u0", "q", "u"]);
    let (qt, ut) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
    eprintln!("corrected ({:.5}, {:.5}) +- ({:.5}, {:.5}), truth ({qt:.5}, {ut:.5})", v[0], v[1], v[2], v[3]);
    assert!((v[0] - qt).abs() < 3.0 * v[2] && (v[1] - ut).abs() < 3.0 * v[3], "{v:?} vs ({qt}, {ut})");
    // Uncorrected, the star is off by far more than that (the efficiency alone takes 10 % of P).
    assert!((v[4].hypot(v[5]) - p).abs() > 5.0 * v[2], "the measured star {v:?} is not already the truth");
}

/// A map of a sky of P = 6.45 %, chi = 68.4 deg seen through the response on a strip
/// instrument (the tiny FORS1, no zero angle) is corrected by a response file of the scene's
/// numbers back to the sky: the bins' weighted mean within 3 of its error, their pulls of
/// unit scatter.
#[test]
fn a_map_through_the_response_is_corrected_to_the_sky() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let tiny = common::tiny_fors1(d, 8.0, 20);
    let (p, chi): (f64, f64) = (0.0645, 68.4);
    std::fs::write(
        d.join("sky.toml"),
        format!(
            "instrument = \"{}\"\nfilter = \"V\"\nseed = 5\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n[sky]\nbrightness_e = 3000\np = {p}\nchi_deg = {chi}\n{}",
            s(&tiny),
            effects(false)
        ),
    )
    .unwrap();
    let (code, _, err) = run(&["simulate", &s(&d.join("sky.toml")), "--out", &s(&d.join("sky"))]);
    assert_eq!(code, 0, "{err}");
    let map = d.join("map.fits");
    let mut a = vec!["reduce".to_string()];
    a.extend(fits_in(&d.join("sky")).iter().map(|p| s(p)));
    a.extend(["--instrument", &s(&tiny), "--bin", "8", "--out", &s(&map)].map(String::from));
    let (code, _, err) = run(&a);
    assert_eq!(code, 0, "reduce: {err}");
    let (q0, u0, efficiency, offset_deg) = TRUTH;
    let cal = d.join("response.fits");
    fit::response::cal::ResponseCal {
        instrument: "FORS1".into(),
        filter: "V".into(),
        plate: "half_wave".into(),
        hwp_chi_offset_deg: 0.0,
        response: field::ConstantResponse { q0, u0, efficiency, offset_deg },
        covariance: [[0.0; 4]; 4],
        n_unpolarized: 0,
        n_polarized: 0,
        product: None,
    }
    .save(&cal)
    .unwrap();
    let out = d.join("map_corr.fits");
    let (code, _, err) = run(&["correct", "--cal", &s(&cal), "--in", &s(&map), "--out", &s(&out)]);
    assert_eq!(code, 0, "correct: {err}");
    let m = skyfield::StokesMap::read_fits(&out).unwrap();
    let (qs, us) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
    let bins: Vec<usize> = (0..m.q.len()).filter(|&k| m.valid[k]).collect();
    assert!(bins.len() >= 10, "{} valid bins", bins.len());
    for (v, sig, truth, what) in [(&m.q, &m.sigma_q, qs, "q"), (&m.u, &m.sigma_u, us, "u")] {
        let w: f64 = bins.iter().map(|&k| sig[k].powi(-2)).sum();
        let mean = bins.iter().map(|&k| v[k] * sig[k].powi(-2)).sum::<f64>() / w;
        let pulls: Vec<f64> = bins.iter().map(|&k| (v[k] - truth) / sig[k]).collect();
        let rms = (pulls.iter().map(|x| x * x).sum::<f64>() / pulls.len() as f64).sqrt();
        eprintln!(
            "{what}: mean {mean:.5} +- {:.5} (truth {truth:.5}), pull rms {rms:.2} over {} bins",
            w.powf(-0.5),
            bins.len()
        );
        assert!((mean - truth).abs() < 3.0 * w.powf(-0.5), "{what}: {mean} vs {truth}");
        assert!(rms > 0.6 && rms < 1.5, "{what}: pull rms {rms}");
    }
}

/// `zero-angle` reports the efficiency beside the zero angle when the standards' catalogued P
/// is known: one star measured at 3.6 +- 0.04 % against 4.0 +- 0.02 % catalogued gives 0.9 with
/// the error `sqrt((0.04 / 4)^2 + (0.9 0.02 / 4)^2)` (written out). `efficiency` refuses, by
/// name, standards without an unpolarized one and a polarized one catalogued at P = 0.
#[test]
fn zero_angle_reports_the_efficiency_and_efficiency_refuses() {
    let dir = tempfile::tempdir().unwrap();
    let t = dir.path().join("measured.csv");
    std::fs::write(
        &t,
        "label,chi_measured_deg,sigma_chi_measured_deg,chi_catalogue_deg,sigma_chi_catalogue_deg,p_measured,sigma_p_measured,p_catalogue,sigma_p_catalogue,filter\n\
         A,10,0.3,12,0.1,0.036,0.0004,0.04,0.0002,V\n",
    )
    .unwrap();
    let (code, out, err) = run(&["zero-angle", "--measured", &s(&t), "--json"]);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    let e = &j["efficiency"];
    let want = (0.01f64.powi(2) + (0.9f64 * 0.005).powi(2)).sqrt();
    assert!((e["efficiency"].as_f64().unwrap() - 0.9).abs() < 1e-12, "{e}");
    assert!((e["sigma_efficiency"].as_f64().unwrap() - want).abs() < 1e-12, "{e}");
    let (code, out, _) = run(&["zero-angle", "--measured", &s(&t)]);
    assert_eq!(code, 0);
    assert!(out.contains("polarimetric efficiency (measured P over catalogued P): 0.9000 +- "), "{out}");

    let cat = dir.path().join("rows.csv");
    std::fs::write(&cat, "x,y,q,u,sigma_q,sigma_u\n10,10,0.004,-0.003,3e-4,3e-4\n30,30,0.018,0.030,3e-4,3e-4\n")
        .unwrap();
    let std = |xy: &str, what: &str| format!("{}:{xy}:{what}", s(&cat));
    let (pol, unpol, zero) =
        (std("30,30", "0.04+-0.0001/30+-0.1"), std("10,10", "unpolarized"), std("30,30", "0+-0.0001/30+-0.1"));
    let base = ["efficiency", "--instrument", "calcite", "--filter", "V", "--standard"];
    let (code, _, err) = run(&[&base[..], &[pol.as_str()]].concat());
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("no unpolarized standard"), "{err}");
    let (code, _, err) = run(&[&base[..], &[unpol.as_str(), "--standard", zero.as_str()]].concat());
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("catalogued P = 0"), "{err}");
}
