"""Writes `crestscan pairs` for every rendered bundle (training/render.py) that has none yet:
training/data/pairs/<split>/<case>.jsonl.

    python training/pairs.py
"""

import subprocess

from common import DATA, binary


def main() -> None:
    for split in ["train", "heldout"]:
        for bundle in sorted((DATA / "bundles" / split).glob("*@*")):
            if bundle.name.endswith(".partial") or not (bundle / "manifest.json").exists():
                continue
            out = DATA / "pairs" / split / f"{bundle.name}.jsonl"
            if out.exists():
                continue
            out.parent.mkdir(parents=True, exist_ok=True)
            run = subprocess.run([str(binary()), "pairs", str(bundle), "--out", str(out)], capture_output=True, text=True)
            # A bundle the pipeline cannot inspect (no depth, no thread at that station) gives no
            # pairs; it is reported and left out.
            print(f"{split} {bundle.name}: {run.stderr.strip().splitlines()[0] if run.stderr.strip() else run.returncode}", flush=True)


if __name__ == "__main__":
    main()
