//! One module per subcommand: each has `Args` (clap) and `run`.

pub mod stokes;
pub mod fresnel;
pub mod correct;
