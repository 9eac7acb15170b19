#!/usr/bin/env python3
"""Offline check of uncertainty variants on station reports against the simulator's truth.

Usage: scripts/u_variants.py REPORTS_DIR WORK_DIR [CASE_GLOB]

REPORTS_DIR holds `<case>.json` (`crestscan inspect <WORK_DIR>/<case> --json`); WORK_DIR/<case>/truth/
truth.json is the truth. For each case, prints the coverage of the expanded uncertainty (the share
of bins whose |error| <= U) as reported and under each variant of the dispersion term, rebuilt from
the report's budget (the per-bin noise term is what remains of U once the budget's shared terms are
taken out). A tool for choosing on some stations and checking on others, not a benchmark.
"""
import fnmatch
import json
import math
import os
import statistics
import sys


def bins_of(report, truth):
    """[(thread, k, measured, true, U)] over the bins both have, mm."""
    out = []
    by_index = {t["index"]: t for t in report["threads"]}
    for t in truth["threads"]:
        r = by_index.get(t["index"])
        if r is None:
            continue
        hv, uv = r["height_mm"]["values"], r["height_mm"].get("uncertainty_mm") or []
        for k, tv in enumerate(t["height_mm"]["values"]):
            if tv is None or k >= len(hv) or hv[k] is None or k >= len(uv) or uv[k] is None:
                continue
            out.append((t["index"], k, hv[k], tv, uv[k]))
    return out


def thread_medians(report):
    med = {}
    for t in report["threads"]:
        hs = [h for h in t["height_mm"]["values"] if h is not None]
        if len(hs) >= 5:
            med[t["index"]] = statistics.median(hs)
    return med


def local_rms(report, med, half):
    """Per (thread, k): RMS departure from the thread's median over measured bins within +-half."""
    out = {}
    for t in report["threads"]:
        if t["index"] not in med:
            continue
        hs = t["height_mm"]["values"]
        m = med[t["index"]]
        for k, h in enumerate(hs):
            if h is None:
                continue
            window = [hs[j] - m for j in range(max(0, k - half), min(len(hs), k + half + 1)) if hs[j] is not None]
            if len(window) >= 5:
                out[(t["index"], k)] = math.sqrt(sum(d * d for d in window) / len(window))
    return out


def along_excluding_black(report, margin_deg):
    """The RMS departure from each thread's median over bins outside its black-crest arcs widened by
    margin_deg (threads with under 5 such bins left out), mm; None without such a thread."""
    ss, n = 0.0, 0
    for t in report["threads"]:
        arcs = t["black_crest_arcs_deg"]
        keep = [
            v
            for v, a in zip(t["height_mm"]["values"], t["height_mm"]["angles_deg"])
            if v is not None and not any(lo - margin_deg <= a <= hi + margin_deg for lo, hi in arcs)
        ]
        if len(keep) < 5:
            continue
        m = statistics.median(keep)
        ss += sum((v - m) ** 2 for v in keep)
        n += len(keep)
    return math.sqrt(ss / n) if n else None


def coverage(pairs):
    return sum(1 for e, u in pairs if e <= u) / len(pairs) if pairs else None


def main():
    reports, work = sys.argv[1], sys.argv[2]
    pattern = sys.argv[3] if len(sys.argv) > 3 else "*"
    names = sorted(n[:-5] for n in os.listdir(reports) if n.endswith(".json") and fnmatch.fnmatch(n[:-5], pattern))
    variants = {}
    rows = []
    for name in names:
        report = json.load(open(os.path.join(reports, name + ".json")))
        if "threads" not in report:
            continue
        truth = json.load(open(os.path.join(work, name, "truth", "truth.json")))
        b = report["uncertainty"]
        k = b["coverage_factor"]
        shared = [1e-3 * b[key] for key in ("method_um", "registration_um", "along_helix_um", "from_nominal_um")]
        method, reg, along, from_nom = shared
        bins = bins_of(report, truth)
        if not bins:
            continue
        med = thread_medians(report)
        local = {w: local_rms(report, med, w) for w in (5, 15, 30, 60)}
        pooled_sq = sum(x * x for x in shared)
        ex = {m: along_excluding_black(report, m) for m in (0, 3, 10)}
        out = {}
        for name_v, fn in {
            "reported": lambda th, kk, h, u_n: None,
            "no along/nominal": lambda th, kk, h, u_n: k * math.sqrt(u_n**2 + method**2 + reg**2),
            **{
                f"local{w}+nom": (
                    lambda w: lambda th, kk, h, u_n: k
                    * math.sqrt(u_n**2 + method**2 + reg**2 + local[w].get((th, kk), along) ** 2 + from_nom**2)
                )(w)
                for w in (5, 15, 30, 60)
            },
            **{
                f"exblack{m}+nom": (
                    lambda m: lambda th, kk, h, u_n: k
                    * math.sqrt(u_n**2 + method**2 + reg**2 + (ex[m] if ex[m] is not None else along) ** 2 + from_nom**2)
                )(m)
                for m in (0, 3, 10)
            },
            "own+nom": lambda th, kk, h, u_n: k
            * math.sqrt(u_n**2 + method**2 + reg**2 + (h - med.get(th, h)) ** 2 + from_nom**2),
            "own+along/2+nom": lambda th, kk, h, u_n: k
            * math.sqrt(u_n**2 + method**2 + reg**2 + (h - med.get(th, h)) ** 2 + (along / 2) ** 2 + from_nom**2),
        }.items():
            pairs = []
            for th, kk, h, tv, u in bins:
                u_n = math.sqrt(max(0.0, (u / k) ** 2 - pooled_sq))
                uu = u if name_v == "reported" else fn(th, kk, h, u_n)
                pairs.append((abs(h - tv), uu))
            out[name_v] = coverage(pairs)
            variants.setdefault(name_v, []).append(out[name_v])
        err = [1e3 * (h - tv) for _, _, h, tv, _ in bins]
        rms = math.sqrt(sum(e * e for e in err) / len(err))
        rows.append((name, len(bins), rms, 1e3 * along, 1e3 * from_nom, out))
    keys = list(variants)
    print("case | bins | err RMS um | along um | nominal um | " + " | ".join(keys))
    for name, n, rms, al, fn_, out in rows:
        print(f"{name} | {n} | {rms:.1f} | {al:.1f} | {fn_:.1f} | " + " | ".join(f"{100 * out[v]:.1f}" for v in keys))
    print()
    print("variant | min | median | within 90-99 | over 99 | under 90")
    for v in keys:
        c = variants[v]
        print(
            f"{v} | {100 * min(c):.1f} | {100 * statistics.median(c):.1f} | "
            f"{sum(0.9 <= x <= 0.99 for x in c)} | {sum(x > 0.99 for x in c)} | {sum(x < 0.9 for x in c)}"
        )


if __name__ == "__main__":
    main()
