//! A station qualified over the real server: created, its master's certificate uploaded, ten
//! repositioned runs of the master inspected and studied, then a part at that station decided with
//! the station's uncertainty; a bundle of other optics named at it refused, naming the mismatch;
//! the refusals a study and a check meet, each naming its culprit; a check run charted in control;
//! a qualification that expires. The master is the `ci-reject` part (LC 4-1/2, three views),
//! placed anew for each run. Then drift: a station around the whole ring refocused after its
//! study, suspended by its first check.

use super::*;
use crestscan::sim;

/// Renders `preset` (part `seed`, placement `placement`) and returns it as a tar whose manifest
/// names `serial` and `station`.
fn run_tar(preset: &str, seed: u64, placement: u64, serial: &str, station: &str) -> (Vec<u8>, Truth) {
    placed_tar(preset, None, seed, placement, serial, station, 0.0)
}

/// As [`run_tar`], the part recorded at the simulator's station `at` (a named one), every frame
/// taken `drift_mm` further along the camera's axis than the manifest says (the station
/// refocused since its study).
fn placed_tar(
    preset: &str,
    at: Option<&str>,
    seed: u64,
    placement: u64,
    serial: &str,
    station: &str,
    drift_mm: f64,
) -> (Vec<u8>, Truth) {
    let dir = crate::common::placed(preset, at, seed, placement, drift_mm);
    let mut manifest: Value = serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    manifest["part"]["serial"] = serial.into();
    manifest["station"] = station.into();
    (bundle_tar_with_manifest(dir, &serde_json::to_vec(&manifest).unwrap()), crate::common::truth_of(dir))
}

async fn post_json(app: &TestApp, path: &str, body: Value) -> reqwest::Response {
    app.client.post(app.url(path)).json(&body).send().await.unwrap()
}

async fn put_certificate(app: &TestApp, station: &str, serial: &str, certificate: &Value) -> reqwest::Response {
    app.client
        .put(app.url(&format!("/v1/stations/{station}/masters/{serial}")))
        .header("content-type", "application/json")
        .body(serde_json::to_vec(certificate).unwrap())
        .send()
        .await
        .unwrap()
}

/// Submits `tar` and waits for it to succeed; its id.
async fn inspected(app: &TestApp, tar: Vec<u8>, query: &str) -> String {
    let created = app.submit(tar, query).await;
    assert_eq!(created.status(), StatusCode::ACCEPTED, "{}", created.text().await.unwrap());
    let id = created.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let done = app.wait(&id, Duration::from_secs(120)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    id
}

/// A webhook endpoint on loopback that keeps every event it is sent.
async fn start_hook() -> (std::sync::Arc<std::sync::Mutex<Vec<Value>>>, String) {
    let got = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let keep = got.clone();
    let app = axum::Router::new().route(
        "/hook",
        axum::routing::post(move |body: axum::body::Bytes| {
            let keep = keep.clone();
            async move {
                keep.lock().unwrap().push(serde_json::from_slice::<Value>(&body).unwrap_or(Value::Null));
                axum::http::StatusCode::OK
            }
        }),
    );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}/hook", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    (got, url)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_qualified_station_decides_with_its_own_uncertainty() {
    let app = spawn_app().await;
    let created =
        post_json(&app, "/v1/stations", serde_json::json!({"name": "line-1", "description": "ci optics"})).await;
    assert_eq!(created.status(), StatusCode::CREATED);
    assert_eq!(created.headers()["location"], "/v1/stations/line-1");
    let station: Value = created.json().await.unwrap();
    assert_eq!(station["status"], "unqualified");
    problem(
        post_json(&app, "/v1/stations", serde_json::json!({"name": "line-1"})).await,
        StatusCode::CONFLICT,
        "station_exists",
    )
    .await;
    let bad = problem(
        post_json(&app, "/v1/stations", serde_json::json!({"name": "line 1/a"})).await,
        StatusCode::UNPROCESSABLE_ENTITY,
        "invalid_option",
    )
    .await;
    assert_eq!(bad["culprit"], "name");

    // The master's certificate, from its truth with 2 µm (k = 2) of calibration noise.
    let (first, truth) = run_tar("ci-reject", 7, 101, "M-1", "line-1");
    let certificate = sim::certificate(&truth, 0.002, 7);
    assert_eq!(put_certificate(&app, "line-1", "M-1", &certificate).await.status(), StatusCode::CREATED);
    let twice =
        problem(put_certificate(&app, "line-1", "M-1", &certificate).await, StatusCode::CONFLICT, "master_exists")
            .await;
    assert_eq!(twice["culprit"], "serial");
    let mut unstated = certificate.clone();
    unstated.as_object_mut().unwrap().remove("uncertainty_mm");
    let refused = problem(
        put_certificate(&app, "line-1", "M-2", &unstated).await,
        StatusCode::UNPROCESSABLE_ENTITY,
        "invalid_certificate",
    )
    .await;
    assert_eq!(refused["culprit"], "points[0].uncertainty_mm");

    // Ten runs, each placed anew (encoders and sensor noise), the same part.
    let mut runs = vec![inspected(&app, first.clone(), "").await];
    for placement in 102..=110 {
        runs.push(inspected(&app, run_tar("ci-reject", 7, placement, "M-1", "line-1").0, "").await);
    }
    let listed: Value = app.get("/v1/inspections?station=line-1&limit=200").await.json().await.unwrap();
    assert_eq!(listed["items"].as_array().unwrap().len(), 10);

    let too_few = problem(
        post_json(&app, "/v1/stations/line-1/studies", serde_json::json!({"inspections": runs[..9]})).await,
        StatusCode::UNPROCESSABLE_ENTITY,
        "study_refused",
    )
    .await;
    assert_eq!(too_few["culprit"], "masters.M-1", "{too_few}");
    assert!(too_few["detail"].as_str().unwrap().contains("9 runs"), "{too_few}");

    let studied = post_json(&app, "/v1/stations/line-1/studies", serde_json::json!({"inspections": runs})).await;
    assert_eq!(studied.status(), StatusCode::CREATED);
    let study: Value = studied.json().await.unwrap();
    let study_id = study["id"].as_str().unwrap().to_string();
    let q = &study["qualification"];
    assert_eq!(q["masters"][0]["runs"], 10);
    assert!(q["uncertainty"]["u_p_um"].as_f64().unwrap() > 0.0, "{q}");
    assert!(q["gauge"]["cg_min"].as_f64().is_some(), "{q}");
    let station: Value = app.get("/v1/stations/line-1").await.json().await.unwrap();
    assert_eq!((station["status"].as_str(), station["study"].as_str()), (Some("qualified"), Some(study_id.as_str())));
    let fetched: Value = app.get(&format!("/v1/stations/line-1/studies/{study_id}")).await.json().await.unwrap();
    assert_eq!(fetched["qualification"], study["qualification"]);

    // Another part of the master's design (another texture and placement), named by the
    // submission: corrected and decided with the station's uncertainty, its report naming both.
    let (part, part_truth) = run_tar("ci-reject", 8, 208, "P-8", "line-1");
    let id = inspected(&app, part, "?station=line-1").await;
    let id_of_part = id.clone();
    let report: Value = app.get(&format!("/v1/inspections/{id}/report")).await.json().await.unwrap();
    assert_eq!(report["qualification"]["applied"], true, "{}", report["qualification"]);
    assert_eq!(report["qualification"]["study"], study_id.as_str());
    assert_eq!(report["station"]["qualified_by"], study_id.as_str());
    let combined = q["uncertainty"]["combined_um"].as_f64().unwrap();
    assert!(
        (report["uncertainty"]["method_um"].as_f64().unwrap() - combined).abs() < 0.01,
        "{}",
        report["uncertainty"]
    );
    assert!(report["quality"]["reasons"].as_array().unwrap().iter().all(|r| r["code"] != "station_unmeasured"));
    assert_eq!(report["verdict"], serde_json::to_value(part_truth.verdict).unwrap());
    assert_ne!(report["decision"], "conforms", "the truth is reject");

    // The station's page, in a real browser: its sections drawn, nothing refused, nothing fetched
    // from elsewhere; the part's report page links to it, and so does the dashboard's row.
    let (dom, log, net_log) = super::report_page::browse(&app.url("/v1/stations/line-1?format=html")).await;
    for section in ["summary", "masters", "fingerprint", "uncertainty", "gauge", "bias-plot", "thread-gauge"] {
        assert!(dom.contains(&format!("id=\"{section}\"")), "section {section} missing");
    }
    assert!(dom.contains(&study_id), "the page names the study");
    let unknown_format =
        problem(app.get("/v1/stations/line-1?format=xml").await, StatusCode::NOT_ACCEPTABLE, "not_acceptable").await;
    assert_eq!(unknown_format["culprit"], "format");
    super::report_page::quiet_and_local(&log, &net_log, &app.base);
    let report_page = app
        .client
        .get(app.url(&format!("/v1/inspections/{id}/report?format=html")))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(report_page.contains("href=\"/v1/stations/line-1?format=html\""), "the report links its station");
    let (dom, _, _) = super::report_page::browse(&app.url("/")).await;
    let row = dom.split(&format!("data-id=\"{id}\"")).nth(1).expect("the part listed").split("</tr>").next().unwrap();
    assert!(row.contains("href=\"/v1/stations/line-1?format=html\""), "{row}");

    // Other optics named at this station: refused, naming the object pixel, and not decided.
    let telecentric = bundle_tar(crate::common::rendered("ci-telecentric"), &|_| true);
    let id = inspected(&app, telecentric, "?station=line-1").await;
    let report: Value = app.get(&format!("/v1/inspections/{id}/report")).await.json().await.unwrap();
    let refusal = report["qualification"]["refused"].as_str().unwrap();
    assert!(refusal.contains("object pixel"), "{refusal}");
    assert_eq!(report["decision"], "indeterminate");
    assert!(report["quality"]["reasons"].as_array().unwrap().iter().any(|r| r["code"] == "station_not_qualified"));
    // An unknown station is refused at submission.
    let unknown =
        problem(app.submit(ci_tar(), "?station=line-9").await, StatusCode::UNPROCESSABLE_ENTITY, "unknown_station")
            .await;
    assert_eq!(unknown["culprit"], "station");

    // Drift control. The study set the master's chart limits; nothing is charted yet.
    let chart: Value = app.get("/v1/stations/line-1/checks").await.json().await.unwrap();
    assert_eq!(chart["study"], study_id.as_str());
    let limits = chart["limits"].as_array().unwrap();
    assert!(limits.iter().any(|l| l["master"] == "M-1" && l["statistic"] == "height_bias"), "{chart}");
    assert!(chart["items"].as_array().unwrap().is_empty());
    // A check run of the master as it was studied: charted, in control, the station qualified.
    let clean = inspected(&app, run_tar("ci-reject", 7, 111, "M-1", "line-1").0, "").await;
    let charted = post_json(&app, "/v1/stations/line-1/checks", serde_json::json!({"inspection": clean})).await;
    assert_eq!(charted.status(), StatusCode::CREATED);
    let outcome: Value = charted.json().await.unwrap();
    assert_eq!((outcome["suspended"].as_bool(), outcome["station_status"].as_str()), (Some(false), Some("qualified")));
    assert!(outcome["check"]["violation"].is_null(), "{outcome}");
    let bias = outcome["check"]["points"].as_array().unwrap().iter().find(|p| p["statistic"] == "height_bias").unwrap();
    assert!(bias["z"].as_f64().unwrap().abs() < 3.0, "{bias}");
    let twice = problem(
        post_json(&app, "/v1/stations/line-1/checks", serde_json::json!({"inspection": clean})).await,
        StatusCode::CONFLICT,
        "check_exists",
    )
    .await;
    assert_eq!(twice["culprit"], "inspection");
    for not_a_check in [&runs[0], &id_of_part] {
        let refused = problem(
            post_json(&app, "/v1/stations/line-1/checks", serde_json::json!({"inspection": not_a_check})).await,
            StatusCode::UNPROCESSABLE_ENTITY,
            "check_refused",
        )
        .await;
        assert_eq!(refused["culprit"], "inspection", "{refused}");
    }

    // A qualification that expires: refused in the past, and read `suspended` once it has passed.
    let study_until = |until: String| {
        post_json(&app, "/v1/stations/line-1/studies", serde_json::json!({"inspections": runs, "valid_until": until}))
    };
    let past =
        problem(study_until("2026-01-01T00:00:00Z".into()).await, StatusCode::UNPROCESSABLE_ENTITY, "study_refused")
            .await;
    assert_eq!(past["culprit"], "valid_until");
    let expires_ms = crestscan::service::store::now_ms() + 6000;
    assert_eq!(study_until(crestscan::service::wire::rfc3339(expires_ms)).await.status(), StatusCode::CREATED);
    let station: Value = app.get("/v1/stations/line-1").await.json().await.unwrap();
    assert_eq!(station["status"], "qualified");
    let left_ms = expires_ms + 500 - crestscan::service::store::now_ms();
    tokio::time::sleep(Duration::from_millis(left_ms.max(0) as u64)).await;
    let station: Value = app.get("/v1/stations/line-1").await.json().await.unwrap();
    assert_eq!(station["status"], "suspended");
    assert!(station["status_reason"].as_str().unwrap().contains("expired"), "{station}");
    let id = inspected(&app, run_tar("ci-reject", 8, 210, "P-8", "line-1").0, "?station=line-1").await;
    let report: Value = app.get(&format!("/v1/inspections/{id}/report")).await.json().await.unwrap();
    assert!(report["qualification"]["refused"].as_str().unwrap().contains("expired"), "{}", report["qualification"]);

    // A certificate naming threads the runs do not have: the study names the master.
    assert_eq!(
        post_json(&app, "/v1/stations", serde_json::json!({"name": "line-2"})).await.status(),
        StatusCode::CREATED
    );
    let mut with_55 = certificate.clone();
    with_55["points"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"thread": 55, "angle_deg": 0.5, "height_mm": 1.8}));
    assert_eq!(put_certificate(&app, "line-2", "M-1", &with_55).await.status(), StatusCode::CREATED);
    let mut at_two = Vec::new();
    for placement in 101..=110 {
        at_two.push(inspected(&app, run_tar("ci-reject", 7, placement, "M-1", "line-2").0, "").await);
    }
    let unknown_threads = problem(
        post_json(&app, "/v1/stations/line-2/studies", serde_json::json!({"inspections": at_two})).await,
        StatusCode::UNPROCESSABLE_ENTITY,
        "study_refused",
    )
    .await;
    assert_eq!(unknown_threads["culprit"], "masters.M-1");
    assert!(unknown_threads["detail"].as_str().unwrap().contains("55"), "{unknown_threads}");
    // A run recorded at another station is refused, naming it.
    let elsewhere = problem(
        post_json(&app, "/v1/stations/line-2/studies", serde_json::json!({"inspections": [runs[0]]})).await,
        StatusCode::UNPROCESSABLE_ENTITY,
        "study_refused",
    )
    .await;
    assert_eq!(elsewhere["culprit"], "inspections[0]");
    app.stop().await;
}

/// Drift control at a whole-ring station (the master, ci-reject's part, recorded at
/// `coarse-survey`: 16 views around, where the crest cone places the surface to ~25 µm): ten study
/// runs, then the station refocused by 0.2 mm. Its first check breaks rule 1 on the crest-cone
/// radius, which suspends the station, tells the webhook endpoint and stops its decisions; the
/// page draws the chart; a new study lifts the suspension and starts a new chart. (A 3-view sector
/// cannot tell a refocus from the part placed further off: docs/benchmark.md, Drift control.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refocused_station_is_suspended_by_its_check() {
    let (hooked, hook_url) = start_hook().await;
    let app = spawn_app_with(|s| {
        s.webhooks = vec![crestscan::service::webhooks::EndpointSettings {
            name: "quality".into(),
            url: hook_url,
            secrets: vec!["whsec_MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw".into()],
            events: vec![crestscan::service::webhooks::EventType::StationSuspended],
        }]
    })
    .await;
    let ring = |placement: u64, drift_mm: f64| {
        placed_tar("ci-reject", Some("coarse-survey"), 7, placement, "M-R", "ring-1", drift_mm)
    };
    assert_eq!(
        post_json(&app, "/v1/stations", serde_json::json!({"name": "ring-1"})).await.status(),
        StatusCode::CREATED
    );
    let (first, truth) = ring(101, 0.0);
    let certificate = sim::certificate(&truth, 0.002, 7);
    assert_eq!(put_certificate(&app, "ring-1", "M-R", &certificate).await.status(), StatusCode::CREATED);
    let mut runs = vec![inspected(&app, first, "").await];
    for placement in 102..=110 {
        runs.push(inspected(&app, ring(placement, 0.0).0, "").await);
    }
    let studied = post_json(&app, "/v1/stations/ring-1/studies", serde_json::json!({"inspections": runs})).await;
    let status = studied.status();
    let study: Value = studied.json().await.unwrap();
    assert_eq!(status, StatusCode::CREATED, "{study}");
    let study_id = study["id"].as_str().unwrap().to_string();
    let chart: Value = app.get("/v1/stations/ring-1/checks").await.json().await.unwrap();
    let radius = chart["limits"].as_array().unwrap().iter().find(|l| l["statistic"] == "crest_cone_radius").unwrap();
    assert_eq!(radius["charted"], true, "the whole ring places the cone: {radius}");

    let drifted = inspected(&app, ring(121, 0.2).0, "").await;
    let outcome: Value = post_json(&app, "/v1/stations/ring-1/checks", serde_json::json!({"inspection": drifted}))
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(outcome["suspended"], true, "{outcome}");
    let violation = &outcome["check"]["violation"];
    assert_eq!(
        (violation["rule_number"].as_u64(), violation["statistic"].as_str()),
        (Some(1), Some("crest_cone_radius")),
        "{violation}"
    );
    assert!(outcome["status_reason"].as_str().unwrap().contains("Western Electric rule 1"), "{outcome}");
    let station: Value = app.get("/v1/stations/ring-1").await.json().await.unwrap();
    assert_eq!(station["status"], "suspended");
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let event = loop {
        if let Some(e) = hooked.lock().unwrap().iter().find(|e| e["type"] == "station.suspended").cloned() {
            break e;
        }
        assert!(std::time::Instant::now() < deadline, "no station.suspended webhook");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(event["data"]["station"], "ring-1");
    assert_eq!(event["data"]["study"], study_id.as_str());
    assert_eq!(event["data"]["inspection"], drifted.as_str());
    assert_eq!(event["data"]["violation"]["master"], "M-R");
    // Its decisions stop: any bundle named at it is refused the qualification.
    let id = inspected(&app, ci_tar(), "?station=ring-1").await;
    let report: Value = app.get(&format!("/v1/inspections/{id}/report")).await.json().await.unwrap();
    assert!(report["qualification"]["refused"].as_str().unwrap().contains("suspended"), "{}", report["qualification"]);
    assert_eq!(report["decision"], "indeterminate");
    // The page draws the chart, the breaking check in red.
    let (dom, log, net_log) = super::report_page::browse(&app.url("/v1/stations/ring-1?format=html")).await;
    assert!(dom.contains("id=\"control-chart\""), "the page has no control chart");
    assert!(dom.contains("class=\"check violation\""), "the page does not mark the check that broke a rule");
    super::report_page::quiet_and_local(&log, &net_log, &app.base);
    // Requalification lifts the suspension and starts a new chart.
    let restudied = post_json(&app, "/v1/stations/ring-1/studies", serde_json::json!({"inspections": runs})).await;
    assert_eq!(restudied.status(), StatusCode::CREATED);
    let station: Value = app.get("/v1/stations/ring-1").await.json().await.unwrap();
    assert_eq!(station["status"], "qualified");
    let chart: Value = app.get("/v1/stations/ring-1/checks").await.json().await.unwrap();
    assert!(chart["items"].as_array().unwrap().is_empty(), "{chart}");
    app.stop().await;
}
