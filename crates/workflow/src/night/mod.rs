//! From a folder of raw frames to products: sort a night's files by their headers
//! ([`mod@scan`]), plan the units of work that make masters, maps, catalogs, calibrations and zero
//! angles from them ([`plan`]), and run the plan in dependency order, idempotently, any number
//! of units at once or one unit at a time for a cluster's job array ([`run`]); and over many
//! nights, the standards' zero angle and instrumental polarization against date, with the
//! steps that stand out of their errors ([`trend`]).
//!
//! `instpol scan` / `instpol run` and Python's `instpol.scan` / `instpol.run` are faces over
//! [`scan::scan`] and [`run::run`]; docs/nights.md gives the Slurm and GNU parallel recipes.

pub mod header;
pub mod plan;
pub mod run;
pub mod scan;
pub mod trend;

pub use plan::{LeftOut, Plan, Unit};
pub use run::{process_executor, Outcome, Report, RunOptions, Status};
pub use scan::{scan, ScanOptions, SkyField};

use std::path::PathBuf;

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
