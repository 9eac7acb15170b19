//! The report as a QIF 3.0 results document (ISO 23952, the Quality Information Framework), what
//! CMM software and quality databases exchange: the part, the station as its measurement device,
//! the characteristics (each thread's height against nominal ± tolerance, each thread's
//! black-crest length within Lc), the measured results per thread and per 1° bin with their
//! uncertainty, the API 5B decision, and traceability (software, bundle sha256).
//!
//! The document's shape follows the official QIF 3.0 schema (`QIFApplications/QIFDocument.xsd`):
//! the elements in the order its sequences demand, one id counter (every `id` unique, `idMax`
//! the largest), each characteristic's definition → nominal → item → measurement of one type
//! (the schema's keyrefs), units declared as mm and degrees. docs/interchange.md has the mapping.
//!
//! Uncertainty: QIF carries a measured value's combined standard uncertainty as the value's
//! `combinedUncertainty` attribute (with `meanError`, 0: crestscan's corrections are applied);
//! the expanded uncertainty (k = 2) that crestscan's decisions use goes with it as an attribute
//! `expanded_uncertainty_mm`.

use crate::pipeline::report::Report;
use crate::pipeline::uncertainty::{Decision, HeightFinding};
use quick_xml::escape::escape;
use std::fmt::Write;

/// The QIF 3.0 namespace.
pub const NAMESPACE: &str = "http://qifstandards.org/xsd/qif3";
/// The media type the service answers with.
pub const MEDIA_TYPE: &str = "application/qif+xml";

/// What the report does not hold that the document names.
#[derive(Clone, Debug, Default)]
pub struct QifInputs<'a> {
    /// The station's name (else the qualification's, where one was applied; else a generic one,
    /// the bundle's optics in its description).
    pub station_name: Option<&'a str>,
    /// When the inspection finished, RFC 3339.
    pub finished_at: Option<&'a str>,
}

/// Writes the document; deterministic (the same report gives the same bytes).
pub fn document(report: &Report, inputs: &QifInputs) -> String {
    let mut ids = Ids(0);
    let standard = ids.next();
    let software = ids.next();
    let device = ids.next();
    let part = ids.next();
    let height_definition = ids.next();
    let black_definition = ids.next();
    let height_nominal = ids.next();
    let black_nominal = ids.next();
    let items: Vec<(u32, u64, u64)> = report.threads.iter().map(|t| (t.index, ids.next(), ids.next())).collect();

    // The results first, into their own buffer: their ids are counted before `idMax` is known.
    let mut results = Xml::default();
    let measurement_results = ids.next();
    let component = ids.next();
    let mut measurements = Xml::default();
    let mut count = 0usize;
    for (thread, &(index, height_item, black_item)) in report.threads.iter().zip(&items) {
        debug_assert_eq!(thread.index, index);
        // The thread's height as it is judged: the mean over its machined crests within Lc.
        let finding = thread.height_finding.as_ref();
        let status = match finding.map(|f| f.finding) {
            Some(HeightFinding::Within) => "PASS",
            Some(HeightFinding::Outside) => "FAIL",
            Some(HeightFinding::Indeterminate) => "INDETERMINATE",
            Some(HeightFinding::NotJudged) | None => "NOT_ANALYZED",
        };
        measurements.open("HeightCharacteristicMeasurement", &[("id", ids.next().to_string())]);
        measurements.attributes(&[
            Attribute::Int("thread", index.into()),
            Attribute::Str("what", "mean height over the machined crests within Lc".into()),
        ]);
        measurements.open("Status", &[]);
        measurements.leaf("CharacteristicStatusEnum", status);
        measurements.close();
        measurements.leaf("CharacteristicItemId", &height_item.to_string());
        measurements.ids("MeasurementDeviceIds", &[device]);
        let mean = finding.and_then(|f| f.mean_height_mm).or(thread.mean_height_mm);
        if let Some(mean) = mean {
            measurements.value("Value", mean, finding.and_then(|f| f.uncertainty_mm));
        }
        if let Some(max) = thread.max_height_mm {
            measurements.value("MaxValue", max, None);
        }
        if let Some(min) = thread.min_height_mm {
            measurements.value("MinValue", min, None);
        }
        measurements.close();
        count += 1;
        // Each 1° bin's height: data of the same item, judged by the thread's mean above.
        let h = &thread.height_mm;
        for (k, (&angle, value)) in h.angles_deg.iter().zip(&h.values).enumerate() {
            let Some(value) = value else { continue };
            measurements.open("HeightCharacteristicMeasurement", &[("id", ids.next().to_string())]);
            measurements.attributes(&[Attribute::Int("thread", index.into()), Attribute::Real("angle_deg", angle)]);
            measurements.open("Status", &[]);
            measurements.leaf("CharacteristicStatusEnum", "NOT_ANALYZED");
            measurements.close();
            measurements.leaf("CharacteristicItemId", &height_item.to_string());
            measurements.value("Value", *value, h.uncertainty_mm.get(k).copied().flatten());
            measurements.close();
            count += 1;
        }
        // The black crest's length within Lc (API 5B limits it on buttress threads).
        measurements.open("LengthCharacteristicMeasurement", &[("id", ids.next().to_string())]);
        measurements.attributes(&[Attribute::Int("thread", index.into())]);
        let black_status = match report.assessment.arc_limit_mm {
            Some(limit) if thread.black_crest_length_mm > limit => "FAIL",
            Some(_) => "PASS",
            // Round threads: the rule counts black crests, it does not limit a length.
            None if thread.black_crest_length_mm > 0.0 => "FAIL",
            None => "PASS",
        };
        measurements.open("Status", &[]);
        measurements.leaf("CharacteristicStatusEnum", black_status);
        measurements.close();
        measurements.leaf("CharacteristicItemId", &black_item.to_string());
        measurements.ids("MeasurementDeviceIds", &[device]);
        measurements.value("Value", thread.black_crest_length_mm, None);
        measurements.close();
        count += 1;
    }

    results.open("Results", &[]);
    results.open("MeasurementResultsSet", &[("n", "1".into())]);
    results.open("MeasurementResults", &[("id", measurement_results.to_string())]);
    let provenance = report.provenance.as_ref();
    let mut attributes = vec![
        Attribute::Str("api5b_verdict", report.verdict.as_str().into()),
        Attribute::Str("decision_iso14253_1", report.decision.as_str().into()),
        Attribute::Str("review_required", report.review_required.to_string()),
    ];
    if let Some(sha) = provenance.and_then(|p| p.bundle_sha256.as_deref()) {
        attributes.push(Attribute::Str("bundle_sha256", sha.into()));
    }
    for m in provenance.map(|p| &p.models[..]).unwrap_or_default() {
        attributes.push(Attribute::Str("model_sha256", format!("{} {}", m.name, m.sha256)));
    }
    if let Some(u) = report.uncertainty.as_ref().and_then(|u| u.expanded_median_um) {
        attributes.push(Attribute::Real("expanded_uncertainty_median_um", u));
    }
    results.attributes(&attributes);
    results.open("InspectionTraceability", &[]);
    if let Some(id) = provenance.and_then(|p| p.inspection_id.as_deref()) {
        results.leaf("ReportNumber", id);
    }
    if let Some(at) = inputs.finished_at {
        results.leaf("InspectionEnd", at);
    }
    results.open("InspectionSoftwareItems", &[]);
    results.ids("AnalysisSoftware", &[software]);
    results.close();
    results.close();
    results.open("MeasuredCharacteristics", &[]);
    results.open("CharacteristicMeasurements", &[("n", count.to_string())]);
    results.raw(&measurements.out);
    results.close();
    results.close();
    results.inspection_status("InspectionStatus", report.decision);
    results.ids("ActualComponentIds", &[component]);
    results.close();
    results.close();
    results.open("ActualComponentSets", &[("n", "1".into())]);
    results.open("ActualComponentSet", &[("n", "1".into())]);
    results.open("ActualComponent", &[("id", component.to_string())]);
    if let Some(serial) = &report.serial {
        results.leaf("SerialNumber", serial);
    }
    results.inspection_status("Status", report.decision);
    results.close();
    results.close();
    results.close();
    results.close();

    let mut doc = Xml::default();
    doc.out.push_str("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n");
    doc.open(
        "QIFDocument",
        &[("xmlns", NAMESPACE.into()), ("versionQIF", "3.0.0".into()), ("idMax", ids.0.to_string())],
    );
    doc.leaf("QPId", &qpid(report));
    if let Some(at) = inputs.finished_at {
        doc.open("Version", &[]);
        doc.leaf("TimeCreated", at);
        doc.close();
    }
    let version = provenance.map(|p| p.software_version.as_str()).unwrap_or(env!("CARGO_PKG_VERSION"));
    doc.open("Header", &[]);
    doc.open("Application", &[]);
    doc.leaf("Name", &format!("crestscan {version}"));
    doc.close();
    doc.close();
    doc.open("StandardsDefinitions", &[("n", "1".into())]);
    doc.open("Standard", &[("id", standard.to_string())]);
    doc.open("Organization", &[]);
    doc.leaf("OtherStandardsOrganization", "API");
    doc.close();
    doc.leaf("Designator", "Spec 5B");
    doc.leaf("Title", "Threading, Gauging and Inspection of Casing, Tubing, and Line Pipe Threads");
    doc.close();
    doc.close();
    doc.open("SoftwareDefinitions", &[("n", "1".into())]);
    doc.open("Software", &[("id", software.to_string())]);
    doc.leaf("VendorName", "crestscan");
    doc.leaf("ApplicationName", "crestscan");
    doc.leaf("Version", version);
    doc.close();
    doc.close();
    doc.raw(
        "<FileUnits><PrimaryUnits><AngularUnit><SIUnitName>radian</SIUnitName><UnitName>degree</UnitName>\
         <UnitConversion><Factor>0.0174532925199433</Factor></UnitConversion></AngularUnit><LinearUnit>\
         <SIUnitName>meter</SIUnitName><UnitName>mm</UnitName><UnitConversion><Factor>0.001</Factor>\
         </UnitConversion></LinearUnit></PrimaryUnits></FileUnits>",
    );
    doc.open("MeasurementResources", &[]);
    doc.open("MeasurementDevices", &[("n", "1".into())]);
    doc.open("MeasurementDevice", &[("id", device.to_string())]);
    let station = inputs.station_name.or(report.qualification.as_ref().map(|q| q.station.as_str()));
    doc.leaf("Name", station.unwrap_or("crestscan focal-stack station"));
    doc.leaf("Description", &station_description(report));
    doc.close();
    doc.close();
    doc.close();
    let part_name = report.connection.clone().unwrap_or_else(|| format!("custom {} thread", report.family.as_str()));
    doc.open("Product", &[]);
    doc.open("PartSet", &[("n", "1".into())]);
    doc.open("Part", &[("id", part.to_string()), ("label", part_name.clone())]);
    doc.open("Header", &[]);
    doc.leaf("Name", &part_name);
    doc.close();
    doc.close();
    doc.close();
    doc.ids_single("RootPart", part);
    doc.close();

    doc.open("Characteristics", &[]);
    doc.leaf("FormalStandardId", &standard.to_string());
    doc.open("CharacteristicDefinitions", &[("n", "2".into())]);
    doc.open("HeightCharacteristicDefinition", &[("id", height_definition.to_string())]);
    doc.leaf("Name", "thread height");
    doc.open("Tolerance", &[]);
    doc.leaf("MaxValue", &number(report.height_tolerance_mm));
    doc.leaf("MinValue", &number(-report.height_tolerance_mm));
    doc.leaf("DefinedAsLimit", "false");
    doc.close();
    doc.close();
    doc.open("LengthCharacteristicDefinition", &[("id", black_definition.to_string())]);
    doc.leaf("Name", "black crest length within Lc");
    // Round threads: none within Lc; the rule is on their presence, so 0 is the only limit.
    doc.open("Tolerance", &[]);
    doc.leaf("MaxValue", &number(report.assessment.arc_limit_mm.unwrap_or(0.0)));
    doc.leaf("MinValue", "0");
    doc.leaf("DefinedAsLimit", "true");
    doc.close();
    doc.close();
    doc.close();
    doc.open("CharacteristicNominals", &[("n", "2".into())]);
    doc.open("HeightCharacteristicNominal", &[("id", height_nominal.to_string())]);
    doc.leaf("CharacteristicDefinitionId", &height_definition.to_string());
    doc.leaf("Name", "thread height");
    doc.leaf("TargetValue", &number(report.nominal_height_mm));
    doc.close();
    doc.open("LengthCharacteristicNominal", &[("id", black_nominal.to_string())]);
    doc.leaf("CharacteristicDefinitionId", &black_definition.to_string());
    doc.leaf("Name", "black crest length within Lc");
    doc.leaf("TargetValue", "0");
    doc.close();
    doc.close();
    if !items.is_empty() {
        doc.open("CharacteristicItems", &[("n", (2 * items.len()).to_string())]);
        for &(index, height_item, black_item) in &items {
            doc.open("HeightCharacteristicItem", &[("id", height_item.to_string())]);
            doc.attributes(&[Attribute::Int("thread", index.into())]);
            doc.leaf("Name", &format!("thread {index} height"));
            doc.ids("MeasurementDeviceIds", &[device]);
            doc.leaf("CharacteristicNominalId", &height_nominal.to_string());
            doc.close();
            doc.open("LengthCharacteristicItem", &[("id", black_item.to_string())]);
            doc.attributes(&[Attribute::Int("thread", index.into())]);
            doc.leaf("Name", &format!("thread {index} black crest length within Lc"));
            doc.ids("MeasurementDeviceIds", &[device]);
            doc.leaf("CharacteristicNominalId", &black_nominal.to_string());
            doc.close();
        }
        doc.close();
    }
    doc.close();
    if count > 0 {
        doc.raw(&results.out);
    }
    doc.close();
    doc.out.push('\n');
    doc.out
}

/// The document's QIF persistent id, a UUID: the inspection's id where it is one (the service's
/// are), else one derived from the bundle's sha256 or the report's own bytes, so that the same
/// result always carries the same id.
fn qpid(report: &Report) -> String {
    let provenance = report.provenance.as_ref();
    if let Some(id) = provenance.and_then(|p| p.inspection_id.as_deref()).and_then(|id| uuid::Uuid::parse_str(id).ok())
    {
        return id.hyphenated().to_string();
    }
    let seed = match provenance.and_then(|p| p.bundle_sha256.clone()) {
        Some(sha) => sha,
        None => {
            use sha2::{Digest, Sha256};
            hex::encode(Sha256::digest(serde_json::to_vec(&report.threads).unwrap_or_default()))
        }
    };
    let hexed: String = seed.chars().filter(char::is_ascii_hexdigit).chain(std::iter::repeat('0')).take(32).collect();
    let mut bytes = [0u8; 16];
    for (i, b) in bytes.iter_mut().enumerate() {
        *b = u8::from_str_radix(&hexed[2 * i..2 * i + 2], 16).unwrap_or(0);
    }
    uuid::Builder::from_custom_bytes(bytes).into_uuid().hyphenated().to_string()
}

fn station_description(report: &Report) -> String {
    match &report.station {
        Some(s) => format!(
            "depth from focus: {} camera, object pixel {:.4} mm, depth of field {:.3} mm, {} views of {} frames{}",
            match s.projection {
                crate::domain::optics::Projection::Perspective => "perspective",
                crate::domain::optics::Projection::Telecentric => "telecentric",
            },
            s.object_pixel_mm,
            s.depth_of_field_mm,
            s.views,
            s.frames_per_view,
            s.class.map(|c| format!(", station class {}", c.as_str())).unwrap_or_default()
        ),
        None => "depth from focus".into(),
    }
}

/// A decimal as QIF's `xs:decimal` takes it: no exponent, no more digits than a micrometre's
/// hundredth needs.
fn number(x: f64) -> String {
    let s = format!("{x:.6}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" || s.is_empty() { "0".into() } else { s.into() }
}

struct Ids(u64);

impl Ids {
    fn next(&mut self) -> u64 {
        self.0 += 1;
        self.0
    }
}

enum Attribute {
    Str(&'static str, String),
    Int(&'static str, i64),
    Real(&'static str, f64),
}

/// A small writer: elements opened and closed in order, text and attribute values escaped.
#[derive(Default)]
struct Xml {
    out: String,
    open: Vec<&'static str>,
}

impl Xml {
    fn open(&mut self, name: &'static str, attributes: &[(&str, String)]) {
        self.out.push('<');
        self.out.push_str(name);
        for (key, value) in attributes {
            let _ = write!(self.out, " {key}=\"{}\"", escape(value.as_str()));
        }
        self.out.push('>');
        self.open.push(name);
    }

    fn close(&mut self) {
        let name = self.open.pop().expect("an open element");
        let _ = write!(self.out, "</{name}>");
    }

    fn leaf(&mut self, name: &str, text: &str) {
        let _ = write!(self.out, "<{name}>{}</{name}>", escape(text));
    }

    fn raw(&mut self, xml: &str) {
        self.out.push_str(xml);
    }

    /// A measured value with its combined standard uncertainty (u = U / 2) where it has one.
    fn value(&mut self, name: &str, mm: f64, expanded_mm: Option<f64>) {
        match expanded_mm {
            Some(u) => {
                let _ = write!(
                    self.out,
                    "<{name} combinedUncertainty=\"{}\" meanError=\"0\">{}</{name}>",
                    number(u / 2.0),
                    number(mm)
                );
            }
            None => {
                let _ = write!(self.out, "<{name}>{}</{name}>", number(mm));
            }
        }
    }

    /// An `ArrayReferenceType` list: `<name n="…"><Id>…</Id>…</name>`.
    fn ids(&mut self, name: &str, ids: &[u64]) {
        let _ = write!(self.out, "<{name} n=\"{}\">", ids.len());
        for id in ids {
            let _ = write!(self.out, "<Id>{id}</Id>");
        }
        let _ = write!(self.out, "</{name}>");
    }

    /// An `ElementReferenceType`: `<name><Id>…</Id></name>`.
    fn ids_single(&mut self, name: &str, id: u64) {
        let _ = write!(self.out, "<{name}><Id>{id}</Id></{name}>");
    }

    fn attributes(&mut self, attributes: &[Attribute]) {
        if attributes.is_empty() {
            return;
        }
        let _ = write!(self.out, "<Attributes n=\"{}\">", attributes.len());
        for a in attributes {
            let _ = match a {
                Attribute::Str(name, value) => {
                    write!(self.out, "<AttributeStr name=\"{name}\" value=\"{}\"/>", escape(value.as_str()))
                }
                Attribute::Int(name, value) => write!(self.out, "<AttributeI1 name=\"{name}\" value=\"{value}\"/>"),
                Attribute::Real(name, value) => {
                    write!(self.out, "<AttributeD1 name=\"{name}\" value=\"{}\"/>", number(*value))
                }
            };
        }
        self.out.push_str("</Attributes>");
    }

    /// `InspectionStatus`: PASS / FAIL, or INDETERMINATE by name (QIF's enumeration has no such
    /// value; its `OtherInspectionStatus` carries one).
    fn inspection_status(&mut self, element: &'static str, decision: Decision) {
        self.open(element, &[]);
        match decision {
            Decision::Conforms => self.leaf("InspectionStatusEnum", "PASS"),
            Decision::DoesNotConform => self.leaf("InspectionStatusEnum", "FAIL"),
            Decision::Indeterminate => self.leaf("OtherInspectionStatus", "INDETERMINATE"),
        }
        self.close();
    }
}
