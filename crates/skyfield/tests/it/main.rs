//! Every integration test of the `instpol-skyfield` package, one module per file, gathered into one test
//! binary: one link instead of one per file, which is where most of a fresh clone's
//! `cargo test --workspace` went. Run one file's tests with `cargo test -p instpol-skyfield --test it
//! <file>::`.

mod bad_frames;
mod clip_reference;
#[path = "../common/mod.rs"]
mod common;
mod fits_append;
mod formats;
mod fors2_geometry;
mod fuzz_regressions;
mod read_paths;
mod stability;
mod tables;
mod wcs_sky;
