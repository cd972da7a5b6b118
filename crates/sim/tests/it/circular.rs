//! Circular polarization end to end: frames of a maskless calcite polarimeter with a
//! quarter-wave plate (`instruments/calcite_qwp.toml`), simulated for stars of given
//! `(q, u, v)` with photon and read noise, measured by the photometry and demodulated
//! (`skyfield::photometry::circular`, `stokes::CircularSolver`) at 2 and 4 plate positions.
//!
//! The expected fluxes are computed here by a Jones calculation, independent of the crates'
//! Mueller code: each star's light is an unpolarized part (two incoherent orthogonal Jones
//! vectors) plus a fully polarized part (one Jones vector with `V = 2 Im(E_x^* E_y)`, the IAU
//! sign), through the Jones matrix of a quarter-wave plate and an ideal Wollaston (o beam: the
//! intensity along x, e beam: along y).

use sim::Scene;
use skyfield::photometry::{circular, circular_with, layout_for, Aperture, PhotOptions};
use skyfield::reduce::{read_frames, FrameSet};
use std::path::{Path, PathBuf};

use crate::jones;
use jones::jones_fluxes;

/// The expected `F` at a plate angle, from the Jones calculation.
fn jones_f(q: f64, u: f64, v: f64, axis: f64) -> f64 {
    let (o, e) = jones_fluxes(q, u, v, axis);
    (o - e) / (o + e)
}

/// The example QWP instrument with a plate-angle keyword in its headers.
fn qwp_instrument(dir: &Path) -> PathBuf {
    let text = include_str!("../../../../instruments/calcite_qwp.toml")
        .replace("hwp_angle_keyword = \"\"", "hwp_angle_keyword = \"QWPANG\"");
    let p = dir.join("calcite_qwp.toml");
    std::fs::write(&p, text).unwrap();
    p
}

/// Stars with V/I of -2 %, 0, +1 % and +3 %, each without and with linear polarization (up
/// to 5 %): `(x, y, p, chi_deg, v)`, on a grid whose e images (70 px to the right) stay clear.
fn stars() -> Vec<(f64, f64, f64, f64, f64)> {
    let vs = [-0.02, 0.0, 0.01, 0.03];
    let mut out = Vec::new();
    for (k, &v) in vs.iter().enumerate() {
        for (l, &(p, chi)) in [(0.0, 0.0), (0.05 - 0.01 * k as f64, 25.0 + 40.0 * k as f64)].iter().enumerate() {
            let x = 90.0 + 150.0 * k as f64 + 0.31 * l as f64;
            let y = 150.0 + 300.0 * l as f64 - 0.17 * k as f64;
            out.push((x, y, p, chi, v));
        }
    }
    out
}

fn scene(dir: &Path, inst: &Path, angles: &str, noise: bool, effects: &str) -> Scene {
    let mut body = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 11\nhwp_angles_deg = {angles}\n[output]\nbitpix = -32\n{}[effects]\nphoton_noise = {noise}\nread_noise = {noise}\n{effects}\n",
        inst.display(),
        if noise { "[sky]\nbrightness_e = 300\n" } else { "" }
    );
    for (x, y, p, chi, v) in stars() {
        body += &format!(
            "[[stars]]\nx = {x}\ny = {y}\ncoords = \"pixel\"\nflux_e = 2e6\np = {p}\nchi_deg = {chi}\nv = {v}\nfwhm_arcsec = 0.9\n"
        );
    }
    Scene::from_toml_str(&body, &dir.join("scene.toml")).unwrap()
}

fn frame_set(frames: &[PathBuf], inst: &instrument::Instrument) -> FrameSet {
    FrameSet::from_frames(read_frames(frames, inst, &|| {}).unwrap(), inst, true).unwrap()
}

/// The Jones calculation agrees with the closed form of `stokes::circular` (`F = q cos^2 2t +
/// u sin 2t cos 2t + v sin 2t`), so `(F(45) - F(-45)) / 2` of it is the star's `v`.
#[test]
fn jones_calculation_is_the_modulation() {
    for (_, _, p, chi, v) in stars() {
        let (q, u) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
        for t in [-45.0f64, 0.0, 30.0, 45.0, 135.0, 225.0] {
            let t = t.to_radians();
            let (s2, c2) = (2.0 * t).sin_cos();
            assert!((jones_f(q, u, v, t) - (q * c2 * c2 + u * s2 * c2 + v * s2)).abs() < 1e-14);
        }
        let pair = 0.5 * (jones_f(q, u, v, 45f64.to_radians()) - jones_f(q, u, v, -45f64.to_radians()));
        assert!((pair - v).abs() < 1e-15);
    }
}

/// Simulated QWP frames at 2 (-45, 45 deg) and 4 (-45, 45, 135, 225 deg) positions with
/// photon and read noise: every star's V/I within its error of the Jones calculation's (pulls
/// over 16 values with an RMS near 1, none beyond 4), and each frame's measured `F` within its
/// error of the Jones `F` at that angle; the catalog's rows carry the same V/I.
#[test]
fn qwp_frames_give_v_within_errors() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = qwp_instrument(dir.path());
    let inst = instrument::Instrument::load(inst_path.to_str().unwrap()).unwrap();
    let ap = Aperture { radius_px: 9.0, annulus: Some((14.0, 24.0)) };
    let mut pulls = Vec::new();
    let mut f_pulls = Vec::new();
    for (n, angles) in [(2, "[-45, 45]"), (4, "[-45, 45, 135, 225]")] {
        let sc = scene(dir.path(), &inst_path, angles, true, "");
        let out = sim::simulate(&sc, &dir.path().join(format!("frames{n}")), &|| {}).unwrap();
        let set = frame_set(&out.frames, &inst);
        assert_eq!(set.angles_deg.len(), n);
        let cfg = skyfield::catalog::CatalogConfig {
            detect: skyfield::detect::DetectConfig { fwhm_px: 4.2, ..Default::default() },
            radius: skyfield::photometry::ApertureRadius::Px(9.0),
            annulus: Some((14.0, 24.0)),
            ..Default::default()
        };
        let cat = skyfield::catalog::catalog(&set, &inst, &cfg).unwrap();
        assert_eq!(cat.qwp_zero_angle_deg, Some(0.0));
        assert_eq!(cat.rows.len(), stars().len());
        for (x, y, p, chi, v) in stars() {
            let (q, u) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
            let ph = circular(&set, &inst, x, y, &ap).unwrap();
            let want = 0.5 * (jones_f(q, u, v, 45f64.to_radians()) - jones_f(q, u, v, -45f64.to_radians()));
            let c = ph.circular;
            let pull = (c.v - want) / c.sigma_v();
            assert!(pull.abs() < 4.0, "{n} positions, star at ({x}, {y}): v = {} +- {} vs {want}", c.v, c.sigma_v());
            // sigma_v as eq:sigp-like closed form: 1 / (sqrt(N) SNR), SNR of one exposure's
            // f_O + f_E with photon noise (the read and background noise add a little).
            let snr = (ph.f_o[0] + ph.f_e[0]).sqrt();
            assert!(c.sigma_v() > 1.0 / ((n as f64).sqrt() * snr) && c.sigma_v() < 1.3 / ((n as f64).sqrt() * snr));
            pulls.push(pull);
            // The catalog measures the same star the same way (its row's v, sigma_v).
            let row = cat.rows.iter().find(|r| (r.x - x).hypot(r.y - y) < 1.0).expect("star in the catalog");
            let (rv, rs) = (row.v.unwrap(), row.sigma_v.unwrap());
            assert!(((rv - want) / rs).abs() < 4.0 && (rs / c.sigma_v() - 1.0).abs() < 0.05, "{rv} +- {rs}");
            assert!(row.q.is_nan() && row.p.is_nan());
            for (i, a) in set.angles_deg.iter().enumerate() {
                let f = stokes::normalized_difference(ph.f_o[i], ph.f_e[i]);
                let s = stokes::sigma_normalized_difference(ph.f_o[i], ph.f_e[i], ph.sigma_o[i], ph.sigma_e[i]);
                f_pulls.push((f - jones_f(q, u, v, a.to_radians())) / s);
            }
        }
    }
    let rms = |v: &[f64]| (v.iter().map(|p| p * p).sum::<f64>() / v.len() as f64).sqrt();
    eprintln!(
        "V/I pulls over {} values: RMS {:.2}; F pulls over {}: RMS {:.2}",
        pulls.len(),
        rms(&pulls),
        f_pulls.len(),
        rms(&f_pulls)
    );
    assert!(rms(&pulls) > 0.5 && rms(&pulls) < 1.5, "{pulls:?}");
    assert!(f_pulls.iter().all(|p| p.abs() < 4.0) && rms(&f_pulls) > 0.5 && rms(&f_pulls) < 1.5, "{f_pulls:?}");
}

/// A plate whose fast axis sits 3 deg from where the headers say (noise-free frames, so that
/// the biases are seen to 1e-5): the -45/+45 pair reduced as if the axis were where the headers
/// say is biased only at second order (`v cos 6 deg`: 0.55 % of `v`), whatever the linear
/// polarization; a single position (+45 deg, `v = F`, the beams'
/// ratio known) reduced the same way is off by `-u sin 6 deg cos 6 deg`, first order in the
/// offset; with the known offset applied the pair gives `v` itself.
#[test]
fn zero_angle_error_is_second_order_for_the_pair() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = qwp_instrument(dir.path());
    let inst = instrument::Instrument::load(inst_path.to_str().unwrap()).unwrap();
    let sc = scene(dir.path(), &inst_path, "[-45, 45]", false, "qwp_zero_angle_deg = 3.0");
    let out = sim::simulate(&sc, &dir.path().join("frames"), &|| {}).unwrap();
    let set = frame_set(&out.frames, &inst);
    let g = layout_for(&set, &inst).unwrap();
    let ap = Aperture { radius_px: 9.0, annulus: Some((14.0, 24.0)) };
    let e = 3f64.to_radians();
    let mut worst_single: f64 = 0.0;
    for (x, y, p, chi, v) in stars() {
        let (q, u) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
        let ignoring = circular_with(&set, &g, x, y, &ap, &PhotOptions::default(), 0.0).unwrap();
        // The Jones calculation at the true axis angles, reduced as if the axis were at +-45.
        let want_ignoring =
            0.5 * (jones_f(q, u, v, 45f64.to_radians() + e) - jones_f(q, u, v, -45f64.to_radians() + e));
        assert!((want_ignoring - v * (2.0 * e).cos()).abs() < 1e-15);
        assert!((ignoring.circular.v - want_ignoring).abs() < 2e-5, "{} vs {want_ignoring}", ignoring.circular.v);
        assert!((ignoring.circular.v - v).abs() < 0.006 * v.abs() + 2e-5);
        let single = stokes::normalized_difference(ignoring.f_o[1], ignoring.f_e[1]);
        let first_order = -u * (2.0 * e).sin() * (2.0 * e).cos() + q * (2.0 * e).sin().powi(2);
        assert!((single - v * (2.0 * e).cos() - first_order).abs() < 2e-5, "single {single}");
        worst_single = worst_single.max((single - v).abs());
        let known = circular_with(&set, &g, x, y, &ap, &PhotOptions::default(), 3.0).unwrap();
        assert!((known.circular.v - v).abs() < 2e-5, "{} vs {v}", known.circular.v);
    }
    // The single position's first-order error reaches u sin 6 deg: 3.5e-3 for the 5 %-polarized
    // star, ten times the pair's worst second-order error (1.6e-4 for v = 3 %).
    assert!(worst_single > 3e-3, "{worst_single}");
}
