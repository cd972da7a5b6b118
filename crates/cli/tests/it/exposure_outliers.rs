//! `instpol photometry` on frames with repeated HWP positions: the frames of
//! a position are summed for the Stokes reduction, and every exposure is also measured on its
//! own and checked against the others. The shipped maskless scene is simulated as two cycles of
//! four HWP angles (two runs), and the second cycle once more with every star's and the sky's
//! light times 0.8: one frame of the second cycle swapped for its dimmed twin is an exposure
//! whose transparency dropped by 20 % (star and sky alike, the exposure time in the header
//! unchanged as through a cloud). It must be the one exposure flagged, with its transparency
//! 0.8; the star's q, u stay right (a change common to both beams cancels in F).

use crate::common;

use common::{fits_in, run};
use std::ffi::OsString;
use std::path::{Path, PathBuf};

/// One cycle of the four HWP angles of the shipped scene (the simulator takes each plate
/// position once; the second cycle is a second run with another seed).
fn simulate(dir: &Path, inst: &Path, light: f64, seed: u64, tag: &str) -> Vec<PathBuf> {
    let mut scene = include_str!("../../../../instruments/scenes/calcite_stars.toml")
        .replace("instrument = \"calcite\"", &format!("instrument = \"{}\"", inst.display()))
        .replace("hwp_angles_deg = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]", "hwp_angles_deg = [0, 22.5, 45, 67.5]")
        .replace(
            "frame_shifts_px = [[0, 0], [1.3, -0.7], [2.6, 0.4], [-1.2, 2.9], [0.5, -2.2], [-2.8, -1.1], [3.0, 1.7], [-0.4, 0.9]]",
            "frame_shifts_px = [[0, 0], [1.3, -0.7], [2.6, 0.4], [-1.2, 2.9]]",
        )
        .replace("seed = 7", &format!("seed = {seed}"));
    // The light of every star and of the sky times `light` (the scene's fluxes are per frame).
    for (key, v) in [("flux_e = 4e5", 4e5), ("flux_e = 2e5", 2e5), ("flux_e = 1e5", 1e5), ("brightness_e = 300", 300.0)]
    {
        assert_eq!(scene.matches(key).count(), 1, "the shipped scene changed: {key}");
        let name = key.split(" = ").next().unwrap();
        scene = scene.replace(key, &format!("{name} = {}", v * light));
    }
    assert!(scene.contains("[0, 22.5, 45, 67.5]\n") && scene.contains("[-1.2, 2.9]]"), "the shipped scene changed");
    let sp = dir.join(format!("scene_{tag}.toml"));
    std::fs::write(&sp, scene).unwrap();
    let out = dir.join(tag);
    let (code, _, err) = run(&["simulate".as_ref(), sp.as_os_str(), "--out".as_ref(), out.as_os_str()]);
    assert_eq!(code, 0, "{err}");
    let f = fits_in(&out);
    assert_eq!(f.len(), 4, "{f:?}");
    f
}

fn photometry(inst: &Path, frames: &[PathBuf]) -> (serde_json::Value, String) {
    let mut args: Vec<OsString> = vec!["photometry".into()];
    args.extend(frames.iter().map(|f| f.clone().into_os_string()));
    for a in ["--instrument", inst.to_str().unwrap(), "--x", "150", "--y", "200", "--aperture", "9"] {
        args.push(a.into());
    }
    for a in ["--annulus", "14,24", "--json"] {
        args.push(a.into());
    }
    let (code, stdout, err) = run(&args);
    assert_eq!(code, 0, "{err}");
    (serde_json::from_str(&stdout).unwrap(), err)
}

/// The instrument (HWP angle from the header), two clear cycles of the four angles (eight
/// exposures), and the second cycle again through a cloud (light times 0.8).
fn two_cycles_and_a_cloud(dir: &Path) -> (PathBuf, Vec<PathBuf>, Vec<PathBuf>) {
    let text = include_str!("../../../../instruments/calcite.toml")
        .replace("hwp_angle_keyword = \"\"", "hwp_angle_keyword = \"HWPANG\"");
    let inst = dir.join("calcite.toml");
    std::fs::write(&inst, &text).unwrap();
    let first = simulate(dir, &inst, 1.0, 7, "first");
    let second = simulate(dir, &inst, 1.0, 8, "second");
    let cloudy = simulate(dir, &inst, 0.8, 8, "cloudy");
    (inst, first.iter().chain(&second).cloned().collect(), cloudy)
}

#[test]
fn a_frame_with_a_20_percent_transparency_drop_is_flagged() {
    let dir = tempfile::tempdir().unwrap();
    let (inst, clear, cloudy) = two_cycles_and_a_cloud(dir.path());

    // All clear: every exposure measured, none flagged, transparencies near 1.
    let (j, _) = photometry(&inst, &clear);
    let ex = j["exposures"].as_array().unwrap_or_else(|| panic!("no exposures: {j}"));
    assert_eq!(ex.len(), 8);
    assert_eq!(j["n_outlier_exposures"], 0, "{j}");
    for e in ex {
        assert!((e["transparency"].as_f64().unwrap() - 1.0).abs() < 0.02, "{e}");
    }
    assert_eq!(j["hwp_deg"].as_array().unwrap().len(), 4, "repeats summed into four positions");

    // Exposure 6 (the second 22.5 deg frame) through a cloud.
    let mut frames = clear.clone();
    frames[5] = cloudy[1].clone();
    let (j, err) = photometry(&inst, &frames);
    let ex = j["exposures"].as_array().unwrap();
    let flagged: Vec<&serde_json::Value> = ex.iter().filter(|e| e["outlier"].as_bool().unwrap()).collect();
    assert_eq!(flagged.len(), 1, "{j}");
    assert_eq!(j["n_outlier_exposures"], 1);
    let e = flagged[0];
    assert_eq!(e["file"].as_str().unwrap(), frames[5].display().to_string());
    let (t, st) = (e["transparency"].as_f64().unwrap(), e["sigma_transparency"].as_f64().unwrap());
    assert!((t - 0.8).abs() < 0.01 + 4.0 * st, "transparency {t} +- {st}");
    assert!(e["why"].as_str().unwrap().contains("80 %"), "{e}");
    // F cancels the common drop: its pull about the repeat is ordinary.
    assert!(e["pull"].as_f64().unwrap().abs() < 4.0, "{e}");
    assert!(err.contains("warning") && err.contains(&frames[5].display().to_string()), "{err}");
    // q, u of the 5.72 % star at 136 deg still within 4 sigma.
    let (p, chi) = (0.0572f64, 136.0f64.to_radians());
    let f = |k: &str| j[k].as_f64().unwrap();
    assert!(((f("q") - p * (2.0 * chi).cos()) / f("sigma_q")).abs() < 4.0, "{j}");
    assert!(((f("u") - p * (2.0 * chi).sin()) / f("sigma_u")).abs() < 4.0, "{j}");
}

/// `instpol catalog` on the same frames (its per-exposure checks): every
/// star is measured in each exposure alone; with the clear set no exposure is flagged, with
/// exposure 6 through the cloud every star flags it (and only it: the row's flag bit and
/// `outlier_exposures` = [5]), and the catalog names it with its stars' median light 0.8.
#[test]
fn catalog_flags_the_dimmed_exposure_for_every_star() {
    let dir = tempfile::tempdir().unwrap();
    let (inst, clear, cloudy) = two_cycles_and_a_cloud(dir.path());
    let catalog = |frames: &[PathBuf], out: &Path| {
        let mut args: Vec<OsString> = vec!["catalog".into()];
        args.extend(frames.iter().map(|f| f.clone().into_os_string()));
        for a in ["--instrument", inst.to_str().unwrap(), "--fwhm", "4.7", "--aperture", "9", "--annulus", "14,24"] {
            args.push(a.into());
        }
        args.extend(["--out".into(), out.as_os_str().to_owned(), "--json".into()]);
        let (code, stdout, err) = run(&args);
        assert_eq!(code, 0, "{err}");
        (serde_json::from_str::<serde_json::Value>(&stdout).unwrap(), err)
    };

    let (j, _) = catalog(&clear, &dir.path().join("clear.csv"));
    let ex = j["exposures"].as_array().unwrap_or_else(|| panic!("no exposures: {j}"));
    assert_eq!(ex.len(), 8);
    let rows = j["rows"].as_array().unwrap();
    let measured: Vec<&serde_json::Value> = rows.iter().filter(|r| r["q"].is_number()).collect();
    assert_eq!(measured.len(), 3, "the scene's three stars: {j}");
    for e in ex {
        assert_eq!(e["n_stars"], 3, "{e}");
        assert_eq!(e["n_stars_flagged"], 0, "{e}");
        assert!((e["median_transparency"].as_f64().unwrap() - 1.0).abs() < 0.02, "{e}");
    }
    assert!(measured.iter().all(|r| r["outlier_exposures"].as_array().unwrap().is_empty()
        && r["flags"].as_u64().unwrap() & skyfield::catalog::flags::OUTLIER_EXPOSURE as u64 == 0));

    let mut frames = clear.clone();
    frames[5] = cloudy[1].clone();
    let out = dir.path().join("cloudy.csv");
    let (j, err) = catalog(&frames, &out);
    let ex = j["exposures"].as_array().unwrap();
    for (i, e) in ex.iter().enumerate() {
        assert_eq!(e["outlier"].as_bool().unwrap(), i == 5, "{e}");
        assert_eq!(e["n_stars_flagged"], if i == 5 { 3 } else { 0 }, "{e}");
    }
    let t = ex[5]["median_transparency"].as_f64().unwrap();
    assert!((t - 0.8).abs() < 0.02, "median transparency {t}");
    assert_eq!(ex[5]["file"].as_str().unwrap(), frames[5].display().to_string());
    for r in j["rows"].as_array().unwrap().iter().filter(|r| r["q"].is_number()) {
        assert_eq!(r["outlier_exposures"], serde_json::json!([5]), "{r}");
        assert!(r["flags"].as_u64().unwrap() & skyfield::catalog::flags::OUTLIER_EXPOSURE as u64 != 0, "{r}");
    }
    assert!(err.contains("warning") && err.contains(&frames[5].display().to_string()), "{err}");
    // The table carries the flag and the exposures' indices.
    // The lines after the `#` lines that say what the catalog is.
    let text = std::fs::read_to_string(&out).unwrap();
    let csv: String = text.lines().filter(|l| !l.starts_with('#')).map(|l| format!("{l}\n")).collect();
    let head: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let col = |n: &str| head.iter().position(|h| *h == n).unwrap_or_else(|| panic!("no column {n}: {head:?}"));
    let (cf, cn, ci) = (col("flags"), col("n_outlier_exposures"), col("outlier_exposures"));
    let mut flagged = 0;
    for line in csv.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        if f[cf].contains("outlier_exposure") {
            assert_eq!((f[cn], f[ci]), ("1", "5"), "{line}");
            flagged += 1;
        }
    }
    assert_eq!(flagged, 3, "{csv}");
}
