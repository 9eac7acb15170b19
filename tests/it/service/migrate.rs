//! A single node's data directory moved into PostgreSQL and the object store
//! (`crestscan migrate-store --to … --object-store …`), its meshes and images out of the rows
//! into objects on the way, then served from there.

use super::*;
use crate::common::{database_for, moto_endpoint};

/// Runs the real binary; its output, after checking how it ended.
fn crestscan(args: &[&str], succeeds: bool) -> String {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_crestscan")).args(args).output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert_eq!(out.status.success(), succeeds, "crestscan {}: {text}", args.join(" "));
    text
}

/// Finished inspections, CMM data and a key, written on the embedded default, moved into
/// PostgreSQL and S3: resumable (a second run copies nothing), verified (every table counted and
/// digested), and served from there with byte-identical answers; a target that has rows of its
/// own is refused as different.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_data_directory_moves_into_postgres_and_the_object_store_with_identical_answers() {
    let app = spawn_app_with(single_node).await;
    let data = app.data.clone();
    let mut ids = Vec::new();
    for reference in ["first", "second"] {
        let created = app.submit(ci_tar(), &format!("?client_reference={reference}")).await;
        assert_eq!(created.status(), StatusCode::ACCEPTED);
        let id = created.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
        assert_eq!(app.wait(&id, Duration::from_secs(120)).await["status"], "succeeded");
        ids.push(id);
    }
    let cmm = "thread,angle_deg,height_mm\n3,12.5,1.575\n4,100,1.58\n";
    let put = app
        .client
        .put(app.url(&format!("/v1/inspections/{}/cmm", ids[0])))
        .header("content-type", "text/csv")
        .body(cmm)
        .send()
        .await
        .unwrap();
    assert!(put.status().is_success(), "{}", put.text().await.unwrap());
    let key = crestscan(
        &["keys", "create", "--name", "mes-line-3", "--scopes", "read", "--data-dir", data.to_str().unwrap()],
        true,
    );
    let key_id = key.split_whitespace().nth(2).unwrap().to_string();
    // Every answer a client could have kept, as bytes.
    let paths: Vec<String> = ids
        .iter()
        .flat_map(|id| {
            ["", "/report", "/threads", "/threads?format=csv", "/cmm", "/cmm/versions", "/cmm-comparison", "/mesh"]
                .map(|tail| format!("/v1/inspections/{id}{tail}"))
        })
        .chain(["/v1/inspections?limit=10".to_string(), "/v1/inspections?client_reference=second".to_string()])
        .collect();
    let mut before = Vec::new();
    for path in &paths {
        let response = app.get(path).await;
        before.push((response.status(), response.bytes().await.unwrap()));
    }
    assert!(
        before.iter().filter(|(s, _)| *s == StatusCode::OK).count() >= 14,
        "{:?}",
        before.iter().map(|b| b.0).collect::<Vec<_>>()
    );
    let dir = app.stop().await.expect("the data directory");

    let url = database_for(&data.join("moved"));
    let prefix = format!(
        "s3://crestscan-it/moved-{}",
        data.file_name().unwrap().to_string_lossy().to_ascii_lowercase().replace('.', "")
    );
    let migrate = |succeeds| {
        crestscan(
            &[
                "migrate-store",
                "--from",
                data.to_str().unwrap(),
                "--to",
                &url,
                "--object-store",
                &prefix,
                "--s3-endpoint",
                moto_endpoint(),
                "--s3-access-key-id",
                "test",
                "--s3-secret-access-key",
                "test",
            ],
            succeeds,
        )
    };
    let first = migrate(true);
    eprintln!("{first}");
    assert!(first.contains("16 tables") && first.contains("identical in postgres://"), "{first}");
    assert!(first.contains("1 live uploads: 1 copied"), "{first}");
    let inspections = first.lines().find(|l| l.starts_with("inspections ")).unwrap();
    assert!(inspections.contains("2 rows") && inspections.contains("2 copied now"), "{first}");
    // The meshes and images left the rows for the object store on the way.
    assert!(first.contains("10 meshes and images in the object store: 10 verified"), "{first}");
    let moved = crestscan::service::store::Store::connect(
        &crestscan::service::store::Database::Postgres(url.clone()),
        &data.join("uploads"),
        &data.join("tmp"),
    )
    .await
    .unwrap();
    let named = "SELECT COUNT(*) FROM artifacts WHERE object_sha256 IS NOT NULL AND length(body) = 0";
    assert_eq!(moved.count(named).await.unwrap(), 10);
    moved.close().await;
    let bucket_prefix = prefix.trim_start_matches("s3://crestscan-it/");
    let listing = std::process::Command::new("curl")
        .args(["-sf", &format!("{}/crestscan-it?list-type=2&prefix={bucket_prefix}/artifacts/", moto_endpoint())])
        .output()
        .unwrap();
    assert_eq!(String::from_utf8_lossy(&listing.stdout).matches("<Key>").count(), 10);
    // Resumed: nothing left to copy, everything still identical.
    let again = migrate(true);
    assert!(
        again.lines().filter(|l| l.contains(" rows,")).all(|l| l.contains(" 0 copied now") && l.ends_with("identical")),
        "{again}"
    );

    // Served from PostgreSQL and the object store, the local uploads gone.
    std::fs::remove_dir_all(data.join("uploads")).unwrap();
    let app = spawn_app_in(&data, |s| {
        s.database_url = Some(url.clone());
        s.object_store = Some(prefix.clone());
        s.s3_endpoint = Some(moto_endpoint().into());
        s.s3_access_key_id = Some("test".into());
        s.s3_secret_access_key = Some("test".into());
    })
    .await;
    let ready: Value = app.get("/readyz").await.json().await.unwrap();
    assert!(ready.to_string().contains("postgres"), "{ready}");
    for (path, (status, body)) in paths.iter().zip(&before) {
        let response = app.get(path).await;
        assert_eq!(response.status(), *status, "{path}");
        assert!(response.bytes().await.unwrap() == *body, "{path} answers otherwise after the move");
    }
    let keys = crestscan(&["keys", "list", "--database-url", &url], true);
    assert!(keys.contains(&key_id) && keys.contains("mes-line-3"), "{keys}");
    // New work goes on where the old stopped; the source no longer matches the target.
    let rerun = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    assert_eq!(app.wait(&rerun, Duration::from_secs(120)).await["status"], "succeeded");
    app.stop().await;
    let refused = migrate(false);
    assert!(refused.contains("differ") && refused.contains("inspections"), "{refused}");
    drop(dir);
}
