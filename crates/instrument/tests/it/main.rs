//! Every integration test of the `instpol-instrument` package, one module per file, gathered into one test
//! binary: one link instead of one per file, which is where most of a fresh clone's
//! `cargo test --workspace` went. Run one file's tests with `cargo test -p instpol-instrument --test it
//! <file>::`.

mod filter_throw;
mod formats;
mod fors2_zero_angle;
mod headers;
mod stability;
mod telescope;
