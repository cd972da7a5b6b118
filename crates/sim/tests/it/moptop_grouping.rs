//! The built-in MOPTOP's camera files grouped into exposures by their headers (MOPRNUM and
//! MOPRPOS, the camera by MOPCNUM), whatever order they are given in: MOPTOP shrunk to two
//! 80 x 80 px cameras, two turns of 16 rotor positions simulated, read in the simulator's order,
//! every camera-1 file before every camera-2 file (as a shell glob of the archive's names gives
//! them) and backwards. Each read gives the simulator's exposures: its plate ranges and its
//! pixels. A file without its partner camera, or given twice, is refused naming it; a master
//! bias or flat for these level-1 frames (declared corrected already) is refused unless asked.

use skyfield::calib::{read_exposures, Grouping, ReadOptions};
use std::path::{Path, PathBuf};

/// The built-in file with its cameras shrunk to 80 x 80 px (the field with them); every other
/// line as built in. `transform`: the simulating file's camera transform line, if any.
fn small_moptop(transform: &str) -> String {
    let text = include_str!("../../../../instruments/moptop.toml");
    let out = text
        .replacen("nx = 2048 ", "nx = 160 ", 1)
        .replacen("ny = 1024 ", "ny = 80 ", 1)
        .replace("size_px = [1024, 1024]", "size_px = [80, 80]")
        .replace("origin_px = [1024, 0]", "origin_px = [80, 0]")
        .replace("width_arcmin = 7.1 ", "width_arcmin = 0.5547 ")
        .replace("height_arcmin = 7.1 ", "height_arcmin = 0.5547 ")
        .replace("max_residual_px = 0.5", &format!("{transform}max_residual_px = 0.5"));
    assert_ne!(out, text);
    out
}

/// The plate's middle angle (deg) of exposure `k`: two turns of 16 positions of 22.5 deg, each
/// exposure sweeping 18.2 deg about its position's middle.
fn middle_deg(k: usize) -> f64 {
    11.25 + 22.5 * (k % 16) as f64
}

fn simulate(dir: &Path) -> (Vec<PathBuf>, instrument::Instrument) {
    let sim_inst = dir.join("moptop_sim.toml");
    std::fs::write(&sim_inst, small_moptop("transform = [1.0, 0.0, 1.5, 0.0, 1.0, -2.0]\n")).unwrap();
    let angles: Vec<String> = (0..32).map(|k| middle_deg(k).to_string()).collect();
    let scene = format!(
        "instrument = \"{}\"\nfilter = \"R\"\nseed = 11\nhwp_angles_deg = [{}]\nhwp_motion = {{ sweep_deg = 18.2 }}\n\
         [output]\nbitpix = -32\n[sky]\nbrightness_e = 100\np = 0.02\nchi_deg = 30\n[effects]\nphoton_noise = true\n\
         [[stars]]\nx = 30.0\ny = 40.0\ncoords = \"pixel\"\nflux_e = 1e5\np = 0.03\nchi_deg = 70\nfwhm_arcsec = 1.2\n",
        sim_inst.display(),
        angles.join(", ")
    );
    let sc = sim::Scene::from_toml_str(&scene, &dir.join("scene.toml")).unwrap();
    let files = sim::simulate(&sc, &dir.join("frames"), &|| {}).unwrap().frames;
    let read = dir.join("moptop_small.toml");
    std::fs::write(&read, small_moptop("")).unwrap();
    (files, instrument::Instrument::load(read.to_str().unwrap()).unwrap())
}

fn read(files: &[PathBuf], inst: &instrument::Instrument) -> Result<Vec<skyfield::frame::Frame>, String> {
    read_exposures(files, inst, &ReadOptions::default()).map_err(|e| e.to_string())
}

/// Read in the simulator's order, camera 1's files first and backwards: the same 32 exposures
/// each time, with the simulator's plate ranges (middle, 18.2 deg sweep), and the same pixels.
#[test]
fn camera_files_are_grouped_by_their_exposure_keywords_in_any_order() {
    let dir = tempfile::tempdir().unwrap();
    let (files, inst) = simulate(dir.path());
    assert_eq!(files.len(), 64);
    assert!(!dir.path().join("frames/bias").exists(), "level-1 frames need no bias frames");
    let given = read(&files, &inst).unwrap();
    assert_eq!(given.len(), 32);
    for (k, f) in given.iter().enumerate() {
        assert!(
            (f.hwp_deg - middle_deg(k)).abs() < 1e-9 && (f.hwp_sweep_deg - 18.2).abs() < 1e-9,
            "{k}: {} +- {}",
            f.hwp_deg,
            f.hwp_sweep_deg
        );
        assert_eq!(f.chips.len(), 2);
    }
    let (cam1, cam2): (Vec<PathBuf>, Vec<PathBuf>) =
        files.iter().cloned().partition(|p| p.to_string_lossy().ends_with("_CAM1.fits"));
    let glob: Vec<PathBuf> = cam1.into_iter().chain(cam2).collect();
    let backwards: Vec<PathBuf> = files.iter().rev().cloned().collect();
    for (name, order) in [("camera 1 first", glob), ("backwards", backwards)] {
        let frames = read(&order, &inst).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(frames.len(), 32, "{name}");
        for f in &frames {
            let g = given.iter().find(|g| g.path == f.path).unwrap_or_else(|| panic!("{name}: {}", f.path.display()));
            assert_eq!((f.hwp_deg, f.hwp_sweep_deg), (g.hwp_deg, g.hwp_sweep_deg), "{name}");
            let same = f.data.iter().zip(&g.data).all(|(a, b)| a == b || (a.is_nan() && b.is_nan()));
            assert!(same, "{name}: {} read other pixels", f.path.display());
        }
    }
    let g = Grouping::of(&inst, &ReadOptions::default(), 64, 32).unwrap();
    assert_eq!(g.exposure_keywords, ["MOPRNUM", "MOPRPOS"]);
    assert_eq!(g.chip_keyword, "MOPCNUM");
    assert_eq!(g.describe(), "64 chip files grouped into 32 exposures by MOPRNUM, MOPRPOS (chip by MOPCNUM)");
}

/// A camera-1 file whose camera-2 partner is not given, and a file given twice, are refused
/// naming the file; a master bias or flat for frames declared corrected already is refused
/// naming the declaration, and taken when the caller asks for the correction again.
#[test]
fn ungroupable_files_and_second_corrections_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (files, inst) = simulate(dir.path());
    let lone = files.iter().position(|p| p.to_string_lossy().ends_with("_CAM2.fits")).unwrap();
    let mut short = files.clone();
    let partner = short.remove(lone);
    let e = read(&short, &inst).unwrap_err();
    let cam1 = partner.to_string_lossy().replace("_CAM2.fits", "_CAM1.fits");
    assert!(e.contains(&cam1) && e.contains("no file of chip CAM2") && e.contains("MOPRNUM"), "{e}");
    let mut twice = files.clone();
    twice.push(files[5].clone());
    let e = read(&twice, &inst).unwrap_err();
    assert!(e.contains(&*files[5].to_string_lossy()) && e.contains("again"), "{e}");
    let master = dir.path().join("no_such_master.fits");
    for (opts, what) in [
        (ReadOptions { bias: Some(master.clone()), ..Default::default() }, "bias"),
        (ReadOptions { flat: Some(master.clone()), ..Default::default() }, "flat"),
    ] {
        let e = read_exposures(&files, &inst, &opts).unwrap_err().to_string();
        assert!(e.contains(&format!("already {what} corrected")) && e.contains("--correct-again"), "{e}");
        let again = ReadOptions { correct_again: true, ..opts };
        let e = read_exposures(&files, &inst, &again).unwrap_err().to_string();
        assert!(!e.contains("already") && e.contains("no_such_master.fits"), "asked again: {e}");
    }
}
