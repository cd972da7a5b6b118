//! Every integration test of the `instpol-stokes` package, one module per file, gathered into one test
//! binary: one link instead of one per file, which is where most of a fresh clone's
//! `cargo test --workspace` went. Run one file's tests with `cargo test -p instpol-stokes --test it
//! <file>::`.

mod mc;
mod reduction;
mod scale;
mod stability;
mod stats;
