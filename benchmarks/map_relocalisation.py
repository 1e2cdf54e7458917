"""Two sessions in one world: map a recording, save it, place a later recording in it.

    python -m benchmarks.map_relocalisation [--data ../shared/data] [--map-frames 0:600]
        [--session-frames 850:1000] [--skip-other] [--skip-rtabmap]

* **Kitchen, two sessions** (7-Scenes redkitchen, the Kinect v1 rig, EfficientNet-Lite0): frames
  ``--map-frames`` are mapped and saved (``run_slam(save_map=...)``, what ``--save-map`` does), the map is
  loaded back, and frames ``--session-frames`` (a recording of their own, numbered from 0) are run in it
  (``run_slam(map_dir=...)``, ``--map``). Printed: whether and where it relocalised, the frames placed,
  the position RMSE in the map's world with **no alignment** against the ground truth expressed in that
  world (the map's first ground-truth camera at the origin), the aligned ATE beside it, and the cost of a
  map query as a ratio to the loop closer's own per-keyframe work measured in the same run (descriptor,
  index query and verification), so that the figure means something on a shared machine.
* **Another place** (unless ``--skip-other``): the synthetic room's loop (80 frames, 320x240, read with
  the kitchen's rig, since a map serves only its own rig) run in the kitchen map must not relocalise
  (0 links) and stays in its own frame.
* **rtabmap-samples** (unless ``--skip-rtabmap``): no depth, so no geometric verification; what it checks
  is the candidate stage of relocalisation: with images 1-45 as the map, the fraction of the revisiting
  images 46-84 whose true place is among the ``RelocalisationConfig.max_candidates`` most similar map
  images (the only candidates verification ever sees).
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import torch

from benchmarks._common import add_data_argument
from slam.config import override
from slam.io import open_sequence
from slam.maps import RelocalisationConfig, load_map
from slam.options import frame_range, resolve_settings
from slam.pipeline import run_slam
from slam.report import evaluate_run


def _per_keyframe_loop_ms(metrics: dict) -> float:
    t = metrics["time_per_stage"]
    total = sum(t.get(k, {}).get("total_s", 0.0) for k in ("descriptor", "loop_detection", "verification"))
    calls = t.get("descriptor", {}).get("calls", 0)
    return 1000.0 * total / calls if calls else math.nan


def kitchen(data: Path, map_frames, session_frames, other: bool) -> dict:
    folder = data / "7scenes-redkitchen"
    seq = open_sequence(folder)
    settings = {"loop.descriptor.backbone": "efficientnet_lite0", "map.enabled": False}
    cfg = resolve_settings(settings, sequence=seq).config
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        mdir = Path(tmp) / "kitchen_map"
        t = time.perf_counter()
        first = run_slam(seq, cfg, progress=False, frames=map_frames, save_map=mdir)
        m1 = evaluate_run(first).as_dict()
        out["map"] = {"frames": list(map_frames), "keyframes": m1["num_keyframes"], "loops": m1["num_loops"],
                      "ate_rmse": m1["ate_rmse"], "seconds": round(time.perf_counter() - t, 1),
                      "size_mb": round(sum(f.stat().st_size for f in mdir.iterdir()) / 1e6, 2)}
        t = time.perf_counter()
        saved = load_map(mdir)
        out["map"]["load_seconds"] = round(time.perf_counter() - t, 3)
        second = run_slam(seq, cfg, progress=False, frames=session_frames, map_dir=saved)
        m2 = evaluate_run(second).as_dict()
        rel = m2["relocalisation"]
        loop_ms = _per_keyframe_loop_ms(m2)
        out["session"] = {"frames": list(session_frames), "num_frames": m2["num_frames"],
                          "relocalised": rel["relocalised"], "relocalised_at_frame": rel["frame"],
                          "frames_in_map": rel["frames_in_map"], "map_links": rel["map_links"],
                          "map_world_rmse": (rel["map_world_errors"] or {}).get("rmse"),
                          "map_world_max": (rel["map_world_errors"] or {}).get("max"),
                          "aligned_ate_rmse": m2["ate_rmse"], "seconds_to_relocalise": rel["seconds_to_relocalise"],
                          "map_query_ms": rel["query_ms"], "loop_closer_ms_per_keyframe": loop_ms,
                          "map_query_over_loop_closer": rel["query_ms"] / loop_ms if loop_ms else None}
        if other:
            from slam.synthetic import SyntheticSequence

            room = SyntheticSequence("loop", num_frames=300, seed=0, width=320, height=240)
            rcfg = resolve_settings({"loop.descriptor.backbone": "efficientnet_lite0", "map.enabled": False},
                                    sequence=room).config
            # a map only serves its own camera rig (MapMismatchError otherwise): the room's registered
            # frames are read with the kitchen's Kinect v1 rig, which tracks them well enough for this check
            rig = saved.rig
            rcfg = override(rcfg, {
                "odometry.features.rgb_intrinsics": tuple(rig["rgb_intrinsics"]) if rig["rgb_intrinsics"] else None,
                "odometry.features.rgb_from_depth_translation": tuple(rig["rgb_from_depth"])})
            run = run_slam(room, rcfg, progress=False, frames=(0, 80), map_dir=saved)
            r = evaluate_run(run).as_dict()["relocalisation"]
            out["other_place"] = {"recording": "synthetic room loop, frames 0-79", "relocalised": r["relocalised"],
                                  "link_hypotheses": r["link_hypotheses"], "queries": r["queries"],
                                  "reason": r["reason"]}
    return out


def rtabmap(data: Path, k: int) -> dict | None:
    import cv2

    from attnloop import AttentionDescriptor
    from attnloop.index import IndexConfig, KeyframeIndex
    from attnloop.vpr.evaluate import read_ground_truth
    from slam.io.images import read_rgb

    d = data / "rtabmap-samples"
    if not (d / "samples_GT.bmp").is_file():
        return None
    gt = read_ground_truth(d / "samples_GT.bmp")  # (84, 84): row i revisits column j
    model = AttentionDescriptor(backbone="efficientnet_lite0").eval()
    def keyframe_image(i):  # downsized as the SLAM keyframes are (OdometryConfig.keyframe_rgb_scale)
        rgb = read_rgb(str(d / f"{i}.jpg"))
        small = cv2.resize(rgb, (rgb.shape[1] // 2, rgb.shape[0] // 2), interpolation=cv2.INTER_AREA)
        return torch.from_numpy(small).permute(2, 0, 1)[None]

    with torch.no_grad():
        desc = torch.cat([model(keyframe_image(i)) for i in range(1, 85)])
    index = KeyframeIndex(IndexConfig(backend="exact"))
    index.add(desc[:45], ids=torch.arange(45))
    hits, queries = 0, 0
    for q in range(45, 84):
        true = gt[q, :45].nonzero().flatten()
        if true.numel() == 0:
            continue
        ids, _ = index.search(desc[q], k=k)
        queries += 1
        hits += bool(torch.isin(ids, true).any())
    return {"map_images": 45, "queries": queries, "k": k, "true_place_in_candidates": hits / max(queries, 1)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_argument(p)
    p.add_argument("--map-frames", type=frame_range, default=(0, 600), metavar="START:END",
                   help="redkitchen frames of the first session, mapped and saved (default 0:600)")
    p.add_argument("--session-frames", type=frame_range, default=(850, 1000), metavar="START:END",
                   help="redkitchen frames of the second session, run in the saved map (default 850:1000)")
    p.add_argument("--skip-other", action="store_true", help="skip the synthetic room in the kitchen map")
    p.add_argument("--skip-rtabmap", action="store_true", help="skip the candidate stage on rtabmap-samples")
    args = p.parse_args()
    torch.set_num_threads(1)
    data = Path(args.data)
    report = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "torch_threads": torch.get_num_threads()}
    if (data / "7scenes-redkitchen").is_dir():
        report["kitchen"] = kitchen(data, args.map_frames, args.session_frames, not args.skip_other)
    else:
        print(f"no 7scenes-redkitchen under {data}: the two-session figure is skipped")
    if not args.skip_rtabmap:
        report["rtabmap"] = rtabmap(data, RelocalisationConfig().max_candidates)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
