"""What the system keeps per frame: a row of fixed size (timestamp, keyframe, pose in it, placed), not an object
per frame, so a long run's records grow by bytes per frame."""
from __future__ import annotations

import gc

import pytest
import torch

from slam.config import SLAMConfig, override

pytestmark = pytest.mark.usefixtures("one_thread")


def test_a_tracked_frame_keeps_a_row_of_bytes():
    from slam.synthetic import SyntheticSequence
    from slam.system import RGBDSLAM

    frame = SyntheticSequence("loop", num_frames=2, width=160, height=120, seed=0)[0]
    slam = RGBDSLAM(override(SLAMConfig(), {"loop.enabled": False}))
    for _ in range(20):  # the same view again and again: tracked, no new keyframe
        slam.track(frame)
    gc.collect()
    before = len(gc.get_objects())
    n = 300
    for _ in range(n):
        assert slam.track(frame).status == "ok"
    gc.collect()
    assert len(slam.keyframes) == 1
    # no object stays per frame (a record and its pose tensor did: 2 a frame): its row is bytes in arrays
    assert len(gc.get_objects()) - before < n // 10, len(gc.get_objects()) - before
    res = slam.finish()
    assert res.num_frames == n + 20 and bool(res.tracked.all())
    assert torch.allclose(res.trajectory.poses, res.trajectory.poses[:1].expand(n + 20, 7), atol=1e-6)
