//! `instpol simulate` end to end on a small instrument.

use crate::common;

use common::instpol;
use std::path::{Path, PathBuf};

/// A 128 x 128 detector with one 40-px strip (rows 20..60 o, 60..100 e).
pub fn tiny_instrument(dir: &Path) -> PathBuf {
    common::tiny_fors1(dir, 8.0, 20)
}

#[test]
fn writes_frames_truth_and_explains() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let scene = dir.path().join("s.toml");
    std::fs::write(
        &scene,
        format!(
            "instrument = \"{}\"\nfilter = \"V\"\n[sky]\nbrightness_e = 3000\np = 0.0174\nchi_deg = -53.8\n[effects]\nphoton_noise = true\nwollaston = {{ t = 0.51 }}\n",
            inst.display()
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    let o =
        instpol().arg("simulate").arg(&scene).arg("--out").arg(&out).arg("--explain").arg("--json").output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("photon noise") && err.contains("Wollaston t = 0.51"), "{err}");
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["outputs"].as_array().unwrap().len(), 4);
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("truth.json")).unwrap()).unwrap();
    assert_eq!(truth["scene"]["sky"]["p"], 0.0174);
    assert_eq!(truth["frames"][1]["hwp_deg"], 22.5);
    // Only the frames and the truth file: no temporary leftovers.
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 5);
}

#[test]
fn unknown_key_exits_2_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("s.toml");
    std::fs::write(&scene, "instrument = \"fors1\"\nfilter = \"V\"\n[effects]\nphotonnoise = true\n").unwrap();
    let out = dir.path().join("out");
    let o = instpol().arg("simulate").arg(&scene).arg("--out").arg(&out).output().unwrap();
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.starts_with("error:") && err.contains("photonnoise"), "{err}");
    assert!(!out.exists());
}

/// A chip instrument's scene (`[format]` with chips): a uniform sky of P = 2%, chi = 30 deg
/// behind the strip mask, with photon and read noise.
fn chip_scene(dir: &Path, inst_text: &str, filter: &str) -> (PathBuf, PathBuf) {
    let inst = dir.join("inst.toml");
    std::fs::write(&inst, inst_text).unwrap();
    let scene = dir.join("s.toml");
    std::fs::write(
        &scene,
        format!(
            "instrument = \"{}\"\nfilter = \"{filter}\"\nseed = 11\n[sky]\nbrightness_e = 40000\np = 0.02\nchi_deg = 30\n[effects]\nphoton_noise = true\nread_noise = true\n",
            inst.display()
        ),
    )
    .unwrap();
    (inst, scene)
}

/// Every valid bin of the map within 5 sigma of the scene's (q, u) = p (cos 2chi, sin 2chi)
/// (eq:poldeg, eq:polang inverted), their mean within 4 standard errors.
fn assert_scene_sky(map: &Path) {
    let m = skyfield::StokesMap::read_fits(map).unwrap();
    let (q0, u0) = (0.02 * 60f64.to_radians().cos(), 0.02 * 60f64.to_radians().sin());
    let v: Vec<usize> = (0..m.q.len()).filter(|&k| m.valid[k]).collect();
    assert!(v.len() >= 10, "{} valid bins", v.len());
    let (mut sq, mut su, mut se) = (0.0, 0.0, 0.0);
    for &k in &v {
        assert!((m.q[k] - q0).abs() < 5.0 * m.sigma_q[k], "bin {k}: Q {} +- {} vs {q0}", m.q[k], m.sigma_q[k]);
        assert!((m.u[k] - u0).abs() < 5.0 * m.sigma_u[k], "bin {k}: U {} +- {} vs {u0}", m.u[k], m.sigma_u[k]);
        sq += m.q[k];
        su += m.u[k];
        se += m.sigma_q[k];
    }
    let n = v.len() as f64;
    let se = se / n / n.sqrt();
    assert!((sq / n - q0).abs() < 4.0 * se && (su / n - u0).abs() < 4.0 * se, "mean Q {} U {} +- {se}", sq / n, su / n);
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

/// `instpol simulate SCENE --out OUT --json`, which must succeed: its JSON.
fn simulate_json(scene: &Path, out: &Path) -> serde_json::Value {
    let o = instpol().arg("simulate").arg(scene).arg("--out").arg(out).arg("--json").output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

fn strings(v: &serde_json::Value) -> Vec<String> {
    v.as_array().unwrap().iter().map(|v| v.as_str().unwrap().into()).collect()
}

/// `instpol reduce FRAMES --instrument INST --bin 8 --out MAP EXTRA...`: (exit code, stdout, stderr).
fn reduce_to(frames: &[String], inst: &Path, map: &Path, extra: &[&str]) -> (i32, String, String) {
    let mut a = vec!["reduce".to_string()];
    a.extend(frames.iter().cloned());
    a.extend(["--instrument", &s(inst), "--bin", "8", "--out", &s(map)].map(String::from));
    a.extend(extra.iter().map(|x| x.to_string()));
    common::run(&a)
}

/// FORS2 (shrunk): `simulate` writes each exposure as the two raw chip files the archive
/// delivers (EXTNAME, 5 prescan and 5 overscan rows on a bias level, ESO keywords), and
/// `reduce` takes them as written (overscan subtracted) to the scene's sky.
#[test]
fn fors2_scene_is_written_as_raw_chip_files_that_reduce_to_its_sky() {
    let dir = tempfile::tempdir().unwrap();
    let (inst, scene) = chip_scene(dir.path(), &common::raw::fors2_tiny_text(), "v_HIGH");
    let out = dir.path().join("f");
    let j = simulate_json(&scene, &out);
    let files = strings(&j["outputs"]);
    assert_eq!(files.len(), 8, "{files:?}");
    assert!(j.get("bias_outputs").is_none(), "FORS2's overscan removes its bias: no bias frames");
    // Each chip file as the archive's, read here with fitsio: 64 x (32 + 5 + 5) px, its chip
    // named in EXTNAME, the scan rows at the default 200 ADU pedestal (read noise 3 e-).
    for (i, f) in files.iter().enumerate() {
        let chip = if i % 2 == 0 { "CHIP1" } else { "CHIP2" };
        assert!(f.ends_with(&format!("_{chip}.fits")), "{f}");
        let mut fits = fitsio::FitsFile::open(f).unwrap();
        let h = fits.primary_hdu().unwrap();
        assert_eq!(h.read_key::<String>(&mut fits, "EXTNAME").unwrap(), chip);
        assert_eq!(h.read_key::<i64>(&mut fits, "HIERARCH ESO DET OUT1 PRSCY").unwrap(), 5);
        assert_eq!(h.read_key::<i64>(&mut fits, "HIERARCH ESO DET WIN1 BINX").unwrap(), 2);
        assert_eq!(h.read_key::<i64>(&mut fits, "HIERARCH ESO DET EXP NO").unwrap(), 1 + i as i64 / 2);
        let px: Vec<f64> = h.read_image(&mut fits).unwrap();
        assert_eq!(px.len(), 64 * 42);
        let scan: Vec<f64> = px[..64 * 5].iter().chain(&px[64 * 37..]).copied().collect();
        let mean = scan.iter().sum::<f64>() / scan.len() as f64;
        assert!((mean - 200.0).abs() < 0.5, "{f}: scan rows at {mean} ADU");
    }
    let (code, _, err) = reduce_to(&files, &inst, &dir.path().join("map.fits"), &[]);
    assert_eq!(code, 0, "{err}");
    assert_scene_sky(&dir.path().join("map.fits"));
}

/// EFOSC2 (shrunk): its over-scan cannot be used, so `simulate` also writes bias frames (in
/// `bias/`, apart from the science frames); the frames are refused without a master bias and
/// reduce to the scene's sky with the one `master-bias` makes of them.
#[test]
fn efosc2_scene_comes_with_bias_frames_for_its_master_bias() {
    let dir = tempfile::tempdir().unwrap();
    let (inst, scene) = chip_scene(dir.path(), &common::raw::efosc2_tiny_text(), "V");
    let out = dir.path().join("e");
    let j = simulate_json(&scene, &out);
    let bias = strings(&j["bias_outputs"]);
    assert_eq!(bias.len(), 5);
    assert!(bias.iter().all(|b| Path::new(b).parent().unwrap() == out.join("bias")), "{bias:?}");
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("truth.json")).unwrap()).unwrap();
    assert_eq!(truth["frames"][2]["chip_files"][0], "frame_02_hwp045.0_CCD40.fits");
    assert_eq!(truth["bias_frames"].as_array().unwrap().len(), 5);
    let ip = s(&inst);
    let frames: Vec<String> =
        common::listing(&out).iter().filter(|f| f.ends_with(".fits")).map(|f| s(&out.join(f))).collect();
    let reduce = |extra: &[&str]| reduce_to(&frames, &inst, &dir.path().join("map.fits"), extra);
    let (code, _, err) = reduce(&[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("still carries its bias level") && err.contains("--bias"), "{err}");
    let mb = s(&dir.path().join("mb.fits"));
    let mut a = vec!["master-bias".to_string()];
    a.extend(bias);
    a.extend(["--instrument", &ip, "--out", &mb].map(String::from));
    let (code, _, err) = common::run(&a);
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = reduce(&["--bias", &mb]);
    assert_eq!(code, 0, "{err}");
    assert_scene_sky(&dir.path().join("map.fits"));
}

/// `--assembled`: the exposures as another pipeline delivers them (each chip's prescan and
/// overscan mean subtracted, trimmed and placed in the detector frame, the chip gap NaN; made
/// here from the raw files read with fitsio) reduce to the raw files' map, bin by bin within a
/// twentieth of its errors (the bias levels differ by the raw path's clipping); without the
/// flag they are refused with a hint that names it.
#[test]
fn assembled_frames_reduce_to_the_raw_files_map() {
    let dir = tempfile::tempdir().unwrap();
    let (inst, scene) = chip_scene(dir.path(), &common::raw::fors2_tiny_text(), "v_HIGH");
    let out = dir.path().join("f");
    let j = simulate_json(&scene, &out);
    let files = strings(&j["outputs"]);
    // Chip geometry of the shrunk FORS2: 64 x 32 px chips with 5 scan rows below and above,
    // CHIP1 at detector row 36, CHIP2 at row 0, the gap rows 32..36 between them.
    let adir = dir.path().join("assembled");
    std::fs::create_dir_all(&adir).unwrap();
    let mut assembled = Vec::new();
    for (k, pair) in files.chunks(2).enumerate() {
        let mut det = vec![f64::NAN; 64 * 68];
        let mut keys = Vec::new();
        for (f, y0) in pair.iter().zip([36usize, 0]) {
            let mut fits = fitsio::FitsFile::open(f).unwrap();
            let h = fits.primary_hdu().unwrap();
            let px: Vec<f64> = h.read_image(&mut fits).unwrap();
            let scan: Vec<f64> = px[..64 * 5].iter().chain(&px[64 * 37..]).copied().collect();
            let level = scan.iter().sum::<f64>() / scan.len() as f64;
            for y in 0..32 {
                for x in 0..64 {
                    det[(y0 + y) * 64 + x] = px[(5 + y) * 64 + x] - level;
                }
            }
            if keys.is_empty() {
                let hwp: f64 = h.read_key(&mut fits, "HIERARCH ESO INS RETA2 POSANG").unwrap();
                let filt: String = h.read_key(&mut fits, "HIERARCH ESO INS FILT1 NAME").unwrap();
                let exptime: f64 = h.read_key(&mut fits, "EXPTIME").unwrap();
                keys = vec![
                    ("HIERARCH ESO INS RETA2 POSANG".to_string(), skyfield::fits::KeyValue::F64(hwp), String::new()),
                    ("HIERARCH ESO INS FILT1 NAME".to_string(), skyfield::fits::KeyValue::Str(filt), String::new()),
                    ("EXPTIME".to_string(), skyfield::fits::KeyValue::F64(exptime), String::new()),
                ];
            }
        }
        let p = adir.join(format!("a{k}.fits"));
        skyfield::fits::write_frame(&p, 64, 68, &det, skyfield::fits::Bitpix::F32, &keys).unwrap();
        assembled.push(s(&p));
    }
    let reduce = |frames: &[String], extra: &[&str], map: &str| reduce_to(frames, &inst, &dir.path().join(map), extra);
    let (code, _, err) = reduce(&assembled, &[], "refused.fits");
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("a0.fits") && err.contains("64 x 68 px") && err.contains("--assembled"), "{err}");
    let (code, _, err) = reduce(&files, &[], "raw.fits");
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = reduce(&assembled, &["--assembled"], "assembled.fits");
    assert_eq!(code, 0, "{err}");
    let raw = skyfield::StokesMap::read_fits(&dir.path().join("raw.fits")).unwrap();
    let asm = skyfield::StokesMap::read_fits(&dir.path().join("assembled.fits")).unwrap();
    assert_eq!(raw.valid, asm.valid);
    let n = (0..raw.q.len()).filter(|&k| raw.valid[k]).count();
    assert!(n >= 10, "{n} valid bins");
    for k in (0..raw.q.len()).filter(|&k| raw.valid[k]) {
        assert!((raw.q[k] - asm.q[k]).abs() < 0.05 * raw.sigma_q[k], "bin {k}: Q {} vs {}", raw.q[k], asm.q[k]);
        assert!((raw.u[k] - asm.u[k]).abs() < 0.05 * raw.sigma_u[k], "bin {k}: U {} vs {}", raw.u[k], asm.u[k]);
    }
    assert_scene_sky(&dir.path().join("assembled.fits"));
}

/// An instrumental field more than fully polarized somewhere on the detector is refused
/// (exit 2) naming its key and the first place found, as the sky's p above 1 is; it was
/// simulated. The radial pattern `p = 12 r^2` (1200 % per arcmin^2) on the tiny 128 px
/// detector stays below 1 on the axes (r = 0.212 arcmin: 0.54) and passes it only towards the
/// corners (r = 0.299: 1.075): the named p is the closed form at the named position, and above
/// 1. The same pattern at 1000 % (0.90 at the corners) is simulated.
#[test]
fn an_instrumental_field_above_full_polarization_is_refused_naming_where() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny_instrument(dir.path());
    let scene = |c: f64| {
        let p = dir.path().join(format!("s{c}.toml"));
        std::fs::write(
            &p,
            format!(
                "instrument = \"{}\"\nfilter = \"V\"\n[sky]\nbrightness_e = 3000\n[effects.instpol]\nkind = \"radial\"\n\
                 coeffs_percent = [0, 0, {c}]\n",
                inst.display()
            ),
        )
        .unwrap();
        p
    };
    let out = dir.path().join("out");
    let o = instpol().arg("simulate").arg(scene(1200.0)).arg("--out").arg(&out).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("effects.instpol.coeffs_percent") && err.contains("more than fully polarized"), "{err}");
    let num = |after: &str| -> Vec<f64> {
        let rest = &err[err.find(after).unwrap() + after.len()..];
        rest.split(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-'))
            .filter(|t| !t.is_empty())
            .take(3)
            .map(|t| t.parse().unwrap())
            .collect()
    };
    let v = num("polarization degree is ");
    let (p, x, y) = (v[0], v[1], v[2]);
    assert!(p > 1.0 && (p - 12.0 * (x * x + y * y)).abs() < 0.01, "{err}");
    assert!(!out.exists() || common::fits_in(&out).is_empty(), "frames written");
    let o = instpol().arg("simulate").arg(scene(1000.0)).arg("--out").arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}
