//! The pages in a real browser: Chromium (Debian's package; `CRESTSCAN_CHROMIUM` names another
//! binary) headless against the real binary, `crestscan serve` on a loopback port. The API
//! browser at /docs is loaded too. The dashboard lists a submitted inspection with a
//! link to its report; the report renders every section and its 3D viewer draws the inspection's
//! mesh (it reads its first frame back and marks itself `drawn`); on both the console stays empty
//! and every request the page makes goes to the service (Chromium's own network log).

use super::*;

fn chromium() -> String {
    std::env::var("CRESTSCAN_CHROMIUM").unwrap_or_else(|_| "chromium".to_string())
}

/// Loads `url` headless and returns the DOM after its scripts ran, the browser's log and its
/// network log (JSON).
pub(super) async fn browse(url: &str) -> (String, String, Value) {
    let dir = tempfile::tempdir().unwrap();
    let net_log = dir.path().join("net.json");
    let (profile, log_path, url) = (dir.path().join("profile"), net_log.clone(), url.to_string());
    // The browser runs for seconds: off the runtime's threads, which serve its requests.
    let output = tokio::task::spawn_blocking(move || {
        std::process::Command::new(chromium())
            .args([
                "--headless",
                // CI runs as root, where Chromium's sandbox cannot start.
                "--no-sandbox",
                // WebGL on the CPU: the machines have no GPU.
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--enable-logging=stderr",
                "--log-level=0",
                "--window-size=1200,2000",
                // Virtual time runs the page's timers and waits for its fetches, up to this long.
                "--virtual-time-budget=60000",
            ])
            .arg(format!("--user-data-dir={}", profile.display()))
            .arg(format!("--log-net-log={}", log_path.display()))
            .args(["--dump-dom", &url])
            .output()
            .unwrap_or_else(|e| panic!("{} could not be started ({e}): install Debian's chromium", chromium()))
    })
    .await
    .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let log: Value = serde_json::from_slice(&std::fs::read(&net_log).unwrap()).unwrap();
    (String::from_utf8(output.stdout).unwrap(), String::from_utf8_lossy(&output.stderr).into_owned(), log)
}

/// The URLs of the requests the page made: those started in its site (the browser's own traffic,
/// updates and the like, belongs to no page).
fn page_requests(net_log: &Value, site: &str) -> Vec<String> {
    let start_job = net_log["constants"]["logEventTypes"]["URL_REQUEST_START_JOB"].as_u64().unwrap();
    net_log["events"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["type"].as_u64() == Some(start_job))
        .filter(|e| {
            let p = &e["params"];
            p["initiator"].as_str().is_some_and(|i| i.contains(site))
                || p["site_for_cookies"].as_str().is_some_and(|s| s.contains(site))
        })
        .filter_map(|e| e["params"]["url"].as_str().map(str::to_string))
        .collect()
}

/// The real binary on a loopback port over a fresh data directory, killed when dropped (its
/// [`super::ServeChild`], before the directory goes).
struct Served {
    _child: super::ServeChild,
    base: String,
    _data: tempfile::TempDir,
}

fn serve_binary() -> Served {
    let data = tempfile::tempdir().unwrap();
    let (child, base) = start_binary(data.path(), &[]);
    Served { _child: child, base, _data: data }
}

/// Nothing on the page's console (no script error, no refused load: a refusal by the page's
/// policy is a console error too), and every request the page made went to `origin`; returns
/// those requests (the caller checks the one it expects is among them, so that they were seen).
pub(super) fn quiet_and_local(log: &str, net_log: &Value, origin: &str) -> Vec<String> {
    let console: Vec<&str> = log.lines().filter(|l| l.contains(":CONSOLE")).collect();
    assert!(console.is_empty(), "console: {console:#?}");
    let host = origin.trim_start_matches("http://").split(':').next().unwrap();
    let requests = page_requests(net_log, host);
    for request in &requests {
        assert!(request.starts_with(origin), "the page requested {request}, outside {origin}");
    }
    requests
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_dashboard_and_the_report_page_work_in_a_real_browser() {
    let served = serve_binary();
    let base = served.base.clone();
    let client = super::client();
    let id = submit_ci_to(&client, &base).await;
    // The long poll answers at each change of status or stage: ask again until it has ended.
    let deadline = std::time::Instant::now() + Duration::from_secs(300);
    let done = loop {
        let v: Value =
            client.get(format!("{base}/v1/inspections/{id}?wait=30s")).send().await.unwrap().json().await.unwrap();
        if v["status"] != "queued" && v["status"] != "running" {
            break v;
        }
        assert!(std::time::Instant::now() < deadline, "not finished: {v}");
    };
    assert_eq!(done["status"], "succeeded", "{done}");

    let url = format!("{base}/v1/inspections/{id}/report?format=html");
    let (dom, log, net_log) = browse(&url).await;
    for section in ["summary", "surface", "heights", "threads-table", "black-crests", "images", "viewer", "provenance"]
    {
        assert!(dom.contains(&format!("id=\"{section}\"")), "section {section} missing");
    }
    // The viewer fetched the mesh, drew it, and found its frame not blank.
    let viewer = dom.split("class=\"viewer\"").nth(1).expect("the viewer").split('>').next().unwrap().to_string();
    assert!(viewer.contains("data-state=\"drawn\""), "viewer: {viewer}");
    let triangles: usize =
        viewer.split("data-triangles=\"").nth(1).unwrap().split('"').next().unwrap().parse().unwrap();
    assert!(triangles > 1000, "{triangles}");
    // The page's requests: the page itself and its mesh, both from the service.
    let requests = quiet_and_local(&log, &net_log, &base);
    assert!(requests.iter().any(|u| u.contains("/mesh?format=glb")), "{requests:?}");

    // The dashboard lists it, with a link to that page, through the public API.
    let (dom, log, net_log) = browse(&format!("{base}/")).await;
    let listed = dom.split(&format!("data-id=\"{id}\"")).nth(1).expect("the inspection listed");
    let listed = listed.split("</tr>").next().unwrap();
    assert!(listed.contains("succeeded") && listed.contains("BC 4-1/2"), "{listed}");
    assert!(listed.contains(&format!("href=\"/v1/inspections/{id}/report?format=html\"")), "{listed}");
    let requests = quiet_and_local(&log, &net_log, &base);
    assert!(requests.iter().any(|u| u.contains("/v1/inspections?")), "{requests:?}");

    // Followed from the dashboard, the finished line shows the decision and the opening sentence
    // of the first reason for review, as the report lists them.
    let report: Value =
        client.get(format!("{base}/v1/inspections/{id}/report")).send().await.unwrap().json().await.unwrap();
    let first = report["quality"]["reasons"][0]["message"]
        .as_str()
        .or(report["decision_finding"]["reasons"][0].as_str())
        .expect("the ci bundle's result asks for review");
    let sentence = first.split(". ").next().unwrap();
    let (dom, log, net_log) = browse(&format!("{base}/#inspection={id}")).await;
    let line = dom.split("id=\"submit-status\"").nth(1).expect("the status line").split("</p>").next().unwrap();
    let decision = done["decision"].as_str().unwrap().replace('_', " ");
    assert!(line.contains(&format!("decision {decision}")), "{line}");
    assert!(line.contains("Why review: ") && line.contains(&html_escape(sentence)), "{sentence:?} not in {line}");
    quiet_and_local(&log, &net_log, &base);

    // The API browser (Swagger UI, compiled in) runs under its own policy: it lists the
    // operations from the binary's OpenAPI document, with nothing refused and nothing fetched
    // from elsewhere.
    let (dom, log, net_log) = browse(&format!("{base}/docs/")).await;
    assert!(dom.contains("opblock") && dom.contains("get_report"), "the operations are not listed");
    let requests = quiet_and_local(&log, &net_log, &base);
    assert!(requests.iter().any(|u| u.ends_with("/openapi.json")), "{requests:?}");
}

/// Text as the DOM dump writes it inside an element.
fn html_escape(text: &str) -> String {
    text.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}
