//! Checks of the workspace's design that a machine can make, run as this crate's tests
//! (`cargo test -p instpol-architecture`). The design itself is `docs/architecture.md`; this
//! crate has no library code and nothing depends on it.
//!
//! - `tests/it/citations.rs`: no file under `crates/` cites a document outside the repository
//!   or a numbered issue or work session instead of saying the reason (`docs/architecture.md`,
//!   Conventions, "Citations").
//! - `tests/it/import_circles.rs`: no file-level import circle in a crate's `src/` (a module file
//!   that uses another which, directly or through others, uses it back), so that each crate's
//!   files form layers (in `skyfield`: the FITS primitives below the frame below the raw
//!   calibration below the frame entry point).
//! - `tests/it/one_of_each.rs`: one median (`stokes::stats::robust::median`) and one
//!   MAD-to-sigma factor (`stokes::stats::robust::MAD_TO_SIGMA`) in the workspace.
