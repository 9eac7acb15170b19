//! Inspections: submit, validate, idempotency, cancel, list.

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_get_their_problem_codes_and_store_nothing() {
    // No workers: this is about the API alone.
    let app = spawn_app_with(|s| s.workers = 0).await;
    let post = |ct: &'static str, body: Vec<u8>| {
        app.client.post(app.url("/v1/inspections")).header("content-type", ct).body(body).send()
    };
    problem(
        post("application/json", b"{}".to_vec()).await.unwrap(),
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_media_type",
    )
    .await;
    problem(post("application/zip", Vec::new()).await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_archive")
        .await;
    problem(
        post("application/zip", b"not a zip at all".to_vec()).await.unwrap(),
        StatusCode::UNPROCESSABLE_ENTITY,
        "invalid_archive",
    )
    .await;
    // A frame missing from the archive: named.
    let files: Vec<String> =
        walk(ci_bundle()).iter().map(|p| p.strip_prefix(ci_bundle()).unwrap().to_string_lossy().into_owned()).collect();
    let victim = files.iter().find(|f| f.ends_with(".png")).unwrap().clone();
    let missing_victim = bundle_tar(ci_bundle(), &|rel| rel != victim);
    let v = problem(
        post("application/x-tar", missing_victim).await.unwrap(),
        StatusCode::UNPROCESSABLE_ENTITY,
        "missing_file",
    )
    .await;
    assert_eq!(v["culprit"], victim.as_str());
    assert_eq!(v["instance"], "/v1/inspections");
    // A broken manifest: the JSON path is named.
    let dir = tempfile::tempdir().unwrap();
    crate::common::copy_tree(ci_bundle(), dir.path(), &|p| !p.starts_with("truth"));
    let mut manifest: Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("manifest.json")).unwrap()).unwrap();
    // The bundle with `manifest` in place of its own, posted as a tar.
    let post_with = |manifest: &Value| {
        std::fs::write(dir.path().join("manifest.json"), serde_json::to_vec(manifest).unwrap()).unwrap();
        post("application/x-tar", bundle_tar(dir.path(), &|_| true))
    };
    manifest["optics"]["f_number"] = Value::from(-2.0);
    let v = problem(post_with(&manifest).await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_optics").await;
    assert!(v["culprit"].as_str().unwrap().contains("optics."), "{v}");
    // Well formed, but a pixel pitch typed in mm: refused at upload, before a worker could run
    // out of memory on it.
    manifest["optics"]["f_number"] = Value::from(1.4);
    manifest["optics"]["pixel_pitch_um"] = Value::from(0.012);
    let v =
        problem(post_with(&manifest).await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "inspection_too_large").await;
    assert_eq!(v["culprit"], "manifest.json: optics.pixel_pitch_um", "{v}");
    // Options: unknown pipeline option, bad arc rule, bad query.
    let form = reqwest::multipart::Form::new()
        .part("bundle", reqwest::multipart::Part::bytes(ci_tar()))
        .text("options", r#"{"pipeline": {"depth": {"no_such_knob": 1}}}"#);
    let v = problem(
        app.client.post(app.url("/v1/inspections")).multipart(form).send().await.unwrap(),
        StatusCode::UNPROCESSABLE_ENTITY,
        "invalid_option",
    )
    .await;
    assert_eq!(v["culprit"], "pipeline.depth.no_such_knob");
    problem(app.submit(ci_tar(), "?arc_rule=sometimes").await, StatusCode::BAD_REQUEST, "invalid_query").await;
    let bad_multipart = app
        .client
        .post(app.url("/v1/inspections"))
        .header("content-type", "multipart/form-data; boundary=XYZ")
        .body("--XYZ\r\nnot a part")
        .send()
        .await
        .unwrap();
    problem(bad_multipart, StatusCode::BAD_REQUEST, "invalid_multipart").await;
    let traversal = reqwest::multipart::Form::new()
        .part("manifest", reqwest::multipart::Part::bytes(std::fs::read(ci_bundle().join("manifest.json")).unwrap()))
        .part("../etc/passwd", reqwest::multipart::Part::bytes(b"x".to_vec()))
        // More after the refused part: the server reads the rest, so the client gets the answer.
        .part("views/a000-z00/000.png", reqwest::multipart::Part::bytes(vec![0u8; 48 << 20]));
    problem(
        app.client.post(app.url("/v1/inspections")).multipart(traversal).send().await.unwrap(),
        StatusCode::UNPROCESSABLE_ENTITY,
        "unsafe_path",
    )
    .await;
    // Too large for the configured limit.
    let small = spawn_app_with(|s| {
        s.workers = 0;
        s.max_upload_mb = 1;
    })
    .await;
    problem(small.submit(ci_tar(), "").await, StatusCode::PAYLOAD_TOO_LARGE, "body_too_large").await;
    assert_eq!(small.uploads().await, 0);
    small.stop().await;

    // Routing and ids.
    problem(app.get("/v2/nothing").await, StatusCode::NOT_FOUND, "route_not_found").await;
    problem(
        app.client.delete(app.url("/v1/inspections")).send().await.unwrap(),
        StatusCode::METHOD_NOT_ALLOWED,
        "method_not_allowed",
    )
    .await;
    problem(app.get("/v1/inspections/not-an-id").await, StatusCode::NOT_FOUND, "invalid_id").await;
    problem(app.get("/v1/inspections/01890a5d-ac96-774b-bcce-b302099a8057").await, StatusCode::NOT_FOUND, "invalid_id")
        .await;
    problem(app.get("/v1/inspections?status=done").await, StatusCode::BAD_REQUEST, "invalid_query").await;
    let p =
        problem(app.get("/v1/inspections?review_required=yes").await, StatusCode::BAD_REQUEST, "invalid_query").await;
    assert_eq!(p["culprit"], "review_required", "{p}");
    problem(app.get("/v1/inspections?limit=0").await, StatusCode::BAD_REQUEST, "invalid_query").await;
    problem(app.get("/v1/inspections?created_after=yesterday").await, StatusCode::BAD_REQUEST, "invalid_query").await;
    problem(app.get("/v1/connections/XYZ%2099").await, StatusCode::NOT_FOUND, "unknown_designation").await;

    // Nothing was stored by any of it.
    let page: Value = app.get("/v1/inspections").await.json().await.unwrap();
    assert_eq!(page["items"].as_array().unwrap().len(), 0);
    assert_eq!(app.uploads().await, 0);

    // Results of an inspection that has none yet, and bad CMM data, once one exists.
    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    problem(app.get(&format!("/v1/inspections/{id}/report")).await, StatusCode::CONFLICT, "inspection_not_succeeded")
        .await;
    problem(app.get(&format!("/v1/inspections/{id}/cmm")).await, StatusCode::NOT_FOUND, "cmm_not_found").await;
    let connection: Value = app.get("/v1/connections/BC%204-1%2F2").await.json().await.unwrap();
    assert_eq!(connection["designation"], "BC 4-1/2");
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idempotent_retry_and_cancel() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let send = |key: &'static str, query: &'static str| {
        app.client
            .post(app.url(&format!("/v1/inspections{query}")))
            .header("content-type", "application/x-tar")
            .header("idempotency-key", key)
            .body(ci_tar())
            .send()
    };
    let first = send("station-7-run-42", "").await.unwrap();
    assert_eq!(first.status(), StatusCode::ACCEPTED);
    let first: Value = first.json().await.unwrap();
    let retry = send("station-7-run-42", "").await.unwrap();
    assert_eq!(retry.status(), StatusCode::ACCEPTED);
    assert_eq!(retry.headers()["idempotent-replayed"], "true");
    let retry: Value = retry.json().await.unwrap();
    assert_eq!(retry["id"], first["id"]);
    let other = send("station-7-run-42", "?arc_rule=combined").await.unwrap();
    let v = problem(other, StatusCode::UNPROCESSABLE_ENTITY, "idempotency_key_reused").await;
    assert_eq!(v["culprit"], "Idempotency-Key");
    let page: Value = app.get("/v1/inspections").await.json().await.unwrap();
    assert_eq!(page["items"].as_array().unwrap().len(), 1);
    assert_eq!(app.uploads().await, 1, "one content-addressed upload");

    // Cancel while queued: at once.
    let id = first["id"].as_str().unwrap();
    let canceled = app.client.post(app.url(&format!("/v1/inspections/{id}/cancel"))).send().await.unwrap();
    assert_eq!(canceled.status(), StatusCode::OK);
    assert_eq!(canceled.json::<Value>().await.unwrap()["status"], "canceled");

    // Cancel while running: requested, seen by the lease holder at its heartbeat.
    let second: Value = send("station-7-run-43", "").await.unwrap().json().await.unwrap();
    let store = app.store().await;
    let claimed = store.claim("test-worker", Duration::from_secs(30)).await.unwrap().expect("one queued");
    assert_eq!(claimed.id, second["id"].as_str().unwrap());
    let response = app.client.post(app.url(&format!("/v1/inspections/{}/cancel", claimed.id))).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let v: Value = response.json().await.unwrap();
    assert_eq!((v["status"].as_str(), v["cancel_requested"].as_bool()), (Some("running"), Some(true)));
    let beat = store.heartbeat(&claimed.id, "test-worker", Duration::from_secs(30), None).await.unwrap();
    assert_eq!(beat, crestscan::service::store::Heartbeat::Held { cancel_requested: true });
    assert_eq!(
        store.heartbeat(&claimed.id, "someone-else", Duration::from_secs(30), None).await.unwrap(),
        crestscan::service::store::Heartbeat::Lost
    );
    assert!(
        store
            .complete_without_results(&claimed.id, "test-worker", crestscan::service::store::Status::Canceled, None)
            .await
            .unwrap()
    );
    let v: Value = app.get(&format!("/v1/inspections/{}", claimed.id)).await.json().await.unwrap();
    assert_eq!(v["status"], "canceled");
    // A finished inspection cannot be canceled.
    let response = app.client.post(app.url(&format!("/v1/inspections/{}/cancel", claimed.id))).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK, "canceling a canceled inspection is a no-op");

    // Cancel requested while running, then the worker gives the job back (a retryable failure or
    // a release at shutdown): it ends canceled, not queued (claims skip canceled-requested jobs,
    // so a queued one would wait forever).
    let third: Value = send("station-7-run-44", "").await.unwrap().json().await.unwrap();
    let claimed = store.claim("test-worker", Duration::from_secs(30)).await.unwrap().expect("one queued");
    assert_eq!(claimed.id, third["id"].as_str().unwrap());
    let response = app.client.post(app.url(&format!("/v1/inspections/{}/cancel", claimed.id))).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    assert!(store.requeue(&claimed.id, "test-worker", Duration::ZERO, None, true).await.unwrap());
    let v: Value = app.get(&format!("/v1/inspections/{}", claimed.id)).await.json().await.unwrap();
    assert_eq!(v["status"], "canceled");
    assert!(v["finished_at"].is_string(), "{v}");
    assert!(store.claim("test-worker", Duration::from_secs(30)).await.unwrap().is_none(), "nothing left queued");
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cursor_pagination_walks_every_inspection_once() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let mut ids = Vec::new();
    for i in 0..5 {
        let v: Value = app.submit(ci_tar(), &format!("?client_reference=batch-{}", i % 2)).await.json().await.unwrap();
        ids.push(v["id"].as_str().unwrap().to_string());
    }
    let mut seen = Vec::new();
    let mut cursor: Option<String> = None;
    loop {
        let path = match &cursor {
            Some(c) => format!("/v1/inspections?limit=2&cursor={c}"),
            None => "/v1/inspections?limit=2".to_string(),
        };
        let page: Value = app.get(&path).await.json().await.unwrap();
        seen.extend(page["items"].as_array().unwrap().iter().map(|i| i["id"].as_str().unwrap().to_string()));
        match page["next_cursor"].as_str() {
            Some(c) => cursor = Some(c.to_string()),
            None => break,
        }
    }
    ids.reverse();
    assert_eq!(seen, ids, "newest first, each once");
    let batch0: Value = app.get("/v1/inspections?client_reference=batch-0").await.json().await.unwrap();
    assert_eq!(batch0["items"].as_array().unwrap().len(), 3);
    let none: Value = app.get("/v1/inspections?created_after=2100-01-01T00:00:00Z").await.json().await.unwrap();
    assert_eq!(none["items"].as_array().unwrap().len(), 0);
    app.stop().await;
}

/// `?wait=` answers as soon as the inspection changes (here: canceled by another client while a
/// long-poll waits), at once when it is finished, and after the wait when nothing happens;
/// `finished_after` lists what finished since a time.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn long_polls_answer_on_change_and_the_list_takes_finished_after() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let response = app.submit(ci_tar(), "").await;
    let id = response.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let path = format!("/v1/inspections/{id}");

    // Nothing happens: the wait runs out, and the answer is the queued inspection.
    let started = Instant::now();
    let v: Value = app.get(&format!("{path}?wait=700ms")).await.json().await.unwrap();
    assert_eq!(v["status"], "queued");
    assert!(started.elapsed() >= Duration::from_millis(650), "{:?}", started.elapsed());

    // A cancel during a 30 s wait ends it at once.
    let before_cancel = time::OffsetDateTime::now_utc();
    let waiting = {
        let (client, url) = (app.client.clone(), app.url(&format!("{path}?wait=30s")));
        tokio::spawn(async move {
            let started = Instant::now();
            let v: Value = client.get(url).send().await.unwrap().json().await.unwrap();
            (v, started.elapsed())
        })
    };
    tokio::time::sleep(Duration::from_millis(300)).await;
    let cancel = app.client.post(app.url(&format!("{path}/cancel"))).send().await.unwrap();
    assert_eq!(cancel.status(), StatusCode::OK);
    let (v, took) = waiting.await.unwrap();
    assert_eq!(v["status"], "canceled", "{v}");
    assert!(took < Duration::from_secs(3), "{took:?}");

    // Finished: answered at once however long the wait.
    let started = Instant::now();
    let v: Value = app.get(&format!("{path}?wait=60")).await.json().await.unwrap();
    assert_eq!(v["status"], "canceled");
    assert!(started.elapsed() < Duration::from_secs(2));
    for bad in ["soon", "-1s", "1.5s", "1234567s"] {
        let response = app.get(&format!("{path}?wait={bad}")).await;
        assert_eq!(response.status(), StatusCode::BAD_REQUEST, "{bad}");
        assert_eq!(response.json::<Value>().await.unwrap()["culprit"], "wait", "{bad}");
    }

    let rfc = |t: time::OffsetDateTime| t.format(&time::format_description::well_known::Rfc3339).unwrap();
    let listed = |v: Value| {
        v["items"].as_array().unwrap().iter().map(|i| i["id"].as_str().unwrap().to_string()).collect::<Vec<_>>()
    };
    let since =
        app.get(&format!("/v1/inspections?finished_after={}", rfc(before_cancel))).await.json::<Value>().await.unwrap();
    assert_eq!(listed(since), vec![id.clone()]);
    let later = rfc(time::OffsetDateTime::now_utc() + time::Duration::seconds(1));
    let none = app.get(&format!("/v1/inspections?finished_after={later}")).await.json::<Value>().await.unwrap();
    assert!(listed(none).is_empty());
    app.stop().await;
}

/// The events of a server-sent stream, read until the server ends it: (id, event, data) each.
async fn read_events(response: reqwest::Response, timeout: Duration) -> Vec<(String, String, String)> {
    assert_eq!(response.status(), StatusCode::OK);
    assert!(response.headers()["content-type"].to_str().unwrap().starts_with("text/event-stream"));
    let mut response = response;
    let mut text = String::new();
    let started = Instant::now();
    while let Some(chunk) = tokio::time::timeout(timeout.saturating_sub(started.elapsed()), response.chunk())
        .await
        .expect("the stream ended within the timeout")
        .unwrap()
    {
        text.push_str(std::str::from_utf8(&chunk).unwrap());
    }
    text.split("\n\n")
        .filter_map(|block| {
            let field = |name: &str| {
                block.lines().find_map(|l| l.strip_prefix(&format!("{name}:"))).map(|v| v.trim_start().to_string())
            };
            // Keep-alive comments (`:`) carry no event.
            field("event").map(|event| (field("id").unwrap_or_default(), event, field("data").unwrap_or_default()))
        })
        .collect()
}

/// `GET /v1/inspections/{id}/events`: one event per change, every status in order (queued behind
/// another job, running with its stages, succeeded), ids counting up, and the stream ends after
/// the terminal state; a stream on a job that never runs ends when the service stops, so the
/// drain does not wait on it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn event_streams_send_every_state_in_order_and_end_with_the_job_or_the_service() {
    let app = spawn_app().await;
    let first = app.submit(ci_tar(), "?client_reference=first").await;
    assert_eq!(first.status(), StatusCode::ACCEPTED);
    let second = app.submit(ci_tar(), "?client_reference=second").await;
    let id = second.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let events = read_events(app.get(&format!("/v1/inspections/{id}/events")).await, Duration::from_secs(600)).await;
    let states: Vec<Value> = events
        .iter()
        .map(|(_, event, data)| {
            assert_eq!(event, "state");
            serde_json::from_str(data).unwrap()
        })
        .collect();
    let ids: Vec<String> = events.iter().map(|(id, _, _)| id.clone()).collect();
    assert_eq!(ids, (1..=events.len()).map(|i| i.to_string()).collect::<Vec<_>>());
    let mut statuses: Vec<&str> = states.iter().map(|s| s["status"].as_str().unwrap()).collect();
    statuses.dedup();
    // Every status, however short: the worker runs in this process, whose store sends each
    // change to the stream.
    assert_eq!(statuses, ["queued", "running", "succeeded"], "{states:?}");
    assert!(states.iter().all(|s| s["id"] == id.as_str()));
    let last = states.last().unwrap();
    let truth: Value =
        serde_json::from_slice(&std::fs::read(crate::common::ci_bundle().join("truth/truth.json")).unwrap()).unwrap();
    assert_eq!(last["verdict"], truth["verdict"], "{last}");
    // Consecutive events differ (a change each), and the running ones name their stages.
    for pair in states.windows(2) {
        assert_ne!(
            (&pair[0]["status"], &pair[0]["progress"]["stage"]),
            (&pair[1]["status"], &pair[1]["progress"]["stage"])
        );
    }
    // The running events' stages come in the pipeline's order.
    let order = ["depth", "register", "fuse", "mesh", "profile", "crest_and_rules"];
    let stages: Vec<usize> = states
        .iter()
        .filter_map(|s| s["progress"]["stage"].as_str())
        .map(|stage| order.iter().position(|o| *o == stage).unwrap_or_else(|| panic!("stage {stage}")))
        .collect();
    assert!(stages.windows(2).all(|w| w[0] < w[1]), "{stages:?}");

    // A finished inspection: one event, and the stream ends at once.
    let events = read_events(app.get(&format!("/v1/inspections/{id}/events")).await, Duration::from_secs(5)).await;
    assert_eq!(events.len(), 1);
    problem(
        app.get("/v1/inspections/00000000-0000-0000-0000-000000000000/events").await,
        StatusCode::NOT_FOUND,
        "invalid_id",
    )
    .await;
    app.stop().await;

    // No workers: the job stays queued; stopping the service ends the stream with `shutdown`.
    let app = spawn_app_with(|s| s.workers = 0).await;
    let response = app.submit(ci_tar(), "").await;
    let id = response.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let stream = app.get(&format!("/v1/inspections/{id}/events")).await;
    let reading = tokio::spawn(read_events(stream, Duration::from_secs(30)));
    tokio::time::sleep(Duration::from_millis(300)).await;
    let started = Instant::now();
    app.stop().await;
    assert!(started.elapsed() < Duration::from_secs(5), "the drain waited {:?}", started.elapsed());
    let events = reading.await.unwrap();
    let kinds: Vec<&str> = events.iter().map(|(_, e, _)| e.as_str()).collect();
    assert_eq!(kinds, ["state", "shutdown"]);
}

/// Issue 49: a `.tar.gz` upload is taken as its tar is; a tar made from outside the bundle's
/// folder is answered with the `tar -C` that makes it right.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gzipped_tar_is_accepted_and_a_too_deep_one_gets_the_hint() {
    use std::io::Write;
    let app = spawn_app_with(|s| s.workers = 0).await;
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    gz.write_all(&ci_tar()).unwrap();
    let gz = gz.finish().unwrap();
    let response = app
        .client
        .post(app.url("/v1/inspections"))
        .header("content-type", "application/gzip")
        .body(gz)
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::ACCEPTED);

    let mut builder = tar::Builder::new(Vec::new());
    for file in walk(ci_bundle()) {
        let rel = file.strip_prefix(ci_bundle()).unwrap().to_string_lossy().replace('\\', "/");
        if !rel.starts_with("truth") {
            builder.append_path_with_name(&file, format!("out/ci/{rel}")).unwrap();
        }
    }
    let v =
        problem(app.submit(builder.into_inner().unwrap(), "").await, StatusCode::UNPROCESSABLE_ENTITY, "missing_file")
            .await;
    assert!(v["detail"].as_str().unwrap().contains("tar -C out/ci"), "{v}");
    app.stop().await;
}
