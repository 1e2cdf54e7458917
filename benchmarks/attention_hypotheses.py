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

Session 3 (one more cache per set, ``*_taps.pt``: L and G at stage4 ... stage7 from one forward and two
backwards, G plain and G with the negative gradient zeroed at the head's ReLU6 output, for the full
frames and for crops of 75 % width at the left and at the right):

* ``spatial``: the share of G's variance that is spatial (within a channel, over (H, W)) against the
  share between channels, at every tap and at the head; the same for the clamped G; the cosine of each
  part between the two views of a true pair; the cost of G at each tap (multiply-adds of the backward,
  and CPU time against the plain forward).
* ``taps``: lower taps (stage5 and stage4, 14 x 18, where the backward crosses the stride-2 depthwise
  convolutions), alone and joined with stage6+stage7 (each tap fused and pooled on its own, at its
  own resolution), the clamp at the head output, |G| and |G| summed over channels for GAF/EGA, and G's
  within-channel and between-channel parts on their own.
* ``layouts``: the regions of the pooling: the whole map only, + a 2 x 2 grid (the default), +
  horizontal strips (1 column x 2 or 3 rows), overlapping 2 x 2 cells, R-MAC regions summed.
* ``shift``: the four protocols with the queries cropped to the left 75 % of the frame and the
  database to the right 75 % (a simulated lateral offset), beside the real ones; never chosen on alone.
* ``halves3``: every session-3 variant chosen on the first half of each protocol's queries, reported
  on the second.
* ``local``: G seeded with each position's own softmax of the classifier applied per position (the
  class activation map's logits W_fc head(h, w) + b, whose mean is the network's logits):
  G = d/dL sum_{h,w} |S(h, w)|^2 / 2, over all 1000 classes, the image's top-5 / top-20 classes, a
  64-class subset learnt on the other set, or with every position's seed at unit norm (cached as
  ``*_local.pt`` from the stage6 maps of ``*_taps.pt``); how spatial and how repeatable between two views
  it is, the four protocols with the shift check and the held-out halves, its multiply-adds and cost.

Session 6 (the same ``*_taps.pt`` caches):

* ``encoding``: what encodes the regional code of the default's fused maps: the paper's 16 random RNNs
  of 64 (sessions 1-5's default; the mean over ``--rnn-seeds``), no RNNs (the code itself, L2: the
  default since session 6), 40 RNNs of 64 (as many dims as the code), 16 RNNs at input norm 3 (the tanh
  nearer linear), each position's feature vector L2-normalised before the GeM, and the code's signed
  square root (power normalisation), with and without RNNs; the four protocols, the shift check, the
  held-out halves, and the similarity scale the SLAM's loop threshold sits on (kitchen frames >= 100 apart);
  then the GeM exponent (2, 3, 4) and three region layouts chosen again without RNNs, and session 3's
  forms of G (its within-channel part, G clamped at the head output, GAF/EGA on sum_c |G_c|) and the
  input size (224 x 224, 192 x 256, 224 x 288, 288 x 384; tap maps cached per size) without RNNs; and
  VLAD of the fused maps' local descriptors (16 or 32 words per stage, the vocabulary learnt on the other
  set) in place of the regional code.

Session 7 (the same caches):

* ``imagenet``: the tap L standardised per channel with ImageNet's own statistics before the fusion:
  whitening "learnt on unrelated images" from the one large such set at hand, through the network's
  batch-norms (:func:`imagenet_tap_statistics`): centred, scaled, or both.
* ``conditions``: session 3's forms of G at stage7 judged on more than the colour frames: grayscale
  copies (the held-out corridor is grayscale), copies at 1/4 of the width and height (a low-resolution
  camera, upsampled by the descriptor's resize), both, and the shift check; per fusion mode, the
  number of (condition, protocol, metric) figures below ``none``'s and the sum of those deficits
  (tap maps cached per condition as ``*_<condition>_cond.pt``).

Session 9 (the same ``*_taps.pt`` caches):

* ``subregions``: the issue's "RNNs over sub-regions" (CNN-randRNN's answer to the flat RNN's rigidity)
  against pooling first: the paper's random RNNs over each region's raw fused sub-map (the whole map and
  the 2 x 2 cells, 4 or 16 RNNs of 64 each, input at norm 10), the paper's RNNs over each stage's whole
  map, and the default's regional GeM without RNNs; the four protocols, the shift check, the held-out halves.

Usage:
    python benchmarks/attention_hypotheses.py [--data ../shared/data] [--only range norm ...] [--threads 1]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from descriptor_ablation import scores, sets
from slam.eval.place_recognition import evaluate

from attnloop.backbones.efficientnet_lite import efficientnet_lite, efficientnet_lite_taps
from attnloop.backbones.preprocess import prepare_images
from attnloop.fusion import FUSION_MODES, fuse, minmax_normalize
from attnloop.pooling import gem_regions, regional_code, unit_scale
from attnloop.presets import DEFAULT_BACKBONE_SETTINGS
from attnloop.rnn_pool import random_rnn_pool, random_rnn_weights

GROUPS = (192, 320)  # the channels of the default's tap, stage6 and stage7
_DEFAULT_LITE0 = DEFAULT_BACKBONE_SETTINGS["efficientnet_lite0"]
if _DEFAULT_LITE0["tap"] != "stage6+stage7":
    raise RuntimeError(f"this study's caches and GROUPS are stage6+stage7; the default tap is {_DEFAULT_LITE0['tap']}")
#: Per stage of GROUPS (stage6, stage7): whether the default descriptor fuses it (its ``attend``).
ATTENDED = tuple(t in _DEFAULT_LITE0["attend"].split("+") for t in _DEFAULT_LITE0["tap"].split("+"))
SIZE = (224, 288)
SEEDS = ("own", "top5", "top5-uniform", "T2", "entropy")
HYPOTHESES = ("range", "hotspot", "norm", "smooth", "sign", "seed", "rnnseed", "regions",
              "spatial", "taps", "layouts", "shift", "halves3", "local", "encoding", "imagenet",
              "conditions", "subregions")
SESSION3 = ("spatial", "taps", "layouts", "shift", "halves3", "local", "encoding", "imagenet",
            "conditions", "subregions")


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
    """The session-2 variants of the default's fusion: the attended stage (ATTENDED) fused, the other as L."""
    if mode == "none":
        return L
    parts = []
    for lt, gt, attended in zip(L.split(GROUPS, 1), G.split(GROUPS, 1), ATTENDED):
        if not attended:
            parts.append(lt)
            continue
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


def table(title: str, variants: dict, feats: dict, protos: dict, code_fn=None, seeds=(0,)) -> None:
    """One row per variant and mode: R@1 / R@P100 per protocol, each the mean over the RNN seeds ``seeds``."""
    names = [p for s in protos.values() for p in s]
    print(f"\n#### {title}\n\n| variant | mode | " + " | ".join(names) + " | mean |\n|---|---|"
          + "---|" * (len(names) + 1))
    for label, fn in variants.items():
        for m in FUSION_MODES:
            if m == "none" and label != next(iter(variants)):
                continue
            fused_maps = {k: fn(feats[k], m) for k in feats}
            runs = [scores({k: descriptor(f, seed, code_fn) for k, f in fused_maps.items()}, protos) for seed in seeds]
            s = {p: tuple(float(np.mean([r[p][i] for r in runs])) for i in (0, 1)) for p in names}
            cells = [f"{s[p][0]:.3f} / {s[p][1]:.3f}" for p in names]
            r1, rp = np.mean([s[p][0] for p in names]), np.mean([s[p][1] for p in names])
            print(f"| {label} | {m} | " + " | ".join(cells) + f" | {r1:.3f} / {rp:.3f} |", flush=True)


# --------------------------------------------------------------------------- session 3: taps, G's form, layouts
TAPS = ("stage4", "stage5", "stage6", "stage7")
VIEWS = ("full", "left", "right")
CROP = 0.75  # the share of the width kept by the shift check's crops


def crop(image: np.ndarray, view: str, frac: float = CROP) -> np.ndarray:
    """The frame (``full``) or its left / right ``frac`` of the width: a simulated lateral offset (pan)."""
    if view == "full":
        return image
    w = image.shape[1]
    k = int(round(frac * w))
    return np.ascontiguousarray(image[:, :k] if view == "left" else image[:, w - k:])


def spatial_share(g: torch.Tensor) -> torch.Tensor:
    """(N, C, H, W) -> (N,): the share of g's variance over (C, H, W) that lies within the channels.

    Variance over (C, H, W) = the mean over channels of the variance over (H, W) (spatial) + the
    variance of the channel means (between channels). 0: every channel map is constant over (H, W);
    1: every channel has the same mean.
    """
    g = g.double()
    within = g.var((2, 3), unbiased=False).mean(1)
    total = g.flatten(1).var(1, unbiased=False)
    return (within / total.clamp_min(1e-300)).float()


def extract_taps(images: list[np.ndarray], batch: int = 8, net=None, size: tuple[int, int] = SIZE
                 ) -> dict[str, torch.Tensor]:
    """L and G at stage4 ... stage7 from one forward and two backwards (input ``size``, 224 x 288 by default).

    Keys ``L:<tap>``, ``G:<tap>`` (the plain seeded gradient, as the library's), ``Gc:<tap>`` (the
    negative gradient zeroed at the head's output, after its ReLU6: the last non-negative map, VGG's
    pool5 analogue), ``logits``, and the spatial shares (:func:`spatial_share`) ``share:<tap>``,
    ``share_c:<tap>``, ``share:head`` (dS/d head output) and ``share:head_pre`` (before the ReLU6).
    ``net``: a Lite0 of input size ``size`` (default: the pretrained one); ``size``: the input (H, W).
    """
    net = net or efficientnet_lite("lite0", pretrained=True, tap="stage7", input_size=size)
    info = efficientnet_lite_taps("lite0", size)
    at = {info[t][0]: t for t in TAPS}
    first = info[TAPS[0]][0]
    out: dict[str, list] = {}

    def add(key, value):
        out.setdefault(key, []).append(value.detach())

    for s in range(0, len(images), batch):
        x = torch.stack([prepare_images(torch.from_numpy(im).permute(2, 0, 1)[None], size, net.mean, net.std)[0]
                         for im in images[s:s + batch]])
        with torch.no_grad():
            h = F.relu6(net._bn0(net._conv_stem(x)))
            for block in net._blocks[: first + 1]:
                h = block(h)
        with torch.enable_grad():
            acts = {TAPS[0]: h.detach().requires_grad_(True)}
            y = acts[TAPS[0]]
            for k in range(first + 1, len(net._blocks)):
                y = net._blocks[k](y)
                if k in at:
                    acts[at[k]] = y
            pre = net._bn1(net._conv_head(y))
            head = F.relu6(pre)
            z = net._fc(torch.flatten(F.adaptive_avg_pool2d(head, 1), 1))
            p = z.softmax(1)
            g_head, g_pre = torch.autograd.grad(p, [head, pre], grad_outputs=p.detach(), retain_graph=True)
            plain = torch.autograd.grad(head, [acts[t] for t in TAPS], grad_outputs=g_head, retain_graph=True)
            clamped = torch.autograd.grad(head, [acts[t] for t in TAPS], grad_outputs=g_head.clamp(min=0))
        for t, g, gc in zip(TAPS, plain, clamped):
            add(f"L:{t}", acts[t])
            add(f"G:{t}", g)
            add(f"Gc:{t}", gc)
            add(f"share:{t}", spatial_share(g))
            add(f"share_c:{t}", spatial_share(gc))
        add("share:head", spatial_share(g_head))
        add("share:head_pre", spatial_share(g_pre))
        add("logits", z)
    return {k: torch.cat(v) for k, v in out.items()}


def load_taps(name: str, images: list[np.ndarray], cache: Path, size: tuple[int, int] = SIZE
              ) -> dict[str, dict[str, torch.Tensor]]:
    """{view: extract_taps of the set's frames in that view at input ``size``}, cached in ``cache``."""
    views = {}
    for view in VIEWS:
        path = cache / f"{name}_{view}_lite0_{size[0]}x{size[1]}_taps.pt"
        if path.is_file():
            views[view] = torch.load(path)
        else:
            t0 = time.perf_counter()
            views[view] = extract_taps([crop(im, view) for im in images], size=size)
            torch.save(views[view], path)
            print(f"<!-- {name} {view}: tap maps in {time.perf_counter() - t0:.0f} s -->", flush=True)
    return views


def fuse_taps(f: dict, taps: tuple[str, ...], mode: str, g: str = "G") -> list[torch.Tensor]:
    """Each tap fused on its own with the four formulas, at its own resolution.

    ``g``: ``G`` (plain), ``Gc`` (clamped at the head output), ``absG`` (|G| in every formula),
    ``chsum`` (GAF/EGA's map N(sum_c |G_c|), without the per-channel inner N; DAM/EAM as ``G``),
    ``spatial`` (G minus each channel's mean over (H, W)), ``channel`` (each channel's mean over (H, W)
    broadcast: the part a GAP head's gradient keeps). GAF/EGA's inner per-channel N ignores a channel's
    offset, so ``spatial`` leaves them unchanged and ``channel`` makes them degenerate (a constant map).
    A form ending in ``@last`` fuses the last tap only and passes the others unfused (the library's
    ``attend``: G at the last stage alone).
    """
    last_only = g.endswith("@last")
    g = g.removesuffix("@last")
    maps = []
    for t in taps:
        L = f[f"L:{t}"]
        if mode == "none" or (last_only and t != taps[-1]):
            maps.append(L)
            continue
        # the plain G transformed below, or a cached form by its key prefix (``Gc``, the local ``Gloc`` ...)
        plain = g in ("G", "absG", "chsum", "spatial", "channel")
        G = unit_scale(f[f"G:{t}" if plain else f"{g}:{t}"])
        if g == "absG":
            G = G.abs()
        elif g == "spatial":  # the within-channel part: each channel's mean over (H, W) removed
            G = G - G.mean((2, 3), keepdim=True)
        elif g == "channel":  # the between-channel part: each channel's mean over (H, W), broadcast
            G = G.mean((2, 3), keepdim=True).expand_as(G)
        if g == "chsum" and mode in ("gaf", "ega"):
            a = minmax_normalize(G.abs().sum(1, keepdim=True), (2, 3))
            maps.append(L * (a.exp() if mode == "ega" else a))
        else:
            maps.append(fuse(L, G, mode))
    return maps


def _cells(n: int, k: int) -> list[tuple[int, int]]:
    # adaptive_avg_pool2d's cells: [floor(i n / k), ceil((i + 1) n / k))
    return [(i * n // k, -(-(i + 1) * n // k)) for i in range(k)]


def _rmac_boxes(h: int, w: int, levels: int = 3, overlap: float = 0.4) -> list[tuple[int, int, int, int]]:
    # R-MAC's regions (Tolias et al. 2016, the reference code's rule): squares of side 2 min(h, w) / (l + 1)
    # at level l, ~40 % overlap, one more region along the long side.
    side = min(h, w)
    steps = np.arange(2, 7)
    b = (max(h, w) - side) / (steps - 1)
    extra = int(np.argmin(np.abs((side ** 2 - side * b) / side ** 2 - overlap))) + 1 if h != w else 0
    wd, hd = (extra, 0) if w > h else (0, extra)
    out = []
    for lv in range(1, levels + 1):
        wl = int(2 * side // (lv + 1))
        wl2 = int(wl // 2 - 1)
        bw = (w - wl) / (lv + wd - 1) if lv + wd > 1 else 0
        bh = (h - wl) / (lv + hd - 1) if lv + hd > 1 else 0
        xs = [int(wl2 + i * bw) - wl2 for i in range(lv + wd)]
        ys = [int(wl2 + i * bh) - wl2 for i in range(lv + hd)]
        out += [(y, y + wl, x, x + wl) for y in ys for x in xs]
    return out


#: layout -> (the regions of an h x w map as (y0, y1, x0, x1), "concat" or "sum")
LAYOUTS = {
    "whole + 2x2 (default)": (lambda h, w: [(0, h, 0, w)] + [(a, b, c, d) for a, b in _cells(h, 2)
                                                             for c, d in _cells(w, 2)], "concat"),
    "whole": (lambda h, w: [(0, h, 0, w)], "concat"),
    "whole + 2 strips": (lambda h, w: [(0, h, 0, w)] + [(a, b, 0, w) for a, b in _cells(h, 2)], "concat"),
    "whole + 3 strips": (lambda h, w: [(0, h, 0, w)] + [(a, b, 0, w) for a, b in _cells(h, 3)], "concat"),
    "3 strips": (lambda h, w: [(a, b, 0, w) for a, b in _cells(h, 3)], "concat"),
    "whole + 2x2 overlapping (2/3 size)": (lambda h, w: [(0, h, 0, w)] + [
        (a, a + -(-2 * h // 3), c, c + -(-2 * w // 3)) for a in (0, h - -(-2 * h // 3))
        for c in (0, w - -(-2 * w // 3))], "concat"),
    "whole + 2x2 summed": (lambda h, w: [(0, h, 0, w)] + [(a, b, c, d) for a, b in _cells(h, 2)
                                                          for c, d in _cells(w, 2)], "sum"),
    "R-MAC regions summed": (_rmac_boxes, "sum"),
    "whole + 2x2 + 3 strips": (lambda h, w: [(0, h, 0, w)] + [(a, b, c, d) for a, b in _cells(h, 2)
                                                              for c, d in _cells(w, 2)]
                               + [(a, b, 0, w) for a, b in _cells(h, 3)], "concat"),
}
DEFAULT_LAYOUT = "whole + 2x2 (default)"


def layout_code(maps: list[torch.Tensor], layout: str = DEFAULT_LAYOUT, p: float = 2.0) -> torch.Tensor:
    """GeM (p) over each region of ``layout`` per map, every region L2-normalised; concatenated, or
    summed and L2-normalised per map (R-MAC); the maps' codes concatenated. For the default layout this
    is :func:`attnloop.pooling.regional_code` (tested)."""
    regions, agg = LAYOUTS[layout]
    parts = []
    for x in maps:
        scale = x.abs().amax((1, 2, 3), keepdim=True)
        xp = (x / torch.where(scale > 0, scale, torch.ones_like(scale))).clamp_min(1e-6).pow(p)
        r = torch.stack([xp[:, :, a:b, c:d].mean((2, 3)) for a, b, c, d in regions(*x.shape[2:])], 1).pow(1 / p)
        r = F.normalize(r, dim=2)  # (B, R, C)
        parts.append(F.normalize(r.sum(1), dim=1) if agg == "sum" else r.flatten(1))
    return torch.cat(parts, 1)


def rnn_code(code: torch.Tensor, seed: int | None = 0, num_rnn: int = 16, scale: float = 10.0) -> torch.Tensor:
    """``num_rnn`` RNNs of 64 (the paper's 16; the default of sessions 1-5) on the code scaled to norm
    ``scale``, L2; None: the code itself, L2 (the default since session 6)."""
    code = F.normalize(code, dim=1)
    if seed is None:
        return code
    key = (code.shape[1], seed, num_rnn)
    if key not in _W:
        _W[key] = random_rnn_weights(num_rnn, code.shape[1], 64, seed=seed)
    return F.normalize(random_rnn_pool(scale * code[:, :, None, None], _W[key], merge=False), dim=1)


def block_macs() -> tuple[int, dict[str, int]]:
    """Multiply-adds of one Lite0 forward at 224 x 288 (convolutions and the classifier), and per tap
    those of the layers above it: the input-gradient backward from the logits to that tap costs as many."""
    net = efficientnet_lite("lite0", pretrained=False, tap="stage7", input_size=SIZE)
    counts: list[tuple[str, int]] = []

    def hook(name):
        def fn(m, inp, out):
            if isinstance(m, torch.nn.Linear):
                counts.append((name, m.in_features * m.out_features))
            else:
                counts.append((name, out[0].numel() * m.in_channels // m.groups * m.kernel_size[0] * m.kernel_size[1]))
        return fn
    handles = [m.register_forward_hook(hook(n)) for n, m in net.named_modules()
               if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]
    with torch.no_grad():
        net(torch.rand(1, 3, *SIZE))
    for hd in handles:
        hd.remove()
    info = efficientnet_lite_taps("lite0", SIZE)
    total = sum(c for _, c in counts)

    def above(block):
        return sum(c for n, c in counts if not n.startswith("_blocks.") and not n.startswith("_conv_stem")
                   or n.startswith("_blocks.") and int(n.split(".")[1]) > block)
    return total, {t: above(info[t][0]) for t in TAPS}


def _paired_cpu_ratios(variants: dict, rounds: int, warmup: int = 2) -> tuple[dict, dict]:
    """CPU seconds of each variant per round (interleaved, no autograd, after ``warmup`` rounds) and the
    median per-round ratio of each to ``variants["plain"]``."""
    times = {k: [] for k in variants}
    with torch.no_grad():
        for r in range(rounds + warmup):
            for k, fn in variants.items():
                t0 = time.process_time()
                fn()
                if r >= warmup:
                    times[k].append(time.process_time() - t0)
    ratios = {k: float(np.median([a / b for a, b in zip(v, times["plain"])])) for k, v in times.items()}
    return times, ratios


def tap_cost(batches=(1, 8), rounds: int = 10) -> list[str]:
    """Measured cost of L and G at each tap: CPU time (``time.process_time``) of the forward to the logits
    with the seeded backward to that tap, against the plain forward of the same network, in interleaved
    rounds; the median of the per-round ratios. Synthetic 224 x 288 inputs (the weights do not matter)."""
    net = efficientnet_lite("lite0", pretrained=False, tap="stage7", input_size=SIZE)
    info = efficientnet_lite_taps("lite0", SIZE)

    def to_tap(x, tap):
        k = info[tap][0]
        with torch.no_grad():
            h = F.relu6(net._bn0(net._conv_stem(x)))
            for block in net._blocks[: k + 1]:
                h = block(h)
        with torch.enable_grad():
            leaf = h.requires_grad_(True)
            y = leaf
            for block in net._blocks[k + 1:]:
                y = block(y)
            p = net._fc(torch.flatten(F.adaptive_avg_pool2d(net._head_features(y), 1), 1)).softmax(1)
            return torch.autograd.grad(p, leaf, grad_outputs=p.detach())[0]

    rows = []
    for batch in batches:
        x = torch.randn(batch, 3, *SIZE, generator=torch.Generator().manual_seed(0))
        variants = {"plain": lambda: net.forward_from_tap(net.forward_to_tap(x))}
        variants.update({t: (lambda t=t: to_tap(x, t)) for t in reversed(TAPS)})
        times, ratios = _paired_cpu_ratios(variants, rounds)
        rows.append(f"| {batch} | {1000 * float(np.median(times['plain'])) / batch:.1f} | "
                    + " | ".join(f"{ratios[t]:.2f}" for t in reversed(TAPS)) + " |")
    return rows


def anchors(data: dict, views: dict, protos: dict) -> dict:
    """The anchors of benchmarks/place_recognition.py on the real protocols and on the shift check:
    GAP and GeM (p = 3) of the default's tap L, ORB-BoW (vocabulary learnt on the other set's frames).
    {name: {"full" | "shift": {protocol: (R@1, R@P100)}}}."""
    from place_recognition import OrbBagOfWords, skimage_photos

    def pooled(f, p):
        L = torch.cat([f["L:stage6"], f["L:stage7"]], 1)
        return F.normalize(L.mean((2, 3)) if p == 1 else L.clamp_min(1e-6).pow(p).mean((2, 3)).pow(1 / p), dim=1)

    def rates(sims):
        out = {}
        for k, sim in sims.items():
            for pname, (gt, cand) in protos[k].items():
                r = evaluate(sim, gt, candidates=cand)
                out[pname] = (r.recall_at(1), r.recall_at_full_precision)
        return out

    res = {}
    for name, p in (("GAP", 1), ("GeM", 3)):
        codes = {k: {v: pooled(f[v], p) for v in VIEWS} for k, f in views.items()}
        res[name] = {"full": rates({k: c["full"] @ c["full"].T for k, c in codes.items()}),
                     "shift": rates({k: c["left"] @ c["right"].T for k, c in codes.items()})}
    names = list(data)
    full, shift = {}, {}
    for i, k in enumerate(names):
        train = [im for other in names if other != k for im in data[other][0]]
        bow = OrbBagOfWords().fit(train + (skimage_photos() if k == "kitchen" else []))
        v = {view: bow.transform([crop(im, view) for im in data[k][0]]) for view in VIEWS}
        full[k] = bow.similarity(v["full"], v["full"])
        shift[k] = bow.similarity(v["left"], v["right"])
    res["ORB-BoW"] = {"full": rates(full), "shift": rates(shift)}
    return res


#: session-3 variants: name -> (taps, G's form, layout)
TAP_VARIANTS = {
    "stage6 unfused + stage7, G (default)": (("stage6", "stage7"), "G@last", DEFAULT_LAYOUT),
    "stage6+stage7, G at both (the default until session 4)": (("stage6", "stage7"), "G", DEFAULT_LAYOUT),
    "stage6 unfused + stage7, G clamped at the head output": (("stage6", "stage7"), "Gc@last", DEFAULT_LAYOUT),
    "stage6 unfused + stage7, abs G": (("stage6", "stage7"), "absG@last", DEFAULT_LAYOUT),
    "stage6+stage7, G clamped at the head output": (("stage6", "stage7"), "Gc", DEFAULT_LAYOUT),
    "stage6+stage7, abs G": (("stage6", "stage7"), "absG", DEFAULT_LAYOUT),
    "stage6+stage7, GAF/EGA on sum_c abs G": (("stage6", "stage7"), "chsum", DEFAULT_LAYOUT),
    "stage6+stage7, G's within-channel part": (("stage6", "stage7"), "spatial", DEFAULT_LAYOUT),
    "stage6+stage7, G's between-channel part": (("stage6", "stage7"), "channel", DEFAULT_LAYOUT),
    "stage5": (("stage5",), "G", DEFAULT_LAYOUT),
    "stage5, clamped at the head": (("stage5",), "Gc", DEFAULT_LAYOUT),
    "stage4": (("stage4",), "G", DEFAULT_LAYOUT),
    "stage4+stage5": (("stage4", "stage5"), "G", DEFAULT_LAYOUT),
    "stage5+stage6+stage7": (("stage5", "stage6", "stage7"), "G", DEFAULT_LAYOUT),
    "stage5+stage6+stage7, clamped at the head": (("stage5", "stage6", "stage7"), "Gc", DEFAULT_LAYOUT),
    "stage5+stage6+stage7, GAF/EGA on sum_c abs G": (("stage5", "stage6", "stage7"), "chsum", DEFAULT_LAYOUT),
    "stage4+stage5+stage6+stage7": (TAPS, "G", DEFAULT_LAYOUT),
}
LAYOUT_VARIANTS = {f"stage6 unfused + stage7, {lay}": (("stage6", "stage7"), "G@last", lay) for lay in LAYOUTS}


def evaluate_variant(views: dict, protos: dict, taps, g, layout, seeds=(0,), *, maps_fn=None, code_fn=None,
                     rnn_fn=rnn_code, p: float = 2.0, pool_fn=None) -> dict:
    """{mode: {"full" | "shift" | "half0" | "half1": {protocol: (R@1, R@P100)}}} of one variant, each
    figure the mean over the RNN seeds ``seeds`` (``(None,)``: no RNNs). Session 6's encodings:
    ``maps_fn`` transforms the fused maps before the pooling, ``code_fn`` the regional code after it,
    ``rnn_fn(code, seed)`` replaces :func:`rnn_code`, ``p`` is the GeM exponent, and
    ``pool_fn(maps, set_name)`` replaces the regional pooling (``layout``, ``p``) altogether."""
    out = {}
    maps_fn = maps_fn or (lambda maps: maps)
    code_fn = code_fn or (lambda code: code)
    pool_fn = pool_fn or (lambda maps, _set: layout_code(maps, layout, p))
    for m in FUSION_MODES:
        code = {k: {v: code_fn(pool_fn(maps_fn(fuse_taps(f[v], taps, m, g)), k)) for v in VIEWS}
                for k, f in views.items()}
        runs = []
        for seed in seeds:
            codes = {k: {v: rnn_fn(c, seed) for v, c in cv.items()} for k, cv in code.items()}
            full = {k: c["full"] for k, c in codes.items()}
            runs.append({"full": scores(full, protos), "half0": scores(full, protos, half=0),
                         "half1": scores(full, protos, half=1),
                         "shift": scores({k: (c["left"], c["right"]) for k, c in codes.items()}, protos)})
        out[m] = {key: {p: tuple(float(np.mean([r[key][p][i] for r in runs])) for i in (0, 1))
                        for p in runs[0][key]} for key in runs[0]}
        # the standard error of that mean over the seeds (the noise floor of a comparison)
        out[m]["sem"] = {p: tuple(float(np.std([r["full"][p][i] for r in runs], ddof=1) / np.sqrt(len(runs)))
                                  if len(runs) > 1 else float("nan") for i in (0, 1)) for p in runs[0]["full"]}
    return out


def summary_table(title: str, results: dict) -> None:
    """Mean over the four protocols of R@1 / R@P100 per mode; then the same on the shift check."""
    print(f"\n#### {title}\n\n| variant | " + " | ".join(FUSION_MODES) + " | shift check: "
          + " | ".join(FUSION_MODES) + " |\n|---|" + "---|" * (2 * len(FUSION_MODES)))
    for label, res in results.items():
        real = [("%.3f / %.3f" % _mean(res[m]["full"])) for m in FUSION_MODES]
        shift = [("%.3f / %.3f" % _mean(res[m]["shift"])) for m in FUSION_MODES]
        print(f"| {label} | " + " | ".join(real) + " | " + " | ".join(shift) + " |", flush=True)
    base = next(iter(results.values()))
    sem = np.array([[base[m]["sem"][p] for p in base[m]["sem"]] for m in FUSION_MODES])  # (modes, protocols, 2)
    if np.isfinite(sem).all():
        print(f"\nStandard error of one protocol's figure (the mean over the RNN seeds), median over the first "
              f"variant's modes and protocols: R@1 {np.median(sem[..., 0]):.3f}, R@P100 {np.median(sem[..., 1]):.3f}; "
              f"of a four-protocol mean about half that.")


def _mean(s: dict) -> tuple[float, float]:
    return float(np.mean([v[0] for v in s.values()])), float(np.mean([v[1] for v in s.values()]))


def variant_table(title: str, results: dict, names: list[str], key: str = "full") -> None:
    print(f"\n#### {title}\n\n| variant | mode | " + " | ".join(names) + " | mean | shift check: mean |\n|---|---|"
          + "---|" * (len(names) + 2))
    for label, res in results.items():
        for m in FUSION_MODES:
            s, sh = res[m][key], res[m]["shift"]
            cells = [f"{s[p][0]:.3f} / {s[p][1]:.3f}" for p in names]
            r1, rp = _mean(s)
            a, b = _mean(sh)
            print(f"| {label} | {m} | " + " | ".join(cells) + f" | {r1:.3f} / {rp:.3f} | {a:.3f} / {b:.3f} |",
                  flush=True)


# --------------------------------------------------------------------------- local class evidence (the CAM seed)
#: local forms of G: name -> (cache key prefix, which classes each position's softmax runs over, their count)
LOCAL_FORMS = {
    "local S, 1000 classes": ("Gloc", "all", 1000),
    "local S, the image's top-5 classes": ("Gtop5", "top", 5),
    "local S, the image's top-20 classes": ("Gtop20", "top", 20),
    "local S, a 64-class subset (the other set's)": ("Gsub64", "subset", 64),
    "local S, 1000 classes, every position's seed at unit norm": ("Glocn", "all-equal", 1000),
}
SUBSET_TOP = 5  # the subset: the classes most often among the top-5 of the other set's frames


def local_gradients(net, l6: torch.Tensor, classes: str = "all", k: int = 1000,
                    subset: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """G at stage6 and stage7 seeded with each position's own softmax (the class activation map's).

    A GAP head's logits are the mean over (h, w) of the per-position logits z(h, w) = W_fc head(h, w) + b
    (the same classifier). With S(h, w) = softmax(z(h, w)) over ``classes``:

        G = d/dL sum_{h,w} |S(h, w)|^2 / 2 = sum_{h,w} (dS(h, w)/dL)^T S(h, w)

    the paper's seeded form, position by position. ``classes``: ``all`` (1000), ``all-equal`` (1000, each
    position's seed of its logits, S(h, w) * (S(h, w) - |S(h, w)|^2), scaled to unit norm: every position
    weighs the same, however confident its classifier), ``top`` (the image's
    top-``k`` classes of the network's own logits, per image), ``subset`` (the fixed indices ``subset``),
    ``global`` (the library's G: one softmax of the pooled logits; a check). ``l6``: stage6's output
    (N, 192, h, w) at ``SIZE``; the blocks of stage7 and the head run from it (the joined tap's G:
    stage6's slice is the total gradient at stage6's output, stage7's the gradient at its own).

    Returns:
        {"stage6": (N, 192, h, w), "stage7": (N, 320, h, w), "logits": (N, 1000) of the GAP head,
        "local_top1": (N, h, w) each position's own top-1 class among ``classes``}.
    """
    info = efficientnet_lite_taps(net.variant, net.input_size)
    b6, b7 = info["stage6"][0], info["stage7"][0]
    with torch.enable_grad():
        leaf = l6.detach().requires_grad_(True)
        y7 = leaf
        for block in net._blocks[b6 + 1: b7 + 1]:
            y7 = block(y7)
        head = net._head_features(y7)  # (N, 1280, h, w)
        z = net._fc(head.mean((2, 3)))  # the network's logits
        W, b = net._fc.weight, net._fc.bias
        if classes == "global":
            p = z.softmax(1)
            idx = z.detach().argmax(1)[:, None, None].expand(-1, *head.shape[2:])
        else:
            if classes in ("all", "all-equal"):
                zl = torch.einsum("nchw,kc->nkhw", head, W) + b[:, None, None]
                pick = None
            else:
                pick = z.detach().topk(k, 1).indices if classes == "top" else subset.expand(len(l6), -1)
                zl = torch.einsum("nchw,nkc->nkhw", head, W[pick]) + b[pick][:, :, None, None]
            p = zl.softmax(1)  # (N, K, h, w): each position's own softmax
            top = p.detach().argmax(1)
            idx = top if pick is None else pick.gather(1, top.flatten(1)).view_as(top)
        if classes == "all-equal":
            q = p.detach()
            seed = q * (q - (q * q).sum(1, keepdim=True))  # d(|S(h, w)|^2 / 2) / dz(h, w)
            g6, g7 = torch.autograd.grad(zl, [leaf, y7], grad_outputs=F.normalize(seed, dim=1))
        else:
            g6, g7 = torch.autograd.grad(p, [leaf, y7], grad_outputs=p.detach())
    return {"stage6": g6, "stage7": g7, "logits": z.detach(), "local_top1": idx}


def local_subset(logits: torch.Tensor, size: int = 64, top: int = SUBSET_TOP) -> torch.Tensor:
    """(size,) the classes most often among the ``top`` classes of ``logits``' frames (ties: lower index)."""
    counts = torch.bincount(logits.topk(top, 1).indices.flatten(), minlength=logits.shape[1])
    order = sorted(range(len(counts)), key=lambda c: (-int(counts[c]), c))
    return torch.tensor(order[:size])


def load_local(views: dict, cache: Path, net=None) -> None:
    """Adds the local forms of G (``LOCAL_FORMS``' keys ``<prefix>:stage6`` / ``:stage7`` and
    ``<prefix>:top1``) to every set's and view's tap maps, from their cached stage6 L; cached in ``cache``."""
    net = net or efficientnet_lite("lite0", pretrained=True, tap="stage7", input_size=SIZE)
    names = list(views)
    for k, vs in views.items():
        other = [n for n in names if n != k]
        subset = local_subset(torch.cat([views[n]["full"]["logits"] for n in other]) if other
                              else vs["full"]["logits"])
        for view, f in vs.items():
            path = cache / f"{k}_{view}_lite0_{SIZE[0]}x{SIZE[1]}_local.pt"
            have = torch.load(path) if path.is_file() else {}
            f.update(have)
            missing = [form for form in LOCAL_FORMS.values() if f"{form[0]}:stage6" not in have]
            if not missing:
                continue
            t0 = time.perf_counter()
            out: dict[str, list] = {}
            for s in range(0, len(f["L:stage6"]), 16):
                l6 = f["L:stage6"][s:s + 16]
                for prefix, classes, n in missing:
                    g = local_gradients(net, l6, classes, n, subset)
                    for key, val in ((f"{prefix}:stage6", g["stage6"]), (f"{prefix}:stage7", g["stage7"]),
                                     (f"{prefix}:top1", g["local_top1"])):
                        out.setdefault(key, []).append(val)
            new = {key: torch.cat(v) for key, v in out.items()}
            torch.save({**have, **new}, path)
            f.update(new)
            print(f"<!-- {k} {view}: local G in {time.perf_counter() - t0:.0f} s -->", flush=True)


def view_cosines(f: dict, gt: torch.Tensor, g: str) -> list[str]:
    """Cosine between the two views of a true pair (mean over the pairs of ``gt``) of G (form ``g``), its
    between-channel part and its within-channel part, stage6 and stage7 joined; 'same / different top-1'."""
    q, r = torch.nonzero(gt, as_tuple=True)
    same = f["logits"].argmax(1)[q] == f["logits"].argmax(1)[r]
    G = [f[f"{g}:{t}"] for t in ("stage6", "stage7")]
    parts = (torch.cat([x.flatten(1) for x in G], 1), torch.cat([x.mean((2, 3)) for x in G], 1),
             torch.cat([(x - x.mean((2, 3), keepdim=True)).flatten(1) for x in G], 1))
    cells = []
    for x in parts:
        c = (F.normalize(x[q], dim=1) * F.normalize(x[r], dim=1)).sum(1)
        cells.append(f"{float(c.mean()):.2f} ({float(c[same].mean()):.2f} / {float(c[~same].mean()):.2f})")
    return cells


def local_macs(k: int, hw: int = 63) -> int:
    """Multiply-adds the per-position classifier adds to the default's G, forward and input-gradient
    backward: 1280 x k per position each way, less the pooled classifier's 1280 x 1000 both ways that
    the 1000-class form replaces (its logits are the mean of the positions')."""
    return 2 * 1280 * k * hw - (2 * 1280 * 1000 if k == 1000 else 0)


def local_cost(batches=(1, 8), rounds: int = 10) -> list[str]:
    """Measured cost: CPU time of the forward with the seeded backward to stage6+stage7 (the default's
    G, and each local form) against the plain forward, median of the paired ratios of interleaved rounds."""
    net = efficientnet_lite("lite0", pretrained=False, tap="stage7", input_size=SIZE)
    info = efficientnet_lite_taps("lite0", SIZE)
    subset = torch.arange(0, 1000, 1000 // 64)[:64]

    def to_stage6(x):
        with torch.no_grad():
            h = F.relu6(net._bn0(net._conv_stem(x)))
            for block in net._blocks[: info["stage6"][0] + 1]:
                h = block(h)
        return h

    rows = []
    for batch in batches:
        x = torch.randn(batch, 3, *SIZE, generator=torch.Generator().manual_seed(0))
        variants = {"plain": lambda x=x: net.forward_from_tap(net.forward_to_tap(x)),
                    "global": lambda x=x: local_gradients(net, to_stage6(x), "global")}
        variants.update({name: (lambda c=c, n=n, x=x: local_gradients(net, to_stage6(x), c, n, subset))
                         for name, (_, c, n) in LOCAL_FORMS.items()})
        times, ratios = _paired_cpu_ratios(variants, rounds)
        rows.append(f"| {batch} | {1000 * float(np.median(times['plain'])) / batch:.1f} | "
                    + " | ".join(f"{ratios[k]:.2f}" for k in list(variants)[1:]) + " |")
    return rows


def local_section(args, views: dict, protos: dict, seeds: tuple[int, ...]) -> dict:
    """The local (per-position) class evidence as G's seed: how spatial and how repeatable it is, what it
    does on the four protocols and the shift check, its held-out halves, its cost. Returns the variants'
    results (:func:`evaluate_variant`)."""
    names = [p for s in protos.values() for p in s]
    forms = {"G (global S)": "G", **{n: v[0] for n, v in LOCAL_FORMS.items()}}
    print("\n#### local: G seeded with each position's own softmax (the class activation map's), stage6+stage7"
          "\n\nShare of G's variance within channels (median over frames, stage6 / stage7); positions whose own "
          "top-1 class differs from the image's (mean); the two views of a true pair (cosine, mean over the pairs "
          "of the set's first protocol; in brackets: image top-1 the same / different): G, its between-channel "
          "part, its within-channel part; the share of |G|^2 (both stages) on the hottest of the positions "
          "(median; uniform: 1/63)\n\n| set | G | spatial share | positions off the image's top-1 | "
          "cos G | between-channel | within-channel | hottest position |\n|---|---|---|---|---|---|---|---|")
    for k, v in views.items():
        f = v["full"]
        gt = next(iter(protos[k].values()))[0]
        for label, g in forms.items():
            share = " / ".join(f"{float(spatial_share(f[f'{g}:{t}']).median()):.3f}" for t in ("stage6", "stage7"))
            top1 = f["logits"].argmax(1)[:, None, None]
            off = f"{float((f[f'{g}:top1'] != top1).float().mean()):.2f}" if f"{g}:top1" in f else "-"
            energy = sum(f[f"{g}:{t}"].pow(2).sum(1) for t in ("stage6", "stage7")).flatten(1)  # (N, h w)
            hot = float((energy.amax(1) / energy.sum(1).clamp_min(1e-30)).median())
            print(f"| {k} | {label} | {share} | {off} | " + " | ".join(view_cosines(f, gt, g)) + f" | {hot:.3f} |",
                  flush=True)
    results = {label: evaluate_variant(views, protos, ("stage6", "stage7"), g, DEFAULT_LAYOUT, seeds)
               for label, g in forms.items()}
    variant_table(f"local: per protocol, R@1 / R@P100, mean over {len(seeds)} RNN seed(s)", results, names)
    summary_table("local: mean over the four protocols, then the shift check", results)
    crit = {n: np.mean([sum(_mean(res[m]["half0"])) for m in FUSION_MODES]) for n, res in results.items()}
    best = max(crit, key=crit.get)
    print(f"\nChosen on the first half of each protocol's queries (mean over modes and protocols of R@1 + R@P100): "
          f"{best} ({crit[best]:.3f}; " + ", ".join(f"{n} {c:.3f}" for n, c in crit.items() if n != best) + ")")
    variant_table("local: the second half of each protocol's queries", results, names, key="half1")
    total, _ = block_macs()
    print(f"\nMultiply-adds the local seed adds to the default's G (forward {total / 1e6:.1f} M): " + ", ".join(
        f"{n} {local_macs(c) / 1e6:.1f} M ({100 * local_macs(c) / total:.1f} %)" for n, (_, _, c) in LOCAL_FORMS.items()))
    print(f"\nMeasured (CPU time, {torch.get_num_threads()} thread(s), load average {os.getloadavg()[0]:.1f}): forward "
          "+ seeded backward to stage6+stage7 / plain forward, median of the paired ratios of 10 interleaved rounds"
          "\n\n| batch | plain forward ms/frame | G (global S, both stages) | " + " | ".join(LOCAL_FORMS) + " |\n|---|---|---|"
          + "---|" * len(LOCAL_FORMS))
    for row in local_cost():
        print(row, flush=True)
    return results


def _position_l2(maps: list[torch.Tensor]) -> list[torch.Tensor]:
    # each (h, w) position's feature vector to unit length: every position weighs the same in the GeM
    return [F.normalize(m, dim=1) for m in maps]


def _signed_sqrt(code: torch.Tensor) -> torch.Tensor:
    # power normalisation (Perronnin et al. 2010; Jegou et al. 2012): damps the code's bursty entries
    return code.sign() * code.abs().sqrt()


def _kmeans_unit(x: torch.Tensor, k: int, iters: int = 30, seed: int = 0) -> torch.Tensor:
    # spherical k-means of unit rows (N, C) -> (k, C) unit centres, seeded draw of the initial centres
    g = torch.Generator().manual_seed(seed)
    c = x[torch.randperm(len(x), generator=g)[:k]].clone()
    for _ in range(iters):
        a = (x @ c.T).argmax(1)
        for j in range(k):
            if (a == j).any():
                c[j] = F.normalize(x[a == j].mean(0), dim=0)
    return c


def _local_descriptors(maps: list[torch.Tensor]) -> list[torch.Tensor]:
    # (N, C, h, w) maps -> (N, h w, C) unit local descriptors, one per position. The unit length cancels a
    # weight a position has in every channel alike: GAF's and EGA's (their VLAD rows are `none`'s, up to
    # GAF's zero-weight positions), so VLAD measures DAM and EAM against `none`.
    return [F.normalize(m.flatten(2).transpose(1, 2), dim=2) for m in maps]


def vlad_code(maps: list[torch.Tensor], centres: list[torch.Tensor]) -> torch.Tensor:
    """VLAD (Jegou et al. 2010; NetVLAD's aggregation without its training) of each map's local
    descriptors against its vocabulary: hard assignment, residuals summed per word, intra-normalised,
    signed square root, L2."""
    parts = []
    for x, c in zip(_local_descriptors(maps), centres):
        a = F.one_hot((x @ c.T).argmax(2), c.shape[0]).to(x.dtype)  # (N, P, K)
        v = torch.einsum("npk,npc->nkc", a, x) - a.sum(1)[..., None] * c[None]
        parts.append(F.normalize(v, dim=2).flatten(1))
    d = torch.cat(parts, 1)
    return F.normalize(d.sign() * d.abs().sqrt(), dim=1)


def vlad_variant(views: dict, protos: dict, taps: tuple[str, ...], words: int) -> dict:
    """evaluate_variant's result for VLAD codes of the fused maps; each set's vocabulary is learnt on the
    *other* set's unfused L (never on the evaluated images, as ORB-BoW's)."""
    if len(views) != 2:
        raise ValueError(f"VLAD learns each set's vocabulary on the other set: two sets needed, got {list(views)}")
    other = {a: b for a, b in zip(views, reversed(list(views)))}
    centres = {k: [_kmeans_unit(x.reshape(-1, x.shape[2]), words)
                   for x in _local_descriptors([views[other[k]]["full"][f"L:{t}"] for t in taps])] for k in views}
    return evaluate_variant(views, protos, taps, "G@last", DEFAULT_LAYOUT, (None,),
                            pool_fn=lambda maps, k: vlad_code(maps, centres[k]))


def encodings(seeds: tuple[int, ...]) -> dict[str, dict]:
    """Session 6: label -> the keyword arguments of :func:`evaluate_variant` (and its ``seeds``)."""
    none = (None,)
    return {
        "the paper's 16 RNNs of 64 on the code (sessions 1-5)": {"seeds": seeds},
        "no RNNs: the code itself (the default since session 6)": {"seeds": none},
        "40 RNNs of 64 (2560 dims, the code's size)": {"seeds": seeds, "rnn_fn": lambda c, s: rnn_code(c, s, 40)},
        "16 RNNs, input at norm 3 (the tanh nearer linear)": {"seeds": seeds,
                                                              "rnn_fn": lambda c, s: rnn_code(c, s, scale=3.0)},
        "positions L2-normalised before the GeM, no RNNs": {"seeds": none, "maps_fn": _position_l2},
        "positions L2-normalised before the GeM, 16 RNNs": {"seeds": seeds, "maps_fn": _position_l2},
        "signed square root of the code, no RNNs": {"seeds": none, "code_fn": _signed_sqrt},
        "signed square root of the code, 16 RNNs": {"seeds": seeds, "code_fn": _signed_sqrt},
    }


def encoding_section(views: dict, protos: dict, seeds: tuple[int, ...], frames: dict, cache: Path) -> None:
    """Session 6; ``frames``: {set: its images} and ``cache``, for the tap maps at other input sizes."""
    names = [p for s in protos.values() for p in s]
    spec = encodings(seeds)
    results = {label: evaluate_variant(views, protos, ("stage6", "stage7"), "G@last", DEFAULT_LAYOUT, **kw)
               for label, kw in spec.items()}
    variant_table(f"encoding of the regional code (stage6 unfused + stage7, R@1 / R@P100; RNN rows the mean "
                  f"over {len(seeds)} RNN seed(s))", results, names)
    summary_table("encoding: mean over the four protocols, R@1 / R@P100", results)
    crit = {n: np.mean([sum(_mean(res[m]["half0"])) for m in FUSION_MODES]) for n, res in results.items()}
    print("\nHeld-out halves: the criterion on the first half of each protocol's queries (mean over modes and "
          "protocols of R@1 + R@P100): " + "; ".join(f"{n} {c:.3f}" for n, c in crit.items()))
    best = max(crit, key=crit.get)
    first = next(iter(results))
    variant_table(f"encoding, second half: the chosen ({best}) and the RNNs", {
        f"chosen: {best}": results[best], first: results[first]}, names, key="half1")
    # Sessions 1 and 3 chose the GeM exponent and the regions with the RNNs: chosen again without them.
    pooling = {f"p = {p:g}, {lay}": evaluate_variant(views, protos, ("stage6", "stage7"), "G@last", lay, (None,), p=p)
               for p in (2.0, 3.0, 4.0) for lay in (DEFAULT_LAYOUT, "whole + 2x2 + 3 strips",
                                                     "whole + 2x2 overlapping (2/3 size)")}
    summary_table("pooling without RNNs: the GeM exponent and the regions (four-protocol mean, R@1 / R@P100)",
                  pooling)
    crit = {n: np.mean([sum(_mean(res[m]["half0"])) for m in FUSION_MODES]) for n, res in pooling.items()}
    print("\nHeld-out halves, the same criterion: " + "; ".join(f"{n} {c:.3f}" for n, c in crit.items())
          + f"; chosen: {max(crit, key=crit.get)}")
    # Session 1 chose the input size with the RNNs: chosen again without them (taps cached per size).
    sizes = {}
    for size in ((224, 224), (192, 256), (224, 288), (288, 384)):
        at = views if size == SIZE else {k: load_taps(k, images, cache, size) for k, images in frames.items()}
        sizes[f"{size[0]} x {size[1]}"] = evaluate_variant(at, protos, ("stage6", "stage7"), "G@last", DEFAULT_LAYOUT,
                                                           (None,))
    summary_table("input size without RNNs (four-protocol mean, R@1 / R@P100)", sizes)
    crit = {n: np.mean([sum(_mean(res[m]["half0"])) for m in FUSION_MODES]) for n, res in sizes.items()}
    print("\nHeld-out halves, the same criterion: " + "; ".join(f"{n} {c:.3f}" for n, c in crit.items()))
    # An orderless aggregation instead of the regions: VLAD of the fused maps' local descriptors
    vlad = {f"VLAD, {words} words per stage, {'+'.join(taps)}": vlad_variant(views, protos, taps, words)
            for taps, words in ((("stage6", "stage7"), 16), (("stage6", "stage7"), 32),
                                (("stage5", "stage6", "stage7"), 16))}
    summary_table("VLAD of the fused maps, vocabulary learnt on the other set (four-protocol mean, R@1 / R@P100)",
                  {"the regional code (the default)": results["no RNNs: the code itself (the default since session 6)"],
                   **vlad})
    # Session 3's forms of G at stage7, again without the RNNs (fuse_taps: the within-channel part, G clamped
    # at the head output, GAF/EGA on the channel-summed |G|), per protocol.
    forms = {f"G as {g.removesuffix('@last')}, no RNNs": evaluate_variant(views, protos, ("stage6", "stage7"), g,
                                                                       DEFAULT_LAYOUT, (None,))
             for g in ("G@last", "spatial@last", "Gc@last", "chsum@last")}
    variant_table("forms of G at stage7 without the RNNs (R@1 / R@P100)", forms, names)
    crit = {n: np.mean([sum(_mean(res[m]["half0"])) for m in FUSION_MODES]) for n, res in forms.items()}
    print("\nHeld-out halves, the same criterion: " + "; ".join(f"{n} {c:.3f}" for n, c in crit.items()))
    variant_table("forms of G, second half of each protocol's queries", forms, names, key="half1")
    # The SLAM's loop threshold has an absolute floor (slam/config.py): the scale of the similarities.
    print("\nSimilarity scale, kitchen frames >= 100 apart (every 5th frame), median [10th, 90th percentile]:\n\n"
          "| encoding | " + " | ".join(FUSION_MODES) + " |\n|---|" + "---|" * len(FUSION_MODES))
    f = views["kitchen"]["full"]
    for label in (first, "no RNNs: the code itself (the default since session 6)",
                  "signed square root of the code, no RNNs"):
        kw = spec[label]
        cells = []
        for m in FUSION_MODES:
            code = (kw.get("code_fn") or (lambda c: c))(layout_code(fuse_taps(f, ("stage6", "stage7"), m, "G@last")))
            d = rnn_code(code, kw["seeds"][0])
            i, j = torch.triu_indices(len(d), len(d), 20)
            v = (d @ d.T)[i, j]
            cells.append(f"{float(v.median()):.3f} [{float(v.quantile(0.1)):.3f}, {float(v.quantile(0.9)):.3f}]")
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)


def _conditions() -> dict:
    from place_recognition import downscaled, grayscale

    # colour: the full frames, already in the views (load_taps); the others are extracted and cached here
    return {"colour": None, "grey": grayscale, "1/4 size": lambda ims: downscaled(ims, 4),
            "grey, 1/4 size": lambda ims: grayscale(downscaled(ims, 4))}


def conditions_section(data: dict, views: dict, protos: dict, cache: Path) -> None:
    """Session 7: the forms of G on colour, grey, 1/4-size and grey 1/4-size copies, and the shift check."""
    names = [p for s in protos.values() for p in s]
    conds = _conditions()
    feats = {}
    for cname, transform in conds.items():
        feats[cname] = {}
        for k, (images, _) in data.items():
            if transform is None:
                feats[cname][k] = views[k]["full"]
                continue
            path = cache / f"{k}_{cname.replace(' ', '').replace(',', '_').replace('/', 'of')}_cond.pt"
            if path.is_file():
                feats[cname][k] = torch.load(path)
            else:
                t0 = time.perf_counter()
                feats[cname][k] = extract_taps(transform(images))
                torch.save(feats[cname][k], path)
                print(f"<!-- {k}, {cname}: tap maps in {time.perf_counter() - t0:.0f} s -->", flush=True)
    columns = [*conds, "shift check"]
    taps = ("stage6", "stage7")
    for form in ("G@last", "spatial@last", "Gc@last", "chsum@last"):
        print(f"\n#### conditions: G as {form.removesuffix('@last')} at stage7 (R@1 / R@P100 on "
              + ", ".join(names) + ")\n\n| mode | " + " | ".join(columns) + " |\n|---|" + "---|" * len(columns))
        per = {}
        for m in FUSION_MODES:
            for cname in conds:
                per[m, cname] = scores({k: layout_code(fuse_taps(f, taps, m, form)) for k, f in feats[cname].items()},
                                       protos)
            per[m, "shift check"] = scores({k: (layout_code(fuse_taps(v["left"], taps, m, form)),
                                                layout_code(fuse_taps(v["right"], taps, m, form)))
                                            for k, v in views.items()}, protos)
            print(f"| {m} | " + " | ".join(" ".join(f"{per[m, c][p][0]:.3f}/{per[m, c][p][1]:.3f}" for p in names)
                                           for c in columns) + " |", flush=True)
        cells = len(columns) * len(names) * 2
        for m in FUSION_MODES[1:]:
            d = np.array([per[m, c][p][i] - per["none", c][p][i] for c in columns for p in names for i in (0, 1)])
            print(f"- {m}: {int((d < -1e-9).sum())} of {cells} figures below `none`'s (R@1 "
                  f"{int((d[0::2] < -1e-9).sum())}, R@P100 {int((d[1::2] < -1e-9).sum())}), deficits summed "
                  f"{d[d < 0].sum():+.3f}, all differences summed {d.sum():+.3f}")


def imagenet_tap_statistics(net=None) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """{tap: (mean, std)} per channel of Lite0's stage6 and stage7 outputs over ImageNet, read from the weights.

    Each MBConv block ends in a batch-norm without activation, whose output over the training set has
    mean ``beta`` and standard deviation ``|gamma|`` (eval-mode running statistics). stage7 is one block:
    (beta, |gamma|) exactly. stage6's first block has no skip connection and its three others add their
    output to their input, so its mean is the sum of the four betas; its standard deviation is taken as
    sqrt(sum gamma^2), as if the four blocks' outputs were uncorrelated (an approximation).
    """
    net = net or efficientnet_lite("lite0", pretrained=True, tap="stage7")
    info = efficientnet_lite_taps("lite0", SIZE)
    out = {}
    first = info["stage5"][0] + 1
    for tap in ("stage6", "stage7"):
        last = info[tap][0]
        bns = [net._blocks[k]._bn2 for k in range(first, last + 1)]
        mean = torch.stack([bn.bias.detach() for bn in bns]).sum(0)
        std = torch.stack([bn.weight.detach() ** 2 for bn in bns]).sum(0).sqrt()
        out[tap] = (mean, std)
        first = last + 1
    return out


def imagenet_standardised(views: dict, stats: dict, centre: bool, scale: bool) -> dict:
    """``views`` with L at stage6 and stage7 replaced by (L - mean) / std of ``stats`` (either part
    optional); G unchanged (the fusions read G through N(.), and L's affine change is the hypothesis)."""
    out = {}
    for k, v in views.items():
        out[k] = {}
        for view, f in v.items():
            g = dict(f)
            for tap, (mean, std) in stats.items():
                L = f[f"L:{tap}"]
                if centre:
                    L = L - mean[None, :, None, None].to(L)
                if scale:
                    L = L / std[None, :, None, None].to(L)
                g[f"L:{tap}"] = L
            out[k][view] = g
    return out


def imagenet_section(views: dict, protos: dict) -> None:
    """Session 7: the tap standardised with ImageNet's statistics from the batch-norms (see the module doc)."""
    names = [p for s in protos.values() for p in s]
    stats = imagenet_tap_statistics()
    for tap, (mean, std) in stats.items():
        emp = {k: v["full"][f"L:{tap}"] for k, v in views.items()}
        corr = "; ".join(f"{k}: mean {float(torch.corrcoef(torch.stack([L.mean((0, 2, 3)), mean]))[0, 1]):.2f}, "
                         f"std {float(torch.corrcoef(torch.stack([L.std((0, 2, 3)), std]))[0, 1]):.2f}"
                         for k, L in emp.items())
        print(f"\n{tap}: ImageNet mean over channels {float(mean.abs().mean()):.3g} (|.|), std {float(std.mean()):.3g}; "
              f"the sets' own per-channel statistics against them (correlation over channels): {corr}")
    variants = {"as is (the default)": (False, False), "centred by ImageNet's mean": (True, False),
                "scaled by ImageNet's std": (False, True), "standardised (both)": (True, True)}
    results = {label: evaluate_variant(imagenet_standardised(views, stats, c, s) if c or s else views, protos,
                                       ("stage6", "stage7"), "G@last", DEFAULT_LAYOUT, (None,))
               for label, (c, s) in variants.items()}
    variant_table("the tap standardised with ImageNet's statistics (R@1 / R@P100)", results, names)
    summary_table("the tap standardised with ImageNet's statistics: four-protocol mean, R@1 / R@P100", results)
    crit = {n: np.mean([sum(_mean(res[m]["half0"])) for m in FUSION_MODES]) for n, res in results.items()}
    print("\nHeld-out halves, the criterion on the first half: " + "; ".join(f"{n} {c:.3f}" for n, c in crit.items()))
    best = max(crit, key=crit.get)
    variant_table(f"second half: the chosen ({best}) and the default", {
        f"chosen: {best}": results[best], "default": results["as is (the default)"]}, names, key="half1")


# --------------------------------------------------------------------------- session 9: RNNs over sub-regions
def region_vectors(maps: list[torch.Tensor], layout: str = DEFAULT_LAYOUT) -> tuple[torch.Tensor, list[int]]:
    """Each region of ``layout`` of each fused map, raw (no pooling), flattened and L2-normalised:
    ``(B, sum of C h w over maps and regions)`` and the split sizes, map-major, regions in layout order."""
    regions, _ = LAYOUTS[layout]
    parts = [F.normalize(x[:, :, a:b, c:d].flatten(1), dim=1)
             for x in maps for a, b, c, d in regions(*x.shape[2:])]
    return torch.cat(parts, 1), [v.shape[1] for v in parts]


def subregion_rnn(vectors: torch.Tensor, sizes: list[int], seed: int, num_rnn: int, scale: float = 10.0
                  ) -> torch.Tensor:
    """The paper's one-level random RNNs (U[-0.1, 0.1], tanh, no bias) over each region's raw sub-map
    (CNN-randRNN's RNNs over sub-regions) at input norm ``scale`` (the library's ``pool_scale``): every
    region its own ``num_rnn`` RNNs of 64 (seeded by ``seed`` and the region's place), each region's
    output L2-normalised, concatenated, L2."""
    out = []
    for r, v in enumerate(vectors.split(sizes, 1)):
        key = ("subregion", v.shape[1], seed, r, num_rnn)
        if key not in _W:
            _W[key] = random_rnn_weights(num_rnn, v.shape[1], 64, seed=1000 * seed + r)
        out.append(F.normalize(random_rnn_pool(scale * v[:, :, None, None], _W[key], merge=False), dim=1))
    return F.normalize(torch.cat(out, 1), dim=1)


def subregion_section(views: dict, protos: dict, seeds: tuple[int, ...]) -> None:
    """Session 9: the issue's "RNNs over sub-regions" against pooling first (the default) and the paper's
    RNN over the whole map, on the default's fused maps (stage6 unfused + stage7 fused)."""
    names = [p for s in protos.values() for p in s]
    taps = ("stage6", "stage7")
    sizes = {}

    def pool(layout):
        def fn(maps, _set):
            v, sizes[layout] = region_vectors(maps, layout)
            return v
        return fn

    def rnn(layout, num_rnn):
        return lambda code, seed: subregion_rnn(code, sizes[layout], seed, num_rnn)

    whole, grid = "whole", DEFAULT_LAYOUT
    results = {
        "regional GeM, no RNNs (the default)": evaluate_variant(views, protos, taps, "G@last", grid, (None,)),
        "16 RNNs over each stage's whole map (the paper's flat pooling)":
            evaluate_variant(views, protos, taps, "G@last", whole, seeds, pool_fn=pool(whole), rnn_fn=rnn(whole, 16)),
        "RNNs over sub-regions: whole + 2 x 2, 4 RNNs each (2560 dims)":
            evaluate_variant(views, protos, taps, "G@last", grid, seeds, pool_fn=pool(grid), rnn_fn=rnn(grid, 4)),
        "RNNs over sub-regions: whole + 2 x 2, 16 RNNs each (10240 dims)":
            evaluate_variant(views, protos, taps, "G@last", grid, seeds, pool_fn=pool(grid), rnn_fn=rnn(grid, 16)),
    }
    variant_table(f"RNNs over sub-regions (R@1 / R@P100; RNN rows the mean over {len(seeds)} RNN seed(s))",
                  results, names)
    summary_table("RNNs over sub-regions: four-protocol mean, R@1 / R@P100", results)
    crit = {n: np.mean([sum(_mean(res[m]["half0"])) for m in FUSION_MODES]) for n, res in results.items()}
    print("\nHeld-out halves, the criterion on the first half: " + "; ".join(f"{n} {c:.3f}" for n, c in crit.items()))


def session3(args, data: dict, protos: dict) -> None:
    views = {k: load_taps(k, images, args.cache) for k, (images, _) in data.items()}
    names = [p for s in protos.values() for p in s]
    if "encoding" in args.only:
        if len(views) != 2:
            raise SystemExit("encoding needs both sets (rtabmap-samples and the kitchen)")
        encoding_section(views, protos, tuple(range(args.rnn_seeds)), {k: v[0] for k, v in data.items()},
                         args.cache)
    if "imagenet" in args.only:
        imagenet_section(views, protos)
    if "subregions" in args.only:
        subregion_section(views, protos, tuple(range(args.rnn_seeds)))
    if "conditions" in args.only:
        conditions_section(data, views, protos, args.cache)
    local = {}
    if "local" in args.only:
        load_local(views, args.cache)
        local = local_section(args, views, protos, tuple(range(args.rnn_seeds)))
    if "spatial" in args.only:
        print("\n#### spatial: the share of G's variance within channels, over (H, W), median [10th, 90th "
              "percentile] over frames\n\n| set | G at | plain G | G clamped at the head output |\n|---|---|---|---|")
        for k, v in views.items():
            f = v["full"]
            q = lambda x: f"{float(x.median()):.3f} [{float(x.quantile(0.1)):.3f}, {float(x.quantile(0.9)):.3f}]"
            for t in (*TAPS, "head_pre", "head"):
                clamped = q(f[f"share_c:{t}"]) if f"share_c:{t}" in f else "-"
                print(f"| {k} | {t} | {q(f[f'share:{t}'])} | {clamped} |")
        print("\nHow alike the two views of a true pair are (cosine, mean over the pairs of the set's first "
              "protocol; top-1 class the same / different): G's between-channel part (each channel's mean over "
              "(H, W)), its within-channel part (G minus that mean), and L\n\n| set | G at | pairs | top-1 "
              "differs | between-channel part | within-channel part | L |\n|---|---|---|---|---|---|---|")
        for k, v in views.items():
            f = v["full"]
            gt = next(iter(protos[k].values()))[0]
            q, r = torch.nonzero(gt, as_tuple=True)
            same = f["logits"].argmax(1)[q] == f["logits"].argmax(1)[r]
            for t in ("stage6", "stage7"):
                G = f[f"G:{t}"]
                parts = (G.mean((2, 3)), (G - G.mean((2, 3), keepdim=True)).flatten(1), f[f"L:{t}"].flatten(1))
                cells = []
                for x in parts:
                    c = (F.normalize(x[q], dim=1) * F.normalize(x[r], dim=1)).sum(1)
                    cells.append(f"{float(c[same].mean()):.2f} / {float(c[~same].mean()):.2f}")
                print(f"| {k} | {t} | {len(q)} | {float((~same).float().mean()):.2f} | " + " | ".join(cells) + " |")
        total, above = block_macs()
        print(f"\nLite0 forward at {SIZE[0]} x {SIZE[1]}: {total / 1e6:.1f} M multiply-adds; the backward from "
              "the logits to a tap (input gradients only): " + ", ".join(
                  f"{t} {above[t] / 1e6:.1f} M ({100 * above[t] / total:.1f} %)" for t in TAPS))
    if "spatial" in args.only:
        print(f"\nMeasured (CPU time, {torch.get_num_threads()} thread(s), load average "
              f"{os.getloadavg()[0]:.1f}): forward + seeded backward to the tap / plain forward, median of "
              "the paired ratios of 10 interleaved rounds\n\n| batch | plain forward ms/frame | "
              + " | ".join(f"G at {t}" for t in reversed(TAPS)) + " |\n|---|---|---|---|---|---|")
        for row in tap_cost():
            print(row, flush=True)
    results = {}
    seeds = tuple(range(args.rnn_seeds))
    if "taps" in args.only or "halves3" in args.only:
        results.update({n: evaluate_variant(views, protos, *spec, seeds) for n, spec in TAP_VARIANTS.items()})
        if "taps" in args.only:
            variant_table("taps and the form of G (regional whole + 2x2, R@1 / R@P100)",
                          {n: results[n] for n in TAP_VARIANTS}, names)
    if "layouts" in args.only or "halves3" in args.only:
        results.update({n: evaluate_variant(views, protos, *spec, seeds) for n, spec in LAYOUT_VARIANTS.items()})
        if "layouts" in args.only:
            variant_table("layouts of the regions (stage6+stage7, R@1 / R@P100)",
                          {n: results[n] for n in LAYOUT_VARIANTS}, names)
    if results:
        summary_table(f"summary: mean over the four protocols, R@1 / R@P100, mean over {len(seeds)} RNN seed(s)",
                      results)
    if "shift" in args.only:
        picked = {n: results[n] for n in results} or local or {
            n: evaluate_variant(views, protos, *spec, seeds) for n, spec in {**TAP_VARIANTS, **LAYOUT_VARIANTS}.items()}
        print(f"\n#### shift check: queries the left {CROP:.0%} of each frame, the database the right {CROP:.0%} "
              "(R@1 / R@P100)\n\n| variant | mode | " + " | ".join(names) + " | mean |\n|---|---|" + "---|" * (len(names) + 1))
        for label, res in picked.items():
            for m in FUSION_MODES:
                s = res[m]["shift"]
                r1, rp = _mean(s)
                print(f"| {label} | {m} | " + " | ".join(f"{s[p][0]:.3f} / {s[p][1]:.3f}" for p in names)
                      + f" | {r1:.3f} / {rp:.3f} |")
        print("\nAnchors (real protocols, then the shift check):\n\n| anchor | | " + " | ".join(names)
              + " | mean |\n|---|---|" + "---|" * (len(names) + 1))
        if len(data) == 2:
            for label, res in anchors(data, views, protos).items():
                for key in ("full", "shift"):
                    s = res[key]
                    print(f"| {label} | {'real' if key == 'full' else 'shift'} | "
                          + " | ".join(f"{s[p][0]:.3f} / {s[p][1]:.3f}" for p in names)
                          + " | %.3f / %.3f |" % _mean(s), flush=True)
    if "halves3" in args.only:
        # the criterion on the first half: the mean over protocols and the five modes of R@1 + R@P100
        crit = {n: np.mean([sum(_mean(res[m]["half0"])) for m in FUSION_MODES]) for n, res in results.items()}
        best = max(crit, key=crit.get)
        print(f"\n#### halves3: chosen on the first half of each protocol's queries (mean over modes and protocols "
              f"of R@1 + R@P100): {best} ({crit[best]:.3f}; the default {crit[next(iter(TAP_VARIANTS))]:.3f})")
        variant_table("second half: the chosen variant and the default", {
            f"chosen: {best}": results[best], "default": results[next(iter(TAP_VARIANTS))]}, names, key="half1")


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
    parser.add_argument("--rnn-seeds", type=int, default=1,
                        help="each figure the mean over RNN seeds 0 .. N-1 (default 1: seed 0 only); "
                             "session 2's tables and session 3's")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    data = sets(args.data)
    if not data:
        raise SystemExit(f"no real set under {args.data}")
    protos = {k: v[1] for k, v in data.items()}
    feats = {}
    args.cache.mkdir(parents=True, exist_ok=True)
    print(f"# Attention hypotheses ({time.strftime('%Y-%m-%d %H:%M')}), R@1 / R@P100 per protocol")
    if any(h in SESSION3 for h in args.only):
        session3(args, data, protos)
    if not any(h not in SESSION3 for h in args.only):
        return
    for k, (images, _) in data.items():
        path = args.cache / f"{k}_lite0_{SIZE[0]}x{SIZE[1]}.pt"
        feats[k] = torch.load(path) if path.is_file() else {}
        missing = [kind for kind in SEEDS if kind not in feats[k]]
        if missing:
            t0 = time.perf_counter()
            feats[k].update(extract(images, missing))
            torch.save(feats[k], path)
            print(f"<!-- {k}: features in {time.perf_counter() - t0:.0f} s -->", flush=True)

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

    seeds = tuple(range(args.rnn_seeds))
    own = lambda **kw: (lambda f, m: fused(f["L"], f["own"], m, **kw))
    if "norm" in args.only:
        table("norm: N(.) over (C, H, W) as the paper, or per channel (dam/eam) / inner over (C, H, W) "
              "(gaf/ega), or N = the rank (percentile) of each entry", {"paper N": own(), "per-channel N":
              own(norm="channel"), "rank N": own(norm="rank")}, feats, protos, seeds=seeds)
    if "smooth" in args.only:
        table("smooth: G averaged over 3 x 3 before N", {"paper": own(), "smoothed G": own(smooth=True)},
              feats, protos, seeds=seeds)
    if "sign" in args.only:
        table("sign: N(abs G) instead of N(G)", {"paper": own(), "abs G": own(sign=True),
                                                "abs G, smoothed": own(sign=True, smooth=True)}, feats, protos, seeds=seeds)
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
              code_fn=region_weighted_code, seeds=seeds)
    if "seed" in args.only:
        table("seed: the softmax seed of the backward",
              {kind: (lambda f, m, kind=kind: fused(f["L"], f[kind], m)) for kind in SEEDS}, feats, protos, seeds=seeds)


if __name__ == "__main__":
    main()
