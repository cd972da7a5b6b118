//! The interface every instrumental-polarization field model offers: [`FieldModel`] and its
//! value [`InstPol`] live in the `field` crate (shared with the simulator) and are re-exported
//! here so `fit::models::model::FieldModel` keeps naming them.

pub use field::model::{FieldModel, InstPol};
