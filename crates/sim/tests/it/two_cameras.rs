//! Two cameras behind a polarizing beam splitter with a continuously turning half-wave plate
//! (the MOPTOP class), end to end: each exposure is two raw files, one per camera (named by a
//! CAMERA keyword, paired by the run number), the e camera flipped in x, with a 3 % higher gain
//! and its own flat-field errors; the rotor's position (16 per turn, two turns) in the header
//! gives each exposure's 22.5 deg range of plate angle. The reading instrument file gives no
//! camera transform: it is measured from the stars. 40 stars of known P and chi come back
//! within their errors; demodulated as if the plate stood still, P is low by
//! sin(2d)/(2d) = 0.9003.

use sim::Scene;
use skyfield::photometry::{layout_for, photometry_with, Aperture, PhotOptions};
use skyfield::reduce::{read_frames, FrameSet};
use std::path::{Path, PathBuf};

use crate::two_cameras_setup as two_cameras;
use two_cameras::TRANSFORM;

/// Two 160 x 160 px cameras (`common/two_cameras.rs`) behind a plate turning through 16
/// positions a turn; the simulating file gives the camera transform, the reading one
/// (`measured`) leaves it to the stars.
fn instrument(dir: &Path, measured: bool) -> PathBuf {
    let transform = if measured { String::new() } else { format!("transform = {TRANSFORM}\n") };
    let plate =
        "rotation = { position_keyword = \"MOPRPOS\", positions_per_turn = 16, first_position = 1, zero_deg = 0.0 }\n";
    let text = two_cameras::instrument_text(plate, &format!("{transform}max_residual_px = 0.3\n"));
    let p = dir.join(if measured { "twocam_read.toml" } else { "twocam_sim.toml" });
    std::fs::write(&p, text).unwrap();
    p
}

/// 40 stars on an 8 x 5 grid of the o camera, P from 0.5 % to 5 %, chi all round.
fn stars() -> Vec<(f64, f64, f64, f64, f64)> {
    (0..40)
        .map(|k| {
            let (i, j) = (k % 8, k / 8);
            let (x, y) = (16.0 + 18.3 * i as f64 + 0.13 * j as f64, 17.0 + 30.5 * j as f64 - 0.11 * i as f64);
            let p = 0.005 + 0.045 * ((7 * k) % 40) as f64 / 39.0;
            let chi = (11.0 + 47.0 * k as f64) % 180.0;
            (x, y, p, chi, 2.5e5 * (1.0 + (k % 3) as f64 * 0.5))
        })
        .collect()
}

fn simulate(dir: &Path) -> Vec<PathBuf> {
    let inst = instrument(dir, false);
    // Two turns of the rotor: positions 1..16 twice, each sweeping 22.5 deg about its middle.
    let angles: Vec<String> = (0..32).map(|k| format!("{}", 11.25 + 22.5 * (k % 16) as f64)).collect();
    let mut body = format!(
        "instrument = \"{}\"\nfilter = \"R\"\nseed = 3\nhwp_angles_deg = [{}]\nhwp_motion = {{ sweep_deg = 22.5 }}\n\
         [output]\nbitpix = -32\n[sky]\nbrightness_e = 60\np = 0.0\nchi_deg = 0\n[effects]\nphoton_noise = true\n\
         read_noise = true\nflat = {{ pixel_rms_o = 0.004, pixel_rms_e = 0.007, large_scale_o = 0.01, large_scale_e = 0.02 }}\n",
        inst.display(),
        angles.join(", ")
    );
    for (x, y, p, chi, f) in stars() {
        body += &format!(
            "[[stars]]\nx = {x}\ny = {y}\ncoords = \"pixel\"\nflux_e = {f}\np = {p}\nchi_deg = {chi}\nfwhm_arcsec = 0.9\n"
        );
    }
    let sc = Scene::from_toml_str(&body, &dir.join("scene.toml")).unwrap();
    sim::simulate(&sc, &dir.join("frames"), &|| {}).unwrap().frames
}

/// The must-show: every star's q, u within its errors (RMS pull near 1, each below 4) through
/// the measured camera transform (residual below 0.1 px, the true map to 0.05 px), and the
/// same frames demodulated as if the plate stood still low in P by sin(2d)/(2d) = 0.9003 (the
/// mean ratio over the 40 stars within 3 of its errors of it, and more than 5 of them below 1).
#[test]
fn two_cameras_with_a_turning_plate_give_every_star_within_errors() {
    let dir = tempfile::tempdir().unwrap();
    let files = simulate(dir.path());
    assert_eq!(files.len(), 64, "two files per exposure");
    let inst = instrument::Instrument::load(instrument(dir.path(), true).to_str().unwrap()).unwrap();
    let frames = read_frames(&files, &inst, &|| {}).unwrap();
    assert_eq!(frames.len(), 32);
    let mut set = FrameSet::from_frames(frames, &inst, true).unwrap();
    assert_eq!((set.angles_deg.len(), set.hwp_sweep_deg), (16, 22.5));
    assert!(set.files.iter().all(|f| f.len() == 2), "each position twice, one per turn");
    let g = layout_for(&set, &inst).unwrap();
    let c = g.cameras.clone().unwrap();
    let (t, (rms, pairs)) = (c.transform.unwrap(), c.measured.unwrap());
    eprintln!("camera transform {t:?}: residual RMS {rms:.3} px over {pairs} pairs");
    assert!(pairs >= 30 && rms < 0.1, "{pairs} pairs, RMS {rms}");
    // The true map at the camera's corners and centre, to 0.05 px.
    for (u, v) in [(0.0, 0.0), (159.0, 0.0), (0.0, 159.0), (159.0, 159.0), (80.0, 80.0)] {
        let (x, y) = (t[0] * u + t[1] * v + t[2], t[3] * u + t[4] * v + t[5]);
        assert!((x - u - 1.7).abs() < 0.05 && (y - v + 2.3).abs() < 0.05, "({u}, {v}) -> ({x}, {y})");
    }
    let ap = Aperture { radius_px: 4.0, annulus: Some((6.0, 8.5)) };
    let opts = PhotOptions::default();
    let measure = |set: &FrameSet| -> Vec<stokes::Reduction> {
        stars().iter().map(|&(x, y, ..)| photometry_with(set, &g, x, y, &ap, &opts).unwrap().reduction).collect()
    };
    let (mut pulls, mut ratios, mut sig) = (Vec::new(), Vec::new(), Vec::new());
    for ((x, y, p, chi, _), r) in stars().into_iter().zip(measure(&set)) {
        let (q0, u0) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
        let (pq, pu) = ((r.qu.q - q0) / r.qu.var_q.sqrt(), (r.qu.u - u0) / r.qu.var_u.sqrt());
        assert!(pq.abs() < 4.0 && pu.abs() < 4.0, "star at ({x}, {y}): q {} vs {q0}, u {} vs {u0}", r.qu.q, r.qu.u);
        pulls.extend([pq, pu]);
    }
    // The same frames as if the plate stood still at each range's middle.
    set.hwp_sweep_deg = 0.0;
    for ((_, _, p, _, _), r) in stars().into_iter().zip(measure(&set)) {
        ratios.push(r.p / p);
        sig.push(r.sigma_p / p);
    }
    let rms_pull = (pulls.iter().map(|p| p * p).sum::<f64>() / pulls.len() as f64).sqrt();
    let n = ratios.len() as f64;
    let mean = ratios.iter().sum::<f64>() / n;
    let err = sig.iter().map(|s| s * s).sum::<f64>().sqrt() / n;
    let sinc = (2.0 * 22.5f64.to_radians()).sin() / (2.0 * 22.5f64.to_radians());
    eprintln!("two cameras: RMS pull {rms_pull:.2} over {}; as if fixed: P ratio {mean:.4} +- {err:.4} (closed form {sinc:.4})", pulls.len());
    assert!(rms_pull > 0.6 && rms_pull < 1.4, "RMS pull {rms_pull} ({pulls:?})");
    assert!((mean - sinc).abs() < 3.0 * err, "fixed-plate P ratio {mean} +- {err}, closed form {sinc}");
    assert!(1.0 - mean > 5.0 * err, "the fixed-plate reduction should be measurably low: {mean} +- {err}");

    // The catalog finds and pairs the stars across the cameras by itself, reports the measured
    // transform, and measures each star within its errors too.
    let cfg = skyfield::catalog::CatalogConfig {
        radius: skyfield::photometry::ApertureRadius::Px(4.0),
        annulus: Some((6.0, 8.5)),
        ..Default::default()
    };
    let (cat, warnings) =
        skyfield::catalog::catalog_files(&files, &inst, &Default::default(), &cfg, Box::new(|| {})).unwrap();
    let ct = cat.camera_transform.unwrap();
    assert!(ct.residual_rms_px.unwrap() < 0.1 && ct.pairs.unwrap() >= 30, "{ct:?}");
    assert!(warnings.iter().any(|w| w.message.contains("camera transform measured")), "{warnings:?}");
    let mut found = 0;
    for (x, y, p, chi, _) in stars() {
        let Some(r) = cat.rows.iter().find(|r| (r.x - x).hypot(r.y - y) < 1.5 && r.q.is_finite()) else { continue };
        let (q0, u0) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
        assert!(
            (r.q - q0).abs() < 4.0 * r.sigma_q && (r.u - u0).abs() < 4.0 * r.sigma_u,
            "catalog star ({x}, {y}): {r:?}"
        );
        found += 1;
    }
    assert!(found >= 36, "the catalog measured {found} of the 40 stars");
}

/// The camera transform is refused, with what to do, when too few stars match (two stars) and
/// when the fitted map's residual is beyond the instrument file's bound; a per-pixel map of two
/// cameras is refused naming the reason.
#[test]
fn camera_transform_and_maps_refuse_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let files = simulate(dir.path());
    let read = instrument(dir.path(), true);
    let text = std::fs::read_to_string(&read).unwrap();
    let tight = dir.path().join("tight.toml");
    std::fs::write(&tight, text.replace("max_residual_px = 0.3", "max_residual_px = 0.001")).unwrap();
    let inst = instrument::Instrument::load(tight.to_str().unwrap()).unwrap();
    let set = FrameSet::from_frames(read_frames(&files[..4], &inst, &|| {}).unwrap(), &inst, false).unwrap();
    let e = layout_for(&set, &inst).unwrap_err().to_string();
    assert!(e.contains("RMS residual") && e.contains("max_residual_px") && e.contains("transform"), "{e}");
    // A frame with two stars only: its first exposure, all but two stars' light cut.
    let inst = instrument::Instrument::load(read.to_str().unwrap()).unwrap();
    let mut set = FrameSet::from_frames(read_frames(&files[..4], &inst, &|| {}).unwrap(), &inst, false).unwrap();
    let (nx, keep) = (set.nx, [(16.0, 17.0), (125.0, 80.0)]);
    for d in &mut set.data {
        for (p, v) in d.iter_mut().enumerate() {
            let (x, y) = ((p % nx) as f64, (p / nx) as f64);
            let near = keep.iter().any(|&(sx, sy)| {
                (x - sx).hypot(y - sy) < 8.0 || (x - (170.0 + 159.0 - sx - 1.7)).hypot(y - sy + 2.3) < 8.0
            });
            if !near && v.is_finite() && *v > -1e30 {
                *v = 60.0;
            }
        }
    }
    let e = layout_for(&set, &inst).unwrap_err().to_string();
    assert!(e.contains("fewer than 3 star pairs") && e.contains("give [polarimetry.cameras] transform"), "{e}");
    let g = skyfield::beams::BeamGeometry::new(&inst);
    assert!(g.require_separable_sky().unwrap_err().contains("two cameras"));
}
