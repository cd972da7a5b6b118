//! `instpol simulate` end to end on a small instrument.

mod common;

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
