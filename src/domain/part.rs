//! The inspected part: its thread form, pipe size and Lc, as the bundle and the connection table
//! resolve them.

use crate::domain::thread::{Family, GaugePlane, ThreadForm};

/// The inspected part, resolved from the connection table and/or the custom thread form.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Part {
    pub serial: Option<String>,
    /// The designation as given (a table row's canonical name when it was found there).
    pub connection: Option<String>,
    pub form: ThreadForm,
    pub pipe_od_mm: f64,
    pub lc_mm: f64,
    /// Where the thread cone sits, when the table knows it.
    pub gauge: Option<GaugePlane>,
}

impl Part {
    pub fn family(&self) -> Family {
        self.form.family
    }
    pub fn circumference_mm(&self) -> f64 {
        std::f64::consts::PI * self.pipe_od_mm
    }
}
