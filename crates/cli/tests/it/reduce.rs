//! `instpol reduce` end to end: simulate, reduce, read the map back.

use crate::common;

use common::{fits_in, instpol};
use std::path::Path;

/// A 128 x 128 detector with one 40-px strip (rows 20..60 o, 60..100 e).
fn tiny_instrument(dir: &Path) -> std::path::PathBuf {
    common::tiny_fors1(dir, 8.0, 20)
}

fn sim(dir: &Path, inst: &Path, angles: &str, out: &str) -> Vec<std::path::PathBuf> {
    let scene = dir.join(format!("{out}.toml"));
    std::fs::write(
        &scene,
        format!(
            "instrument = \"{}\"\nfilter = \"V\"\nhwp_angles_deg = {angles}\n[output]\nbitpix = -64\n[sky]\nbrightness_e = 3000\np = 0.0645\nchi_deg = 68.4\n",
            inst.display()
        ),
    )
    .unwrap();
    let o = instpol().arg("simulate").arg(&scene).arg("--out").arg(dir.join(out)).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    fits_in(&dir.join(out))
}

#[test]
fn reduce_round_trip_through_the_map_file() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let frames = sim(dir.path(), &inst, "[0, 22.5, 45, 67.5]", "a");
    let map = dir.path().join("map.fits");
    let o = instpol()
        .arg("reduce")
        .args(&frames)
        .arg("--instrument")
        .arg(&inst)
        .arg("--bin")
        .arg("10")
        .arg("--out")
        .arg(&map)
        .arg("--json")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!((j["median_p"].as_f64().unwrap() - 0.0645).abs() < 1e-10, "{j}");
    let m = skyfield::StokesMap::read_fits(&map).unwrap();
    assert_eq!(m.geometry.bin_px, 10);
    assert_eq!(m.hwp_angles_deg, vec![0.0, 22.5, 45.0, 67.5]);
    let q0 = 0.0645 * (2.0 * 68.4f64.to_radians()).cos();
    for (k, _, _) in m.valid_bins() {
        assert!((m.q[k] - q0).abs() < 1e-10);
    }
}

#[test]
fn missing_angle_exits_2_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let frames = sim(dir.path(), &inst, "[0, 22.5, 45, 67.5]", "b");
    let map = dir.path().join("map.fits");
    let o = instpol()
        .arg("reduce")
        .args(&frames[..3])
        .arg("--instrument")
        .arg(&inst)
        .arg("--out")
        .arg(&map)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("missing [67.5 deg]"), "{err}");
    assert!(!map.exists());
    assert_eq!(
        std::fs::read_dir(dir.path())
            .unwrap()
            .filter(|e| e.as_ref().unwrap().path().extension().is_some_and(|x| x == "tmp"))
            .count(),
        0
    );
}

/// Errors that hold at every bin size: a photon-noise sky of known polarization (2 % at 30
/// deg) reduced in bins of 2 x 2, 4 x 4 and 8 x 8 px has (q - q_true) / sigma_q with an RMS
/// of 1 over its bins (within 0.8..1.25; over 60 to 576 bins the RMS itself is known to a few
/// per cent). The bins' scatter alone gave 2.5 and 2.8 at the two smaller sizes: the photon
/// error is its floor there (`skyfield::reduce::SCATTER_MIN_PIXELS`).
#[test]
fn bin_errors_are_right_at_every_bin_size() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let ins = d.join("mini.toml");
    std::fs::write(&ins, common::MINI.toml()).unwrap();
    let scene = d.join("scene.toml");
    std::fs::write(
        &scene,
        "instrument = \"mini.toml\"\nfilter = \"V\"\nseed = 3\n[sky]\nbrightness_e = 20000\np = 0.02\nchi_deg = 30\n[effects]\nphoton_noise = true\n",
    )
    .unwrap();
    let o = instpol().arg("simulate").arg(&scene).arg("--out").arg(d.join("f")).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (q0, u0) = (0.02 * 60f64.to_radians().cos(), 0.02 * 60f64.to_radians().sin());
    for bin in [2, 4, 8] {
        let map = d.join(format!("m{bin}.fits"));
        let o = instpol()
            .args(["reduce", "--instrument"])
            .arg(&ins)
            .args(["--bin", &bin.to_string(), "--out"])
            .arg(&map)
            .args(fits_in(&d.join("f")))
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let m = skyfield::StokesMap::read_uncorrected(&map).unwrap();
        let (mut sq, mut su, mut n) = (0.0, 0.0, 0.0);
        for k in (0..m.valid.len()).filter(|&k| m.valid[k]) {
            sq += ((m.q[k] - q0) / m.sigma_q[k]).powi(2);
            su += ((m.u[k] - u0) / m.sigma_u[k]).powi(2);
            n += 1.0;
        }
        let (rq, ru) = ((sq / n).sqrt(), (su / n).sqrt());
        assert!(n >= 60.0, "bin {bin}: {n} bins");
        assert!(
            (0.8..1.25).contains(&rq) && (0.8..1.25).contains(&ru),
            "bin {bin}: RMS pulls {rq:.2}, {ru:.2} over {n} bins"
        );
    }
}

/// Plain strip-mask frames (FORS1 shrunk) that still carry a 200 ADU pedestal: the masked
/// strips, which receive no light, show it, and the reduction is refused naming the frame
/// (it reduced silently with every P low by the pedestal's fraction of the strips' level,
/// 200 / (3000 / gain + 200)). With the pedestal stated as the instrument's `bias_adu`, the
/// frames give the simulated sky's P exactly.
#[test]
fn a_pedestal_left_in_plain_frames_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let inst = tiny_instrument(d);
    let frames = sim(d, &inst, "[0, 22.5, 45, 67.5]", "a");
    for f in &frames {
        let mut ff = fitsio::FitsFile::edit(f).unwrap();
        let hdu = ff.primary_hdu().unwrap();
        let img: Vec<f64> = hdu.read_image(&mut ff).unwrap();
        let img: Vec<f64> = img.iter().map(|v| v + 200.0).collect();
        hdu.write_image(&mut ff, &img).unwrap();
    }
    let reduce = |ins: &Path, out: &str| {
        instpol()
            .arg("reduce")
            .args(&frames)
            .arg("--instrument")
            .arg(ins)
            .args(["--bin", "10", "--json", "--out"])
            .arg(d.join(out))
            .output()
            .unwrap()
    };
    let o = reduce(&inst, "map.fits");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    let name = frames[0].file_name().unwrap().to_str().unwrap();
    assert!(err.contains(name) && err.contains("masked strips") && err.contains("200.0 ADU"), "{err}");
    assert!(!d.join("map.fits").exists());
    // The pedestal stated as the instrument's bias: the sky's P, as without it.
    let text = std::fs::read_to_string(&inst).unwrap();
    assert!(text.contains("bias_adu = 0.0"), "the tiny FORS1 states no bias");
    let with_bias = d.join("tiny_bias.toml");
    std::fs::write(&with_bias, text.replace("bias_adu = 0.0", "bias_adu = 200.0")).unwrap();
    let o = reduce(&with_bias, "map2.fits");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!((j["median_p"].as_f64().unwrap() - 0.0645).abs() < 1e-9, "{j}");
}

/// Through a quarter-wave plate (the tiny FORS1 with `plate = "quarter_wave"`), `instpol reduce`
/// writes a V/I map: noiseless frames of a sky with V/I = 1.5 % and 4 % linear polarization at
/// -45 and 45 deg give every valid bin the sky's V/I (the closed form `v = (F(45) - F(-45)) /
/// 2`, where the linear terms vanish), read back from the file (`STOKES = 'V'`); the JSON
/// summary says so. The commands that need Q/I, U/I (calibrate, calibrate-mueller, correct)
/// refuse the map, saying what it is.
#[test]
fn quarter_wave_plate_reduces_to_a_v_map_the_q_u_readers_refuse() {
    let dir = tempfile::tempdir().unwrap();
    let tiny = std::fs::read_to_string(tiny_instrument(dir.path())).unwrap();
    let inst = dir.path().join("tiny_qwp.toml");
    std::fs::write(&inst, tiny.replace("[polarimetry]\n", "[polarimetry]\nplate = \"quarter_wave\"\n")).unwrap();
    let scene = dir.path().join("qwp.toml");
    std::fs::write(
        &scene,
        format!(
            "instrument = \"{}\"\nfilter = \"V\"\nhwp_angles_deg = [-45, 45]\n[output]\nbitpix = -64\n[sky]\n\
             brightness_e = 3000\np = 0.04\nchi_deg = 30\nv = 0.015\n",
            inst.display()
        ),
    )
    .unwrap();
    let o = instpol().arg("simulate").arg(&scene).arg("--out").arg(dir.path().join("f")).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let frames = fits_in(&dir.path().join("f"));
    let map = dir.path().join("vmap.fits");
    let o = instpol()
        .arg("reduce")
        .args(&frames)
        .args(["--instrument", inst.to_str().unwrap(), "--bin", "10", "--out", map.to_str().unwrap(), "--json"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["stokes"], "V", "{j}");
    assert_eq!(j["plate_deg"], serde_json::json!([-45.0, 45.0]));
    assert!((j["median_v"].as_f64().unwrap() - 0.015).abs() < 1e-10, "{j}");
    let m = skyfield::CircularMap::read_fits(&map).unwrap();
    // The V map says what it is: a quarter-wave plate's, of this instrument file.
    let p = m.product.as_ref().expect("the V map's product");
    assert_eq!(p.plate.as_deref(), Some("quarter_wave"));
    assert_eq!(p.instrument_hash, Some(skyfield::provenance::hash_hex(&std::fs::read(&inst).unwrap())));
    assert_eq!(p.inputs.len(), frames.len() + 1, "the frames' and the instrument file's hashes");
    // One 40-px strip (4 bin rows), 128 px across: 12 bins of 10 px and one of 8.
    assert_eq!(m.n_valid(), 13 * 4);
    for (k, _, _) in m.valid_bins() {
        assert!((m.v[k] - 0.015).abs() < 1e-10, "bin {k}: {}", m.v[k]);
    }
    let cal = dir.path().join("cal.fits");
    common::fors1_radial_calibration("V", common::V_COEFFS).save(&cal).unwrap();
    let m_s = map.to_str().unwrap();
    let field = format!("{m_s}:4:10");
    let out = |n: &str| dir.path().join(n).to_string_lossy().into_owned();
    for args in [
        common::calibrate_v_args(&map, &dir.path().join("c.fits")),
        ["calibrate-mueller", "--field", &field, "--out", &out("mf.json")].map(String::from).to_vec(),
        ["correct", "--cal", cal.to_str().unwrap(), "--in", m_s, "--out", &out("corr.fits")].map(String::from).to_vec(),
    ] {
        let (code, _, err) = common::run(&args);
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(
            err.contains("vmap.fits") && err.contains("STOKES = 'V'") && err.contains("holds no Q/I, U/I"),
            "{args:?}: {err}"
        );
    }
}

/// The tiny FORS1 with a turning plate: the rotor's position (MOPRPOS, 16 a turn from 1)
/// gives each exposure's 22.5 deg range of plate angle.
fn turning_instrument(dir: &Path) -> std::path::PathBuf {
    let tiny = std::fs::read_to_string(tiny_instrument(dir)).unwrap().replace(
        "hwp_angle_keyword = \"HIERARCH ESO INS RETA2 POSANG\"",
        "rotation = { position_keyword = \"MOPRPOS\", positions_per_turn = 16, first_position = 1, zero_deg = 0.0 }",
    );
    let p = dir.join("turning.toml");
    std::fs::write(&p, tiny).unwrap();
    p
}

/// A turning plate's set of 16 rotor positions with one missing is refused naming the
/// missing range's middle angle (56.25 deg), as a fixed plate's incomplete set is, where it
/// was reduced to P 3.78 % for a 4 % sky; with --allow-incomplete it is reduced by least
/// squares with that angle named in a warning. The whole set gives the sky's P back (the
/// scene's 4 %, with the rotor's averaged modulation).
#[test]
fn a_turning_plate_set_missing_a_position_is_refused_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let inst = turning_instrument(dir.path());
    let scene = dir.path().join("s.toml");
    let angles: Vec<String> = (0..16).map(|k| format!("{}", 11.25 + 22.5 * k as f64)).collect();
    std::fs::write(
        &scene,
        format!(
            "instrument = \"{}\"\nfilter = \"V\"\nhwp_angles_deg = [{}]\n[hwp_motion]\nsweep_deg = 22.5\n[output]\nbitpix = -64\n\
             [sky]\nbrightness_e = 3000\np = 0.04\nchi_deg = 30\n",
            inst.display(),
            angles.join(", ")
        ),
    )
    .unwrap();
    let o = instpol().arg("simulate").arg(&scene).arg("--out").arg(dir.path().join("f")).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let frames = fits_in(&dir.path().join("f"));
    assert_eq!(frames.len(), 16);
    let reduce = |frames: &[std::path::PathBuf], extra: &[&str]| {
        let map = dir.path().join("m.fits");
        let _ = std::fs::remove_file(&map);
        let o = instpol()
            .arg("reduce")
            .args(frames)
            .args(["--instrument", inst.to_str().unwrap(), "--bin", "10", "--json", "--out"])
            .arg(&map)
            .args(extra)
            .output()
            .unwrap();
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stdout).to_string(),
            String::from_utf8_lossy(&o.stderr).to_string(),
        )
    };
    let (code, out, err) = reduce(&frames, &[]);
    assert_eq!(code, Some(0), "{err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert!((j["median_p"].as_f64().unwrap() - 0.04).abs() < 1e-9, "{j}");
    let short: Vec<_> = frames.iter().filter(|f| !f.to_str().unwrap().contains("frame_02_")).cloned().collect();
    assert_eq!(short.len(), 15);
    let (code, _, err) = reduce(&short, &[]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("missing [56.25 deg]") && err.contains("N = 16"), "{err}");
    assert!(!dir.path().join("m.fits").exists());
    let (code, _, err) = reduce(&short, &["--allow-incomplete"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(err.contains("missing [56.25 deg]") && err.contains("least squares"), "{err}");
}
