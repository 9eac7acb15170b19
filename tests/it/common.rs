use crestscan::sim;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

pub const CI_SEED: u64 = 7;

/// The `ci` preset rendered once per test run (seed 7), shared read-only by the tests.
pub fn ci_bundle() -> &'static Path {
    rendered("ci")
}

static CI: OnceLock<PathBuf> = OnceLock::new();
static TELECENTRIC: OnceLock<PathBuf> = OnceLock::new();
static REJECT: OnceLock<PathBuf> = OnceLock::new();

/// A `ci*` preset rendered once per test run (seed 7), removed when the test process exits.
pub fn rendered(preset: &'static str) -> &'static Path {
    let cell = match preset {
        "ci" => &CI,
        "ci-telecentric" => &TELECENTRIC,
        "ci-reject" => &REJECT,
        other => panic!("tests render only the ci presets, not {other}"),
    };
    cell.get_or_init(|| {
        remove_renders_at_exit();
        let dir = tempfile::Builder::new().prefix(&format!("crestscan-{preset}-")).tempdir().unwrap();
        sim::simulate(&sim::preset(preset).unwrap(), CI_SEED, dir.path()).unwrap();
        // Kept (and so removed at exit) only once rendered: a failed render is dropped here.
        dir.keep()
    })
}

/// A rendered bundle's truth (`truth/truth.json` under `dir`).
pub fn truth_of(dir: &Path) -> sim::Truth {
    serde_json::from_slice(&std::fs::read(dir.join("truth/truth.json")).unwrap()).unwrap()
}

/// What a placed render is: preset, the simulator's station (if named), part seed, placement
/// seed, focus drift (its bits).
type PlacedKey = (String, Option<String>, u64, u64, u64);

/// Placed renders made so far in this process, each its own cell (a render in progress holds only
/// its own).
static PLACED: std::sync::Mutex<Vec<(PlacedKey, &'static OnceLock<PathBuf>)>> = std::sync::Mutex::new(Vec::new());

/// A `ci*` preset's part `seed`, placed anew (`placement`: encoders and sensor noise), recorded at
/// the simulator's named station `at` if given, every frame `drift_mm` further along the camera's
/// axis than its manifest says: rendered once per test process (several tests study the same
/// master runs), shared read-only, removed when the process exits. Truth under `truth/`.
pub fn placed(preset: &str, at: Option<&str>, seed: u64, placement: u64, drift_mm: f64) -> &'static Path {
    let key: PlacedKey = (preset.to_string(), at.map(str::to_string), seed, placement, drift_mm.to_bits());
    let cell: &'static OnceLock<PathBuf> = {
        let mut placed = PLACED.lock().unwrap_or_else(|e| e.into_inner());
        match placed.iter().find(|(k, _)| *k == key) {
            Some((_, cell)) => cell,
            None => {
                let cell: &'static OnceLock<PathBuf> = Box::leak(Box::new(OnceLock::new()));
                placed.push((key, cell));
                cell
            }
        }
    };
    cell.get_or_init(|| {
        assert!(preset.starts_with("ci"), "tests render only the ci presets, not {preset}");
        remove_renders_at_exit();
        let dir =
            tempfile::Builder::new().prefix(&format!("crestscan-{preset}-{seed}-{placement}-")).tempdir().unwrap();
        let mut spec = sim::preset(preset).unwrap();
        if let Some(at) = at {
            let station =
                sim::station::station(at, seed, spec.part.pipe_od_mm / 2.0, sim::station::z_span_mm(&spec)).unwrap();
            spec = sim::station::at_station(&spec, &station);
        }
        let spec = sim::SimSpec { focus_drift_mm: drift_mm, ..spec };
        sim::simulate_placed(&spec, seed, placement, dir.path(), &|_| {}).unwrap();
        dir.keep()
    })
}

/// Statics are never dropped, so a `TempDir` kept in one would never be removed: the renders are
/// deleted by a C `atexit` hook instead, which runs when the test harness returns from `main`.
fn remove_renders_at_exit() {
    extern "C" fn remove_renders() {
        for dir in [&CI, &TELECENTRIC, &REJECT].into_iter().filter_map(|cell| cell.get()) {
            let _ = std::fs::remove_dir_all(dir);
        }
        let placed = match PLACED.try_lock() {
            Ok(placed) => placed,
            // A test that panicked while holding the list poisoned it; the renders still go.
            Err(std::sync::TryLockError::Poisoned(e)) => e.into_inner(),
            // A thread still running at exit holds it: leave the renders rather than wait.
            Err(std::sync::TryLockError::WouldBlock) => return,
        };
        for dir in placed.iter().filter_map(|(_, cell)| cell.get()) {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
    unsafe extern "C" {
        fn atexit(callback: extern "C" fn()) -> std::os::raw::c_int;
    }
    static HOOK: std::sync::Once = std::sync::Once::new();
    // SAFETY: the declaration matches C's `int atexit(void (*)(void))`, and the callback never
    // unwinds (it ignores every error).
    HOOK.call_once(|| assert_eq!(unsafe { atexit(remove_renders) }, 0, "atexit refused the hook"));
}

/// A private copy of the ci bundle (without truth/) whose manifest a test may edit.
pub struct Scratch {
    pub dir: tempfile::TempDir,
}

impl Scratch {
    pub fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        copy_tree(ci_bundle(), dir.path(), &|p| !p.starts_with("truth"));
        Self { dir }
    }

    pub fn path(&self) -> &Path {
        self.dir.path()
    }

    pub fn manifest(&self) -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(self.path().join("manifest.json")).unwrap()).unwrap()
    }

    pub fn set_manifest(&self, value: &serde_json::Value) {
        std::fs::write(self.path().join("manifest.json"), serde_json::to_vec_pretty(value).unwrap()).unwrap();
    }

    pub fn edit(&self, f: impl FnOnce(&mut serde_json::Value)) {
        let mut m = self.manifest();
        f(&mut m);
        self.set_manifest(&m);
    }
}

pub fn copy_tree(from: &Path, to: &Path, keep: &dyn Fn(&Path) -> bool) {
    for entry in walk(from) {
        let rel = entry.strip_prefix(from).unwrap();
        if !keep(rel) {
            continue;
        }
        let target = to.join(rel);
        std::fs::create_dir_all(target.parent().unwrap()).unwrap();
        std::fs::copy(&entry, &target).unwrap();
    }
}

/// Every file under `dir`, sorted.
pub fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() { stack.push(p) } else { out.push(p) }
        }
    }
    out.sort();
    out
}

/// An S3-compatible server for the tests: moto's (`pip install 'moto[server]'`, which the README's
/// test command and `.ci/run` install), started once per test process on a free loopback port
/// with the bucket `crestscan-it`, killed when the process exits. Its endpoint URL.
pub fn moto_endpoint() -> &'static str {
    static ENDPOINT: OnceLock<String> = OnceLock::new();
    static PID: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    ENDPOINT.get_or_init(|| {
        extern "C" fn stop_moto() {
            let pid = PID.load(std::sync::atomic::Ordering::Relaxed);
            if pid != 0 {
                // SAFETY: signals the child this process started; nothing else is touched.
                unsafe { libc::kill(pid as libc::pid_t, libc::SIGKILL) };
            }
        }
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        // As a module rather than the `moto_server` script, which pip may put off the PATH.
        let child = std::process::Command::new("python3")
            .args(["-m", "moto.server", "-H", "127.0.0.1", "-p", &port.to_string()])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap_or_else(|e| {
                panic!("moto's server could not be started ({e}): python3 -m pip install 'moto[server]==5.2.1'")
            });
        PID.store(child.id(), std::sync::atomic::Ordering::Relaxed);
        // SAFETY: registers a plain C function to run at exit.
        unsafe { libc::atexit(stop_moto) };
        let endpoint = format!("http://127.0.0.1:{port}");
        // Ready when it answers; then the bucket (a plain PUT on its path).
        let start = std::time::Instant::now();
        loop {
            let put = std::process::Command::new("curl")
                .args(["-sf", "-X", "PUT", &format!("{endpoint}/crestscan-it")])
                .output()
                .expect("curl runs");
            if put.status.success() {
                break;
            }
            assert!(
                start.elapsed() < std::time::Duration::from_secs(30),
                "moto's server did not answer on {endpoint} (is `moto[server]` installed?)"
            );
            std::thread::sleep(std::time::Duration::from_millis(200));
        }
        endpoint
    })
}

/// A PostgreSQL server for the tests: Debian's `postgresql-15` (which `.ci/run` installs; the
/// README's test command says how), a cluster of its own initialised in a temporary directory and
/// started once per test process on a free loopback port, stopped and removed when the process
/// exits. `initdb` refuses root, so as root the cluster is the `postgres` user's. Its URL without
/// a database (`postgres://postgres@127.0.0.1:PORT`); each caller names its own database, which
/// the store creates.
pub fn postgres_url() -> &'static str {
    static URL: OnceLock<String> = OnceLock::new();
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    URL.get_or_init(|| {
        extern "C" fn stop_postgres() {
            if let Some(dir) = DIR.get() {
                let _ = pg_command("pg_ctl", dir)
                    .args(["-D", &dir.join("data").to_string_lossy(), "-m", "immediate", "stop"])
                    .stdout(std::process::Stdio::null())
                    .stderr(std::process::Stdio::null())
                    .status();
                let _ = std::fs::remove_dir_all(dir);
            }
        }
        let dir = std::env::temp_dir().join(format!("crestscan-pg-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        // SAFETY: geteuid only reads the process's user id.
        if unsafe { libc::geteuid() } == 0 {
            let chown = std::process::Command::new("chown").args(["postgres:"]).arg(&dir).status();
            assert!(chown.is_ok_and(|s| s.success()), "chown postgres {} (is postgresql-15 installed?)", dir.display());
        }
        let data = dir.join("data");
        let init = pg_command("initdb", &dir)
            .args(["-D", &data.to_string_lossy(), "-A", "trust", "-U", "postgres", "-E", "UTF8", "--locale=C.UTF-8"])
            .arg("--no-sync")
            .output()
            .unwrap_or_else(|e| panic!("initdb could not run ({e}): apt-get install postgresql-15"));
        assert!(init.status.success(), "initdb failed: {}", String::from_utf8_lossy(&init.stderr));
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        // TLS with a certificate of its own for 127.0.0.1 (openssl comes with postgresql-15):
        // sqlx prefers TLS where the server offers it, so every test connection is encrypted.
        let (_, cert, key) = self_signed(&dir, "server");
        // fsync off: the tests kill crestscan's processes, never this server.
        let options = format!(
            "-p {port} -c listen_addresses=127.0.0.1 -k {} -c max_connections=400 -c fsync=off \
             -c synchronous_commit=off -c full_page_writes=off -c ssl=on -c ssl_cert_file={} -c ssl_key_file={}",
            dir.display(),
            cert.display(),
            key.display()
        );
        let start = pg_command("pg_ctl", &dir)
            .args(["-D", &data.to_string_lossy(), "-o", &options, "-l", &dir.join("log").to_string_lossy(), "-w"])
            .arg("start")
            .output()
            .unwrap();
        assert!(
            start.status.success(),
            "pg_ctl start failed: {}{}",
            String::from_utf8_lossy(&start.stderr),
            std::fs::read_to_string(dir.join("log")).unwrap_or_default()
        );
        DIR.set(dir).unwrap();
        // SAFETY: registers a plain C function to run at exit.
        unsafe { libc::atexit(stop_postgres) };
        format!("postgres://postgres@127.0.0.1:{port}")
    })
}

/// The authority that signed the test server's TLS certificate (for 127.0.0.1): the root a client
/// that verifies the server (`sslmode=verify-full&sslrootcert=…`) is given.
pub fn postgres_tls_root() -> PathBuf {
    postgres_url();
    std::env::temp_dir().join(format!("crestscan-pg-{}", std::process::id())).join("server-ca.crt")
}

/// A certificate authority of its own and, signed by it, a certificate and key for 127.0.0.1,
/// under `dir`: (`NAME-ca.crt`, `NAME.crt`, `NAME.key`), readable by the server (owned by
/// `postgres` when this process is root; the key 0600). A leaf apart from its root, as rustls
/// accepts no CA certificate as the server's own.
pub fn self_signed(dir: &Path, name: &str) -> (PathBuf, PathBuf, PathBuf) {
    let path = |suffix: &str| dir.join(format!("{name}{suffix}"));
    let (ca_key, ca, key, csr, cert, ext) =
        (path("-ca.key"), path("-ca.crt"), path(".key"), path(".csr"), path(".crt"), path(".ext"));
    std::fs::write(&ext, "basicConstraints=CA:FALSE\nsubjectAltName=IP:127.0.0.1\n").unwrap();
    let openssl = |args: &[&std::ffi::OsStr]| {
        let out = std::process::Command::new("openssl")
            .args(args)
            .output()
            .unwrap_or_else(|e| panic!("openssl could not run ({e}): apt-get install openssl"));
        assert!(out.status.success(), "openssl {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    };
    let os = |s: &'static str| std::ffi::OsStr::new(s);
    openssl(&[
        os("req"),
        os("-x509"),
        os("-newkey"),
        os("rsa:2048"),
        os("-nodes"),
        os("-days"),
        os("2"),
        os("-subj"),
        os("/CN=crestscan test CA"),
        os("-keyout"),
        ca_key.as_os_str(),
        os("-out"),
        ca.as_os_str(),
    ]);
    openssl(&[
        os("req"),
        os("-newkey"),
        os("rsa:2048"),
        os("-nodes"),
        os("-subj"),
        os("/CN=127.0.0.1"),
        os("-keyout"),
        key.as_os_str(),
        os("-out"),
        csr.as_os_str(),
    ]);
    openssl(&[
        os("x509"),
        os("-req"),
        os("-in"),
        csr.as_os_str(),
        os("-CA"),
        ca.as_os_str(),
        os("-CAkey"),
        ca_key.as_os_str(),
        os("-CAcreateserial"),
        os("-days"),
        os("2"),
        os("-extfile"),
        ext.as_os_str(),
        os("-out"),
        cert.as_os_str(),
    ]);
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
    // SAFETY: geteuid only reads the process's user id.
    if unsafe { libc::geteuid() } == 0 {
        let chown = std::process::Command::new("chown").arg("postgres:").args([&cert, &key]).status();
        assert!(chown.is_ok_and(|s| s.success()), "chown postgres {}", key.display());
    }
    (ca, cert, key)
}

/// A PostgreSQL program (Debian keeps them off the PATH, under /usr/lib/postgresql/15/bin), run as
/// the `postgres` user when this process is root, from `dir` (which that user can read).
fn pg_command(program: &str, dir: &Path) -> std::process::Command {
    let debian = Path::new("/usr/lib/postgresql/15/bin").join(program);
    let program = if debian.is_file() { debian.to_string_lossy().into_owned() } else { program.to_string() };
    // SAFETY: geteuid only reads the process's user id.
    let mut command = if unsafe { libc::geteuid() } == 0 {
        let mut c = std::process::Command::new("runuser");
        c.args(["-u", "postgres", "--", &program]);
        c
    } else {
        std::process::Command::new(program)
    };
    command.current_dir(dir);
    command
}

/// The test suite's backend for the service's records: PostgreSQL ([`postgres_url`]) where
/// `CRESTSCAN_TEST_DATABASE=postgres` (`.ci/run` runs the service suite a third time so), else
/// the embedded SQLite file. Under PostgreSQL each data directory has a database of its own,
/// named from its path, so that processes started on one directory share it.
pub fn test_database_url(data: &Path) -> Option<String> {
    match std::env::var("CRESTSCAN_TEST_DATABASE").as_deref() {
        Ok("postgres") => Some(database_for(data)),
        Ok("sqlite") | Ok("") | Err(_) => None,
        Ok(other) => panic!("CRESTSCAN_TEST_DATABASE={other}: postgres or sqlite"),
    }
}

/// A PostgreSQL database of the test server for `data`: `cs_` and a hash of its path.
pub fn database_for(data: &Path) -> String {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    data.hash(&mut h);
    format!("{}/cs_{:016x}", postgres_url(), h.finish())
}
