//! Every integration test of the `instpol` package, one module per file, gathered into one test
//! binary: one link instead of one per file, which is where most of a fresh clone's
//! `cargo test --workspace` went. Run one file's tests with `cargo test -p instpol --test it
//! <file>::`.

mod bad_inputs;
mod bias;
mod calibrate;
mod calibrate_mueller;
mod calibrate_stars;
mod calibration_product;
mod catalog;
mod catalog_alignment;
mod chip_grouping;
#[path = "../common/mod.rs"]
mod common;
mod correct;
mod demo;
mod doc_examples;
mod efficiency;
mod explain;
mod exposure_outliers;
mod file_modes;
mod fit_standards;
mod fresnel;
mod full_disk;
mod fuzz;
mod hostile;
mod hostile_edited;
mod hostile_found;
mod import_map;
mod json_schema;
mod layouts;
mod mc;
mod moptop_frames;
mod mueller_smooth;
mod night;
mod numbers_of_record;
mod photometry;
mod plot_publication;
mod raw_fors2;
mod raytrace;
mod reduce;
mod reliability;
mod report;
mod scene_file_page;
mod simulate;
mod simulate_field;
mod stokes;
mod stokes_plot;
mod table_formats;
mod telescope_frames;
mod trend_instrument;
mod validate;
mod zero_angle_measured;
mod zero_angle_stars;
