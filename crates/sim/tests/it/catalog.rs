//! The catalog of every star on simulated frames of both beam layouts: 50+ stars of
//! known P and chi over three magnitudes, frames moving by up to 3 px between HWP positions, a
//! few saturated stars and one star across a mask edge. The truth is the scene; the checks are
//! the pulls of q and u against the catalog's own errors, and the flags.

use sim::Scene;
use skyfield::catalog::{catalog, flags, CatalogConfig};
use skyfield::detect::DetectConfig;
use skyfield::photometry::Aperture;
use skyfield::reduce::{read_frames, FrameSet};
use std::path::Path;

const SHIFTS: &str = "frame_shifts_px = [[0, 0], [1.3, -0.7], [2.6, 0.4], [-1.2, 2.9], [0.5, -2.2], [-2.8, -1.1], [3.0, 1.7], [-0.4, 0.9]]";

struct Truth {
    x: f64,
    y: f64,
    p: f64,
    chi: f64,
    saturated: bool,
    edge: bool,
}

fn scene_text(inst: &Path, stars: &[Truth], fwhm_arcsec: f64) -> String {
    let mut s = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 21\nhwp_angles_deg = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]\n{SHIFTS}\n[output]\nbitpix = -32\n[sky]\nbrightness_e = 200\np = 0.01\nchi_deg = 70\n[effects]\nphoton_noise = true\nread_noise = true\nsaturation = true\n",
        inst.display()
    );
    for (k, t) in stars.iter().enumerate() {
        // Three magnitudes of flux (a factor 15.8), or a saturating star.
        let flux = if t.saturated { 4e6 } else { 1.5e4 * 10f64.powf(0.4 * (k % 7) as f64 / 2.0) };
        s += &format!(
            "[[stars]]\nx = {}\ny = {}\ncoords = \"pixel\"\nflux_e = {flux}\np = {}\nchi_deg = {}\nfwhm_arcsec = {fwhm_arcsec}\n",
            t.x, t.y, t.p, t.chi
        );
    }
    s
}

fn truth_p(k: usize) -> (f64, f64) {
    ([0.0, 0.004, 0.011, 0.023, 0.037, 0.052, 0.008][k % 7], (13.0 + 29.0 * k as f64) % 180.0)
}

/// Run the scene, build the catalog and check it against the truth.
fn check(dir: &Path, inst_path: &Path, stars: &[Truth], fwhm_arcsec: f64, ap: Aperture) {
    let sc = Scene::from_toml_str(&scene_text(inst_path, stars, fwhm_arcsec), &dir.join("s.toml")).unwrap();
    let out = sim::simulate(&sc, &dir.join("f"), &|| {}).unwrap();
    let inst = instrument::Instrument::load(inst_path.to_str().unwrap()).unwrap();
    let set = FrameSet::from_frames(read_frames(&out.frames, &inst, &|| {}).unwrap(), &inst, true).unwrap();
    let fwhm_px = fwhm_arcsec / inst.detector.pixel_scale_arcsec;
    let cfg = CatalogConfig {
        detect: DetectConfig { fwhm_px, ..Default::default() },
        radius: skyfield::photometry::ApertureRadius::Px(ap.radius_px),
        annulus: ap.annulus,
        weighting: skyfield::aperture::Weighting::Exact,
        ..Default::default()
    };
    let cat = catalog(&set, &inst, &cfg).unwrap();
    // What `instpol catalog` runs: the frames read band by band from disk and each star
    // measured as its rows arrive. The same rows as from the frames in memory, to the bit, so
    // the truth checks below hold for both.
    let (streamed, _) = skyfield::catalog::catalog_files(
        &out.frames,
        &inst,
        &skyfield::calib::ReadOptions::default(),
        &cfg,
        Box::new(|| {}),
    )
    .unwrap();
    assert_eq!(streamed.rows.len(), cat.rows.len());
    for (a, b) in streamed.rows.iter().zip(&cat.rows) {
        let bits = |r: &skyfield::catalog::Row| {
            (
                r.x.to_bits(),
                r.q.to_bits(),
                r.u.to_bits(),
                r.sigma_q.to_bits(),
                r.sigma_u.to_bits(),
                r.flags,
                r.note.clone(),
            )
        };
        assert_eq!(bits(a), bits(b));
    }
    let mut pulls = Vec::new();
    let (mut n_sat, mut n_edge) = (0, 0);
    for t in stars {
        let row = cat.rows.iter().find(|r| (r.x - t.x).hypot(r.y - t.y) < 2.0);
        if t.edge {
            // Across the mask edge: flagged (or not detected as a pair), never measured wrongly.
            if let Some(r) = row {
                assert!(r.flags & flags::MASK_EDGE != 0 && r.q.is_nan(), "edge star measured: {r:?}");
                n_edge += 1;
            }
            continue;
        }
        let r = row.unwrap_or_else(|| panic!("star at ({}, {}) not in the catalog", t.x, t.y));
        if t.saturated {
            assert!(r.flags & flags::SATURATED != 0 && r.q.is_nan(), "saturated star not flagged: {r:?}");
            n_sat += 1;
            continue;
        }
        assert_eq!(r.flags & !flags::BLENDED, 0, "{r:?}");
        let (q0, u0) = (t.p * (2.0 * t.chi.to_radians()).cos(), t.p * (2.0 * t.chi.to_radians()).sin());
        pulls.push((r.q - q0) / r.sigma_q);
        pulls.push((r.u - u0) / r.sigma_u);
    }
    let rms = (pulls.iter().map(|p| p * p).sum::<f64>() / pulls.len() as f64).sqrt();
    let worst = pulls.iter().fold(0.0f64, |a, p| a.max(p.abs()));
    eprintln!(
        "{}: {} rows, {} sources, {} unpaired; {} measured stars, RMS pull {rms:.2}, worst {worst:.1}; {n_sat} saturated flagged, {n_edge} edge flagged",
        inst.name,
        cat.rows.len(),
        cat.n_sources,
        cat.unpaired.len(),
        pulls.len() / 2
    );
    assert!(pulls.len() >= 100, "{} stars measured", pulls.len() / 2);
    assert!((0.8..1.25).contains(&rms), "RMS pull {rms}");
    assert!(worst < 4.5, "worst pull {worst}");
    assert_eq!(n_sat, stars.iter().filter(|t| t.saturated).count());
}

/// Maskless calcite frames: 55 stars on a jittered grid (their e images 70 px to the right),
/// three of them saturated.
#[test]
fn maskless_catalog_of_55_stars() {
    let dir = tempfile::tempdir().unwrap();
    let ip = calcite_with_hwp_keyword(dir.path());
    let mut stars = Vec::new();
    let mut k = 0;
    for j in 0..11 {
        for i in 0..5 {
            let (p, chi) = truth_p(k);
            let x = 40.0 + 120.0 * i as f64 + ((k * 37) % 11) as f64 * 0.7;
            let y = 40.0 + 58.0 * j as f64 + ((k * 53) % 13) as f64 * 0.5;
            stars.push(Truth { x, y, p, chi, saturated: k % 23 == 5, edge: false });
            k += 1;
        }
    }
    check(dir.path(), &ip, &stars, 1.0, Aperture { radius_px: 8.0, annulus: Some((12.0, 20.0)) });
}

/// A strip mask (5 strips of 50 px): 55 stars in the middle of the o strips, three saturated,
/// and one star 2 px from a strip edge, whose aperture would reach behind the mask.
#[test]
fn strip_catalog_of_55_stars_with_an_edge_star() {
    let dir = tempfile::tempdir().unwrap();
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 600")
        .replace("ny = 2048", "ny = 520")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 10.0")
        .replace("strip_count = 9", "strip_count = 5")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 10");
    let ip = dir.path().join("strips.toml");
    std::fs::write(&ip, text).unwrap();
    let mut stars = Vec::new();
    let mut k = 0;
    for j in 0..5 {
        for i in 0..11 {
            let (p, chi) = truth_p(k);
            let x = 30.0 + 50.0 * i as f64 + ((k * 37) % 11) as f64 * 0.6;
            let y = 10.0 + 100.0 * j as f64 + 25.0 + ((k * 53) % 7) as f64 * 0.3 - 1.0;
            stars.push(Truth { x, y, p, chi, saturated: k % 23 == 5, edge: false });
            k += 1;
        }
    }
    stars.push(Truth { x: 575.0, y: 112.0, p: 0.02, chi: 40.0, saturated: false, edge: true });
    check(dir.path(), &ip, &stars, 0.8, Aperture { radius_px: 6.0, annulus: Some((9.0, 14.0)) });
}

/// The maskless example instrument, its HWP angle read from the simulator's HWPANG keyword,
/// written into `dir`.
fn calcite_with_hwp_keyword(dir: &Path) -> std::path::PathBuf {
    let text = include_str!("../../../../instruments/calcite.toml")
        .replace("hwp_angle_keyword = \"\"", "hwp_angle_keyword = \"HWPANG\"");
    let ip = dir.join("calcite.toml");
    std::fs::write(&ip, text).unwrap();
    ip
}

/// The catalog settings for bright stars of 1" FWHM through the maskless example: 9 px
/// apertures, a 14-24 px annulus.
fn bright_config() -> CatalogConfig {
    CatalogConfig {
        detect: DetectConfig { fwhm_px: 4.7, ..Default::default() },
        radius: skyfield::photometry::ApertureRadius::Px(9.0),
        annulus: Some((14.0, 24.0)),
        weighting: skyfield::aperture::Weighting::Exact,
        ..Default::default()
    }
}

/// The catalog's rows for 40 bright stars through the maskless example with extra effects.
fn bright_rows(dir: &Path, effects: &str) -> Vec<skyfield::catalog::Row> {
    let ip = calcite_with_hwp_keyword(dir);
    let mut s = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 9\nhwp_angles_deg = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]\n{SHIFTS}\n[output]\nbitpix = -64\n[sky]\nbrightness_e = 100\n[effects]\nphoton_noise = true\n{effects}\n",
        ip.display()
    );
    for j in 0..8 {
        for i in 0..5 {
            let (p, chi) = truth_p(i + 5 * j);
            s += &format!(
                "[[stars]]\nx = {}\ny = {}\ncoords = \"pixel\"\nflux_e = 6e5\np = {p}\nchi_deg = {chi}\nfwhm_arcsec = 1.0\n",
                40.0 + 120.0 * i as f64,
                50.0 + 80.0 * j as f64
            );
        }
    }
    let sc = Scene::from_toml_str(&s, &dir.join("s.toml")).unwrap();
    let out = sim::simulate(&sc, &dir.join("f"), &|| {}).unwrap();
    let inst = instrument::Instrument::load(ip.to_str().unwrap()).unwrap();
    let set = FrameSet::from_frames(read_frames(&out.frames, &inst, &|| {}).unwrap(), &inst, true).unwrap();
    let cfg = bright_config();
    catalog(&set, &inst, &cfg).unwrap().rows.into_iter().filter(|r| r.q.is_finite()).collect()
}

/// Mean reduced modulation chi^2 over the rows: the square of the scatter-based error over the
/// propagated one, on average.
fn mean_chi2_red(rows: &[skyfield::catalog::Row]) -> f64 {
    rows.iter().map(|r| r.chi2_mod / r.dof_mod as f64).sum::<f64>() / rows.len() as f64
}

/// The scatter-based error agrees with the propagated one on photon-limited frames (mean
/// reduced chi^2 of the modulation 1 within its error sqrt(2 / (40 x 5)) = 0.1), still does
/// with 5 % frame-to-frame transparency noise (both beams scale together: eq:F cancels it, the
/// reason for the dual-beam method), and exceeds it when uncorrected flat-field errors that
/// differ between the beams meet stars moving over the detector between frames.
#[test]
fn scatter_error_against_propagated() {
    let photon = bright_rows(tempfile::tempdir().unwrap().path(), "");
    let transp = bright_rows(tempfile::tempdir().unwrap().path(), "transparency_rms = 0.05");
    let flat = bright_rows(tempfile::tempdir().unwrap().path(), "flat = { pixel_rms_o = 0.05, pixel_rms_e = 0.05 }");
    let (a, b, c) = (mean_chi2_red(&photon), mean_chi2_red(&transp), mean_chi2_red(&flat));
    eprintln!("mean reduced modulation chi^2: photon {a:.2}, + transparency {b:.2}, + flat errors {c:.2}");
    assert!(photon.len() >= 38 && transp.len() >= 38 && flat.len() >= 38);
    assert!((0.7..1.3).contains(&a), "photon-limited: {a}");
    assert!((0.7..1.3).contains(&b), "transparency: {b}");
    assert!(c > 2.5, "flat-field errors with moving stars: {c}");
    let ratio = flat.iter().map(|r| r.sigma_q_scatter / r.sigma_q).sum::<f64>() / flat.len() as f64;
    assert!(ratio > 1.3, "{ratio}");
}

/// A star that cannot be measured is flagged by why (its error's kind), not by the words of
/// its note, which hold the frames' file names: frames in a folder whose name says "saturated"
/// and "off the", one star given a NaN and another a saturated pixel in the fourth frame only
/// (after the detection, which looks at the first). The NaN star is FAILED, the other
/// SATURATED, the rest measured.
#[test]
fn failed_stars_are_flagged_by_kind_not_by_file_names() {
    let dir = tempfile::tempdir().unwrap();
    let ip = calcite_with_hwp_keyword(dir.path());
    let mut s = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 5\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n[output]\nbitpix = -64\n[sky]\nbrightness_e = 100\n[effects]\nphoton_noise = true\n",
        ip.display()
    );
    let stars = [(100.0, 120.0), (300.0, 320.0), (200.0, 520.0)];
    for (x, y) in stars {
        s += &format!("[[stars]]\nx = {x}\ny = {y}\ncoords = \"pixel\"\nflux_e = 2e5\np = 0.01\nchi_deg = 30\nfwhm_arcsec = 1.0\n");
    }
    let frames_dir = dir.path().join("saturated, off the shelf");
    std::fs::create_dir(&frames_dir).unwrap();
    let sc = Scene::from_toml_str(&s, &frames_dir.join("s.toml")).unwrap();
    let out = sim::simulate(&sc, &frames_dir.join("f"), &|| {}).unwrap();
    let inst = instrument::Instrument::load(ip.to_str().unwrap()).unwrap();
    let mut set = FrameSet::from_frames(read_frames(&out.frames, &inst, &|| {}).unwrap(), &inst, true).unwrap();
    let nx = set.nx;
    set.data[3][120 * nx + 100] = f64::NAN;
    set.data[3][320 * nx + 300] = inst.detector.saturation_adu + 1.0;
    let cfg = bright_config();
    let cat = catalog(&set, &inst, &cfg).unwrap();
    let row = |x: f64, y: f64| {
        cat.rows.iter().find(|r| (r.x - x).hypot(r.y - y) < 2.0).unwrap_or_else(|| panic!("no row at ({x}, {y})"))
    };
    let nan = row(100.0, 120.0);
    assert!(nan.note.contains("saturated, off the shelf") && nan.note.contains("NaN"), "{}", nan.note);
    assert_eq!(nan.flags, flags::FAILED, "{nan:?}");
    let sat = row(300.0, 320.0);
    assert_eq!(sat.flags, flags::SATURATED, "{sat:?}");
    assert!(sat.note.contains("is saturated"), "{}", sat.note);
    let good = row(200.0, 520.0);
    assert!(good.flags == 0 && good.q.is_finite(), "{good:?}");
}
