//! Frames to maps: the sky side of a dual-beam imaging polarimeter.
//!
//! This crate reads raw-like FITS frames (real or simulated, by the same code path), knows
//! where the ordinary and extraordinary images of each focal-plane mask strip fall on the
//! detector ([`beams`], the one place that geometry lives), reduces a set of frames taken at
//! `N` half-wave-plate angles to per-pixel `F_i` and `Q/I`, `U/I` with the one Stokes solver of
//! the `stokes` crate, bins them with a sigma-clipped average ([`bin`]) into a [`StokesMap`]
//! ([`maps`], with its FITS format), and measures point sources by aperture photometry with
//! the background removed vectorially ([`photometry`]). It does not fit field models (that is
//! the `fit` crate) and does not simulate (that is `sim`).
//!
//! The frame I/O is in layers, each file using only those below it: the FITS primitives
//! ([`fits`]), the frame and the reading of a plain one ([`frame`]), the calibration of raw
//! chip files ([`calib`]), and the entry point that chooses between them ([`io`]); the
//! celestial WCS a map carries is [`wcs`], the tables of stars and catalogs [`table`].

pub mod align;
pub mod aperture;
pub mod beams;
pub mod bin;
pub mod calib;
pub mod catalog;
pub mod detect;
pub mod durable;
pub mod fits;
pub mod frame;
pub mod io;
pub mod layout;
pub mod maps;
pub mod pedestal;
pub mod photometry;
pub mod provenance;
pub mod reduce;
pub mod same;
pub mod sky_angle;
pub mod solve;
pub mod table;
pub mod wcs;

pub use beams::BeamGeometry;
pub use maps::{BinGeometry, CircularMap, CorrectionStamp, ExposureTrack, RecordedAngles, StokesMap, TelescopeStamp};

use std::path::PathBuf;

/// Errors of the frame side: each names the file, keyword, HWP angle or pixel at fault.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("{path}: {message}")]
    Fits { path: PathBuf, message: String },
    #[error("{path}: cannot write: {message}")]
    Write { path: PathBuf, message: String },
    #[error("{path}: BITPIX {bitpix} is not a detector frame type (expected 16, 32, -32 or -64)")]
    BadBitpix { path: PathBuf, bitpix: i32 },
    #[error("{path}: primary HDU is not a 2-D image (shape {shape:?})")]
    NotImage { path: PathBuf, shape: Vec<usize> },
    #[error("{path}: missing header keyword '{keyword}'")]
    MissingKeyword { path: PathBuf, keyword: String },
    #[error("{path}: header keyword '{keyword}' = '{value}' is not {expected}")]
    BadKeyword { path: PathBuf, keyword: String, value: String, expected: String },
    #[error("{path}: image is {got_nx} x {got_ny} px but {expected}")]
    SizeMismatch { path: PathBuf, got_nx: usize, got_ny: usize, expected: String },
    #[error("{path}: filter '{filter}' is not one of instrument {instrument}'s filters ({known})")]
    UnknownFilter { path: PathBuf, filter: String, instrument: String, known: String },
    #[error("frames mix filters: {details}")]
    MixedFilters { details: String },
    #[error("incomplete HWP angle set in filter {filter}: have {have}, missing {missing} (expected the N = {n} set {expected})")]
    MissingAngle { filter: String, have: String, missing: String, n: usize, expected: String },
    #[error("{path}: every pixel is NaN or infinite")]
    AllNonFinite { path: PathBuf },
    #[error("no frames given")]
    NoFrames,
    #[error("{files}: no sky pixel has f_O + f_E > 0 after removing the instrument's bias of {bias} ADU (gain {gain} e-/ADU): are the frames already bias-subtracted, or is the instrument's bias_adu wrong?")]
    NoFlux { files: String, bias: f64, gain: f64 },
    #[error("no valid bins: every pixel was masked (saturated, non-finite or non-positive flux)")]
    NoValidBins,
    #[error("{0}")]
    Invalid(String),
    /// A star that cannot be measured where it is, and why: the catalog flags its row by
    /// `why` (`catalog::flags`), never by the message's words, which hold file names.
    #[error("{message}")]
    Unmeasurable { why: Unmeasurable, message: String },
    #[error("{path}: {message}")]
    Table { path: PathBuf, message: String },
    #[error(transparent)]
    Stokes(#[from] stokes::Error),
    #[error(transparent)]
    Instrument(#[from] instrument::Error),
}

/// Why a star cannot be measured ([`Error::Unmeasurable`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unmeasurable {
    /// Its position, aperture or e image lies behind the focal-plane mask, off the detector or
    /// in the gap between chips.
    MaskEdge,
    /// An aperture pixel reaches the saturation level.
    Saturated,
}

impl Error {
    /// A star that cannot be measured where it is: behind the mask, off the detector, in a
    /// chip gap ([`Unmeasurable::MaskEdge`]).
    pub(crate) fn mask_edge(message: String) -> Self {
        Error::Unmeasurable { why: Unmeasurable::MaskEdge, message }
    }

    /// A star whose aperture reaches the saturation level ([`Unmeasurable::Saturated`]).
    pub(crate) fn saturated(message: String) -> Self {
        Error::Unmeasurable { why: Unmeasurable::Saturated, message }
    }
}

/// A non-fatal problem worth telling the user (NaN or saturated pixels masked, ...).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Warning {
    pub file: Option<PathBuf>,
    pub message: String,
}

impl std::fmt::Display for Warning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.file {
            Some(p) => write!(f, "{}: {}", p.display(), self.message),
            None => write!(f, "{}", self.message),
        }
    }
}

pub(crate) fn fits_err(path: &std::path::Path, e: impl std::fmt::Display) -> Error {
    Error::Fits { path: path.to_path_buf(), message: e.to_string() }
}

/// `v` resized to `n` values, the ones added set to `x` by all of rayon's threads at once.
/// Tens of MB filled by one thread have the kernel fault in and clear every page on that one
/// core while the others wait: two such fills of 34 MB (a background map, a filtered image)
/// were a tenth of a catalog's wall time.
/// New memory of tens of MB is also asked for in huge pages ([`advise_huge_pages`]).
pub(crate) fn par_resize(v: &mut Vec<f64>, n: usize, x: f64) {
    use rayon::prelude::*;
    if v.len() >= n {
        v.truncate(n);
    } else {
        let more = n - v.len();
        if n > v.capacity() {
            v.reserve_exact(more);
            let spare = v.spare_capacity_mut();
            advise_huge_pages(spare.as_ptr() as usize, std::mem::size_of_val(spare));
        }
        v.par_extend(rayon::iter::repeat_n(x, more));
    }
}

/// Ask Linux for transparent huge pages under `bytes` of fresh memory at `start`, before its
/// first write. A frame of 2048 x 2048 in f64 is 32 MB: in 4 kB pages its first write is 8192
/// page faults, each clearing a page, and a catalog's fresh buffers (the detection's images,
/// one frame per thread) spent a seventh of its CPU time in them (`perf`, bench/catalog.sh).
/// A hint only: nothing changes where THP is off (or `always` already), or on other systems.
pub fn advise_huge_pages(start: usize, bytes: usize) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        if bytes < 4 * HUGE {
            return;
        }
        let (a, e) = ((start + HUGE - 1) & !(HUGE - 1), (start + bytes) & !(HUGE - 1));
        if e > a {
            // SAFETY: [a, e) lies inside the caller's allocation; MADV_HUGEPAGE changes no
            // contents, only how the kernel backs the pages.
            unsafe {
                libc::madvise(a as *mut libc::c_void, e - a, libc::MADV_HUGEPAGE);
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (start, bytes);
}

/// The crate README's example, compiled and run with the documentation tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
