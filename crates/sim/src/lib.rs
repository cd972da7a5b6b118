//! Scene simulation: raw-like dual-beam polarimetric frames of a scene, computing only what
//! the scene asks for.
//!
//! A [`Scene`] (TOML, [`scene`]) names the instrument, the sky and sources and the instrument
//! effects to apply. [`Plan::build`] turns it into a short list of steps, built once:
//! - the **sky at the plate**: the Stokes vector of every sky pixel, constant when the scene is
//!   a uniform sky with no field-dependent effect (then nothing is stored per pixel), otherwise
//!   an image made once per scene (sky, gradient, stars, extended sources, and the
//!   instrumental field `Element::PartialPolarizer{p, phi}` applied per pixel);
//! - the **instrumental field** is any [`field::FieldModel`]: the one the scene's
//!   `[effects.instpol]` names (radial pattern, Q/U maps, ray-trace profile), or a model value
//!   handed over directly ([`Plan::build_with_field`], [`simulate_with_field`]: a calibration's
//!   model, a fitted polynomial, a paper field), evaluated at each pixel's field position by
//!   `field::FieldCoords`, the same conversion the fitter uses;
//! - the **optics**: the one forward model `mueller::DualBeam` (HWP defects, Wollaston,
//!   post-analyzer), compiled once and reduced, per HWP angle, to the two rows that give
//!   `f_O`, `f_E` from the Stokes vector at the plate (the model is linear, so two dot
//!   products per pixel replace all the matrices);
//! - the **detector steps** (flat-field errors, photon noise, cosmic rays, read noise, gain,
//!   bias, saturation), only those the scene lists: an absent effect draws no random number
//!   and multiplies nothing.
//!
//! Frames are placed on the detector by `skyfield::beams` (the same geometry the reduction
//! uses) and written by `skyfield::fits` (the format the reduction reads with `skyfield::io`),
//! one FITS file per exposure plus a truth file (JSON), in parallel and atomically. Randomness
//! is seeded per (scene seed, frame, detector row), so results do not depend on the number of
//! threads.

pub mod hwp_causes;
pub mod night;
pub mod plan;
pub mod raw;
pub mod scene;
pub mod stress;

pub use plan::{simulate, simulate_with_field, Plan, Simulated};
pub use scene::Scene;

use std::path::PathBuf;

/// Errors of scene loading and simulation; each names the file and key at fault.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("scene {path}: {message}")]
    Scene { path: PathBuf, message: String },
    #[error("scene {path}: {key} = {v}: {why}", v = shortened(.value))]
    Invalid { path: PathBuf, key: String, value: String, why: String },
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
    #[error(transparent)]
    Instrument(#[from] instrument::Error),
    #[error(transparent)]
    Frames(#[from] skyfield::Error),
    #[error(transparent)]
    Stokes(#[from] stokes::Error),
}

/// A value as an error message quotes it: whole up to 100 characters, else its start and how
/// long it is (a list of 1000 HWP angles filled a screen before the reason).
fn shortened(v: &str) -> String {
    const KEEP: usize = 100;
    match v.char_indices().nth(KEEP) {
        Some((cut, _)) => format!("{} ... ({} characters)", &v[..cut], v.chars().count()),
        None => v.to_string(),
    }
}

/// The crate README's example, compiled and run with the documentation tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
