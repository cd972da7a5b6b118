//! Models of the instrumental polarization field and their use: radial polynomials with an
//! optional free optical-axis centre (argmin), the polar-angle test, the wavelength law, the
//! Delaunay-interpolated residual map (spade), the per-filter calibration file, and the
//! correction of measured Stokes parameters with error propagation.
//!
//! A model is a value that answers "what is the instrumental polarization here"
//! ([`model::FieldModel`]); fitters, the calibration file and the correction do not care which
//! model it is.

pub mod model;
pub mod correct;
pub mod standards;
