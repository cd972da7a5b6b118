//! Dual-beam reduction of one source and the statistics of polarization measurements.
//!
//! From the fluxes of the ordinary and extraordinary beams at `N` half-wave-plate angles this
//! crate computes the normalized flux differences `F_i` (`eq:F`), the normalized Stokes
//! parameters `Q/I`, `U/I` (Fourier sums `eq:Q`, `eq:U` for the optimal angle set, weighted
//! least squares for any other), `P`, `chi` and their errors. It knows nothing of frames,
//! files or pixels: callers hand it numbers. The optics that produce the fluxes live in the
//! `mueller` crate.
//!
//! There is exactly one `F_i` ([`normalized_difference`]) and one Stokes solver
//! ([`StokesSolver`]); everything in the workspace that needs them calls these. Circular
//! polarization from a quarter-wave plate has its own demodulation ([`circular`]: `V/I` from
//! the same `F_i`, the value [`Circular`]).

pub mod circular;
pub mod equivalent;
pub mod fourier;
pub mod kappa;
pub mod mc;
pub mod reduce;
pub mod repeats;
pub mod solver;
pub mod stats;

pub use circular::{Circular, CircularSolver};
/// The one value of normalized `(q, u)` with its covariance (defined in `mueller`).
pub use mueller::Qu;
pub use reduce::{
    check_degrees, looks_like_radians, reduce, Estimator, KappaCorrection, LooksLikeRadians, Measurement, Reduction,
    Warning,
};
pub use solver::{
    fast_variance_in_range, normalized_difference, polarization, sigma_normalized_difference,
    variance_normalized_difference, variance_normalized_difference_fast, StokesSolver,
};

/// Errors of the reduction: each names the offending input.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum Error {
    #[error("need at least 2 HWP angles, got {0}")]
    TooFewAngles(usize),
    #[error("HWP angle {deg} deg is the same plate position as an earlier one (positions {first} and {second}, equal modulo 360 deg)")]
    DuplicateAngle { deg: f64, first: usize, second: usize },
    #[error(
        "the quarter-wave-plate angles {angles_deg} deg do not determine V: F = q cos^2 2theta + u sin 2theta cos 2theta \
         + v sin 2theta needs positions where sin 2theta differs in a way the offset and the linear terms cannot mimic \
         (e.g. -45 and +45 deg, or -45, 45, 135 and 225 deg)"
    )]
    CircularUndetermined { angles_deg: String },
    #[error("the HWP angles do not constrain both Q and U (all angles give the same modulation modulo 45 deg)")]
    Degenerate,
    #[error(
        "the plate's motion leaves nothing modulated: exposure {index} swept {sweep_deg} deg of plate angle \
         (a sweep d keeps sin(2d)/(2d) of the modulation, none at 90 deg), and Q and U cannot be solved; \
         check the exposures' begin and end angles"
    )]
    NoModulation { index: usize, sweep_deg: f64 },
    #[error("{what} has {got} values but there are {expected} HWP angles")]
    LengthMismatch { what: &'static str, got: usize, expected: usize },
    #[error("total flux f_O + f_E = {total} at HWP angle index {index} is not positive")]
    NonPositiveFlux { index: usize, total: f64 },
    #[error("non-finite value ({value}) in {what} at index {index}")]
    NonFinite { what: &'static str, index: usize, value: f64 },
    #[error("{what} = {value} at index {index} is invalid: {why}")]
    Invalid { what: &'static str, index: usize, value: f64, why: &'static str },
    #[error("kappa = {0} is outside the open interval (-1, 1)")]
    KappaOutOfRange(f64),
    #[error("kappa cannot be estimated from these data ({0}), so it cannot be applied; give a known kappa instead")]
    KappaNotEstimable(String),
    #[error(
        "sigma_F = {sigma_f:.3e} at index {index}: the flux errors are so far above the fluxes that F is \
         undetermined (and its variance would overflow); check the errors"
    )]
    Undetermined { index: usize, sigma_f: f64 },
    #[error("photon counts cannot be negative (give sigma_o, sigma_e for background-subtracted fluxes)")]
    NegativeCount { index: usize },
    #[error(
        "P = {:.2} % (+- {:.2} %) exceeds 100 % by more than 3 sigma: no light is more than fully polarized{}",
        100.0 * p, 100.0 * sigma_p,
        dark_beam.map_or(String::new(), |i| format!(" (a beam has no flux at HWP angle index {i}: a dark, masked or off-chip beam?)"))
    )]
    MoreThanFullyPolarized { p: f64, sigma_p: f64, dark_beam: Option<usize> },
}

/// The crate README's example, compiled and run with the documentation tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
