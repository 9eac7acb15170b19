//! A report measured against ground truth: the simulator's truth (the benchmark suites behind
//! `crestscan bench`) or a CMM's measurements.

pub mod budget;
pub mod cmm;
pub mod cmm_qif;
pub mod pairs;
pub mod qualify;
pub mod suite;
pub mod table;
pub mod truth;

pub use suite::{ACCURACY_SUITE, BenchError, Case, CaseResult, HOLDOUT_SUITE, Suite, TUNING_SUITE, run_case};
pub use table::{TargetCheck, table, targets};
pub use truth::{Accuracy, BlackCrest, RegistrationError, black_crests, compare};

#[cfg(test)]
mod tests;
