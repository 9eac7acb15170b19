//! The shop floor's languages: the results as a QIF 3.0 document, and CMM results read from one.

use super::*;

/// Every element of a document: its local name, its attributes, its text, its children.
struct Element {
    name: String,
    attributes: Vec<(String, String)>,
    text: String,
    children: Vec<Element>,
}

impl Element {
    fn parse(xml: &str) -> Element {
        use quick_xml::events::Event;
        let mut reader = quick_xml::Reader::from_str(xml);
        reader.config_mut().trim_text(true);
        let mut stack: Vec<Element> = vec![Element::new("#document".into(), Vec::new())];
        loop {
            match reader.read_event().expect("well-formed XML") {
                Event::Start(e) => stack.push(Element::from_start(&e)),
                Event::Empty(e) => {
                    let element = Element::from_start(&e);
                    stack.last_mut().unwrap().children.push(element);
                }
                Event::End(_) => {
                    let done = stack.pop().unwrap();
                    stack.last_mut().unwrap().children.push(done);
                }
                Event::Text(t) => stack.last_mut().unwrap().text.push_str(&t.xml_content().unwrap()),
                Event::Eof => break,
                _ => {}
            }
        }
        assert_eq!(stack.len(), 1, "every element closed");
        stack.pop().unwrap().children.pop().expect("a root element")
    }

    fn new(name: String, attributes: Vec<(String, String)>) -> Element {
        Element { name, attributes, text: String::new(), children: Vec::new() }
    }

    fn from_start(e: &quick_xml::events::BytesStart) -> Element {
        let attributes = e
            .attributes()
            .map(|a| {
                let a = a.unwrap();
                (String::from_utf8_lossy(a.key.as_ref()).into_owned(), a.unescape_value().unwrap().into_owned())
            })
            .collect();
        Element::new(String::from_utf8_lossy(e.local_name().as_ref()).into_owned(), attributes)
    }

    fn attribute(&self, name: &str) -> Option<&str> {
        self.attributes.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }

    fn child(&self, name: &str) -> Option<&Element> {
        self.children.iter().find(|c| c.name == name)
    }

    fn path(&self, path: &[&str]) -> &Element {
        path.iter().fold(self, |at, name| at.child(name).unwrap_or_else(|| panic!("no {name} under {}", at.name)))
    }

    fn walk<'a>(&'a self, out: &mut Vec<&'a Element>) {
        out.push(self);
        for c in &self.children {
            c.walk(out);
        }
    }

    /// A user attribute (`Attributes/Attribute*[@name]`).
    fn user(&self, name: &str) -> Option<&str> {
        self.child("Attributes")?.children.iter().find(|a| a.attribute("name") == Some(name))?.attribute("value")
    }
}

/// The rules of QIF 3.0 that its schema's keys and keyrefs state (and the `n` counts and `idMax`
/// its documentation asks for), checked on a document.
fn check_qif_rules(doc: &Element) {
    let mut all = Vec::new();
    doc.walk(&mut all);
    let mut ids = std::collections::HashMap::new();
    for e in &all {
        if let Some(id) = e.attribute("id") {
            let n: u64 = id.parse().expect("ids are positive integers");
            assert!(n >= 1);
            assert!(ids.insert(n, e.name.as_str()).is_none(), "id {id} used twice");
        }
        if let Some(n) = e.attribute("n") {
            assert_eq!(n.parse::<usize>().unwrap(), e.children.len(), "{}'s n", e.name);
            assert!(!e.children.is_empty(), "{}: an empty list", e.name);
        }
    }
    let id_max: u64 = doc.attribute("idMax").unwrap().parse().unwrap();
    assert_eq!(ids.keys().max().copied(), Some(id_max), "idMax is the largest id");
    // Each measurement points at an item of its own type, each item at a nominal, each nominal at a
    // definition (QIF's *ToItemKeyref, *ItemToNominalKeyref, *NominalToDefinitionKeyref).
    let refers = |e: &Element, child: &str, suffix: &str| {
        let target: u64 = e.child(child).unwrap_or_else(|| panic!("{} lacks {child}", e.name)).text.parse().unwrap();
        let prefix = e.name.split("Characteristic").next().unwrap();
        assert_eq!(ids.get(&target).copied(), Some(format!("{prefix}Characteristic{suffix}").as_str()), "{}", e.name);
    };
    for e in &all {
        if e.name.ends_with("CharacteristicMeasurement") {
            refers(e, "CharacteristicItemId", "Item");
        } else if e.name.ends_with("CharacteristicItem") {
            refers(e, "CharacteristicNominalId", "Nominal");
        } else if e.name.ends_with("CharacteristicNominal") {
            refers(e, "CharacteristicDefinitionId", "Definition");
        }
        if e.name == "MeasurementDeviceIds" {
            for id in &e.children {
                assert_eq!(ids.get(&id.text.parse::<u64>().unwrap()).copied(), Some("MeasurementDevice"));
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_report_is_a_qif_document_and_qif_cmm_results_compare_as_their_csv_twin() {
    let app = spawn_app().await;
    let created = app.submit(ci_tar(), "").await;
    assert_eq!(created.status(), StatusCode::ACCEPTED);
    let id = created.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let done = app.wait(&id, Duration::from_secs(120)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let location = format!("/v1/inspections/{id}");
    let report: crestscan::pipeline::report::Report =
        app.get(&format!("{location}/report")).await.json().await.unwrap();

    // The results as QIF, by the query and by Accept alike; cached by its own ETag.
    let qif = app.get(&format!("{location}/report?format=qif")).await;
    assert_eq!(qif.status(), StatusCode::OK);
    assert_eq!(qif.headers()["content-type"], "application/qif+xml");
    let etag = qif.headers()["etag"].to_str().unwrap().to_string();
    let text = qif.text().await.unwrap();
    let by_accept = app
        .client
        .get(app.url(&format!("{location}/report")))
        .header("accept", "application/qif+xml")
        .send()
        .await
        .unwrap();
    assert_eq!(by_accept.text().await.unwrap(), text, "the same document either way");
    let json_etag = app.get(&format!("{location}/report")).await.headers()["etag"].to_str().unwrap().to_string();
    assert_ne!(etag, json_etag, "the QIF has an ETag of its own");
    let again = app
        .client
        .get(app.url(&format!("{location}/report?format=qif")))
        .header("if-none-match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(again.status(), StatusCode::NOT_MODIFIED);

    let doc = Element::parse(&text);
    assert_eq!(doc.name, "QIFDocument");
    assert_eq!(doc.attribute("xmlns"), Some("http://qifstandards.org/xsd/qif3"));
    assert_eq!(doc.attribute("versionQIF"), Some("3.0.0"));
    assert_eq!(doc.path(&["QPId"]).text, id, "the document's persistent id is the inspection's");
    check_qif_rules(&doc);
    // What it says: the decision, the traceability, the heights with their uncertainty.
    let results = doc.path(&["Results", "MeasurementResultsSet", "MeasurementResults"]);
    assert_eq!(results.user("decision_iso14253_1"), Some(report.decision.as_str()));
    assert_eq!(results.user("api5b_verdict"), Some(report.verdict.as_str()));
    let upload = app.get(&location).await.json::<Value>().await.unwrap();
    assert_eq!(results.user("bundle_sha256"), upload["bundle"]["sha256"].as_str(), "{upload}");
    assert_eq!(results.path(&["InspectionTraceability", "ReportNumber"]).text, id);
    let status = results.path(&["InspectionStatus"]);
    match report.decision.as_str() {
        "conforms" => assert_eq!(status.path(&["InspectionStatusEnum"]).text, "PASS"),
        "does_not_conform" => assert_eq!(status.path(&["InspectionStatusEnum"]).text, "FAIL"),
        _ => assert_eq!(status.path(&["OtherInspectionStatus"]).text, "INDETERMINATE"),
    }
    let definition = doc.path(&["Characteristics", "CharacteristicDefinitions", "HeightCharacteristicDefinition"]);
    let tolerance: f64 = definition.path(&["Tolerance", "MaxValue"]).text.parse().unwrap();
    assert!((tolerance - report.height_tolerance_mm).abs() < 1e-6);
    let nominal = doc.path(&["Characteristics", "CharacteristicNominals", "HeightCharacteristicNominal"]);
    assert!((nominal.path(&["TargetValue"]).text.parse::<f64>().unwrap() - report.nominal_height_mm).abs() < 1e-6);
    let measurements = &results.path(&["MeasuredCharacteristics", "CharacteristicMeasurements"]).children;
    let bins: Vec<&Element> = measurements.iter().filter(|m| m.user("angle_deg").is_some()).collect();
    let measured: usize = report.threads.iter().map(|t| t.height_mm.values.iter().flatten().count()).sum();
    assert_eq!(bins.len(), measured, "every measured bin");
    assert_eq!(measurements.len(), measured + 2 * report.threads.len(), "a mean and a black crest per thread");
    let with_mean: Vec<_> = report.threads.iter().filter(|t| t.mean_height_mm.is_some()).collect();
    let thread = with_mean[with_mean.len() / 2];
    let k = thread.height_mm.values.iter().position(Option::is_some).unwrap();
    let angle = thread.height_mm.angles_deg[k];
    let bin = bins
        .iter()
        .find(|m| {
            m.user("thread") == Some(&thread.index.to_string())
                && (m.user("angle_deg").unwrap().parse::<f64>().unwrap() - angle).abs() < 1e-6
        })
        .expect("the bin's measurement");
    let value = bin.path(&["Value"]);
    assert!((value.text.parse::<f64>().unwrap() - thread.height_mm.values[k].unwrap()).abs() < 1e-6);
    if let Some(u) = thread.height_mm.uncertainty_mm[k] {
        let combined: f64 = value.attribute("combinedUncertainty").unwrap().parse().unwrap();
        assert!((2.0 * combined - u).abs() < 2e-6, "u = U / 2");
    }

    // CMM results: the same points as CSV and as a QIF export; the comparisons must agree.
    let mut points = Vec::new();
    for t in &report.threads {
        for (a, v) in t.height_mm.angles_deg.iter().zip(&t.height_mm.values).step_by(7) {
            if let Some(v) = v {
                points.push((t.index, Some(*a), v + 0.004));
            }
        }
    }
    points.push((thread.index, None, thread.mean_height_mm.unwrap() - 0.002));
    let mut csv = String::from("# instrument: Contura G2\nthread,angle_deg,height_mm,uncertainty_mm\n");
    for (t, a, h) in &points {
        csv.push_str(&format!("{t},{},{h},0.0024\n", a.map(|a| a.to_string()).unwrap_or_default()));
    }
    let put = |body: String, content_type: &'static str| {
        app.client.put(app.url(&format!("{location}/cmm"))).header("content-type", content_type).body(body).send()
    };
    assert_eq!(put(csv, "text/csv").await.unwrap().status(), StatusCode::OK);
    let from_csv: Value = app.get(&format!("{location}/cmm-comparison")).await.json().await.unwrap();

    // As a CMM's software writes it, in inches: one item per thread, its name the thread.
    let threads: std::collections::BTreeSet<u32> = points.iter().map(|p| p.0).collect();
    let item_of = |t: u32| 100 + t;
    let mut items = String::new();
    for t in &threads {
        items.push_str(&format!(
            "<HeightCharacteristicItem id=\"{}\"><Name>Thread_{t} height</Name><CharacteristicNominalId>3</CharacteristicNominalId></HeightCharacteristicItem>",
            item_of(*t)
        ));
    }
    let mut measured = String::new();
    for (k, (t, a, h)) in points.iter().enumerate() {
        let angle = a
            .map(|a| format!("<Attributes n=\"1\"><AttributeD1 name=\"angle_deg\" value=\"{a}\"/></Attributes>"))
            .unwrap_or_default();
        measured.push_str(&format!(
            "<HeightCharacteristicMeasurement id=\"{}\">{angle}<Status><CharacteristicStatusEnum>PASS</CharacteristicStatusEnum></Status><CharacteristicItemId>{}</CharacteristicItemId><Value combinedUncertainty=\"{}\" meanError=\"0\">{}</Value></HeightCharacteristicMeasurement>",
            1000 + k,
            item_of(*t),
            0.0012 / 25.4,
            h / 25.4
        ));
    }
    let qif_cmm = format!(
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<QIFDocument xmlns=\"http://qifstandards.org/xsd/qif3\" versionQIF=\"3.0.0\" idMax=\"9999\">\
         <QPId>6f1d3c1e-7d43-4c0e-9a55-1b0f3f2a9c10</QPId>\
         <FileUnits><PrimaryUnits><LinearUnit><SIUnitName>meter</SIUnitName><UnitName>inch</UnitName><UnitConversion><Factor>0.0254</Factor></UnitConversion></LinearUnit></PrimaryUnits></FileUnits>\
         <MeasurementResources><MeasurementDevices n=\"1\"><MeasurementDevice id=\"1\"><Name>Contura G2</Name></MeasurementDevice></MeasurementDevices></MeasurementResources>\
         <Characteristics><FormalStandardId>2</FormalStandardId>\
         <CharacteristicItems n=\"{}\">{items}</CharacteristicItems></Characteristics>\
         <Results><MeasurementResultsSet n=\"1\"><MeasurementResults id=\"4\">\
         <MeasuredCharacteristics><CharacteristicMeasurements n=\"{}\">{measured}</CharacteristicMeasurements></MeasuredCharacteristics>\
         <InspectionStatus><InspectionStatusEnum>PASS</InspectionStatusEnum></InspectionStatus></MeasurementResults></MeasurementResultsSet></Results>\
         </QIFDocument>",
        threads.len(),
        points.len()
    );
    let stored = put(qif_cmm.clone(), "application/qif+xml").await.unwrap();
    assert_eq!(stored.status(), StatusCode::OK);
    let stored: Value = stored.json().await.unwrap();
    assert_eq!(stored["version"], 2);
    assert_eq!(stored["instrument"], "Contura G2");
    let from_qif: Value = app.get(&format!("{location}/cmm-comparison")).await.json().await.unwrap();
    assert_eq!(from_qif["points"].as_array().unwrap().len(), points.len());
    assert_eq!(from_qif["points"], from_csv["points"], "the same points, deviations and Eₙ");
    assert_eq!(from_qif["agreement"], from_csv["agreement"], "the same figures");

    // What cannot be mapped is refused by id: another characteristic, an item naming no thread.
    let refused = qif_cmm.replacen(&format!("<Name>Thread_{} height", thread.index), "<Name>Flank angle", 1).replacen(
        "<HeightCharacteristicMeasurement id=\"1000\">",
        "<LengthCharacteristicMeasurement id=\"1000\">",
        1,
    );
    let refused =
        refused.replacen("</Value></HeightCharacteristicMeasurement>", "</Value></LengthCharacteristicMeasurement>", 1);
    let v =
        problem(put(refused, "application/qif+xml").await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_cmm")
            .await;
    let detail = v["detail"].as_str().unwrap();
    assert!(detail.contains("1000 (LengthCharacteristicMeasurement"), "{detail}");
    assert!(detail.contains("names no thread"), "{detail}");
    assert_eq!(v["culprit"], "CharacteristicMeasurements", "{v}");
    // Another media type: the answer names the three that are taken.
    let v = problem(
        put("x".into(), "application/pdf").await.unwrap(),
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_media_type",
    )
    .await;
    assert!(v["detail"].as_str().unwrap().contains("application/qif+xml"), "{v}");
    app.stop().await;
}
