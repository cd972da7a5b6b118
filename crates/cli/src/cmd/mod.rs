//! One module per subcommand: each has `Args` (clap) and `run`.

pub mod bias;
pub mod calibrate;
pub mod calibrate_mueller;
pub mod catalog;
pub mod correct;
pub mod demo;
pub mod explain;
pub mod fit;
pub mod fit_standards;
pub mod frame_opts;
pub mod fresnel;
pub mod import_map;
pub mod master;
pub mod mc;
pub mod mc_plot;
pub mod photometry;
pub mod plan;
pub mod plot;
pub mod raytrace;
pub mod reduce;
pub mod simulate;
pub mod stokes;
pub mod stokes_plot;
pub mod validate;
pub mod wavelength_law;
pub mod zero_angle;
