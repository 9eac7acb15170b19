//! CMM measurements (docs/bundle.md, "CMM measurements") and their comparison with an
//! inspection's thread heights: per point deviation, bias, RMS, max |deviation|, Bland–Altman
//! limits of agreement, and a tolerance verdict. Pure: parsing and statistics, no I/O.

use crate::pipeline::report::Report;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CmmPoint {
    /// Thread number as the contract counts them (1 = nearest the pipe end); one of the
    /// inspection's threads (its report's `threads[].index`), else the upload is refused.
    #[schema(minimum = 1, maximum = 1000)]
    pub thread: u32,
    /// Angle around the pipe, [0, 360); absent means the thread's mean height.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(minimum = 0.0, exclusive_maximum = 360.0)]
    pub angle_deg: Option<f64>,
    /// [0, 25) mm.
    #[schema(minimum = 0.0, exclusive_maximum = 25.0)]
    pub height_mm: f64,
    /// The CMM's expanded uncertainty (k = 2) of this height, mm, where its software states one:
    /// with crestscan's own it gives the point's normalised error Eₙ.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(exclusive_minimum = 0.0, maximum = 1.0)]
    pub uncertainty_mm: Option<f64>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CmmMeasurements {
    /// The CMM that measured: 1 to 200 characters, no control characters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(min_length = 1, max_length = 200)]
    pub instrument: Option<String>,
    /// RFC 3339.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(format = DateTime, max_length = 64)]
    pub measured_at: Option<String>,
    /// 1 to 100 000 points.
    #[schema(min_items = 1, max_items = 100_000)]
    pub points: Vec<CmmPoint>,
    /// The CMM's expanded uncertainty (k = 2), mm, for every point that states none of its own
    /// (`# uncertainty_mm: …` in CSV); kept with each point.
    #[serde(default, skip_serializing)]
    #[schema(exclusive_minimum = 0.0, maximum = 1.0)]
    pub uncertainty_mm: Option<f64>,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct CmmError {
    /// JSON path (`points[3].height_mm`) or CSV position (`line 4, height_mm`).
    pub field: String,
    pub message: String,
}

fn err(field: impl Into<String>, message: impl Into<String>) -> CmmError {
    CmmError { field: field.into(), message: message.into() }
}

pub const MAX_POINTS: usize = 100_000;

/// Angles are kept to 0.0001°, the resolution every answer rounds them to.
const ANGLE_STEPS_PER_DEG: f64 = 10_000.0;

/// The unit a CSV export gives its heights in.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Unit {
    Mm,
    In,
}

impl Unit {
    fn parse(value: &str, field: &str) -> Result<Self, CmmError> {
        match value.trim().to_ascii_lowercase().as_str() {
            "mm" | "millimetre" | "millimeter" | "millimetres" | "millimeters" => Ok(Self::Mm),
            "in" | "inch" | "inches" | "\"" => Ok(Self::In),
            other => Err(err(field, format!("{other:?} is not a unit crestscan reads (mm or in)"))),
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Mm => "mm",
            Self::In => "in",
        }
    }

    fn to_mm(self, value: f64) -> f64 {
        match self {
            Self::Mm => value,
            Self::In => value * 25.4,
        }
    }
}
/// The highest thread number a point may name (a connection has a few dozen).
pub const MAX_THREAD: u32 = 1000;

impl CmmMeasurements {
    pub fn from_json(bytes: &[u8]) -> Result<Self, CmmError> {
        let de = &mut serde_json::Deserializer::from_slice(bytes);
        let parsed: Self = serde_path_to_error::deserialize(de).map_err(|e| {
            let path = e.path().to_string();
            err(if path == "." { "body".into() } else { path }, e.inner().to_string())
        })?;
        parsed.validate()?;
        Ok(parsed.normalised())
    }

    /// CSV as CMM software exports it. The header names the columns `thread`, `angle_deg` and the
    /// height, `height_mm` or `height_in` (inches, converted); an optional `unit` column (`mm` or
    /// `in`) sets each row's unit instead. An empty angle means the thread's mean. The separator is
    /// `,`, or `;` or a tab where the header uses one (European exports), and then a decimal comma
    /// (`1,5748`) reads as a point. Lines before the header starting with `#` may carry
    /// `instrument: …`, `measured_at: …` (RFC 3339) and `units: mm|in` (the default for a
    /// `height` column without its unit in the name).
    pub fn from_csv(bytes: &[u8]) -> Result<Self, CmmError> {
        let text = std::str::from_utf8(bytes).map_err(|e| err("body", format!("not UTF-8 text: {e}")))?;
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        // Metadata lines before the header.
        let (mut instrument, mut measured_at, mut file_unit, mut file_uncertainty) = (None, None, None, None);
        let mut body_start = 0;
        let mut header_line = 1;
        for line in text.split_inclusive('\n') {
            let trimmed = line.trim();
            if !(trimmed.starts_with('#') || trimmed.is_empty()) {
                break;
            }
            body_start += line.len();
            header_line += 1;
            let Some((key, value)) = trimmed.trim_start_matches('#').split_once(':') else { continue };
            let value = value.trim().to_string();
            match key.trim().to_ascii_lowercase().as_str() {
                "instrument" => instrument = Some(value),
                "measured_at" => measured_at = Some(value),
                "units" | "unit" => file_unit = Some(Unit::parse(&value, "units")?),
                "uncertainty_mm" => {
                    let u = value.replacen(',', ".", 1).parse::<f64>().map_err(|_| {
                        err("uncertainty_mm", format!("{} is not a number", crate::domain::text::preview(&value)))
                    })?;
                    file_uncertainty = Some(u);
                }
                _ => {}
            }
        }
        let body = &text[body_start..];
        let first = body.lines().next().unwrap_or("");
        let delimiter = if first.contains(';') {
            b';'
        } else if first.contains('\t') {
            b'\t'
        } else {
            b','
        };
        let decimal_comma = delimiter != b',';
        let mut reader =
            csv::ReaderBuilder::new().delimiter(delimiter).trim(csv::Trim::All).from_reader(body.as_bytes());
        let headers = reader.headers().map_err(|e| err("header", e.to_string()))?.clone();
        let find = |name: &str| headers.iter().position(|h| h.eq_ignore_ascii_case(name));
        let expected = "expected thread, angle_deg and height_mm (or height_in)";
        let column =
            |name: &str| find(name).ok_or_else(|| err("header", format!("missing column {name:?} ({expected})")));
        let (thread_col, angle_col) = (column("thread")?, column("angle_deg")?);
        let (height_col, column_unit) = match (find("height_mm"), find("height_in"), find("height")) {
            (Some(c), None, _) => (c, Some(Unit::Mm)),
            (None, Some(c), _) => (c, Some(Unit::In)),
            (None, None, Some(c)) => (c, None),
            (Some(_), Some(_), _) => return Err(err("header", "both height_mm and height_in: which is the height?")),
            (None, None, None) => return Err(err("header", format!("missing the height column ({expected})"))),
        };
        let unit_col = find("unit").or_else(|| find("units"));
        let uncertainty_col = find("uncertainty_mm");
        if column_unit.is_none() && unit_col.is_none() && file_unit.is_none() {
            return Err(err(
                "header",
                "a `height` column needs its unit: name it height_mm or height_in, add a unit column, or a `# units: mm` line",
            ));
        }
        let number = |s: &str| -> Option<f64> {
            let s = if decimal_comma && !s.contains('.') { s.replacen(',', ".", 1) } else { s.to_string() };
            s.parse::<f64>().ok()
        };
        let mut points = Vec::new();
        for (i, record) in reader.records().enumerate() {
            let line = header_line + 1 + i;
            let record = record.map_err(|e| err(format!("line {line}"), e.to_string()))?;
            let get = |c: usize| record.get(c).unwrap_or("");
            let thread = get(thread_col).parse::<u32>().map_err(|_| {
                err(format!("line {line}, thread"), format!("{:?} is not a thread number", get(thread_col)))
            })?;
            let angle_deg = match get(angle_col) {
                "" => None,
                a => Some(
                    number(a)
                        .ok_or_else(|| err(format!("line {line}, angle_deg"), format!("{a:?} is not a number")))?,
                ),
            };
            let h = get(height_col);
            let height = number(h).ok_or_else(|| {
                err(format!("line {line}, {}", &headers[height_col]), format!("{h:?} is not a number"))
            })?;
            let row_unit = match unit_col.map(get).filter(|u| !u.is_empty()) {
                Some(u) => Some(Unit::parse(u, &format!("line {line}, unit"))?),
                None => None,
            };
            let unit = match (row_unit, column_unit) {
                (Some(r), Some(c)) if r != c => {
                    return Err(err(
                        format!("line {line}, unit"),
                        format!("{} in a {} column", r.name(), headers.get(height_col).unwrap_or("height")),
                    ));
                }
                (Some(r), _) => r,
                (None, Some(c)) => c,
                (None, None) => file_unit.expect("checked above: some unit is declared"),
            };
            let uncertainty_mm = match uncertainty_col.map(get).filter(|u| !u.is_empty()) {
                Some(u) => Some(
                    number(u)
                        .ok_or_else(|| err(format!("line {line}, uncertainty_mm"), format!("{u:?} is not a number")))?,
                ),
                None => None,
            };
            points.push(CmmPoint { thread, angle_deg, height_mm: unit.to_mm(height), uncertainty_mm });
        }
        let parsed = Self { instrument, measured_at, points, uncertainty_mm: file_uncertainty };
        parsed.validate()?;
        Ok(parsed.normalised())
    }

    /// Checked as every upload is, and normalised: what the parsers of other formats return.
    pub(crate) fn checked(self) -> Result<Self, CmmError> {
        self.validate()?;
        Ok(self.normalised())
    }

    /// Angles at the resolution they are published with (0.0001°, export::json), wrapped into
    /// [0, 360): 359.99999 is stored as 0, not as a 360 that the range forbids and no bin matches.
    fn normalised(mut self) -> Self {
        for p in &mut self.points {
            p.uncertainty_mm = p.uncertainty_mm.or(self.uncertainty_mm);
            if let Some(a) = p.angle_deg.as_mut() {
                let at_resolution = (*a * ANGLE_STEPS_PER_DEG).round() / ANGLE_STEPS_PER_DEG;
                *a = if at_resolution >= 360.0 { 0.0 } else { at_resolution };
            }
        }
        self
    }

    fn validate(&self) -> Result<(), CmmError> {
        if self.points.is_empty() {
            return Err(err("points", "no measurements"));
        }
        if self.points.len() > MAX_POINTS {
            return Err(err("points", format!("{} points; at most {MAX_POINTS}", self.points.len())));
        }
        use crate::domain::text::{self, INSTRUMENT_CHARS, TIMESTAMP_CHARS};
        if let Some(name) = &self.instrument {
            text::check(name, INSTRUMENT_CHARS).map_err(|e| err("instrument", e.to_string()))?;
        }
        if let Some(t) = &self.measured_at {
            text::check(t, TIMESTAMP_CHARS).map_err(|e| err("measured_at", e.to_string()))?;
            time::OffsetDateTime::parse(t, &time::format_description::well_known::Rfc3339)
                .map_err(|e| err("measured_at", format!("{t:?} is not an RFC 3339 time: {e}")))?;
        }
        for (i, p) in self.points.iter().enumerate() {
            if p.thread == 0 || p.thread > MAX_THREAD {
                return Err(err(format!("points[{i}].thread"), format!("threads are numbered 1 to {MAX_THREAD}")));
            }
            if let Some(a) = p.angle_deg
                && !(a.is_finite() && (0.0..360.0).contains(&a))
            {
                return Err(err(format!("points[{i}].angle_deg"), format!("{a} is outside [0, 360)")));
            }
            if let Some(u) = p.uncertainty_mm.or(self.uncertainty_mm)
                && !(u.is_finite() && u > 0.0 && u <= 1.0)
            {
                return Err(err(
                    format!("points[{i}].uncertainty_mm"),
                    format!("{u} is not a CMM's expanded uncertainty in mm (0 < U ≤ 1)"),
                ));
            }
            if !(p.height_mm.is_finite() && p.height_mm >= 0.0 && p.height_mm < 25.0) {
                return Err(err(
                    format!("points[{i}].height_mm"),
                    format!("{} is not a thread height in mm", p.height_mm),
                ));
            }
        }
        Ok(())
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct PointComparison {
    pub thread: u32,
    /// None: the CMM gave the thread's mean, compared with crestscan's mean over measured bins.
    pub angle_deg: Option<f64>,
    pub cmm_height_mm: f64,
    /// None where crestscan has no height there (thread or bin not measured).
    pub crestscan_height_mm: Option<f64>,
    /// crestscan − CMM.
    pub deviation_mm: Option<f64>,
    /// crestscan's expanded uncertainty (k = 2) of its height there, mm.
    pub crestscan_uncertainty_mm: Option<f64>,
    /// The CMM's, where it stated one.
    pub cmm_uncertainty_mm: Option<f64>,
    /// Normalised error Eₙ = deviation / √(U_crestscan² + U_CMM²) (ISO/IEC 17043): |Eₙ| ≤ 1 is
    /// agreement within the two instruments' stated uncertainties. Null where either is unknown.
    pub en: Option<f64>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Agreement {
    /// Points with both heights.
    pub compared: usize,
    /// CMM points crestscan did not measure.
    pub unmatched: usize,
    /// Mean deviation (crestscan − CMM).
    pub bias_mm: Option<f64>,
    pub rms_mm: Option<f64>,
    pub max_abs_deviation_mm: Option<f64>,
    /// Sample standard deviation of the deviations.
    pub sd_mm: Option<f64>,
    /// Bland–Altman 95% limits of agreement: bias ± 1.96 sd.
    pub limits_of_agreement_mm: Option<[f64; 2]>,
    /// 95% confidence interval of the bias: bias ± t(0.975, n − 1)·sd/√n (two or more points).
    pub bias_ci95_mm: Option<[f64; 2]>,
    /// 95% confidence intervals of the lower and the upper limit of agreement: each ± t(0.975, n −
    /// 1)·sd·√(3/n) (Bland and Altman 1986): how well so few points pin the limits down.
    pub limits_of_agreement_ci95_mm: Option<[[f64; 2]; 2]>,
    /// Points with an Eₙ (both uncertainties known).
    pub en_points: usize,
    /// The largest |Eₙ|; null when no point has one.
    pub en_max_abs: Option<f64>,
    /// Every Eₙ within ±1; null when no point has one.
    pub en_within_1: Option<bool>,
    /// The agreement tolerance, mm (`tolerance_mm`; default a tenth of the thread-height band).
    pub tolerance_mm: f64,
    /// Every compared deviation within ± tolerance, over at least [`MIN_AGREEMENT_POINTS`] points
    /// (fewer say nothing of the limits: `warnings` says so).
    pub within_tolerance: bool,
    /// What limits these figures, in words: too few points, CMM points where crestscan measured
    /// nothing, no uncertainty stated for the CMM.
    pub warnings: Vec<String>,
}

/// The fewest compared points from which agreement is claimed: with fewer, the limits of agreement
/// are uncertain by more than their own width's half (their interval at n = 10 is ±1.2 sd).
pub const MIN_AGREEMENT_POINTS: usize = 10;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Comparison {
    pub points: Vec<PointComparison>,
    pub agreement: Agreement,
}

/// The default tolerance: one tenth of the thread-height tolerance band (± tol → 2·tol / 10).
pub fn default_tolerance_mm(report: &Report) -> f64 {
    2.0 * report.height_tolerance_mm / 10.0
}

/// crestscan's height of `thread` at `angle_deg` (the bin whose centre is nearest, within half a
/// bin), or its mean over measured bins when no angle is given.
/// With the height, its expanded uncertainty where the report has one for that very quantity: a
/// bin's; none for a thread's mean over its measured bins (the report's U is of its finding's
/// mean, over machined crests within Lc: another quantity).
fn crestscan_height(report: &Report, thread: u32, angle_deg: Option<f64>) -> Option<(f64, Option<f64>)> {
    let t = report.threads.iter().find(|t| t.index == thread)?;
    let Some(angle) = angle_deg else { return t.mean_height_mm.map(|h| (h, None)) };
    let series = &t.height_mm;
    let spacing = if series.angles_deg.len() > 1 { 360.0 / series.angles_deg.len() as f64 } else { 360.0 };
    let circular = |a: f64, b: f64| {
        let d = (a - b).rem_euclid(360.0);
        d.min(360.0 - d)
    };
    let (i, d) = series
        .angles_deg
        .iter()
        .enumerate()
        .map(|(i, &a)| (i, circular(a, angle)))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    if d > spacing / 2.0 + 1e-9 {
        return None;
    }
    let height = series.values.get(i).copied().flatten()?;
    Some((height, series.uncertainty_mm.get(i).copied().flatten()))
}

/// Refuses CMM points on threads the inspection does not have (a typo, another part's table):
/// the field names the first such point, the message every unknown thread and the known ones.
pub fn check_threads(report: &Report, cmm: &CmmMeasurements) -> Result<(), CmmError> {
    let known: std::collections::BTreeSet<u32> = report.threads.iter().map(|t| t.index).collect();
    let unknown: std::collections::BTreeSet<u32> =
        cmm.points.iter().map(|p| p.thread).filter(|t| !known.contains(t)).collect();
    let Some(first) = cmm.points.iter().position(|p| !known.contains(&p.thread)) else { return Ok(()) };
    let list = |set: &std::collections::BTreeSet<u32>| set.iter().map(u32::to_string).collect::<Vec<_>>().join(", ");
    Err(err(
        format!("points[{first}].thread"),
        format!("thread(s) {} are not threads of this inspection (it has {})", list(&unknown), list(&known)),
    ))
}

pub fn compare(report: &Report, cmm: &CmmMeasurements, tolerance_mm: f64) -> Comparison {
    let points: Vec<PointComparison> = cmm
        .points
        .iter()
        .map(|p| {
            let found = crestscan_height(report, p.thread, p.angle_deg);
            let (ours, ours_u) = (found.map(|f| f.0), found.and_then(|f| f.1));
            PointComparison {
                thread: p.thread,
                angle_deg: p.angle_deg,
                cmm_height_mm: p.height_mm,
                crestscan_height_mm: ours,
                deviation_mm: ours.map(|h| h - p.height_mm),
                crestscan_uncertainty_mm: ours_u,
                cmm_uncertainty_mm: p.uncertainty_mm,
                en: ours.zip(ours_u).zip(p.uncertainty_mm).and_then(|((h, u), v)| {
                    let combined = (u * u + v * v).sqrt();
                    (combined > 0.0).then(|| (h - p.height_mm) / combined)
                }),
            }
        })
        .collect();
    let deviations: Vec<f64> = points.iter().filter_map(|p| p.deviation_mm).collect();
    let n = deviations.len();
    let mean = (n > 0).then(|| deviations.iter().sum::<f64>() / n as f64);
    let rms = (n > 0).then(|| (deviations.iter().map(|d| d * d).sum::<f64>() / n as f64).sqrt());
    // The largest |value|; None when there is none.
    let max_abs = |values: &[f64]| values.iter().map(|v| v.abs()).reduce(f64::max);
    let max_abs_deviation = max_abs(&deviations);
    let sd = mean
        .filter(|_| n > 1)
        .map(|m| (deviations.iter().map(|d| (d - m).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt());
    let limits = mean.zip(sd).map(|(m, s)| [m - 1.96 * s, m + 1.96 * s]);
    let t = (n > 1).then(|| crate::numeric::stats::student_t_975(n - 1));
    let bias_ci = mean.zip(sd).zip(t).map(|((m, s), t)| {
        let half = t * s / (n as f64).sqrt();
        [m - half, m + half]
    });
    let limits_ci = limits.zip(sd).zip(t).map(|((l, s), t)| {
        let half = t * s * (3.0 / n as f64).sqrt();
        [[l[0] - half, l[0] + half], [l[1] - half, l[1] + half]]
    });
    let ens: Vec<f64> = points.iter().filter_map(|p| p.en).collect();
    let en_max = max_abs(&ens);
    let unmatched = points.len() - n;
    let mut warnings = Vec::new();
    if n < MIN_AGREEMENT_POINTS {
        warnings.push(format!(
            "Only {n} point(s) could be compared; agreement is not claimed from fewer than {MIN_AGREEMENT_POINTS} \
             (the limits of agreement would be uncertain by more than half their width)."
        ));
    }
    if unmatched > 0 {
        warnings
            .push(format!("{unmatched} CMM point(s) fall where crestscan measured no height; they are not compared."));
    }
    if n > 0 && ens.is_empty() {
        warnings.push(
            "The CMM data state no uncertainty (`uncertainty_mm`), so no normalised error Eₙ is given.".to_string(),
        );
    }
    Comparison {
        agreement: Agreement {
            compared: n,
            unmatched,
            bias_mm: mean,
            rms_mm: rms,
            max_abs_deviation_mm: max_abs_deviation,
            sd_mm: sd,
            limits_of_agreement_mm: limits,
            bias_ci95_mm: bias_ci,
            limits_of_agreement_ci95_mm: limits_ci,
            en_points: ens.len(),
            en_max_abs: en_max,
            en_within_1: en_max.map(|m| m <= 1.0),
            tolerance_mm,
            within_tolerance: n >= MIN_AGREEMENT_POINTS && max_abs_deviation.is_some_and(|m| m <= tolerance_mm),
            warnings,
        },
        points,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angles_a_hair_under_360_wrap_to_0_not_360() {
        let m = CmmMeasurements::from_json(
            br#"{"points":[{"thread":3,"angle_deg":359.99999,"height_mm":1.5},{"thread":3,"angle_deg":359.9999,"height_mm":1.5},{"thread":3,"angle_deg":12.345678,"height_mm":1.5}]}"#,
        )
        .unwrap();
        let angles: Vec<f64> = m.points.iter().map(|p| p.angle_deg.unwrap()).collect();
        assert_eq!(angles, [0.0, 359.9999, 12.3457]);
        let csv = CmmMeasurements::from_csv(b"thread,angle_deg,height_mm\n3,359.99999,1.5\n").unwrap();
        assert_eq!(csv.points[0].angle_deg, Some(0.0));
    }

    #[test]
    fn free_texts_have_caps_named_by_their_field() {
        let long = "x".repeat(201);
        let body = format!(r#"{{"instrument":"{long}","points":[{{"thread":3,"height_mm":1.5}}]}}"#);
        let e = CmmMeasurements::from_json(body.as_bytes()).unwrap_err();
        assert_eq!(e.field, "instrument");
        assert!(e.message.contains("at most 200"), "{e}");
        let csv = format!("# instrument: {long}\nthread,angle_deg,height_mm\n3,1,1.5\n");
        assert_eq!(CmmMeasurements::from_csv(csv.as_bytes()).unwrap_err().field, "instrument");
    }

    #[test]
    fn csv_and_json_agree_and_errors_name_the_place() {
        let csv = b"thread,angle_deg,height_mm\n3,90.0,0.9826\n4,,0.98\n";
        let a = CmmMeasurements::from_csv(csv).unwrap();
        let b = CmmMeasurements::from_json(
            br#"{"points":[{"thread":3,"angle_deg":90.0,"height_mm":0.9826},{"thread":4,"height_mm":0.98}]}"#,
        )
        .unwrap();
        assert_eq!(a.points, b.points);
        let e = CmmMeasurements::from_csv(b"thread,angle_deg,height_mm\n3,90,abc\n").unwrap_err();
        assert_eq!(e.field, "line 2, height_mm");
        let e =
            CmmMeasurements::from_json(br#"{"points":[{"thread":3,"angle_deg":400,"height_mm":1.0}]}"#).unwrap_err();
        assert_eq!(e.field, "points[0].angle_deg");
        let e = CmmMeasurements::from_json(br#"{"points":[{"thread":"x","height_mm":1.0}]}"#).unwrap_err();
        assert_eq!(e.field, "points[0].thread");
        let e = CmmMeasurements::from_csv(b"thread,height\n1,2\n").unwrap_err();
        assert!(e.message.contains("angle_deg"), "{e}");
    }

    fn heights(m: &CmmMeasurements) -> Vec<f64> {
        m.points.iter().map(|p| p.height_mm).collect()
    }

    #[test]
    fn the_contracts_csv_reads_as_before() {
        let m = CmmMeasurements::from_csv(b"thread,angle_deg,height_mm\n3,12.5,1.5748\n4,,1.576\n").unwrap();
        assert_eq!(m.points[0], CmmPoint { thread: 3, angle_deg: Some(12.5), height_mm: 1.5748, uncertainty_mm: None });
        assert_eq!(m.points[1].angle_deg, None);
        assert_eq!((m.instrument, m.measured_at), (None, None));
    }

    #[test]
    fn a_european_export_with_semicolons_decimal_commas_and_its_metadata_reads() {
        let csv = "\u{feff}# instrument: Zeiss Contura\n# measured_at: 2026-11-30T10:00:00Z\n\
                   thread;angle_deg;height_mm\n3;12,5;1,5748\n4;;1,5760\n";
        let m = CmmMeasurements::from_csv(csv.as_bytes()).unwrap();
        assert_eq!(m.points[0], CmmPoint { thread: 3, angle_deg: Some(12.5), height_mm: 1.5748, uncertainty_mm: None });
        assert_eq!(heights(&m), [1.5748, 1.576]);
        assert_eq!(m.instrument.as_deref(), Some("Zeiss Contura"));
        assert_eq!(m.measured_at.as_deref(), Some("2026-11-30T10:00:00Z"));
        // Tabs too.
        let m = CmmMeasurements::from_csv(b"thread\tangle_deg\theight_mm\n3\t1,0\t1,5\n").unwrap();
        assert_eq!(heights(&m), [1.5]);
    }

    #[test]
    fn inches_are_converted_not_read_as_millimetres() {
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        let m = CmmMeasurements::from_csv(b"thread,angle_deg,height_in\n3,12.5,0.062\n").unwrap();
        assert!(close(m.points[0].height_mm, 0.062 * 25.4));
        let m = CmmMeasurements::from_csv(b"thread,angle_deg,height,unit\n3,1,0.062,in\n3,2,1.5748,mm\n").unwrap();
        assert!(close(m.points[0].height_mm, 1.5748) && close(m.points[1].height_mm, 1.5748));
        let m = CmmMeasurements::from_csv(b"# units: inch\nthread,angle_deg,height\n3,1,0.062\n").unwrap();
        assert!(close(m.points[0].height_mm, 1.5748));
    }

    #[test]
    fn a_unit_missing_unknown_or_contradicted_is_named() {
        let e = CmmMeasurements::from_csv(b"thread,angle_deg,height\n3,1,1.5\n").unwrap_err();
        assert_eq!(e.field, "header");
        assert!(e.message.contains("unit"), "{e}");
        let e = CmmMeasurements::from_csv(b"# units: ft\nthread,angle_deg,height\n3,1,1.5\n").unwrap_err();
        assert_eq!(e.field, "units");
        let e = CmmMeasurements::from_csv(b"thread,angle_deg,height_mm,unit\n3,1,1.5,mm\n3,2,0.06,in\n").unwrap_err();
        assert_eq!(e.field, "line 3, unit");
        let e = CmmMeasurements::from_csv(b"thread,angle_deg,height_mm,height_in\n3,1,1.5,0.06\n").unwrap_err();
        assert_eq!(e.field, "header");
        // A comma decimal in a comma-separated file is a column too many, not a number.
        let e = CmmMeasurements::from_csv(b"thread,angle_deg,height_mm\n3,1,1,5\n").unwrap_err();
        assert_eq!(e.field, "line 2");
    }
}
