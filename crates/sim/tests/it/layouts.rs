//! Beam layouts end to end: frames of a maskless calcite polarimeter (every star imaged twice,
//! the e image at a sub-pixel 2-D offset, the sky of the two beams overlapping) and of a strip
//! mask whose throw varies across the field, simulated with the stars moving between HWP
//! positions, then measured by the photometry with the layout's own geometry. The truth is
//! the scene's P and chi; the check is the pulls against the photometry's own errors.

use sim::Scene;
use skyfield::photometry::{layout_for, measure_oe_offset, photometry, photometry_with, Aperture, PhotOptions};
use skyfield::reduce::{read_frames, reduce_set, FrameSet, ReduceConfig};
use std::path::{Path, PathBuf};

/// The built-in maskless example with an HWP keyword in its headers (the built-in one has
/// none: its frames take --hwp-angles), optionally without its o/e offset.
fn calcite(dir: &Path, with_offset: bool) -> PathBuf {
    let mut text = include_str!("../../../../instruments/calcite.toml")
        .replace("hwp_angle_keyword = \"\"", "hwp_angle_keyword = \"HWPANG\"");
    if !with_offset {
        text = text.replace("oe_offset_px = [70.2, 0.0]", "");
    }
    let p = dir.join(if with_offset { "calcite.toml" } else { "calcite_nooffset.toml" });
    std::fs::write(&p, text).unwrap();
    p
}

/// Stars on a grid (their e images 70 px to the right, clear of the next star), P from 0.3 %
/// to 6 %, chi all round, fluxes over a factor 10.
fn stars() -> Vec<(f64, f64, f64, f64, f64)> {
    let mut v = Vec::new();
    let mut k = 0;
    for j in 0..3 {
        for i in 0..3 {
            let (x, y) = (90.0 + 190.0 * i as f64 + 0.37 * k as f64, 110.0 + 220.0 * j as f64 - 0.21 * k as f64);
            let p = [0.003, 0.012, 0.025, 0.06, 0.0, 0.041, 0.008, 0.018, 0.033][k];
            let chi = (17.0 + 37.0 * k as f64) % 180.0;
            let flux = 1e5 * (1.0 + (k % 4) as f64 * 3.0);
            v.push((x, y, p, chi, flux));
            k += 1;
        }
    }
    v
}

fn scene(dir: &Path, inst: &Path, shifts: &str) -> Scene {
    let mut body = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 5\nhwp_angles_deg = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]\n{shifts}\n[output]\nbitpix = -32\n[sky]\nbrightness_e = 400\np = 0.02\nchi_deg = 40\n[effects]\nphoton_noise = true\nread_noise = true\n",
        inst.display()
    );
    for (x, y, p, chi, f) in stars() {
        body += &format!(
            "[[stars]]\nx = {x}\ny = {y}\ncoords = \"pixel\"\nflux_e = {f}\np = {p}\nchi_deg = {chi}\nfwhm_arcsec = 0.9\n"
        );
    }
    Scene::from_toml_str(&body, &dir.join("scene.toml")).unwrap()
}

const SHIFTS: &str = "frame_shifts_px = [[0, 0], [1.3, -0.7], [2.6, 0.4], [-1.2, 2.9], [0.5, -2.2], [-2.8, -1.1], [3.0, 1.7], [-0.4, 0.9]]";

fn frame_set(frames: &[PathBuf], inst: &instrument::Instrument) -> FrameSet {
    FrameSet::from_frames(read_frames(frames, inst, &|| {}).unwrap(), inst, true).unwrap()
}

/// Every star's P and chi come back within errors from maskless frames whose stars move by up
/// to 3 px between HWP positions: the photometry re-centres the o aperture in each frame and
/// puts the e aperture at the sub-pixel offset (70.2, 0) px. RMS of the pulls of q and u over
/// the 9 stars (18 numbers) near 1; no pull beyond 4.
#[test]
fn maskless_stars_are_measured_within_errors() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = calcite(dir.path(), true);
    let sc = scene(dir.path(), &inst_path, SHIFTS);
    let out = sim::simulate(&sc, &dir.path().join("frames"), &|| {}).unwrap();
    let inst = instrument::Instrument::load(inst_path.to_str().unwrap()).unwrap();
    let set = frame_set(&out.frames, &inst);
    let ap = Aperture { radius_px: 9.0, annulus: Some((14.0, 24.0)) };
    let mut pulls = Vec::new();
    for (x, y, p, chi, _) in stars() {
        let ph = photometry(&set, &inst, x, y, &ap).unwrap();
        let r = &ph.reduction;
        let (q0, u0) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
        let (pq, pu) = ((r.qu.q - q0) / r.qu.var_q.sqrt(), (r.qu.u - u0) / r.qu.var_u.sqrt());
        assert!(pq.abs() < 4.0 && pu.abs() < 4.0, "star at ({x}, {y}): q {} vs {q0}, u {} vs {u0}", r.qu.q, r.qu.u);
        pulls.extend([pq, pu]);
        // The apertures followed the star: frame k's o centre is the star plus the shift.
        let c = ph.centres[3];
        assert!((c[0] - (x - 1.2)).abs() < 0.05 && (c[1] - (y + 2.9)).abs() < 0.05, "{c:?}");
        assert!((c[2] - c[0] - 70.2).abs() < 1e-12 && (c[3] - c[1]).abs() < 1e-12);
    }
    let rms = (pulls.iter().map(|p| p * p).sum::<f64>() / pulls.len() as f64).sqrt();
    eprintln!("maskless: RMS pull of q, u over {} values: {rms:.2}", pulls.len());
    assert!(rms > 0.4 && rms < 1.6, "RMS pull {rms} ({pulls:?})");
}

/// Whole-pixel apertures at fixed positions (no re-centring), as before this layout existed,
/// are measurably wrong on the same frames: the test above is sensitive to what it checks.
#[test]
fn fixed_whole_pixel_apertures_are_biased_on_moving_maskless_frames() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = calcite(dir.path(), true);
    let sc = scene(dir.path(), &inst_path, SHIFTS);
    let out = sim::simulate(&sc, &dir.path().join("frames"), &|| {}).unwrap();
    let inst = instrument::Instrument::load(inst_path.to_str().unwrap()).unwrap();
    let set = frame_set(&out.frames, &inst);
    let g = layout_for(&set, &inst).unwrap();
    let ap = Aperture { radius_px: 4.0, annulus: Some((14.0, 24.0)) };
    let opts = PhotOptions { weighting: skyfield::aperture::Weighting::Centre, recentre: false, ..Default::default() };
    let mut worst: f64 = 0.0;
    for (x, y, p, chi, _) in stars() {
        let r = photometry_with(&set, &g, x, y, &ap, &opts).unwrap().reduction;
        let (q0, u0) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
        worst = worst.max(((r.qu.q - q0) / r.qu.var_q.sqrt()).abs()).max(((r.qu.u - u0) / r.qu.var_u.sqrt()).abs());
    }
    eprintln!("fixed whole-pixel apertures: worst pull {worst:.1}");
    assert!(worst > 5.0, "fixed apertures on moving frames should fail: worst pull {worst}");
}

/// The o/e offset of a maskless instrument file that does not give it is measured from the
/// stars' pairs to 0.05 px, and reduction of an extended sky is refused with the reason.
#[test]
fn maskless_offset_is_measured_and_sky_maps_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let with = calcite(dir.path(), true);
    let sc = scene(dir.path(), &with, "");
    let out = sim::simulate(&sc, &dir.path().join("frames"), &|| {}).unwrap();
    let without = instrument::Instrument::load(calcite(dir.path(), false).to_str().unwrap()).unwrap();
    let set = frame_set(&out.frames, &without);
    let (dx, dy, n) = measure_oe_offset(&set, &without).unwrap();
    assert!((dx - 70.2).abs() < 0.05 && dy.abs() < 0.05 && n >= 6, "({dx}, {dy}) from {n} pairs");
    let e = reduce_set(&set, &without, &ReduceConfig::default()).unwrap_err().to_string();
    assert!(e.contains("maskless") && e.contains("overlap"), "{e}");
}

/// A strip mask whose throw varies across the field (FORS2-like: +-1.5 px over the detector,
/// within a 2 px strip margin): a star far from the centre, where the e image sits 1.4 px off
/// the nominal throw, is measured within errors with the varying throw, and a polarized
/// uniform sky still reduces to its Q, U.
#[test]
fn varying_throw_strips_are_followed() {
    let dir = tempfile::tempdir().unwrap();
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 256")
        .replace("ny = 2048", "ny = 256")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 20.0")
        .replace("strip_count = 9", "strip_count = 1")
        .replace(
            "first_strip_y_px = 34",
            "first_strip_y_px = 20\nstrip_margin_px = 2\nthrow_terms = [{ i = 1, j = 0, c = 1.5 }]",
        );
    let ip = dir.path().join("vt.toml");
    std::fs::write(&ip, text).unwrap();
    let inst = instrument::Instrument::load(ip.to_str().unwrap()).unwrap();
    let g = skyfield::BeamGeometry::new(&inst);
    let (_, dy) = g.e_offset(240.0, 70.0).unwrap();
    let u = (240.0 - 127.5) / 127.5;
    assert!((dy - (100.0 + 1.5 * u)).abs() < 1e-12, "{dy}");
    let (p, chi) = (0.021f64, 63.0f64);
    let body = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 3\nframe_shifts_px = [[0, 0], [0.6, -0.4], [-0.5, 0.3], [0.2, 0.7]]\n[output]\nbitpix = -32\n[sky]\nbrightness_e = 300\n[effects]\nphoton_noise = true\n[[stars]]\nx = 232\ny = 70\ncoords = \"pixel\"\nflux_e = 8e5\np = {p}\nchi_deg = {chi}\nfwhm_arcsec = 0.8\n",
        ip.display()
    );
    let sc = Scene::from_toml_str(&body, &dir.path().join("s.toml")).unwrap();
    let out = sim::simulate(&sc, &dir.path().join("f"), &|| {}).unwrap();
    let set = frame_set(&out.frames, &inst);
    let r = photometry(&set, &inst, 232.0, 70.0, &Aperture { radius_px: 7.0, annulus: Some((10.0, 16.0)) })
        .unwrap()
        .reduction;
    let (q0, u0) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
    let (pq, pu) = ((r.qu.q - q0) / r.qu.var_q.sqrt(), (r.qu.u - u0) / r.qu.var_u.sqrt());
    assert!(pq.abs() < 4.0 && pu.abs() < 4.0, "pulls {pq} {pu}");
    // A polarized uniform sky through the same mask: every bin returns the sky.
    let body = format!(
        "instrument = \"{}\"\nfilter = \"V\"\n[output]\nbitpix = -64\n[sky]\nbrightness_e = 5000\np = 0.03\nchi_deg = 20\n",
        ip.display()
    );
    let sc = Scene::from_toml_str(&body, &dir.path().join("s2.toml")).unwrap();
    let out = sim::simulate(&sc, &dir.path().join("f2"), &|| {}).unwrap();
    let map = reduce_set(&frame_set(&out.frames, &inst), &inst, &ReduceConfig { bin_px: 16, ..Default::default() })
        .unwrap()
        .map;
    let (q0, u0) = (0.03 * 40f64.to_radians().cos(), 0.03 * 40f64.to_radians().sin());
    let mut n = 0;
    for (q, u) in map.q.iter().zip(&map.u) {
        if q.is_finite() {
            assert!((q - q0).abs() < 1e-9 && (u - u0).abs() < 1e-9, "{q} {u}");
            n += 1;
        }
    }
    assert!(n > 10, "{n} bins");
}
