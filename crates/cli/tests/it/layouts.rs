//! Beam layouts through the binary: maskless calcite frames simulated and measured with the
//! tool alone, and the layout errors a user can make in an instrument file, each refused with
//! exit 2 and a message naming the file and key.

use crate::common;

use common::{fits_in, run};
use std::path::Path;

/// `simulate` then `photometry` of the scene shipped for the maskless example (three stars, a
/// 5.7 % standard among them, frames moving by up to 3 px): each star's q, u within 4 sigma of
/// the scene's, and `reduce` of the same frames refused because the two beams' sky overlaps.
#[test]
fn maskless_scene_is_simulated_and_measured_with_the_tool_alone() {
    // The shipped scene and the built-in instrument as they are: no HWP keyword in the
    // headers, so the angles come with the frames (--hwp-angles, in the frames' order).
    let dir = tempfile::tempdir().unwrap();
    let sp = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/scenes/calcite_stars.toml");
    let out = dir.path().join("f");
    let (code, _, err) = run(&["simulate".as_ref(), sp.as_os_str(), "--out".as_ref(), out.as_os_str()]);
    assert_eq!(code, 0, "{err}");
    let frames = fits_in(&out);
    assert_eq!(frames.len(), 8);
    let angles = "0,22.5,45,67.5,90,112.5,135,157.5";
    for (x, y, p, chi) in [(150.0, 200.0, 0.0572, 136.0), (420.0, 450.0, 0.0, 0.0), (300.0, 600.0, 0.021, 12.0)] {
        let mut args: Vec<std::ffi::OsString> = vec!["photometry".into()];
        args.extend(frames.iter().map(|f| f.clone().into_os_string()));
        for a in ["--instrument", "calcite", "--hwp-angles", angles, "--x", &format!("{x}"), "--y", &format!("{y}")] {
            args.push(a.into());
        }
        for a in ["--aperture", "9", "--annulus", "14,24", "--json"] {
            args.push(a.into());
        }
        let (code, stdout, err) = run(&args);
        assert_eq!(code, 0, "{err}");
        let j: serde_json::Value = serde_json::from_str(&stdout).unwrap();
        let f = |k: &str| j[k].as_f64().unwrap();
        let (q0, u0) = (p * (2.0 * f64::to_radians(chi)).cos(), p * (2.0 * f64::to_radians(chi)).sin());
        let (pq, pu) = ((f("q") - q0) / f("sigma_q"), (f("u") - u0) / f("sigma_u"));
        assert!(pq.abs() < 4.0 && pu.abs() < 4.0, "star at ({x}, {y}): pulls {pq:.2}, {pu:.2}: {j}");
        let off = j["oe_offset_px"].as_array().unwrap();
        assert_eq!(off[0].as_f64(), Some(70.2));
    }
    // Without the angles the frames cannot be read, and the message says what to give.
    let mut args: Vec<std::ffi::OsString> = vec!["photometry".into()];
    args.extend(frames.iter().map(|f| f.clone().into_os_string()));
    for a in ["--instrument", "calcite", "--x", "150", "--y", "200"] {
        args.push(a.into());
    }
    let (code, _, err) = run(&args);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("--hwp-angles"), "{err}");
    let mut args: Vec<std::ffi::OsString> = vec!["reduce".into()];
    args.extend(frames.iter().map(|f| f.clone().into_os_string()));
    for a in ["--instrument", "calcite", "--hwp-angles", angles, "--out"] {
        args.push(a.into());
    }
    args.push(dir.path().join("map.fits").into_os_string());
    let (code, _, err) = run(&args);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("maskless") && err.contains("overlap"), "{err}");
    assert!(!dir.path().join("map.fits").exists());
}

/// Layout mistakes in an instrument file: an unknown layout, a maskless offset outside the
/// detector, a throw that varies more than the strip margin allows.
#[test]
fn layout_mistakes_in_the_instrument_file_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let fors1 = include_str!("../../../../instruments/fors1.toml");
    let calcite = include_str!("../../../../instruments/calcite.toml");
    let cases = [
        ("unknown.toml", fors1.replace("strip_axis = \"y\"", "layout = \"savart\"\nstrip_axis = \"y\""), "savart"),
        ("far.toml", calcite.replace("oe_offset_px = [70.2, 0.0]", "oe_offset_px = [70.2, 800.0]"), "oe_offset_px"),
        (
            "swing.toml",
            fors1.replace("strip_axis = \"y\"", "strip_axis = \"y\"\nthrow_terms = [{ i = 2, j = 0, c = 3.0 }]"),
            "strip_margin_px",
        ),
    ];
    refused_by_simulate(dir.path(), &cases);
}

/// Each instrument file `(name, text, key)` of `cases`, written to `dir/name` and simulated
/// through a bare scene, is refused (exit 2) naming the file and the key, before any output.
fn refused_by_simulate(dir: &Path, cases: &[(&str, String, &str)]) {
    for (name, text, key) in cases {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        let scene = dir.join(format!("{name}.scene.toml"));
        std::fs::write(&scene, format!("instrument = \"{}\"\nfilter = \"V\"\n", p.display())).unwrap();
        let out = dir.join(format!("{name}.out"));
        let (code, _, err) = run(&["simulate".as_ref(), scene.as_os_str(), "--out".as_ref(), out.as_os_str()]);
        assert_eq!(code, 2, "{name}: {err}");
        assert!(err.contains(name) && err.contains(key), "{name}: {err}");
        assert!(!out.exists(), "{name}: output folder created");
    }
}

/// Mistakes in a turning plate's and two cameras' keys: the rotation given both ways, a rotor of
/// 4 positions per turn (90 deg per exposure modulates nothing), two cameras without their
/// table or naming a chip the format lacks; and a scene whose plate sweeps 90 deg. Each is
/// refused before anything is written, naming the file and the key.
#[test]
fn plate_motion_and_camera_mistakes_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let fors1 = include_str!("../../../../instruments/fors1.toml");
    let moptop = include_str!("../../../../instruments/moptop.toml");
    let rot = |table: &str| {
        fors1.replace("exptime_keyword = \"EXPTIME\"\n", &format!("exptime_keyword = \"EXPTIME\"\n{table}\n"))
    };
    let no_cameras = {
        let cut = &moptop[..moptop.find("[polarimetry.cameras]").unwrap()];
        format!("{cut}{}", &moptop[moptop.find("[format]").unwrap()..])
    };
    let cases = [
        (
            "both.toml",
            rot("rotation = { begin_keyword = \"B\", end_keyword = \"E\", position_keyword = \"P\", positions_per_turn = 16 }"),
            "begin_keyword/position_keyword",
        ),
        ("four.toml", rot("rotation = { position_keyword = \"P\", positions_per_turn = 4 }"), "positions_per_turn"),
        ("nocams.toml", no_cameras, "polarimetry.cameras"),
        ("chip.toml", moptop.replace("e_chip = \"CAM2\"", "e_chip = \"CAM9\""), "e_chip"),
    ];
    refused_by_simulate(dir.path(), &cases);
    let scene = dir.path().join("quarter.scene.toml");
    std::fs::write(
        &scene,
        "instrument = \"fors1\"\nfilter = \"V\"\nhwp_angles_deg = [0, 22.5, 45, 67.5]\nhwp_motion = { sweep_deg = 90 }\n",
    )
    .unwrap();
    let out = dir.path().join("quarter.out");
    let (code, _, err) = run(&["simulate".as_ref(), scene.as_os_str(), "--out".as_ref(), out.as_os_str()]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("quarter.scene.toml") && err.contains("nothing modulated"), "{err}");
    assert!(!out.exists());
}
