"""Why the paper's attention did not help place recognition, one measured figure per hypothesis.

Every figure is given on four protocols of the two real sets (rtabmap-samples forward / reverse, the
kitchen forward / time split; see benchmarks/place_recognition.py) as ``R@1/R@P100`` and as the mean
over the four, for each fusion mode. Nothing is fitted on an evaluated image: the whitening is learnt
on the *other* set.

Hypotheses (issue 13):

* ``flip``: the softmax's top class differs between the two views of a true pair, so G (class-
  conditional) flips: the share of true pairs with different top-1 classes and the cosine of their G,
  with each frame's softmax as the seed and with a fixed seed (the other set's mean softmax).
* ``hotspot``: N(G) over (C, H, W) is set by a few extreme entries: the share of N(G) in (0.35, 0.65)
  and the descriptors with G clipped to its 1st-99th percentiles first.
* ``tap``: stage6, stage7, head, stage6+stage7 (with the regional pooling).
* ``pooling``: the paper's flat RNN over the whole map, global GeM, regional GeM (whole map + 2 x 2),
  with and without the RNNs; GeM exponent 2 / 3 / 4.
* ``size``: the input 224 x 224 (the paper's direct resize), 224 x 288 (a 4:3 frame's aspect), 288 x 384.
* ``backbone``: EfficientNet-Lite0 / Lite1 / Lite2 (each at its resolution, 4:3).
* ``whitening``: PCA-whitening (128 dims) or centring of the regional code, learnt on the other set.
* ``halves``: settings chosen on the first half of each protocol's queries, reported on the second.

Usage:
    python benchmarks/descriptor_ablation.py [--data ../shared/data] [--only flip hotspot tap ...]

Prints markdown tables; several minutes per input size on two busy cores (one backbone pass per size).
"""
from __future__ import annotations

import argparse
import itertools
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from place_recognition import data_root, kitchen_poses, load_rgb

from attnloop.backbones.efficientnet_lite import efficientnet_lite, efficientnet_lite_taps
from attnloop.backbones.preprocess import prepare_images
from attnloop.descriptor import descriptor_from_attention
from attnloop.fusion import FUSION_MODES, minmax_normalize
from attnloop.pooling import fuse_groups, regional_code
from attnloop.rnn_pool import random_rnn_pool, random_rnn_weights
from slam.eval.loops import LoopGroundTruthConfig
from slam.eval.place_recognition import (
    evaluate,
    ground_truth_from_poses,
    read_ground_truth,
    sequence_candidates,
)

TAPS = ("stage6", "stage7", "head")


def extract(images, variant, size, seed_vec=None, batch=8):
    """{tap: (L, G)} for stage6, stage7 and head from one forward and one seeded backward, + logits."""
    net = efficientnet_lite(variant, pretrained=True)
    info = efficientnet_lite_taps(variant, size)
    want = {info[t][0]: t for t in TAPS if t != "head"}
    acc = {t: ([], []) for t in TAPS}
    logits = []
    for s in range(0, len(images), batch):
        x = torch.stack([prepare_images(torch.from_numpy(im).permute(2, 0, 1)[None], size, net.mean, net.std)[0]
                         for im in images[s:s + batch]])
        with torch.enable_grad():
            acts = {}
            h = F.relu6(net._bn0(net._conv_stem(x)))
            for k, blk in enumerate(net._blocks):
                h = blk(h)
                if k in want:
                    acts[want[k]] = h
            acts["head"] = net._head_features(h)
            z = net._fc(torch.flatten(F.adaptive_avg_pool2d(acts["head"], 1), 1))
            p = z.softmax(1)
            seed = p.detach() if seed_vec is None else seed_vec.expand_as(p)
            grads = torch.autograd.grad(p, [acts[t] for t in TAPS], grad_outputs=seed)
        for t, g in zip(TAPS, grads):
            acc[t][0].append(acts[t].detach())
            acc[t][1].append(g.detach())
        logits.append(z.detach())
    out = {t: (torch.cat(acc[t][0]), torch.cat(acc[t][1])) for t in TAPS}
    out["logits"] = torch.cat(logits)
    return out


def sets(data: Path):
    rt = data / "rtabmap-samples"
    k = data / "7scenes-redkitchen"
    out = {}
    if (rt / "samples_GT.bmp").is_file():
        gt = read_ground_truth(rt / "samples_GT.bmp")
        sym, cand = gt | gt.T, sequence_candidates(84, 10)
        out["rtabmap"] = ([load_rgb(rt / f"{i}.jpg") for i in range(1, 85)],
                          {"rt fwd": (sym & cand, cand), "rt rev": (sym & cand.T, cand.T)})
    if (k / "frame-000000.color.jpg").is_file():
        frames = list(range(0, 1000, 5))
        poses = kitchen_poses(k, frames)
        gt = ground_truth_from_poses(poses, config=LoopGroundTruthConfig(0.5, 45.0, 20))
        cand = sequence_candidates(200, 20)
        split = torch.zeros_like(cand)
        split[100:, :100] = True
        gts = torch.zeros_like(gt)
        gts[100:, :100] = ground_truth_from_poses(poses[100:], poses[:100])
        out["kitchen"] = ([load_rgb(k / f"frame-{i:06d}.color.jpg") for i in frames],
                          {"k fwd": (gt, cand), "k split": (gts, split)})
    return out


def scores(codes: dict[str, torch.Tensor], protos: dict, half: int | None = None):
    """{protocol: (R@1, R@P100)}; half 0/1 keeps the first/second half of each protocol's queries.

    ``codes[set]`` is one (N, D) tensor (each image against the others) or a (query, database) pair.
    """
    out = {}
    for set_name, c in codes.items():
        # a (query codes, database codes) pair: e.g. left crops against right crops (the shift check)
        sim = c[0] @ c[1].T if isinstance(c, tuple) else c @ c.T
        for pname, (gt, cand) in protos[set_name].items():
            g, m = gt, cand
            if half is not None:
                rows = torch.nonzero(gt.any(1) | cand.any(1)).flatten()
                keep = torch.zeros(gt.shape[0], dtype=torch.bool)
                sel = rows[: len(rows) // 2] if half == 0 else rows[len(rows) // 2:]
                keep[sel] = True
                g, m = gt & keep[:, None], cand & keep[:, None]
            r = evaluate(sim, g, candidates=m)
            out[pname] = (r.recall_at(1), r.recall_at_full_precision)
    return out


def row(label: str, per_mode: dict[str, dict]) -> str:
    cells = []
    for s in per_mode.values():
        r1 = np.mean([v[0] for v in s.values()])
        rp = np.mean([v[1] for v in s.values()])
        cells.append(f"{r1:.3f} / {rp:.3f}")
    return f"| {label} | " + " | ".join(cells) + " |"


def header(first: str) -> str:
    return (f"| {first} | " + " | ".join(FUSION_MODES) + " |\n|---|" + "---|" * len(FUSION_MODES)
            + "\n")


def regional(feats, taps, mode, p=2.0, levels=(1, 2), rnn=True, gtf=None):
    L = torch.cat([feats[t][0] for t in taps], 1)
    G = torch.cat([(gtf or (lambda g: g))(feats[t][1]) for t in taps], 1)
    groups = tuple(feats[t][0].shape[1] for t in taps)
    if not rnn:
        return F.normalize(regional_code(fuse_groups(L, G, mode, groups), groups, p, levels), dim=1)
    code = regional_code(fuse_groups(L, G, mode, groups), groups, p, levels)
    w = random_rnn_weights(16, code.shape[1], 64, seed=0)
    return F.normalize(random_rnn_pool(10.0 * F.normalize(code, dim=1)[:, :, None, None], w, merge=False), dim=1)


def flat(feats, tap, mode):
    L, G = feats[tap]
    c, h, w = L.shape[1:]
    return descriptor_from_attention(L, G, random_rnn_weights(16, c // 2 * h * w, 64, seed=0), mode,
                                     pooling="flat", pool_scale=10.0)[1]


def per_mode(fn, data_sets, protos, half=None):
    return {m: scores({k: fn(k, m) for k in data_sets}, protos, half) for m in FUSION_MODES}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=data_root(), help="the shared data folder (default: ATTNLOOP_DATA or ../shared/data)")
    parser.add_argument("--only", nargs="*", default=["flip", "hotspot", "tap", "pooling", "size", "backbone",
                                                      "whitening", "halves"], help="the studies to run (default: all)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    data = sets(args.data)
    if not data:
        raise SystemExit(f"no real set under {args.data}")
    protos = {k: v[1] for k, v in data.items()}
    images = {k: v[0] for k, v in data.items()}
    cache: dict = {}

    def feats(variant="lite0", size=(224, 288), seed=None):
        key = (variant, size, seed)
        if key not in cache:
            t0 = time.perf_counter()
            seeds = {}
            if seed == "other-mean":  # each set's fixed seed: the other set's mean softmax
                base = {k: feats(variant, size)[k]["logits"].softmax(1).mean(0) for k in images}
                names = list(images)
                seeds = {k: base[names[(i + 1) % len(names)]] for i, k in enumerate(names)}
            cache[key] = {k: extract(images[k], variant, size, seeds.get(k)) for k in images}
            print(f"<!-- features {variant} {size} seed={seed}: {time.perf_counter() - t0:.0f} s -->", flush=True)
        return cache[key]

    print(f"# Descriptor ablation ({time.strftime('%Y-%m-%d %H:%M')}): mean over "
          f"{sum(len(p) for p in protos.values())} protocols of R@1 / R@P100\n")
    base = feats()
    s67 = ("stage6", "stage7")

    if "flip" in args.only:
        fixed = feats(seed="other-mean")
        print("## flip: the top-1 class and G between the two views of a true pair (stage7, 224 x 288)\n")
        print("| set | true pairs | top-1 differs | cos G same class / differs (own S) | "
              "(fixed seed) | regional dam, own S | regional dam, fixed seed |\n|---|---|---|---|---|---|---|")
        for k, (gt, _) in ((k, next(iter(protos[k].values()))) for k in images):
            q, r = torch.nonzero(gt, as_tuple=True)
            top = base[k]["logits"].argmax(1)
            same = top[q] == top[r]
            cos = []
            for f in (base, fixed):
                G = F.normalize(f[k]["stage7"][1].flatten(1), dim=1)
                c = (G[q] * G[r]).sum(1)
                cos.append(f"{float(c[same].mean()):.2f} / {float(c[~same].mean()):.2f}")
            d_own = scores({k: regional(base[k], s67, "dam")}, {k: protos[k]})
            d_fix = scores({k: regional(fixed[k], s67, "dam")}, {k: protos[k]})
            fmt = lambda s: " ".join(f"{a:.2f}/{b:.2f}" for a, b in s.values())
            print(f"| {k} | {len(q)} | {float((~same).float().mean()):.2f} | {cos[0]} | {cos[1]} | {fmt(d_own)} | "
                  f"{fmt(d_fix)} |")
        print()

    if "hotspot" in args.only:
        print("## hotspot: N(G) over (C, H, W) (stage7)\n")
        for k in images:
            Nn = minmax_normalize(base[k]["stage7"][1], (1, 2, 3)).flatten(1)
            mid = ((Nn > 0.35) & (Nn < 0.65)).float().mean(1)
            print(f"- {k}: median share of N(G) entries in (0.35, 0.65): {float(mid.median()):.2f}")

        def clip(g, q=0.01):
            f = g.flatten(1)
            lo, hi = f.quantile(q, dim=1), f.quantile(1 - q, dim=1)
            return torch.maximum(torch.minimum(g, hi[:, None, None, None]), lo[:, None, None, None])
        print("\n" + header("G before the fusion (regional, stage6+stage7)"), end="")
        print(row("G as is", per_mode(lambda k, m: regional(base[k], s67, m), images, protos)))
        print(row("G clipped to its 1st-99th percentiles", per_mode(lambda k, m: regional(base[k], s67, m, gtf=clip),
                                                                    images, protos)))
        print()

    if "tap" in args.only:
        print("## tap (regional pooling, 224 x 288)\n\n" + header("tap"), end="")
        for taps in (("stage6",), ("stage7",), ("head",), s67):
            print(row("+".join(taps), per_mode(lambda k, m, t=taps: regional(base[k], t, m), images, protos)))
        print()

    if "pooling" in args.only:
        print("## pooling (224 x 288)\n\n" + header("pooling"), end="")
        print(row("flat RNN over stage7 (the paper's pooling)", per_mode(lambda k, m: flat(base[k], "stage7", m),
                                                                         images, protos)))
        for (levels, rnn, p) in (((1,), True, 2.0), ((1, 2), False, 2.0), ((1, 2), True, 2.0), ((1, 2), True, 3.0),
                                 ((1, 2), True, 4.0), ((1, 2, 3), True, 2.0)):
            label = f"GeM p={p:g} levels {levels} {'+ RNN' if rnn else 'no RNN'}, stage6+stage7"
            print(row(label, per_mode(lambda k, m, a=levels, b=rnn, c=p: regional(base[k], s67, m, c, a, b),
                                      images, protos)))
        print()

    if "size" in args.only:
        print("## input size (regional, stage6+stage7; flat = the paper's pooling at stage7)\n\n"
              + header("input (H x W)"), end="")
        for size in ((224, 224), (224, 288), (288, 384)):
            f = feats("lite0", size)
            print(row(f"{size[0]} x {size[1]}", per_mode(lambda k, m, f=f: regional(f[k], s67, m), images, protos)))
            print(row(f"{size[0]} x {size[1]}, flat", per_mode(lambda k, m, f=f: flat(f[k], "stage7", m),
                                                               images, protos)))
        print()

    if "backbone" in args.only:
        print("## backbone (regional, stage6+stage7, 4:3 input)\n\n" + header("backbone"), end="")
        for variant, size in (("lite0", (224, 288)), ("lite1", (240, 320)), ("lite2", (260, 352))):
            f = feats(variant, size)
            print(row(f"{variant} {size[0]} x {size[1]}", per_mode(lambda k, m, f=f: regional(f[k], s67, m),
                                                                   images, protos)))
        print()

    if "whitening" in args.only and len(images) > 1:
        names = list(images)

        def learnt(k, m, dim):
            other = names[(names.index(k) + 1) % len(names)]
            train = F.normalize(regional(base[other], s67, m, rnn=False).double(), dim=1)
            mu = train.mean(0)
            _u, S, Vt = torch.linalg.svd(train - mu, full_matrices=False)
            X = F.normalize(regional(base[k], s67, m, rnn=False).double(), dim=1) - mu
            if dim == 0:
                return F.normalize(X, dim=1).float()
            d = min(dim, Vt.shape[0])
            P = Vt[:d] / (S[:d, None] / math.sqrt(train.shape[0]) + 1e-6 * S[0])
            return F.normalize(X @ P.T, dim=1).float()
        print("## whitening of the regional code (no RNN), learnt on the other set\n\n" + header("code"), end="")
        print(row("as is", per_mode(lambda k, m: regional(base[k], s67, m, rnn=False), images, protos)))
        print(row("centred (the other set's mean)", per_mode(lambda k, m: learnt(k, m, 0), images, protos)))
        print(row("PCA-whitened to 64 dims", per_mode(lambda k, m: learnt(k, m, 64), images, protos)))
        print()

    if "halves" in args.only:
        print("## held-out halves: the setting chosen on the first half of each protocol's queries (mean R@1 + "
              "R@P100 of dam), reported on the second\n")
        grid = list(itertools.product((("stage6",), ("stage7",), s67), (2.0, 3.0), ((1,), (1, 2))))
        best, best_v = None, -1.0
        for taps, p, levels in grid:
            s = scores({k: regional(base[k], taps, "dam", p, levels) for k in images}, protos, half=0)
            v = np.mean([a + b for a, b in s.values()])
            if v > best_v:
                best, best_v = (taps, p, levels), v
        taps, p, levels = best
        print(f"chosen on the first half: taps {'+'.join(taps)}, p {p:g}, levels {levels}\n\n"
              + header("second half"), end="")
        print(row("chosen", per_mode(lambda k, m: regional(base[k], taps, m, p, levels), images, protos, half=1)))
        print(row("stage6+stage7, both fused (the library default until 2026-12-02)", per_mode(lambda k, m: regional(base[k], s67, m), images, protos, half=1)))
        print(row("paper pooling (flat, stage7)", per_mode(lambda k, m: flat(base[k], "stage7", m), images, protos,
                                                           half=1)))


if __name__ == "__main__":
    main()
