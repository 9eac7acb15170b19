"""Shared settings of the training code: where data lives, which seeds it uses, the binary."""

import os
import pathlib
import subprocess

ROOT = pathlib.Path(__file__).resolve().parent
REPO = ROOT.parent
DATA = pathlib.Path(os.environ.get("CRESTSCAN_TRAINING_DATA", ROOT / "data"))

# The defect presets the station suites draw from (src/eval/suite.rs, STATION_PRESETS): every
# thread family and defect kind.
PRESETS = [
    "bc-black-1", "bc-black-2", "bc-black-3", "bc-arc-over-25", "lc-round-black",
    "lc-accept", "bc-polished", "bc-polished-long", "bc-polished-end", "seed-table1",
]

# Station and part seeds, disjoint from every test (< 100), the tuning stations (1–12), the
# station benchmark (101–140) and the stations rendered after it (141–150).
TRAIN_SEEDS = range(1001, 1041)
HELDOUT_SEEDS = range(1101, 1111)

# Renders above this many frame pixels (frames × width × height) are skipped: the budget of a
# 2-core machine. A random station's stack ranges from ~0.1 to ~2 G pixels.
MAX_STACK_PIXELS = 400e6


def binary() -> pathlib.Path:
    path = pathlib.Path(os.environ.get("CRESTSCAN_BIN", REPO / "target" / "release" / "crestscan"))
    if not path.exists():
        subprocess.run(["cargo", "build", "--release", "--locked"], cwd=REPO, check=True)
    return path


def case_name(preset: str, seed: int) -> str:
    return f"{preset}@{seed}"


def preset_of(seed: int) -> str:
    return PRESETS[seed % len(PRESETS)]
