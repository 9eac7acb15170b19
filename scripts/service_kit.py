"""What the service proofs under scripts/ share: the release build, the ci bundle as a tar, and a
server on a loopback port. Imported by kill-storm, schemathesis, mixed-load, priority-check and
hostile-peak (each runs from any directory)."""
import os, shutil, subprocess, tarfile

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


def serve(data, *extra, stderr=subprocess.DEVNULL):
    """Starts `crestscan serve` on 127.0.0.1:0 over `data`; returns the process and its base URL."""
    proc = subprocess.Popen([BIN, "serve", "--bind", "127.0.0.1:0", "--data-dir", data, "--log", "warn", *extra],
                            stdout=subprocess.PIPE, stderr=stderr, text=True)
    line = proc.stdout.readline()
    if "listening on" not in line:
        proc.kill()
        raise SystemExit(f"server did not start: {line!r}")
    return proc, line.strip().split()[-1]
