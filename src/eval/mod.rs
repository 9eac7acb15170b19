//! A report measured against ground truth: the simulator's truth (the benchmark suites) or a CMM.

pub mod bench;
pub mod cmm;
