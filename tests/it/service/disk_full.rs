//! A full disk (issue 48): on a real size-limited file system (tmpfs), a write that fails for want
//! of space is a 507, never a 500 and never a 202 that is not durable; the database is never left
//! locked; once space returns everything works again without a restart, and every accepted
//! inspection is there after one.
//!
//! tmpfs needs the right to mount: root, or passwordless sudo (as `.ci/run` uses for its
//! packages); a machine with neither fails these tests with the reason rather than skipping them.

use super::*;
use crestscan::service::store::{Inserted, NewInspection, Store, UploadInfo};
use std::io::Write;

/// A tmpfs of a given size, owned by this process's user, unmounted on drop.
struct Tmpfs {
    dir: tempfile::TempDir,
    /// `sudo -n` where this process is not root (as `.ci/run` installs packages).
    sudo: bool,
}

/// Runs `args`, through `sudo -n` when asked; its error output when it fails.
fn privileged(sudo: bool, args: &[&str]) -> Result<(), String> {
    let mut command = if sudo { std::process::Command::new("sudo") } else { std::process::Command::new(args[0]) };
    if sudo {
        command.arg("-n").args(args);
    } else {
        command.args(&args[1..]);
    }
    match command.output() {
        Ok(out) if out.status.success() => Ok(()),
        Ok(out) => Err(String::from_utf8_lossy(&out.stderr).trim().to_string()),
        Err(e) => Err(e.to_string()),
    }
}

impl Tmpfs {
    fn mount(size_mib: u64) -> Self {
        let dir = tempfile::tempdir().unwrap();
        // SAFETY: getuid and getgid only read the process's ids.
        let (uid, gid) = unsafe { (libc::getuid(), libc::getgid()) };
        let options = format!("size={size_mib}m,uid={uid},gid={gid},mode=0700");
        let path = dir.path().to_str().unwrap().to_string();
        let args = ["mount", "-t", "tmpfs", "-o", options.as_str(), "tmpfs", path.as_str()];
        let direct = privileged(false, &args);
        let sudo = match &direct {
            Ok(()) => false,
            Err(_) if uid != 0 && privileged(true, &args).is_ok() => true,
            Err(e) => panic!(
                "these tests need a size-limited file system: `mount -t tmpfs` failed ({e}); run them as root or \
                 with passwordless sudo"
            ),
        };
        Self { dir, sudo }
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Free bytes, as statvfs reports them.
    fn free(&self) -> u64 {
        let out = std::process::Command::new("df").args(["-B1", "--output=avail"]).arg(self.path()).output().unwrap();
        String::from_utf8_lossy(&out.stdout).lines().nth(1).unwrap().trim().parse().unwrap()
    }

    /// Fills the file system with a file until at most `leave` bytes are free (down to the last
    /// page when `leave` is 0); the file is removed to give the space back.
    fn fill(&self, leave: u64) -> Filler {
        let path = self.path().join(format!("filler-{}", uuid::Uuid::now_v7()));
        let mut file = std::fs::File::create(&path).unwrap();
        let mut chunk = 1usize << 20;
        loop {
            let free = self.free();
            if free <= leave {
                break;
            }
            while chunk as u64 > free - leave && chunk > 4096 {
                chunk /= 2;
            }
            match file.write_all(&vec![0u8; chunk]).and_then(|_| file.flush()) {
                Ok(()) => {}
                Err(e) if e.raw_os_error() == Some(libc::ENOSPC) => {
                    if chunk <= 4096 {
                        break;
                    }
                    chunk /= 2;
                }
                Err(e) => panic!("filling the disk: {e}"),
            }
        }
        Filler { path }
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = privileged(self.sudo, &["umount", "-l", self.dir.path().to_str().unwrap()]);
    }
}

struct Filler {
    path: std::path::PathBuf,
}

impl Filler {
    fn give_back(self) {
        std::fs::remove_file(&self.path).unwrap();
    }
}

/// A stored upload of `bytes` and its inspection, as a submission would record them.
async fn insert(store: &Store, bytes: &[u8], options_json: String, key: Option<&str>) -> Result<Inserted, String> {
    let mut file = store.files.temp_file().map_err(|e| e.to_string())?;
    file.write_all(bytes).map_err(|e| e.to_string())?;
    store.files.prepare(&file).map_err(|e| e.to_string())?;
    let sha256 = crestscan::service::store::files::sha256_hex(bytes);
    let new = NewInspection {
        id: uuid::Uuid::now_v7().to_string(),
        upload: UploadInfo { sha256: sha256.clone(), size_bytes: bytes.len() as u64, views: 1, frames: 3 },
        serial: None,
        connection: None,
        client_reference: None,
        station: None,
        request_sha256: crestscan::service::store::files::sha256_hex(format!("{sha256}{options_json}").as_bytes()),
        options_json,
        idempotency_key: key.map(str::to_string),
        max_attempts: 3,
    };
    store.insert_inspection(&new, file).await.map_err(|e| {
        assert!(e.is_storage_full(), "a write failed otherwise than for want of space: {e}");
        e.to_string()
    })
}

/// The data directory's SQLite file, whichever backend the suite runs the service on: the tests
/// that use it check SQLite's own behaviour (its write lock, its WAL on a full disk).
async fn open_sqlite(data: &Path) -> Store {
    Store::open(&data.join("crestscan.db"), &data.join("uploads"), &data.join("tmp")).await.unwrap()
}

fn created(inserted: Inserted) -> String {
    match inserted {
        Inserted::Created(row) => row.id,
        Inserted::Replayed(_) => panic!("expected a new inspection"),
    }
}

/// The root cause of issue 48's lost 202s: a COMMIT that failed with SQLITE_FULL left sqlx
/// counting a transaction SQLite had already rolled back, and the connection went back to the
/// pool. Later transactions on it were savepoints inside a transaction that never committed,
/// holding the write lock. Here: commits fail on a full disk, then, with the space back, every
/// commit is durable (seen after the store is closed and opened again) and another connection
/// gets the write lock at once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_commit_that_fails_for_space_leaves_no_transaction_behind() {
    let disk = Tmpfs::mount(16);
    let data = disk.path().join("d");
    let store = open_sqlite(&data).await;
    let first = created(insert(&store, b"first upload", "{}".into(), None).await.unwrap());

    // Options of 2 MiB: the row fits the page cache, and its WAL frames cannot be written.
    let big = format!("{{\"pad\":\"{}\"}}", "x".repeat(2 << 20));
    let filler = disk.fill(256 << 10);
    for i in 0..3 {
        let error = insert(&store, format!("big {i}").as_bytes(), big.clone(), None)
            .await
            .err()
            .expect("a commit on a full disk");
        // The commit's error, or (once the failed commit's frames took the last pages) the
        // upload file's own.
        assert!(error.contains("full") || error.contains("No space left"), "{error}");
    }
    filler.give_back();

    // Space is back: new inspections, an idempotent replay (its transaction rolls back), more.
    let mut ids = vec![first];
    ids.push(created(insert(&store, b"keyed", "{}".into(), Some("k-1")).await.unwrap()));
    assert!(matches!(insert(&store, b"keyed", "{}".into(), Some("k-1")).await.unwrap(), Inserted::Replayed(_)));
    for i in 0..4 {
        ids.push(created(insert(&store, format!("after {i}").as_bytes(), "{}".into(), None).await.unwrap()));
    }
    store.probe_write().await.expect("a write commits");

    // Another connection takes the write lock at once: nothing holds it.
    {
        use sqlx::{ConnectOptions, Connection};
        let mut other = sqlx::sqlite::SqliteConnectOptions::new()
            .filename(data.join("crestscan.db"))
            .busy_timeout(Duration::from_secs(2))
            .connect()
            .await
            .unwrap();
        sqlx::raw_sql("BEGIN IMMEDIATE; ROLLBACK").execute(&mut other).await.expect("the write lock is free");
        other.close().await.unwrap();
    }
    store.close().await;
    drop(store);

    let reopened = open_sqlite(&data).await;
    for id in &ids {
        reopened.inspection(id).await.unwrap_or_else(|e| panic!("inspection {id} accepted but not stored: {e}"));
    }
    let stored: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM inspections")
        .fetch_one(reopened.sqlite_pool().unwrap())
        .await
        .unwrap();
    assert_eq!(stored, ids.len() as i64, "only the accepted inspections are stored");
    reopened.close().await;
}

/// A connection handed back with a transaction open (here begun by hand, behind sqlx's back) is
/// closed by the pool, not lent to the next caller: the next write commits for real.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_pool_closes_a_connection_returned_inside_a_transaction() {
    let dir = tempfile::tempdir().unwrap();
    let store = open_sqlite(dir.path()).await;
    {
        let mut conn = store.sqlite_pool().unwrap().acquire().await.unwrap();
        sqlx::raw_sql("BEGIN IMMEDIATE").execute(&mut *conn).await.unwrap();
    }
    store.probe_write().await.unwrap();
    let id = created(insert(&store, b"after", "{}".into(), None).await.unwrap());
    store.close().await;
    let reopened = open_sqlite(dir.path()).await;
    reopened.inspection(&id).await.expect("committed");
    reopened.close().await;
}

/// The reproduction over HTTP, three rounds in a row: with the disk full every upload is
/// 507 (none 500, no 202), CMM data too, and `/readyz` says not ready; with the space back
/// `/readyz` is ready again without a restart and uploads are accepted; after a restart every
/// accepted inspection is there and no upload file is left without its row.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_answers_507_and_every_202_survives_recovery_and_restart() {
    let disk = Tmpfs::mount(96);
    let data = disk.path().join("d");
    let settings = |s: &mut Settings| {
        s.min_free_disk_mb = 1;
        s.workers = 1;
    };
    let app = spawn_app_in(&data, settings).await;
    let bundle = ci_tar();
    let submit = |app: &TestApp| {
        let (client, url, body) = (app.client.clone(), app.url("/v1/inspections"), bundle.clone());
        async move { client.post(url).header("content-type", "application/x-tar").body(body).send().await.unwrap() }
    };
    // One inspection done with room to spare: its result takes CMM data below.
    let first = submit(&app).await;
    assert_eq!(first.status(), StatusCode::ACCEPTED);
    let first: String = first.json::<Value>().await.unwrap()["id"].as_str().unwrap().into();
    assert_eq!(app.wait(&first, Duration::from_secs(120)).await["status"], "succeeded");
    let mut accepted = vec![first.clone()];

    for round in 0..3 {
        // Room for the upload but not much more: the worker's result may not fit (it goes back to
        // the queue). Then nothing at all.
        let tight = disk.fill((2 << 20) + 2 * bundle.len() as u64);
        let response = submit(&app).await;
        let status = response.status();
        assert!(
            [StatusCode::ACCEPTED, StatusCode::INSUFFICIENT_STORAGE].contains(&status),
            "round {round}: {status} {}",
            response.text().await.unwrap()
        );
        if status == StatusCode::ACCEPTED {
            accepted.push(response.json::<Value>().await.unwrap()["id"].as_str().unwrap().into());
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
        let full = disk.fill(0);
        for i in 0..8 {
            let response = submit(&app).await;
            let status = response.status();
            let body = response.text().await.unwrap();
            assert_eq!(status, StatusCode::INSUFFICIENT_STORAGE, "round {round}, upload {i}: {body}");
            assert!(body.contains("insufficient_storage"), "{body}");
        }
        let cmm = app
            .client
            .put(app.url(&format!("/v1/inspections/{first}/cmm")))
            .header("content-type", "text/csv")
            .body(format!("# instrument: {}\nthread,angle_deg,height_mm\n3,12.5,1.5748\n", "x".repeat(150)))
            .send()
            .await
            .unwrap();
        let status = cmm.status();
        assert!(
            [StatusCode::OK, StatusCode::INSUFFICIENT_STORAGE].contains(&status),
            "round {round}: CMM data on a full disk: {status} {}",
            cmm.text().await.unwrap()
        );
        // Full again at this moment: a job that ended meanwhile frees its temporaries (with an
        // object store, the worker's downloaded copy of its bundle).
        let refill = disk.fill(0);
        let ready = app.get("/readyz").await;
        assert_eq!(ready.status(), StatusCode::SERVICE_UNAVAILABLE, "round {round}: ready on a full disk");

        refill.give_back();
        full.give_back();
        tight.give_back();
        let start = Instant::now();
        while app.get("/readyz").await.status() != StatusCode::OK {
            assert!(
                start.elapsed() < Duration::from_secs(15),
                "round {round}: not ready again after the space returned"
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        for i in 0..8 {
            let response = submit(&app).await;
            let status = response.status();
            let v: Value = response.json().await.unwrap();
            assert_eq!(status, StatusCode::ACCEPTED, "round {round}, upload {i} with room again: {v}");
            let id = v["id"].as_str().unwrap().to_string();
            assert_eq!(app.get(&format!("/v1/inspections/{id}")).await.status(), StatusCode::OK);
            accepted.push(id);
        }
    }

    app.stop().await;
    let app = spawn_app_in(&data, |s| {
        s.min_free_disk_mb = 1;
        s.workers = 0;
    })
    .await;
    for id in &accepted {
        let response = app.get(&format!("/v1/inspections/{id}")).await;
        assert_eq!(response.status(), StatusCode::OK, "inspection {id} answered 202 and is gone after a restart");
    }
    // Every upload file has its row (one bundle, so one file), and no row lacks its file.
    let store = app.store().await;
    let live: Vec<String> = store.live_uploads().await.unwrap().into_iter().map(|(sha, _)| sha).collect();
    let stored = store.blobs.list().await.unwrap();
    assert_eq!(stored.len(), live.len(), "upload files without a row, or rows without a file");
    for sha in &live {
        assert!(stored.contains(sha), "row {sha} has no file");
    }
    store.close().await;
    app.stop().await;
}

/// An upload file that no row names (its submission's commit failed after the file was placed) is
/// deleted when the service starts; a file whose row exists is kept.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn upload_files_without_a_row_are_removed_at_start_up() {
    let dir = tempfile::tempdir().unwrap();
    let store = open_store(dir.path()).await;
    let kept = created(insert(&store, b"a real upload", "{}".into(), None).await.unwrap());
    let kept_sha = store.inspection(&kept).await.unwrap().upload_sha256;
    // An upload placed in the blob store (the local directory, or the object store the suite
    // runs against) whose row never committed.
    let orphan_sha = crestscan::service::store::files::sha256_hex(b"an upload whose commit failed");
    let mut staged = store.files.temp_file().unwrap();
    std::io::Write::write_all(&mut staged, b"an upload whose commit failed").unwrap();
    store.blobs.put(&orphan_sha, staged).await.unwrap();
    assert!(store.blobs.list().await.unwrap().contains(&orphan_sha));
    store.close().await;
    // Not ours: names of another shape are left alone.
    std::fs::create_dir_all(dir.path().join("uploads")).unwrap();
    let stranger = dir.path().join("uploads").join("README");
    std::fs::write(&stranger, b"left by a person").unwrap();

    let app = spawn_app_in(dir.path(), |s| s.workers = 0).await;
    let store = app.store().await;
    let stored = store.blobs.list().await.unwrap();
    assert!(!stored.contains(&orphan_sha), "the orphan upload is still there");
    assert!(stranger.exists());
    assert!(stored.contains(&kept_sha), "the upload with its row was removed");
    store.close().await;
    app.stop().await;
}
