//! Uploaded bundles in an S3-compatible object store (moto's server, a real S3 API on loopback):
//! the blob store on its own (a multipart bundle, a corrupted object refused, removal), and the
//! service keeping its uploads there end to end.

use super::*;
use crate::common::moto_endpoint;
use crestscan::service::store::blobs::{ArtifactKey, ArtifactStore, BlobStore, S3Blobs, S3Location, S3Settings};

fn s3_settings() -> S3Settings {
    S3Settings {
        endpoint: Some(moto_endpoint().into()),
        region: None,
        credentials: Some(("test".into(), "test".into())),
    }
}

/// A staged file of `bytes` in `tmp`, as an upload leaves one.
fn staged(tmp: &Path, bytes: &[u8]) -> tempfile::NamedTempFile {
    let mut file = tempfile::NamedTempFile::new_in(tmp).unwrap();
    std::io::Write::write_all(&mut file, bytes).unwrap();
    file.as_file().sync_all().unwrap();
    file
}

#[tokio::test]
async fn s3_blobs_keep_a_multipart_bundle_and_refuse_bytes_that_are_not_it() {
    let dir = tempfile::tempdir().unwrap();
    let location = S3Location::parse("s3://crestscan-it/blobs-roundtrip").unwrap();
    let blobs = S3Blobs::open(location, &s3_settings(), dir.path()).unwrap();
    blobs.check().await.unwrap();
    // 20 MiB: three parts of a multipart upload (S3 wants ≥ 5 MiB for all but the last).
    let bytes: Vec<u8> = (0..20u32 << 20).map(|i| (i.wrapping_mul(2654435761) >> 24) as u8).collect();
    let sha = crestscan::service::store::files::sha256_hex(&bytes);
    blobs.put(&sha, staged(dir.path(), &bytes)).await.unwrap();
    // Put again: kept, not uploaded twice.
    blobs.put(&sha, staged(dir.path(), &bytes)).await.unwrap();
    assert_eq!(blobs.list().await.unwrap(), vec![sha.clone()]);
    let copy = blobs.fetch(&sha).await.unwrap();
    assert!(std::fs::read(copy.path()).unwrap() == bytes, "the fetched bytes are the uploaded ones");
    let path = copy.path().to_path_buf();
    drop(copy);
    assert!(!path.exists(), "a download is removed with its copy");
    // Bytes under the name that are not the blob's (a store that lost or mangled it): refused.
    let key = format!("{}/crestscan-it/blobs-roundtrip/uploads/{}/{sha}", moto_endpoint(), &sha[..2]);
    let put = std::process::Command::new("curl").args(["-sf", "-X", "PUT", "--data-binary", "other", &key]).status();
    assert!(put.unwrap().success());
    let err = blobs.fetch(&sha).await.err().expect("a corrupted blob is refused");
    assert_eq!(err.kind(), std::io::ErrorKind::InvalidData);
    assert!(err.to_string().contains(&sha), "{err}");
    blobs.remove(&sha).await.unwrap();
    assert!(blobs.list().await.unwrap().is_empty());
    assert_eq!(blobs.fetch(&sha).await.err().unwrap().kind(), std::io::ErrorKind::NotFound);
    // Removing what is not there is no error.
    blobs.remove(&sha).await.unwrap();
}

/// The service with `object_store` set keeps each upload in the bucket, none in its data
/// directory, and inspects it from there.
#[tokio::test]
async fn the_service_keeps_uploads_in_the_object_store() {
    let app = spawn_app_with(|s| {
        s.object_store = Some("s3://crestscan-it/service-end-to-end".into());
        s.s3_endpoint = Some(moto_endpoint().into());
        s.s3_access_key_id = Some("test".into());
        s.s3_secret_access_key = Some("test".into());
    })
    .await;
    let ready: Value = app.get("/readyz").await.json().await.unwrap();
    assert_eq!(ready["status"], "ready", "{ready}");
    let response = app.submit(ci_tar(), "").await;
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let id = response.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let done = app.wait(&id, Duration::from_secs(120)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let location = S3Location::parse("s3://crestscan-it/service-end-to-end").unwrap();
    let blobs = S3Blobs::open(location, &s3_settings(), &app.data.join("tmp")).unwrap();
    assert_eq!(blobs.list().await.unwrap().len(), 1);
    let local = app.data.join("uploads");
    assert!(!local.exists() || walk(&local).is_empty(), "nothing kept in the data directory");
    // The object under the prefix, read straight from the server.
    let listing = std::process::Command::new("curl")
        .args(["-sf", &format!("{}/crestscan-it?list-type=2&prefix=service-end-to-end/uploads/", moto_endpoint())])
        .output()
        .unwrap();
    let listing = String::from_utf8_lossy(&listing.stdout);
    assert_eq!(listing.matches("<Key>").count(), 1, "{listing}");
    app.stop().await;
}

/// The keys under `prefix/` in moto's bucket, read straight from the server.
fn listed(prefix: &str) -> Vec<String> {
    let listing = std::process::Command::new("curl")
        .args(["-sf", &format!("{}/crestscan-it?list-type=2&prefix={prefix}/", moto_endpoint())])
        .output()
        .unwrap();
    let listing = String::from_utf8_lossy(&listing.stdout);
    listing.split("<Key>").skip(1).map(|k| k.split("</Key>").next().unwrap().to_string()).collect()
}

/// With an object store, a finished inspection's meshes and images are objects named by their
/// rows (which keep an empty body), served from there byte for byte; an object no row names is
/// swept once older than the grace, a named one is kept; the retention deletes the objects with
/// the rows.
#[tokio::test]
async fn meshes_and_images_live_in_the_object_store_and_leave_no_orphans() {
    let prefix = format!("artifacts-{}", std::process::id());
    let url = format!("s3://crestscan-it/{prefix}");
    let app = spawn_app_with(|s| {
        s.object_store = Some(url.clone());
        s.s3_endpoint = Some(moto_endpoint().into());
        s.s3_access_key_id = Some("test".into());
        s.s3_secret_access_key = Some("test".into());
    })
    .await;
    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    assert_eq!(app.wait(&id, Duration::from_secs(120)).await["status"], "succeeded");
    let objects = listed(&format!("{prefix}/artifacts"));
    let mut store = open_store(&app.data).await;
    let blobs =
        std::sync::Arc::new(S3Blobs::open(S3Location::parse(&url).unwrap(), &s3_settings(), &app.data).unwrap());
    store.artifact_objects = Some(blobs.clone());
    let rows = store.count("SELECT COUNT(*) FROM artifacts WHERE object_sha256 IS NOT NULL AND length(body) = 0").await;
    assert_eq!(rows.unwrap(), 5, "mesh.ply, mesh.stl, two PNGs and the pitch profiles, each an object");
    assert_eq!(store.count("SELECT COUNT(*) FROM artifacts").await.unwrap(), 5);
    assert_eq!(objects.len(), 5, "{objects:?}");
    let mesh = app.get(&format!("/v1/inspections/{id}/mesh")).await;
    assert_eq!(mesh.status(), StatusCode::OK);
    let sha = crestscan::service::store::files::sha256_hex(&mesh.bytes().await.unwrap());
    assert!(objects.contains(&format!("{prefix}/artifacts/{id}/mesh.ply/{sha}")), "{sha} {objects:?}");

    // A worker's upload whose completion never committed.
    let stray = ArtifactKey { inspection_id: id.clone(), kind: "mesh.ply".into(), sha256: "0".repeat(64) };
    blobs.put_artifact(&stray, b"not this inspection's mesh".to_vec()).await.unwrap();
    let now = crestscan::service::store::now_ms();
    assert_eq!(store.remove_orphan_artifacts(now - 60_000).await.unwrap(), 0, "within the grace: kept");
    assert_eq!(store.remove_orphan_artifacts(now + 1000).await.unwrap(), 1, "only the stray is an orphan");
    assert_eq!(listed(&format!("{prefix}/artifacts")), objects);
    let again = app.get(&format!("/v1/inspections/{id}/mesh")).await;
    assert_eq!(crestscan::service::store::files::sha256_hex(&again.bytes().await.unwrap()), sha);

    // Bytes under a row's key that are not its own are refused, not served.
    let key = ArtifactKey { inspection_id: id.clone(), kind: "mesh.ply".into(), sha256: sha.clone() };
    blobs.put_artifact(&key, b"mangled".to_vec()).await.unwrap();
    let refused = app.get(&format!("/v1/inspections/{id}/mesh")).await;
    assert_eq!(refused.status(), StatusCode::INTERNAL_SERVER_ERROR);

    // The retention takes the objects with their rows.
    assert_eq!(store.purge_artifacts(now + 1000).await.unwrap(), 1);
    assert!(listed(&format!("{prefix}/artifacts")).is_empty());
    assert_eq!(app.get(&format!("/v1/inspections/{id}/mesh")).await.status(), StatusCode::GONE);
    app.stop().await;
}

#[tokio::test]
async fn the_service_does_not_start_on_an_object_store_it_cannot_write() {
    let closed = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let dir = tempfile::tempdir().unwrap();
    let mut settings = test_settings(dir.path());
    settings.object_store = Some("s3://crestscan-it/nowhere".into());
    settings.s3_endpoint = Some(format!("http://127.0.0.1:{closed}"));
    settings.s3_access_key_id = Some("test".into());
    settings.s3_secret_access_key = Some("test".into());
    let err = crestscan::service::startup::Application::build(settings).await.err().expect("refused");
    let text = err.to_string();
    assert!(text.contains("object store s3://crestscan-it/nowhere"), "{text}");
    // A malformed location is a settings error naming the field.
    let mut settings = test_settings(dir.path());
    settings.object_store = Some("s3://Not_A_Bucket".into());
    let err = crestscan::service::startup::Application::build(settings).await.err().expect("refused");
    assert!(err.to_string().contains("object_store"), "{err}");
}

/// A data directory that started on the embedded default moves its uploads into the object store
/// (`crestscan migrate-store`): resumable, verified, and served from there afterwards with the
/// same answers.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_data_directory_moves_its_uploads_into_the_object_store() {
    let app = spawn_app_with(single_node).await;
    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    assert_eq!(app.wait(&id, Duration::from_secs(120)).await["status"], "succeeded");
    let report_before = app.get(&format!("/v1/inspections/{id}/report")).await.bytes().await.unwrap();
    let data = app.data.clone();
    let dir = app.stop().await.expect("the data directory");

    let migrate = || {
        std::process::Command::new(env!("CARGO_BIN_EXE_crestscan"))
            .args(["migrate-store", "--from"])
            .arg(&data)
            .args(["--object-store", "s3://crestscan-it/migrated", "--s3-endpoint", moto_endpoint()])
            .args(["--s3-access-key-id", "test", "--s3-secret-access-key", "test", "--verify-hashes"])
            .output()
            .unwrap()
    };
    let first = migrate();
    let stdout = String::from_utf8_lossy(&first.stdout);
    assert!(first.status.success(), "{stdout}{}", String::from_utf8_lossy(&first.stderr));
    assert!(
        stdout.contains("1 live uploads: 1 copied, 0 already in") && stdout.contains("1 verified by size and sha256"),
        "{stdout}"
    );
    // Again: nothing to copy, everything verified.
    let again = migrate();
    let stdout = String::from_utf8_lossy(&again.stdout);
    assert!(again.status.success() && stdout.contains("0 copied, 1 already in"), "{stdout}");
    // The local files gone, the service on the object store answers as before and inspects the
    // moved bundle again from there.
    std::fs::remove_dir_all(data.join("uploads")).unwrap();
    let app = spawn_app_in(&data, |s| {
        s.database_url = None;
        s.object_store = Some("s3://crestscan-it/migrated".into());
        s.s3_endpoint = Some(moto_endpoint().into());
        s.s3_access_key_id = Some("test".into());
        s.s3_secret_access_key = Some("test".into());
    })
    .await;
    let report_after = app.get(&format!("/v1/inspections/{id}/report")).await.bytes().await.unwrap();
    assert!(report_before == report_after, "the report reads the same from the migrated store");
    let rerun = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    assert_eq!(app.wait(&rerun, Duration::from_secs(120)).await["status"], "succeeded");
    app.stop().await;
    // A store missing a live upload fails the verification, naming it.
    let location = S3Location::parse("s3://crestscan-it/migrated").unwrap();
    let blobs = S3Blobs::open(location, &s3_settings(), &data.join("tmp")).unwrap();
    let sha = blobs.list().await.unwrap().pop().unwrap();
    blobs.remove(&sha).await.unwrap();
    let broken = migrate();
    assert!(!broken.status.success());
    let stderr = String::from_utf8_lossy(&broken.stderr);
    assert!(stderr.contains(&sha) && stderr.contains("not in the store"), "{stderr}");
    drop(dir);
}
