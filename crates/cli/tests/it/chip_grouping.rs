//! Chip files grouped into exposures by the instrument's exposure keywords, whatever order
//! they are given in: a shrunk FORS2's raw chip files (`common/raw.rs`, exposure numbers in
//! `HIERARCH ESO DET EXP NO`) reduced in exposure order, with two exposures' CHIP2 files
//! swapped, and with every CHIP1 file first (as a glob of names ending in the chip gives them):
//! the same map each time, the grouping reported, and the sky's known polarization measured.

use crate::common;

use common::raw::{fors2_tiny_text, write_raw_set, Q0, U0};
use common::run;
use std::path::PathBuf;

fn reduce(files: &[PathBuf], inst: &str, out: &std::path::Path) -> serde_json::Value {
    let mut args: Vec<String> = vec!["reduce".into()];
    args.extend(files.iter().map(|p| p.to_str().unwrap().to_string()));
    args.extend(["--instrument", inst, "--bin", "8", "--json", "--out", out.to_str().unwrap()].map(String::from));
    let (code, stdout, err) = run(&args);
    assert_eq!(code, 0, "{err}");
    serde_json::from_str(&stdout).unwrap()
}

#[test]
fn chip_files_in_any_order_reduce_to_the_same_map() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = dir.path().join("fors2_tiny.toml");
    std::fs::write(&inst_path, fors2_tiny_text()).unwrap();
    let set = write_raw_set(dir.path(), &common::raw::fors2_tiny());
    let inst = inst_path.to_str().unwrap();
    let given = reduce(&set.science, inst, &dir.path().join("given.fits"));
    let mut swapped = set.science.clone();
    swapped.swap(1, 3);
    let (chip1, chip2): (Vec<PathBuf>, Vec<PathBuf>) =
        set.science.iter().cloned().partition(|p| p.to_string_lossy().ends_with("_CHIP1.fits"));
    let chip_first: Vec<PathBuf> = chip1.into_iter().chain(chip2).collect();
    assert_ne!(chip_first, set.science);
    let g = &given["grouping"];
    assert_eq!((g["files"].as_u64(), g["exposures"].as_u64()), (Some(8), Some(4)), "{g}");
    assert_eq!(g["exposure_keywords"], serde_json::json!(["HIERARCH ESO DET EXP NO"]));
    // The sky's polarization as the frames were written (`common/raw.rs`), to its noise.
    let p = given["median_p"].as_f64().unwrap();
    assert!((p - Q0.hypot(U0)).abs() < 3.0 * given["median_sigma_q"].as_f64().unwrap(), "P {p}");
    for (name, files) in [("swapped", swapped), ("CHIP1 first", chip_first)] {
        let got = reduce(&files, inst, &dir.path().join(format!("{name}.fits")));
        for key in ["hwp_deg", "n_valid_bins", "median_p", "median_chi_deg", "median_sigma_q", "grouping"] {
            assert_eq!(got[key], given[key], "{name}: {key}");
        }
    }
}
