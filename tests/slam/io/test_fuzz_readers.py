"""Fuzz test of the readers: mutated real files give a result or one of the named errors, nothing else.

Real inputs (the shared TUM lists and ground truth, 7-Scenes pose files and images, g2o graphs) are
mutated by ``tests/helpers.py`` (seeded: a failing case is reproduced from its printed seed) and read.
Allowed outcomes:

* a result whose every number is finite (warnings of the documented kinds allowed: ``DatasetWarning``,
  ``G2OWarning``, the trajectory reader's duplicate-timestamp warning);
* one of the documented errors, and its message names the file: ``DatasetError`` (TUM lists, 7-Scenes
  intrinsics), ``TrajectoryFormatError`` (trajectories, ``groundtruth.txt``), ``G2OFormatError``,
  ``FrameReadError`` (an image that does not decode; only at read time).

Anything else (``UnicodeDecodeError``, ``OverflowError``, ``IndexError``, a NaN or Infinity in what was
read, a 7-Scenes frame that lost its image because of its pose file) fails the test. The counts of cases
and outcomes are printed (``pytest -s``).
"""
from __future__ import annotations

import random
import shutil
import time
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import torch
from helpers import MUTATIONS, mutate

from slam.graph import G2OFormatError, read_g2o
from slam.io import DatasetError, FrameReadError, SevenScenesSequence, TUMSequence
from slam.io.trajectory import TrajectoryFormatError, read_tum_trajectory

SEEDS_PER_KIND = 5  # cases per (file, mutation kind); 12 kinds
NAMED = (DatasetError, TrajectoryFormatError, G2OFormatError, FrameReadError)
_SECONDS: Counter = Counter()  # time spent reading, per target


def _finite(*tensors) -> bool:
    return all(bool(np.isfinite(np.asarray(t)).all()) for t in tensors)


def _run(read, path: Path, counts: Counter, key: str, seed: int) -> str:
    """Call ``read()``; classify and check the outcome."""
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            read()
            outcome = "ok, warned" if caught else "ok"
        except NAMED as e:
            assert path.name in str(e), f"{key} seed {seed}: {type(e).__name__} does not name {path.name}: {e}"
            outcome = type(e).__name__
        except Exception as e:
            raise AssertionError(f"{key} seed {seed}: {type(e).__name__} (not a named error): {e}") from e
    counts[(key, outcome)] += 1
    _SECONDS[key] += time.perf_counter() - t0
    return outcome


def _head(path: Path, lines: int) -> bytes:
    """The first ``lines`` lines of a real file (the whole file costs time and finds nothing more)."""
    return b"\n".join(path.read_bytes().split(b"\n")[:lines]) + b"\n"


def _cases():
    for kind in MUTATIONS:
        for s in range(SEEDS_PER_KIND):
            yield kind, 1000 * MUTATIONS.index(kind) + s


def test_fuzz_readers(tum_gt_dir, posegraph_dir, redkitchen_dir, tmp_path, capsys):
    counts: Counter = Counter()

    # --- TUM trajectories: both shared ground-truth files ------------------------------------
    for name in ("fr1_xyz-groundtruth.txt", "fr3_long_office_household-groundtruth.txt"):
        real = _head(tum_gt_dir / name, 120)
        for kind, seed in _cases():
            path = tmp_path / f"traj_{kind}_{seed}.txt"
            path.write_bytes(mutate(real, kind, random.Random(seed)))

            def read(path=path):
                traj = read_tum_trajectory(path)
                assert _finite(traj.timestamps, traj.poses), f"{path.name}: non-finite values read"
                assert traj.timestamps.dtype == torch.float64
            _run(read, path, counts, "TUM trajectory", seed)

    # --- TUM sequence folders: rgb.txt, depth.txt, groundtruth.txt (no images: open time only) ----
    lists = {"rgb.txt": _head(tum_gt_dir / "fr1_xyz-rgb.txt", 80),
             "depth.txt": _head(tum_gt_dir / "fr1_xyz-depth.txt", 80),
             "groundtruth.txt": _head(tum_gt_dir / "fr1_xyz-groundtruth.txt", 300)}
    for target in lists:
        for kind, seed in _cases():
            folder = tmp_path / f"rgbd_dataset_freiburg1_xyz_{target[:-4]}_{kind}_{seed}"
            folder.mkdir()
            for name, data in lists.items():
                (folder / name).write_bytes(mutate(data, kind, random.Random(seed)) if name == target else data)

            def read(folder=folder):
                seq = TUMSequence(folder)
                gt = seq.groundtruth
                assert _finite(seq.timestamps, seq.K) and (gt is None or _finite(gt.timestamps, gt.poses))
            _run(read, folder / target, counts, f"TUM {target}", seed)

    # --- 7-Scenes: three real frames; their pose files, the intrinsics, the images -------------
    src = tmp_path / "7scenes_src"
    src.mkdir()
    frames = (240, 241, 242)
    for k in frames:
        for ext in ("color.jpg", "depth.png", "pose.txt"):
            shutil.copy(redkitchen_dir / f"frame-{k:06d}.{ext}", src / f"frame-{k:06d}.{ext}")
    shutil.copy(redkitchen_dir / "camera-intrinsics.txt", src / "camera-intrinsics.txt")
    targets = [("pose", f"frame-{frames[1]:06d}.pose.txt", 3),  # each case decodes a frame: fewer
               ("intrinsics", "camera-intrinsics.txt", SEEDS_PER_KIND),
               ("colour image", f"frame-{frames[1]:06d}.color.jpg", 1),
               ("depth image", f"frame-{frames[1]:06d}.depth.png", 1)]
    for label, target, seeds in targets:
        data = (src / target).read_bytes()
        for kind in MUTATIONS:
            if label.endswith("image") and kind not in ("truncate", "flip_byte", "empty", "not_utf8"):
                continue
            for s in range(seeds):
                seed = 1000 * MUTATIONS.index(kind) + s
                folder = tmp_path / f"seq-{label[:4]}-{kind}-{seed}"
                folder.mkdir()
                for f in src.iterdir():  # the unchanged files linked, not copied
                    (folder / f.name).symlink_to(f)
                (folder / target).unlink()
                (folder / target).write_bytes(mutate(data, kind, random.Random(seed)))

                def read(folder=folder, label=label):
                    seq = SevenScenesSequence(folder)
                    assert _finite(seq.K)
                    if label == "intrinsics":
                        return
                    # the mutated frame (for an image: every frame) keeps its images whatever its pose file holds
                    for g in seq.frames(on_error="yield") if label.endswith("image") else [seq[1]]:
                        if isinstance(g, FrameReadError):
                            assert label.endswith("image"), f"{folder.name}: a frame was lost: {g}"
                            raise g
                        assert g.rgb.shape == (480, 640, 3) and _finite(g.depth, g.K)
                        assert g.pose_gt is None or _finite(g.pose_gt)
                    gt = seq.groundtruth
                    assert gt is None or _finite(gt.timestamps, gt.poses)
                _run(read, folder / target, counts, f"7-Scenes {label}", seed)

    # --- g2o: a 3D benchmark file and a 2D excerpt of another --------------------------------
    intel = [ln for ln in (posegraph_dir / "input_INTEL_g2o.g2o").read_bytes().split(b"\n")
             if ln.split()[1:2] and all(int(t) < 60 for t in ln.split()[1:3] if t.isdigit())]
    graphs = {"tinyGrid3D": (posegraph_dir / "tinyGrid3D.g2o").read_bytes(),
              "INTEL excerpt (2D)": b"\n".join(intel) + b"\n"}
    for label, real in graphs.items():
        for kind, seed in _cases():
            path = tmp_path / f"graph_{kind}_{seed}.g2o"
            path.write_bytes(mutate(real, kind, random.Random(seed)))

            def read(path=path):
                g = read_g2o(path)
                assert _finite(g.poses, g.measurements, g.information), f"{path.name}: non-finite values read"
                assert (torch.linalg.eigvalsh(g.information) > 0).all() if g.num_edges else True
            _run(read, path, counts, f"g2o {label}", seed)

    # --- the counts ---------------------------------------------------------------------------
    total = sum(counts.values())
    by_target = Counter()
    for (key, _), n in counts.items():
        by_target[key] += n
    with capsys.disabled():
        print(f"\nfuzz test of the readers: {total} cases")
        for key in by_target:
            outcomes = ", ".join(f"{o} {n}" for (k, o), n in sorted(counts.items()) if k == key)
            print(f"  {key}: {by_target[key]} cases ({_SECONDS[key]:.1f} s): {outcomes}")
    assert total >= 400
    # every target saw both readable mutations and refused ones (the mutations do reach the checks)
    for key in by_target:
        assert key.endswith("image") or any(o.startswith("ok") for (k, o) in counts if k == key), key
        assert any(o != "ok" for (k, o) in counts if k == key), key
