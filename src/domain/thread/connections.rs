//! The API 5B casing connection table, built from the tables in `data/api5b/` (see SOURCE.md there).
//!
//! Designations read like the trade's: `BC 4-1/2` (buttress), `LC 7` (long round), `STC 9-5/8`
//! (short round). Sizes with several rows carry a suffix: the weight in lb/ft (`STC 4-1/2 9.50`) or
//! the minimum yield in ksi (`STC 9-5/8 YP110`); the plain designation is the row for other weights.

use super::{Family, FormError, MM_PER_INCH, ThreadForm};
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ConnectionKind {
    /// Buttress thread casing.
    #[serde(rename = "BC")]
    Buttress,
    /// Long round thread casing.
    #[serde(rename = "LC")]
    LongRound,
    /// Short round thread casing.
    #[serde(rename = "STC")]
    ShortRound,
}

impl ConnectionKind {
    pub fn prefix(self) -> &'static str {
        match self {
            ConnectionKind::Buttress => "BC",
            ConnectionKind::LongRound => "LC",
            ConnectionKind::ShortRound => "STC",
        }
    }
}

/// Where the thread cone sits on the pin: the pitch diameter at an axial distance from the end face
/// (E7 at L7 for buttress, E1 at L1 for round threads).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GaugePlane {
    pub z_mm: f64,
    pub pitch_diameter_mm: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Connection {
    pub designation: String,
    pub kind: ConnectionKind,
    pub family: Family,
    pub pipe_od_mm: f64,
    pub threads_per_inch: u32,
    pub pitch_mm: f64,
    pub taper_on_diameter: f64,
    pub thread_height_mm: f64,
    pub height_tolerance_mm: f64,
    /// Thread length from the pipe end.
    pub l4_mm: f64,
    /// Minimum length of full-crest threads from the pipe end.
    pub lc_mm: f64,
    pub gauge: GaugePlane,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub weight_lb_per_ft: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_yield_ksi: Option<f64>,
    #[serde(skip)]
    form: Option<ThreadForm>,
}

impl Connection {
    pub fn circumference_mm(&self) -> f64 {
        std::f64::consts::PI * self.pipe_od_mm
    }

    /// The thread form (validated when the table was built).
    pub fn form(&self) -> &ThreadForm {
        self.form.as_ref().expect("table rows carry their form")
    }
}

/// 8-round thread height hs = 0.07125 in and its ±0.002 in tolerance (SOURCE.md). Public sources give no
/// buttress height tolerance: the table assumes the same ±0.002 in; a custom form overrides it.
const ROUND_HEIGHT_IN: f64 = 0.07125;
const HEIGHT_TOLERANCE_IN: f64 = 0.002;
const BUTTRESS_HEIGHT_IN: f64 = 0.062;

const BTC_CSV: &str = include_str!("../../../data/api5b/BTC.csv");
const LTC_CSV: &str = include_str!("../../../data/api5b/LTC.csv");
const STC_CSV: &str = include_str!("../../../data/api5b/STC.csv");

#[derive(Deserialize)]
#[serde(rename_all = "PascalCase")]
struct Row {
    #[serde(rename = "D")]
    d: f64,
    #[serde(rename = "TPI")]
    tpi: u32,
    #[serde(rename = "L4")]
    l4: f64,
    #[serde(rename = "Lc")]
    lc: f64,
    #[serde(rename = "T", default)]
    t: Option<f64>,
    #[serde(rename = "L7", default)]
    l7: Option<f64>,
    #[serde(rename = "E7", default)]
    e7: Option<f64>,
    #[serde(rename = "L1", default)]
    l1: Option<f64>,
    #[serde(rename = "E1", default)]
    e1: Option<f64>,
    #[serde(rename = "Srn", default)]
    srn: Option<f64>,
    #[serde(rename = "WPF", default)]
    wpf: Option<f64>,
    #[serde(rename = "YP", default)]
    yp: Option<f64>,
}

/// All connections of the embedded API 5B tables.
#[derive(Clone, Debug)]
pub struct ConnectionTable {
    rows: Vec<Connection>,
}

#[derive(Debug, thiserror::Error)]
pub enum TableError {
    #[error("data/api5b/{file}: {message}")]
    Data { file: &'static str, message: String },
    #[error("data/api5b/{file} row for D={d}: {source}")]
    Form { file: &'static str, d: f64, source: FormError },
}

impl ConnectionTable {
    /// The embedded table. Built once per call; callers keep it (it is small).
    pub fn api5b() -> Self {
        Self::from_csv(BTC_CSV, LTC_CSV, STC_CSV).expect("embedded API 5B data is valid (tested)")
    }

    pub fn from_csv(btc: &str, ltc: &str, stc: &str) -> Result<Self, TableError> {
        let mut rows = Vec::new();
        for (file, text, kind) in [
            ("BTC.csv", btc, ConnectionKind::Buttress),
            ("LTC.csv", ltc, ConnectionKind::LongRound),
            ("STC.csv", stc, ConnectionKind::ShortRound),
        ] {
            let mut reader = csv::Reader::from_reader(text.as_bytes());
            for record in reader.deserialize::<Row>() {
                let row = record.map_err(|e| TableError::Data { file, message: e.to_string() })?;
                rows.push(Self::connection(file, kind, &row)?);
            }
        }
        Ok(Self { rows })
    }

    fn connection(file: &'static str, kind: ConnectionKind, row: &Row) -> Result<Connection, TableError> {
        let missing = |col: &str| TableError::Data { file, message: format!("row D={} lacks {col}", row.d) };
        let pitch_mm = MM_PER_INCH / row.tpi as f64;
        let (family, height_in, taper, gauge_z_in, gauge_e_in) = match kind {
            ConnectionKind::Buttress => (
                Family::Buttress,
                BUTTRESS_HEIGHT_IN,
                row.t.ok_or_else(|| missing("T"))?,
                row.l7.ok_or_else(|| missing("L7"))?,
                row.e7.ok_or_else(|| missing("E7"))?,
            ),
            ConnectionKind::LongRound | ConnectionKind::ShortRound => (
                Family::Round,
                ROUND_HEIGHT_IN,
                0.0625,
                row.l1.ok_or_else(|| missing("L1"))?,
                row.e1.ok_or_else(|| missing("E1"))?,
            ),
        };
        let height_mm = height_in * MM_PER_INCH;
        let tolerance_mm = HEIGHT_TOLERANCE_IN * MM_PER_INCH;
        let form = match family {
            Family::Round => {
                ThreadForm::api_round(pitch_mm, height_mm, tolerance_mm, taper, row.srn.map(|s| s * MM_PER_INCH))
            }
            Family::Buttress => ThreadForm::api_buttress(pitch_mm, height_mm, tolerance_mm, taper),
        }
        .map_err(|source| TableError::Form { file, d: row.d, source })?;
        let mut designation = format!("{} {}", kind.prefix(), inch_fraction(row.d));
        if let Some(w) = row.wpf {
            designation.push_str(&format!(" {w:.2}"));
        } else if let Some(yp) = row.yp {
            designation.push_str(&format!(" YP{yp:.0}"));
        }
        Ok(Connection {
            designation,
            kind,
            family,
            pipe_od_mm: row.d * MM_PER_INCH,
            threads_per_inch: row.tpi,
            pitch_mm,
            taper_on_diameter: taper,
            thread_height_mm: height_mm,
            height_tolerance_mm: tolerance_mm,
            l4_mm: row.l4 * MM_PER_INCH,
            lc_mm: row.lc * MM_PER_INCH,
            gauge: GaugePlane { z_mm: gauge_z_in * MM_PER_INCH, pitch_diameter_mm: gauge_e_in * MM_PER_INCH },
            weight_lb_per_ft: row.wpf,
            min_yield_ksi: row.yp,
            form: Some(form),
        })
    }

    pub fn all(&self) -> &[Connection] {
        &self.rows
    }

    /// Finds a designation, ignoring case and repeated spaces; `BTC`/`LTC` are accepted for `BC`/`LC`.
    pub fn get(&self, designation: &str) -> Option<&Connection> {
        let wanted = normalise(designation);
        self.rows.iter().find(|c| normalise(&c.designation) == wanted)
    }
}

fn normalise(designation: &str) -> String {
    let upper = designation.split_whitespace().collect::<Vec<_>>().join(" ").to_ascii_uppercase();
    for (alias, canonical) in [("BTC ", "BC "), ("LTC ", "LC ")] {
        if let Some(rest) = upper.strip_prefix(alias) {
            return format!("{canonical}{rest}");
        }
    }
    upper
}

/// 4.5 → "4-1/2", 9.625 → "9-5/8", 7.0 → "7".
fn inch_fraction(inches: f64) -> String {
    let whole = inches.trunc();
    let eighths = ((inches - whole) * 8.0).round() as u32;
    if eighths == 0 {
        return format!("{whole:.0}");
    }
    let (mut num, mut den) = (eighths, 8);
    while num % 2 == 0 {
        num /= 2;
        den /= 2;
    }
    format!("{whole:.0}-{num}/{den}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_holds_every_row_with_trade_designations() {
        let table = ConnectionTable::api5b();
        assert_eq!(table.all().len(), 14 + 11 + 24);
        let bc = table.get("BC 4-1/2").unwrap();
        assert_eq!(bc.family, Family::Buttress);
        assert!((bc.lc_mm - 31.8389).abs() < 1e-3, "{}", bc.lc_mm);
        assert!((bc.pitch_mm - 5.08).abs() < 1e-12);
        assert!((bc.thread_height_mm - 1.5748).abs() < 1e-9);
        assert!((bc.pipe_od_mm - 114.3).abs() < 1e-9);
        assert_eq!(table.get("btc  4-1/2").unwrap().designation, "BC 4-1/2");
        let lc = table.get("LC 7").unwrap();
        assert_eq!(lc.family, Family::Round);
        assert!((lc.pitch_mm - 3.175).abs() < 1e-12);
        assert!((lc.lc_mm - 2.875 * 25.4).abs() < 1e-9);
        assert!(table.get("STC 9-5/8").is_some());
        assert!(table.get("STC 9-5/8 YP110").is_some());
        assert!(table.get("STC 4-1/2 9.50").is_some());
        assert!(table.get("EUE 2-7/8").is_none());
        let designations: std::collections::HashSet<_> = table.all().iter().map(|c| &c.designation).collect();
        assert_eq!(designations.len(), table.all().len(), "every row has its own designation");
        assert!(table.get("LC 9-5/8 YP110").is_some());
    }

    #[test]
    fn source_consistency_checks_hold() {
        // SOURCE.md: round Lc = L4 − 1.125 in; buttress Lc = L7 − 0.400 in.
        for c in ConnectionTable::api5b().all() {
            match c.kind {
                ConnectionKind::Buttress => {
                    assert!((c.lc_mm - (c.gauge.z_mm - 0.4 * MM_PER_INCH)).abs() < 1e-6, "{}", c.designation)
                }
                _ => assert!((c.lc_mm - (c.l4_mm - 1.125 * MM_PER_INCH)).abs() < 1e-6, "{}", c.designation),
            }
        }
    }

    #[test]
    fn fractions() {
        assert_eq!(inch_fraction(4.5), "4-1/2");
        assert_eq!(inch_fraction(13.375), "13-3/8");
        assert_eq!(inch_fraction(10.75), "10-3/4");
        assert_eq!(inch_fraction(16.0), "16");
    }
}
