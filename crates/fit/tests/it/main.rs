//! Every integration test of the `instpol-fit` package, one module per file, gathered into one test
//! binary: one link instead of one per file, which is where most of a fresh clone's
//! `cargo test --workspace` went. Run one file's tests with `cargo test -p instpol-fit --test it
//! <file>::`.

mod calfile;
#[path = "../common/mod.rs"]
mod common;
mod correct;
mod correct_map;
mod correct_validate;
mod efosc2_standards;
mod elements;
mod errors;
mod fields;
mod fors2;
mod fuzz_regressions;
mod lsq_bits;
mod mueller_cal;
mod mueller_explain;
mod mueller_smooth;
mod poly;
mod radial_eval;
mod request;
mod stability;
mod standards_list;
mod stars_field;
mod telescope_chain;
mod telescope_night;
mod telescope_polarized;
mod telescope_rotator;
mod zero_angle;
mod zero_field;
