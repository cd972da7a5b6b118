//! Workflows that span the simulator and the fits, above both (`sim` simulates, `fit`
//! calibrates, corrects and validates, and neither depends on the other): the main job end to
//! end on the paper's fields ([`demo`]), which the CLI's `instpol demo` and the Python
//! package's `instpol.demo` call.

pub mod demo;
pub mod night;

/// The crate README's example, compiled and run with the documentation tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
