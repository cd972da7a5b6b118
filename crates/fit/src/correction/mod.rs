//! Correcting measurements with a calibration: what a caller asks of a calibration file and
//! the refusals it may meet ([`request`]), whether data and calibration belong together
//! ([`setup`]), the chain from the sky to the plate that answers it ([`chain`]), the correction
//! of one row or a Stokes map with its errors ([`correct`]), a table's rows column by column
//! ([`columns`]), and a catalog corrected in the run that measured it ([`catalog_correct`]).

pub mod catalog_correct;
pub mod chain;
pub mod columns;
pub mod correct;
pub mod request;
pub mod setup;
