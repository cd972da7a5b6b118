//! Every integration test of the `instpol-sim` package, one module per file, gathered into one test
//! binary: one link instead of one per file, which is where most of a fresh clone's
//! `cargo test --workspace` went. Run one file's tests with `cargo test -p instpol-sim --test it
//! <file>::`.

mod aperture_choice;
mod catalog;
mod chain_end_to_end;
mod chain_order;
mod circular;
mod circular_map;
#[path = "../common/mod.rs"]
mod common;
mod field_model;
mod fuzz_regressions;
#[path = "../../../fit/tests/common/given.rs"]
mod given;
#[path = "../common/jones.rs"]
mod jones;
mod layouts;
mod moptop_grouping;
mod mueller_field;
mod mueller_plan;
mod raw_calibration_bits;
mod rotating_plate;
mod roundtrip;
mod sky_angle;
mod toml_numbers;
mod two_cameras;
mod two_cameras_map;
#[path = "../common/two_cameras.rs"]
mod two_cameras_setup;
mod two_elements;
