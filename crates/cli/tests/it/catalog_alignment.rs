//! `instpol catalog` measures each frame's shift and rotation against the first from the
//! stars' centroids (`skyfield::align`, a least-squares similarity transform).
//! The shipped maskless scene's known frame shifts come back; and frames whose stars are turned
//! by 0.2 deg per frame about a point (each frame simulated from a scene with the star
//! positions rotated about (350, 350) px, independently computed here) give rotations of
//! 0, 0.2, 0.4, 0.6 deg within their errors, reported as significant with a warning.

use crate::common;

use common::{fits_in, run};
use std::ffi::OsString;
use std::path::{Path, PathBuf};

const SCENE: &str = include_str!("../../../../instruments/scenes/calcite_stars.toml");

fn instrument(dir: &Path) -> PathBuf {
    let text = include_str!("../../../../instruments/calcite.toml")
        .replace("hwp_angle_keyword = \"\"", "hwp_angle_keyword = \"HWPANG\"");
    let inst = dir.join("calcite.toml");
    std::fs::write(&inst, &text).unwrap();
    inst
}

fn simulate(dir: &Path, scene: String, tag: &str) -> Vec<PathBuf> {
    let sp = dir.join(format!("scene_{tag}.toml"));
    std::fs::write(&sp, scene).unwrap();
    let out = dir.join(tag);
    let (code, _, err) = run(&["simulate".as_ref(), sp.as_os_str(), "--out".as_ref(), out.as_os_str()]);
    assert_eq!(code, 0, "{err}");
    fits_in(&out)
}

fn catalog(inst: &Path, frames: &[PathBuf]) -> (serde_json::Value, String) {
    let mut args: Vec<OsString> = vec!["catalog".into()];
    args.extend(frames.iter().map(|f| f.clone().into_os_string()));
    for a in
        ["--instrument", inst.to_str().unwrap(), "--fwhm", "4.7", "--aperture", "9", "--annulus", "14,24", "--json"]
    {
        args.push(a.into());
    }
    let (code, stdout, err) = run(&args);
    assert_eq!(code, 0, "{err}");
    (serde_json::from_str(&stdout).unwrap(), err)
}

/// The scene's stars as TOML, positions turned by `deg` about (350, 350).
fn stars_rotated(deg: f64) -> String {
    let stars = [
        (150.0, 200.0, 4e5, 0.0572, 136.0),
        (420.0, 450.0, 2e5, 0.0, 0.0),
        (300.0, 600.0, 1e5, 0.021, 12.0),
        (500.0, 300.0, 3e5, 0.04, 70.0),
        (560.0, 560.0, 3e5, 0.05, 100.0),
        (250.0, 420.0, 3e5, 0.01, 40.0),
    ];
    let (s, c) = deg.to_radians().sin_cos();
    stars
        .iter()
        .map(|&(x, y, f, p, chi)| {
            let (dx, dy) = (x - 350.0, y - 350.0);
            format!(
                "[[stars]]\nx = {}\ny = {}\ncoords = \"pixel\"\nflux_e = {f}\np = {p}\nchi_deg = {chi}\nfwhm_arcsec = 1.0\n\n",
                350.0 + c * dx - s * dy,
                350.0 + s * dx + c * dy
            )
        })
        .collect()
}

#[test]
fn catalog_reports_the_scenes_frame_shifts() {
    let dir = tempfile::tempdir().unwrap();
    let inst = instrument(dir.path());
    let scene = SCENE.replace("instrument = \"calcite\"", &format!("instrument = \"{}\"", inst.display()));
    let frames = simulate(dir.path(), scene, "shifted");
    let (j, err) = catalog(&inst, &frames);
    let al = j["alignment"].as_array().unwrap_or_else(|| panic!("{j}"));
    assert_eq!(al.len(), 8, "{j}");
    // The scene's frame_shifts_px, relative to the first frame.
    let shifts = [[0.0, 0.0], [1.3, -0.7], [2.6, 0.4], [-1.2, 2.9], [0.5, -2.2], [-2.8, -1.1], [3.0, 1.7], [-0.4, 0.9]];
    assert!(SCENE.contains("frame_shifts_px = [[0, 0], [1.3, -0.7], [2.6, 0.4]"), "the shipped scene changed");
    for (f, s) in al.iter().zip(shifts) {
        let g = |k: &str| f[k].as_f64().unwrap();
        assert!((g("dx_px") - s[0]).abs() < 0.1 && (g("dy_px") - s[1]).abs() < 0.1, "{f} vs {s:?}");
        assert!(!f["rotation_significant"].as_bool().unwrap(), "{f}");
    }
    assert!(!err.contains("rotated"), "{err}");
}

#[test]
fn frames_rotated_by_0_2_deg_per_frame() {
    let dir = tempfile::tempdir().unwrap();
    let inst = instrument(dir.path());
    let base = SCENE
        .replace("instrument = \"calcite\"", &format!("instrument = \"{}\"", inst.display()))
        .replace("hwp_angles_deg = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]", "hwp_angles_deg = [0, 22.5, 45, 67.5]")
        .replace(
            "frame_shifts_px = [[0, 0], [1.3, -0.7], [2.6, 0.4], [-1.2, 2.9], [0.5, -2.2], [-2.8, -1.1], [3.0, 1.7], [-0.4, 0.9]]",
            "frame_shifts_px = []",
        );
    let head = &base[..base.find("[[stars]]").unwrap()];
    let effects = &base[base.find("[effects]").unwrap()..];
    assert!(head.contains("[0, 22.5, 45, 67.5]") && head.contains("frame_shifts_px = []"), "scene changed");
    // Frame k from a scene turned by 0.2 k deg.
    let frames: Vec<PathBuf> = (0..4)
        .map(|k| {
            let scene = format!("{head}{}{effects}", stars_rotated(0.2 * k as f64));
            simulate(dir.path(), scene, &format!("rot{k}"))[k].clone()
        })
        .collect();
    let (j, err) = catalog(&inst, &frames);
    let al = j["alignment"].as_array().unwrap();
    assert_eq!(al.len(), 4, "{j}");
    for (k, f) in al.iter().enumerate() {
        let (r, s) = (f["rotation_deg"].as_f64().unwrap(), f["sigma_rotation_deg"].as_f64().unwrap_or(0.0));
        let want = 0.2 * k as f64;
        assert!((r - want).abs() < 4.0 * s + 1e-9, "frame {k}: {r} +- {s} deg vs {want}");
        assert!(s < 0.02, "frame {k}: rotation error {s} deg");
        assert_eq!(f["rotation_significant"].as_bool().unwrap(), k > 0, "{f}");
    }
    assert!(err.contains("rotated by"), "{err}");
    // Every star still measured: the apertures followed the centroids.
    let rows = j["rows"].as_array().unwrap();
    assert_eq!(rows.iter().filter(|r| r["q"].is_number()).count(), 6, "{j}");
}
