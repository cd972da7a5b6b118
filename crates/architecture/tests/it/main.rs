//! Every integration test of the `instpol-architecture` package, one module per file, gathered into one test
//! binary: one link instead of one per file, which is where most of a fresh clone's
//! `cargo test --workspace` went. Run one file's tests with `cargo test -p instpol-architecture --test it
//! <file>::`.

mod citations;
#[path = "../common/mod.rs"]
mod common;
mod crate_layers;
mod docs_links;
mod folders;
mod function_length;
mod import_circles;
mod one_of_each;
