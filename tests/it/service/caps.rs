//! Caps that keep one client from bloating or stalling the server (issue 48): every free text has
//! a length cap that names its field, list pages are bounded in bytes, and slow uploads cannot
//! keep a normal one out.

use super::*;

/// The ci bundle as a tar with its manifest edited.
fn ci_tar_with(edit: impl Fn(&mut Value)) -> Vec<u8> {
    let dir = ci_bundle();
    let mut manifest: Value = serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    edit(&mut manifest);
    let manifest = serde_json::to_vec(&manifest).unwrap();
    let mut builder = tar::Builder::new(Vec::new());
    for file in crate::common::walk(dir) {
        let rel = file.strip_prefix(dir).unwrap().to_string_lossy().replace('\\', "/");
        if !(rel.starts_with("truth") || rel == "manifest.json") {
            builder.append_path_with_name(&file, &rel).unwrap();
        }
    }
    let mut header = tar::Header::new_ustar();
    header.set_size(manifest.len() as u64);
    header.set_mode(0o644);
    builder.append_data(&mut header, "manifest.json", manifest.as_slice()).unwrap();
    builder.into_inner().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_free_text_of_a_submission_has_a_cap_that_names_its_field() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let huge = "S".repeat(64 << 10);
    let cases: Vec<(Box<dyn Fn(&mut Value)>, &str)> = vec![
        (Box::new(|m: &mut Value| m["part"]["serial"] = Value::from(huge.clone())), "manifest.json: part.serial"),
        (Box::new(|m: &mut Value| m["part"]["serial"] = Value::from("SN\u{7}1")), "manifest.json: part.serial"),
        (
            Box::new(|m: &mut Value| m["part"]["connection"] = Value::from(huge.clone())),
            "manifest.json: part.connection",
        ),
        (Box::new(|m: &mut Value| m["views"][0]["id"] = Value::from("v".repeat(65))), "manifest.json: views[0].id"),
    ];
    for (edit, culprit) in cases {
        let response = app.submit(ci_tar_with(edit), "").await;
        let status = response.status();
        let body = response.text().await.unwrap();
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{culprit}: {}", &body[..body.len().min(300)]);
        let v: Value = serde_json::from_str(&body).unwrap();
        assert_eq!(v["culprit"], culprit, "{v}");
        // The answer quotes no more than a preview of what it refused.
        assert!(body.len() < 2000, "a {} byte problem", body.len());
    }
    // At the cap is inside.
    let at_cap = app.submit(ci_tar_with(|m| m["part"]["serial"] = Value::from("S".repeat(128))), "").await;
    assert_eq!(at_cap.status(), StatusCode::ACCEPTED);

    // A model name is checked whatever the depth method (it is stored with the options).
    let options = serde_json::json!({"pipeline": {"depth": {"model": "m".repeat(900 << 10)}}});
    let response = app
        .client
        .post(app.url("/v1/inspections"))
        .multipart(
            reqwest::multipart::Form::new()
                .part("bundle", reqwest::multipart::Part::bytes(ci_tar()))
                .text("options", options.to_string()),
        )
        .send()
        .await
        .unwrap();
    let status = response.status();
    let body = response.text().await.unwrap();
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{}", &body[..body.len().min(300)]);
    let v: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(v["culprit"], "pipeline.depth.model", "{v}");
    assert!(body.len() < 2000, "a {} byte problem", body.len());

    // An API key's name, empty or too long, as the schema says.
    let doc: Value = serde_json::from_str(&crestscan::service::api::openapi().to_pretty_json().unwrap()).unwrap();
    let name = &doc["components"]["schemas"]["NewApiKey"]["properties"]["name"];
    assert_eq!((name["minLength"].as_u64(), name["maxLength"].as_u64()), (Some(1), Some(100)), "{name}");
    let serial = &doc["components"]["schemas"]["PartManifest"]["properties"]["serial"];
    assert_eq!(serial["maxLength"].as_u64(), Some(128), "{serial}");
    app.stop().await;
}

/// Opens a raw connection from `local` and sends a tar upload's head announcing 1 MiB.
async fn trickle_from(app: &TestApp, local: std::net::IpAddr) -> tokio::net::TcpStream {
    use tokio::io::AsyncWriteExt;
    let address: std::net::SocketAddr = app.base.trim_start_matches("http://").parse().unwrap();
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.bind(std::net::SocketAddr::new(local, 0)).unwrap();
    let mut stream = socket.connect(address).await.unwrap();
    let head = format!(
        "POST /v1/inspections HTTP/1.1\r\nHost: {address}\r\nContent-Type: application/x-tar\r\nContent-Length: {}\r\n\r\n",
        1 << 20
    );
    stream.write_all(head.as_bytes()).await.unwrap();
    stream
}

/// Issue 48: uploads at a byte a second from four addresses, as many as the server takes at once
/// (32, eight per address), and a normal upload beside them still gets its 202; the trickles are
/// cut off with 408 within the rate floor's grace, long before the 30 s idle limit.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thirty_two_trickles_from_four_addresses_leave_room_for_a_normal_upload() {
    use tokio::io::AsyncWriteExt;
    // The defaults: 32 places, 8 per client, 64 KiB/s floor, 30 s idle limit.
    let app = spawn_app_with(|s| s.workers = 0).await;
    assert_eq!(app_settings_places(), (32, 8));
    // The normal upload's bytes first: rendering them (the first call in a process renders the
    // bundle) must not delay the upload past the trickles' grace.
    let bundle = ci_tar();
    let started = Instant::now();
    let mut tricklers = Vec::new();
    for a in 1..=4u8 {
        for _ in 0..8 {
            let mut stream = trickle_from(&app, std::net::IpAddr::from([127, 0, 0, a])).await;
            tricklers.push(tokio::spawn(async move {
                use tokio::io::AsyncReadExt;
                let mut answer = Vec::new();
                for _ in 0..60 {
                    if stream.write_all(b"x").await.is_err() {
                        break;
                    }
                    let mut buf = [0u8; 4096];
                    match tokio::time::timeout(Duration::from_secs(1), stream.read(&mut buf)).await {
                        Ok(Ok(0)) | Ok(Err(_)) => break,
                        Ok(Ok(n)) => answer.extend_from_slice(&buf[..n]),
                        Err(_) => {}
                    }
                    if !answer.is_empty() {
                        break;
                    }
                }
                let _ = tokio::time::timeout(Duration::from_secs(2), stream.read_to_end(&mut answer)).await;
                (String::from_utf8_lossy(&answer).into_owned(), started.elapsed())
            }));
        }
    }
    // Every place is taken, and each trickle has run long enough to be judged.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let normal =
        super::client_builder().local_address("127.0.0.5".parse::<std::net::IpAddr>().unwrap()).build().unwrap();
    let response = normal
        .post(app.url("/v1/inspections"))
        .header("content-type", "application/x-tar")
        .body(bundle)
        .send()
        .await
        .unwrap();
    let status = response.status();
    assert_eq!(status, StatusCode::ACCEPTED, "{}", response.text().await.unwrap());

    let mut evicted = 0;
    for trickler in tricklers {
        let (answer, at) = trickler.await.unwrap();
        assert!(answer.starts_with("HTTP/1.1 408"), "a trickle answered {answer:?}");
        assert!(answer.contains("min_upload_kib_per_s"), "{answer}");
        evicted += answer.contains("place") as usize;
        assert!(at < Duration::from_secs(12), "a trickle held its place for {at:?}");
    }
    assert!(evicted >= 1, "the normal upload took no trickle's place");
    app.stop().await;
}

fn app_settings_places() -> (usize, usize) {
    let s = Settings::default();
    (s.max_concurrent_uploads, s.max_uploads_per_client)
}
