//! Results: the whole round trip on the ci preset (report, threads, mesh, images, CMM comparison).

use super::*;
use crestscan::pipeline::quality::QualityCode;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn round_trip_on_the_ci_preset() {
    let app = spawn_app().await;
    let response = app.submit(ci_tar(), "?client_reference=MES-4711").await;
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let location = response.headers()["location"].to_str().unwrap().to_string();
    let created: Value = response.json().await.unwrap();
    let id = created["id"].as_str().unwrap().to_string();
    assert_eq!(location, format!("/v1/inspections/{id}"));
    assert_eq!(created["status"], "queued");
    assert_eq!(created["client_reference"], "MES-4711");
    assert_eq!(created["connection"], "BC 4-1/2");
    assert_eq!(created["bundle"]["views"], 3);

    let done = app.wait(&id, Duration::from_secs(300)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 1);
    let truth = truth();
    assert_eq!(done["verdict"], truth.verdict.as_str());
    for t in ["created_at", "started_at", "finished_at"] {
        time::OffsetDateTime::parse(done[t].as_str().unwrap(), &time::format_description::well_known::Rfc3339).unwrap();
    }

    // Report, with a strong ETag and 304 on a match.
    let response = app.get(&format!("{location}/report")).await;
    assert_eq!(response.status(), StatusCode::OK);
    let etag = response.headers()["etag"].to_str().unwrap().to_string();
    assert!(etag.starts_with('"') && !etag.starts_with("W/"));
    let report: crestscan::pipeline::report::Report = response.json().await.unwrap();
    assert_eq!(report.verdict, truth.verdict);
    // The ci bundle's three views show a sliver of the crest within Lc: the result needs review,
    // on the inspection and in its report, with the coverage among the reasons.
    assert!(report.review_required);
    assert_eq!(done["review_required"], true, "{done}");
    assert!(
        report.quality.reasons.iter().any(|r| r.message.starts_with("Only ") && r.message.contains("crest within Lc")),
        "{:?}",
        report.quality
    );
    // Its three views overlap by 1.5°, outside the envelope the accuracy figures were measured in.
    let station = report.quality.reasons.iter().find(|r| r.code == QualityCode::StationUnmeasured).unwrap();
    assert!(station.message.contains("overlap between neighbouring views 1.5"), "{}", station.message);
    assert_eq!(report.station.as_ref().unwrap().views, 3);
    // Its provenance: this inspection, its bundle's hash, the software and the settings it ran with.
    let provenance = report.provenance.as_ref().unwrap();
    assert_eq!(provenance.inspection_id.as_deref(), Some(id.as_str()));
    assert_eq!(provenance.bundle_sha256.as_deref(), created["bundle"]["sha256"].as_str());
    assert_eq!(provenance.software_version, env!("CARGO_PKG_VERSION"));
    assert_eq!(provenance.settings, crestscan::pipeline::PipelineOptions::default());
    let again =
        app.client.get(app.url(&format!("{location}/report"))).header("if-none-match", &etag).send().await.unwrap();
    assert_eq!(again.status(), StatusCode::NOT_MODIFIED);

    // The same report as a page for a person: every section, the images inline, nothing loaded
    // from anywhere, and no CMM panel before CMM data exists.
    let page = html_report(&app, &location, "").await;
    for section in ["summary", "surface", "heights", "threads-table", "black-crests", "images", "provenance"] {
        assert!(page.contains(&format!("id=\"{section}\"")), "section {section} missing");
    }
    assert!(!page.contains("id=\"cmm\""));
    assert!(page.contains(&format!("verdict: {}", truth.verdict.as_str())));
    assert!(page.contains(&id));
    assert_eq!(page.matches("src=\"data:image/png;base64,").count(), 2);
    assert!(page.contains(&format!("href=\"/v1/inspections/{id}/images/all-in-focus\"")));
    assert_eq!(page.matches("<figure><figcaption>thread ").count(), report.threads.len());
    assert_eq!(html_report(&app, &location, "?format=html").await, page);
    problem(app.get(&format!("{location}/report?format=pdf")).await, StatusCode::NOT_ACCEPTABLE, "not_acceptable")
        .await;

    // Per-thread table: JSON and CSV carry the same heights.
    let table: Value = app.get(&format!("{location}/threads")).await.json().await.unwrap();
    let threads = table["threads"].as_array().unwrap();
    assert_eq!(threads.len(), report.threads.len());
    let json_bins: usize = threads.iter().map(|t| t["heights"].as_array().unwrap().len()).sum();
    let csv =
        app.client.get(app.url(&format!("{location}/threads"))).header("accept", "text/csv").send().await.unwrap();
    assert!(csv.headers()["content-type"].to_str().unwrap().starts_with("text/csv"));
    let csv = csv.text().await.unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("thread,angle_deg,height_mm,uncertainty_mm"));
    assert_eq!(lines.count(), json_bins);
    // Each measured height with its expanded uncertainty, in the report, the CSV and the JSON table.
    let first_measured = report.threads.iter().find_map(|t| {
        let h = &t.height_mm;
        (0..h.values.len()).find_map(|k| Some((t.index, h.angles_deg[k], h.values[k]?, h.uncertainty_mm[k]?)))
    });
    let (thread, angle, height, u) = first_measured.expect("some bin measured, with its uncertainty");
    assert!(u > 0.0 && u < 0.05, "{u}");
    assert!(
        csv.contains(&format!("{thread},{angle},{height:.6},{u:.6}")),
        "CSV lacks {thread},{angle},{height:.6},{u:.6}"
    );
    let row = threads.iter().find(|t| t["thread"] == thread).unwrap();
    let bin = row["heights"].as_array().unwrap().iter().find(|b| b["angle_deg"] == angle).unwrap();
    assert_eq!(bin["uncertainty_mm"].as_f64(), Some(u));
    for t in &report.threads {
        for (v, u) in t.height_mm.values.iter().zip(&t.height_mm.uncertainty_mm) {
            assert_eq!(v.is_some(), u.is_some(), "thread {}: a height without its uncertainty or the reverse", t.index);
        }
    }
    // A sliver of crest within Lc seen: the verdict cannot be shown to hold (ISO 14253-1).
    assert_eq!(report.decision, crestscan::pipeline::uncertainty::Decision::Indeterminate);
    assert_eq!(done["decision"], "indeterminate", "{done}");
    // Weights decide, not the order the client lists them in.
    let weighted = app
        .client
        .get(app.url(&format!("{location}/threads")))
        .header("accept", "text/csv;q=0.5, application/json")
        .send()
        .await
        .unwrap();
    assert!(weighted.headers()["content-type"].to_str().unwrap().starts_with("application/json"));

    // Mesh in all three formats, images as PNG.
    let ply = app.get(&format!("{location}/mesh")).await;
    assert_eq!(ply.headers()["content-type"], "application/x-ply");
    let ply_etag = ply.headers()["etag"].clone();
    let ply = ply.bytes().await.unwrap();
    assert!(ply.starts_with(b"ply\n"));
    let stl = app.client.get(app.url(&format!("{location}/mesh"))).header("accept", "model/stl").send().await.unwrap();
    assert_eq!(stl.headers()["content-type"], "model/stl");
    let stl = stl.bytes().await.unwrap();
    let triangles = u32::from_le_bytes(stl[80..84].try_into().unwrap()) as usize;
    assert_eq!(stl.len(), 84 + 50 * triangles);
    // The GLB is made from the stored PLY: the same mesh, read back by a glTF reader.
    let glb = app.get(&format!("{location}/mesh?format=glb")).await;
    assert_eq!(glb.headers()["content-type"], "model/gltf-binary");
    let glb_etag = glb.headers()["etag"].clone();
    assert_ne!(glb_etag, ply_etag, "each representation has its own validator");
    assert!(glb.headers()["content-disposition"].to_str().unwrap().ends_with(".glb\""));
    let glb = gltf::Gltf::from_slice(&glb.bytes().await.unwrap()).unwrap();
    let blob = glb.blob.clone().unwrap();
    let primitive = glb.meshes().next().unwrap().primitives().next().unwrap();
    let reader = primitive.reader(|_| Some(&blob));
    let stored = crestscan::export::ply::read(&ply).unwrap();
    assert_eq!(reader.read_positions().unwrap().collect::<Vec<_>>(), stored.vertices);
    assert_eq!(reader.read_indices().unwrap().into_u32().count(), 3 * triangles);
    let revalidated = app
        .client
        .get(app.url(&format!("{location}/mesh")))
        .header("accept", "model/gltf-binary")
        .header("if-none-match", glb_etag)
        .send()
        .await
        .unwrap();
    assert_eq!(revalidated.status(), StatusCode::NOT_MODIFIED);
    for kind in ["height-map", "all-in-focus"] {
        let png = app.get(&format!("{location}/images/{kind}")).await;
        assert_eq!(png.headers()["content-type"], "image/png");
        let bytes = png.bytes().await.unwrap();
        let decoded = image::load_from_memory(&bytes).unwrap();
        assert!(decoded.width() > 10 && decoded.height() > 10);
    }
    problem(app.get(&format!("{location}/mesh?format=obj")).await, StatusCode::NOT_ACCEPTABLE, "not_acceptable").await;

    // CMM: the truth's heights, offset by +5 µm, at every bin crestscan measured, as the CMM's
    // CSV. crestscan − CMM is then its own error minus 5 µm: the comparison's statistics must be
    // exactly those of the listed deviations.
    let mut cmm_csv = String::from("thread,angle_deg,height_mm\n");
    for t in &report.threads {
        let truth_thread = truth.threads.iter().find(|u| u.index == t.index).expect("same numbering");
        for ((a, ours), theirs) in
            t.height_mm.angles_deg.iter().zip(&t.height_mm.values).zip(&truth_thread.height_mm.values)
        {
            if let (Some(_), Some(v)) = (ours, theirs) {
                cmm_csv.push_str(&format!("{},{a},{}\n", t.index, v + 0.005));
            }
        }
    }
    // One thread's mean, without an angle: compared with crestscan's mean of that thread.
    let mean = report.threads.iter().find(|t| t.index == thread).unwrap().mean_height_mm.unwrap();
    cmm_csv.push_str(&format!("{thread},,{}\n", mean + 0.005));
    let put = app
        .client
        .put(app.url(&format!("{location}/cmm")))
        .header("content-type", "text/csv")
        .body(cmm_csv)
        .send()
        .await
        .unwrap();
    assert_eq!(put.status(), StatusCode::OK);
    let cmp: Value = app.get(&format!("{location}/cmm-comparison")).await.json().await.unwrap();
    let devs: Vec<f64> = cmp["points"].as_array().unwrap().iter().filter_map(|p| p["deviation_mm"].as_f64()).collect();
    let agreement = &cmp["agreement"];
    assert!(devs.len() >= 10, "{cmp}");
    assert_eq!(agreement["unmatched"], 0);
    let mean_point = cmp["points"].as_array().unwrap().iter().find(|p| p["angle_deg"].is_null()).unwrap();
    assert!((mean_point["deviation_mm"].as_f64().unwrap() + 0.005).abs() < 1e-9);
    assert_eq!(agreement["compared"], devs.len());
    let bias = devs.iter().sum::<f64>() / devs.len() as f64;
    let rms = (devs.iter().map(|d| d * d).sum::<f64>() / devs.len() as f64).sqrt();
    // The answer's numbers are rounded to 0.1 µm (docs/service.md): the statistics of the rounded
    // deviations agree with the rounded statistics to that resolution.
    assert!((agreement["bias_mm"].as_f64().unwrap() - bias).abs() <= 1e-4, "{agreement} {bias}");
    assert!((agreement["rms_mm"].as_f64().unwrap() - rms).abs() <= 1e-4, "{agreement} {rms}");
    assert!(bias < -0.005 + 0.015 && bias > -0.005 - 0.015, "bias {bias}: crestscan's own error is within 15 µm");
    let [lo, hi] = [
        agreement["limits_of_agreement_mm"][0].as_f64().unwrap(),
        agreement["limits_of_agreement_mm"][1].as_f64().unwrap(),
    ];
    assert!(lo < bias && bias < hi);
    // Default tolerance: a tenth of the ±tolerance band.
    let tol = cmp["height_tolerance_mm"].as_f64().unwrap();
    assert!((agreement["tolerance_mm"].as_f64().unwrap() - 2.0 * tol / 10.0).abs() <= 1e-4);
    let strict: Value =
        app.get(&format!("{location}/cmm-comparison?tolerance_mm=0.000001")).await.json().await.unwrap();
    assert_eq!(strict["agreement"]["within_tolerance"], false);
    let loose: Value = app.get(&format!("{location}/cmm-comparison?tolerance_mm=1")).await.json().await.unwrap();
    assert_eq!(loose["agreement"]["within_tolerance"], true);
    // Issue 49: the bias and the limits with their 95% intervals (t with n − 1 degrees of freedom,
    // Bland–Altman's √(3/n) for the limits), and what limits them said in words.
    let n = devs.len() as f64;
    let sd = (devs.iter().map(|d| (d - bias).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    let t = crestscan::numeric::stats::student_t_975(devs.len() - 1);
    let ci = &agreement["bias_ci95_mm"];
    assert!((ci[0].as_f64().unwrap() - (bias - t * sd / n.sqrt())).abs() <= 2e-4, "{agreement}");
    assert!((ci[1].as_f64().unwrap() - (bias + t * sd / n.sqrt())).abs() <= 2e-4, "{agreement}");
    let loa_ci = &agreement["limits_of_agreement_ci95_mm"];
    let half = t * sd * (3.0 / n).sqrt();
    assert!(
        (loa_ci[0][1].as_f64().unwrap() - loa_ci[0][0].as_f64().unwrap() - 2.0 * half).abs() <= 3e-4,
        "{agreement}"
    );
    assert!(loa_ci[1][0].as_f64().unwrap() < hi && hi < loa_ci[1][1].as_f64().unwrap(), "{agreement}");
    // No uncertainty stated by this CMM: no Eₙ, and the warning says why.
    assert_eq!(agreement["en_points"], 0);
    assert!(
        agreement["warnings"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().contains("Eₙ")),
        "{agreement}"
    );
    // The page now shows crestscan against the CMM, with the comparison's own figures.
    let page = html_report(&app, &location, "").await;
    assert!(page.contains("id=\"cmm\""));
    assert!(page.contains(&format!("{} points compared", devs.len())));
    assert!(page.contains(&format!("bias {:+.1} µm", 1e3 * agreement["bias_mm"].as_f64().unwrap())));
    assert!(page.contains("aria-label=\"Bland–Altman\""));
    // A European export in inches, with its instrument: read as the plant wrote it, stored in mm.
    let european =
        "# instrument: Zeiss Contura\n# measured_at: 2026-11-30T10:00:00Z\nthread;angle_deg;height_in\n3;12,5;0,062\n";
    let put = app
        .client
        .put(app.url(&format!("{location}/cmm")))
        .header("content-type", "text/csv")
        .body(european)
        .send()
        .await
        .unwrap();
    assert_eq!(put.status(), StatusCode::OK);
    let stored: Value = app.get(&format!("{location}/cmm")).await.json().await.unwrap();
    assert_eq!(stored["instrument"], "Zeiss Contura");
    assert_eq!(stored["measured_at"], "2026-11-30T10:00:00Z");
    assert!((stored["points"][0]["height_mm"].as_f64().unwrap() - 0.062 * 25.4).abs() < 1e-9, "{stored}");
    assert_eq!(stored["points"][0]["angle_deg"], 12.5);
    // Each upload is kept as a version, with who sent it; the latest is compared unless asked.
    assert_eq!(stored["version"], 2);
    assert_eq!(stored["uploaded_by"], "127.0.0.1");
    let versions: Value = app.get(&format!("{location}/cmm/versions")).await.json().await.unwrap();
    let versions = versions["versions"].as_array().unwrap().clone();
    assert_eq!(versions.iter().map(|v| v["version"].as_i64().unwrap()).collect::<Vec<_>>(), [1, 2]);
    assert_eq!(versions[0]["points"].as_u64().unwrap() as usize, devs.len());
    assert_eq!(versions[0]["instrument"], Value::Null);
    assert_eq!((versions[1]["points"].as_u64(), versions[1]["instrument"].as_str()), (Some(1), Some("Zeiss Contura")));
    let first: Value = app.get(&format!("{location}/cmm?version=1")).await.json().await.unwrap();
    assert_eq!(first["points"].as_array().unwrap().len(), devs.len());
    let latest: Value = app.get(&format!("{location}/cmm-comparison")).await.json().await.unwrap();
    let (compared, unmatched) = (&latest["agreement"]["compared"], &latest["agreement"]["unmatched"]);
    assert_eq!(latest["cmm_version"], 2);
    assert_eq!(compared.as_u64().unwrap() + unmatched.as_u64().unwrap(), 1, "the one point of version 2: {latest}");
    let again: Value = app.get(&format!("{location}/cmm-comparison?version=1")).await.json().await.unwrap();
    assert_eq!(again["cmm_version"], 1);
    assert!((again["agreement"]["rms_mm"].as_f64().unwrap() - rms).abs() <= 1e-4);
    let missing =
        problem(app.get(&format!("{location}/cmm?version=3")).await, StatusCode::NOT_FOUND, "cmm_not_found").await;
    assert_eq!(missing["culprit"], "version");
    problem(app.get(&format!("{location}/cmm?version=0")).await, StatusCode::BAD_REQUEST, "invalid_query").await;
    // The one point of version 2 is too few to claim agreement from, however close.
    let one: Value = app.get(&format!("{location}/cmm-comparison?tolerance_mm=1")).await.json().await.unwrap();
    assert_eq!(one["agreement"]["within_tolerance"], false, "{one}");
    assert!(one["agreement"]["warnings"][0].as_str().unwrap().starts_with("Only "), "{one}");

    // A thread the inspection does not have is refused, naming the point and the threads there are.
    let unknown = app
        .client
        .put(app.url(&format!("{location}/cmm")))
        .header("content-type", "text/csv")
        .body(format!("thread,angle_deg,height_mm\n{thread},12,1.57\n55,12,1.57\n"))
        .send()
        .await
        .unwrap();
    let v = problem(unknown, StatusCode::UNPROCESSABLE_ENTITY, "invalid_cmm").await;
    assert_eq!(v["culprit"], "points[1].thread", "{v}");
    assert!(v["detail"].as_str().unwrap().contains("55"), "{v}");
    // With the CMM's stated uncertainty, each bin point gets its normalised error Eₙ.
    let (t0, a0, h0, u0) = report
        .threads
        .iter()
        .find_map(|t| {
            let i = t.height_mm.values.iter().position(|v| v.is_some())?;
            Some((t.index, t.height_mm.angles_deg[i], t.height_mm.values[i]?, t.height_mm.uncertainty_mm[i]?))
        })
        .expect("a measured bin with its U");
    let put = app
        .client
        .put(app.url(&format!("{location}/cmm")))
        .header("content-type", "text/csv")
        .body(format!("# uncertainty_mm: 0.002\nthread,angle_deg,height_mm\n{t0},{a0},{}\n", h0 + 0.004))
        .send()
        .await
        .unwrap();
    assert_eq!(put.status(), StatusCode::OK);
    let en: Value = app.get(&format!("{location}/cmm-comparison")).await.json().await.unwrap();
    let expected = -0.004 / (u0 * u0 + 0.002f64 * 0.002).sqrt();
    let got = en["points"][0]["en"].as_f64().unwrap();
    assert!((got - expected).abs() <= 0.01 * expected.abs().max(1.0), "Eₙ {got}, expected {expected}: {en}");
    assert_eq!(en["agreement"]["en_points"], 1);

    // The list finds it by its client reference; metrics counted the polls by route.
    let page: Value = app.get("/v1/inspections?client_reference=MES-4711&status=succeeded").await.json().await.unwrap();
    assert_eq!(page["items"].as_array().unwrap().len(), 1);
    // And by whether it needs review.
    let page: Value = app.get("/v1/inspections?review_required=true").await.json().await.unwrap();
    assert_eq!(page["items"].as_array().unwrap().len(), 1);
    assert_eq!(page["items"][0]["id"], id.as_str());
    let page: Value = app.get("/v1/inspections?review_required=false").await.json().await.unwrap();
    assert_eq!(page["items"].as_array().unwrap().len(), 0, "{page}");
    let metrics = app.get("/metrics").await.text().await.unwrap();
    assert!(metrics.contains(r#"route="/v1/inspections/{id}",status="200""#), "{metrics}");
    assert!(metrics.contains("crestscan_jobs_finished_total{outcome=\"succeeded\"} 1"), "{metrics}");
    // The result counted by its verdict and decision, and the build by its version.
    let spelled = |v: Value| v.as_str().unwrap().to_string();
    let result = format!(
        "crestscan_inspection_results_total{{verdict=\"{}\",decision=\"{}\",review_required=\"{}\"}} 1",
        spelled(serde_json::to_value(report.verdict).unwrap()),
        spelled(serde_json::to_value(report.decision).unwrap()),
        report.review_required
    );
    assert!(metrics.contains(&result), "{result} in {metrics}");
    let build = format!("crestscan_build_info{{version=\"{}\"}} 1", env!("CARGO_PKG_VERSION"));
    assert!(metrics.contains(&build), "{metrics}");
    app.stop().await;
}

/// The report as HTML (`Accept: text/html`, plus `query`): a page that loads nothing from anywhere
/// (no external URL, no script or style file), under a policy that allows no other origin.
async fn html_report(app: &TestApp, location: &str, query: &str) -> String {
    let response = app
        .client
        .get(app.url(&format!("{location}/report{query}")))
        .header("accept", "text/html")
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    assert_eq!(response.headers()["content-type"], "text/html; charset=utf-8");
    let csp = response.headers()["content-security-policy"].to_str().unwrap().to_string();
    assert!(csp.starts_with("default-src 'none'") && csp.contains("script-src 'sha256-"), "{csp}");
    let page = response.text().await.unwrap();
    assert!(page.starts_with("<!DOCTYPE html>"));
    for external in ["src=\"http", "href=\"http", "<link", "<script src", "url(http", "@import"] {
        assert!(!page.contains(external), "the page refers outside itself: {external}");
    }
    page
}
