//! The instrumental-polarization field models and their fits: the interface every model offers
//! ([`model`]), the radial model ([`radial`]) with its polar-angle test ([`polar`]) and
//! wavelength law ([`wavelength`]), 2-D polynomials ([`poly`]), the residual map
//! ([`residual`]), the field from field stars ([`stars_field`]), where a model is valid
//! ([`region`]), the binned measurements they are fitted to ([`bins`]) and how correlated
//! those bins' errors are ([`correlation`]), the paper's own fields ([`paper`]), synthetic
//! measurements for tests and the demo ([`synth`]), and the fit from bins to a field
//! calibration ([`pipeline`]).

pub mod bins;
pub mod correlation;
pub mod model;
pub mod paper;
pub mod pipeline;
pub mod polar;
pub mod poly;
pub mod radial;
pub mod region;
pub mod residual;
pub mod stars_field;
pub mod synth;
pub mod wavelength;
