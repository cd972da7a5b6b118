//! Outputs are written through a temporary file and a rename; they must still get the
//! permissions of an ordinary new file (tempfile's own are private, 0o600), so that shared
//! calibration files and frames are readable by the group as the user's umask intends.

#![cfg(unix)]

use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::process::Command;

fn mode(p: &Path) -> u32 {
    std::fs::metadata(p).unwrap().permissions().mode() & 0o777
}

#[test]
fn outputs_have_the_mode_of_an_ordinary_new_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // The reference: what this process's umask gives a plain new file here.
    let plain = d.join("plain");
    std::fs::File::create(&plain).unwrap();
    let want = mode(&plain);

    let bin = env!("CARGO_BIN_EXE_instpol");
    let o = Command::new(bin).args(["demo", "--no-frames", "--json", "--out"]).arg(d.join("demo")).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let scene = d.join("scene.toml");
    std::fs::write(
        &scene,
        include_str!("../../../../instruments/fors1.toml")
            .replace("nx = 2048", "nx = 64")
            .replace("ny = 2048", "ny = 64")
            .replace("throw_arcsec = 22.0", "throw_arcsec = 2.0")
            .replace("strip_count = 9", "strip_count = 2")
            .replace("first_strip_y_px = 34", "first_strip_y_px = 4"),
    )
    .unwrap();
    let inst = d.join("mini.toml");
    std::fs::rename(&scene, &inst).unwrap();
    std::fs::write(
        &scene,
        format!("instrument = \"{}\"\nfilter = \"V\"\nseed = 1\n[sky]\nbrightness_e = 100\n", inst.display()),
    )
    .unwrap();
    let o = Command::new(bin).arg("simulate").arg(&scene).arg("--out").arg(d.join("sim")).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let cat = d.join("cat.csv");
    std::fs::write(&cat, "x,y,q,u,sigma_q,sigma_u\n0.5,0.5,0.01,0.0,0.001,0.001\n").unwrap();
    let o = Command::new(bin)
        .args(["correct", "--cal"])
        .arg(d.join("demo/cal_V.fits"))
        .arg("--in")
        .arg(&cat)
        .arg("--out")
        .arg(d.join("out.csv"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let mut checked = 0;
    for sub in ["demo", "sim", "."] {
        for e in std::fs::read_dir(d.join(sub)).unwrap() {
            let p = e.unwrap().path();
            if p.is_file() {
                assert_eq!(mode(&p), want, "{} has mode {:o}, an ordinary new file {:o}", p.display(), mode(&p), want);
                checked += 1;
            }
        }
    }
    // Calibration files, plots, frames, the truth file, the corrected catalog.
    assert!(checked > 10, "{checked}");
}
