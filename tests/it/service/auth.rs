//! API keys and scopes over real HTTP: the authorisation matrix over the router's own routes, the
//! start-up refusal, the CLI's first key, per-key submission limits and the audit log.

use super::*;
use crestscan::service::auth::Scope;

/// Every route of the OpenAPI document (the router's own list) and the pages beside it, with a
/// concrete path.
fn every_route() -> Vec<(reqwest::Method, String)> {
    let mut routes = vec![
        (reqwest::Method::GET, "/".to_string()),
        (reqwest::Method::GET, "/openapi.json".to_string()),
        (reqwest::Method::GET, "/docs/".to_string()),
    ];
    routes.extend(documented_operations().into_iter().map(|(method, _, concrete)| (method, concrete)));
    assert!(routes.len() > 20, "{routes:?}");
    routes
}

/// Every route × {no key, a wrong key, a revoked key, each scope}: only the keys whose scope the
/// route needs get past the guard (their answer is whatever the route says: 200, 404, 422, …);
/// the others get 401 (with `WWW-Authenticate`) or 403; `/healthz` and `/readyz` need no key.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_authorisation_matrix_over_every_route() {
    let app = spawn_app_with(|s| {
        s.workers = 0;
        s.auth = crestscan::service::config::AuthMode::Required;
    })
    .await;
    let store = app.store().await;
    let mut tokens = Vec::new();
    for scope in Scope::ALL {
        let (_, token) = store.create_key(&format!("{scope:?}"), &[scope]).await.unwrap();
        tokens.push((Some(scope), token));
    }
    let (revoked, revoked_token) = store.create_key("revoked", &[Scope::Admin]).await.unwrap();
    store.revoke_key(&revoked.id).await.unwrap();
    let wrong = format!("csk_{}_{}", "0".repeat(12), "0".repeat(64));
    let public = ["/healthz", "/readyz"];
    let mut checked = 0;
    for (method, path) in every_route() {
        let send = |token: Option<&str>| {
            let mut request = app.client.request(method.clone(), app.url(&path));
            if let Some(t) = token {
                request = request.bearer_auth(t);
            }
            if method != reqwest::Method::GET {
                request = request.header("content-type", "application/json").body("{}");
            }
            request.send()
        };
        for (label, token) in
            [("no key", None), ("wrong key", Some(wrong.as_str())), ("revoked key", Some(revoked_token.as_str()))]
        {
            let response = send(token).await.unwrap();
            if public.contains(&path.as_str()) {
                assert!(response.status().is_success(), "{method} {path} with {label}: {}", response.status());
                continue;
            }
            assert_eq!(response.status(), StatusCode::UNAUTHORIZED, "{method} {path} with {label}");
            assert!(response.headers()[reqwest::header::WWW_AUTHENTICATE].to_str().unwrap().starts_with("Bearer"));
            let body: Value = response.json().await.unwrap();
            let expected = if token.is_none() { "unauthorized" } else { "invalid_key" };
            assert_eq!(body["code"], expected, "{method} {path} with {label}");
        }
        let needed = if public.contains(&path.as_str()) {
            None
        } else if path.starts_with("/v1/keys") || path == "/v1/audit" || path.starts_with("/v1/webhooks") {
            Some(Scope::Admin)
        } else if method == reqwest::Method::GET {
            Some(Scope::Read)
        } else {
            Some(Scope::Submit)
        };
        for (scope, token) in &tokens {
            let response = send(Some(token)).await.unwrap();
            let status = response.status();
            let allowed = match needed {
                None => true,
                Some(n) => *scope == Some(n) || *scope == Some(Scope::Admin),
            };
            if allowed {
                assert!(
                    status != StatusCode::UNAUTHORIZED && status != StatusCode::FORBIDDEN,
                    "{method} {path} with {scope:?}: {status}"
                );
            } else {
                assert_eq!(status, StatusCode::FORBIDDEN, "{method} {path} with {scope:?}");
                let body: Value = response.json().await.unwrap();
                assert_eq!(body["code"], "insufficient_scope");
            }
            checked += 1;
        }
    }
    assert!(checked >= 60, "{checked}");
    app.stop().await;
}

/// Binding beyond loopback with auth off is refused at start-up, naming the fix; with auth
/// required it starts.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_non_loopback_bind_without_auth_is_refused_at_start_up() {
    let dir = tempfile::tempdir().unwrap();
    let mut settings = test_settings(dir.path());
    settings.bind = "0.0.0.0:0".parse().unwrap();
    let error = Application::build(settings.clone()).await.err().expect("refused");
    let message = error.to_string();
    assert!(message.contains("auth") && message.contains("0.0.0.0"), "{message}");
    settings.auth = crestscan::service::config::AuthMode::Required;
    settings.workers = 0;
    Application::build(settings).await.expect("auth required: starts");
}

/// The first key comes from the CLI (printed alone on its last line); the served binary takes it,
/// limits its submissions per minute (429 with Retry-After), and the audit log, read with an
/// admin key, says which key submitted and read what.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_cli_key_works_against_the_served_binary_and_the_audit_names_it() {
    let dir = tempfile::tempdir().unwrap();
    let create = |name: &str, scopes: &str| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_crestscan"))
            .args(["keys", "create", "--name", name, "--scopes", scopes, "--data-dir"])
            .arg(dir.path())
            .args(
                crate::common::test_database_url(dir.path())
                    .map(|url| ["--database-url".to_string(), url])
                    .iter()
                    .flatten(),
            )
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8(out.stdout).unwrap().lines().last().unwrap().to_string()
    };
    let admin = create("root", "admin");
    let mes = create("mes-line-3", "read,submit");
    assert!(admin.starts_with("csk_") && mes.starts_with("csk_") && admin != mes);
    let bad = std::process::Command::new(env!("CARGO_BIN_EXE_crestscan"))
        .args(["keys", "create", "--name", "x", "--scopes", "read,write", "--data-dir"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("write"));

    let (mut child, base) =
        start_binary(dir.path(), &["--auth", "required", "--workers", "0", "--submissions-per-minute", "2"]);
    let client = super::client();
    let list = client.get(format!("{base}/v1/inspections")).send().await.unwrap();
    assert_eq!(list.status(), StatusCode::UNAUTHORIZED);
    let list = client.get(format!("{base}/v1/inspections")).bearer_auth(&mes).send().await.unwrap();
    assert_eq!(list.status(), StatusCode::OK);
    // The scheme's name is case-insensitive (RFC 9110 §11.1).
    for scheme in ["bearer", "BEARER", "BeArEr"] {
        let list = client
            .get(format!("{base}/v1/inspections"))
            .header("authorization", format!("{scheme} {mes}"))
            .send()
            .await
            .unwrap();
        assert_eq!(list.status(), StatusCode::OK, "{scheme}");
    }
    let submit = || {
        client
            .post(format!("{base}/v1/inspections"))
            .bearer_auth(&mes)
            .header("content-type", "application/x-tar")
            .body(ci_tar())
            .send()
    };
    let first = submit().await.unwrap();
    assert_eq!(first.status(), StatusCode::ACCEPTED);
    let id = first.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    assert_eq!(submit().await.unwrap().status(), StatusCode::ACCEPTED);
    let third = submit().await.unwrap();
    assert_eq!(third.status(), StatusCode::TOO_MANY_REQUESTS);
    let wait: u64 = third.headers()["retry-after"].to_str().unwrap().parse().unwrap();
    assert!((1..=60).contains(&wait), "{wait}");
    assert_eq!(third.json::<Value>().await.unwrap()["code"], "too_many_submissions");
    let cancel = client.post(format!("{base}/v1/inspections/{id}/cancel")).bearer_auth(&mes).send().await.unwrap();
    assert_eq!(cancel.status(), StatusCode::OK);
    // The mes key cannot read the audit; the admin key can, and sees who did what.
    let audit = client.get(format!("{base}/v1/audit?target={id}")).bearer_auth(&mes).send().await.unwrap();
    assert_eq!(audit.status(), StatusCode::FORBIDDEN);
    let mut entries = Vec::new();
    for _ in 0..50 {
        let audit: Value = client
            .get(format!("{base}/v1/audit?target={id}"))
            .bearer_auth(&admin)
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        entries = audit["entries"].as_array().unwrap().clone();
        if entries.len() >= 2 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let actions: Vec<(&str, &str, i64)> = entries
        .iter()
        .map(|e| (e["action"].as_str().unwrap(), e["key_name"].as_str().unwrap(), e["status"].as_i64().unwrap()))
        .collect();
    assert_eq!(
        actions,
        [("POST /v1/inspections/{id}/cancel", "mes-line-3", 200), ("POST /v1/inspections", "mes-line-3", 202)],
        "{entries:?}"
    );
    assert_eq!(entries[0]["client"], "127.0.0.1");
    // Revoked over the API: the key stops working at once.
    let keys: Value =
        client.get(format!("{base}/v1/keys")).bearer_auth(&admin).send().await.unwrap().json().await.unwrap();
    let mes_id = keys["keys"].as_array().unwrap().iter().find(|k| k["name"] == "mes-line-3").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    assert!(!keys.to_string().contains(&mes[20..]), "no secret in the list");
    let revoked = client.delete(format!("{base}/v1/keys/{mes_id}")).bearer_auth(&admin).send().await.unwrap();
    assert_eq!(revoked.status(), StatusCode::OK);
    let list = client.get(format!("{base}/v1/inspections")).bearer_auth(&mes).send().await.unwrap();
    assert_eq!(list.status(), StatusCode::UNAUTHORIZED);
    let created = client
        .post(format!("{base}/v1/keys"))
        .bearer_auth(&admin)
        .json(&serde_json::json!({"name": "reader", "scopes": ["read"]}))
        .send()
        .await
        .unwrap();
    assert_eq!(created.status(), StatusCode::CREATED);
    let reader = created.json::<Value>().await.unwrap()["token"].as_str().unwrap().to_string();
    let list = client.get(format!("{base}/v1/inspections")).bearer_auth(&reader).send().await.unwrap();
    assert_eq!(list.status(), StatusCode::OK);
    child.kill().unwrap();
    let _ = child.wait();
}
