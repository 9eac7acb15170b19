"""What the service proofs under scripts/ share: the release build, the ci bundle as a tar, a
server on a loopback port, an HTTP call, and moto's S3 server. Imported by kill-storm,
schemathesis, mixed-load, priority-check, hostile-peak, soak-processes and scale-workers (each runs
from any directory)."""
import os, shutil, socket, subprocess, sys, tarfile, threading, time, urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BIN = os.path.join(ROOT, "target", "release", "crestscan")


def build():
    subprocess.run(["cargo", "build", "--release", "--locked", "--quiet"], cwd=ROOT, check=True)


def fresh_dir(path):
    """`path` made absolute, emptied and created."""
    path = os.path.abspath(path)
    shutil.rmtree(path, ignore_errors=True)
    os.makedirs(path)
    return path


def ci_bundle(work, seed=1):
    """Renders the ci preset into work/ci and writes work/ci.tar (truth/ left out); returns both paths."""
    bundle = os.path.join(work, "ci")
    subprocess.run([BIN, "simulate", "--preset", "ci", "--seed", str(seed), "--out", bundle], check=True,
                   stdout=subprocess.DEVNULL)
    tar_path = os.path.join(work, "ci.tar")
    with tarfile.open(tar_path, "w") as t:
        for name in sorted(os.listdir(bundle)):
            if name != "truth":
                t.add(os.path.join(bundle, name), arcname=name)
    return bundle, tar_path


def serve(data, *extra, stderr=subprocess.DEVNULL, binary=None):
    """Starts `crestscan serve` on 127.0.0.1:0 over `data` (the release build, or `binary`);
    returns the process and its base URL."""
    proc = subprocess.Popen([binary or BIN, "serve", "--bind", "127.0.0.1:0", "--data-dir", data, "--log", "warn", *extra],
                            stdout=subprocess.PIPE, stderr=stderr, text=True)
    line = proc.stdout.readline()
    if "listening on" not in line:
        proc.kill()
        raise SystemExit(f"server did not start: {line!r}")
    # Its logs go on to stdout: read and dropped, or a full pipe would stop the server mid-write.
    threading.Thread(target=lambda: sum(0 for _ in proc.stdout), daemon=True).start()
    return proc, line.strip().split()[-1]


def http(method, url, body=None, headers=None, timeout=60):
    """One request; its status and body (an HTTP error status raises urllib's HTTPError)."""
    request = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    with urllib.request.urlopen(request, timeout=timeout) as response:
        return response.status, response.read()


def moto(bucket):
    """Starts moto's S3 server (`pip install 'moto[server]'`) on a free loopback port with `bucket`
    created; returns the process and its endpoint URL."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    endpoint = f"http://127.0.0.1:{port}"
    for _ in range(150):
        try:
            http("PUT", f"{endpoint}/{bucket}")
            return proc, endpoint
        except OSError:
            time.sleep(0.2)
    proc.kill()
    raise SystemExit(f"moto's server did not answer on {endpoint} (is `moto[server]` installed?)")


def list_keys(endpoint, bucket, prefix):
    """Every key under `prefix` in `bucket`, page by page (S3 answers at most 1000 a request)."""
    import urllib.parse
    keys, token = [], None
    while True:
        query = {"list-type": "2", "prefix": prefix}
        if token:
            query["continuation-token"] = token
        _, body = http("GET", f"{endpoint}/{bucket}?{urllib.parse.urlencode(query)}")
        text = body.decode()
        keys += [k.split("</Key>")[0] for k in text.split("<Key>")[1:]]
        if "<NextContinuationToken>" not in text:
            return keys
        token = text.split("<NextContinuationToken>")[1].split("</NextContinuationToken>")[0]


def s3_flags(bucket, prefix, endpoint):
    """`serve`'s flags for uploads in moto's `bucket` under `prefix` (moto takes any key)."""
    return ["--object-store", f"s3://{bucket}/{prefix}", "--s3-endpoint", endpoint,
            "--s3-access-key-id", "test", "--s3-secret-access-key", "test"]


def postgres(work):
    """Starts a PostgreSQL 15 server of its own (Debian's `postgresql-15`) under work/pg on a free
    loopback port, as the `postgres` user when run as root (initdb refuses root); returns a stop
    function and the server's URL without a database (`postgres://postgres@127.0.0.1:PORT`)."""
    bindir = "/usr/lib/postgresql/15/bin"
    pg = os.path.join(work, "pg")
    shutil.rmtree(pg, ignore_errors=True)
    os.makedirs(pg)
    as_user = []
    if os.geteuid() == 0:
        shutil.chown(pg, "postgres")
        # mkdtemp's directories are root's alone: the postgres user must pass through.
        os.chmod(work, os.stat(work).st_mode | 0o711)
        as_user = ["runuser", "-u", "postgres", "--"]

    def run(program, *args):
        path = os.path.join(bindir, program)
        subprocess.run([*as_user, path if os.path.exists(path) else program, *args], check=True, cwd=pg,
                       stdout=subprocess.DEVNULL)

    run("initdb", "-D", os.path.join(pg, "data"), "-A", "trust", "-U", "postgres", "-E", "UTF8",
        "--locale=C.UTF-8", "--no-sync")
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    # A server as a plant would run one (fsync on): the proofs measure crestscan on it.
    run("pg_ctl", "-D", os.path.join(pg, "data"), "-l", os.path.join(pg, "log"), "-w", "-o",
        f"-p {port} -c listen_addresses=127.0.0.1 -k {pg} -c max_connections=300", "start")

    def stop():
        run("pg_ctl", "-D", os.path.join(pg, "data"), "-m", "fast", "stop")
    return stop, f"postgres://postgres@127.0.0.1:{port}"
