//! From a folder of raw frames to products: sort a night's files by their headers
//! ([`mod@scan`]), plan the units of work that make masters, maps, catalogs, calibrations and zero
//! angles from them ([`plan`]), and run the plan in dependency order, idempotently, any number
//! of units at once or one unit at a time for a cluster's job array ([`run`]); and over many
//! nights, the standards' zero angle and instrumental polarization against date, with the
//! steps that stand out of their errors ([`trend`]); and what a report of nights shows, gathered
//! from the plans, the run's records and the products ([`report`], printed by `instpol report`).
//!
//! `instpol scan` / `instpol run` and Python's `instpol.scan` / `instpol.run` are faces over
//! [`scan::scan`] and [`run::run`]; docs/nights.md gives the Slurm and GNU parallel recipes.

pub mod call;
pub mod header;
pub mod plan;
pub mod report;
pub mod run;
pub mod scan;
pub mod trend;

pub use call::library_executor;
pub use plan::{LeftOut, Plan, Unit};
pub use run::{process_executor, Outcome, Report, RunOptions, Status};
pub use scan::{scan, ScanOptions, SkyField};

use std::path::{Path, PathBuf};

/// Errors of scanning and running; each names the file, unit or option at fault.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("{path}: {why}")]
    Input { path: PathBuf, why: String },
    #[error("cannot write {path}: {why}")]
    Output { path: PathBuf, why: String },
    #[error("{0}")]
    Instrument(String),
    #[error("{0}")]
    Option(String),
    #[error("plan {path}: {why}")]
    Plan { path: PathBuf, why: String },
    #[error("unit {id}: {why}")]
    Unit { id: String, why: String },
}

/// Write `bytes` to `path` through a temporary file in the same folder and a rename, so that
/// `path` holds either its old content or all of the new.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), Error> {
    write_atomic_tagged(path, None, bytes)
}

/// [`write_atomic`] through a temporary tagged `tag` (`skyfield::fits::temp_prefix`).
pub(crate) fn write_atomic_tagged(path: &Path, tag: Option<&str>, bytes: &[u8]) -> Result<(), Error> {
    use std::io::Write;
    let err = |e: std::io::Error| Error::Output { path: path.into(), why: e.to_string() };
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(err)?;
    // The workspace's one durable writer (skyfield::durable): a temporary beside the file,
    // fsynced, then renamed; on error the temporary is deleted.
    let mut tmp = skyfield::fits::temp_beside_tagged(path, tag, ".tmp").map_err(err)?;
    tmp.write_all(bytes).and_then(|_| tmp.flush()).map_err(err)?;
    skyfield::durable::finish(tmp.into_temp_path(), path).map_err(err)
}
