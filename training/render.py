"""Renders the training and held-out bundles with `crestscan simulate` at random stations.

Each seed s draws its station and its part's randomness from s, and its defect preset as
PRESETS[s mod 10] (as the station suites do). Bundles already rendered are kept.

    python training/render.py [--split train|heldout|all] [--max N]
"""

import argparse
import json
import shutil
import subprocess
import sys

from common import DATA, HELDOUT_SEEDS, MAX_STACK_PIXELS, TRAIN_SEEDS, binary, case_name, preset_of


def stack_pixels(spec: dict) -> float:
    return len(spec["views"]) * len(spec["offsets_mm"]) * spec["width"] * spec["height"]


def render(seed: int, split: str) -> str:
    preset = preset_of(seed)
    out = DATA / "bundles" / split / case_name(preset, seed)
    if (out / "manifest.json").exists():
        return "cached"
    args = [str(binary()), "simulate", "--preset", preset, "--station", "random", "--station-seed", str(seed),
            "--seed", str(seed), "--quiet"]
    spec = json.loads(subprocess.run(args + ["--print-spec"], check=True, capture_output=True, text=True).stdout)
    if stack_pixels(spec) > MAX_STACK_PIXELS:
        return f"skipped ({stack_pixels(spec) / 1e6:.0f} M stack pixels)"
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    subprocess.run(args + ["--out", str(partial)], check=True, capture_output=True)
    partial.rename(out)
    return "rendered"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--split", choices=["train", "heldout", "all"], default="all")
    parser.add_argument("--max", type=int, default=None, help="render at most this many seeds per split")
    a = parser.parse_args()
    splits = {"train": TRAIN_SEEDS, "heldout": HELDOUT_SEEDS}
    for split, seeds in splits.items():
        if a.split not in (split, "all"):
            continue
        for seed in list(seeds)[: a.max]:
            print(f"{split} {case_name(preset_of(seed), seed)}: {render(seed, split)}", flush=True)
            sys.stdout.flush()


if __name__ == "__main__":
    main()
