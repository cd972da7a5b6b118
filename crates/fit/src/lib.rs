//! Fitted models of the instrumental polarization and their use, one folder per part of the
//! instrument and one per step around them:
//!
//! - [`models`]: the field models and their fits (radial polynomials with an optional free
//!   optical-axis centre, 2-D polynomials, the polar-angle test, the wavelength law, the
//!   residual map, field stars, the paper's own fields) and the fit from binned measurements to
//!   a field calibration ([`models::pipeline`]);
//! - [`telescope`]: the telescope term, a Nasmyth M3 model fitted to standard stars against the
//!   parallactic angle, its calibration file and its validation;
//! - [`mueller_field`]: the instrument's Mueller field fitted to sky fields of known
//!   polarization, its calibration file, its causes and what a calibration costs;
//! - [`response`]: the instrument's constant response (efficiency, cross-talk) from standards
//!   and its calibration file;
//! - [`correction`]: what a caller asks of a calibration and the one chain that answers it, for
//!   a row, a table or a Stokes map, with the compatibility check of data and calibration;
//! - [`files`]: the field calibration file, the reading of any calibration file, the keywords
//!   they share, and imported maps of other tools.
//!
//! Beside them: the one least-squares loop ([`lsq`]) and the one judge of whether data determine
//! a fit ([`conditioning`]); the validation of a calibration on a standard star in frames
//! ([`validate`], with the standards' catalogue and predictions in [`standards`]); and the HWP
//! zero angle from polarized standards ([`zeroangle`]). The main job end to end, which also
//! simulates, is one crate up (`workflow::demo`).
//!
//! A model is a value that answers "what is the instrumental polarization here"
//! ([`models::model::FieldModel`], defined in the `field` crate with the field coordinates, so
//! the simulator evaluates the same values); fitters, the calibration file and the correction do
//! not care which model it is. This crate does not make Stokes maps from frames (that is
//! `skyfield`, which [`validate`] calls for the star's photometry), and it draws no plots and
//! parses no arguments (that is the CLI).

pub mod conditioning;
pub mod correction;
pub mod files;
pub mod lsq;
pub mod models;
pub mod mueller_field;
pub mod response;
pub mod telescope;
pub mod validate;

/// The gridded map lives in the `field` crate (the simulator evaluates it too).
pub use field::grid as gridmap;

pub use files::calfile::{Calibration, Model};
pub use models::bins::Bin;
pub use models::model::{FieldModel, InstPol};
pub use models::poly::{fit_poly, PolyFit, PolyModel};
pub use models::radial::{fit_radial, CovarianceScaling, ErrorScaling, RadialFit, RadialFitOptions, RadialModel};
pub use models::region::{Exclusion, FieldRegion};

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
pub mod standards;
pub mod zeroangle;

/// The crate README's example, compiled and run with the documentation tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
