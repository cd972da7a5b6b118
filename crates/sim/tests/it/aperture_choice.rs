//! The aperture radius chosen on the curve of growth (`--aperture best`), checked
//! against the continuous closed form: for a Gaussian star of total flux `F` (per beam) on a
//! sky of `B` e-/px, the flux inside radius `r` is `F (1 - exp(-r^2 / 2 s^2))` and the
//! photon variance of the sum `F (1 - ...) + pi r^2 B`; the S/N is maximal where that ratio is.
//! Background-dominated (a faint star): near `1.585 s = 0.673 FWHM`. Source-dominated (a bright
//! star on a dark sky): several FWHM, where the last of the wings no longer pays for its sky.

use sim::Scene;
use skyfield::photometry::{layout_for, photometry_sized, ApertureRadius, PhotOptions};
use skyfield::reduce::{read_frames, FrameSet};

/// The radius (in FWHM, on the 0.5, 0.6, ..., 4.0 grid, below `r_max` px) of best S/N for
/// the continuous Gaussian, computed here from the closed form.
fn best_continuous(f: f64, b: f64, fwhm: f64, r_max: f64) -> f64 {
    let s = fwhm / (8.0 * 2f64.ln()).sqrt();
    let snr = |r: f64| {
        let g = 1.0 - (-r * r / (2.0 * s * s)).exp();
        f * g / (f * g + std::f64::consts::PI * r * r * b).sqrt()
    };
    (5..=40)
        .map(|i| i as f64 * 0.1)
        .filter(|k| k * fwhm <= r_max)
        .max_by(|a, c| snr(a * fwhm).total_cmp(&snr(c * fwhm)))
        .unwrap()
}

/// Noiseless frames of one unpolarized star through the maskless example instrument; the
/// radius `photometry_sized` picks, in units of the FWHM.
fn chosen(dir: &std::path::Path, flux: f64, sky: f64, annulus: (f64, f64)) -> (f64, f64, f64) {
    let text = include_str!("../../../../instruments/calcite.toml")
        .replace("hwp_angle_keyword = \"\"", "hwp_angle_keyword = \"HWPANG\"");
    let ip = dir.join("calcite.toml");
    std::fs::write(&ip, text).unwrap();
    let s = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n[output]\nbitpix = -64\n[sky]\nbrightness_e = {sky}\n[[stars]]\nx = 300\ny = 350\ncoords = \"pixel\"\nflux_e = {flux}\nfwhm_arcsec = 1.0\n",
        ip.display()
    );
    let sc = Scene::from_toml_str(&s, &dir.join("s.toml")).unwrap();
    let out = sim::simulate(&sc, &dir.join("f"), &|| {}).unwrap();
    let inst = instrument::Instrument::load(ip.to_str().unwrap()).unwrap();
    let set = FrameSet::from_frames(read_frames(&out.frames, &inst, &|| {}).unwrap(), &inst, true).unwrap();
    let g = layout_for(&set, &inst).unwrap();
    let fwhm = 1.0 / inst.detector.pixel_scale_arcsec;
    let (_, r) =
        photometry_sized(&set, &g, 300.0, 350.0, ApertureRadius::BestSnr, fwhm, Some(annulus), &PhotOptions::default())
            .unwrap();
    // The read noise's variance per pixel adds to the sky's (in e-).
    (r / fwhm, fwhm, inst.detector.read_noise_e.powi(2))
}

#[test]
fn best_snr_radius_follows_the_closed_form() {
    let d = tempfile::tempdir().unwrap();
    // A faint star on a bright sky: ~0.67 FWHM whatever the exact split of sky and star
    // between the beams (both splits give the same grid radius here).
    let (k, fwhm, rn2) = chosen(d.path(), 3000.0, 400.0, (20.0, 28.0));
    for (f, b) in [(1500.0, 400.0), (1500.0, 200.0), (3000.0, 400.0)] {
        let want = best_continuous(f, b + rn2, fwhm, 20.0);
        assert!((k - want).abs() <= 0.1 + 1e-9, "faint star: chose {k:.1} FWHM, closed form {want:.1} (F {f}, B {b})");
    }
    assert!((0.5..=0.9).contains(&k), "{k}");
    // A bright star on a dark sky: the S/N keeps growing to several FWHM.
    let d = tempfile::tempdir().unwrap();
    let (k, fwhm, rn2) = chosen(d.path(), 1e6, 0.5, (20.0, 28.0));
    let want = best_continuous(5e5, 0.5 + rn2, fwhm, 20.0);
    assert!((k - want).abs() <= 0.1 + 1e-9, "bright star: chose {k:.1} FWHM, closed form {want:.1}");
    assert!(k >= 1.2, "a bright star needs a wider aperture than a faint one: {k}");
}
