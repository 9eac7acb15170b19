//! Browsers cannot be turned against the service (issue 29): over every operation of the served
//! OpenAPI document (the router's own list, so a new route cannot be forgotten), a foreign `Host`
//! is refused, and so is a foreign `Origin` on every state-changing one; every answer carries the
//! security headers.

use super::*;
use reqwest::Method;

/// Every (method, path) of the served document, path parameters filled in.
async fn operations(app: &TestApp, id: &str) -> Vec<(Method, String)> {
    let doc: Value = app.get("/openapi.json").await.json().await.unwrap();
    let mut out = Vec::new();
    for (path, item) in doc["paths"].as_object().unwrap() {
        let path = path
            .replace("{id}", id)
            .replace("{designation}", "BC%207")
            .replace("{kind}", "height-map")
            .replace("{name}", "line-x")
            .replace("{serial}", "M-1")
            .replace("{study}", "s-1");
        assert!(!path.contains('{'), "a path parameter this test does not fill: {path}");
        for method in item.as_object().unwrap().keys() {
            out.push((Method::from_bytes(method.to_uppercase().as_bytes()).unwrap(), path.clone()));
        }
    }
    assert!(out.len() >= 17, "{} operations", out.len());
    out
}

fn assert_secured(response: &reqwest::Response, what: &str) {
    let h = response.headers();
    assert_eq!(h["x-content-type-options"], "nosniff", "{what}");
    assert_eq!(h["x-frame-options"], "DENY", "{what}");
    assert_eq!(h["referrer-policy"], "no-referrer", "{what}");
    assert!(h["content-security-policy"].to_str().unwrap().contains("frame-ancestors 'none'"), "{what}");
    assert!(h.get("access-control-allow-origin").is_none(), "{what}: no CORS by default");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn foreign_hosts_and_origins_are_refused_on_every_route() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let response = app.submit(ci_tar(), "").await;
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let id = response.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let own_origin = app.base.clone();

    for (method, path) in operations(&app, &id).await {
        let what = format!("{method} {path}");
        // DNS rebinding: the attacker's name, pointed at the loopback address.
        let response = app
            .client
            .request(method.clone(), app.url(&path))
            .header("host", "evil.example:8080")
            .send()
            .await
            .unwrap();
        assert_eq!(response.status().as_u16(), 421, "{what}");
        assert_secured(&response, &what);
        let v: Value = response.json().await.unwrap();
        assert_eq!((v["code"].as_str(), v["culprit"].as_str()), (Some("host_not_allowed"), Some("Host")), "{what}");

        let changes_state = method != Method::GET && method != Method::HEAD;
        for origin in ["http://evil.example", "null", "http://127.0.0.1:1"] {
            let response =
                app.client.request(method.clone(), app.url(&path)).header("origin", origin).send().await.unwrap();
            if changes_state {
                assert_eq!(response.status().as_u16(), 403, "{what} from {origin}");
                let v: Value = response.json().await.unwrap();
                assert_eq!(v["code"], "origin_not_allowed", "{what}: {v}");
            } else {
                assert_ne!(response.status().as_u16(), 403, "{what} from {origin}: reads are not refused by origin");
            }
        }
        if changes_state {
            let response = app
                .client
                .request(method.clone(), app.url(&path))
                .header("sec-fetch-site", "cross-site")
                .send()
                .await
                .unwrap();
            assert_eq!(response.status().as_u16(), 403, "{what} marked cross-site");
            // The service's own origin and clients that send none get past the check (to whatever
            // the route itself answers to an empty request).
            for own in [Some(own_origin.as_str()), None] {
                let mut request = app.client.request(method.clone(), app.url(&path));
                if let Some(o) = own {
                    request = request.header("origin", o);
                }
                let response = request.send().await.unwrap();
                assert_ne!(response.status().as_u16(), 403, "{what} from {own:?}");
                assert_secured(&response, &what);
            }
        }
    }
    // A read from a foreign page is answered (without CORS its page cannot see it), with the
    // security headers; the API browser's page gets its own policy.
    let response = app
        .client
        .get(app.url(&format!("/v1/inspections/{id}")))
        .header("origin", "http://evil.example")
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    assert_secured(&response, "GET inspection");
    let docs = app.get("/docs/").await;
    assert_eq!(docs.status(), StatusCode::OK);
    assert!(docs.headers()["content-security-policy"].to_str().unwrap().contains("script-src 'self'"));
    // The same cancel from the service's own origin works.
    let cancel = app
        .client
        .post(app.url(&format!("/v1/inspections/{id}/cancel")))
        .header("origin", own_origin.as_str())
        .send()
        .await
        .unwrap();
    assert_eq!(cancel.status(), StatusCode::OK);
    app.stop().await;
}

/// Listed names and origins are let in, and the listed origin gets CORS.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn listed_hosts_and_origins_are_let_in_with_cors() {
    let app = spawn_app_with(|s| {
        s.workers = 0;
        s.allowed_hosts = vec!["crestscan.plant.local".into()];
        s.allowed_origins = vec!["https://mes.plant.local".into()];
    })
    .await;
    let response =
        app.client.get(app.url("/v1/inspections")).header("host", "CrestScan.plant.local:8080").send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let response =
        app.client.get(app.url("/v1/inspections")).header("origin", "https://mes.plant.local").send().await.unwrap();
    assert_eq!(response.headers()["access-control-allow-origin"], "https://mes.plant.local");
    let preflight = app
        .client
        .request(Method::OPTIONS, app.url("/v1/inspections"))
        .header("origin", "https://mes.plant.local")
        .header("access-control-request-method", "POST")
        .send()
        .await
        .unwrap();
    assert!(preflight.status().is_success(), "{}", preflight.status());
    assert!(preflight.headers()["access-control-allow-methods"].to_str().unwrap().contains("POST"));
    let response = app.submit_from("https://mes.plant.local").await;
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let response = app.submit_from("https://other.plant.local").await;
    assert_eq!(response.status().as_u16(), 403);
    app.stop().await;
}
