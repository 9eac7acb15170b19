//! The queue and its durability: kill -9, graceful shutdown, API and worker nodes, retention.

use super::*;

/// Uploaded bundles are deleted once every inspection that uses them finished before the cutoff;
/// one still shared by an unfinished inspection is kept, and the records stay readable.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn finished_uploads_are_purged_and_shared_ones_kept() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let store = app.store().await;
    let later_ms =
        || (std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_millis() as i64) + 3_600_000;
    let cancel = |id: String| {
        let request = app.client.post(app.url(&format!("/v1/inspections/{id}/cancel")));
        async move { assert_eq!(request.send().await.unwrap().status(), StatusCode::OK) }
    };
    let first: Value = app.submit(ci_tar(), "").await.json().await.unwrap();
    let first = first["id"].as_str().unwrap().to_string();
    cancel(first.clone()).await;
    // The same bundle again: the same content-addressed upload, now in use by a queued inspection.
    let second: Value = app.submit(ci_tar(), "").await.json().await.unwrap();
    let second = second["id"].as_str().unwrap().to_string();
    assert_eq!(app.uploads().await, 1);
    assert_eq!(store.purge_uploads(later_ms()).await.unwrap(), 0, "an unfinished inspection still needs it");
    assert_eq!(app.uploads().await, 1);
    cancel(second.clone()).await;
    // Finished, but after the cutoff: kept.
    assert_eq!(store.purge_uploads(later_ms() - 7_200_000).await.unwrap(), 0);
    assert_eq!(store.purge_uploads(later_ms()).await.unwrap(), 1);
    assert_eq!(app.uploads().await, 0);
    assert_eq!(store.purge_uploads(later_ms()).await.unwrap(), 0, "purged once");
    for id in [&first, &second] {
        let v: Value = app.get(&format!("/v1/inspections/{id}")).await.json().await.unwrap();
        assert_eq!(v["status"], "canceled", "{v}");
    }
    app.stop().await;
}

/// The real binary, SIGKILLed with jobs queued and running, then restarted on the same data
/// directory: every accepted inspection finishes, exactly once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_loses_no_accepted_inspection() {
    let data = tempfile::tempdir().unwrap();
    let start = |data: &Path| {
        start_binary(data, &["--lease-seconds", "1", "--heartbeat-seconds", "0.2", "--poll-interval-ms", "50"])
    };
    let client = super::client();
    let (mut child, base) = start(data.path());
    let mut ids = Vec::new();
    for _ in 0..3 {
        ids.push(submit_ci_to(&client, &base).await);
    }
    // Kill it while the first is running.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let v: Value =
            client.get(format!("{base}/v1/inspections/{}", ids[0])).send().await.unwrap().json().await.unwrap();
        if v["status"] == "running" {
            break;
        }
        assert!(Instant::now() < deadline, "never started: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    child.kill().unwrap();
    child.wait().unwrap();

    let (mut child, base) = start(data.path());
    let deadline = Instant::now() + Duration::from_secs(300);
    for id in &ids {
        loop {
            let v: Value =
                client.get(format!("{base}/v1/inspections/{id}")).send().await.unwrap().json().await.unwrap();
            if v["status"] == "succeeded" {
                break;
            }
            assert!(v["status"] == "queued" || v["status"] == "running", "{v}");
            assert!(Instant::now() < deadline, "not finished: {v}");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
    let first: Value =
        client.get(format!("{base}/v1/inspections/{}", ids[0])).send().await.unwrap().json().await.unwrap();
    assert_eq!(first["attempts"], 2, "the killed run and the one that finished");
    child.kill().unwrap();
    child.wait().unwrap();
    // Exactly once: one report and one set of thread rows per inspection.
    let store = open_store(data.path()).await;
    let reports = store.count("SELECT COUNT(*) FROM reports").await.unwrap();
    assert_eq!(reports, 3);
    let dupes = store
        .count(
            "SELECT COUNT(*) FROM (SELECT inspection_id, thread_index FROM threads GROUP BY 1, 2 HAVING COUNT(*) > 1) d",
        )
        .await
        .unwrap();
    assert_eq!(dupes, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn graceful_shutdown_lets_the_running_job_finish() {
    // A grace period long enough for a starved CI machine (the compute pool runs at SCHED_IDLE).
    let app = spawn_app_with(|s| s.shutdown_grace_seconds = 300.0).await;
    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let v: Value = app.get(&format!("/v1/inspections/{id}")).await.json().await.unwrap();
        if v["status"] == "running" {
            break;
        }
        assert_eq!(v["status"], "queued");
        assert!(Instant::now() < deadline);
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let data = app.data.clone();
    let _dir = app.stop().await;
    let row = open_store(&data).await.inspection(&id).await.unwrap();
    assert_eq!(row.status, "succeeded", "the job finished within the grace period before the process stopped");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_api_node_and_a_worker_node_share_a_data_directory_and_failures_are_problems() {
    // An API-only node accepts; the upload then vanishes (an operator's mistake).
    let api = spawn_app_with(|s| s.workers = 0).await;
    let created: Value = api.submit(ci_tar(), "").await.json().await.unwrap();
    let id = created["id"].as_str().unwrap();
    let sha = created["bundle"]["sha256"].as_str().unwrap();
    api.store().await.blobs.remove(sha).await.unwrap();
    // A worker node on the same directory claims it and fails it with a problem object.
    let worker = spawn_app_in(&api.data, |_| {}).await;
    let done = api.wait(id, Duration::from_secs(60)).await;
    assert_eq!(done["status"], "failed");
    assert_eq!(done["error"]["code"], "upload_missing");
    assert_eq!(done["error"]["status"], 500);
    assert!(done["error"]["detail"].as_str().unwrap().contains(sha));
    assert_eq!(done["attempts"], 1, "a permanent failure is not retried");
    worker.stop().await;
    api.stop().await;
}

/// A database a newer binary migrated is refused at start-up with what to do, not misread.
#[tokio::test]
async fn a_database_from_a_newer_binary_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let store = open_store(dir.path()).await;
    // What the newer binary's migrator would have recorded, on whichever backend.
    let future = "INSERT INTO _sqlx_migrations (version, description, success, checksum, execution_time) \
                  VALUES (999999, 'from the future', TRUE, '\\x00', 0)";
    match test_settings(dir.path()).database() {
        crestscan::service::store::Database::Sqlite(_) => {
            let pool = store.sqlite_pool().unwrap();
            sqlx::query(&future.replace("'\\x00'", "X'00'")).execute(pool).await.unwrap();
        }
        crestscan::service::store::Database::Postgres(url) => {
            let pool = sqlx::PgPool::connect(&url).await.unwrap();
            sqlx::query(future).execute(&pool).await.unwrap();
            pool.close().await;
        }
    }
    store.close().await;
    let err = crestscan::service::startup::Application::build(test_settings(dir.path())).await.err().expect("refused");
    let text = err.to_string();
    assert!(text.contains("newer crestscan") && text.contains("999999"), "{text}");
}

/// Eight claimers on two pools (as two processes would hold them) drain a queue of 40 jobs
/// together: each job is claimed exactly once (PostgreSQL: `FOR UPDATE SKIP LOCKED`; SQLite: its
/// write lock), and a claimed job is not claimed again while its lease holds.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_claimers_take_each_job_once() {
    let dir = tempfile::tempdir().unwrap();
    let stores = [open_store(dir.path()).await, open_store(dir.path()).await];
    let mut queued = std::collections::BTreeSet::new();
    for k in 0..40 {
        queued.insert(queue_one(&stores[0], &format!("bundle {k}")).await);
    }
    let claimers = (0..8).map(|c| {
        let store = stores[c % 2].clone();
        tokio::spawn(async move {
            let mut mine = Vec::new();
            while let Some(job) = store.claim(&format!("claimer-{c}"), Duration::from_secs(600)).await.unwrap() {
                mine.push(job.id);
            }
            mine
        })
    });
    let mut claimed = Vec::new();
    for c in claimers {
        claimed.extend(c.await.unwrap());
    }
    let distinct: std::collections::BTreeSet<String> = claimed.iter().cloned().collect();
    assert_eq!(claimed.len(), 40, "claims: {} for 40 jobs", claimed.len());
    assert_eq!(distinct, queued, "every job claimed exactly once");
    assert!(stores[1].claim("late", Duration::from_secs(600)).await.unwrap().is_none());
    for s in &stores {
        s.close().await;
    }
}

/// Queues an inspection of a one-file "bundle" `text` straight in the store; its id.
async fn queue_one(store: &crestscan::service::store::Store, text: &str) -> String {
    use crestscan::service::store::{NewInspection, UploadInfo};
    let mut file = store.files.temp_file().unwrap();
    std::io::Write::write_all(&mut file, text.as_bytes()).unwrap();
    store.files.prepare(&file).unwrap();
    let sha256 = crestscan::service::store::files::sha256_hex(text.as_bytes());
    let new = NewInspection {
        id: uuid::Uuid::now_v7().to_string(),
        upload: UploadInfo { sha256: sha256.clone(), size_bytes: text.len() as u64, views: 1, frames: 3 },
        serial: None,
        connection: None,
        client_reference: None,
        station: None,
        request_sha256: sha256,
        options_json: "{}".into(),
        idempotency_key: None,
        max_attempts: 3,
    };
    store.insert_inspection(&new, file).await.unwrap();
    new.id
}

/// Under PostgreSQL a claim passes over a job another transaction holds (a claimer mid-claim in
/// another process) and takes the next, without waiting: `SKIP LOCKED`. Without it the claim
/// would wait for the holder and then take the same job again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_postgres_claim_skips_a_job_another_claimer_holds() {
    use crestscan::service::store::{Database, Store};
    let dir = tempfile::tempdir().unwrap();
    let url = crate::common::database_for(dir.path());
    let store = Store::connect(&Database::Postgres(url.clone()), &dir.path().join("uploads"), &dir.path().join("tmp"))
        .await
        .unwrap();
    let first = queue_one(&store, "first").await;
    let second = queue_one(&store, "second").await;
    let other = sqlx::PgPool::connect(&url).await.unwrap();
    let mut held = other.begin().await.unwrap();
    sqlx::query("SELECT id FROM inspections WHERE id = $1 FOR UPDATE").bind(&first).execute(&mut *held).await.unwrap();
    let claimed = tokio::time::timeout(Duration::from_secs(5), store.claim("w", Duration::from_secs(60)))
        .await
        .expect("the claim waited on the held job")
        .unwrap()
        .expect("a job");
    assert_eq!(claimed.id, second);
    held.rollback().await.unwrap();
    assert_eq!(store.claim("w", Duration::from_secs(60)).await.unwrap().unwrap().id, first);
    assert!(store.claim("w", Duration::from_secs(60)).await.unwrap().is_none());
    other.close().await;
    store.close().await;
}
