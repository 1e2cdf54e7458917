"""Why attention lowers recall at 100 % precision against ``none``: one figure per hypothesis, every set.

Session 2 of the issue-13 ablation (the first is benchmarks/descriptor_ablation.py). The backbone's tap
maps (L and G at stage6 and stage7 of EfficientNet-Lite0, 224 x 288) depend only on the backbone, the
input and the softmax seed, not on the fusion or the pooling: they are extracted once per set and seed
and cached (``--cache``, default ``runs/attention_cache``), so every fusion/pooling variant costs seconds.

Protocols (as benchmarks/place_recognition.py): rtabmap-samples fwd / rev, the kitchen fwd / split.
For each hypothesis the table gives R@1 / R@P100 on each protocol and their mean, every fusion mode.

Hypotheses:

* ``range``: the fusion's dynamic range after pooling: the cosine between the regional code of the
  fused map and that of L (``none``), median over frames; 1.0 means the attention changes nothing.
* ``hotspot``: where N(G) concentrates: the share of N(G) above 0.9 / in (0.35, 0.65), and the share
  of the top 1 % of |G| that falls on the map's single hottest (h, w) position.
* ``norm``: N(.) over (C, H, W) (the paper), per channel over (H, W), and over (H, W) of the
  channel-summed |G|... in the same four formulas (DAM/EAM/GAF/EGA).
* ``smooth``: G averaged over 3 x 3 neighbourhoods before N (spatial smoothing).
* ``sign``: N(|G|) instead of N(G) (where the class evidence is, whatever its sign).
* ``seed``: the softmax seed: each frame's S (the paper), S restricted to its top-5 classes
  (renormalised), uniform over the top-5, softmax(z / 2) (flatter, less winner-dependent), and the
  entropy-weighted S (each class's share -S_k log S_k of the entropy). A seed scaled by a per-frame
  constant (S times the frame's confidence) changes nothing: the descriptor fuses G / max|G|.
* ``rnnseed``: R@1 / R@P100 over 8 RNN seeds, and the regional code without RNNs.
* ``regions``: the regional code without the per-region L2.

Usage:
    python benchmarks/attention_hypotheses.py [--data ../shared/data] [--only range norm ...] [--threads 1]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from descriptor_ablation import scores, sets

from attnloop.backbones.efficientnet_lite import efficientnet_lite
from attnloop.backbones.preprocess import prepare_images
from attnloop.fusion import FUSION_MODES, minmax_normalize
from attnloop.pooling import gem_regions, regional_code, unit_scale
from attnloop.rnn_pool import random_rnn_pool, random_rnn_weights

GROUPS = (192, 320)
SIZE = (224, 288)
SEEDS = ("own", "top5", "top5-uniform", "T2", "entropy")
HYPOTHESES = ("range", "hotspot", "norm", "smooth", "sign", "seed", "rnnseed", "regions")


def _seed(p: torch.Tensor, z: torch.Tensor, kind: str) -> torch.Tensor:
    if kind == "own":
        return p
    if kind == "T2":
        return (z / 2).softmax(1)
    if kind == "entropy":  # each class's share of the softmax's entropy, -S_k log S_k (the runners-up weigh more)
        h = -p * p.clamp_min(1e-30).log()
        return h / h.sum(1, keepdim=True)
    top = p.topk(5, dim=1).indices
    mask = torch.zeros_like(p).scatter_(1, top, 1.0)
    s = p * mask if kind == "top5" else mask
    return s / s.sum(1, keepdim=True)


def extract(images: list[np.ndarray], kinds=SEEDS, batch: int = 8) -> dict:
    """{seed kind: G (N, 512, 7, 9)}, plus "L" and "logits": one forward, one backward per seed kind."""
    net = efficientnet_lite("lite0", pretrained=True, tap="stage6+stage7", input_size=SIZE)
    out = {k: [] for k in (*kinds, "L", "logits")}
    for s in range(0, len(images), batch):
        x = torch.stack([prepare_images(torch.from_numpy(im).permute(2, 0, 1)[None], SIZE, net.mean, net.std)[0]
                         for im in images[s:s + batch]])
        with torch.no_grad():
            tap = net.forward_to_tap(x)
        with torch.enable_grad():
            var = tap.detach().requires_grad_(True)
            z = net.forward_from_tap(var)
            p = z.softmax(1)
            for k, kind in enumerate(kinds):
                (g,) = torch.autograd.grad(p, var, grad_outputs=_seed(p.detach(), z.detach(), kind),
                                           retain_graph=k < len(kinds) - 1)
                out[kind].append(g)
        out["L"].append(tap)
        out["logits"].append(z.detach())
    return {k: torch.cat(v) for k, v in out.items()}


# --------------------------------------------------------------------------- fusion variants
def rank_normalize(g: torch.Tensor, dims: tuple[int, ...]) -> torch.Tensor:
    """Each entry's rank among the entries of ``dims``, scaled to [0, 1] (a min-max that no hot spot sets)."""
    moved = g.movedim(dims, tuple(range(g.ndim - len(dims), g.ndim)))
    flat = moved.reshape(*moved.shape[: g.ndim - len(dims)], -1)
    r = flat.argsort(-1).argsort(-1).to(g.dtype) / max(flat.shape[-1] - 1, 1)
    return r.reshape(moved.shape).movedim(tuple(range(g.ndim - len(dims), g.ndim)), dims)


def attention_map(g: torch.Tensor, mode: str, norm: str) -> torch.Tensor:
    """The multiplier of L: N(G) for dam/eam, N(sum_c N(G_c)) for gaf/ega, with N over ``norm``'s dims."""
    if norm == "rank":
        if mode in ("dam", "eam"):
            a = rank_normalize(g, (1, 2, 3))
        else:
            a = minmax_normalize(rank_normalize(g, (2, 3)).sum(1, keepdim=True), (2, 3))
        return torch.exp(a) if mode in ("eam", "ega") else a
    if mode in ("dam", "eam"):
        dims = {"global": (1, 2, 3), "channel": (2, 3)}[norm]
        a = minmax_normalize(g, dims)
    else:  # the GAF map: the inner N is per channel in the paper already; "global" keeps the formula
        inner = minmax_normalize(g, (2, 3) if norm == "global" else (1, 2, 3))
        a = minmax_normalize(inner.sum(1, keepdim=True), (2, 3))
    return torch.exp(a) if mode in ("eam", "ega") else a


def fused(L, G, mode, norm="global", smooth=False, sign=False):
    if mode == "none":
        return L
    parts = []
    for lt, gt in zip(L.split(GROUPS, 1), G.split(GROUPS, 1)):
        g = unit_scale(gt)
        if sign:
            g = g.abs()
        if smooth:
            g = F.avg_pool2d(g, 3, stride=1, padding=1, count_include_pad=False)
        parts.append(lt * attention_map(g, mode, norm))
    return torch.cat(parts, 1)


_W = {0: random_rnn_weights(16, 2560, 64, seed=0)}


def region_weighted_code(f: torch.Tensor) -> torch.Tensor:
    """Regional GeM without the per-region L2: each region keeps its magnitude relative to the others
    (the attention's between-region contrast), each tap group L2-normalised on its own."""
    parts = []
    for fg in f.split(GROUPS, 1):
        regions = gem_regions(fg / fg.abs().amax((1, 2, 3), keepdim=True).clamp_min(1e-30), 2.0, (1, 2))
        parts.append(F.normalize(regions.flatten(1), dim=1))
    return torch.cat(parts, 1)


def descriptor(f: torch.Tensor, seed: int | None = 0, code_fn=None) -> torch.Tensor:
    """The default's regional code and RNNs of RNN seed ``seed``; None: the regional code without RNNs."""
    code = F.normalize((code_fn or (lambda x: regional_code(x, GROUPS, 2.0, (1, 2))))(f), dim=1)
    if seed is None:
        return code
    if seed not in _W:
        _W[seed] = random_rnn_weights(16, 2560, 64, seed=seed)
    return F.normalize(random_rnn_pool(10.0 * code[:, :, None, None], _W[seed], merge=False), dim=1)


def table(title: str, variants: dict, feats: dict, protos: dict, code_fn=None) -> None:
    names = [p for s in protos.values() for p in s]
    print(f"\n#### {title}\n\n| variant | mode | " + " | ".join(names) + " | mean |\n|---|---|"
          + "---|" * (len(names) + 1))
    for label, fn in variants.items():
        for m in FUSION_MODES:
            if m == "none" and label != next(iter(variants)):
                continue
            s = scores({k: descriptor(fn(feats[k], m), code_fn=code_fn) for k in feats}, protos)
            cells = [f"{s[p][0]:.3f} / {s[p][1]:.3f}" for p in names]
            r1, rp = np.mean([s[p][0] for p in names]), np.mean([s[p][1] for p in names])
            print(f"| {label} | {m} | " + " | ".join(cells) + f" | {r1:.3f} / {rp:.3f} |", flush=True)


def main(argv=None) -> None:
    from place_recognition import data_root

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=data_root(),
                        help="the shared data folder (default: ATTNLOOP_DATA or ../shared/data)")
    parser.add_argument("--cache", type=Path, default=Path("runs/attention_cache"),
                        help="folder of the cached tap maps L and G per set (extracted when missing)")
    parser.add_argument("--only", nargs="*", choices=HYPOTHESES, default=list(HYPOTHESES),
                        help="the hypotheses to measure (default: all)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    data = sets(args.data)
    if not data:
        raise SystemExit(f"no real set under {args.data}")
    protos = {k: v[1] for k, v in data.items()}
    feats = {}
    args.cache.mkdir(parents=True, exist_ok=True)
    for k, (images, _) in data.items():
        path = args.cache / f"{k}_lite0_{SIZE[0]}x{SIZE[1]}.pt"
        feats[k] = torch.load(path) if path.is_file() else {}
        missing = [kind for kind in SEEDS if kind not in feats[k]]
        if missing:
            t0 = time.perf_counter()
            feats[k].update(extract(images, missing))
            torch.save(feats[k], path)
            print(f"<!-- {k}: features in {time.perf_counter() - t0:.0f} s -->", flush=True)
    print(f"# Attention hypotheses ({time.strftime('%Y-%m-%d %H:%M')}), R@1 / R@P100 per protocol")

    if "range" in args.only:
        print("\n#### range: cos(regional code of the fused map, regional code of L), median over frames\n")
        print("| set | " + " | ".join(FUSION_MODES[1:]) + " |\n|---|" + "---|" * 4)
        for k, f in feats.items():
            base = F.normalize(regional_code(f["L"], GROUPS), dim=1)
            cells = []
            for m in FUSION_MODES[1:]:
                c = F.normalize(regional_code(fused(f["L"], f["own"], m), GROUPS), dim=1)
                cells.append(f"{float((c * base).sum(1).median()):.3f}")
            print(f"| {k} | " + " | ".join(cells) + " |")

    if "hotspot" in args.only:
        print("\n#### hotspot: where N(G) concentrates (stage7, median over frames)\n")
        print("| set | N(G) > 0.9 | N(G) in (0.35, 0.65) | top-1 % of abs G on the hottest position | "
              "top-1 class differs on true pairs |\n|---|---|---|---|---|")
        for k, f in feats.items():
            g = f["own"][:, 192:]
            n = minmax_normalize(g, (1, 2, 3)).flatten(1)
            a = g.abs().flatten(2)  # (N, C, HW)
            thr = a.flatten(1).quantile(0.99, dim=1)
            hot = (a > thr[:, None, None]).float().sum(1)  # (N, HW) count of top entries per position
            share = hot.amax(1) / hot.sum(1).clamp_min(1)
            gt = next(iter(protos[k].values()))[0]
            q, r = torch.nonzero(gt, as_tuple=True)
            top = f["logits"].argmax(1)
            print(f"| {k} | {float((n > 0.9).float().mean(1).median()):.4f} | "
                  f"{float(((n > 0.35) & (n < 0.65)).float().mean(1).median()):.2f} | {float(share.median()):.2f} | "
                  f"{float((top[q] != top[r]).float().mean()):.2f} |")

    own = lambda **kw: (lambda f, m: fused(f["L"], f["own"], m, **kw))
    if "norm" in args.only:
        table("norm: N(.) over (C, H, W) as the paper, or per channel (dam/eam) / inner over (C, H, W) "
              "(gaf/ega), or N = the rank (percentile) of each entry", {"paper N": own(), "per-channel N":
              own(norm="channel"), "rank N": own(norm="rank")}, feats, protos)
    if "smooth" in args.only:
        table("smooth: G averaged over 3 x 3 before N", {"paper": own(), "smoothed G": own(smooth=True)},
              feats, protos)
    if "sign" in args.only:
        table("sign: N(abs G) instead of N(G)", {"paper": own(), "abs G": own(sign=True),
                                                "abs G, smoothed": own(sign=True, smooth=True)}, feats, protos)
    if "rnnseed" in args.only:
        names = [p for s in protos.values() for p in s]
        print("\n#### rnnseed: the metric's spread over 8 RNN seeds (mean [min, max]), and without the RNNs\n")
        print("| mode | " + " | ".join(names) + " |\n|---|" + "---|" * len(names))
        for m in FUSION_MODES:
            runs = [scores({k: descriptor(fused(f["L"], f["own"], m), seed) for k, f in feats.items()}, protos)
                    for seed in range(8)]
            cells = []
            for p in names:
                a = np.array([[r[p][0], r[p][1]] for r in runs])
                cells.append(f"{a[:, 0].mean():.3f} [{a[:, 0].min():.2f}, {a[:, 0].max():.2f}] / "
                             f"{a[:, 1].mean():.3f} [{a[:, 1].min():.2f}, {a[:, 1].max():.2f}]")
            print(f"| {m} | " + " | ".join(cells) + " |", flush=True)
        for m in FUSION_MODES:
            s = scores({k: descriptor(fused(f["L"], f["own"], m), None) for k, f in feats.items()}, protos)
            print(f"| {m}, no RNN | " + " | ".join(f"{s[p][0]:.3f} / {s[p][1]:.3f}" for p in names) + " |")
    if "regions" in args.only:
        table("regions: the regional code without the per-region L2 (regions weighted by their pooled magnitude, "
              "which carries the attention's between-region contrast)", {"region-weighted": own()}, feats, protos,
              code_fn=region_weighted_code)
    if "seed" in args.only:
        table("seed: the softmax seed of the backward",
              {kind: (lambda f, m, kind=kind: fused(f["L"], f[kind], m)) for kind in SEEDS}, feats, protos)


if __name__ == "__main__":
    main()
