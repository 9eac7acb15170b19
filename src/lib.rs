//! crestscan: thread geometry of oil-country tubing and casing from focal stacks, and API 5B
//! black-crest acceptance.
//!
//! Data flows bundle → depth → cloud → register → fuse/mesh → profile → crest → rules. This crate
//! holds the pure stages; files, HTTP and the database stay at the edges.

pub mod api;
pub mod bench;
pub mod bundle;
pub mod cloud;
pub mod cmm;
pub mod config;
pub mod crest;
pub mod depth;
pub mod endface;
pub mod fuse;
pub mod images;
pub mod jobs;
pub mod mesh;
pub mod optics;
pub mod pipeline;
pub mod profile;
pub mod register;
pub mod report;
pub mod rules;
pub mod sim;
pub mod startup;
pub mod store;
pub mod telemetry;
pub mod thread;
