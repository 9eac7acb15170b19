//! Requests meant to hurt the server (issue 28): each gets a clear 4xx naming what is at fault, or a
//! job that fails cleanly, and nothing half-stored.

use super::*;
use crestscan::pipeline::options::RANGES;

/// The multipart upload of the ci bundle with `options` as its options part.
fn with_options(options: &Value) -> reqwest::multipart::Form {
    reqwest::multipart::Form::new()
        .part("bundle", reqwest::multipart::Part::bytes(ci_tar()))
        .text("options", options.to_string())
}

/// `{"pipeline": {...}}` with `value` at the dotted `field`.
fn pipeline_with(field: &str, value: Value) -> Value {
    let mut root = serde_json::json!({});
    let mut slot = &mut root;
    for key in field.split('.') {
        slot = slot.as_object_mut().unwrap().entry(key).or_insert_with(|| serde_json::json!({}));
    }
    *slot = value;
    serde_json::json!({ "pipeline": root })
}

/// `value` as JSON of the option's kind (a count as an integer).
fn number(range: &crestscan::pipeline::options::OptionRange, value: f64) -> Value {
    if range.integer { Value::from(value as i64) } else { Value::from(value) }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn options_outside_their_documented_range_are_refused_by_name() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    // The two that took the server down (a 1.28 TB allocation; a loop that never ended), then one
    // past each end of every documented range, and a fraction where a count is due.
    let mut cases = vec![
        ("cell_px", Value::from(0.01)),
        ("mesh.max_vertices", Value::from(0)),
        ("depth.window_radius_px", Value::from(2.5)),
    ];
    for r in RANGES {
        cases.push((r.field, number(r, r.max + 1.0)));
        cases.push((r.field, number(r, r.min - 1.0)));
    }
    for (field, value) in cases {
        let response = app
            .client
            .post(app.url("/v1/inspections"))
            .multipart(with_options(&pipeline_with(field, value.clone())))
            .send()
            .await
            .unwrap();
        let status = response.status();
        let v: Value = response.json().await.unwrap();
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{field} = {value}: {v}");
        // A negative count fails to parse (invalid_option) before its range is checked; either
        // way the field is named.
        assert!(["option_out_of_range", "invalid_option"].contains(&v["code"].as_str().unwrap()), "{v}");
        assert_eq!(v["culprit"], format!("pipeline.{field}"), "{v}");
    }
    // Every end of every range is inside.
    for r in RANGES {
        for edge in [r.min, r.max] {
            let options = pipeline_with(r.field, number(r, edge));
            let response =
                app.client.post(app.url("/v1/inspections")).multipart(with_options(&options)).send().await.unwrap();
            let status = response.status();
            assert_eq!(status, StatusCode::ACCEPTED, "{} = {edge}: {}", r.field, response.text().await.unwrap());
        }
    }
    app.stop().await;
}

#[test]
fn the_document_states_the_ranges_the_server_checks() {
    let document: Value = serde_json::from_str(&std::fs::read_to_string("openapi/openapi.json").unwrap()).unwrap();
    let pipeline = &document["components"]["schemas"]["SubmitOptions"]["properties"]["pipeline"];
    assert_eq!(pipeline["additionalProperties"], false);
    for r in RANGES {
        let mut node = pipeline;
        for key in r.field.split('.') {
            node = &node["properties"][key];
        }
        assert_eq!(node["minimum"].as_f64(), Some(r.min), "{}", r.field);
        assert_eq!(node["maximum"].as_f64(), Some(r.max), "{}", r.field);
        assert_eq!(node["type"], if r.integer { "integer" } else { "number" }, "{}", r.field);
    }
}

/// A PNG that is only its signature, header and end: `width`×`height` 8-bit RGB declared, no pixels.
fn png_header_only(width: u32, height: u32) -> Vec<u8> {
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = !0u32;
        for &b in bytes {
            crc ^= b as u32;
            for _ in 0..8 {
                crc = if crc & 1 != 0 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
            }
        }
        !crc
    }
    let mut header = width.to_be_bytes().to_vec();
    header.extend(height.to_be_bytes());
    header.extend([8, 2, 0, 0, 0]); // 8 bits, RGB, deflate, no filter method, no interlace
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    // The header, then an empty image-data chunk and the end.
    for (kind, data) in [(&b"IHDR"[..], &header[..]), (b"IDAT", &[]), (b"IEND", &[])] {
        let chunk = [kind, data].concat();
        png.extend((data.len() as u32).to_be_bytes());
        png.extend(&chunk);
        png.extend(crc32(&chunk).to_be_bytes());
    }
    png
}

/// The ci bundle's manifest cut to 3 views, each frame a 3600×3600 header with no pixel data: tens
/// of KB that declare hundreds of millions of pixels (each view's stack within the bundle reader's
/// own caps, so the memory budget is what refuses it).
fn huge_headers_tar() -> Vec<u8> {
    let mut manifest: Value =
        serde_json::from_slice(&std::fs::read(ci_bundle().join("manifest.json")).unwrap()).unwrap();
    let views = manifest["views"].as_array_mut().unwrap();
    views.truncate(3);
    let mut builder = tar::Builder::new(Vec::new());
    let mut add = |name: &str, data: &[u8]| {
        let mut header = tar::Header::new_ustar();
        header.set_size(data.len() as u64);
        header.set_mode(0o644);
        builder.append_data(&mut header, name, data).unwrap();
    };
    for view in views.iter_mut() {
        for frame in view["frames"].as_array().unwrap() {
            add(frame["file"].as_str().unwrap(), &png_header_only(3600, 3600));
        }
    }
    add("manifest.json", &serde_json::to_vec(&manifest).unwrap());
    builder.into_inner().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bundle_over_the_memory_budget_is_refused_before_the_202() {
    let app = spawn_app_with(|s| {
        s.workers = 0;
        s.worker_memory_mb = 2048;
    })
    .await;
    let body = huge_headers_tar();
    assert!(body.len() < 64 << 10, "{} bytes", body.len());
    let v = problem(app.submit(body, "").await, StatusCode::UNPROCESSABLE_ENTITY, "inspection_too_large").await;
    assert_eq!(v["culprit"], "views[].frames", "{v}");
    let detail = v["detail"].as_str().unwrap();
    assert!(detail.contains("worker_memory_mb") && detail.contains("2048 MiB"), "{detail}");
    assert_eq!(app.uploads().await, 0);
    // The ci bundle fits the same budget.
    assert_eq!(app.submit(ci_tar(), "").await.status(), StatusCode::ACCEPTED);
    app.stop().await;
}

/// A tar of `manifest.json` alone.
fn manifest_only_tar(manifest: &[u8]) -> Vec<u8> {
    let mut builder = tar::Builder::new(Vec::new());
    let mut header = tar::Header::new_ustar();
    header.set_size(manifest.len() as u64);
    header.set_mode(0o644);
    builder.append_data(&mut header, "manifest.json", manifest).unwrap();
    builder.into_inner().unwrap()
}

/// A manifest over the size cap, one with more views than allowed and one with a view of more
/// frames than allowed are refused from the manifest alone: no frame is read, nothing is stored.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn huge_manifests_are_refused_by_their_limit_before_any_frame_is_read() {
    let mut manifest: Value =
        serde_json::from_slice(&std::fs::read(ci_bundle().join("manifest.json")).unwrap()).unwrap();
    let view = manifest["views"][0].clone();
    let frames_per_view = view["frames"].as_array().unwrap().len();
    let app = spawn_app_with(|s| {
        s.workers = 0;
        s.max_manifest_kib = 1024;
        s.max_frames_per_view = frames_per_view;
    })
    .await;

    // Over 1 MiB of views whose frames are not in the archive: the size is what refuses it.
    let mut big = manifest.clone();
    let view_bytes = serde_json::to_vec(&view).unwrap().len();
    big["views"] = Value::from(
        (0..(2 << 20) / view_bytes)
            .map(|i| {
                let mut v = view.clone();
                v["id"] = Value::from(format!("v{i}"));
                v
            })
            .collect::<Vec<_>>(),
    );
    let bytes = serde_json::to_vec(&big).unwrap();
    assert!(bytes.len() > 1 << 20, "{} bytes", bytes.len());
    let v = problem(app.submit(manifest_only_tar(&bytes), "").await, StatusCode::PAYLOAD_TOO_LARGE, "bundle_too_large")
        .await;
    assert_eq!(v["culprit"], "manifest.json", "{v}");
    assert!(v["detail"].as_str().unwrap().contains("max_manifest_kib"), "{v}");

    // 1001 views: the count is what refuses it (the default max_views).
    big["views"] = Value::from(
        (0..1001)
            .map(|i| serde_json::json!({"id": format!("v{i}"), "pose": view["pose"], "frames": []}))
            .collect::<Vec<_>>(),
    );
    let v = problem(
        app.submit(manifest_only_tar(&serde_json::to_vec(&big).unwrap()), "").await,
        StatusCode::PAYLOAD_TOO_LARGE,
        "bundle_too_large",
    )
    .await;
    assert_eq!(v["culprit"], "manifest.json: views", "{v}");
    assert!(v["detail"].as_str().unwrap().contains("1001 views, more than max_views (1000)"), "{v}");

    // A second view with one frame more than allowed.
    let mut frames = view["frames"].as_array().unwrap().clone();
    frames.push(frames[0].clone());
    manifest["views"][1]["frames"] = Value::from(frames);
    let v = problem(
        app.submit(manifest_only_tar(&serde_json::to_vec(&manifest).unwrap()), "").await,
        StatusCode::PAYLOAD_TOO_LARGE,
        "bundle_too_large",
    )
    .await;
    assert_eq!(v["culprit"], "manifest.json: views[1].frames", "{v}");
    let expected = format!("max_frames_per_view ({frames_per_view})");
    assert!(v["detail"].as_str().unwrap().contains(&expected), "{v}");
    assert_eq!(app.uploads().await, 0);
    app.stop().await;
}

/// A zip whose frame inflates 1000-fold (a bomb: 32 MiB of zeros in about 32 KB) is refused from
/// the archive's directory by the compression-ratio cap, naming the entry; the same bytes stored
/// uncompressed meet the frame check instead.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_inflating_zip_is_refused_by_its_compression_ratio() {
    use std::io::Write;
    let app = spawn_app_with(|s| s.workers = 0).await;
    let manifest = std::fs::read(ci_bundle().join("manifest.json")).unwrap();
    let parsed: Value = serde_json::from_slice(&manifest).unwrap();
    let first = parsed["views"][0]["frames"][0]["file"].as_str().unwrap().to_string();
    let zeros = vec![0u8; 32 << 20];
    let zip = |method: zip::CompressionMethod| {
        let mut writer = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        let options = zip::write::SimpleFileOptions::default().compression_method(method);
        writer.start_file("manifest.json", options).unwrap();
        writer.write_all(&manifest).unwrap();
        writer.start_file(first.as_str(), options).unwrap();
        writer.write_all(&zeros).unwrap();
        writer.finish().unwrap().into_inner()
    };
    let bomb = zip(zip::CompressionMethod::Deflated);
    assert!(bomb.len() < 256 << 10, "{} bytes", bomb.len());
    let send = |body: Vec<u8>| {
        app.client.post(app.url("/v1/inspections")).header("content-type", "application/zip").body(body).send()
    };
    let v = problem(send(bomb).await.unwrap(), StatusCode::PAYLOAD_TOO_LARGE, "bundle_too_large").await;
    assert_eq!(v["culprit"].as_str(), Some(first.as_str()), "{v}");
    assert!(v["detail"].as_str().unwrap().contains("max_compression_ratio (100:1)"), "{v}");

    let stored = zip(zip::CompressionMethod::Stored);
    let v = problem(send(stored).await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "unreadable_frame").await;
    assert_eq!(v["culprit"].as_str(), Some(first.as_str()), "{v}");
    assert_eq!(app.uploads().await, 0);
    app.stop().await;
}

/// A job accepted under one budget and run under a smaller one fails cleanly with the budget's
/// problem; the worker goes on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_queued_job_over_a_lowered_budget_fails_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let accepting = spawn_app_in(dir.path(), |s| s.workers = 0).await;
    let response = accepting.submit(ci_tar(), "").await;
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let id = response.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    accepting.stop().await;
    let running = spawn_app_in(dir.path(), |s| s.worker_memory_mb = 1).await;
    let done = running.wait(&id, Duration::from_secs(60)).await;
    assert_eq!(done["status"], "failed", "{done}");
    assert_eq!(done["error"]["code"], "inspection_too_large", "{done}");
    assert!(done["error"]["detail"].as_str().unwrap().contains("worker_memory_mb"), "{done}");
    running.stop().await;
}

/// Below the free-space floor: uploads get 507 before anything is written, readiness says why,
/// workers leave queued jobs queued; once space returns (here: the floor lowered) it all goes on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_disk_under_its_floor_refuses_uploads_with_507_and_recovers() {
    let dir = tempfile::tempdir().unwrap();
    // A job queued while there was room.
    let roomy = spawn_app_in(dir.path(), |s| s.workers = 0).await;
    let queued = roomy.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    roomy.stop().await;
    let uploads_before = walk(&dir.path().join("uploads")).len();

    // No file system has an exbibyte free.
    let full = spawn_app_in(dir.path(), |s| s.min_free_disk_mb = 1 << 40).await;
    let v = problem(
        full.submit(ci_tar(), "?client_reference=late").await,
        StatusCode::INSUFFICIENT_STORAGE,
        "insufficient_storage",
    )
    .await;
    assert!(v["detail"].as_str().unwrap().contains("min_free_disk_mb"), "{v}");
    let ready = full.get("/readyz").await;
    assert_eq!(ready.status(), StatusCode::SERVICE_UNAVAILABLE);
    let ready: Value = ready.json().await.unwrap();
    assert!(ready["detail"].as_str().unwrap().contains("floor"), "{ready}");
    tokio::time::sleep(Duration::from_millis(600)).await;
    let job: Value = full.get(&format!("/v1/inspections/{queued}")).await.json().await.unwrap();
    assert_eq!(job["status"], "queued", "a worker claimed under the floor: {job}");
    assert_eq!(walk(&dir.path().join("uploads")).len(), uploads_before, "nothing stored");
    assert_eq!(walk(&dir.path().join("tmp")).len(), 0, "no temporary left");
    full.stop().await;

    let recovered = spawn_app_in(dir.path(), |s| s.min_free_disk_mb = 0).await;
    let ready: Value = recovered.get("/readyz").await.json().await.unwrap();
    assert!(ready["disk_free_mb"].as_u64().unwrap() > 0 && ready["disk_floor_mb"] == 0, "{ready}");
    assert_eq!(recovered.wait(&queued, Duration::from_secs(120)).await["status"], "succeeded");
    assert_eq!(recovered.submit(ci_tar(), "?client_reference=late").await.status(), StatusCode::ACCEPTED);
    recovered.stop().await;
}

/// A refused archive's problem names it as "the upload", not by the server's temporary path; an
/// internal error shows a reference, not its cause.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_facing_errors_carry_no_server_paths() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let v =
        problem(app.submit(b"not a tar".to_vec(), "").await, StatusCode::UNPROCESSABLE_ENTITY, "invalid_archive").await;
    let detail = v["detail"].as_str().unwrap();
    let data = app.data.to_string_lossy().into_owned();
    assert!(detail.starts_with("the upload") && !detail.contains(&data) && !detail.contains("/tmp"), "{detail}");
    app.stop().await;
}

/// Opens a raw connection and sends a tar upload's head announcing `length` body bytes.
async fn slow_upload(app: &TestApp, length: usize) -> tokio::net::TcpStream {
    use tokio::io::AsyncWriteExt;
    let address = app.base.trim_start_matches("http://").to_string();
    let mut stream = tokio::net::TcpStream::connect(&address).await.unwrap();
    let head = format!(
        "POST /v1/inspections HTTP/1.1\r\nHost: {address}\r\nContent-Type: application/x-tar\r\nContent-Length: {length}\r\n\r\n"
    );
    stream.write_all(head.as_bytes()).await.unwrap();
    stream
}

/// Reads what the server answered on a raw connection (until it closes or 5 s pass).
async fn answer(stream: &mut tokio::net::TcpStream) -> String {
    use tokio::io::AsyncReadExt;
    let mut buffer = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(5), stream.read_to_end(&mut buffer)).await;
    String::from_utf8_lossy(&buffer).into_owned()
}

/// A trickling upload and a stalled one are cut off with 408 within the configured times, while a
/// normal upload beside them is served; one client's uploads beyond its share get 429.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_uploads_are_cut_off_and_others_are_served() {
    use tokio::io::AsyncWriteExt;
    let app = spawn_app_with(|s| {
        s.workers = 0;
        s.upload_idle_seconds = 1.0;
        s.min_upload_kib_per_s = 64.0;
        s.max_uploads_per_client = 3;
    })
    .await;
    let bundle = ci_tar();
    let started = Instant::now();
    // Trickles a byte every 100 ms: never idle for a second, far under 64 KiB/s.
    let mut trickle = slow_upload(&app, 1 << 20).await;
    let trickler = tokio::spawn(async move {
        for _ in 0..100 {
            if trickle.write_all(b"x").await.is_err() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        answer(&mut trickle).await
    });
    // Sends a little, then nothing.
    let mut stalled = slow_upload(&app, 1 << 20).await;
    stalled.write_all(&[0u8; 1000]).await.unwrap();
    // A third open upload fills this client's share; a fourth is refused.
    let mut third = slow_upload(&app, 1 << 20).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let refused = app.submit(bundle.clone(), "").await;
    assert_eq!(refused.status(), StatusCode::TOO_MANY_REQUESTS);
    assert!(refused.headers().contains_key("retry-after"));
    assert_eq!(refused.json::<Value>().await.unwrap()["code"], "too_many_uploads");
    // Another client (another loopback address) is served meanwhile.
    let other =
        super::client_builder().local_address("127.0.0.2".parse::<std::net::IpAddr>().unwrap()).build().unwrap();
    let served = other
        .post(app.url("/v1/inspections"))
        .header("content-type", "application/x-tar")
        .body(bundle.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(served.status(), StatusCode::ACCEPTED);

    let stalled_answer = answer(&mut stalled).await;
    assert!(stalled_answer.starts_with("HTTP/1.1 408"), "{stalled_answer}");
    assert!(stalled_answer.contains("upload_idle_seconds"), "{stalled_answer}");
    let trickled = trickler.await.unwrap();
    assert!(trickled.starts_with("HTTP/1.1 408"), "{trickled}");
    assert!(trickled.contains("min_upload_kib_per_s"), "{trickled}");
    assert!(started.elapsed() < Duration::from_secs(15), "cut off late: {:?}", started.elapsed());
    assert!(answer(&mut third).await.starts_with("HTTP/1.1 408"));
    // Their places are free again, and nothing of theirs is stored.
    // (the same bundle as the other client's: one stored file)
    assert_eq!(app.submit(bundle, "").await.status(), StatusCode::ACCEPTED);
    assert_eq!(app.uploads().await, 1);
    app.stop().await;
}

/// A URI or a head past the limits gets problem+json (it had empty bodies); a connection that
/// sends its head slowly, or sits idle, is closed after header_timeout_seconds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn long_heads_get_problems_and_slow_or_idle_connections_are_closed() {
    use tokio::io::AsyncWriteExt;
    let app = spawn_app_with(|s| {
        s.workers = 0;
        s.header_timeout_seconds = 1.0;
    })
    .await;
    let long = format!("/v1/inspections?client_reference={}", "x".repeat(10_000));
    let v = problem(app.get(&long).await, StatusCode::URI_TOO_LONG, "uri_too_long").await;
    assert!(v["detail"].as_str().unwrap().contains("8192"), "{v}");
    let mut request = app.client.get(app.url("/v1/inspections"));
    for i in 0..150 {
        request = request.header(format!("x-filler-{i}"), "y");
    }
    problem(request.send().await.unwrap(), StatusCode::from_u16(431).unwrap(), "headers_too_large").await;
    let big = app.client.get(app.url("/v1/inspections")).header("x-big", "z".repeat(80_000)).send().await.unwrap();
    problem(big, StatusCode::from_u16(431).unwrap(), "headers_too_large").await;

    let address = app.base.trim_start_matches("http://").to_string();
    // Idle: connected, nothing sent.
    let started = Instant::now();
    let mut idle = tokio::net::TcpStream::connect(&address).await.unwrap();
    let idle_answer = answer(&mut idle).await;
    assert!(started.elapsed() < Duration::from_secs(4), "idle connection held {:?}", started.elapsed());
    // Slow head: a byte every 200 ms, never finishing.
    let started = Instant::now();
    let mut slow = tokio::net::TcpStream::connect(&address).await.unwrap();
    let closed = tokio::time::timeout(Duration::from_secs(6), async {
        for byte in b"GET /v1/inspections HTTP/1.1\r\nHost: x\r\nX-Slow: ".iter().cycle() {
            if slow.write_all(&[*byte]).await.is_err() {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        false
    })
    .await
    .unwrap_or(false);
    assert!(closed, "a slow head was held for 6 s (idle answer: {idle_answer:?})");
    assert!(started.elapsed() < Duration::from_secs(4), "slow head held {:?}", started.elapsed());
    // Others are served throughout.
    assert_eq!(app.get("/healthz").await.status(), StatusCode::OK);
    app.stop().await;
}

/// A claim whose process dies (its lease lapses) is an interruption, not an attempt: the job is
/// re-run with its retry budget whole, and only a job whose process died `max_interruptions` times
/// is failed, as poisonous.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn crashes_are_not_counted_against_a_job_until_they_repeat() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let mut store = app.store().await;
    store.max_interruptions = 3;
    // A lease of 1 ms lapses at once: as if the process died right after claiming.
    let lapse = Duration::from_millis(1);
    let first = store.claim("dies-1", lapse).await.unwrap().unwrap();
    assert_eq!((first.attempts, first.interruptions, first.failed_attempts()), (1, 0, 1));
    tokio::time::sleep(Duration::from_millis(5)).await;
    let second = store.claim("dies-2", lapse).await.unwrap().unwrap();
    assert_eq!((second.id.as_str(), second.interruptions, second.failed_attempts()), (id.as_str(), 1, 1));
    tokio::time::sleep(Duration::from_millis(5)).await;
    let third = store.claim("dies-3", lapse).await.unwrap().unwrap();
    assert_eq!((third.interruptions, third.failed_attempts()), (2, 1), "two crashes cost no retry");
    tokio::time::sleep(Duration::from_millis(5)).await;
    // The third death: failed as poisonous, not claimed again.
    assert!(store.claim("dies-4", lapse).await.unwrap().is_none());
    let v: Value = app.get(&format!("/v1/inspections/{id}")).await.json().await.unwrap();
    assert_eq!((v["status"].as_str(), v["error"]["code"].as_str()), (Some("failed"), Some("job_poisonous")), "{v}");
    assert!(v["error"]["detail"].as_str().unwrap().contains("3 times"), "{v}");
    app.stop().await;
}

/// The result retention deletes an old inspection's meshes and images, keeps its report and thread
/// table, answers 410 for what it deleted, and frees the pages for the next results.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_result_retention_frees_meshes_and_images_and_says_so() {
    let app = spawn_app().await;
    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    assert_eq!(app.wait(&id, Duration::from_secs(300)).await["status"], "succeeded");
    let store = app.store().await;
    // SQLite's free pages, in bytes; None under PostgreSQL, which reclaims its space by autovacuum.
    let free_page_bytes = || async {
        let pool = store.sqlite_pool()?;
        let pragma = |sql| sqlx::query_scalar::<_, i64>(sql).fetch_one(pool);
        Some(pragma("PRAGMA freelist_count").await.unwrap() * pragma("PRAGMA page_size").await.unwrap())
    };
    assert_eq!(store.count("SELECT COUNT(*) FROM artifacts").await.unwrap(), 5);
    // Bytes in the rows: all of them, or none where an object store holds them.
    let artifact_bytes = store.count("SELECT COALESCE(SUM(LENGTH(body)), 0) FROM artifacts").await.unwrap();
    assert_eq!(artifact_bytes > 0, store.artifact_objects.is_none(), "{artifact_bytes} B in the rows");
    let free_before = free_page_bytes().await;
    // Nothing is old enough yet.
    assert_eq!(store.purge_artifacts(0).await.unwrap(), 0);
    assert_eq!(app.get(&format!("/v1/inspections/{id}/mesh")).await.status(), StatusCode::OK);
    let now_ms = (std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_millis() + 1) as i64;
    assert_eq!(store.purge_artifacts(now_ms).await.unwrap(), 1);
    assert_eq!(store.count("SELECT COUNT(*) FROM artifacts").await.unwrap(), 0);
    let freed_bytes = free_page_bytes().await.zip(free_before).map(|(after, before)| after - before);
    if let Some(freed) = freed_bytes {
        assert!(freed * 2 >= artifact_bytes, "freed {freed} B of {artifact_bytes} B of artifacts");
    }
    let v = problem(app.get(&format!("/v1/inspections/{id}/mesh")).await, StatusCode::GONE, "result_expired").await;
    assert!(v["detail"].as_str().unwrap().contains("artifact_retention_days"), "{v}");
    problem(app.get(&format!("/v1/inspections/{id}/images/height-map")).await, StatusCode::GONE, "result_expired")
        .await;
    assert_eq!(app.get(&format!("/v1/inspections/{id}/report")).await.status(), StatusCode::OK);
    assert_eq!(app.get(&format!("/v1/inspections/{id}/threads")).await.status(), StatusCode::OK);
    // The report's page still stands, and says what is gone instead of showing a broken viewer.
    let page = app.client.get(app.url(&format!("/v1/inspections/{id}/report?format=html"))).send().await.unwrap();
    assert_eq!(page.status(), StatusCode::OK);
    let page = page.text().await.unwrap();
    assert!(page.contains("were deleted on") && page.contains("artifact_retention_days"));
    assert!(!page.contains("data:image/png") && !page.contains("id=\"viewer\""));
    // A second purge has nothing to do.
    assert_eq!(store.purge_artifacts(now_ms).await.unwrap(), 0);
    eprintln!("retention: {artifact_bytes} B of meshes and images, {freed_bytes:?} B of SQLite pages freed");
    app.stop().await;
}
