#!/usr/bin/env python3
"""Offline check of uncertainty variants on station reports against the simulator's truth.

Usage: scripts/u_variants.py REPORTS_DIR WORK_DIR [CASE_GLOB]

REPORTS_DIR holds `<case>.json` (`crestscan inspect <WORK_DIR>/<case> --json`); WORK_DIR/<case>/truth/
truth.json is the truth. For each case, prints the coverage of the expanded uncertainty (the share
of bins whose |error| <= U) and the 95th percentile of |error| / U, as reported and under each
variant of the dispersion and from-nominal terms, rebuilt from the report's budget (the per-bin
noise term is what remains of U once the budget's shared terms are taken out). "before" is the
rule up to 2026-12-04 (dispersion over every height, the part's median's distance from nominal
taken whole). A tool for choosing on some stations and checking on others, not a benchmark.
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


def along_all(report):
    """The RMS departure from each thread's median over every measured bin (threads with under 5
    left out), mm: the dispersion before black crests were left out of it."""
    ss, n = 0.0, 0
    for t in report["threads"]:
        keep = [v for v in t["height_mm"]["values"] if v is not None]
        if len(keep) < 5:
            continue
        m = statistics.median(keep)
        ss += sum((v - m) ** 2 for v in keep)
        n += len(keep)
    return math.sqrt(ss / n) if n else 0.0


def part_from_nominal_all(report):
    """Every measured height's median's distance from nominal, mm (the rule before 2026-12-04's
    per-thread term)."""
    hs = [v for t in report["threads"] for v in t["height_mm"]["values"] if v is not None]
    return abs(statistics.median(hs) - report["nominal_height_mm"]) if hs else 0.0


def coverage(pairs):
    return sum(1 for e, u in pairs if e <= u) / len(pairs) if pairs else None


def ratio_p95(pairs):
    """The 95th percentile (nearest rank) of |error| / U: the factor U would need for 95%."""
    r = sorted(e / u if u > 0 else math.inf for e, u in pairs)
    return r[max(0, math.ceil(0.95 * len(r)) - 1)] if r else None


def main():
    reports, work = sys.argv[1], sys.argv[2]
    pattern = sys.argv[3] if len(sys.argv) > 3 else "*"
    names = sorted(n[:-5] for n in os.listdir(reports) if n.endswith(".json") and fnmatch.fnmatch(n[:-5], pattern))
    variants = {}
    rows = []
    for name in names:
        try:
            report = json.load(open(os.path.join(reports, name + ".json")))
        except json.JSONDecodeError:
            continue  # a refused case's empty report
        if "threads" not in report:
            continue
        truth = json.load(open(os.path.join(work, name, "truth", "truth.json")))
        b = report["uncertainty"]
        k = b["coverage_factor"]
        method, reg, along, part = (1e-3 * b[key] for key in ("method_um", "registration_um", "along_helix_um", "from_nominal_um"))
        by_thread = {t["thread"]: 1e-3 * t["um"] for t in b.get("from_nominal_by_thread", [])}
        failed = along > 0 or part > 0 or bool(by_thread)
        bins = bins_of(report, truth)
        if not bins:
            continue
        med = thread_medians(report)
        local = {w: local_rms(report, med, w) for w in (5, 15, 30, 60)}
        a_all, p_all = (along_all(report), part_from_nominal_all(report)) if failed else (0.0, 0.0)
        nom = lambda th: by_thread.get(th, part)  # noqa: E731
        out = {}
        for name_v, fn in {
            "reported": None,
            "before (every height, the part's distance)": lambda th, kk, h, u_n: k
            * math.sqrt(u_n**2 + method**2 + reg**2 + a_all**2 + p_all**2),
            "no along/nominal": lambda th, kk, h, u_n: k * math.sqrt(u_n**2 + method**2 + reg**2),
            "thread's distance whole": lambda th, kk, h, u_n: k
            * math.sqrt(u_n**2 + method**2 + reg**2 + along**2 + nom(th) ** 2),
            "part's distance / sqrt3": lambda th, kk, h, u_n: k
            * math.sqrt(u_n**2 + method**2 + reg**2 + along**2 + part**2 / 3),
            "along over every height": lambda th, kk, h, u_n: k
            * math.sqrt(u_n**2 + method**2 + reg**2 + a_all**2 + nom(th) ** 2 / 3),
            **{
                f"local{w}": (
                    lambda w: lambda th, kk, h, u_n: k
                    * math.sqrt(u_n**2 + method**2 + reg**2 + local[w].get((th, kk), along) ** 2 + nom(th) ** 2 / 3)
                )(w)
                for w in (5, 15, 30, 60)
            },
            "own departure": lambda th, kk, h, u_n: k
            * math.sqrt(u_n**2 + method**2 + reg**2 + (h - med.get(th, h)) ** 2 + nom(th) ** 2 / 3),
        }.items():
            pairs = []
            for th, kk, h, tv, u in bins:
                # The per-bin noise: what the reported U holds beyond the shared terms.
                u_n = math.sqrt(max(0.0, (u / k) ** 2 - method**2 - reg**2 - along**2 - nom(th) ** 2 / 3))
                uu = u if fn is None or not failed else fn(th, kk, h, u_n)
                pairs.append((abs(h - tv), uu))
            out[name_v] = (coverage(pairs), ratio_p95(pairs))
            variants.setdefault(name_v, []).append(out[name_v])
        err = [1e3 * (h - tv) for _, _, h, tv, _ in bins]
        rms = math.sqrt(sum(e * e for e in err) / len(err))
        rows.append((name, len(bins), rms, 1e3 * along, out))
    keys = list(variants)
    print("coverage % (p95 |error| / U)")
    print("case | bins | err RMS um | along um | " + " | ".join(keys))
    for name, n, rms, al, out in rows:
        print(f"{name} | {n} | {rms:.1f} | {al:.1f} | " + " | ".join(f"{100 * out[v][0]:.1f} ({out[v][1]:.2f})" for v in keys))
    print()
    print("variant | min | median | within 90-99 | over 99 | under 90 | p95 |e|/U min-max")
    for v in keys:
        c = [x[0] for x in variants[v]]
        q = [x[1] for x in variants[v]]
        print(
            f"{v} | {100 * min(c):.1f} | {100 * statistics.median(c):.1f} | "
            f"{sum(0.9 <= x <= 0.99 for x in c)} | {sum(x > 0.99 for x in c)} | {sum(x < 0.9 for x in c)} | "
            f"{min(q):.2f}-{max(q):.2f}"
        )


if __name__ == "__main__":
    main()
