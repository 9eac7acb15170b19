//! The domain: what a threaded pipe end, a station and the API 5B rules are, independent of how a
//! bundle arrives or how the pipeline measures.

pub mod arcs;
pub mod control;
pub mod frame;
pub mod optics;
pub mod part;
pub mod qualification;
pub mod rules;
pub mod station;
pub mod text;
pub mod thread;
