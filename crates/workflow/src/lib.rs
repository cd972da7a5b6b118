//! Workflows that span the simulator and the fits, above both (`sim` simulates, `fit`
//! calibrates, corrects and validates, and neither depends on the other): the main job end to
//! end on the paper's fields ([`demo`]), which the CLI's `instpol demo` and the Python
//! package's `instpol.demo` call; and the steps from frames to products that the CLI, the
//! Python package and a night's units make alike ([`steps`]).

pub mod demo;
pub mod night;
pub mod steps;

/// The crate README's example, compiled and run with the documentation tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
