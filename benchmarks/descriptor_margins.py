"""Loop-closure margins of the attention descriptor on real revisits (7-Scenes redkitchen).

For each query/revisit pair (250/945, 255/950, 260/955; ~1-7 cm apart, 16-20 degrees turned) the margin
is  sim(query, revisit) - max over negatives of sim(query, negative),  with sim the cosine of the
descriptors. Negatives: every frame that the ground truth puts more than 0.8 m away from the query OR
whose relative rotation to the query (the angle of R_q^T R_j) exceeds 60 degrees. A positive margin
means the revisit is ranked above every far view.

Rows (all with the pretrained EfficientNet-Lite0 tapped at stage7, 320 x 7 x 7):

- ``straightforward``: negative gradients zeroed at the tap (as at VGG16's pool5) and the raw fused map
  fed to the random RNNs (the paper's recipe transplanted as is);
- ``no clamp``: plain softmax-seeded gradient at the tap (EfficientNet has no max-pool transitions);
- ``library``: no clamp and the fused map scaled to L2 norm 10 before the RNNs (AttentionDescriptor's
  defaults).

With ``--seeds N`` the RNN weights are redrawn N times (seeds 0..N-1) and the table also gives the mean
and the worst margin over seeds: the random projection to 1024 dims has its own noise.

The backbone runs once per frame (batched); all variants and fusion modes reuse (L, G). Nothing is
cached between runs.

Usage:
    python benchmarks/descriptor_margins.py                       # all 1000 frames, RNN seed 0
    python benchmarks/descriptor_margins.py --seeds 16            # + spread over 16 RNN seeds
    python benchmarks/descriptor_margins.py --stride 5            # negatives from every 5th frame (fast)

Prints markdown tables.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from attnloop.backbones import efficientnet_lite0
from attnloop.descriptor import descriptor_from_attention
from attnloop.fusion import FUSION_MODES
from attnloop.guided_backprop import guided_backprop
from attnloop.rnn_pool import random_rnn_weights

PAIRS = ((250, 945), (255, 950), (260, 955))
MAX_DIST_M = 0.8
MAX_ANGLE_DEG = 60.0
# The ImageNet classes these kitchen frames fall into (for the printout).
CLASS_NAMES = {624: "library", 526: "desk", 454: "bookshop", 548: "entertainment center", 553: "file cabinet"}


def default_sequence() -> Path:
    root = Path(os.environ.get("ATTNLOOP_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    return root / "7scenes-redkitchen"


def load_rgb(seq: Path, index: int) -> torch.Tensor:
    """Frame ``index`` as a (3, H, W) uint8 RGB tensor."""
    path = seq / f"frame-{index:06d}.color.jpg"
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"cannot read {path}")
    return torch.from_numpy(np.ascontiguousarray(bgr[:, :, ::-1])).permute(2, 0, 1)


def load_pose(seq: Path, index: int) -> np.ndarray:
    """Camera-to-world 4x4 pose of frame ``index``."""
    return np.loadtxt(seq / f"frame-{index:06d}.pose.txt").reshape(4, 4)


def negatives(poses: dict[int, np.ndarray], query: int, frames: list[int]) -> list[int]:
    """Frames more than 0.8 m from ``query`` or more than 60 degrees of relative rotation away."""
    tq, rq = poses[query][:3, 3], poses[query][:3, :3]
    out = []
    for j in frames:
        dist = np.linalg.norm(poses[j][:3, 3] - tq)
        cos = (np.trace(rq.T @ poses[j][:3, :3]) - 1.0) / 2.0
        angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        if dist > MAX_DIST_M or angle > MAX_ANGLE_DEG:
            out.append(j)
    return out


def attention_for_frames(seq: Path, frames: list[int], batch: int, tap: str = "stage7"):
    """(L, G, logits) of the pretrained EfficientNet-Lite0 for ``frames``, batched."""
    net = efficientnet_lite0(pretrained=True, tap=tap)
    taps, grads, logits = [], [], []
    with torch.no_grad():
        for start in range(0, len(frames), batch):
            images = torch.stack([load_rgb(seq, i) for i in frames[start:start + batch]])
            tap_l, grad = guided_backprop(net, images)
            taps.append(tap_l)
            grads.append(grad)
            logits.append(net.forward_from_tap(tap_l))
    return torch.cat(taps), torch.cat(grads), torch.cat(logits)


def margins(desc: torch.Tensor, row: dict[int, int], negs: dict[int, list[int]]) -> list[float]:
    """Margin of every pair: sim(q, revisit) - max sim(q, negatives); ``row`` maps frame -> row."""
    out = []
    for q, p in PAIRS:
        sims = desc @ desc[row[q]]
        neg_rows = torch.tensor([row[j] for j in negs[q]])
        out.append(float(sims[row[p]] - sims[neg_rows].max()))
    return out


VARIANTS = {
    "straightforward": {"clamp": True, "pool_scale": None},
    "no clamp": {"clamp": False, "pool_scale": None},
    "library": {"clamp": False, "pool_scale": 10.0},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=default_sequence(), help="the redkitchen folder")
    parser.add_argument("--stride", type=int, default=1, help="negatives from every stride-th frame")
    parser.add_argument("--batch", type=int, default=25, help="frames per forward/backward pass")
    parser.add_argument("--seeds", type=int, default=1, help="RNN seeds 0..N-1")
    args = parser.parse_args()
    seq = args.data
    if not (seq / "frame-000000.color.jpg").is_file():
        raise SystemExit(f"redkitchen sequence not found at {seq} (set ATTNLOOP_DATA)")
    n_frames = len(list(seq.glob("frame-*.color.jpg")))
    pool = list(range(0, n_frames, args.stride))
    frames = sorted(set(pool) | {i for pair in PAIRS for i in pair})
    row = {f: k for k, f in enumerate(frames)}
    poses = {i: load_pose(seq, i) for i in frames}
    negs = {q: negatives(poses, q, pool) for q, _ in PAIRS}

    t0 = time.perf_counter()
    tap, grad, logits = attention_for_frames(seq, frames, args.batch)
    seconds = time.perf_counter() - t0
    print(f"# Descriptor margins on 7-Scenes redkitchen ({time.strftime('%Y-%m-%d')})\n")
    print(f"{len(frames)} frames through EfficientNet-Lite0 (tap stage7 {tuple(tap.shape[1:])}) in {seconds:.1f} s "
          f"({1000 * seconds / len(frames):.1f} ms/frame, batch {args.batch}, {torch.get_num_threads()} threads, "
          f"{platform.processor() or platform.machine()}); negatives: "
          + ", ".join(f"{q}: {len(negs[q])}" for q, _ in PAIRS) + f" (every {args.stride}. frame)\n")

    probs = logits.softmax(1)
    print("| frame | top-1 ImageNet class (p) | top-2 (p) |\n|---|---|---|")
    for q, p in PAIRS:
        for f in (q, p):
            v, c = probs[row[f]].topk(2)
            names = [f"{CLASS_NAMES.get(int(k), int(k))} ({float(x):.2f})" for k, x in zip(c, v)]
            print(f"| {f} | {names[0]} | {names[1]} |")
    print()

    c, h, w = tap.shape[1:]
    weights = [random_rnn_weights(16, c // 2 * h * w, 64, seed=s) for s in range(args.seeds)]
    header = "| variant | fusion | " + " | ".join(f"{q}/{p}" for q, p in PAIRS) + " | min |"
    if args.seeds > 1:
        header += f" mean over {args.seeds} seeds | worst over seeds | seeds with a negative pair |"
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for name, cfg in VARIANTS.items():
        g = grad.clamp(min=0) if cfg["clamp"] else grad
        for mode in FUSION_MODES:
            per_seed = []
            for wts in weights:
                _, desc = descriptor_from_attention(tap, g, wts, mode, pool_scale=cfg["pool_scale"], pooling="flat")
                per_seed.append(margins(desc, row, negs))
            m0 = per_seed[0]
            line = f"| {name} | {mode} | " + " | ".join(f"{m:+.3f}" for m in m0) + f" | {min(m0):+.3f} |"
            if args.seeds > 1:
                arr = np.array(per_seed)
                line += f" {arr.mean():+.3f} | {arr.min():+.3f} | {int((arr.min(1) < 0).sum())}/{args.seeds} |"
            print(line)


if __name__ == "__main__":
    main()
