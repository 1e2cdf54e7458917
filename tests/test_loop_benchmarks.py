"""The loop benchmarks' own logic: the detector replay of benchmarks/loop_threshold.py --streams and the
config overrides of benchmarks/slam_pipeline.py."""
from __future__ import annotations

import pytest
import torch

from attnloop.threshold import ThresholdConfig
from slam.config import SLAMConfig


def _stream():
    """40 keyframes 0.5 s apart walking a straight line 0.2 m per keyframe, then 10 revisiting keyframes
    0-9. Each place has its own axis as descriptor (plus 0.1 % noise): different places have similarities
    within ~0.005 of 0, a revisit ~1."""
    gen = torch.Generator().manual_seed(0)
    places = torch.eye(64)[:40]
    desc = torch.cat([places, places[:10]]) + 0.001 * torch.randn(50, 64, generator=gen)
    desc = torch.nn.functional.normalize(desc, dim=1)
    pos = torch.cat([torch.arange(40.0) * 0.2, torch.arange(10.0) * 0.2])
    gt = torch.zeros(50, 7, dtype=torch.float64)
    gt[:, 0], gt[:, 6] = pos.double(), 1.0
    return {"desc": desc, "stamps": torch.arange(50.0, dtype=torch.float64) * 0.5,
            "frames": torch.arange(50) * 15, "gt": gt, "gap": torch.tensor(100), "name": "toy"}


def test_replay_counts_candidates_recall_and_precision(load_script):
    mod = load_script("benchmarks/loop_threshold.py")
    st = _stream()
    none = mod.replay(st, ThresholdConfig(min_similarity=2.0))  # a floor above any cosine: nothing sent
    # only the 10 revisits have an eligible true match: the walk's keyframes within 0.5 m of each other are
    # inside the 3 s window
    assert none["positives"] == 10 and none["candidates"] == 0 and none["recall"] == 0.0
    # the 0.02 margin sits above the noise: each revisit sends its place alone, nothing else is sent
    res = mod.replay(st, ThresholdConfig(k_sigma=3.0, min_samples=16))
    assert res == {"candidates": 10, "false": 0, "recall": 1.0, "positives": 10, "best_precision": 1.0,
                   "queries_with_candidates": 10}
    # no margin: half the noise is above the median, up to 5 candidates per query, nearly all false
    loose = mod.replay(st, ThresholdConfig(k_sigma=0.0, min_margin=0.0, min_samples=16))
    assert loose["recall"] == 1.0 and loose["false"] > 50 and loose["candidates"] > loose["false"] >= 10
    assert loose["best_precision"] < 0.5


def test_slam_pipeline_overrides_set_config_fields(load_script):
    mod = load_script("benchmarks/slam_pipeline.py")
    cfg = mod.apply_overrides(SLAMConfig(), ["loop.information_scale=0.005", "backend.loop_kernel=gnc",
                                             "loop.consistency.min_support=0"])
    assert cfg.loop.information_scale == 0.005 and cfg.backend.loop_kernel == "gnc"
    assert cfg.loop.consistency.min_support == 0
    with pytest.raises(SystemExit, match="no field"):
        mod.apply_overrides(SLAMConfig(), ["loop.bogus=1"])
    with pytest.raises(SystemExit, match="FIELD=VALUE"):
        mod.apply_overrides(SLAMConfig(), ["loop.information_scale"])
    with pytest.raises(ValueError, match="min_support"):  # the config's own checks run on the new value
        mod.apply_overrides(SLAMConfig(), ["loop.consistency.min_support=-1"])
