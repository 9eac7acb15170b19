//! Thread domain: thread forms (the axial profile of one pitch) and the API 5B connection table.

mod connections;
mod form;

pub use connections::{Connection, ConnectionKind, ConnectionTable, GaugePlane};
pub use form::{Family, FormError, ProfileKernel, ProfileShape, READ_SHARE_OF_FLAT, ThreadForm};

/// Millimetres per inch; API 5B tables are in inches.
pub const MM_PER_INCH: f64 = 25.4;
