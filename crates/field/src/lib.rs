//! Field coordinates and field models: where a detector pixel lies in the field, and what
//! the instrumental polarization is there.
//!
//! - [`FieldCoords`]: the one conversion between 0-based detector pixels (binned or not) and
//!   field positions in arcminutes about an origin (the detector centre by default, or a
//!   fitted optical-axis centre; `docs/architecture.md`, Conventions).
//! - [`radial`]: the one evaluation of the paper's radial polynomial `p(r) = sum c_k r^k`
//!   (section `sec:fors1`) and the radial pattern `phi = alpha` it describes.
//! - [`FieldModel`]: the interface every model of the instrumental field offers (evaluate at a
//!   position, parameters, covariance, Jacobian), with [`InstPol`], the value it returns.
//! - [`grid::GridMap`]: a gridded `Q/I`, `U/I` map with errors, evaluated bilinearly (the form
//!   of calibration-file images and imported third-party maps) or by nearest cell.
//!
//! - [`InstrumentChain`]: the instrument's optical chain as one value (telescope, field
//!   elements, plate and analyser), with its forward model to the two beams' fluxes
//!   ([`render`]) and to demodulated `(q, u)`, and its inverses ([`chain`]).
//! - [`StressedLens`]: a stressed lens's retardance field, an element of the chain that the
//!   simulator renders and a calibration file stores.
//! - [`ConstantResponse`]: the instrument's constant response calibrated on standard stars
//!   (`(q0, u0)`, efficiency, angle offset), the same over the field.
//!
//! This crate is separate from `fit` because both the simulator (`sim`, which puts a model's
//! field into frames) and the fitter (`fit`, which fits and stores models) need the same model
//! values and the same coordinates, and `sim` must not depend on `fit`'s fitting machinery
//! (argmin, spade, the calibration file). It fits nothing, reads no files and knows no
//! instrument: instruments give it their pixel scale and size.

pub mod analyser;
pub mod chain;
pub mod coords;
pub mod grid;
pub mod lens;
pub mod model;
pub mod radial;
pub mod render;
pub mod response;

pub use analyser::{Analyser, PlateMotion};
pub use chain::{ChainError, FieldChain, InstrumentChain};
pub use coords::FieldCoords;
pub use grid::{GridMap, NearestCell};
pub use lens::StressedLens;
pub use model::{FieldModel, InstPol, LinearElement, PartialPolarizer};
pub use radial::RadialPattern;
pub use render::{ExposureForward, FieldBlock};
pub use response::ConstantResponse;

/// The crate README's example, compiled and run with the documentation tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
