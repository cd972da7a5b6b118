//! One module per subcommand: each has `Args` (clap) and `run`.

pub mod stokes;
pub mod fresnel;
pub mod raytrace;
pub mod bias;
pub mod mc;
pub mod mc_plot;
pub mod correct;
pub mod calibrate;
pub mod demo;
pub mod fit;
pub mod import_map;
pub mod plot;
pub mod wavelength_law;
pub mod validate;
pub mod photometry;
pub mod reduce;
pub mod simulate;
