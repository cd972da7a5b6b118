//! Every integration test of the `instpol-mueller` package, one module per file, gathered into one test
//! binary: one link instead of one per file, which is where most of a fresh clone's
//! `cargo test --workspace` went. Run one file's tests with `cargo test -p instpol-mueller --test it
//! <file>::`.

mod causes_singular;
mod oblique_plate;
mod quarter_wave;
mod stability;
