//! Numeric primitives shared by the stages, each written once.

pub mod angle;
pub mod calibration;
pub mod lsq;
pub mod runs;
pub mod sequence;
pub mod stats;
pub mod union_find;
