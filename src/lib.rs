//! crestscan: thread geometry of oil-country tubing and casing from focal stacks, and API 5B
//! black-crest acceptance.
//!
//! Data flows bundle → depth → cloud → register → fuse/mesh → profile → crest → rules. This crate
//! holds the pure stages; files, HTTP and the database stay at the edges.

pub mod bundle;
pub mod depth;
pub mod optics;
pub mod rules;
pub mod sim;
pub mod thread;
