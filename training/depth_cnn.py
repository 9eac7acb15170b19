"""Trains the seed's depth networks and exports them, as one graph, to models/depth-unet.onnx.

The seed: a defocus U-Net on 8-channel frames (RGB, HSV, gray, Canny edges) and a depth U-Net on
the stacked defocus maps, 4 down / 4 up levels of two 3×3 convolutions and a 2×2 max-pool, L2 on
depth only. Here:

- The frames are brought onto the offset-0 pixel grid first (focus breathing: a perspective
  frame at offset o is scaled about the principal point by (F − o)/F, as the classical depth stage
  does), so a pixel's column through the stack sees one point of the part.
- The 8 channels are computed inside the graph from RGB in [0, 1], so Rust feeds plain colour:
  RGB, HSV, gray and an edge channel. The edge channel is Canny's gradient stage (Gaussian, then
  the Sobel magnitude) without non-maximum suppression and hysteresis, which are not
  differentiable and would need thresholds per station.
- Stacks differ in length and spacing: the defocus U-Net runs on every frame (shared weights), and
  its maps are resampled linearly, in offset, onto K fixed planes spanning the stack (the matrix
  `planes` [K, n], computed by the caller from the offsets). The depth U-Net maps the K defocus
  maps to K logits; the depth is the softmax-weighted plane index (soft argmax), in plane units,
  so the net never sees millimetres and works at any spacing. Its peak probability is the
  confidence.
- Training is end to end, supervised on depth only (L2 in plane units over the pixels with truth).

    python training/depth_cnn.py                       # crops from training/data, writes models/
"""

import argparse
import hashlib
import json
import pathlib
import random
import time

import cv2
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from common import DATA, REPO

PLANES = 16
CROP = 64
BASE = 8


# ---------------------------------------------------------------------------------------------
# The data: aligned crops of real renders with their true depth, in plane units.


def axis_taps(length: int, centre: float, scale: float, start: int, count: int):
    """Bilinear taps of the offset-0 grid's indices start..start+count in a frame scaled by
    `scale` about `centre` (src/pipeline/depth/resample.rs, axis_taps)."""
    i = np.arange(start, start + count, dtype=np.float64)
    s = centre + (i + 0.5 - centre) * scale - 0.5
    i0 = np.clip(np.floor(s), 0, length - 1).astype(np.int64)
    i1 = np.minimum(i0 + 1, length - 1)
    f = np.clip(s - i0, 0.0, 1.0).astype(np.float32)
    return i0, i1, f


def plane_matrix(offsets: np.ndarray, planes: int = PLANES) -> np.ndarray:
    """[planes, n]: each plane's linear weights on the frames bracketing its offset; the planes
    span the stack's offsets evenly (src/learned/depth_cnn.rs computes the same)."""
    n = len(offsets)
    order = np.argsort(offsets, kind="stable")
    o = offsets[order]
    lo, hi = o[0], o[-1]
    m = np.zeros((planes, n), dtype=np.float32)
    for j in range(planes):
        p = lo + (hi - lo) * j / (planes - 1)
        k = int(np.clip(np.searchsorted(o, p, side="right") - 1, 0, n - 2))
        span = o[k + 1] - o[k]
        f = 0.0 if span <= 0 else float(np.clip((p - o[k]) / span, 0.0, 1.0))
        m[j, order[k]] += 1.0 - f
        m[j, order[k + 1]] += f
    return m


def read_frame(path: pathlib.Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SystemExit(f"{path}: cannot read")
    full = 65535.0 if img.dtype == np.uint16 else 255.0
    img = img.astype(np.float32) / full
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    else:
        img = img[:, :, ::-1]  # BGR → RGB
    return img


def read_pfm(path: pathlib.Path) -> np.ndarray:
    with open(path, "rb") as f:
        kind = f.readline().strip()
        w, h = map(int, f.readline().split())
        scale = float(f.readline())
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    channels = 3 if kind == b"PF" else 1
    img = data.reshape(h, w, channels)[:, :, 0] if channels == 3 else data.reshape(h, w)
    return np.flipud(img).copy()


def crops_of(bundle: pathlib.Path, count: int, rng: random.Random, crop: int = CROP):
    manifest = json.loads((bundle / "manifest.json").read_text())
    optics = manifest["optics"]
    big_f = optics["focus_distance_mm"]
    telecentric = optics["projection"] == "telecentric"
    views = list(manifest["views"])
    rng.shuffle(views)
    out = []
    for view in views:
        if len(out) >= count:
            break
        truth = read_pfm(bundle / "truth" / f"{view['id']}.depth.pfm")
        h, w = truth.shape
        if h < crop or w < crop:
            continue
        offsets = np.array([f["offset_mm"] for f in view["frames"]], dtype=np.float64)
        lo, hi = offsets.min(), offsets.max()
        in_focus = big_f - truth
        target = (in_focus - lo) / (hi - lo) * (PLANES - 1)
        valid = np.isfinite(target) & (target >= 0) & (target <= PLANES - 1)
        cx, cy = optics["principal_point_px"] if optics.get("principal_point_px") else (w / 2, h / 2)
        frames = None
        for _ in range(4):  # a few tries per view for a crop mostly on the part
            y0, x0 = rng.randrange(0, h - crop + 1), rng.randrange(0, w - crop + 1)
            if valid[y0:y0 + crop, x0:x0 + crop].mean() < 0.5:
                continue
            if frames is None:
                frames = [read_frame(bundle / f["file"]) for f in view["frames"]]
            stack = np.empty((len(frames), 3, crop, crop), dtype=np.float16)
            for k, (img, o) in enumerate(zip(frames, offsets)):
                scale = 1.0 if telecentric else (big_f - o) / big_f
                ys = axis_taps(h, cy, scale, y0, crop)
                xs = axis_taps(w, cx, scale, x0, crop)
                rows = img[ys[0]] * (1 - ys[2])[:, None, None] + img[ys[1]] * ys[2][:, None, None]
                pix = rows[:, xs[0]] * (1 - xs[2])[None, :, None] + rows[:, xs[1]] * xs[2][None, :, None]
                stack[k] = pix.transpose(2, 0, 1)
            t = np.where(valid, target, np.nan)[y0:y0 + crop, x0:x0 + crop].astype(np.float32)
            step_mm = (hi - lo) / (PLANES - 1)
            out.append({"frames": stack, "planes": plane_matrix(offsets), "target": t, "step_mm": step_mm,
                        "source": bundle.name})
            if len(out) >= count:
                break
    return out


# ---------------------------------------------------------------------------------------------
# The networks.


def block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
    )


class UNet(nn.Module):
    """The seed's U-Net: 4 levels down (two 3×3 convolutions, a 2×2 max-pool), a bottleneck, 4 up
    (a 2×2 transposed convolution, the skip, two 3×3 convolutions)."""

    def __init__(self, cin: int, cout: int, base: int = BASE):
        super().__init__()
        widths = [base, base * 2, base * 4, base * 8]
        self.down = nn.ModuleList()
        c = cin
        for wdt in widths:
            self.down.append(block(c, wdt))
            c = wdt
        self.bottom = block(c, c * 2)
        c = c * 2
        self.ups, self.up_blocks = nn.ModuleList(), nn.ModuleList()
        for wdt in reversed(widths):
            self.ups.append(nn.ConvTranspose2d(c, wdt, 2, stride=2))
            self.up_blocks.append(block(wdt * 2, wdt))
            c = wdt
        self.head = nn.Conv2d(c, cout, 1)

    def forward(self, x):
        skips = []
        for d in self.down:
            x = d(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        x = self.bottom(x)
        for up, blk, skip in zip(self.ups, self.up_blocks, reversed(skips)):
            x = blk(torch.cat([up(x), skip], dim=1))
        return self.head(x)


def gaussian_sobel():
    g = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0])
    g = (g[:, None] * g[None, :]) / 256.0
    sx = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8.0
    return g[None, None], sx[None, None], sx.t().contiguous()[None, None]


class DepthCnn(nn.Module):
    """frames [n, 3, H, W] (RGB in [0, 1], on the offset-0 grid), planes [K, n] →
    plane [1, 1, H, W] (soft-argmax plane index) and confidence [1, 1, H, W]."""

    def __init__(self, base: int = BASE):
        super().__init__()
        self.defocus = UNet(8, 1, base)
        self.depth = UNet(PLANES, PLANES, base)
        g, sx, sy = gaussian_sobel()
        self.register_buffer("gauss", g)
        self.register_buffer("sobel_x", sx)
        self.register_buffer("sobel_y", sy)
        self.register_buffer("index", torch.arange(PLANES, dtype=torch.float32).view(1, PLANES, 1, 1))

    def channels(self, rgb):
        """The seed's 8 channels from RGB: brightness-normalised RGB, HSV, gray, edges."""
        rgb = rgb / (rgb.mean() * 2.0 + 1e-3)
        r, g, b = rgb[:, 0:1], rgb[:, 1:2], rgb[:, 2:3]
        v = torch.maximum(torch.maximum(r, g), b)
        mn = torch.minimum(torch.minimum(r, g), b)
        c = v - mn
        s = c / (v + 1e-6)
        cs = c + 1e-6
        hue = torch.where(v == r, (g - b) / cs, torch.where(v == g, 2.0 + (b - r) / cs, 4.0 + (r - g) / cs))
        hue = torch.where(c > 1e-6, hue / 6.0, torch.zeros_like(hue))
        gray = 0.299 * r + 0.587 * g + 0.114 * b
        smooth = F.conv2d(F.pad(gray, (2, 2, 2, 2), mode="replicate"), self.gauss)
        padded = F.pad(smooth, (1, 1, 1, 1), mode="replicate")
        edge = torch.sqrt(F.conv2d(padded, self.sobel_x) ** 2 + F.conv2d(padded, self.sobel_y) ** 2 + 1e-8)
        return torch.cat([r, g, b, hue, s, v, gray, edge * 4.0], dim=1)

    def forward_batch(self, frames, planes):
        """frames [B, n, 3, H, W], planes [B, K, n] → plane [B, H, W], confidence [B, H, W]."""
        bsz, n, _, h, w = frames.shape
        x = torch.stack([self.channels(frames[i]) for i in range(bsz)])  # normalised per stack
        d = self.defocus(x.view(bsz * n, 8, h, w)).view(bsz, n, h, w)
        stacked = torch.einsum("bkn,bnhw->bkhw", planes, d)
        p = torch.softmax(self.depth(stacked), dim=1)
        return (p * self.index).sum(1), p.max(1).values

    def forward(self, frames, planes):
        plane, confidence = self.forward_batch(frames[None], planes[None])
        return plane[:, None], confidence[:, None]


# ---------------------------------------------------------------------------------------------
# Training.


def batches(samples, size: int, rng: random.Random):
    """Batches of stacks of equal length where possible (sorted by length, then shuffled)."""
    order = sorted(range(len(samples)), key=lambda i: (samples[i]["frames"].shape[0], rng.random()))
    groups = [order[i:i + size] for i in range(0, len(order), size)]
    rng.shuffle(groups)
    for g in groups:
        n = max(samples[i]["frames"].shape[0] for i in g)
        frames = torch.zeros(len(g), n, 3, CROP, CROP)
        planes = torch.zeros(len(g), PLANES, n)
        target = torch.empty(len(g), CROP, CROP)
        step = torch.empty(len(g))
        for j, i in enumerate(g):
            s = samples[i]
            k = s["frames"].shape[0]
            frames[j, :k] = torch.from_numpy(s["frames"].astype(np.float32))
            frames[j, k:] = frames[j, k - 1]  # padding frames carry no weight in `planes`
            planes[j, :, :k] = torch.from_numpy(s["planes"])
            target[j] = torch.from_numpy(s["target"])
            step[j] = s["step_mm"]
        yield frames, planes, target, step


def evaluate(model, samples):
    """Depth RMS and median over the pixels with truth, µm; per source class later."""
    model.eval()
    errors = []
    with torch.no_grad():
        for frames, planes, target, step in batches(samples, 8, random.Random(0)):
            plane, _ = model.forward_batch(frames, planes)
            e = (plane - target) * step[:, None, None] * 1e3
            errors.append(e[torch.isfinite(target)].abs())
    e = torch.cat(errors)
    return {"rms_um": round(float(e.pow(2).mean().sqrt()), 1), "median_um": round(float(e.median()), 1),
            "pixels": int(e.numel())}


def export(model, path: pathlib.Path):
    model.eval()
    frames = torch.rand(5, 3, 32, 32)
    planes = torch.from_numpy(plane_matrix(np.linspace(-1.0, 1.0, 5)))
    torch.onnx.export(
        model, (frames, planes), str(path), input_names=["frames", "planes"], output_names=["plane", "confidence"],
        dynamic_axes={"frames": {0: "n", 2: "height", 3: "width"}, "planes": {1: "n"},
                      "plane": {2: "height", 3: "width"}, "confidence": {2: "height", 3: "width"}},
        opset_version=17, dynamo=False,
    )
    import onnx
    m = onnx.load(str(path))
    m.ir_version = min(m.ir_version, 9)  # ONNX Runtime 1.31 reads IR ≤ 13 (shared/notes/ort.md)
    onnx.save(m, str(path))


def gather(split: str, per_bundle: int, seed: int):
    cache = DATA / "depth" / f"{split}-{per_bundle}-{seed}.pt"
    if cache.exists():
        return torch.load(cache, weights_only=False)
    rng = random.Random(seed)
    samples = []
    for bundle in sorted((DATA / "bundles" / split).iterdir()):
        if (bundle / "manifest.json").exists():
            got = crops_of(bundle, per_bundle, rng)
            print(f"{split} {bundle.name}: {len(got)} crops", flush=True)
            samples.extend(got)
    cache.parent.mkdir(parents=True, exist_ok=True)
    torch.save(samples, cache)
    return samples


def card_markdown(card) -> str:
    t, m = card["training"], card["metrics"]
    return "\n".join([
        f"# {card['name']}: the seed's defocus and depth U-Nets",
        "",
        f"- role: `{card['role']}`; sha256 `{card['sha256']}`; {card['parameters']} parameters",
        f"- architecture: {card['architecture']}",
        f"- inputs: `frames` [n, 3, H, W] (RGB in [0, 1] on the offset-0 grid; H, W multiples of 16), "
        f"`planes` [{PLANES}, n] (linear weights of each plane on the frames)",
        f"- outputs: `plane` (soft-argmax plane index, 0 … {PLANES - 1}) and `confidence` (peak probability)",
        f"- data: {t['crops']} crops of {CROP}×{CROP} px from {len(t['sources'])} bundles rendered at random stations "
        f"(seeds {t['seeds']}); held out: {t['heldout_crops']} crops of {len(t['heldout_sources'])} bundles",
        f"- training: {t['epochs']} epochs, lr {t['lr']}, {t['optimizer']}, batch {t['batch']}, seed {t['seed']}, "
        f"{t['seconds']:.0f} s on this 2-core CPU (torch {t['torch']})",
        f"- against the seed (800 samples, 1000 epochs, lr 1e-4): {t['budget_note']}",
        "",
        "| set | depth RMS (µm) | median (µm) | pixels |",
        "|---|---|---|---|",
        *[f"| {k} | {v['rms_um']} | {v['median_um']} | {v['pixels']} |" for k, v in m.items() if isinstance(v, dict) and "rms_um" in v],
        "",
        "Reproduce: `training/all.sh` (or `python training/depth_cnn.py` once the bundles are rendered).",
        "",
    ])


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--per-bundle", type=int, default=48)
    parser.add_argument("--out", type=pathlib.Path, default=REPO / "models")
    parser.add_argument("--name", default="depth-unet")
    a = parser.parse_args()
    seed = 26
    torch.manual_seed(seed)
    random.seed(seed)
    np.random.seed(seed)
    torch.set_num_threads(2)
    train = gather("train", a.per_bundle, seed)
    heldout = gather("heldout", a.per_bundle // 2, seed + 1)
    # The last training source is the validation set (the best epoch is kept).
    sources = sorted({s["source"] for s in train})
    val_source = sources[-1]
    fit = [s for s in train if s["source"] != val_source]
    val = [s for s in train if s["source"] == val_source]
    model = DepthCnn()
    params = sum(p.numel() for p in model.parameters())
    opt = torch.optim.AdamW(model.parameters(), lr=a.lr, weight_decay=1e-4)
    steps = a.epochs * ((len(fit) + a.batch - 1) // a.batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=a.lr, total_steps=steps, pct_start=0.15)
    rng = random.Random(seed)
    best, best_state, best_epoch = float("inf"), None, -1
    started = time.time()
    for epoch in range(a.epochs):
        model.train()
        total, count = 0.0, 0
        for frames, planes, target, _ in batches(fit, a.batch, rng):
            if rng.random() < 0.5:  # the axis direction carries nothing: flip for more data
                frames, target = frames.flip(-1), target.flip(-1)
            plane, _ = model.forward_batch(frames, planes)
            mask = torch.isfinite(target)
            loss = (plane - torch.nan_to_num(target))[mask].pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total, count = total + loss.item(), count + 1
        v = evaluate(model, val)
        print(f"epoch {epoch}: train {total / count:.3f} plane², val {v['rms_um']} µm RMS, "
              f"{time.time() - started:.0f} s", flush=True)
        if v["rms_um"] < best:
            best, best_epoch = v["rms_um"], epoch
            best_state = {k: t.clone() for k, t in model.state_dict().items()}
    seconds = time.time() - started
    model.load_state_dict(best_state)
    metrics = {"validation": evaluate(model, val), "heldout": evaluate(model, heldout), "best_epoch": best_epoch}
    by_source = {}
    for s in heldout:
        by_source.setdefault(s["source"], []).append(s)
    for source, samples in sorted(by_source.items()):
        metrics[f"heldout {source}"] = evaluate(model, samples)
    a.out.mkdir(parents=True, exist_ok=True)
    onnx_path = a.out / f"{a.name}.onnx"
    export(model, onnx_path)
    torch.save(model.state_dict(), a.out / f"{a.name}.pt")
    # The check the Rust test repeats through ONNX Runtime: the framework's output on a fixed input.
    g = torch.Generator().manual_seed(7)
    check_frames = torch.rand(6, 3, 32, 48, generator=g)
    check_planes = torch.from_numpy(plane_matrix(np.array([0.3, -0.2, 0.1, 0.0, -0.1, 0.2])))
    with torch.no_grad():
        plane, confidence = model(check_frames, check_planes)
    (a.out / f"{a.name}.check.json").write_text(json.dumps({
        "frames": check_frames.numpy().round(6).flatten().tolist(), "frames_shape": list(check_frames.shape),
        "planes": check_planes.numpy().flatten().tolist(), "plane": plane.numpy().flatten().tolist(),
        "confidence": confidence.numpy().flatten().tolist()}))
    sha = hashlib.sha256(onnx_path.read_bytes()).hexdigest()
    card = {
        "name": a.name,
        "role": "depth",
        "sha256": sha,
        "parameters": params,
        "planes": PLANES,
        "architecture": f"defocus U-Net 8→1 and depth U-Net {PLANES}→{PLANES} (4 levels, widths {BASE}–{BASE * 16}, "
                        "batch norm, ReLU), soft argmax over the planes",
        "input": {"frames": ["n", 3, "height", "width"], "planes": [PLANES, "n"]},
        "output": {"plane": [1, 1, "height", "width"], "confidence": [1, 1, "height", "width"]},
        "training": {
            "crops": len(fit), "sources": sorted({s["source"] for s in fit}), "validation_source": val_source,
            "heldout_crops": len(heldout), "heldout_sources": sorted(by_source), "seeds": "1001–1019 (held out 1101–1108)",
            "epochs": a.epochs, "lr": a.lr, "batch": a.batch, "seed": seed,
            "optimizer": "AdamW (weight decay 1e-4), one-cycle schedule", "loss": "L2 on depth (plane units) only",
            "seconds": round(seconds, 1), "torch": torch.__version__,
            "budget_note": f"{len(fit)} crops of {CROP}² px (the seed's 800 samples of whole frames), "
                           f"{a.epochs} epochs at lr {a.lr} with a one-cycle schedule (the seed's 1000 at 1e-4): "
                           "about 1/80 of the seed's optimiser steps",
        },
        "metrics": metrics,
    }
    (a.out / f"{a.name}.json").write_text(json.dumps(card, indent=1) + "\n")
    (a.out / f"{a.name}.md").write_text(card_markdown(card))
    print(json.dumps(metrics, indent=1))
    print(f"{onnx_path}: sha256 {sha}, {seconds:.0f} s")


if __name__ == "__main__":
    main()
