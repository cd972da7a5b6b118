//! Archive nights for a FORS2 shrunk to 160 x 216 px (instruments/tiny_fors2.toml), written by
//! the library's `sim::night` (archive-like file names and ESO DPR keywords through the scene's
//! `[output]`), for the night tests (night.rs), the report test (report.rs) and the
//! hostile-input generator (its `scan`, `run` and `trend` invocations).

use std::path::{Path, PathBuf};

/// One observation block of a night (`sim::night::Block`).
pub use sim::night::Block as Spec;

/// The shrunk FORS2's instrument file.
pub fn tiny_fors2() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/tiny_fors2.toml")
}

/// `s` through the instrument file `instrument`, its field's radial pattern (percent), and
/// `extra` scene text (a `[telescope]` section) at the end: `root/<dir>.toml` and
/// `root/raw/<dir>/`.
pub fn simulate_scene(root: &Path, s: &Spec, instrument: &Path, pattern: [f64; 4], extra: &str) {
    if let Err(e) = s.simulate(root, instrument, pattern, extra) {
        panic!("simulate {}: {e}", s.dir);
    }
}
