"""Place recognition on real places: every fusion mode and the anchors side by side, in one run.

Sets (each skipped with a note when its data is absent):

* ``rtabmap``: rtabmap-samples, 84 images of a corridor walked twice with RTAB-Map's ground-truth loop
  matrix. ``fwd``: each image against those at least 10 earlier (the existing protocol: the 44
  revisiting images 41-84 have a true match); ``rev``: against those at least 10 later (images 1-45).
* ``kitchen``: 7-Scenes redkitchen, every 5th frame (200), ground truth from the poses (0.5 m,
  45 degrees). ``fwd``: each frame against those at least 100 frames earlier; ``split``: the second
  half of the sequence (frames 500-995) against the first.
* ``--query DIR --reference DIR --ground-truth FILE``: a VPR-Bench-style pair of folders (images in
  natural order of their names, numbers compared as numbers: VPR-Bench's order) with a ``ground_truth_new.npy``
  or a binary matrix (:mod:`attnloop.vpr.evaluate`).

Methods (all L2-normalised, cosine similarity; ORB-BoW with its own score):

* ``<mode>``: ``AttentionDescriptor("efficientnet_lite0", fusion=mode, pretrained=True)``, the default's tap
  and pooling with each fusion (the default's own: ``none``);
* ``paper <mode>``: the same with ``preset="paper"``;
* ``GAP`` / ``GeM``: the default descriptor's tap L (Lite0 stage5 of 256 x 320, 112 x 16 x 20) globally
  average-pooled / GeM-pooled (p = 3), no attention, no RNN;
* ``ORB-BoW``: a bag of ORB words as ORB-SLAM2 / RTAB-Map detect loops: 1000 ORB features per image,
  a 1000-word vocabulary (DBoW2's k-means for binary codes: Hamming distance, words the bitwise majority;
  deterministic at any thread count, without faiss), tf-idf weights and DBoW2's
  L1 score ``1 - |v1 - v2|_1 / 2`` (0 for an image without features). The vocabulary and idf are learnt on
  images other than the evaluated ones: the kitchen's frames for rtabmap and for user folders, rtabmap-samples plus
  scikit-image's photographs for the kitchen.

Usage:
    python -m benchmarks.place_recognition [--data ../shared/data] [--sets rtabmap kitchen] [--out runs/pr]
    python -m benchmarks.place_recognition --methods orb      # the ORB-BoW anchor alone (2 min)
    python -m benchmarks.place_recognition --methods orb --bow-seeds 0 1 2 3 4   # its spread over vocabularies
    python -m benchmarks.place_recognition --grayscale        # grayscale copies (the held-out corridor is grayscale)
    python -m benchmarks.place_recognition --downscale 4      # every image at 1/4 of its width and height
    python -m benchmarks.place_recognition --sequence 1 3 5   # also score sequences of 3 and 5 frames (SeqSLAM)
    python -m benchmarks.place_recognition --misses           # and which queries each method misses, and how
    python -m benchmarks.place_recognition --sets --query corridor/query --reference corridor/ref \\
        --ground-truth corridor/ground_truth_new.npy

Prints markdown tables (R@1, R@5, R@10, AUC-PR as VPR-Bench defines it, recall at 100 % precision and
its threshold) and writes one PR-curve PNG per protocol to ``--out``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from attnloop import AttentionDescriptor
from attnloop.fusion import FUSION_MODES
from attnloop.vpr.describe import VPRInputError, folder_images, load_rgb
from attnloop.vpr.evaluate import (
    evaluate,
    ground_truth_from_poses,
    plot_place_recognition,
    read_ground_truth,
    sequence_candidates,
    sequence_similarity,
)
from benchmarks._common import DATA_HELP, data_root
from slam.eval.loops import LoopGroundTruthConfig
from slam.io.images import FrameReadError


def grayscale(images: list[np.ndarray]) -> list[np.ndarray]:
    """Each (H, W, 3) RGB image as its luminance (OpenCV's RGB -> gray) in all three channels: what a
    grayscale set such as VPR-Bench's corridor gives a colour network."""
    return [np.repeat(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)[:, :, None], 3, axis=2) for im in images]


def downscaled(images: list[np.ndarray], factor: int) -> list[np.ndarray]:
    """Each (H, W, 3) image shrunk ``factor`` times in width and height (OpenCV's area interpolation, sizes
    rounded down): a low-resolution camera, which the descriptor's resize then upsamples to its input."""
    if factor == 1:
        return images
    return [cv2.resize(im, (max(1, im.shape[1] // factor), max(1, im.shape[0] // factor)),
                       interpolation=cv2.INTER_AREA) for im in images]


# ------------------------------------------------------------------------------------------ ORB-BoW
def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances of binary codes given as 0/1 bits: (n, B) and (k, B) float32 -> (n, k) int32.

    |a| + |b| - 2 a.b through one matrix product: every product and partial sum is an integer below
    2^24, so float32 holds it exactly in any summation order, and the result is the same whatever the
    BLAS library, its blocking or its thread count.
    """
    dots = a @ b.T
    return (a.sum(1, dtype=np.float32)[:, None] + b.sum(1, dtype=np.float32)[None, :] - 2 * dots).astype(np.int32)


def nearest_word(bits: np.ndarray, words: np.ndarray, chunk: int = 8192) -> np.ndarray:
    """(n, B) 0/1 float32 codes, (k, B) 0/1 float32 words -> (n,) int64 index of the nearest word in
    Hamming distance; ties go to the lowest index (``np.argmin``)."""
    out = np.empty(bits.shape[0], np.int64)
    for s in range(0, bits.shape[0], chunk):
        out[s:s + chunk] = hamming(bits[s:s + chunk], words).argmin(1)
    return out


class VocabularyTooSmall(ValueError):
    """Fewer distinct ORB descriptors than words: no vocabulary can be learnt (e.g. images so small that
    ORB, which keeps 31 pixels from every border at every pyramid level, finds no keypoint in them)."""


def k_majority(bits: np.ndarray, k: int, seed: int = 0, iterations: int = 20,
               init: np.ndarray | None = None) -> np.ndarray:
    """DBoW2's k-means for binary descriptors: Hamming assignment, each word the bitwise majority of its
    codes. (n, B) 0/1 -> (k, B) 0/1 float32.

    Deterministic by construction: integer arithmetic only (distances through :func:`hamming`, bit
    counts summed as integers), ties to the lowest index, the initial words a seeded draw of distinct
    codes. So the vocabulary is the same at any thread count and with or without optional packages
    (faiss's k-means, the previous implementation, depends on them). A word whose cluster empties keeps
    its value; the loop stops early when no assignment changes. A bit is set when at least half of the
    cluster's codes have it (DBoW2's ``sum >= ceil(n / 2)``). ``init``: the (k, B) initial words instead of
    the seeded draw.
    """
    if init is not None:
        words = np.array(init, np.float32)
        if words.shape != (k, bits.shape[1]):
            raise ValueError(f"init must have shape ({k}, {bits.shape[1]}), got {words.shape}")
    else:
        codes = np.unique(bits.astype(np.uint8), axis=0)  # sorted distinct codes: the draw ignores their order
        if codes.shape[0] < k:
            raise VocabularyTooSmall(f"{codes.shape[0]} distinct ORB descriptors for a vocabulary of {k} words: "
                                     "train on more images or ask for fewer words")
        words = codes[np.random.default_rng(seed).choice(codes.shape[0], k, replace=False)].astype(np.float32)
    ints = bits.astype(np.int32)
    assign = None
    for _ in range(iterations):
        new = nearest_word(bits, words)
        if assign is not None and np.array_equal(new, assign):
            break
        assign = new
        order = np.argsort(assign, kind="stable")
        n = np.bincount(assign, minlength=k)
        used = np.flatnonzero(n)
        starts = np.concatenate([[0], np.cumsum(n[used])[:-1]])
        ones = np.add.reduceat(ints[order], starts, axis=0)  # (used, B) bit counts, exact
        words[used] = (2 * ones >= n[used, None]).astype(np.float32)
    return words


class OrbBagOfWords:
    """A flat ORB vocabulary with tf-idf weights and DBoW2's L1 score (see the module docstring).

    The vocabulary is learnt by :func:`k_majority`: the same words at any thread count and whether or
    not faiss is installed.
    """

    def __init__(self, words: int = 1000, features: int = 1000, seed: int = 0):
        self.words, self.features, self.seed = words, features, seed
        self.orb = cv2.ORB_create(nfeatures=features)

    def _describe(self, rgb: np.ndarray) -> np.ndarray:
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        _, d = self.orb.detectAndCompute(grey, None)
        return np.zeros((0, 32), np.uint8) if d is None else d

    def fit(self, images: list[np.ndarray]) -> OrbBagOfWords:
        descs = [self._describe(im) for im in images]
        bits = np.unpackbits(np.concatenate(descs), axis=1).astype(np.float32)
        rng = np.random.default_rng(self.seed)
        if bits.shape[0] > 100_000:
            bits = bits[rng.choice(bits.shape[0], 100_000, replace=False)]
        self._word_bits = k_majority(bits, self.words, self.seed)
        self.vocab = np.packbits(self._word_bits.astype(np.uint8), axis=1)  # (words, 32) binary words
        counts = np.stack([np.bincount(self._assign(d), minlength=self.words) > 0 for d in descs])
        self.idf = np.log(len(descs) / np.maximum(counts.sum(0), 1)).astype(np.float32)
        return self

    def _assign(self, d: np.ndarray) -> np.ndarray:
        # the nearest word in Hamming distance, ties to the lowest index (exact at any thread count)
        if d.shape[0] == 0:
            return np.zeros(0, np.int64)
        return nearest_word(np.unpackbits(d, axis=1).astype(np.float32), self._word_bits)

    def transform(self, images: list[np.ndarray]) -> torch.Tensor:
        out = np.zeros((len(images), self.words), np.float32)
        for i, im in enumerate(images):
            w = self._assign(self._describe(im))
            if w.size:
                tf = np.bincount(w, minlength=self.words) / w.size
                v = tf * self.idf
                out[i] = v / max(np.abs(v).sum(), 1e-12)
        return torch.from_numpy(out)

    @staticmethod
    def similarity(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """DBoW2's L1 score ``(|a|_1 + |b|_1 - |a - b|_1) / 2 = sum_i min(a_i, b_i)`` (non-negative vectors).

        For L1-normalised vectors it is ``1 - |a - b|_1 / 2``; an image without ORB features (an empty
        vector) scores 0 with every image, as in DBoW2.
        """
        return torch.stack([torch.minimum(a[i:i + 1], b).sum(1) for i in range(a.shape[0])])


# ------------------------------------------------------------------------------------------ descriptors
def same_size_batches(images: list[np.ndarray], batch: int) -> list[list[np.ndarray]]:
    """Runs of at most ``batch`` consecutive images of one shape, in order (a batch is one tensor; a folder
    may mix sizes, and a frame's descriptor does not depend on its batch)."""
    runs: list[list[np.ndarray]] = []
    for im in images:
        if runs and len(runs[-1]) < batch and runs[-1][0].shape == im.shape:
            runs[-1].append(im)
        else:
            runs.append([im])
    return runs


def attention_codes(images: list[np.ndarray], preset: str | None, batch: int = 8) -> dict[str, torch.Tensor]:
    """Descriptors of every fusion mode from one backbone pass, plus GAP/GeM of the tap for the default."""
    desc = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=True, preset=preset)
    taps, grads = [], []
    with torch.no_grad():
        for run in same_size_batches(images, batch):
            x = torch.stack([torch.from_numpy(im).permute(2, 0, 1) for im in run])
            parts = desc.parts(x)
            taps.append(parts.tap)
            grads.append(parts.grad)
    tap, grad = torch.cat(taps), torch.cat(grads)
    prefix = "paper " if preset else ""
    out = {prefix + m: desc.from_attention(tap, grad, fusion=m) for m in FUSION_MODES}
    if preset is None:
        out["GAP"] = F.normalize(tap.mean((2, 3)), dim=1)
        out["GeM"] = F.normalize(tap.clamp_min(1e-6).pow(3.0).mean((2, 3)).pow(1.0 / 3.0), dim=1)
    return out


METHODS = ("default", "paper", "orb")


def all_methods(query: list[np.ndarray], reference: list[np.ndarray] | None, bow_train: list[np.ndarray],
                methods=METHODS, bow_seeds=(0,)):
    """{method: (Q, R) similarity}; reference None: one sequence against itself. ``methods``: ``default``
    (the five modes with GAP and GeM), ``paper`` (the five modes of ``preset="paper"``), ``orb`` (ORB-BoW,
    one vocabulary per seed of ``bow_seeds``, named ``ORB-BoW seed <s>`` when there are several)."""
    both = query + (reference or [])
    nq = len(query)
    codes = {}
    if "default" in methods:
        codes.update(attention_codes(both, None))
    if "paper" in methods:
        codes.update(attention_codes(both, "paper"))
    sims = {}
    for name, c in codes.items():
        q, r = c[:nq], (c[nq:] if reference else c)
        sims[name] = q @ r.T
    if "orb" in methods and not bow_train:
        print("\nORB-BoW: not measured: no training images other than the evaluated ones (the shared sets or "
              "scikit-image's photographs)")
    elif "orb" in methods:
        for seed in bow_seeds:
            name = "ORB-BoW" if len(bow_seeds) == 1 else f"ORB-BoW seed {seed}"
            try:
                bow = OrbBagOfWords(seed=seed).fit(bow_train)
            except VocabularyTooSmall as err:  # the anchor cannot run on these images: say so, measure the rest
                print(f"\n{name}: not measured: {err} ({len(bow_train)} training images)")
                continue
            v = bow.transform(both)
            sims[name] = bow.similarity(v[:nq], v[nq:] if reference else v)
    return sims


# ------------------------------------------------------------------------------------------ sets
def kitchen_poses(seq: Path, frames: list[int]) -> torch.Tensor:
    from slam.lie import rotmat_to_quat

    T = torch.tensor(np.stack([np.loadtxt(seq / f"frame-{i:06d}.pose.txt").reshape(4, 4) for i in frames]))
    return torch.cat([T[:, :3, 3], rotmat_to_quat(T[:, :3, :3])], dim=1)


def skimage_photos() -> list[np.ndarray]:
    try:
        import skimage.data as sk
    except ImportError:
        return []
    out = []
    for name in ("astronaut", "chelsea", "coffee", "rocket", "motorcycle_left", "hubble_deep_field"):
        fn = getattr(sk, name, None)
        try:
            im = fn() if fn else None
        except Exception:  # noqa: BLE001  (some need a download)
            im = None
        if im is not None and im.ndim == 3:
            out.append(np.ascontiguousarray(im[..., :3]))
    return out


def protocols_rtabmap(data: Path):
    d = data / "rtabmap-samples"
    if not (d / "samples_GT.bmp").is_file():
        return None
    images = [load_rgb(d / f"{i}.jpg") for i in range(1, 85)]
    gt = read_ground_truth(d / "samples_GT.bmp")
    sym = gt | gt.T
    cand = sequence_candidates(84, 10)
    kitchen = data / "7scenes-redkitchen"
    bow_train = [load_rgb(kitchen / f"frame-{i:06d}.color.jpg") for i in range(0, 1000, 5)]
    names = [str(i) for i in range(1, 85)]  # image i.jpg
    return images, None, bow_train, {"fwd": (sym & cand, cand), "rev": (sym & cand.T, cand.T)}, (names, names)


def protocols_kitchen(data: Path, step: int = 5):
    d = data / "7scenes-redkitchen"
    if not (d / "frame-000000.color.jpg").is_file():
        return None
    frames = list(range(0, 1000, step))
    images = [load_rgb(d / f"frame-{i:06d}.color.jpg") for i in frames]
    poses = kitchen_poses(d, frames)
    gap = 100 // step
    gt = ground_truth_from_poses(poses, config=LoopGroundTruthConfig(0.5, 45.0, gap))
    cand = sequence_candidates(len(frames), gap)
    half = len(frames) // 2
    split = torch.zeros_like(cand)
    split[half:, :half] = True
    gt_split = torch.zeros_like(gt)
    gt_split[half:, :half] = ground_truth_from_poses(poses[half:], poses[:half])
    rt = data / "rtabmap-samples"
    bow_train = [load_rgb(rt / f"{i}.jpg") for i in range(1, 85) if (rt / f"{i}.jpg").is_file()] + skimage_photos()
    names = [f"frame {i}" for i in frames]
    return images, None, bow_train, {"fwd": (gt, cand), "split": (gt_split, split)}, (names, names)


def protocols_folders(query: Path, reference: Path, gt_file: Path, data: Path):
    try:
        q_files, r_files = folder_images(query), folder_images(reference)
    except (OSError, VPRInputError) as err:
        raise SystemExit(str(err)) from None
    try:
        q = [load_rgb(p) for p in q_files]
        r = [load_rgb(p) for p in r_files]
    except FrameReadError as err:  # one line naming the file, not a traceback
        raise SystemExit(str(err)) from None
    try:
        gt = read_ground_truth(gt_file, num_references=len(r))
    except (OSError, ValueError) as err:  # the reader's named errors say which file and what is wrong
        raise SystemExit(str(err)) from None
    if gt.shape[0] != len(q):
        raise SystemExit(f"{gt_file}: {gt.shape[0]} queries in the ground truth, {len(q)} images in {query}")
    kitchen = data / "7scenes-redkitchen"
    bow_train = [load_rgb(kitchen / f"frame-{i:06d}.color.jpg") for i in range(0, 1000, 5)
                 if (kitchen / f"frame-{i:06d}.color.jpg").is_file()]
    rt = data / "rtabmap-samples"
    bow_train += [load_rgb(rt / f"{i}.jpg") for i in range(1, 85) if (rt / f"{i}.jpg").is_file()]
    # never the evaluated images: without the shared sets, scikit-image's photographs (or no ORB-BoW at all)
    return q, r, bow_train or skimage_photos(), {"pairs": (gt, torch.ones_like(gt))}, ([p.name for p in q_files],
                                                                        [p.name for p in r_files])


def missed_queries(results: dict, gt: torch.Tensor, query_names: list[str], reference_names: list[str]) -> list[str]:
    """Markdown rows, one per query with a true match that some method's best candidate misses: the query,
    its true matches, how many methods miss it, and per method its best candidate and, in brackets, the
    rank of its best-ranked true match (1: found)."""
    rows = []
    for q in torch.nonzero(gt.any(1)).flatten().tolist():
        if all(bool(r.correct[q]) for r in results.values()):
            continue
        true = ", ".join(reference_names[j] for j in torch.nonzero(gt[q]).flatten().tolist())
        cells = [f"{reference_names[int(r.best[q])]} ({int(r.first_true_rank[q]) + 1})" if int(r.best[q]) >= 0
                 else "no candidate" for r in results.values()]
        missed = sum(not bool(r.correct[q]) for r in results.values())
        rows.append(f"| {query_names[q]} | {true} | {missed} of {len(results)} | " + " | ".join(cells) + " |")
    return rows


def report(set_name: str, sims: dict[str, torch.Tensor], protos: dict, out: Path | None, suffix: str = "", *,
           names: tuple[list[str], list[str]] | None = None) -> None:
    """One table per protocol; with ``names`` (the query and reference images' names) also the queries some
    method misses (:func:`missed_queries`)."""
    for pname, (gt, cand) in protos.items():
        results = {m: evaluate(s, gt, candidates=cand) for m, s in sims.items()}
        any_r = next(iter(results.values()))
        print(f"\n#### {set_name} / {pname}: {any_r.num_queries} queries, {any_r.num_with_match} with a true match\n")
        print("| method | R@1 | R@5 | R@10 | AUC-PR (VPR-Bench) | R@P100 | threshold at P100 |")
        print("|---|---|---|---|---|---|---|")
        for m, r in results.items():
            thr = r.threshold_at_full_precision
            print(f"| {m} | {r.recall_at(1):.3f} | {r.recall_at(5):.3f} | {r.recall_at(10):.3f} | {r.auc_pr:.3f} | "
                  f"{r.recall_at_full_precision:.3f} | {thr:.3f} |")
        if any_r.num_with_match < any_r.num_queries:
            # VPR-Bench divides by every query: its recall and accuracy differ from R@k here
            print(f"\nR@k is over the {any_r.num_with_match} queries with a true match; VPR-Bench's accuracy (the best "
                  f"candidate correct, over all {any_r.num_queries} queries): "
                  + ", ".join(f"{m} {r.accuracy:.3f}" for m, r in results.items()))
        if names is not None:
            rows = missed_queries(results, gt, *names)
            print(f"\nQueries some method misses ({len(rows)}): per method its best candidate (the rank of its "
                  "best true match)\n\n| query | true matches | missed by | " + " | ".join(results)
                  + " |\n|---|---|---|" + "---|" * len(results))
            print("\n".join(rows))
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            keep = [m for m in results if not m.startswith("paper ") or m == "paper dam"]
            plot_place_recognition(out / f"pr_{set_name}_{pname}{suffix}.png", [(m, results[m]) for m in keep
                                                                         if m in ("none", "dam", "ega", "GeM",
                                                                                  "ORB-BoW", "paper dam")],
                                   title=f"{set_name} / {pname}{suffix.replace('_', ', ')}")


def report_sequences(set_name: str, sims: dict[str, torch.Tensor], protos: dict, out: Path | None, suffix: str,
                     lengths: list[int], *, names: tuple[list[str], list[str]] | None = None) -> None:
    """:func:`report` once per sequence length (1: the images themselves, under the set's own name)."""
    for n in lengths:
        if n == 1:
            report(set_name, sims, protos, out, suffix, names=names)
        else:
            print(f"\n### {set_name}: sequences of {n} frames (sequence_similarity)")
            report(set_name, {m: sequence_similarity(s, n) for m, s in sims.items()}, protos, out,
                   f"{suffix}_seq{n}", names=names)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=data_root(), help=DATA_HELP)
    parser.add_argument("--sets", nargs="*", default=["rtabmap", "kitchen"], choices=["rtabmap", "kitchen"],
                        help="the shared sets to run (none: only --query/--reference)")
    parser.add_argument("--query", type=Path, help="a folder of query images (with --reference and --ground-truth)")
    parser.add_argument("--reference", type=Path, help="a folder of reference images")
    parser.add_argument("--ground-truth", type=Path,
                        help="the query x reference ground truth of --query (.npy or image)")
    parser.add_argument("--out", type=Path, default=None, help="folder for the PR-curve PNGs")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS,
                        help="what to measure: default (the five modes, GAP, GeM), paper (preset='paper'), orb "
                             "(ORB-BoW); default: all")
    parser.add_argument("--grayscale", action="store_true",
                        help="evaluate grayscale copies of every image, the ORB-BoW vocabulary's included (the "
                             "held-out corridor set is grayscale)")
    parser.add_argument("--downscale", type=int, default=1, metavar="N",
                        help="evaluate every image (the ORB-BoW vocabulary's included) at 1/N of its width and "
                             "height: a low-resolution camera (default 1: as read)")
    parser.add_argument("--sequence", nargs="+", type=int, default=[1], metavar="N",
                        help="score each pair over N frames (attnloop.vpr.evaluate.sequence_similarity: "
                             "the pair and the N - 1 pairs before it, SeqSLAM's diagonal); one set of tables "
                             "per N (default: 1, single images)")
    parser.add_argument("--bow-seeds", nargs="+", type=int, default=[0],
                        help="seeds of the ORB-BoW vocabulary (its k-means draw and sample); one row per seed "
                             "(default: 0)")
    parser.add_argument("--misses", action="store_true",
                        help="after each table, the queries some method misses at top-1: per method its best "
                             "candidate and the rank of its best true match")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if (args.query is None) != (args.reference is None) or (args.query is not None and args.ground_truth is None):
        parser.error("--query, --reference and --ground-truth go together")
    if args.downscale < 1:
        parser.error(f"--downscale must be a positive integer, got {args.downscale}")
    if min(args.sequence) < 1:
        parser.error(f"--sequence lengths must be positive integers, got {args.sequence}")
    copies = (["grayscale copies"] if args.grayscale else []) + ([f"at 1/{args.downscale} size"]
                                                                  if args.downscale > 1 else [])
    print(f"# Place recognition ({time.strftime('%Y-%m-%d %H:%M')}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} thread(s){''.join(', ' + c for c in copies)})")

    def prepare(images: list[np.ndarray]) -> list[np.ndarray]:  # what every evaluated image goes through
        small = downscaled(images, args.downscale)
        return grayscale(small) if args.grayscale else small

    # the PR curves' names: a grey or small run keeps the colour, full-size run's
    suffix = ("_grayscale" if args.grayscale else "") + (f"_1of{args.downscale}" if args.downscale > 1 else "")
    jobs = [(name, {"rtabmap": protocols_rtabmap, "kitchen": protocols_kitchen}[name]) for name in args.sets]
    for name, fn in jobs:
        t0 = time.perf_counter()
        got = fn(args.data)
        if got is None:
            print(f"\n{name}: data not found under {args.data}; skipped", file=sys.stderr)
            continue
        query, reference, bow_train, protos, names = got
        sims = all_methods(prepare(query), reference and prepare(reference), prepare(bow_train), args.methods,
                           args.bow_seeds)
        report_sequences(name, sims, protos, args.out, suffix, args.sequence, names=names if args.misses else None)
        print(f"\n({name}: {len(query)} images, {time.perf_counter() - t0:.0f} s)")
    if args.query is not None:
        query, reference, bow_train, protos, names = protocols_folders(args.query, args.reference, args.ground_truth,
                                                                       args.data)
        sims = all_methods(prepare(query), prepare(reference), prepare(bow_train), args.methods, args.bow_seeds)
        report_sequences(args.query.parent.name or "folders", sims, protos, args.out, suffix, args.sequence,
                         names=names if args.misses else None)


if __name__ == "__main__":
    main()
