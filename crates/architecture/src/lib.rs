//! Checks of the workspace's design that a machine can make, run as this crate's tests
//! (`cargo test -p instpol-architecture`). The design itself is `docs/architecture.md`; this
//! crate has no library code and nothing depends on it.
//!
//! - `tests/citations.rs`: no file under `crates/` cites a document outside the repository
//!   or a numbered issue or work session instead of saying the reason (`docs/architecture.md`,
//!   Conventions, "Citations").
