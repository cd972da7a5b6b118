//! A per-pixel Stokes map of two cameras behind a polarizing beam splitter: simulated frames of
//! a uniformly polarized sky (each exposure two raw files, one per camera; the e camera flipped
//! in x, shifted by a fraction of a pixel, with a 3 % higher gain and flat-field errors of its
//! own) reduced by `skyfield::reduce` (the e camera resampled onto the o camera's pixels
//! through the camera transform, bilinearly) to the sky's q, u within the bins' errors.

use skyfield::reduce::{reduce_circular_files_with, reduce_files, ReduceConfig};
use std::path::{Path, PathBuf};

use crate::two_cameras_setup as two_cameras;

/// The two cameras of `common/two_cameras.rs` (the o camera's pixel (x, y) falls at
/// (x + 1.7, y - 2.3) on the e camera once that is flipped back in x; the e camera's gain 3 %
/// above the o camera's) behind a plate standing still at the header's angle.
fn instrument(dir: &Path) -> PathBuf {
    let p = dir.join("twocam.toml");
    std::fs::write(&p, twocam()).unwrap();
    p
}

/// That instrument file's text.
fn twocam() -> String {
    two_cameras::instrument_text(
        "hwp_angle_keyword = \"HWPANG\"\n",
        &format!("transform = {}\n", two_cameras::TRANSFORM),
    )
}

const P: f64 = 0.04;
const CHI_DEG: f64 = 30.0;

/// The must-show: the sky's q, u (the simulator's truth, `P cos 2chi`, `P sin 2chi`) in every
/// valid bin within its errors (pulls over all bins with an RMS near 1, none beyond 4.5); every
/// bin's error is the photon error of its mean, the closed form `sqrt(2 / N) / sqrt(n S)`
/// (`eq:sigp` over `n` pixels of `S` e- per exposure; read noise added), which the bins'
/// scatter understates for the resampled pixels' correlated noise; the bins cover the o camera
/// at the instrument's field positions (arcmin from the o camera's centre).
#[test]
fn uniform_sky_through_two_cameras_gives_its_q_u() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = instrument(dir.path());
    let body = format!(
        "instrument = \"{}\"\nfilter = \"R\"\nseed = 12\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n[output]\nbitpix = -32\n\
         [sky]\nbrightness_e = 4000\np = {P}\nchi_deg = {CHI_DEG}\n[effects]\nphoton_noise = true\nread_noise = true\n\
         flat = {{ pixel_rms_o = 0.004, pixel_rms_e = 0.007, large_scale_o = 0.01, large_scale_e = 0.02 }}\n",
        inst_path.display()
    );
    let sc = sim::Scene::from_toml_str(&body, &dir.path().join("scene.toml")).unwrap();
    let files = sim::simulate(&sc, &dir.path().join("frames"), &|| {}).unwrap().frames;
    assert_eq!(files.len(), 8, "two files per exposure");
    let inst = instrument::Instrument::load(inst_path.to_str().unwrap()).unwrap();
    let m = reduce_files(&files, &inst, &ReduceConfig { bin_px: 16, ..Default::default() }, &|| {}).unwrap().map;
    let g = &m.geometry;
    // The map's detector is the o camera (at the frame's origin here): its bins' field positions
    // are the instrument's, arcmin from the o camera's centre.
    assert_eq!((g.origin_x, g.origin_y, g.nx, g.ny, g.detector_nx, g.detector_ny), (0, 0, 10, 10, 160, 160));
    for (i, j) in [(0, 0), (9, 4), (3, 9)] {
        let (x, y) = g.centre_px(i, j);
        let (a, b) = (g.centre_arcmin(i, j), inst.pixel_to_arcmin(x, y));
        assert!((a.0 - b.0).abs() < 1e-12 && (a.1 - b.1).abs() < 1e-12, "bin ({i}, {j}): {a:?} vs {b:?}");
    }
    // Bilinear interpolation needs the four e pixels around a point: the o camera's last two
    // columns (x + 1.7 + 1 > 159, flipped: below e column 0) and first three rows (y - 2.3 < 0)
    // have them off the e camera and are masked; their bins keep the rest.
    assert_eq!(m.n_valid(), 100);
    let (q0, u0) = (P * (2.0 * CHI_DEG.to_radians()).cos(), P * (2.0 * CHI_DEG.to_radians()).sin());
    let mut pulls = Vec::new();
    for (k, i, j) in m.valid_bins() {
        let full = if i == 9 { 14 } else { 16 } * if j == 0 { 13 } else { 16 };
        // (The sigma clipping of q, u and the intensity keeps most of the rest.)
        assert!(
            m.n_pixels[k] as usize <= full && m.n_pixels[k] as f64 >= 0.9 * full as f64,
            "bin ({i}, {j}): {}",
            m.n_pixels[k]
        );
        let (pq, pu) = ((m.q[k] - q0) / m.sigma_q[k], (m.u[k] - u0) / m.sigma_u[k]);
        assert!(pq.abs() < 4.5 && pu.abs() < 4.5, "bin ({i}, {j}): q {} u {} +- {}", m.q[k], m.u[k], m.sigma_q[k]);
        pulls.extend([pq, pu]);
        // eq:sigp per pixel and exposure, sigma_F^2 = (S + 2 rn^2) / S^2 (S = f_O + f_E), over n
        // pixels and N = 4 angles: sigma_Q^2 = (2 / N) sigma_F^2 / n.
        let s = m.intensity[k];
        let closed = (0.5 * (s + 2.0 * 25.0) / (s * s) / m.n_pixels[k] as f64).sqrt();
        assert!((m.sigma_q[k] / closed - 1.0).abs() < 0.03, "bin ({i}, {j}): {} vs {closed}", m.sigma_q[k]);
    }
    // The scatter of the resampled pixels understates the error: in (nearly) every bin the
    // photon error is the larger, and the error given.
    let photon = m.valid_bins().filter(|&(k, _, _)| m.sigma_q[k] == m.sigma_q_phot[k]).count();
    eprintln!("two cameras: the photon error is the larger in {photon} of {} bins", m.n_valid());
    assert!(photon >= 90, "{photon}");
    let rms = (pulls.iter().map(|p| p * p).sum::<f64>() / pulls.len() as f64).sqrt();
    let mean = pulls.iter().sum::<f64>() / pulls.len() as f64;
    eprintln!("two cameras: {} pulls, RMS {rms:.3}, mean {mean:+.3}", pulls.len());
    assert!((0.8..1.2).contains(&rms), "pull RMS {rms}");
    assert!(mean.abs() < 4.0 / (pulls.len() as f64).sqrt(), "mean pull {mean}");
}

/// Without a transform in the instrument file the reduction measures it from the stars of the
/// first frame (`skyfield::layout`) and says so in a warning: frames of the same sky with 12
/// stars of the sky's own polarization (so that the bins they fall in keep the sky's q, u)
/// reduce to a map whose bins agree with the sky's q, u within their errors, as with the
/// file's transform.
#[test]
fn transform_measured_from_stars_gives_the_sky() {
    let dir = tempfile::tempdir().unwrap();
    let sim_inst = instrument(dir.path());
    let read = dir.path().join("twocam_read.toml");
    let base = twocam();
    let text = base.replace("transform = [1.0, 0.0, 1.7, 0.0, 1.0, -2.3]\n", "max_residual_px = 0.3\n");
    assert_ne!(text, base);
    std::fs::write(&read, text).unwrap();
    let mut body = format!(
        "instrument = \"{}\"\nfilter = \"R\"\nseed = 13\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n[output]\nbitpix = -32\n\
         [sky]\nbrightness_e = 4000\np = {P}\nchi_deg = {CHI_DEG}\n[effects]\nphoton_noise = true\nread_noise = true\n",
        sim_inst.display()
    );
    for k in 0..12 {
        let (x, y) = (20.0 + 37.3 * (k % 4) as f64, 25.0 + 48.1 * (k / 4) as f64);
        body += &format!(
            "[[stars]]\nx = {x}\ny = {y}\ncoords = \"pixel\"\nflux_e = 4e5\np = {P}\nchi_deg = {CHI_DEG}\nfwhm_arcsec = 1.0\n"
        );
    }
    let sc = sim::Scene::from_toml_str(&body, &dir.path().join("scene.toml")).unwrap();
    let files = sim::simulate(&sc, &dir.path().join("frames"), &|| {}).unwrap().frames;
    let inst = instrument::Instrument::load(read.to_str().unwrap()).unwrap();
    let r = reduce_files(&files, &inst, &ReduceConfig { bin_px: 16, ..Default::default() }, &|| {}).unwrap();
    let note: Vec<String> = r.warnings.iter().map(|w| w.to_string()).collect();
    assert!(note.iter().any(|w| w.contains("camera transform measured from")), "{note:?}");
    let m = &r.map;
    assert_eq!(m.n_valid(), 100);
    let (q0, u0) = (P * (2.0 * CHI_DEG.to_radians()).cos(), P * (2.0 * CHI_DEG.to_radians()).sin());
    let pulls: Vec<f64> =
        m.valid_bins().flat_map(|(k, _, _)| [(m.q[k] - q0) / m.sigma_q[k], (m.u[k] - u0) / m.sigma_u[k]]).collect();
    let rms = (pulls.iter().map(|p| p * p).sum::<f64>() / pulls.len() as f64).sqrt();
    eprintln!("two cameras, measured transform: {} pulls, RMS {rms:.3}; {note:?}", pulls.len());
    assert!(pulls.iter().all(|p| p.abs() < 4.5) && (0.8..1.2).contains(&rms), "RMS {rms}: {pulls:?}");
}

/// A quarter-wave plate on the same two cameras: a uniform sky of V/I = 1.5 % (and the 4 %
/// linear polarization) at the four positions reduces, through the same resampling, to a V map
/// whose bins agree with the sky's V/I (the simulator's truth) within their errors.
#[test]
fn quarter_wave_plate_on_two_cameras_gives_the_sky_v() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = dir.path().join("twocam_qwp.toml");
    let base = twocam();
    let text = base.replace("layout = \"two_cameras\"\n", "layout = \"two_cameras\"\nplate = \"quarter_wave\"\n");
    assert_ne!(text, base);
    std::fs::write(&inst_path, text).unwrap();
    let body = format!(
        "instrument = \"{}\"\nfilter = \"R\"\nseed = 14\nhwp_angles_deg = [-45, 45, 135, 225]\n[output]\nbitpix = -32\n\
         [sky]\nbrightness_e = 4000\np = {P}\nchi_deg = {CHI_DEG}\nv = 0.015\n[effects]\nphoton_noise = true\n\
         read_noise = true\n",
        inst_path.display()
    );
    let sc = sim::Scene::from_toml_str(&body, &dir.path().join("scene.toml")).unwrap();
    let files = sim::simulate(&sc, &dir.path().join("frames"), &|| {}).unwrap().frames;
    let inst = instrument::Instrument::load(inst_path.to_str().unwrap()).unwrap();
    let cfg = ReduceConfig { bin_px: 16, ..Default::default() };
    let m = reduce_circular_files_with(&files, &inst, &cfg, &Default::default(), &|| {}).unwrap().map;
    assert_eq!(m.n_valid(), 100);
    let pulls: Vec<f64> = m.valid_bins().map(|(k, _, _)| (m.v[k] - 0.015) / m.sigma_v[k]).collect();
    let rms = (pulls.iter().map(|p| p * p).sum::<f64>() / pulls.len() as f64).sqrt();
    eprintln!("two cameras, quarter-wave plate: {} bins, pull RMS {rms:.3}", pulls.len());
    assert!(pulls.iter().all(|p| p.abs() < 4.5) && (0.75..1.25).contains(&rms), "RMS {rms}: {pulls:?}");
}
