"""Which adaptive-threshold settings the default descriptor needs in the SLAM loop detector.

The kitchen (7-Scenes redkitchen) as a keyframe stream: every ``--step``-th frame is a keyframe, fed in
order to :class:`attnloop.index.LoopCandidateDetector` (exclusion window ``100 / step`` keyframes, i.e.
100 frames, as the loop ground truth's frame gap). For each :class:`attnloop.threshold.ThresholdConfig`
the accepted best candidates are labelled by the poses (0.5 m, 45 degrees): precision, recall (over the
keyframes that have a true earlier match) and the number of false accepts, for the default descriptor
and for ``preset="paper"``, fusion ``dam``. Recall at 100 % precision of the raw top-1 similarity is
given for reference (the best any single similarity threshold can do).

Usage:
    python -m benchmarks.loop_threshold [--data ../shared/data] [--step 5]

``--streams``: the keyframe streams the SLAM system itself makes, on every sequence given (the kitchen at
each ``--kitchen-steps``, ``--room DIR``, ``--building DIR``): an odometry-only run picks the keyframes
(those of a loop-closing run: keyframe selection does not depend on the loops), the default descriptor
(EfficientNet-Lite0, ``--fusion``) describes their stored images as the loop closer does, and the
detector of ``slam.config.LoopClosureConfig`` (ids in milliseconds, window 3 s) is replayed with each
threshold setting. Per sequence and setting: candidates sent to verification (the first
``max_candidates`` accepted) and how many are false, the recall (queries with a true candidate among
them / queries with an eligible true match), and the best candidate's precision. The streams are cached
in ``--cache`` (``<sequence>_step<N>_<fusion>_<descriptor_version>.npz``: another default descriptor is
described anew), so a second sweep is instant::

    python -m benchmarks.loop_threshold --streams --kitchen-steps 1 3 6 --room runs/room_seq \
        --building runs/building_seq --cache runs/loop_streams
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from attnloop import AttentionDescriptor
from attnloop.descriptor import DescriptorRecipe
from attnloop.index import LoopCandidateDetector, LoopDetectorConfig
from attnloop.threshold import ThresholdConfig
from attnloop.vpr.describe import load_rgb
from attnloop.vpr.evaluate import evaluate, ground_truth_from_poses, sequence_candidates
from benchmarks._common import DATA_HELP, data_root
from benchmarks.index_data import descriptor_version
from benchmarks.place_recognition import kitchen_poses
from slam.eval.loops import LoopGroundTruthConfig

# (method, k_sigma, min_margin, min_similarity)
SETTINGS = ([("mad", k, 0.02, 0.0) for k in (1.5, 2.0, 3.0, 4.0)]
            + [("mad", k, 0.005, 0.0) for k in (1.0, 1.5, 2.0)]
            + [("mad", 1.0, 0.005, f) for f in (0.90, 0.93, 0.95)])


# (k_sigma, min_margin, min_similarity) of the MAD rule, for the streams
STREAM_SETTINGS = ([(1.5, 0.02, 0.0), (1.0, 0.005, 0.0), (2.0, 0.02, 0.0), (3.0, 0.02, 0.0)]
                   + [(k, 0.005, f) for k in (0.5, 1.0, 1.5) for f in (0.85, 0.88, 0.90, 0.92, 0.94)]
                   # the floors of a lower tap, whose unrelated keyframes are more alike (cosine ~0.97)
                   + [(k, 0.005, f) for k in (0.5, 1.0, 1.5) for f in (0.96, 0.97, 0.975, 0.98, 0.985, 0.99)]
                   + [(k, 0.02, f) for k in (1.0, 1.5, 2.0) for f in (0.85, 0.90)])


def keyframe_stream(path: Path, step: int, fusion: str, cache: Path | None) -> dict:
    """The keyframes of an odometry-only SLAM run on every ``step``-th frame of ``path`` (as
    ``attnloop-slam`` configures it), described by the loop closer's descriptor: ``desc (M, D)``, ``stamps
    (M,)``, ``gt (M, 7)`` ground truth of the keyframes, ``frames (M,)`` processed-frame indices, ``gap``
    (the loop ground truth's minimum frame gap at this step)."""
    import numpy as np

    from slam.io import open_sequence
    from slam.loop.closer import build_descriptor
    from slam.options import resolve_settings
    from slam.report import loop_ground_truth_for_step
    from slam.system import RGBDSLAM

    seq = open_sequence(path)
    name = f"{seq.name}_step{step}_{fusion}"
    # the cache file also names the default descriptor's configuration: another default is described anew
    f_name = f"{name}_{descriptor_version()}"
    f = None if cache is None else cache / f"{f_name}.npz"
    if f is not None and f.exists():
        z = np.load(f)
        return {k: torch.from_numpy(z[k]) for k in z.files} | {"name": name}
    cfg = resolve_settings({"loop.enabled": False, "map.enabled": False}, sequence=seq).config
    view = seq[0:len(seq):step]
    slam = RGBDSLAM(cfg)
    for frame in view.frames(prefetch=2):
        slam.track(frame)
    kfs = slam.keyframes
    lcfg = resolve_settings({"loop.descriptor.backbone": "efficientnet_lite0", "loop.descriptor.fusion": fusion,
                             "map.enabled": False}, sequence=seq).config.loop
    gt_kf = torch.from_numpy(np.stack([view.groundtruth_pose(kf.frame_index) for kf in kfs]))
    chi2 = edge_calibration(slam, lcfg, gt_kf, cfg)
    model = build_descriptor(lcfg.descriptor)
    with torch.no_grad():
        imgs = [torch.from_numpy(np.ascontiguousarray(kf.rgb)).permute(2, 0, 1) for kf in kfs]
        desc = torch.cat([model(torch.stack(imgs[s:s + 8])) for s in range(0, len(imgs), 8)])
    out = {"desc": desc.float(), "stamps": torch.tensor([kf.timestamp for kf in kfs], dtype=torch.float64),
           "frames": torch.tensor([kf.frame_index for kf in kfs], dtype=torch.long),
           "gt": gt_kf, "gap": torch.tensor(loop_ground_truth_for_step(step).min_frame_gap),
           "chi2_odometry": chi2["odometry"], "chi2_loop": chi2["loop"]}
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        np.savez(f, **{k: v.numpy() for k, v in out.items()})
    return out | {"name": name}


def edge_calibration(slam, loop_config, gt: torch.Tensor, config, max_loops: int = 150) -> dict:
    """Squared Mahalanobis errors ``(E,)`` against ground truth of the registration's *unscaled* information:
    of the odometry edges between keyframes, and of loop edges registered as the loop closer does
    (``loop_config.registration``, at least ``min_inliers``) between keyframes >= 3 s apart that ground
    truth puts within the verification's view limits (up to ``max_loops`` pairs, evenly spread). Ground
    truth is moved into the tracked camera's frame (the colour camera's, for an unregistered rig)."""
    from slam.eval.loops import LoopGroundTruthConfig, is_true_loop
    from slam.graph.costs import edge_residuals
    from slam.keyframe_graph import EdgeKind
    from slam.lie import se3_compose, se3_inv
    from slam.odometry.registration import register

    feats = config.odometry.features
    t = tuple(feats.rgb_from_depth_translation) if feats.rgb_intrinsics else (0.0, 0.0, 0.0)
    T_rd = torch.tensor([*t, 0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(gt.shape[0], 7)
    P = se3_compose(se3_compose(T_rd, gt.to(torch.float64)), se3_inv(T_rd))

    def chi2(ii, jj, Z, info):
        if not ii:
            return torch.zeros(0, dtype=torch.float64)
        r, _ = edge_residuals(P, torch.tensor(ii), torch.tensor(jj), torch.stack(Z))
        return torch.einsum("ei,eij,ej->e", r, torch.stack(info).to(torch.float64), r)

    odo = [e for e in slam.graph.edges if e.kind is EdgeKind.ODOMETRY and not e.weak]
    out = {"odometry": chi2([e.i for e in odo], [e.j for e in odo], [e.T_ij for e in odo],
                            [e.information for e in odo])}
    kfs = slam.keyframes
    stamps = torch.tensor([kf.timestamp for kf in kfs], dtype=torch.float64)
    n = len(kfs)
    pairs = torch.tensor([(a, b) for b in range(n) for a in range(b) if stamps[b] - stamps[a] >= 3.0]).reshape(-1, 2)
    lim = LoopGroundTruthConfig(loop_config.max_translation, loop_config.max_rotation_deg, 1)
    pairs = pairs[is_true_loop(gt, pairs, lim)] if pairs.numel() else pairs
    if pairs.shape[0] > max_loops:
        pairs = pairs[torch.linspace(0, pairs.shape[0] - 1, max_loops).round().long()]
    ii, jj, Z, info = [], [], [], []
    for a, b in pairs.tolist():
        r = register(kfs[a].features, kfs[b].features, loop_config.registration)
        if r.success and r.num_inliers >= loop_config.min_inliers:
            ii.append(a), jj.append(b), Z.append(r.T_ab.to(torch.float64)), info.append(r.information)
    out["loop"] = chi2(ii, jj, Z, info)
    return out


def replay(stream: dict, threshold: ThresholdConfig) -> dict:
    """The SLAM's detector (``LoopClosureConfig().detector`` with ``threshold``) on a keyframe stream."""
    import dataclasses

    from slam.config import LoopClosureConfig
    from slam.eval.loops import LoopGroundTruthConfig, is_true_loop

    lc = LoopClosureConfig()
    det = LoopCandidateDetector(dataclasses.replace(lc.detector, threshold=threshold))
    stamps, gt = stream["stamps"], stream["gt"]
    ids, last = [], -1
    for t in stamps.tolist():  # milliseconds since the first keyframe, as LoopCloser._detector_id
        last = max(round((t - float(stamps[0])) * 1000.0), last + 1)
        ids.append(last)
    judge = LoopGroundTruthConfig(min_frame_gap=1)
    close = is_true_loop(gt, torch.tensor([[a, b] for a in range(len(ids)) for b in range(len(ids))]).reshape(-1, 2),
                         judge).reshape(len(ids), len(ids))
    frames = stream["frames"]
    gap = int(stream["gap"])
    cand = false = q_true = positives = best_true = best_n = 0
    for q, kid in enumerate(ids):
        out = det.add_and_query(stream["desc"][q], keyframe_id=kid)
        eligible = [k for k in range(q) if ids[k] <= kid - lc.detector.window and frames[q] - frames[k] >= gap]
        positives += int(any(bool(close[q, k]) for k in eligible))
        sent = [ids.index(int(c)) for c in out.ids[: lc.max_candidates]]
        cand += len(sent)
        false += sum(not bool(close[q, k]) for k in sent)
        q_true += int(any(bool(close[q, k]) for k in sent))
        if sent:
            best_n += 1
            best_true += int(bool(close[q, sent[0]]))
    return {"candidates": cand, "false": false, "recall": q_true / max(positives, 1), "positives": positives,
            "best_precision": best_true / best_n if best_n else float("nan"), "queries_with_candidates": best_n}


def streams_main(args) -> None:
    streams = [keyframe_stream(args.data / "7scenes-redkitchen", s, args.fusion, args.cache)
               for s in args.kitchen_steps]
    if args.room:
        streams.append(keyframe_stream(args.room, 1, args.fusion, args.cache))
    if args.building:
        streams.append(keyframe_stream(args.building, 1, args.fusion, args.cache))
    print(f"# Loop-detector thresholds on the SLAM's keyframe streams ({time.strftime('%Y-%m-%d %H:%M')}), "
          f"default descriptor, fusion {args.fusion}\n")
    print("| stream | keyframes | queries with a true match | unscaled chi2 vs truth, odometry edges: "
          "median / mean (n) | loop edges: median / mean (n) |\n|---|---|---|---|---|")
    for st in streams:
        probe = replay(st, ThresholdConfig(min_similarity=2.0))  # nothing accepted: counts the positives
        c = {k: st[f"chi2_{k}"] for k in ("odometry", "loop")}
        cells = [f"{float(v.median()):.1f} / {float(v.mean()):.1f} ({v.numel()})" if v.numel() else "-"
                 for v in c.values()]
        print(f"| {st['name']} | {st['desc'].shape[0]} | {probe['positives']} | {cells[0]} | {cells[1]} |")
    names = [st["name"] for st in streams]
    print("\nPer stream: recall / candidates sent to verification (false among them) / best candidate's precision\n")
    print("| k_sigma | min_margin | min_similarity | " + " | ".join(names) + " | min recall | false / sent |")
    print("|" + "---|" * (len(names) + 5))
    for k, margin, floor in STREAM_SETTINGS:
        cfg = ThresholdConfig(k_sigma=k, min_margin=margin, min_similarity=floor, min_samples=16)
        rows = [replay(st, cfg) for st in streams]
        cells = [f"{r['recall']:.2f} / {r['candidates']} ({r['false']}) / {r['best_precision']:.2f}" for r in rows]
        print(f"| {k:g} | {margin:g} | {floor:g} | " + " | ".join(cells)
              + f" | {min(r['recall'] for r in rows):.2f} | {sum(r['false'] for r in rows)} / "
              f"{sum(r['candidates'] for r in rows)} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=data_root(), help=DATA_HELP)
    parser.add_argument("--step", type=int, default=5, help="every STEP-th kitchen frame is a keyframe")
    parser.add_argument("--presets", nargs="+", default=["default", "paper"], choices=["default", "paper"],
                        help="descriptor presets to compare")
    parser.add_argument("--streams", action="store_true", help="sweep on the SLAM's keyframe streams (see above)")
    parser.add_argument("--kitchen-steps", type=int, nargs="*", default=[1, 3, 6],
                        help="--streams: kitchen frame steps")
    parser.add_argument("--room", type=Path, default=None, help="--streams: the room demo's sequence folder")
    parser.add_argument("--building", type=Path, default=None, help="--streams: the building's sequence folder")
    parser.add_argument("--fusion", default=DescriptorRecipe.fusion,
                        help="--streams: fusion mode of the descriptor (default: the default's)")
    parser.add_argument("--cache", type=Path, default=None, help="--streams: folder caching the described streams")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.streams:
        streams_main(args)
        return
    seq = args.data / "7scenes-redkitchen"
    frames = list(range(0, 1000, args.step))
    images = [torch.from_numpy(load_rgb(seq / f"frame-{i:06d}.color.jpg")).permute(2, 0, 1) for i in frames]
    gap = 100 // args.step
    gt = ground_truth_from_poses(kitchen_poses(seq, frames), config=LoopGroundTruthConfig(0.5, 45.0, gap))
    has = gt.any(1)
    print(f"# Loop-detector thresholds on the kitchen stream ({time.strftime('%Y-%m-%d %H:%M')}): {len(frames)} "
          f"keyframes (every {args.step}th frame), window {gap}, {int(has.sum())} with a true earlier match\n")
    print("| descriptor | threshold | accepted | precision | recall | false accepts |\n|---|---|---|---|---|---|")
    for label, preset in [(f"{p} dam", None if p == "default" else p) for p in args.presets]:
        desc = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=True, preset=preset)
        with torch.no_grad():
            d = torch.cat([desc(torch.stack(images[s:s + 8])) for s in range(0, len(images), 8)])
        r = evaluate(d @ d.T, gt, candidates=sequence_candidates(len(frames), gap))
        print(f"| {label} | top-1 similarity at 100 % precision: {r.threshold_at_full_precision:.3f} | - | 1.000 | "
              f"{r.recall_at_full_precision:.3f} | 0 |")
        for method, k, margin, floor in SETTINGS:
            cfg = LoopDetectorConfig(window=gap, threshold=ThresholdConfig(k_sigma=k, min_margin=margin,
                                                                           min_similarity=floor, min_samples=16),
                                     threshold_samples=4096)
            det = LoopCandidateDetector(cfg)
            tp = fp = 0
            for i in range(len(frames)):
                out = det.add_and_query(d[i], keyframe_id=i)
                if out.ids.numel():
                    j = int(out.ids[0])
                    tp, fp = tp + int(gt[i, j]), fp + int(not gt[i, j])
            acc = tp + fp
            print(f"| {label} | {method} k={k:g} margin={margin:g} floor={floor:g} | {acc} | "
                  f"{tp / acc if acc else float('nan'):.3f} | {tp / max(int(has.sum()), 1):.3f} | {fp} |", flush=True)
    print(f"\n(recall over the {int(has.sum())} keyframes with a true match; min_samples 16)")


if __name__ == "__main__":
    main()
