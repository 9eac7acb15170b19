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

/// Statics are never dropped, so a `TempDir` kept in one would never be removed: the renders are
/// deleted by a C `atexit` hook instead, which runs when the test harness returns from `main`.
fn remove_renders_at_exit() {
    extern "C" fn remove_renders() {
        for dir in [&CI, &TELECENTRIC, &REJECT].into_iter().filter_map(|cell| cell.get()) {
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
