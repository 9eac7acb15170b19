"""Trains the seed's profile-correction MLP and exports it to models/profile-mlp.onnx.

The seed: an MLP with three hidden layers on 256 samples of one pitch of profile, AdamW, dropout
0.2, MSE, mapping the reconstructed profile to the CMM's. Here the answers are the simulator's true
pitches (`crestscan pairs` over the bundles training/render.py rendered at random stations), or,
for a plant's refit, a CMM's heights (`--pairs` files from `GET /v1/inspections/{id}/training-pairs`
have `target_height_mm` and no `target`): the height is a linear function of the pitch (the crest
window's mean minus the root windows'), so those rows are fitted on it alone.

The net predicts a correction added to its input (a residual): an untrained net changes nothing,
and what it must learn is the reconstruction's error, not the thread form.

    python training/profile_mlp.py                 # pairs from training/data, writes models/
    python training/profile_mlp.py --pairs F.jsonl --init models/profile-mlp.onnx --name plant-a --out DIR
"""

import argparse
import hashlib
import json
import pathlib
import random
import time

import numpy as np
import torch
from torch import nn

from common import DATA, REPO

SAMPLES = 256
HIDDEN = 256


class ProfileMlp(nn.Module):
    def __init__(self, hidden: int = HIDDEN, dropout: float = 0.2):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(SAMPLES, hidden), nn.GELU(), nn.Dropout(dropout),
            nn.Linear(hidden, hidden), nn.GELU(), nn.Dropout(dropout),
            nn.Linear(hidden, hidden), nn.GELU(), nn.Dropout(dropout),
            nn.Linear(hidden, SAMPLES),
        )
        # Starts as the identity: the last layer's weights at zero.
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, profile: torch.Tensor) -> torch.Tensor:
        return profile + self.net(profile)


def read_pairs(paths):
    rows = []
    for path in paths:
        with open(path) as f:
            rows.extend(json.loads(line) for line in f if line.strip())
    return rows


def height_operator(row):
    """The row vector h with h · pitch = the height the pitch reads, mm: the crest window's mean
    minus the root windows' means interpolated at the crest (pipeline::profile::pitch::pitch_height_mm)."""
    (c0, c1), (b0, b1), (a0, a1) = row["windows"]
    w_after = row["root_weight_after"]
    h = np.zeros(SAMPLES, dtype=np.float64)
    h[c0:c1] += 1.0 / max(c1 - c0, 1)
    h[b0:b1] -= (1.0 - w_after) / max(b1 - b0, 1)
    h[a0:a1] -= w_after / max(a1 - a0, 1)
    return (h * row["scale_mm"]).astype(np.float32)


def tensors(rows):
    """Inputs, profile targets (where simulated), the height operators, the fits' heights and the
    answers' heights."""
    x = torch.tensor(np.array([r["input"] for r in rows], dtype=np.float32))
    has_target = torch.tensor([r.get("target") is not None for r in rows])
    y = torch.tensor(np.array([r["target"] if r.get("target") is not None else r["input"] for r in rows], dtype=np.float32))
    h_op = torch.tensor(np.array([height_operator(r) for r in rows]))
    raw = torch.tensor([r["raw_height_mm"] for r in rows], dtype=torch.float32)
    target_h = torch.tensor([r["target_height_mm"] if r.get("target_height_mm") is not None else float("nan") for r in rows], dtype=torch.float32)
    scale = torch.tensor([r["scale_mm"] for r in rows], dtype=torch.float32)
    return x, y, has_target, h_op, raw, target_h, scale


HEIGHT_WEIGHT = 1.0


def loss_of(model, batch):
    """MSE on the pitch where the answer is a pitch, plus MSE on the height the corrected pitch
    reads (in nominal thread heights, the pitch's units) wherever the answer has a height: the
    pipeline reads heights off the corrected pitch, and a CMM gives heights only."""
    x, y, has_target, h_op, raw, target_h, scale = batch
    out = model(x)
    loss = torch.zeros(())
    if has_target.any():
        loss = loss + ((out[has_target] - y[has_target]) ** 2).mean()
    with_height = ~torch.isnan(target_h)
    if with_height.any():
        read = (h_op[with_height] * out[with_height]).sum(1)
        loss = loss + HEIGHT_WEIGHT * (((read - target_h[with_height]) / scale[with_height]) ** 2).mean()
    return loss


def heights_rms_um(model, batch):
    """RMS against the answers, µm: the bins' own fits (the classical height), and the height the
    corrected pitch reads."""
    x, y, has_target, h_op, raw, target_h, scale = batch
    model.eval()
    with torch.no_grad():
        read = (h_op * model(x)).sum(1)
    ok = ~torch.isnan(target_h)
    before = ((raw - target_h)[ok] ** 2).mean().sqrt().item() * 1e3
    after = ((read - target_h)[ok] ** 2).mean().sqrt().item() * 1e3
    return before, after, int(ok.sum())


def subset(batch, index):
    return tuple(t[index] for t in batch)


def export(model, path: pathlib.Path, example: torch.Tensor):
    model.eval()
    torch.onnx.export(
        model, (example,), str(path), input_names=["profile"], output_names=["corrected"],
        dynamic_axes={"profile": {0: "batch"}, "corrected": {0: "batch"}}, opset_version=17, dynamo=False,
    )
    import onnx
    m = onnx.load(str(path))
    # ONNX Runtime 1.31 reads IR ≤ 13 (shared/notes/ort.md).
    m.ir_version = min(m.ir_version, 9)
    onnx.save(m, str(path))


def card_markdown(card) -> str:
    """The model card for people, from the same figures as the JSON card."""
    t, m = card["training"], card["metrics"]
    lines = [
        f"# Model card: {card['name']}",
        "",
        f"- **Role:** {card['role']} (one pitch of reconstructed profile in, the corrected pitch out; heights are read off it).",
        f"- **sha256:** `{card['sha256']}`",
        f"- **Architecture:** {card['architecture']}; input `{card['input']['name']}` {card['input']['shape']}, output `{card['output']['name']}` {card['output']['shape']}.",
        f"- **Input:** {card['input']['meaning']}.",
        f"- **Data:** {t['pairs']} training pairs from {len(t['files'])} bundles rendered at random stations by `training/render.py` (station and part seeds {', '.join(f.split('@')[1].split('.')[0] for f in t['files'])}), validation bundles {', '.join(t['validation_sources']) or 'none'}.",
        f"- **Held out:** {len(t['heldout_files'])} bundles at stations never trained on: {', '.join(f.split('.jsonl')[0] for f in t['heldout_files'])}.",
        f"- **Training:** {t['optimizer']}; {t['loss']}; {t['epochs']} epochs (best at {m.get('best_epoch')}), lr {t['lr']}, seed {t['seed']}, torch {t['torch']}, {t['seconds']} s on this machine's CPU{'; refitted from ' + t['init'] if t.get('init') else ''}.",
        "",
    ]
    if "heldout_height_rms_um" in m:
        lines += ["## Held-out heights (each bin's own height, before the trimmed mean along the helix)", "",
                  "| stations | bins | classical fit RMS µm | read off the MLP's pitch RMS µm |", "|---|---|---|---|"]
        for cls, v in list(m.get("heldout_by_class", {}).items()) + [("all", m["heldout_height_rms_um"])]:
            lines.append(f"| {cls} | {v['bins']} | {v['before']} | {v['after']} |")
        lines.append("")
    lines += ["Reproduce: `python training/profile_mlp.py` (docs/models.md). The whole pipeline's figures with and without",
              "the model are in docs/models.md, measured by `crestscan bench --profile-correction on|off`.", ""]
    return "\n".join(lines)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pairs", nargs="*", help="training pair files [default: training/data/pairs/train/*.jsonl]")
    p.add_argument("--heldout", nargs="*", help="held-out pair files [default: training/data/pairs/heldout/*.jsonl]")
    p.add_argument("--init", help="start from these weights (the .pt file written beside a model's .onnx)")
    p.add_argument("--name", default="profile-mlp")
    p.add_argument("--out", default=str(REPO / "models"))
    p.add_argument("--epochs", type=int, default=60)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=27)
    a = p.parse_args()

    random.seed(a.seed)
    np.random.seed(a.seed)
    torch.manual_seed(a.seed)
    torch.set_num_threads(2)
    train_files = a.pairs or sorted(str(f) for f in (DATA / "pairs" / "train").glob("*.jsonl"))
    heldout_files = a.heldout if a.heldout is not None else sorted(str(f) for f in (DATA / "pairs" / "heldout").glob("*.jsonl"))
    train_rows, heldout_rows = read_pairs(train_files), read_pairs(heldout_files)
    print(f"{len(train_rows)} training pairs from {len(train_files)} files, {len(heldout_rows)} held out from {len(heldout_files)}")
    train = tensors(train_rows)
    n = len(train_rows)
    # A tenth of the training pairs, by bundle, chooses the epoch (early stopping).
    files = sorted({r["source"] for r in train_rows})
    val_sources = set(files[:: max(len(files) // max(len(files) // 10, 1), 1)][: max(len(files) // 10, 1)])
    is_val = torch.tensor([r["source"] in val_sources for r in train_rows])
    fit, val = subset(train, ~is_val), subset(train, is_val)

    model = ProfileMlp()
    if a.init:
        model.load_state_dict(torch.load(a.init))
    opt = torch.optim.AdamW(model.parameters(), lr=a.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, a.epochs)
    best, best_state, best_epoch = float("inf"), None, -1
    started = time.time()
    batch_size = 256
    m = fit[0].shape[0]
    for epoch in range(a.epochs):
        model.train()
        order = torch.randperm(m)
        total = 0.0
        for i in range(0, m, batch_size):
            b = subset(fit, order[i:i + batch_size])
            opt.zero_grad()
            loss = loss_of(model, b)
            loss.backward()
            opt.step()
            total += loss.item() * b[0].shape[0]
        sched.step()
        model.eval()
        with torch.no_grad():
            v = loss_of(model, val).item() if val[0].shape[0] else total / m
        if v < best:
            best, best_epoch = v, epoch
            best_state = {k: t.clone() for k, t in model.state_dict().items()}
        print(f"epoch {epoch}: train {total / m:.5f} val {v:.5f}", flush=True)
    model.load_state_dict(best_state)
    seconds = time.time() - started

    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    onnx_path = out / f"{a.name}.onnx"
    export(model, onnx_path, train[0][:2])
    torch.save(model.state_dict(), out / f"{a.name}.pt")

    # The check the Rust test repeats through ONNX Runtime: the framework's own output on a fixed
    # input (the first held-out pitches, or the first training ones).
    check_rows = (tensors(heldout_rows[:4]) if heldout_rows else subset(train, torch.arange(4)))[0]
    model.eval()
    with torch.no_grad():
        check_out = model(check_rows)
    (out / f"{a.name}.check.json").write_text(json.dumps(
        {"input": check_rows.numpy().round(6).tolist(), "output": check_out.numpy().tolist()}))

    metrics = {"val_loss": best, "best_epoch": best_epoch}
    by_class = {}
    if heldout_rows:
        held = tensors(heldout_rows)
        before, after, count = heights_rms_um(model, held)
        metrics["heldout_height_rms_um"] = {"before": round(before, 2), "after": round(after, 2), "bins": count}
        for cls, lo, hi in [("fine", 0, 0.06), ("medium", 0.06, 0.10), ("coarse", 0.10, 9)]:
            idx = torch.tensor([lo < r["object_pixel_mm"] <= hi for r in heldout_rows])
            if idx.any():
                b, af, c = heights_rms_um(model, subset(held, idx))
                by_class[cls] = {"before": round(b, 2), "after": round(af, 2), "bins": c}
        metrics["heldout_by_class"] = by_class
        print(json.dumps(metrics, indent=1))
    sha = hashlib.sha256(onnx_path.read_bytes()).hexdigest()
    card = {
        "name": a.name,
        "role": "profile_correction",
        "sha256": sha,
        "input": {"name": "profile", "shape": ["batch", SAMPLES], "meaning": "one pitch, root centre to root centre, minus its mean, in nominal thread heights"},
        "output": {"name": "corrected", "shape": ["batch", SAMPLES]},
        "architecture": f"residual MLP {SAMPLES}-{HIDDEN}-{HIDDEN}-{HIDDEN}-{SAMPLES}, GELU, dropout 0.2",
        "training": {
            "pairs": n, "files": [pathlib.Path(f).name for f in train_files], "validation_sources": sorted(val_sources),
            "heldout_files": [pathlib.Path(f).name for f in heldout_files], "epochs": a.epochs, "lr": a.lr,
            "optimizer": "AdamW (weight decay 1e-4), cosine schedule, batch 256", "loss": "MSE on the pitch plus MSE on the height read off it (simulated pairs); on the height alone (CMM pairs)",
            "seed": a.seed, "seconds": round(seconds, 1), "torch": torch.__version__, "init": a.init,
        },
        "metrics": metrics,
    }
    (out / f"{a.name}.json").write_text(json.dumps(card, indent=1) + "\n")
    (out / f"{a.name}.md").write_text(card_markdown(card))
    print(f"{onnx_path}: sha256 {sha}, {seconds:.0f} s")


if __name__ == "__main__":
    main()
