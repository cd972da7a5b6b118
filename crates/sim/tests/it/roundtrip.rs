//! Simulate small scenes and reduce them with `skyfield`: each effect alone must produce the
//! signature the paper derives, and the reduction must return what went in.

use sim::{Plan, Scene};
use skyfield::beams::BeamGeometry;
use skyfield::reduce::{reduce_files, FrameSet, ReduceConfig};
use std::path::{Path, PathBuf};

/// A 256 x 256 detector, 0.2"/px, 8" throw (40 px strips), 3 strips from row 8.
fn tiny_instrument(dir: &Path) -> PathBuf {
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 256")
        .replace("ny = 2048", "ny = 256")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 8.0")
        .replace("strip_count = 9", "strip_count = 3")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 8");
    let p = dir.join("tiny.toml");
    std::fs::write(&p, text).unwrap();
    p
}

/// One 100-px strip (rows 20..120 o, 120..220 e) for photometry.
fn tall_instrument(dir: &Path) -> PathBuf {
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 256")
        .replace("ny = 2048", "ny = 256")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 20.0")
        .replace("strip_count = 9", "strip_count = 1")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 20");
    let p = dir.join("tall.toml");
    std::fs::write(&p, text).unwrap();
    p
}

fn scene(dir: &Path, inst: &Path, body: &str) -> Scene {
    let text = format!("instrument = \"{}\"\nfilter = \"V\"\nseed = 11\n{body}", inst.display());
    Scene::from_toml_str(&text, &dir.join("scene.toml")).unwrap()
}

fn run(dir: &Path, sc: &Scene, sub: &str) -> (Vec<PathBuf>, instrument::Instrument) {
    let out = dir.join(sub);
    let s = sim::simulate(sc, &out, &|| {}).unwrap();
    (s.frames, instrument::Instrument::load(&sc.instrument).unwrap())
}

fn q_u(p: f64, chi_deg: f64) -> (f64, f64) {
    let c = 2.0 * chi_deg.to_radians();
    (p * c.cos(), p * c.sin())
}

/// Per-pixel F_i of every sky pixel, frame by frame (the one F of `stokes`).
fn pixel_f(frames: &[PathBuf], inst: &instrument::Instrument) -> Vec<Vec<f64>> {
    let g = BeamGeometry::new(inst);
    frames
        .iter()
        .map(|p| {
            let fr = skyfield::io::read_frame(p, inst).unwrap();
            g.sky_pixels()
                .map(|(x, y)| {
                    let (o, e) = g.beams_of_sky(x, y).unwrap();
                    stokes::normalized_difference(fr.data[o], fr.data[e])
                })
                .collect()
        })
        .collect()
}

#[test]
fn ideal_scene_round_trips_to_1e_10() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let (q0, u0) = q_u(0.0174, -53.8);
    let sc = scene(
        dir.path(),
        &inst,
        "[output]\nbitpix = -64\n[sky]\nbrightness_e = 20000\np = 0.0174\nchi_deg = -53.8\ngradient_e_per_arcmin = [300, -200]\n",
    );
    let (frames, inst) = run(dir.path(), &sc, "ideal");
    assert_eq!(frames.len(), 4);
    let r = reduce_files(&frames, &inst, &ReduceConfig::default(), &|| {}).unwrap();
    let m = &r.map;
    assert!(m.n_valid() >= 20, "{}", m.n_valid());
    for (k, _, _) in m.valid_bins() {
        assert!((m.q[k] - q0).abs() < 1e-10 && (m.u[k] - u0).abs() < 1e-10, "bin {k}: {} {}", m.q[k], m.u[k]);
        assert!((m.p[k] - 0.0174).abs() < 1e-10);
        assert!((m.chi[k].to_degrees() - (180.0 - 53.8)).abs() < 1e-7);
    }
    assert!(r.warnings.is_empty(), "{:?}", r.warnings);
}

/// eq:sigp: with photon noise only, the scatter of bins is sigma_P / sqrt(n) with
/// sigma_P = 1 / (sqrt(N/2) SNR), SNR = sqrt(I) of one exposure's intensity image.
#[test]
fn photon_noise_bin_scatter_matches_eq_sigp() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let (q0, u0) = q_u(0.02, 30.0);
    let i_sky: f64 = 10000.0;
    let sc = scene(
        dir.path(),
        &inst,
        &format!("[output]\nbitpix = -64\n[sky]\nbrightness_e = {i_sky}\np = 0.02\nchi_deg = 30\n[effects]\nphoton_noise = true\n"),
    );
    let (frames, inst) = run(dir.path(), &sc, "noise");
    let cfg = ReduceConfig { bin_px: 4, ..Default::default() };
    let m = reduce_files(&frames, &inst, &cfg, &|| {}).unwrap().map;
    let sig_p = 1.0 / ((4.0f64 / 2.0).sqrt() * i_sky.sqrt());
    let (mut zz, mut n, mut ratio) = (0.0, 0.0, 0.0);
    for (k, _, _) in m.valid_bins() {
        let s = sig_p / (m.n_pixels[k] as f64).sqrt();
        zz += ((m.q[k] - q0) / s).powi(2) + ((m.u[k] - u0) / s).powi(2);
        ratio += m.sigma_q_phot[k] / s;
        n += 1.0;
    }
    let rms = (zz / (2.0 * n)).sqrt();
    assert!(n > 1500.0, "{n} bins");
    assert!((rms - 1.0).abs() < 0.05, "bin scatter / eq:sigp = {rms}");
    // The propagated photon error is eq:sigp to O(P^2).
    assert!((ratio / n - 1.0).abs() < 0.01, "{}", ratio / n);
}

/// Section wollaston: t alone gives F_i = 2t - 1 for an unpolarized sky; N = 4 cancels it,
/// N = 2 gives P = sqrt(2) (2t - 1) at chi = pi/8.
#[test]
fn wollaston_t_signature_and_cancellation() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let t = 0.53;
    let body = format!("[output]\nbitpix = -64\n[sky]\nbrightness_e = 5000\n[effects]\nwollaston = {{ t = {t} }}\n");
    let sc = scene(dir.path(), &inst, &body);
    let (frames, instr) = run(dir.path(), &sc, "t4");
    for f in pixel_f(&frames, &instr) {
        assert!(f.iter().all(|v| (v - (2.0 * t - 1.0)).abs() < 1e-12));
    }
    let m = reduce_files(&frames, &instr, &ReduceConfig::default(), &|| {}).unwrap().map;
    for (k, _, _) in m.valid_bins() {
        assert!(m.q[k].abs() < 1e-12 && m.u[k].abs() < 1e-12);
    }
    let sc2 = scene(dir.path(), &inst, &format!("hwp_angles_deg = [0, 22.5]\n{body}"));
    let (frames, instr) = run(dir.path(), &sc2, "t2");
    let m = reduce_files(&frames, &instr, &ReduceConfig::default(), &|| {}).unwrap().map;
    for (k, _, _) in m.valid_bins() {
        assert!((m.p[k] - 2f64.sqrt() * (2.0 * t - 1.0)).abs() < 1e-12);
        assert!((m.chi[k].to_degrees() - 22.5).abs() < 1e-9);
    }
}

/// Section postwp: B alone gives F_i = B cos 2phi at every angle, i.e. a0 = B cos 2phi
/// (eq:a0); N = 4 cancels it, N = 2 does not.
#[test]
fn post_analyzer_gives_a0_and_cancels_for_n4() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let (b, phi) = (0.004, 25.0f64);
    let body =
        format!("[output]\nbitpix = -64\n[sky]\nbrightness_e = 5000\n[effects]\npost_analyzer = {{ b = {b}, phi_deg = {phi} }}\n");
    let sc = scene(dir.path(), &inst, &format!("hwp_angles_deg = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]\n{body}"));
    let (frames, instr) = run(dir.path(), &sc, "pa8");
    let fs = pixel_f(&frames, &instr);
    let a0: f64 = fs.iter().map(|f| f[100]).sum::<f64>() / fs.len() as f64;
    assert!((a0 - b * (2.0 * phi.to_radians()).cos()).abs() < 1e-12, "{a0}");
    let m = reduce_files(&frames, &instr, &ReduceConfig::default(), &|| {}).unwrap().map;
    for (k, _, _) in m.valid_bins() {
        assert!(m.p[k] < 1e-12);
    }
    let sc2 = scene(dir.path(), &inst, &format!("hwp_angles_deg = [0, 22.5]\n{body}"));
    let (frames, instr) = run(dir.path(), &sc2, "pa2");
    let m = reduce_files(&frames, &instr, &ReduceConfig::default(), &|| {}).unwrap().map;
    for (k, _, _) in m.valid_bins() {
        assert!((m.p[k] - 2f64.sqrt() * b * (2.0 * phi.to_radians()).cos()).abs() < 1e-9, "{}", m.p[k]);
    }
}

/// Section flat: flat-field errors cancel in the redundant pairs of N = 4 (to second order,
/// Q (1 - eps^2) like the Wollaston term) and do not for N = 2 (first order).
#[test]
fn flat_field_errors_cancel_in_redundant_pairs() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let (q0, u0) = q_u(0.02, 40.0);
    let body = "[output]\nbitpix = -64\n[sky]\nbrightness_e = 5000\np = 0.02\nchi_deg = 40\n[effects]\nflat = { pixel_rms_o = 0.01, pixel_rms_e = 0.015, large_scale_o = 0.02, large_scale_e = 0.03 }\n";
    let rms_err = |angles: &str, sub: &str| {
        let sc = scene(dir.path(), &inst, &format!("hwp_angles_deg = {angles}\n{body}"));
        let (frames, instr) = run(dir.path(), &sc, sub);
        let set = FrameSet::from_frames(
            frames.iter().map(|p| skyfield::io::read_frame(p, &instr).unwrap()).collect(),
            &instr,
            true,
        )
        .unwrap();
        let (q, u) = skyfield::reduce::pixel_qu(&set, &instr).unwrap();
        let v: Vec<f64> =
            q.iter().zip(&u).filter(|(a, _)| a.is_finite()).map(|(a, b)| (a - q0).hypot(b - u0)).collect();
        (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
    };
    let e4 = rms_err("[0, 22.5, 45, 67.5]", "f4");
    let e2 = rms_err("[0, 22.5]", "f2");
    // First order for N = 2: about the rms of (g_o - g_e)/(g_o + g_e) ~ 1e-2.
    assert!(e2 > 3e-3, "N = 2 error {e2}");
    // Second order for N = 4: P eps^2 ~ 0.02 * 1e-4.
    assert!(e4 < 1e-5, "N = 4 error {e4}");
}

/// Section background: a polarized star on a polarized sky. With the annulus subtracted beam
/// by beam the star's own P and chi come back; without it, the combined values of the
/// section's formula.
#[test]
fn background_is_removed_vectorially() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tall_instrument(dir.path());
    let (ps, chis, fs) = (0.05, 30.0f64, 4.0e5);
    let (pb, chib, ib) = (0.06, 120.0f64 - 20.0, 800.0);
    let body = format!(
        "[output]\nbitpix = -64\n[sky]\nbrightness_e = {ib}\np = {pb}\nchi_deg = {chib}\n\
         [[stars]]\nx = 128\ny = 70\ncoords = \"pixel\"\nflux_e = {fs}\np = {ps}\nchi_deg = {chis}\nfwhm_arcsec = 0.6\n"
    );
    let sc = scene(dir.path(), &inst, &body);
    let (frames, instr) = run(dir.path(), &sc, "bg");
    let set = FrameSet::from_frames(
        frames.iter().map(|p| skyfield::io::read_frame(p, &instr).unwrap()).collect(),
        &instr,
        true,
    )
    .unwrap();
    let ap = skyfield::photometry::Aperture { radius_px: 8.0, annulus: Some((12.0, 20.0)) };
    let r = skyfield::photometry::photometry(&set, &instr, 128.0, 70.0, &ap).unwrap().reduction;
    assert!((r.p - ps).abs() < 1e-7, "P = {}", r.p);
    assert!((r.chi.to_degrees() - chis).abs() < 1e-4, "chi = {}", r.chi.to_degrees());
    // Without the annulus: S = S_star + n_ap S_sky.
    let ap0 = skyfield::photometry::Aperture { radius_px: 8.0, annulus: None };
    let ph = skyfield::photometry::photometry(&set, &instr, 128.0, 70.0, &ap0).unwrap();
    let i_b = ph.aperture_area_px * ib;
    let rr = i_b * pb / (fs * ps);
    let dchi = 2.0 * (chis - chib).to_radians();
    let p_comb = fs * ps / (fs + i_b) * (1.0 + rr * rr + 2.0 * rr * dchi.cos()).sqrt();
    let (s2o, c2o) = (2.0 * chis.to_radians()).sin_cos();
    let (s2b, c2b) = (2.0 * chib.to_radians()).sin_cos();
    let chi_comb = (0.5 * (s2o + rr * s2b).atan2(c2o + rr * c2b)).rem_euclid(std::f64::consts::PI);
    assert!((ph.reduction.p - p_comb).abs() < 1e-7, "{} vs {p_comb}", ph.reduction.p);
    assert!((ph.reduction.chi - chi_comb).abs() < 1e-5);
    assert!((ph.reduction.p - ps).abs() > 0.005, "the test must be sensitive");
}

/// The same seed gives the same frames on any number of threads.
#[test]
fn frames_do_not_depend_on_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let sc = scene(
        dir.path(),
        &inst,
        "[sky]\nbrightness_e = 3000\np = 0.01\n[effects]\nphoton_noise = true\nread_noise = true\ncosmic_rays = { rate_per_frame = 5 }\nflat = { pixel_rms_o = 0.01 }\n",
    );
    let plan = Plan::build(&sc).unwrap();
    let a = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap().install(|| plan.render(2));
    let b = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap().install(|| plan.render(2));
    assert_eq!(a, b);
    let c = plan.render(3);
    assert_ne!(a, c);
}

/// Absent effects are not in the plan; present ones are, in the documented order.
#[test]
fn explain_lists_only_requested_steps() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let ideal = Plan::build(&scene(dir.path(), &inst, "[sky]\nbrightness_e = 3000\n")).unwrap().explain();
    assert!(ideal.contains("nothing per pixel") && ideal.contains("ideal HWP"), "{ideal}");
    assert!(!ideal.contains("Poisson") && !ideal.contains("read noise"), "{ideal}");
    let full = Plan::build(&scene(
        dir.path(),
        &inst,
        "[sky]\nbrightness_e = 3000\n[effects]\nphoton_noise = true\nread_noise = true\nsaturation = true\n\
         instpol = { kind = \"radial\", coeffs_percent = [0, 0.012, 0.046, 0.002] }\nwollaston = { t = 0.51 }\n",
    ))
    .unwrap()
    .explain();
    for s in ["PartialPolarizer", "Wollaston t = 0.51", "photon noise", "read noise 5 e-", "saturation"] {
        assert!(full.contains(s), "{s}: {full}");
    }
}

/// The paper's FORS1 V pattern: p(r) = 0.012 r + 0.046 r^2 + 0.002 r^3 percent, radial. On
/// an unpolarized sky the reduced map gives p(r) (eq:approx) at each bin centre.
#[test]
fn radial_instpol_field_is_recovered() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let sc = scene(
        dir.path(),
        &inst,
        "[output]\nbitpix = -64\n[sky]\nbrightness_e = 5000\n[effects]\ninstpol = { kind = \"radial\", coeffs_percent = [0, 10.0, 5.0] }\n",
    );
    let (frames, instr) = run(dir.path(), &sc, "ip");
    let m = reduce_files(&frames, &instr, &ReduceConfig { bin_px: 2, ..Default::default() }, &|| {}).unwrap().map;
    let mut checked = 0;
    for (k, i, j) in m.valid_bins() {
        if m.n_pixels[k] != 4 {
            continue;
        }
        let (xa, ya) = m.geometry.centre_arcmin(i, j);
        let r = xa.hypot(ya);
        let p = (10.0 * r + 5.0 * r * r) / 100.0;
        // A 2x2 bin averages p over 0.4": second-order difference only.
        assert!((m.p[k] - p).abs() < 2e-4 * (1.0 + 10.0 * p), "r = {r}: {} vs {p}", m.p[k]);
        let mut dphi = (m.chi[k] - ya.atan2(xa)).rem_euclid(std::f64::consts::PI);
        if dphi > 0.5 * std::f64::consts::PI {
            dphi -= std::f64::consts::PI;
        }
        if r > 0.1 {
            assert!(dphi.abs() < 0.02, "phi off by {dphi} at ({xa}, {ya})");
        }
        checked += 1;
    }
    assert!(checked > 1000);
}

/// A ray tracer's field file (`instpol-field-v1`, written as `instpol raytrace --field-out`
/// writes it) drives the simulator: the reduced map returns the file's own `eval` (the one
/// interpolation, `mueller::raytrace::FieldFile`) bin by bin, including a non-radial offset.
#[test]
fn raytrace_field_file_is_recovered() {
    use mueller::raytrace::{FieldFile, Polynomial};
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let radius: Vec<f64> = (0..=10).map(|k| 0.05 * k as f64).collect();
    let field = FieldFile {
        format: FieldFile::FORMAT.into(),
        source: "test profile".into(),
        wavelength_nm: 554.0,
        p: radius.iter().map(|r| 0.04 * r * r + 0.01 * r).collect(),
        phi_rel_deg: radius.iter().map(|r| 20.0 * r).collect(),
        radius_arcmin: radius,
        polynomial: Polynomial { powers: vec![1, 2], coefficients: vec![0.01, 0.04] },
    };
    let file = dir.path().join("field.json");
    std::fs::write(&file, serde_json::to_string(&field).unwrap()).unwrap();
    let sc = scene(
        dir.path(),
        &inst,
        &format!(
            "[output]\nbitpix = -64\n[sky]\nbrightness_e = 5000\n[effects]\ninstpol = {{ kind = \"raytrace\", file = \"{}\" }}\n",
            file.display()
        ),
    );
    let (frames, instr) = run(dir.path(), &sc, "rt");
    let m = reduce_files(&frames, &instr, &ReduceConfig { bin_px: 2, ..Default::default() }, &|| {}).unwrap().map;
    let mut checked = 0;
    for (k, i, j) in m.valid_bins() {
        if m.n_pixels[k] != 4 {
            continue;
        }
        let (xa, ya) = m.geometry.centre_arcmin(i, j);
        if xa.hypot(ya) < 0.1 {
            continue;
        }
        let (p, phi) = field.eval(xa, ya);
        assert!((m.p[k] - p).abs() < 2e-4, "({xa}, {ya}): p {} vs {p}", m.p[k]);
        let mut dphi = (m.chi[k] - phi).rem_euclid(std::f64::consts::PI);
        if dphi > 0.5 * std::f64::consts::PI {
            dphi -= std::f64::consts::PI;
        }
        assert!(dphi.abs() < 0.02, "phi off by {dphi} at ({xa}, {ya})");
        checked += 1;
    }
    assert!(checked > 1000, "{checked}");
}
