//! CMM results as CMM software exports them in QIF 3.0 (ISO 23952): a `QIFDocument` whose one
//! `MeasurementResults` holds height measurements, mapped onto the thread / angle points the CMM
//! comparison uses (docs/interchange.md, "QIF CMM results in"):
//!
//! - each `HeightCharacteristicMeasurement` names its item (`CharacteristicItemId`); the item says
//!   which thread by an attribute `thread` (`AttributeI1`, `AttributeD1` or `AttributeStr`) or by
//!   its `Name` (`thread 3 height`, `Thread_3`, `T3`);
//! - the angle, where the point has one, is an attribute `angle_deg` of the measurement (or of its
//!   item); without one the value is the thread's mean height;
//! - the value's unit is the file's primary linear unit (`FileUnits`; QIF's default is the
//!   metre), its `combinedUncertainty` (k = 1) becomes the point's expanded uncertainty (k = 2);
//! - any other measurement, an item that names no thread, a reference to no item: refused, every
//!   one named by its id.

use super::cmm::{CmmError, CmmMeasurements, CmmPoint};

/// Elements deeper than this are refused (a QIF results document nests about ten deep).
const MAX_DEPTH: usize = 64;

struct Node {
    name: String,
    attributes: Vec<(String, String)>,
    text: String,
    children: Vec<usize>,
}

struct Tree {
    nodes: Vec<Node>,
}

impl Tree {
    fn parse(bytes: &[u8]) -> Result<Tree, CmmError> {
        use quick_xml::events::Event;
        let mut reader = quick_xml::Reader::from_reader(bytes);
        reader.config_mut().trim_text(true);
        let mut nodes: Vec<Node> = Vec::new();
        let mut stack: Vec<usize> = Vec::new();
        let mut buf = Vec::new();
        let position = |reader: &quick_xml::Reader<&[u8]>| format!("byte {}", reader.buffer_position());
        loop {
            let event =
                reader.read_event_into(&mut buf).map_err(|e| err(position(&reader), format!("not XML: {e}")))?;
            match event {
                Event::Start(ref e) | Event::Empty(ref e) => {
                    let empty = matches!(event, Event::Empty(_));
                    let name = String::from_utf8_lossy(e.local_name().as_ref()).into_owned();
                    let mut attributes = Vec::new();
                    for a in e.attributes() {
                        let a = a.map_err(|e| err(position(&reader), format!("an attribute: {e}")))?;
                        let value = a
                            .unescape_value()
                            .map_err(|e| err(position(&reader), format!("an attribute's value: {e}")))?
                            .into_owned();
                        attributes.push((String::from_utf8_lossy(a.key.local_name().as_ref()).into_owned(), value));
                    }
                    let id = nodes.len();
                    nodes.push(Node { name, attributes, text: String::new(), children: Vec::new() });
                    match stack.last() {
                        Some(&parent) => nodes[parent].children.push(id),
                        None if id != 0 => return Err(err("body", "more than one root element")),
                        None => {}
                    }
                    if !empty {
                        stack.push(id);
                        if stack.len() > MAX_DEPTH {
                            return Err(err(position(&reader), format!("elements nested deeper than {MAX_DEPTH}")));
                        }
                    }
                }
                Event::End(_) => {
                    stack.pop();
                }
                Event::Text(t) => {
                    if let Some(&open) = stack.last() {
                        let text = t.xml_content().map_err(|e| err(position(&reader), format!("text: {e}")))?;
                        nodes[open].text.push_str(&text);
                    }
                }
                // `&amp;`, `&#176;`: text split around its references.
                Event::GeneralRef(r) => {
                    if let Some(&open) = stack.last() {
                        let name = r.decode().map_err(|e| err(position(&reader), format!("a reference: {e}")))?;
                        let resolved = match r.resolve_char_ref() {
                            Ok(Some(c)) => c.to_string(),
                            _ => quick_xml::escape::resolve_xml_entity(&name)
                                .ok_or_else(|| err(position(&reader), format!("unknown entity &{name};")))?
                                .to_string(),
                        };
                        nodes[open].text.push_str(&resolved);
                    }
                }
                Event::CData(t) => {
                    if let Some(&open) = stack.last() {
                        nodes[open].text.push_str(&String::from_utf8_lossy(&t));
                    }
                }
                Event::Eof => break,
                _ => {}
            }
            buf.clear();
        }
        if nodes.is_empty() {
            return Err(err("body", "no XML element"));
        }
        Ok(Tree { nodes })
    }

    fn node(&self, id: usize) -> &Node {
        &self.nodes[id]
    }

    fn children<'a>(&'a self, id: usize, name: &'a str) -> impl Iterator<Item = usize> + 'a {
        self.nodes[id].children.iter().copied().filter(move |&c| self.nodes[c].name == name)
    }

    fn child(&self, id: usize, name: &str) -> Option<usize> {
        self.children(id, name).next()
    }

    /// The node at the end of `path` below `id`, taking the first of each name.
    fn at(&self, id: usize, path: &[&str]) -> Option<usize> {
        path.iter().try_fold(id, |at, name| self.child(at, name))
    }

    fn text(&self, id: usize, path: &[&str]) -> Option<&str> {
        self.at(id, path).map(|n| self.nodes[n].text.trim()).filter(|t| !t.is_empty())
    }

    fn attribute(&self, id: usize, name: &str) -> Option<&str> {
        self.nodes[id].attributes.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }

    /// A QIF user attribute (`Attributes/Attribute*[@name]`) of the element `id`, as text.
    fn user_attribute(&self, id: usize, name: &str) -> Option<&str> {
        let attributes = self.child(id, "Attributes")?;
        self.nodes[attributes]
            .children
            .iter()
            .find(|&&a| self.nodes[a].name.starts_with("Attribute") && self.attribute(a, "name") == Some(name))
            .and_then(|&a| self.attribute(a, "value"))
    }
}

fn err(field: impl Into<String>, message: impl Into<String>) -> CmmError {
    CmmError { field: field.into(), message: message.into() }
}

/// The thread an item's name gives: `thread 3 …`, `Thread_3`, `thread-3`, or `T3` alone.
fn thread_in_name(name: &str) -> Option<u32> {
    let lower = name.to_ascii_lowercase();
    if let Some(at) = lower.find("thread") {
        let rest = lower[at + "thread".len()..].trim_start_matches([' ', '_', '-', '#', ':']);
        let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
        return digits.parse().ok();
    }
    let word = lower.trim();
    word.strip_prefix('t')
        .filter(|d| !d.is_empty() && d.chars().all(|c| c.is_ascii_digit()))
        .and_then(|d| d.parse().ok())
}

/// The primary linear unit's size in mm (`FileUnits/PrimaryUnits/LinearUnit`): its conversion
/// factor to the metre where given, else its name; the metre where the file declares none.
fn linear_unit_mm(tree: &Tree) -> Result<(f64, String), CmmError> {
    let Some(unit) = tree.at(0, &["FileUnits", "PrimaryUnits", "LinearUnit"]) else {
        return Ok((1000.0, "meter".into()));
    };
    let name = tree.text(unit, &["UnitName"]).unwrap_or("").to_string();
    if let Some(factor) = tree.text(unit, &["UnitConversion", "Factor"]) {
        let factor: f64 = factor.parse().map_err(|_| {
            err("FileUnits/PrimaryUnits/LinearUnit/UnitConversion/Factor", format!("{factor:?} is not a number"))
        })?;
        if !(factor.is_finite() && factor > 0.0) {
            return Err(err("FileUnits/PrimaryUnits/LinearUnit/UnitConversion/Factor", "must be positive"));
        }
        return Ok((factor * 1000.0, name));
    }
    let mm = match name.to_ascii_lowercase().as_str() {
        "mm" | "millimeter" | "millimetre" => 1.0,
        "inch" | "in" => 25.4,
        "m" | "meter" | "metre" => 1000.0,
        "um" | "µm" | "micrometer" | "micron" => 0.001,
        other => {
            return Err(err(
                "FileUnits/PrimaryUnits/LinearUnit/UnitName",
                format!("{other:?} without a UnitConversion: give its Factor to the metre"),
            ));
        }
    };
    Ok((mm, name))
}

impl CmmMeasurements {
    /// A QIF 3.0 results document (module docs): the thread / angle points it measured.
    pub fn from_qif(bytes: &[u8]) -> Result<Self, CmmError> {
        let tree = Tree::parse(bytes)?;
        let root = tree.node(0);
        if root.name != "QIFDocument" {
            return Err(err("body", format!("the root element is {}, not a QIFDocument", root.name)));
        }
        let (unit_mm, unit_name) = linear_unit_mm(&tree)?;

        // Items by id: their kind and the thread they name.
        let mut items = std::collections::HashMap::new();
        if let Some(list) = tree.at(0, &["Characteristics", "CharacteristicItems"]) {
            for &item in &tree.node(list).children {
                let Some(id) = tree.attribute(item, "id") else { continue };
                let name = tree.text(item, &["Name"]);
                let thread = match tree.user_attribute(item, "thread") {
                    Some(t) => t.trim().parse::<f64>().ok().filter(|t| t.fract() == 0.0 && *t >= 1.0).map(|t| t as u32),
                    None => name.and_then(thread_in_name),
                };
                items.insert(id.to_string(), (item, thread, name.map(str::to_string)));
            }
        }

        let results: Vec<usize> = tree
            .at(0, &["Results", "MeasurementResultsSet"])
            .map(|set| tree.children(set, "MeasurementResults").collect())
            .unwrap_or_default();
        let results = match results[..] {
            [one] => one,
            [] => return Err(err("Results", "no MeasurementResults: a QIF results document holds one")),
            _ => {
                return Err(err(
                    "Results/MeasurementResultsSet",
                    format!("{} MeasurementResults: upload one part's measurements at a time", results.len()),
                ));
            }
        };
        let measurements = tree
            .at(results, &["MeasuredCharacteristics", "CharacteristicMeasurements"])
            .ok_or_else(|| err("MeasurementResults", "no MeasuredCharacteristics/CharacteristicMeasurements"))?;

        let mut points = Vec::new();
        let mut refused = Vec::new();
        for &m in &tree.node(measurements).children {
            let node = tree.node(m);
            let id = tree.attribute(m, "id").unwrap_or("(no id)");
            if node.name != "HeightCharacteristicMeasurement" {
                refused.push(format!("{id} ({}: only heights map onto thread heights)", node.name));
                continue;
            }
            let Some(item_id) = tree.text(m, &["CharacteristicItemId"]) else {
                refused.push(format!("{id} (no CharacteristicItemId)"));
                continue;
            };
            let Some((item, thread, item_name)) = items.get(item_id) else {
                refused.push(format!("{id} (its item {item_id} is not among the CharacteristicItems)"));
                continue;
            };
            if tree.node(*item).name != "HeightCharacteristicItem" {
                refused.push(format!("{id} (its item {item_id} is a {}, not a height)", tree.node(*item).name));
                continue;
            }
            let Some(thread) = thread else {
                refused.push(format!(
                    "{id} (its item {item_id}{} names no thread: give it an attribute `thread` or a Name like \
                     \"thread 3\")",
                    item_name.as_deref().map(|n| format!(" {n:?}")).unwrap_or_default()
                ));
                continue;
            };
            let Some(value_node) = tree.child(m, "Value") else {
                refused.push(format!("{id} (no Value)"));
                continue;
            };
            if let Some(unit) = tree.attribute(value_node, "linearUnit")
                && !unit.eq_ignore_ascii_case(&unit_name)
            {
                refused.push(format!("{id} (its value is in {unit}, not the file's {unit_name})"));
                continue;
            }
            let text = tree.node(value_node).text.trim();
            let Ok(value) = text.parse::<f64>() else {
                refused.push(format!("{id} (its Value {text:?} is not a number)"));
                continue;
            };
            let angle = tree.user_attribute(m, "angle_deg").or_else(|| tree.user_attribute(*item, "angle_deg"));
            let angle_deg = match angle.map(|a| a.trim().parse::<f64>()) {
                None => None,
                Some(Ok(a)) => Some(a),
                Some(Err(_)) => {
                    refused.push(format!("{id} (its angle_deg {:?} is not a number)", angle.unwrap_or("")));
                    continue;
                }
            };
            let uncertainty_mm = match tree.attribute(value_node, "combinedUncertainty").map(str::parse::<f64>) {
                Some(Ok(u)) => Some(2.0 * u * unit_mm),
                Some(Err(_)) => {
                    refused.push(format!("{id} (its combinedUncertainty is not a number)"));
                    continue;
                }
                None => None,
            };
            points.push(CmmPoint { thread: *thread, angle_deg, height_mm: value * unit_mm, uncertainty_mm });
        }
        if !refused.is_empty() {
            let shown: Vec<&str> = refused.iter().take(20).map(String::as_str).collect();
            let more = refused.len().saturating_sub(shown.len());
            return Err(err(
                "CharacteristicMeasurements",
                format!(
                    "{} measurement(s) cannot be mapped onto a thread height: {}{}",
                    refused.len(),
                    shown.join("; "),
                    if more > 0 { format!("; and {more} more") } else { String::new() }
                ),
            ));
        }
        let instrument = tree
            .at(0, &["MeasurementResources", "MeasurementDevices"])
            .and_then(|devices| tree.node(devices).children.first().copied())
            .and_then(|device| tree.text(device, &["Name"]))
            .map(str::to_string);
        let measured_at = tree
            .text(results, &["InspectionTraceability", "InspectionStart"])
            .or_else(|| tree.text(results, &["InspectionTraceability", "InspectionEnd"]))
            .or_else(|| tree.text(0, &["Version", "TimeCreated"]))
            .map(str::to_string);
        Self { instrument, measured_at, points, uncertainty_mm: None }.checked()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn document(units: &str, measurements: &str, items: &str) -> String {
        format!(
            r#"<?xml version="1.0"?>
<QIFDocument xmlns="http://qifstandards.org/xsd/qif3" versionQIF="3.0.0" idMax="30">
  <QPId>8a2c5e8e-0b5d-4b8f-9a53-2b1c7c1d9e01</QPId>
  {units}
  <MeasurementResources><MeasurementDevices n="1"><MeasurementDevice id="3"><Name>Zeiss Contura</Name></MeasurementDevice></MeasurementDevices></MeasurementResources>
  <Characteristics><FormalStandardId>1</FormalStandardId>
    <CharacteristicItems n="3">{items}</CharacteristicItems>
  </Characteristics>
  <Results><MeasurementResultsSet n="1"><MeasurementResults id="20">
    <InspectionTraceability><InspectionStart>2026-12-01T08:30:00Z</InspectionStart></InspectionTraceability>
    <MeasuredCharacteristics><CharacteristicMeasurements n="3">{measurements}</CharacteristicMeasurements></MeasuredCharacteristics>
    <InspectionStatus><InspectionStatusEnum>PASS</InspectionStatusEnum></InspectionStatus>
  </MeasurementResults></MeasurementResultsSet></Results>
</QIFDocument>"#
        )
    }

    const ITEMS: &str = r#"
      <HeightCharacteristicItem id="10"><Name>thread 3 height</Name><CharacteristicNominalId>7</CharacteristicNominalId></HeightCharacteristicItem>
      <HeightCharacteristicItem id="11"><Attributes n="1"><AttributeI1 name="thread" value="4"/></Attributes><Name>H-04</Name><CharacteristicNominalId>7</CharacteristicNominalId></HeightCharacteristicItem>
      <LengthCharacteristicItem id="12"><Name>thread 3 black crest</Name><CharacteristicNominalId>8</CharacteristicNominalId></LengthCharacteristicItem>"#;

    const MM: &str =
        "<FileUnits><PrimaryUnits><LinearUnit><UnitName>mm</UnitName></LinearUnit></PrimaryUnits></FileUnits>";

    #[test]
    fn heights_map_onto_threads_and_angles_in_the_files_unit() {
        let measurements = r#"
          <HeightCharacteristicMeasurement id="21"><Attributes n="1"><AttributeD1 name="angle_deg" value="12.5"/></Attributes>
            <Status><CharacteristicStatusEnum>PASS</CharacteristicStatusEnum></Status><CharacteristicItemId>10</CharacteristicItemId>
            <Value combinedUncertainty="0.0015" meanError="0">1.575</Value></HeightCharacteristicMeasurement>
          <HeightCharacteristicMeasurement id="22"><Status><CharacteristicStatusEnum>PASS</CharacteristicStatusEnum></Status>
            <CharacteristicItemId>11</CharacteristicItemId><Value>1.58</Value></HeightCharacteristicMeasurement>"#;
        let m = CmmMeasurements::from_qif(document(MM, measurements, ITEMS).as_bytes()).unwrap();
        assert_eq!(m.instrument.as_deref(), Some("Zeiss Contura"));
        assert_eq!(m.measured_at.as_deref(), Some("2026-12-01T08:30:00Z"));
        assert_eq!(m.points.len(), 2);
        assert_eq!((m.points[0].thread, m.points[0].angle_deg), (3, Some(12.5)));
        assert!((m.points[0].height_mm - 1.575).abs() < 1e-12);
        assert!((m.points[0].uncertainty_mm.unwrap() - 0.003).abs() < 1e-12, "k = 2 from the combined u");
        assert_eq!((m.points[1].thread, m.points[1].angle_deg, m.points[1].uncertainty_mm), (4, None, None));
        // Inches by their conversion factor; the metre where the file declares no unit.
        let inch = "<FileUnits><PrimaryUnits><LinearUnit><UnitName>inch</UnitName><UnitConversion><Factor>0.0254</Factor></UnitConversion></LinearUnit></PrimaryUnits></FileUnits>";
        let inches = measurements.replace("1.575", "0.062").replace(">1.58<", ">0.0622<");
        let m = CmmMeasurements::from_qif(document(inch, &inches, ITEMS).as_bytes()).unwrap();
        assert!((m.points[1].height_mm - 0.0622 * 25.4).abs() < 1e-9, "read as inches");
        let metres =
            measurements.replace("1.575", "0.001575").replace(">1.58<", ">0.00158<").replace("0.0015\"", "0.0000015\"");
        let m = CmmMeasurements::from_qif(document("", &metres, ITEMS).as_bytes()).unwrap();
        assert!((m.points[1].height_mm - 1.58).abs() < 1e-9);
    }

    #[test]
    fn unmappable_measurements_are_refused_by_their_ids() {
        let measurements = r#"
          <HeightCharacteristicMeasurement id="21"><Status><CharacteristicStatusEnum>PASS</CharacteristicStatusEnum></Status><CharacteristicItemId>10</CharacteristicItemId><Value>1.575</Value></HeightCharacteristicMeasurement>
          <LengthCharacteristicMeasurement id="23"><Status><CharacteristicStatusEnum>PASS</CharacteristicStatusEnum></Status><CharacteristicItemId>12</CharacteristicItemId><Value>0</Value></LengthCharacteristicMeasurement>
          <HeightCharacteristicMeasurement id="24"><Status><CharacteristicStatusEnum>PASS</CharacteristicStatusEnum></Status><CharacteristicItemId>99</CharacteristicItemId><Value>1.5</Value></HeightCharacteristicMeasurement>
          <HeightCharacteristicMeasurement id="25"><Status><CharacteristicStatusEnum>PASS</CharacteristicStatusEnum></Status><CharacteristicItemId>13</CharacteristicItemId><Value>1.5</Value></HeightCharacteristicMeasurement>"#;
        let items = format!(
            "{ITEMS}<HeightCharacteristicItem id=\"13\"><Name>pitch diameter</Name><CharacteristicNominalId>7</CharacteristicNominalId></HeightCharacteristicItem>"
        );
        let e = CmmMeasurements::from_qif(document(MM, measurements, &items).as_bytes()).unwrap_err();
        assert_eq!(e.field, "CharacteristicMeasurements");
        for named in ["23 (LengthCharacteristicMeasurement", "24 (its item 99", "25 (its item 13 \"pitch diameter\""] {
            assert!(e.message.contains(named), "{named}: {}", e.message);
        }
        assert!(e.message.starts_with("3 measurement(s)"), "{}", e.message);
    }

    #[test]
    fn what_is_not_a_qif_results_document_says_so() {
        let e = CmmMeasurements::from_qif(b"<html><body/></html>").unwrap_err();
        assert!(e.message.contains("not a QIFDocument"), "{e}");
        let e = CmmMeasurements::from_qif(b"<QIFDocument><unclosed></QIFDocument>").unwrap_err();
        assert!(e.message.contains("not XML"), "{e}");
        let deep = format!("<QIFDocument>{}", "<a>".repeat(100));
        assert!(CmmMeasurements::from_qif(deep.as_bytes()).unwrap_err().message.contains("deeper"));
        let e = CmmMeasurements::from_qif(b"<QIFDocument xmlns=\"http://qifstandards.org/xsd/qif3\"/>").unwrap_err();
        assert!(e.message.contains("no MeasurementResults"), "{e}");
        assert_eq!(thread_in_name("Thread_12 height"), Some(12));
        assert_eq!(thread_in_name("T7"), Some(7));
        assert_eq!(thread_in_name("Taper"), None);
    }
}
