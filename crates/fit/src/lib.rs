//! Fitted models of the instrumental polarization field and their use: radial polynomials with
//! an optional free optical-axis centre, the polar-angle test, the wavelength law, the
//! Delaunay-interpolated residual map (spade), the per-filter calibration file with its
//! metadata and refit policy ([`pipeline`]), the correction of measured Stokes parameters (one
//! row or a whole Stokes map) with error propagation ([`correct`]; a table's rows column by
//! column, [`columns`]), the validation of a
//! calibration on a standard star in frames ([`validate`]), the paper's own fields
//! ([`paper`]), the telescope term (a Nasmyth M3 model fitted to standard stars against the
//! parallactic angle, [`telescope`]) and the HWP zero angle from polarized standards
//! ([`zeroangle`]). The main job end to end, which also simulates, is one crate up
//! (`workflow::demo`).
//!
//! A model is a value that answers "what is the instrumental polarization here"
//! ([`model::FieldModel`], defined in the `field` crate with the field coordinates, so the
//! simulator evaluates the same values); fitters, the calibration file and the correction do not
//! care which model it is. Every nonlinear fit runs the one least-squares loop ([`lsq`]) under
//! its own named policy. This crate does not make Stokes maps from frames (that is
//! `skyfield`, which [`validate`] calls for the star's photometry), and it draws no plots and
//! parses no arguments (that is the CLI).

pub mod bins;
pub mod calfile;
pub mod calibration;
pub mod catalog_correct;
pub mod chain;
pub mod columns;
pub mod conditioning;
pub mod correlation;
pub mod efficiency;
pub mod import;
pub mod keys;
pub mod lsq;
pub mod model;
pub mod mueller_block;
pub mod mueller_cal;
pub mod mueller_explain;
pub mod mueller_field;
pub mod mueller_forms;
pub mod mueller_plan;
pub mod mueller_smooth;
pub mod mueller_stars;
pub mod paper;
pub mod pipeline;
pub mod polar;
pub mod poly;
pub mod radial;
pub mod region;
pub mod request;
pub mod residual;
pub mod response_cal;
pub mod setup;
pub mod stars_field;
pub mod synth;
pub mod telescope;
pub mod telescope_cal;
pub mod telescope_report;
pub mod validate;
pub mod validate_telescope;
pub mod wavelength;

/// The gridded map lives in the `field` crate (the simulator evaluates it too).
pub use field::grid as gridmap;

pub use bins::Bin;
pub use calfile::{Calibration, Model};
pub use model::{FieldModel, InstPol};
pub use poly::{fit_poly, PolyFit, PolyModel};
pub use radial::{fit_radial, CovarianceScaling, ErrorScaling, RadialFit, RadialFitOptions, RadialModel};
pub use region::{Exclusion, FieldRegion};

use std::path::PathBuf;

/// Errors of the field models and calibration files: each names the input at fault.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("too few usable bins for the fit: {used} of {total} bins are usable (valid, not excluded), need at least {needed}")]
    TooFewBins { used: usize, total: usize, needed: usize },
    #[error("degenerate fit: {0}")]
    Degenerate(String),
    /// The data leave a parameter free ([`conditioning::judge`]).
    #[error(transparent)]
    Undetermined(#[from] conditioning::Undetermined),
    #[error("fit failed: {0}")]
    FitFailed(String),
    #[error("bad exclusion region '{spec}': {why}")]
    BadExclusion { spec: String, why: String },
    #[error("bad input: {0}")]
    Input(String),
    #[error("{path}: calibration file format version {found} is newer than this instpol understands (up to {supported}); upgrade instpol to read it")]
    NewerFormat { path: PathBuf, found: i64, supported: i64 },
    #[error("{path}: {what}")]
    BadFile { path: PathBuf, what: String },
    #[error("{path}: FITS error while {doing}: {message}")]
    Fits { path: PathBuf, doing: String, message: String },
    /// (The I/O error is a field, not a `source`, so that error chains do not print it twice.)
    #[error("{path}: {err}")]
    Io { path: PathBuf, err: std::io::Error },
    /// A row of an input table, named by its file and row (`at`).
    #[error("{at}: {what}")]
    Row { at: String, what: String },
    /// A table or frame the `skyfield` readers refused (their errors name the file).
    #[error(transparent)]
    Frames(#[from] skyfield::Error),
}

pub type Result<T> = std::result::Result<T, Error>;
pub mod correct;
pub mod standards;
pub mod zeroangle;

/// The crate README's example, compiled and run with the documentation tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
