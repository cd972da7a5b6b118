//! Calibration files: the field calibration file ([`calfile`]), any calibration file read once
//! with the corrections it defines ([`calibration`]), the keywords every calibration file
//! shares ([`keys`]), several field elements in one file ([`elements`]), and instrumental-polarization maps made by other tools ([`import`]).

pub mod calfile;
pub mod calibration;
pub mod elements;
pub mod import;
pub mod keys;
