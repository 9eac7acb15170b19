"""Side-by-side of `crestscan bench --json` runs (the same suite with classic or CNN depth, profile
correction off, on, auto): per station class, the depth error (median over cases of each case's
RMS and median), the heights' RMS (median and worst case), the worst |error|, the uncertainty's
coverage, wrong verdicts and decisions, the depth stage's time per view, and the learned parts'
time against the classical depth measure's in the same run (the U-Nets' share of the depth stage
against the rest of it; the MLP's against the whole depth stage).

    python training/compare.py off=out/st-off.json on=out/st-on.json cnn=out/st-cnn.json
"""

import json
import statistics
import sys


def klass(px):
    # As the bench's table (src/eval/table.rs): fine ≤ 0.06 mm, medium ≤ 0.10 mm, coarse above.
    return "fine" if px <= 0.06 else "medium" if px <= 0.10 else "coarse"


def rows(cases):
    out = {}
    for c in cases:
        a = c.get("accuracy")
        if not a or a["bins_compared"] == 0:
            continue
        cls = klass(c["station"]["object_pixel_mm"])
        stages = dict(c["stage_seconds"])
        out.setdefault(cls, []).append({
            "rms": a["height_rms_um"], "max": a["height_max_um"], "cov": a["uncertainty_coverage"],
            "verdict_wrong": not a["verdict_agrees"], "decision_wrong": bool(a.get("decision_wrong")),
            "depth_s": stages.get("depth", 0.0), "mlp_s": stages.get("profile_correction", 0.0),
            "cnn_s": stages.get("depth_cnn", 0.0),
            "depth_rms": c.get("depth_rms_um"), "depth_median": c.get("depth_median_um"),
            "views": c["station"]["views"],
        })
    return out


def main():
    runs = [arg.split("=", 1) for arg in sys.argv[1:]]
    print("| stations | run | cases | depth RMS / median µm | height RMS median / worst µm | worst abs error µm | "
          "U coverage min / median | verdicts wrong | decisions wrong | depth s / view | U-Nets / classic depth | "
          "MLP / depth |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    data = {name: rows(json.load(open(path))) for name, path in runs}
    for cls in ["fine", "medium", "coarse"]:
        for name, _ in runs:
            r = data[name].get(cls, [])
            if not r:
                continue
            covs = [x["cov"] for x in r if x["cov"] is not None]
            depth, mlp = sum(x["depth_s"] for x in r), sum(x["mlp_s"] for x in r)
            cnn, views = sum(x["cnn_s"] for x in r), sum(x["views"] for x in r)
            d_rms = [x["depth_rms"] for x in r if x["depth_rms"] is not None]
            d_med = [x["depth_median"] for x in r if x["depth_median"] is not None]
            depth_cell = f"{statistics.median(d_rms):.0f} / {statistics.median(d_med):.0f}" if d_rms and d_med else "–"
            print(f"| {cls} | {name} | {len(r)} | {depth_cell} | "
                  f"{statistics.median(x['rms'] for x in r):.1f} / {max(x['rms'] for x in r):.1f} | "
                  f"{max(x['max'] for x in r):.0f} | {100 * min(covs):.1f}% / {100 * statistics.median(covs):.1f}% | "
                  f"{sum(x['verdict_wrong'] for x in r)} | {sum(x['decision_wrong'] for x in r)} | "
                  f"{depth / views:.3f} | {(cnn / (depth - cnn) if depth > cnn else 0):.2f} | "
                  f"{(mlp / depth if depth else 0):.3f} |")


if __name__ == "__main__":
    main()
