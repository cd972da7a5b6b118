//! Where the real data of `../shared/data` are, for every integration test that reads them (the
//! `fit` and `instpol` crates' tests include this one file): the one decision of what happens
//! when they are absent. On a developer's machine without `../shared` the test says SKIPPED on
//! stderr and returns; under `INSTPOL_REQUIRE_DATA=1` (set by `.ci/run`, where `../shared` is
//! always beside the clone) an absent file fails the test, naming the path, as
//! `INSTPOL_REQUIRE_B3` does for the second BLAKE3 implementation.

use std::path::PathBuf;

/// `../shared/data/<rel>` (beside the repository), if every one of `needed` (paths inside it)
/// is a file; otherwise `None` after a loud SKIPPED naming `what` did not run, or a panic when
/// the data are required.
pub fn shared_data(rel: &str, needed: &[&str], what: &str) -> Option<PathBuf> {
    let required = std::env::var_os("INSTPOL_REQUIRE_DATA").is_some_and(|v| v != "0");
    locate(rel, needed, what, required)
}

fn locate(rel: &str, needed: &[&str], what: &str, required: bool) -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data").join(rel);
    let missing: Vec<PathBuf> = needed.iter().map(|f| dir.join(f)).filter(|p| !p.is_file()).collect();
    let missing = if dir.is_dir() { missing } else { vec![dir.clone()] };
    if missing.is_empty() {
        return Some(dir);
    }
    let names: Vec<String> = missing.iter().map(|p| p.display().to_string()).collect();
    if required {
        panic!("INSTPOL_REQUIRE_DATA is set and the real data are missing: {} ({what})", names.join(", "));
    }
    eprintln!("\n*** SKIPPED: {} not found: {what} did not run ***\n", names.join(", "));
    None
}

#[test]
#[should_panic(expected = "real data are missing")]
fn absent_data_fail_when_required() {
    locate("no-such-folder", &[], "this check", true);
}

#[test]
fn absent_data_are_skipped_when_not_required() {
    assert_eq!(locate("no-such-folder", &[], "this check", false), None);
}
